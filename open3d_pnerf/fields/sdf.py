"""A field's geometry as a signed distance (geometry="sdf"): the density that volume rendering
integrates is derived from it, as VolSDF does (Yariv et al., NeurIPS 2021), so the same
probabilistic loss (colour, depth PDF, depth) trains a surface whose zero level set is the mesh.

density(x) = Psi_beta(-sdf(x)) / beta, Psi_beta the CDF of a zero-mean Laplace law of scale beta
(m), sdf in metres, positive in free space. The sharpness 1 / beta is learned. An eikonal term
mean (|grad sdf| - 1)^2 keeps sdf a distance; its gradient is taken by central finite
differences (as Neuralangelo does on hash grids), so no second derivative of the grid encoding is
needed.
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
