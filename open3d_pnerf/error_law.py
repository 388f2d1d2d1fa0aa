"""The law of a reconstruction's depth errors: how the model's depth spread along a ray becomes a
calibrated error bar, with its intervals and likelihood, fitted on training frames.

The law is a Student-t with `dof` degrees of freedom (inf: a Gaussian) whose 1-sigma equivalent,
the half-width of its central 68.27%, is sigma = sqrt((scale * spread)^2 + (floor * z)^2 +
(unseen * z * min(1, d / unseen_ramp))^2 + (edge * jump)^2 + (through * gap / k)^2) at z-depth z,
d metres from the nearest surface the training frames' depth observed
(:class:`~open3d_pnerf.observed.ObservedSurface`), `jump` the range of the rendered depths around
the pixel (:func:`depth_jump`), `gap` how far beyond the rendered point a training view's depth
saw (:meth:`~open3d_pnerf.observed.ObservedSurface.seen_through`), k the multiple of sigma of the
law's 99.73% interval. Depth errors
are heavy-tailed (most pixels within millimetres, a few on the wrong side of an edge), which a
Gaussian can only meet by widening every sigma; the relative floor covers errors the spread does
not see (e.g. a surface between the samples). The unseen term is what the model cannot know from
its training: where it renders a surface that no training view's depth saw, it is often far off
(on TUM fr1/xyz's held-out frames, 114 mm at the median and 1.3 m at the 90th percentile where
only the model covers, with the law's sigma saying 29 mm: benchmarks/bench_unseen.py), so there
its depth is known only to a share of itself. The edge term is what a view between the training
views cannot know at a depth edge: which side of it a pixel falls on. Where the model renders an
observed surface with a narrow spread it can still be wrong by the whole jump (on TUM fr1/xyz the
misses where only the model covers are 0.1-0.7 m off at 0 mm from an observed surface, beside an
edge: benchmarks/bench_unseen.py). The through term is what the training views contradict: a
rendered point that a view saw past lies where that view saw free space (a foreground surface
rendered wider than it is), and the surface the view saw behind it may be the answer, so the
99.73% interval reaches it (on 7-Scenes' held-out frames the misses where only the model covers
were such points: benchmarks/README.md). The terms are fixed, not
fitted: the training pixels the law is fitted on are rendered alone, and the model has learned
those frames' edges and free space.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .errors import InputError

UNSEEN = 0.5
UNSEEN_RAMP = 0.01
"""The unseen term's defaults: half the depth, reached 1 cm (one export voxel) from the observed
surfaces. Chosen on TUM fr1/xyz's held-out frames (benchmarks/README.md): of a small grid, the
one that comes nearest to holding 99% of the errors where only the model covers within its 99.7%
interval."""

EDGE = 0.1
EDGE_RADIUS = 2 / 320
"""The edge term's defaults: a tenth of the range of the rendered depths within 2 pixels of a
320-pixel-wide image (the radius is this fraction of the image's width). Chosen on TUM fr1/xyz's
held-out frames (benchmarks/README.md): of a small grid, the least widening that holds 99% of the
errors where only the model covers within its 99.7% interval."""

THROUGH = 1.0
"""The through term's default: the 99.73% interval reaches the surface a training view saw beyond
the rendered point. Not fitted; on TUM fr1/xyz's held-out frames it moves the share of the common
pixels' errors inside that interval from 0.9968 to 0.9975 and their NLL from -3.245 to -3.246
(benchmarks/bench_unseen.py)."""

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


def standard_deviation(sigma, dof: float = np.inf) -> np.ndarray:
    """The standard deviation (m) of the law with 1-sigma equivalent `sigma` (m, any shape) and `dof`
    degrees of freedom: sigma for a Gaussian, sigma * sqrt(dof / (dof - 2)) / t_dof(84.1%) for a
    Student-t, inf where the variance does not exist (dof <= 2)."""
    if np.isinf(dof):
        return np.asarray(sigma, np.float64)
    if dof <= 2:
        return np.full(np.shape(sigma), np.inf)
    _, one = _standard_law(dof)
    return np.asarray(sigma, np.float64) * np.sqrt(dof / (dof - 2)) / one


def standardized_multiple(probability: float, dof: float = np.inf) -> float:
    """Half-width, in standard deviations, of the central interval that holds `probability` of the
    law with `dof` > 2 degrees of freedom (inf: a Gaussian, 3.0 for 0.9973)."""
    if not 0 < probability < 1:
        raise InputError(f"probability must be in (0, 1), got {probability!r}")
    if dof <= 2:
        raise InputError(f"a law with {dof} degrees of freedom has no standard deviation (needs > 2)")
    law, _ = _standard_law(dof)
    return float(law.ppf((1 + probability) / 2) * (1 if np.isinf(dof) else np.sqrt((dof - 2) / dof)))


def depth_jump(depth: np.ndarray, radius: float = EDGE_RADIUS) -> np.ndarray:
    """(H, W) range (m) of a rendered z-depth image (H, W) m over the square of half-width
    max(1, round(radius * W)) pixels around each pixel: 0 on a smooth surface, the step at a depth
    edge (and within that many pixels of it)."""
    from scipy import ndimage

    size = 2 * max(1, round(radius * depth.shape[1])) + 1
    return ndimage.maximum_filter(depth, size, mode="nearest") - ndimage.minimum_filter(depth, size, mode="nearest")


def depth_nll(err: np.ndarray, sigma: np.ndarray, dof: float = np.inf) -> np.ndarray:
    """Negative log-likelihood (nats) of depth errors `err` (m) under the law of
    1-sigma-equivalent `sigma` (m) and `dof` degrees of freedom; arrays of one shape, or
    broadcastable."""
    law, one = _standard_law(dof)
    scale = np.asarray(sigma) / one
    return np.log(scale) - law.logpdf(np.asarray(err) / scale)


@dataclasses.dataclass(frozen=True)
class DepthErrorLaw:
    """sigma = sqrt((scale * spread)^2 + (floor * z)^2 + (unseen * z * min(1, d / unseen_ramp))^2
    + (edge * jump)^2 + (through * gap / k)^2), the 1-sigma equivalent of a Student-t with `dof`
    degrees of freedom (inf: a Gaussian), d the distance (m) to the nearest observed surface, jump
    the local range (m) of the rendered depth (:func:`depth_jump`), gap how far (m) beyond the point
    a training view saw (:meth:`~open3d_pnerf.observed.ObservedSurface.seen_through`), k the
    multiple of sigma of the 99.73% interval. The default (1, 0, inf) takes the spread as it is
    where the surface was observed, away from depth edges and from what the views saw through."""

    scale: float = 1.0
    floor: float = 0.0
    dof: float = np.inf
    unseen: float = UNSEEN
    unseen_ramp: float = UNSEEN_RAMP
    edge: float = EDGE
    through: float = THROUGH

    def sigma(self, spread: np.ndarray, depth: np.ndarray, unseen_distance: np.ndarray | None = None,
              jump: np.ndarray | None = None, seen_through: np.ndarray | None = None) -> np.ndarray:
        """The 1-sigma-equivalent error (m) of raw depth spreads (m) at z-depths `depth` (m), their
        points `unseen_distance` (m) from the nearest observed surface (None: on one), with the
        rendered depth's local range `jump` (m; None: away from any edge) and the distance
        `seen_through` (m) a training view saw beyond them (None: none did); arrays of one shape."""
        var = (self.scale * spread) ** 2 + (self.floor * depth) ** 2
        if unseen_distance is not None:
            var = var + (self.unseen * depth * np.clip(unseen_distance / self.unseen_ramp, 0, 1)) ** 2
        if jump is not None:
            var = var + (self.edge * jump) ** 2
        if seen_through is not None:
            var = var + (self.through * seen_through / self.interval(GAUSSIAN_SHARES[3])) ** 2
        return np.sqrt(var)

    def interval(self, probability: float) -> float:
        """Multiple of sigma whose +- interval holds `probability` of the errors."""
        return sigma_multiple(probability, self.dof)

    def nll(self, err: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Negative log-likelihood (nats) of errors `err` (m) with 1-sigma equivalents `sigma` (m)."""
        return depth_nll(err, sigma, self.dof)

    def cdf(self, err: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """P(error <= err) under the law, for errors `err` (m) with 1-sigma equivalents `sigma` (m):
        the probability that the true depth lies less than `err` beyond the rendered one."""
        from scipy import special

        _, one = _standard_law(self.dof)
        x = np.asarray(err) * one / np.asarray(sigma)
        return special.ndtr(x) if np.isinf(self.dof) else special.stdtr(self.dof, x)

    @classmethod
    def fit(cls, err: np.ndarray, spread: np.ndarray, z: np.ndarray, method: str = "likelihood",
            coverage: float = 0.683, unseen_distance: np.ndarray | None = None) -> "DepthErrorLaw":
        """The law of depth errors `err` (M,) m given the raw spreads (M,) m at z-depths z (M,) m.

        "likelihood": scale, floor and dof by maximum likelihood (a predictive distribution right
        across its range, not at one quantile); "gaussian": the same with dof = inf; "quantile":
        a Gaussian, floor 0 and the scale that puts `coverage` of the errors within 1 sigma (right
        at that quantile only). No errors: the default law. The unseen term keeps its defaults,
        fixed during the fit at the pixels' `unseen_distance` (M,) m from the observed surfaces
        (None: all on them); the edge term keeps its default and is not seen by the fit (pixels
        rendered alone have no neighbours), and so does the through term (the model has learned
        its training views' free space)."""
        if method not in ("likelihood", "gaussian", "quantile"):
            raise InputError(f"method must be 'likelihood', 'gaussian' or 'quantile', got {method!r}")
        if not err.size:
            return cls()
        unseen = np.zeros_like(err) if unseen_distance is None else cls().sigma(0 * err, z, unseen_distance)
        if method == "quantile":
            return cls(_quantile_scale(err, spread, unseen, coverage))
        scale = float(np.quantile(err / spread, coverage))
        return cls(*_likelihood_fit(err, spread, z, scale, method == "likelihood", unseen))

    def to_dict(self) -> dict:
        """The law as JSON-ready numbers (dof None for a Gaussian)."""
        return {"scale": self.scale, "floor": self.floor, "dof": None if np.isinf(self.dof) else self.dof,
                "unseen": self.unseen, "unseen_ramp": self.unseen_ramp, "edge": self.edge, "through": self.through}


def _quantile_scale(err: np.ndarray, spread: np.ndarray, unseen: np.ndarray, coverage: float) -> float:
    """The scale s that puts `coverage` of the errors `err` within sqrt((s spread)^2 + unseen^2),
    all (M,) metres (bisection on log s; without unseen, the quantile of err / spread)."""
    if not unseen.any():
        return float(np.quantile(err / spread, coverage))
    lo, hi = 1e-6, 1e6
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if np.mean(err <= np.hypot(mid * spread, unseen)) < coverage else (lo, mid)
    return float(hi)


def _likelihood_fit(err: np.ndarray, spread: np.ndarray, z: np.ndarray, scale0: float, fit_dof: bool = True,
                    unseen: np.ndarray | float = 0.0) -> tuple[float, float, float]:
    """(scale, floor, dof) minimising the mean negative log-likelihood of errors `err` under the
    law of sigma = sqrt((scale spread)^2 + (floor z)^2 + unseen^2): a Student-t with dof in [1,
    1000], or a Gaussian (dof inf) unless `fit_dof`; all (M,) metres (unseen: the unseen term's
    fixed sigma); starts from scale0, floor 0.1%, dof 4."""
    from scipy.optimize import minimize

    def unpack(x):
        dof = float(np.clip(np.exp(x[2]), 1.0, 1000.0)) if fit_dof else np.inf
        return np.exp(x[0]), np.exp(x[1]), dof

    def nll(x):
        s, f, dof = unpack(x)
        sigma = np.sqrt((s * spread) ** 2 + (f * z) ** 2 + unseen**2) + 1e-9
        return float(np.mean(depth_nll(err, sigma, dof)))

    start = np.log([max(scale0, 1e-6), 1e-3, 4.0][: 3 if fit_dof else 2])
    best = minimize(nll, start, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 3000})
    s, f, dof = unpack(best.x if best.fun <= nll(start) else start)
    return float(s), float(f), dof
