"""Training losses as pure functions of renderings and targets (all per-ray means), the loss
methods built from them, and the objective's settings (LossWeights, ObjectiveConfig).

PNeRF: L = Kc L_color + Kd L_depth_pdf + Kz L_depth, each an L1 over the fine render (and the
coarse one with ObjectiveConfig.coarse_terms, as the paper; the paper's L_density is the depth-PDF term;
ObjectiveConfig.coarse_color scores the coarse render's colour alone):
  L_color     = |C - C*|_1
  L_depth_pdf = sum_k |p_k - q_k|, p_k = w_k / (sum w + eps) the model's depth mass in bin k,
                q_k the target Gaussian N(mu, sigma^2)'s mass in the same bin, renormalised
                over [near, far]; sigma is floored at half the width of the bin holding mu.
  L_depth     = |sum_k w_k t_k - mu|
DS-NeRF: sum_k -log(w_k + eps) exp(-(t_k - mu)^2 / (2 sigma^2)) delta_k.
Optional with any of them: Mip-NeRF 360's distortion of the weights of every ray. With a
proposal network (sampling.n_proposal), its interlevel loss trains the proposal.
Depth targets (mu, sigma) are ray distances in metres (z-depth times ||d||); NaN = none.

A method (:class:`LossMethod`) is the colour term plus its own depth terms; ``LOSS_METHODS``
holds the library's three by name.
"""

from __future__ import annotations

import dataclasses

import torch

from .settings import FLAG, Settings, number, section, setting


@dataclasses.dataclass(frozen=True)
class LossWeights(Settings):
    """Weights of the loss terms (colour is in [0, 1], depths in metres)."""

    color: float = setting(1.0, number(0))
    """Kc: colour L1."""
    depth_pdf: float = setting(0.5, number(0))
    """Kd: PNeRF's depth-PDF L1 (per-ray mass difference, in [0, 2]); at the start of training
    (see ObjectiveConfig.depth_weight_final_factor)."""
    depth: float = setting(0.5, number(0))
    """Kz: expected-depth L1, per metre of error; at the start of training."""
    dsnerf: float = setting(0.05, number(0))
    """DS-NeRF ray-distribution loss weight (loss="dsnerf" only)."""
    eikonal: float = setting(0.1, number(0))
    """Eikonal term mean (|grad sdf| - 1)^2 (geometry="sdf" only; open3d_pnerf.fields.sdf)."""
    sdf_surface: float = setting(10.0, number(0))
    """The sdf fitted to the projective distance mu - t near each depth target, per metre
    (geometry="sdf" only; open3d_pnerf.fields.sdf). Not decayed over training. Chosen with
    sdf_free on the synthetic room (benchmarks/README.md: where the constants come from)."""
    sdf_free: float = setting(10.0, number(0))
    """The sdf kept in [0, mu - t] in front of each depth target, per metre (geometry="sdf" only)."""
    proposal: float = setting(1.0, number(0))
    """The proposal network's term (sampling.n_proposal > 0 only): its weights must bound the
    field's (Mip-NeRF 360's interlevel loss; trains the proposal network alone)."""
    distortion: float = setting(0.0, number(0))
    """Mip-NeRF 360's distortion regulariser on every ray's weights (per metre; 0 = off), with
    any loss: pulls each ray's weights into one compact interval."""


TERMS = tuple(f.name for f in dataclasses.fields(LossWeights))


@dataclasses.dataclass
class ObjectiveConfig(Settings):
    """What training minimises besides the choice of loss."""

    weights: LossWeights = section(LossWeights)
    """Loss weights Kc, Kd, Kz (and the DS-NeRF weight)."""
    depth_weight_final_factor: float = setting(0.01, number(0, 1, low_open=True))
    """The depth terms' weights (Kd, Kz, and the DS-NeRF weight, so compared losses share one
    schedule) decay exponentially over training to this fraction (1.0 = constant): geometry
    first, colour refined late."""
    coarse_terms: bool = setting(False, FLAG)
    """Add the coarse-render terms (the paper's coarse + fine losses). Off by default: the paper
    trains a coarse network of its own, while here the coarse samples are a subset of the fine
    render's, on the same field, and each stands for a bin as wide as their spacing, so the
    coarse terms ask for density at whichever coarse sample lies in front of the surface inside
    the target's bin: fog in front of every surface, which puts the rendered median in front of
    the depth (benchmarks/README.md: where the constants come from). The forward_facing preset
    keeps them: its Fern figures were measured with them."""
    coarse_color: bool = setting(False, FLAG)
    """Score the coarse render's colour alone besides the fine render's terms (its depth terms
    stay off unless coarse_terms): the field learns to show each surface's colour at the coarse
    samples that place the fine ones. Off: on dense TUM fr1/xyz, the scene the coarse terms were
    chosen on, it leaves held-out colour as it was and costs the field's depth in every seed, and
    it costs both with 10 views and on 7-Scenes; it raises the bundled sample's (`make demo`)
    held-out colour (benchmarks/README.md: where the constants come from)."""
    pose_prior_weight: float = setting(1e-3, number(0))
    """Weight of the pose prior (mean over frames of 0.5 xi^T Sigma^-1 xi), with refine_poses."""


def color_l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over rays of the per-channel-mean absolute colour error; (R, 3) inputs."""
    return (pred - target).abs().mean()


def gaussian_bin_masses(edges: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """(R, S) mass of N(mu, sigma^2) in each bin [e_k, e_{k+1}], renormalised over [e_0, e_S].

    sigma is floored at half the width of the bin containing mu, so a sharp target is never
    narrower than the discretisation can express.
    """
    idx = torch.searchsorted(edges.contiguous(), mu[:, None].contiguous()).clamp(1, edges.shape[1] - 1)
    width = edges.gather(1, idx) - edges.gather(1, idx - 1)
    s = torch.maximum(sigma, 0.5 * width[:, 0]).clamp(min=1e-6)
    cdf = torch.special.ndtr((edges - mu[:, None]) / s[:, None])
    mass = cdf[:, 1:] - cdf[:, :-1]
    return mass / (cdf[:, -1:] - cdf[:, :1]).clamp(min=1e-8)


def depth_pdf_l1(weights, edges, mu, sigma, eps: float = 1e-6) -> torch.Tensor:
    """(R,) sum_k |p_k - q_k| between normalised weights and the target's bin masses."""
    p = weights / (weights.sum(-1, keepdim=True) + eps)
    q = gaussian_bin_masses(edges, mu, sigma)
    return (p - q).abs().sum(-1)


def depth_l1(weights, t, mu) -> torch.Tensor:
    """(R,) |sum_k w_k t_k - mu| (the paper's unnormalised expected depth; metres)."""
    return ((weights * t).sum(-1) - mu).abs()


def distortion(weights, edges) -> torch.Tensor:
    """(R,) Mip-NeRF 360's distortion of weights (R, S) in bins edges (R, S + 1) (metres):
    sum_ij w_i w_j |m_i - m_j| + sum_i w_i^2 delta_i / 3, m the bin midpoints, delta their
    widths; the pairwise sum in O(S) as 2 sum_i w_i (m_i W_<i - (w m)_<i) for sorted bins."""
    mid, delta = (edges[:, 1:] + edges[:, :-1]) / 2, edges[:, 1:] - edges[:, :-1]
    before = torch.cumsum(weights, -1) - weights  # W_<i
    before_m = torch.cumsum(weights * mid, -1) - weights * mid
    return 2 * (weights * (mid * before - before_m)).sum(-1) + (weights**2 * delta).sum(-1) / 3


def proposal_bounds(edges, proposal_edges, proposal_weights) -> torch.Tensor:
    """(R, S) the proposal weights' bound on each bin [e_k, e_{k+1}] of edges (R, S + 1): the sum
    of the proposal weights (R, P) of every proposal bin on proposal_edges (R, P + 1) that
    overlaps it (Mip-NeRF 360's outer measure)."""
    cum = torch.cat([torch.zeros_like(proposal_weights[:, :1]), proposal_weights.cumsum(-1)], -1)
    p = proposal_weights.shape[1]
    # first proposal bin ending after the bin's start, last one starting before its end
    first = torch.searchsorted(proposal_edges[:, 1:].contiguous(), edges[:, :-1].contiguous(), right=True)
    last = torch.searchsorted(proposal_edges[:, :-1].contiguous(), edges[:, 1:].contiguous()) - 1
    first, last = first.clamp(0, p - 1), last.clamp(0, p - 1)
    bound = cum.gather(1, last + 1) - cum.gather(1, first)
    return torch.where(last >= first, bound, torch.zeros_like(bound))


def proposal_loss(weights, edges, proposal_weights, proposal_edges, eps: float = 1e-7) -> torch.Tensor:
    """(R,) Mip-NeRF 360's interlevel loss: sum_k max(0, w_k - bound_k)^2 / w_k over the field's
    weights (R, S) on edges (R, S + 1) (held fixed: it trains the proposal alone), bound_k the
    proposal's (:func:`proposal_bounds`). Zero when the proposal's mass covers the field's."""
    w = weights.detach()
    excess = (w - proposal_bounds(edges.detach(), proposal_edges, proposal_weights)).clamp(min=0)
    return (excess**2 / (w + eps)).sum(-1)


def dsnerf_loss(weights, t, edges, mu, sigma, eps: float = 1e-5) -> torch.Tensor:
    """(R,) DS-NeRF: sum_k -log(w_k + eps) exp(-(t_k - mu)^2 / (2 sigma^2)) delta_k."""
    delta = edges[:, 1:] - edges[:, :-1]
    s = sigma.clamp(min=1e-4)[:, None]
    return (-torch.log(weights + eps) * torch.exp(-((t - mu[:, None]) ** 2) / (2 * s * s)) * delta).sum(-1)


class LossMethod:
    """A training objective: the colour L1 on every ray plus the method's depth terms on the
    rays that have a depth target. `terms` names them (fields of :class:`LossWeights`)."""

    name = "photometric"
    terms: tuple[str, ...] = ()

    def depth_terms(self, weights, t, edges, mu, sigma) -> dict[str, torch.Tensor]:
        """Per-ray (R,) values of each depth term for R rays with targets mu, sigma (R,)."""
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class PNeRFLoss(LossMethod):
    """The paper's: depth-PDF L1 against the target Gaussian, and expected-depth L1."""

    name = "pnerf"
    terms = ("depth_pdf", "depth")

    def depth_terms(self, weights, t, edges, mu, sigma):
        return {"depth_pdf": depth_pdf_l1(weights, edges, mu, sigma), "depth": depth_l1(weights, t, mu)}


class DSNeRFLoss(LossMethod):
    """DS-NeRF's ray-distribution loss."""

    name = "dsnerf"
    terms = ("dsnerf",)

    def depth_terms(self, weights, t, edges, mu, sigma):
        return {"dsnerf": dsnerf_loss(weights, t, edges, mu, sigma)}


LOSS_METHODS = {m.name: m for m in (PNeRFLoss(), LossMethod(), DSNeRFLoss())}
LOSSES = tuple(LOSS_METHODS)


def loss_method(method: str | LossMethod) -> LossMethod:
    """The LossMethod of a name in LOSSES (or the method itself)."""
    if isinstance(method, LossMethod):
        return method
    if method not in LOSS_METHODS:
        raise ValueError(f"unknown loss {method!r}; expected one of {LOSSES}")
    return LOSS_METHODS[method]


def total_loss(method: str | LossMethod, renders, target_rgb, mu, sigma, weights: LossWeights = LossWeights(),
               n_rays: int | None = None, n_target: int | None = None, target_weight=None,
               depth_renders: int | None = None) -> dict:
    """Loss terms and their weighted sum over renders (e.g. [fine, coarse]).

    method: a name in LOSSES or a LossMethod. mu, sigma (R,): ray-distance targets, NaN
    where a ray has none (those rays get the colour term only). Returns a dict of scalar
    tensors: "loss" (the total) and each term summed over the renders.
    n_rays, n_target: when these R rays are a share of a larger batch, that batch's ray
    count and count of rays with a target; every per-ray mean is then taken over the whole
    batch, so the shares' losses (and gradients) add up to the whole batch's.
    target_weight (R,): each target's weight in the depth terms (e.g. DS-NeRF's reprojection
    weight of an SfM point; None = 1): a term is sum_r w_r term_r / n_target.
    depth_renders: the depth terms (and the distortion) score only the first this many renders
    (None: all); the others add their colour term alone.
    """
    method = loss_method(method)
    has = torch.isfinite(mu)
    n_target = has.sum().clamp(min=1) if n_target is None else max(n_target, 1)
    share = 1.0 if n_rays is None else len(target_rgb) / n_rays  # colour: this share's part of the batch mean
    mu_v, sigma_v = mu[has], sigma[has]
    w_v = None if target_weight is None else target_weight[has]
    terms = dict.fromkeys(TERMS, 0.0)
    for i, r in enumerate(renders):
        terms["color"] = terms["color"] + color_l1(r.color, target_rgb) * share
        if depth_renders is not None and i >= depth_renders:
            continue
        if weights.distortion > 0:
            terms["distortion"] = terms["distortion"] + distortion(r.weights, r.edges).mean() * share
        if r.proposal_weights is not None:
            terms["proposal"] = terms["proposal"] + proposal_loss(r.weights, r.edges, r.proposal_weights,
                                                                  r.proposal_edges).mean() * share
        if not method.terms or not has.any():
            continue
        per_ray = method.depth_terms(r.weights[has], r.t[has], r.edges[has], mu_v, sigma_v)
        for name, values in per_ray.items():
            terms[name] = terms[name] + (values if w_v is None else values * w_v).sum() / n_target
    total = sum(getattr(weights, k) * v for k, v in terms.items())
    terms = {k: torch.as_tensor(v) for k, v in terms.items()}
    terms["loss"] = total
    return terms
