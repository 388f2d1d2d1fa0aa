"""Volume rendering: weights from densities, composited colour, depth, depth variance."""

from __future__ import annotations

import contextlib
import dataclasses

import torch
from torch.profiler import record_function

from ..settings import FLAG, Settings, count, setting
from .rays import Rays
from .samplers import BatchShare, bin_edges, depth_guided, importance, invert_cdf, merge, stratified


@dataclasses.dataclass
class RayRender:
    """Rendering of R rays with S samples each.

    t (R, S) sample distances and edges (R, S + 1) bin edges (ray-distance metres);
    weights (R, S); color (R, 3) in [0, 1]; opacity (R,) = sum of weights; depth (R,)
    expected ray distance under the normalised weights (what the depth loss trains); depth_var
    (R,) their variance (m^2); median (R,) their median (the depth renders report); density
    (R, S) the densities (1/m) they were composited from. With a
    proposal network: its bins proposal_edges (R, P + 1) and weights proposal_weights (R, P),
    which placed the coarse samples.
    """

    t: torch.Tensor
    edges: torch.Tensor
    weights: torch.Tensor
    color: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    depth_var: torch.Tensor
    density: torch.Tensor | None = None
    proposal_edges: torch.Tensor | None = None
    proposal_weights: torch.Tensor | None = None

    @property
    def median(self) -> torch.Tensor:
        """(R,) median ray distance of the normalised weights, each bin's weight spread evenly over
        the bin. The point estimate of least expected absolute error under the ray's distribution:
        where a ray's weights split between two surfaces (a depth edge, a faint floater) it lies on
        the heavier one, where the expected depth lies in the empty space between them."""
        return weight_quantile(self.edges, self.weights, 0.5)


def weight_quantile(edges: torch.Tensor, weights: torch.Tensor, q: float) -> torch.Tensor:
    """(R,) q-quantile (ray distance) of the piecewise-constant PDF of weights (R, S) >= 0 on bins
    edges (R, S + 1); a ray without weight counts its bins as equally likely."""
    cdf = torch.cat([torch.zeros_like(weights[:, :1]), weights.cumsum(-1)], -1)
    total = cdf[:, -1:]
    cdf = torch.where(total > 0, cdf / total.clamp(min=1e-30), torch.linspace(0, 1, cdf.shape[1], device=cdf.device))
    return invert_cdf(edges, cdf, torch.full_like(total, q))[:, 0]


def render_weights(sigma: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """w_k = T_k (1 - exp(-sigma_k delta_k)), T_k = prod_{j<k} exp(-sigma_j delta_j). (R, S)."""
    tau = sigma * (edges[:, 1:] - edges[:, :-1])
    alpha = 1 - torch.exp(-tau)
    transmittance = torch.exp(-torch.cat([torch.zeros_like(tau[:, :1]), tau[:, :-1].cumsum(-1)], -1))
    return transmittance * alpha


def composite(t, edges, sigma, rgb) -> RayRender:
    """Composite densities (R, S) and colours (R, S, 3) at samples t with bins `edges`."""
    w = render_weights(sigma, edges)
    opacity = w.sum(-1)
    p = w / (opacity[:, None] + 1e-10)
    depth = (p * t).sum(-1)
    depth_var = (p * (t - depth[:, None]) ** 2).sum(-1)
    color = (w[..., None] * rgb).sum(1)
    return RayRender(t, edges, w, color, opacity, depth, depth_var, sigma)


@dataclasses.dataclass
class SamplingConfig(Settings):
    """Samples per ray: stratified coarse, importance fine, and depth-guided (where a target exists)."""

    n_coarse: int = setting(16, count(2))
    """Stratified samples per ray (coarse pass)."""
    n_fine: int = setting(8, count(0))
    """Importance samples per ray drawn from the coarse weights (fine pass)."""
    n_guided: int = setting(16, count(0))
    """Samples in mean +- 3 sigma of the depth target (extra importance samples without one)."""
    depth_guided: bool = setting(True, FLAG)
    """Place the n_guided samples around the depth target when training with depth terms
    (False: extra importance samples)."""
    n_proposal: int = setting(0, count(0))
    """Samples per ray of a proposal network (a small density-only hash grid, trained to bound the
    field's weights, as nerfacto's) that places the n_coarse samples by importance; 0: none, the
    n_coarse samples are stratified."""
    n_coarse_render: int = setting(32, count(2))
    """Stratified samples per ray when rendering (views, evaluation, calibration, export), at least
    n_coarse: a coarse pass that steps over a thin structure (a table leg) never samples it finely,
    and the ray renders what lies behind it. Only density is evaluated at these samples (colour
    where the weight counts), so renders cost a little more, training nothing."""

    def for_render(self) -> "SamplingConfig":
        """These settings with n_coarse raised to n_coarse_render (what renders sample)."""
        return dataclasses.replace(self, n_coarse=max(self.n_coarse, self.n_coarse_render))


def render_rays(
    field,
    rays: Rays,
    sampling: SamplingConfig,
    target_mean: torch.Tensor | None = None,
    target_sigma: torch.Tensor | None = None,
    generator: torch.Generator | BatchShare | None = None,
    jitter: bool = True,
    with_coarse: bool = False,
    color_min_weight: float = 0.0,
) -> tuple[RayRender, RayRender | None]:
    """Render rays with a coarse (stratified) and a fine pass; returns (fine, coarse or None).

    The coarse samples' densities, computed without gradient, place the fine samples: importance
    samples drawn from them and, on rays with a depth target (target_mean / target_sigma (R,)
    ray-distance Gaussians, NaN where none), n_guided samples in mean +- 3 sigma (the other rays
    get extra importance samples). When training a field whose ``encodes_in_one_pass`` is set (a
    grid's gradient is one dense tensor), the coarse pass runs without gradient and every sample,
    fine and coarse, is then encoded in one call of the field (the coarse encodings are reused),
    so that a step writes the grid's gradient once, and the field's heads run on each set;
    otherwise (renders, MLP fields) the fine samples are evaluated and the coarse ones keep the
    values of the coarse pass. The fine render composites the union
    of the samples; with_coarse: also the coarse samples alone, from the same values (the paper's
    coarse loss terms, at no extra field evaluation). Colour is evaluated at every sample, or,
    with color_min_weight > 0 (renders for viewing), only where a sample's weight reaches it (a
    sample below adds less than that to the pixel; S * color_min_weight in all). generator: the
    random numbers' source (a :class:`BatchShare` renders rows of a larger batch exactly as that
    batch would); jitter=False: samples in the middle of their slices (deterministic renders).
    The coarse samples are even in the field's depth coordinate (in disparity for a field with
    an NDC warp, fields.ndc; in ray distance otherwise), or, for a field with a proposal network
    (``field.proposal``, fields.proposal), importance samples of the proposal's weights at
    n_proposal such samples.
    """
    disparity = getattr(field, "warp", None) is not None  # even in NDC z
    proposal = getattr(field, "proposal", None)
    with record_function("pnerf.coarse_pass"):  # the proposal network's samples count in it
        if proposal is not None:
            t_p = stratified(rays, sampling.n_proposal, generator, jitter, disparity)
            e_p = bin_edges(t_p, rays.near, rays.far)
            x_p = _points(rays, t_p)
            w_p = render_weights((proposal(field.normalize(x_p)) * field.inside(x_p)).view_as(t_p), e_p)
            t_c = importance(e_p, w_p, sampling.n_coarse, generator, jitter)
        else:
            t_c = stratified(rays, sampling.n_coarse, generator, jitter, disparity)
        e_c = bin_edges(t_c, rays.near, rays.far)
        x_c = _points(rays, t_c)
        one_pass = torch.is_grad_enabled() and getattr(field, "encodes_in_one_pass", False)
        with torch.no_grad() if one_pass else contextlib.nullcontext():
            encoded_c = field.encode(x_c)
            sigma_c, features_c = field.geometry(x_c, encoded_c)
        w_c = render_weights(sigma_c.detach().view_as(t_c), e_c)
    with record_function("pnerf.resample"):
        t_f = importance(e_c, w_c, sampling.n_fine + sampling.n_guided, generator, jitter)
        if target_mean is not None and sampling.n_guided > 0:
            # rays with a target: n_fine importance samples drawn on their own over the whole
            # coarse PDF (not the front part of the longer draw), then the guided ones
            has = torch.isfinite(target_mean)
            guided = depth_guided(rays, torch.nan_to_num(target_mean), torch.nan_to_num(target_sigma, nan=1.0),
                                  sampling.n_guided, generator)
            t_own = torch.cat([importance(e_c, w_c, sampling.n_fine, generator, jitter), guided], 1)
            t_f = torch.where(has[:, None], t_own, t_f)
    with record_function("pnerf.fine_field"):
        x_f = _points(rays, t_f)
        if one_pass:  # every sample in one encoding call (fine ones first, as the gradient sums)
            encoded = field.encode(torch.cat([x_f, x_c]), known=encoded_c).split([len(x_f), len(x_c)])
            (sigma_f, features_f), (sigma_c, features_c) = (field.geometry(x, e) for x, e in zip((x_f, x_c), encoded))
        else:  # the coarse samples keep the values of the pass above
            sigma_f, features_f = field.geometry(x_f)
        t, order = merge(t_c, t_f)
        sigma = torch.cat([sigma_c.view_as(t_c), sigma_f.view_as(t_f)], 1).gather(1, order)
        features = torch.cat([features_c.view(*t_c.shape, -1), features_f.view(*t_f.shape, -1)], 1)
        features = features.gather(1, order[..., None].expand(-1, -1, features.shape[-1]))
        edges = bin_edges(t, rays.near, rays.far)
        if color_min_weight > 0:
            rows = (render_weights(sigma, edges) >= color_min_weight).nonzero(as_tuple=True)
            rgb = torch.zeros(*t.shape, 3, device=t.device)
            rgb[rows] = field.color(features[rows], rays.directions[rows[0]])
        else:
            dirs = rays.directions[:, None, :].expand(*t.shape, 3).reshape(-1, 3)
            rgb = field.color(features.reshape(-1, features.shape[-1]), dirs).view(*t.shape, 3)
    with record_function("pnerf.composite"):
        fine = composite(t, edges, sigma, rgb)
        if proposal is not None:  # what its loss needs
            fine.proposal_edges, fine.proposal_weights = e_p, w_p
        coarse = None
        if with_coarse:
            is_coarse = order < sampling.n_coarse
            shape = t_c.shape
            coarse = composite(t_c, e_c, sigma[is_coarse].view(shape), rgb[is_coarse].view(*shape, 3))
    return fine, coarse


def _points(rays: Rays, t: torch.Tensor) -> torch.Tensor:
    return (rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None]).reshape(-1, 3)
