"""Camera rays in world space and their entry/exit distances in the scene box.

Pixel (u, v) of an OpenCV camera with intrinsic K has its centre at integer coordinates.
Its ray is o + t d with the unit direction d = R k / ||k||, k = K^-1 [u, v, 1], so t is
the Euclidean distance along the ray and a point at z-depth z has t = z ||k||
(``Rays.norms`` holds ||k||). Densities integrate over metres of t, the same in every view.
"""

from __future__ import annotations

import dataclasses

import torch

from ..camera import camera_rays


@dataclasses.dataclass
class Rays:
    """A batch of R rays: origins (R, 3), unit directions (R, 3), near/far (R,) metres along
    the ray, and norms (R,) = ||K^-1 [u, v, 1]||: metres along the ray per metre of z-depth."""

    origins: torch.Tensor
    directions: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    norms: torch.Tensor

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index) -> "Rays":
        return Rays(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))

    @classmethod
    def cat(cls, batches: list["Rays"]) -> "Rays":
        """Concatenate ray batches."""
        return cls(*(torch.cat([getattr(b, f.name) for b in batches]) for f in dataclasses.fields(cls)))


def pixel_rays(pose: torch.Tensor, K: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """Origins (R, 3), unit world directions (R, 3) and norms ||K^-1 [u, v, 1]|| (R,) of pixels
    (u, v) (:func:`~open3d_pnerf.camera.camera_rays` rotated into the world).

    pose: (4, 4) or (R, 4, 4) camera-to-world; K: (3, 3) or (R, 3, 3).
    """
    if pose.dim() == 2:
        pose = pose.expand(u.shape[0], 4, 4)
    d_cam = camera_rays(K, u, v)
    norms = d_cam.norm(dim=-1)
    directions = (pose[:, :3, :3] @ (d_cam / norms[:, None])[..., None])[..., 0]
    return pose[:, :3, 3].clone(), directions, norms


def intersect_aabb(origins, directions, aabb, min_near: float = 0.05):
    """Entry and exit distances (R,) of rays in the box aabb (2, 3); far <= near means a miss."""
    inv = 1.0 / torch.where(directions.abs() < 1e-9, torch.full_like(directions, 1e-9), directions)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp(min=min_near)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far


def make_rays(pose, K, u, v, aabb, min_near: float = 0.05, depth_range: torch.Tensor | None = None) -> Rays:
    """World rays for pixels (u, v) clipped to the scene box (misses get far = near + 1e-3) and,
    given depth_range (2,) = [near, far] z-depth (e.g. an LLFF scene's bounds), to that slab
    in front of the camera."""
    origins, directions, norms = pixel_rays(pose, K, u, v)
    near, far = intersect_aabb(origins, directions, aabb, min_near)
    if depth_range is not None:
        near = torch.maximum(near, depth_range[0] * norms)
        far = torch.minimum(far, depth_range[1] * norms)
    far = torch.maximum(far, near + 1e-3)
    return Rays(origins, directions, near, far, norms)
