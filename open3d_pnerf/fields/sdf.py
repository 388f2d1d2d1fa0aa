"""A field's geometry as a signed distance (geometry="sdf"): the density that volume rendering
integrates is derived from it, as VolSDF does (Yariv et al., NeurIPS 2021), so the same
probabilistic loss (colour, depth PDF, depth) trains a surface whose zero level set is the mesh.

density(x) = Psi_beta(-sdf(x)) / beta, Psi_beta the CDF of a zero-mean Laplace law of scale beta
(m), sdf in metres, positive in free space. The sharpness 1 / beta is learned. An eikonal term
mean (|grad sdf| - 1)^2 keeps sdf a distance; its gradient is taken by central finite
differences (as Neuralangelo does on hash grids), so no second derivative of the grid encoding is
needed.

Depth targets also supervise the distance itself near and in front of the surface they measure,
as GO-Surf does (Wang et al., 3DV 2022): a point at ray distance t of a ray whose target depth is
mu lies at most mu - t from a surface (the projective distance bounds the true one), and close to
the surface that bound is the distance. Within `truncation` of mu the sdf is fitted to mu - t
(L1, m), scaled by each ray's target weight and its confidence (truncation / max(truncation,
sigma)); in front of mu - max(truncation, 3 sigma) it must lie in [0, mu - t] (a hinge on each
side).

The depth such a field reports is its surface: the first zero crossing of the signed distance
along the ray (:func:`surface_distance`), not the median of the rendered weights, which a ray
that grazes a surface within a few beta spreads in front of it.
"""

from __future__ import annotations

import dataclasses

import torch

from ..settings import Settings, count, number, setting


@dataclasses.dataclass
class SDFConfig(Settings):
    """The signed-distance geometry's settings (geometry="sdf")."""

    sharpness: float = setting(20.0, number(0, low_open=True, unit="1/m"))
    """Initial sharpness 1 / beta of the SDF-to-density law (learned from there): the density's
    Laplace CDF spreads a surface over about 1 / sharpness metres."""
    max_sharpness: float = setting(2000.0, number(0, low_open=True, unit="1/m"))
    """The learned sharpness stays below this (a density sharper than the samples can see gives
    them no gradient)."""
    eikonal_step: float = setting(0.01, number(0, low_open=True, unit="metres"))
    """Step (m) of the central finite differences that estimate grad sdf for the eikonal term."""
    eikonal_points: int = setting(1024, count(1))
    """Points per training step that the eikonal term is evaluated at: half uniform in the scene
    box, half along the batch's rays."""
    truncation: float = setting(0.05, number(0, low_open=True, unit="metres"))
    """Half-width (m) of the band around each depth target where the sdf is fitted to the
    projective distance (objective.weights.sdf_surface); in front of it, and of three target
    sigmas, the free-space bound holds (objective.weights.sdf_free)."""
    band_points: int = setting(8, count(0))
    """Points per ray with a depth target drawn uniformly in the band mu +- truncation."""
    free_points: int = setting(8, count(0))
    """Points per ray with a depth target drawn uniformly between the ray's near end and three of
    the target's sigmas (at least the band's half-width) before it."""


def laplace_cdf(s: torch.Tensor, beta: torch.Tensor | float) -> torch.Tensor:
    """CDF at s of a zero-mean Laplace law of scale beta (same units): 0.5 exp(s / beta) for
    s <= 0, 1 - 0.5 exp(-s / beta) above."""
    e = 0.5 * torch.exp(-s.abs() / beta)
    return torch.where(s <= 0, e, 1 - e)


def sdf_density(sdf: torch.Tensor, beta: torch.Tensor | float) -> torch.Tensor:
    """VolSDF's density (1/m) of signed distances sdf (m, positive in free space): Psi_beta(-sdf) / beta.
    Along a ray that crosses a plane head-on, the optical depth up to the plane is exactly 1/2."""
    return laplace_cdf(-sdf, beta) / beta


def finite_difference_gradient(sdf, x: torch.Tensor, step: float) -> torch.Tensor:
    """(B, 3) central-difference gradient of a function sdf: (M, 3) -> (M,) at points x (B, 3),
    with a step of `step` along each axis (all six offsets evaluated in one call)."""
    offsets = step * torch.cat([torch.eye(3, device=x.device), -torch.eye(3, device=x.device)])
    values = sdf((x[:, None, :] + offsets[None]).reshape(-1, 3)).reshape(-1, 6)
    return (values[:, :3] - values[:, 3:]) / (2 * step)


def eikonal_loss(sdf, x: torch.Tensor, step: float) -> torch.Tensor:
    """mean over points x (B, 3) of (|grad sdf(x)| - 1)^2, the gradient by finite differences."""
    return ((finite_difference_gradient(sdf, x, step).norm(dim=-1) - 1) ** 2).mean()


def eikonal_points(aabb: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(n, 3) points for the eikonal term: n // 2 uniform in the box aabb (2, 3), the rest at
    uniform distances along rays (origins, unit directions (R, 3), within [near, far] (R,) m)."""
    device = aabb.device
    half = n // 2
    box = aabb[0] + (aabb[1] - aabb[0]) * torch.rand(half, 3, device=device, generator=generator)
    pick = torch.randint(len(origins), (n - half,), device=device, generator=generator)
    t = near[pick] + (far[pick] - near[pick]) * torch.rand(n - half, device=device, generator=generator)
    return torch.cat([box, origins[pick] + t[:, None] * directions[pick]])


FREE_SPACE_SIGMAS = 3.0
"""The free-space bound holds in front of mu - max(truncation, 3 sigma): a surface may lie anywhere
within three of its target's sigmas, so a wide target (far, or seen by disagreeing views) does not
carve free space out of the surface it may be."""


def depth_sdf_samples(near: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, truncation: float, n_band: int,
                      n_free: int, generator: torch.Generator | None = None):
    """Ray distances (m) of the depth-supervised sdf points of R rays with near ends near (R,) and
    depth targets mu, sigma (R,): band (R, n_band) uniform in [mu - truncation, mu + truncation];
    free (R, n_free) uniform in [near, mu - max(truncation, FREE_SPACE_SIGMAS sigma)], and
    has_free (R,) whether that interval is not empty (rows without it hold its end point)."""
    device = mu.device
    band = mu[:, None] + truncation * (2 * torch.rand(len(mu), n_band, device=device, generator=generator) - 1)
    end = mu - torch.clamp(FREE_SPACE_SIGMAS * sigma, min=truncation)
    start = torch.minimum(near, end)
    free = start[:, None] + (end - start)[:, None] * torch.rand(len(mu), n_free, device=device, generator=generator)
    return band, free, end > near


def depth_sdf_loss(sdf, origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, mu: torch.Tensor,
                   sigma: torch.Tensor, weight: torch.Tensor, truncation: float, n_band: int, n_free: int,
                   inside=None, generator: torch.Generator | None = None) -> dict:
    """The depth targets' direct sdf terms (see the module docstring) of R rays (origins, unit
    directions (R, 3), near ends (R,) m) with targets mu, sigma (R,) ray-distance m (all finite)
    and target weights (R,): {"sdf_surface": mean |sdf - (mu - t)| in the band (m),
    "sdf_free": mean of relu(-sdf) + relu(sdf - (mu - t)) in front of it (m)}, means over the
    R n_band and R n_free points (zero without rays); points outside the field's box (inside:
    (M, 3) -> (M,) 1 inside, 0 outside; None: everywhere inside) and the free points of a ray
    without room for them count zero. sdf: (M, 3) -> (M,) signed distance in metres."""
    zero = origins.new_zeros(())
    terms = {"sdf_surface": zero, "sdf_free": zero}
    if len(mu) == 0 or n_band + n_free == 0:
        return terms
    band, free, has_free = depth_sdf_samples(near, mu, sigma, truncation, n_band, n_free, generator)
    t = torch.cat([band, free], 1)
    x = (origins[:, None, :] + t[..., None] * directions[:, None, :]).reshape(-1, 3)
    values = sdf(x).reshape(t.shape)
    counted = weight[:, None].expand_as(t) if inside is None else weight[:, None] * inside(x).reshape(t.shape)
    bound = mu[:, None] - t
    if n_band:
        confidence = truncation / sigma.clamp(min=truncation)
        residual = (values[:, :n_band] - bound[:, :n_band]).abs() * confidence[:, None]
        terms["sdf_surface"] = (residual * counted[:, :n_band]).mean()
    if n_free:
        free_values = values[:, n_band:]
        violation = torch.relu(-free_values) + torch.relu(free_values - bound[:, n_band:])
        terms["sdf_free"] = (violation * counted[:, n_band:] * has_free[:, None]).mean()
    return terms


def surface_distance(signed_distance, origins: torch.Tensor, directions: torch.Tensor, t: torch.Tensor,
                     density: torch.Tensor, beta: torch.Tensor | float, steps: int = 8) -> torch.Tensor:
    """(R,) ray distance (m) of the first zero crossing of the signed distance along each of R rays
    (origins, unit directions (R, 3)) rendered at samples t (R, S) (sorted) with densities density
    (R, S) (1/m, of :func:`sdf_density` with scale beta): the first sample whose density exceeds
    the surface's 1 / (2 beta) (sdf < 0) and the sample before it bracket the crossing, `steps`
    bisections of signed_distance ((M, 3) -> (M,) m) narrow it, and a linear interpolation of the
    last bracket places it. NaN where no sample is inside a surface or the first one is."""
    inside = density * beta > 0.5
    first = inside.float().argmax(1)
    rows = (inside.any(1) & (first > 0)).nonzero(as_tuple=True)[0]
    out = torch.full((len(t),), float("nan"), device=t.device)
    if not len(rows):
        return out
    k = first[rows, None]
    lo, hi = t[rows].gather(1, k - 1)[:, 0], t[rows].gather(1, k)[:, 0]
    o, d = origins[rows], directions[rows]
    for _ in range(steps):
        mid = (lo + hi) / 2
        negative = signed_distance(o + mid[:, None] * d) < 0
        lo, hi = torch.where(negative, lo, mid), torch.where(negative, mid, hi)
    s_lo, s_hi = signed_distance(o + lo[:, None] * d), signed_distance(o + hi[:, None] * d)
    share = (s_lo / (s_lo - s_hi).clamp(min=1e-12)).clamp(0, 1)
    out[rows] = lo + share * (hi - lo)
    return out
