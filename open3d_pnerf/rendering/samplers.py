"""Samples along rays, as sorted ray distances t (R, S) with their bins (R, S + 1).

Each sample t_k represents the interval [e_k, e_{k+1}] of the bin edges e; edges are the
midpoints between neighbouring samples, clipped to [near, far]. Volume rendering uses the
bin widths, and the PNeRF density loss compares per-bin masses, so non-uniform samples
(importance or depth-guided) are handled exactly.
"""

from __future__ import annotations

import dataclasses

import torch

from .rays import Rays


@dataclasses.dataclass(frozen=True)
class BatchShare:
    """Rows [start, stop) of a batch of `size` rays, with the batch's random numbers.

    Given to the samplers in place of a generator, it makes them draw their uniforms for the
    whole batch from `generator` and keep these rows: a share of a batch is sampled exactly
    as inside the whole batch (data-parallel training renders one share per rank).
    """

    generator: torch.Generator
    size: int
    start: int
    stop: int


def uniform(r: int, n: int, device, generator: torch.Generator | BatchShare | None = None) -> torch.Tensor:
    """(r, n) uniforms in [0, 1) from a generator, or this share's rows of the whole batch's."""
    if isinstance(generator, BatchShare):
        if r != generator.stop - generator.start:
            raise ValueError(f"{r} rays but the batch share has rows [{generator.start}, {generator.stop})")
        return _rand(generator.size, n, device, generator.generator)[generator.start:generator.stop]
    return _rand(r, n, device, generator)


def _rand(r: int, n: int, device, generator: torch.Generator | None) -> torch.Tensor:
    """torch.rand drawn on the generator's own device (the trainer's is a CPU generator, so a
    seeded run draws the same numbers on any device), then moved to `device`."""
    if generator is None:
        return torch.rand(r, n, device=device)
    return torch.rand(r, n, device=generator.device, generator=generator).to(device)


def bin_edges(t: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """(R, S + 1) bin edges for sorted samples t (R, S): midpoints, ends clipped to [near, far]."""
    mid = 0.5 * (t[:, 1:] + t[:, :-1])
    first = (2 * t[:, :1] - mid[:, :1]).clamp(min=near[:, None]) if t.shape[1] > 1 else near[:, None]
    last = (2 * t[:, -1:] - mid[:, -1:]).clamp(max=far[:, None]) if t.shape[1] > 1 else far[:, None]
    first = torch.minimum(first, t[:, :1])
    last = torch.maximum(last, t[:, -1:])
    return torch.cat([first, mid, last], 1)


def stratified(rays: Rays, n: int, generator: torch.Generator | BatchShare | None = None,
               jitter: bool = True, disparity: bool = False) -> torch.Tensor:
    """(R, n) sorted samples, one uniformly jittered per equal slice of [near, far], or with
    disparity=True of [1 / near, 1 / far] (inverse ray distance: even steps of NDC z)."""
    r = len(rays)
    u = torch.arange(n, device=rays.near.device, dtype=torch.float32)
    offset = uniform(r, n, u.device, generator) if jitter else torch.full((r, n), 0.5, device=u.device)
    s = (u + offset) / n
    if disparity:
        return 1 / ((1 - s) / rays.near[:, None] + s / rays.far[:, None])
    return rays.near[:, None] + s * (rays.far - rays.near)[:, None]


def importance(
    edges: torch.Tensor, weights: torch.Tensor, n: int, generator: torch.Generator | BatchShare | None = None,
    jitter: bool = True
) -> torch.Tensor:
    """(R, n) sorted samples drawn from the piecewise-constant PDF of `weights` on `edges`.

    edges (R, S + 1), weights (R, S) >= 0 (e.g. coarse rendering weights). A small floor
    keeps rays with zero weight sampling uniformly instead of producing NaN.
    """
    w = weights.detach() + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(-1)], -1).clamp(max=1)
    r = weights.shape[0]
    base = torch.arange(n, device=w.device, dtype=torch.float32)
    offset = uniform(r, n, w.device, generator) if jitter else torch.full((r, n), 0.5, device=w.device)
    return invert_cdf(edges, cdf, (base + offset) / n)


def invert_cdf(edges: torch.Tensor, cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """(R, n) ray distances where a piecewise-linear CDF (R, S + 1), rising from 0 to 1 over the
    bin edges (R, S + 1), reaches the levels u (R, n) in [0, 1]."""
    idx = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(1, cdf.shape[1] - 1)
    c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
    e0, e1 = edges.gather(1, idx - 1), edges.gather(1, idx)
    frac = ((u - c0) / (c1 - c0).clamp(min=1e-8)).clamp(0, 1)
    return e0 + frac * (e1 - e0)


def depth_guided(
    rays: Rays, mean: torch.Tensor, sigma: torch.Tensor, n: int, generator: torch.Generator | BatchShare | None = None,
    spread: float = 3.0
) -> torch.Tensor:
    """(R, n) samples stratified over mean +- spread * sigma (ray-distance units), clipped to [near, far].

    Samples fall on equal-probability slices of the Gaussian (inverse CDF of stratified
    uniforms), so most land near the mean.
    """
    r = mean.shape[0]
    base = torch.arange(n, device=mean.device, dtype=torch.float32)
    u = (base + uniform(r, n, mean.device, generator)) / n
    lo = torch.special.ndtr(torch.tensor(-spread))
    p = lo + u * (1 - 2 * lo)
    t = mean[:, None] + sigma[:, None] * torch.special.ndtri(p)
    return torch.minimum(torch.maximum(t, rays.near[:, None]), rays.far[:, None])


def merge(*samples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted union of sample sets (R, S_i) -> (t (R, S), index of each original column)."""
    t = torch.cat(samples, 1)
    t, order = t.sort(1)
    return t, order
