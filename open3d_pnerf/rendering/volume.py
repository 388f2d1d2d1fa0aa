"""Volume rendering: weights from densities, composited colour, depth, depth variance."""

from __future__ import annotations

import dataclasses

import torch

from .rays import Rays
from .samplers import BatchShare, bin_edges, depth_guided, importance, merge, stratified


@dataclasses.dataclass
class RayRender:
    """Rendering of R rays with S samples each.

    t (R, S) sample distances and edges (R, S + 1) bin edges (ray-distance metres);
    weights (R, S); color (R, 3) in [0, 1]; opacity (R,) = sum of weights; depth (R,)
    expected ray distance under the normalised weights; depth_var (R,) their variance (m^2).
    """

    t: torch.Tensor
    edges: torch.Tensor
    weights: torch.Tensor
    color: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    depth_var: torch.Tensor


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
    return RayRender(t, edges, w, color, opacity, depth, depth_var)


@dataclasses.dataclass
class SamplingConfig:
    """Samples per ray: stratified coarse, importance fine, and depth-guided (where a target exists)."""

    n_coarse: int = 16
    """Stratified samples per ray (coarse pass)."""
    n_fine: int = 8
    """Importance samples per ray drawn from the coarse weights (fine pass)."""
    n_guided: int = 16
    """Samples in mean +- 3 sigma of the depth target (extra importance samples without one)."""
    depth_guided: bool = True
    """Place the n_guided samples around the depth target when training with depth terms
    (False: extra importance samples)."""


def render_rays(
    field,
    rays: Rays,
    sampling: SamplingConfig,
    target_mean: torch.Tensor | None = None,
    target_sigma: torch.Tensor | None = None,
    generator: torch.Generator | BatchShare | None = None,
    jitter: bool = True,
    with_coarse: bool = False,
) -> tuple[RayRender, RayRender | None]:
    """Render rays with a coarse (stratified) and a fine pass; returns (fine, coarse or None).

    The coarse densities are evaluated without gradient to place importance samples; the
    fine pass evaluates the field once on the union of coarse, importance and guided
    samples. The coarse rendering (with_coarse) reuses the fine pass's values at the coarse
    samples, so the paper's coarse loss terms cost no extra field evaluations.
    target_mean / target_sigma: (R,) ray-distance Gaussian targets, NaN where none; rays
    with a target get n_guided samples in mean +- 3 sigma, the others extra importance samples.
    generator: the random numbers' source; a :class:`BatchShare` renders rows of a larger
    batch exactly as that batch would.
    """
    t_c = stratified(rays, sampling.n_coarse, generator, jitter)
    e_c = bin_edges(t_c, rays.near, rays.far)
    with torch.no_grad():
        sigma_c = field.density(_points(rays, t_c)).view_as(t_c)
        w_c = render_weights(sigma_c, e_c)
    n_extra = sampling.n_guided
    t_f = importance(e_c, w_c, sampling.n_fine + n_extra, generator, jitter)
    if target_mean is not None and n_extra > 0:
        has = torch.isfinite(target_mean)
        guided = depth_guided(
            rays, torch.nan_to_num(target_mean), torch.nan_to_num(target_sigma, nan=1.0), n_extra, generator
        )
        t_f = torch.cat([t_f[:, : sampling.n_fine], torch.where(has[:, None], guided, t_f[:, sampling.n_fine :])], 1)
    t, order = merge(t_c, t_f)
    sigma, rgb = _evaluate(field, rays, t)
    fine = composite(t, bin_edges(t, rays.near, rays.far), sigma, rgb)
    coarse = None
    if with_coarse:
        is_coarse = order < sampling.n_coarse
        shape = t_c.shape
        coarse = composite(t_c, e_c, sigma[is_coarse].view(shape), rgb[is_coarse].view(*shape, 3))
    return fine, coarse


def _points(rays: Rays, t: torch.Tensor) -> torch.Tensor:
    return (rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None]).reshape(-1, 3)


def _evaluate(field, rays: Rays, t: torch.Tensor):
    r, s = t.shape
    dirs = rays.directions[:, None, :].expand(r, s, 3).reshape(-1, 3)
    sigma, rgb = field(_points(rays, t), dirs)
    return sigma.view(r, s), rgb.view(r, s, 3)
