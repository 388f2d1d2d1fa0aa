"""Volume rendering: weights from densities, composited colour, depth, depth variance."""

from __future__ import annotations

import dataclasses

import torch
from torch.profiler import record_function

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

    The coarse samples' densities place the importance samples; the fine render composites
    the union of coarse, importance and guided samples, with the field's geometry evaluated
    once per sample (the coarse ones' are reused) and colour at every sample. The coarse
    rendering (with_coarse) reuses the fine pass's values at the coarse samples, so the paper's
    coarse loss terms cost no extra field evaluations. target_mean / target_sigma: (R,)
    ray-distance Gaussian targets, NaN where none; rays with a target get n_guided samples in
    mean +- 3 sigma, the others extra importance samples. generator: the random numbers'
    source; a :class:`BatchShare` renders rows of a larger batch exactly as that batch would.
    """
    with record_function("pnerf.coarse_pass"):
        t_c = stratified(rays, sampling.n_coarse, generator, jitter)
        e_c = bin_edges(t_c, rays.near, rays.far)
        sigma_c, features_c = field.geometry(_points(rays, t_c))
        sigma_c = sigma_c.view_as(t_c)
    with record_function("pnerf.resample"):
        n_extra = sampling.n_guided
        w_c = render_weights(sigma_c.detach(), e_c)
        t_f = importance(e_c, w_c, sampling.n_fine + n_extra, generator, jitter)
        if target_mean is not None and n_extra > 0:
            # rays with a target: n_fine importance samples drawn on their own over the whole
            # coarse PDF (not the front part of the longer draw), then the guided ones
            has = torch.isfinite(target_mean)
            guided = depth_guided(
                rays, torch.nan_to_num(target_mean), torch.nan_to_num(target_sigma, nan=1.0), n_extra, generator
            )
            t_own = torch.cat([importance(e_c, w_c, sampling.n_fine, generator, jitter), guided], 1)
            t_f = torch.where(has[:, None], t_own, t_f)
    with record_function("pnerf.fine_field"):
        t, order, sigma, features = _merged_geometry(field, rays, t_c, sigma_c, features_c, t_f)
        dirs = rays.directions[:, None, :].expand(*t.shape, 3).reshape(-1, 3)
        rgb = field.color(features.reshape(-1, features.shape[-1]), dirs).view(*t.shape, 3)
    with record_function("pnerf.composite"):
        fine = composite(t, bin_edges(t, rays.near, rays.far), sigma, rgb)
        coarse = None
        if with_coarse:
            is_coarse = order < sampling.n_coarse
            shape = t_c.shape
            coarse = composite(t_c, e_c, sigma[is_coarse].view(shape), rgb[is_coarse].view(*shape, 3))
    return fine, coarse


@torch.no_grad()
def render_rays_inference(field, rays: Rays, sampling: SamplingConfig, min_weight: float = 1e-4) -> RayRender:
    """Render rays for viewing, evaluation and export, without gradient: the samples of
    ``render_rays(jitter=False)`` with the guided samples drawn as importance ones (no targets
    here); colour is evaluated only at samples whose weight reaches `min_weight`: a sample below
    it adds less than min_weight to the pixel's colour (at most S * min_weight = 0.004 in all for
    S = 40 samples; densities, weights, depth and opacity are untouched).
    """
    with record_function("pnerf.coarse_pass"):
        t_c = stratified(rays, sampling.n_coarse, jitter=False)
        e_c = bin_edges(t_c, rays.near, rays.far)
        sigma_c, features_c = field.geometry(_points(rays, t_c))
        sigma_c = sigma_c.view_as(t_c)
    with record_function("pnerf.resample"):
        t_f = importance(e_c, render_weights(sigma_c, e_c), sampling.n_fine + sampling.n_guided, jitter=False)
    with record_function("pnerf.fine_field"):
        t, _, sigma, features = _merged_geometry(field, rays, t_c, sigma_c, features_c, t_f)
        edges = bin_edges(t, rays.near, rays.far)
        rows = (render_weights(sigma, edges) >= min_weight).nonzero(as_tuple=True)
        rgb = torch.zeros(*t.shape, 3, device=t.device)
        rgb[rows] = field.color(features[rows], rays.directions[rows[0]])
    with record_function("pnerf.composite"):
        return composite(t, edges, sigma, rgb)


def _merged_geometry(field, rays: Rays, t_c, sigma_c, features_c, t_f):
    """(t, order, sigma, features) of the coarse samples t_c (densities (R, S_c) and features
    already evaluated) and the fine ones t_f (evaluated here) merged in order along each ray:
    t (R, S) sorted, order (R, S) each column's original index (coarse ones first), sigma (R, S),
    features (R, S, C)."""
    sigma_f, features_f = field.geometry(_points(rays, t_f))
    t, order = merge(t_c, t_f)
    sigma = torch.cat([sigma_c, sigma_f.view_as(t_f)], 1).gather(1, order)
    features = torch.cat([features_c.view(*t_c.shape, -1), features_f.view(*t_f.shape, -1)], 1)
    return t, order, sigma, features.gather(1, order[..., None].expand(-1, -1, features.shape[-1]))


def _points(rays: Rays, t: torch.Tensor) -> torch.Tensor:
    return (rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None]).reshape(-1, 3)
