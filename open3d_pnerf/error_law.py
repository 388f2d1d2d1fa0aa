"""The law of a reconstruction's depth errors: how the model's depth spread along a ray becomes a
calibrated error bar, with its intervals and likelihood, fitted on training frames.

The law is a Student-t with `dof` degrees of freedom (inf: a Gaussian) whose 1-sigma equivalent,
the half-width of its central 68.27%, is sigma = sqrt((scale * spread)^2 + (floor * z)^2) at
z-depth z. Depth errors are heavy-tailed (most pixels within millimetres, a few on the wrong side
of an edge), which a Gaussian can only meet by widening every sigma; the relative floor covers
errors the spread does not see (e.g. a surface between the samples).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .errors import InputError

GAUSSIAN_SHARES = {1: 0.6826894921370859, 2: 0.9544997361036416, 3: 0.9973002039367398}
"""Share of a Gaussian within k sigma of its mean, k = 1, 2, 3."""


def _standard_law(dof: float):
    """The standard law (scipy): Student-t with `dof` degrees of freedom, or a Gaussian (inf),
    and the half-width of its central 68.27% interval (the 1-sigma equivalent)."""
    from scipy import stats

    law = stats.norm() if np.isinf(dof) else stats.t(dof)
    return law, float(law.ppf((1 + GAUSSIAN_SHARES[1]) / 2))


def sigma_multiple(probability: float, dof: float = np.inf) -> float:
    """Half-width, in 1-sigma equivalents, of the central interval that holds `probability` of
    the law with `dof` degrees of freedom (inf: a Gaussian, 1, 2, 3 for 0.683, 0.954, 0.997;
    heavier tails, smaller dof, give more)."""
    if not 0 < probability < 1:
        raise InputError(f"probability must be in (0, 1), got {probability!r}")
    law, one = _standard_law(dof)
    return float(law.ppf((1 + probability) / 2) / one)


def depth_nll(err: np.ndarray, sigma: np.ndarray, dof: float = np.inf) -> np.ndarray:
    """Negative log-likelihood (nats) of depth errors `err` (m) under the law of
    1-sigma-equivalent `sigma` (m) and `dof` degrees of freedom; arrays of one shape, or
    broadcastable."""
    law, one = _standard_law(dof)
    scale = np.asarray(sigma) / one
    return np.log(scale) - law.logpdf(np.asarray(err) / scale)


@dataclasses.dataclass(frozen=True)
class DepthErrorLaw:
    """sigma = sqrt((scale * spread)^2 + (floor * z)^2), the 1-sigma equivalent of a Student-t with
    `dof` degrees of freedom (inf: a Gaussian). The default (1, 0, inf) takes the spread as it is."""

    scale: float = 1.0
    floor: float = 0.0
    dof: float = np.inf

    def sigma(self, spread: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The 1-sigma-equivalent error (m) of raw depth spreads (m) at z-depths `depth` (m)."""
        return np.sqrt((self.scale * spread) ** 2 + (self.floor * depth) ** 2)

    def interval(self, probability: float) -> float:
        """Multiple of sigma whose +- interval holds `probability` of the errors."""
        return sigma_multiple(probability, self.dof)

    def nll(self, err: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Negative log-likelihood (nats) of errors `err` (m) with 1-sigma equivalents `sigma` (m)."""
        return depth_nll(err, sigma, self.dof)

    @classmethod
    def fit(cls, err: np.ndarray, spread: np.ndarray, z: np.ndarray, method: str = "likelihood",
            coverage: float = 0.683) -> "DepthErrorLaw":
        """The law of depth errors `err` (M,) m given the raw spreads (M,) m at z-depths z (M,) m.

        "likelihood": scale, floor and dof by maximum likelihood (a predictive distribution right
        across its range, not at one quantile); "gaussian": the same with dof = inf; "quantile":
        a Gaussian, floor 0 and the scale that puts `coverage` of the errors within 1 sigma (right
        at that quantile only). No errors: the default law."""
        if method not in ("likelihood", "gaussian", "quantile"):
            raise InputError(f"method must be 'likelihood', 'gaussian' or 'quantile', got {method!r}")
        if not err.size:
            return cls()
        scale = float(np.quantile(err / spread, coverage))
        if method == "quantile":
            return cls(scale)
        return cls(*_likelihood_fit(err, spread, z, scale, fit_dof=method == "likelihood"))


def _likelihood_fit(err: np.ndarray, spread: np.ndarray, z: np.ndarray, scale0: float,
                    fit_dof: bool = True) -> tuple[float, float, float]:
    """(scale, floor, dof) minimising the mean negative log-likelihood of errors `err` under the
    law of sigma = sqrt((scale spread)^2 + (floor z)^2): a Student-t with dof in [1, 1000], or a
    Gaussian (dof inf) unless `fit_dof`; all (M,) metres; starts from scale0, floor 0.1%, dof 4."""
    from scipy.optimize import minimize

    def unpack(x):
        dof = float(np.clip(np.exp(x[2]), 1.0, 1000.0)) if fit_dof else np.inf
        return np.exp(x[0]), np.exp(x[1]), dof

    def nll(x):
        s, f, dof = unpack(x)
        sigma = np.sqrt((s * spread) ** 2 + (f * z) ** 2) + 1e-9
        return float(np.mean(depth_nll(err, sigma, dof)))

    start = np.log([max(scale0, 1e-6), 1e-3, 4.0][: 3 if fit_dof else 2])
    best = minimize(nll, start, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 3000})
    s, f, dof = unpack(best.x if best.fun <= nll(start) else start)
    return float(s), float(f), dof
