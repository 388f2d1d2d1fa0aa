"""Distance to occupied space and the chance of a collision, from an occupancy grid."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..errors import ConfigError, InputError


@dataclasses.dataclass(eq=False)
class DistanceField:
    """A Euclidean signed distance field (ESDF) on an occupancy grid's voxels: distance (X, Y, Z)
    float32 m from each voxel's centre to the nearest centre of a voxel more likely occupied than
    not (positive outside occupied space, negative inside it, to its nearest other voxel; inf with
    nothing occupied). Its uncertainty: lower, the same distance to every voxel not confidently
    free (occupied with probability >= 0.2, unknown space included), and upper, to the confidently
    occupied voxels only (> 0.8): the true clearance lies between them wherever the grid's calls
    are right. origin (3,) and voxel_size (m) as the grid's."""

    distance: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    origin: np.ndarray
    voxel_size: float

    def at(self, points) -> dict:
        """{"distance", "lower", "upper"}: (N,) m at the voxel of each point (N, 3) m; NaN outside."""
        points = np.asarray(points, np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"points must be (N, 3) in metres, got shape {points.shape}")
        index = np.floor((points - self.origin) / self.voxel_size).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.distance.shape)), axis=1)
        out = {}
        for name in ("distance", "lower", "upper"):
            values = np.full(len(points), np.nan)
            values[inside] = getattr(self, name)[tuple(index[inside].T)]
            out[name] = values
        return out

    def save(self, path) -> Path:
        """Write the three fields, origin and voxel_size to an ``.npz`` (NumPy)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, distance=self.distance, lower=self.lower, upper=self.upper, origin=self.origin,
                            voxel_size=self.voxel_size)
        return path


def signed_distance(obstacle: np.ndarray, voxel_size: float) -> np.ndarray:
    """(X, Y, Z) float32 signed distance (m) between voxel centres: outside `obstacle` (bool,
    (X, Y, Z)) to its nearest voxel, inside it (negative) to the nearest voxel outside; inf (or
    -inf) where there is none (scipy's exact Euclidean distance transform)."""
    if not obstacle.any():
        return np.full(obstacle.shape, np.inf, np.float32)
    if obstacle.all():
        return np.full(obstacle.shape, -np.inf, np.float32)
    outside = ndimage.distance_transform_edt(~obstacle, sampling=voxel_size)
    inside = ndimage.distance_transform_edt(obstacle, sampling=voxel_size)
    return (outside - inside).astype(np.float32)


def distance_field(probability: np.ndarray, origin: np.ndarray, voxel_size: float, free_below: float,
                   occupied_above: float) -> DistanceField:
    """The :class:`DistanceField` of voxels (X, Y, Z) occupied with `probability`: distance to those
    above 0.5, lower to those at or above `free_below`, upper to those above `occupied_above`."""
    return DistanceField(signed_distance(probability > 0.5, voxel_size),
                         signed_distance(probability >= free_below, voxel_size),
                         signed_distance(probability > occupied_above, voxel_size), np.array(origin), voxel_size)


def collision_probability(grid, points, radius: float) -> np.ndarray:
    """(N,) probability that a sphere of `radius` (m) centred at each point (N, 3) m touches
    occupied space: the largest occupancy probability of the voxels whose centres lie within
    `radius` of it (and of its own voxel; 0.5 outside the grid). That is the exact probability when
    the voxels' states go together, and a lower bound otherwise: no product over voxels, since
    neighbouring voxels are seen by the same rays and are not independent. A path's: the largest
    of its points'."""
    if isinstance(radius, bool) or not isinstance(radius, (int, float, np.floating, np.integer)) \
            or not np.isfinite(radius) or radius < 0:
        raise ConfigError(f"radius must be a number of metres >= 0, got {radius!r}")
    reach = int(np.ceil(radius / grid.voxel_size))
    steps = np.arange(-reach, reach + 1)
    offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3)
    index, _ = grid._index(points)
    centers = grid.origin + (index[:, None, :] + offsets[None] + 0.5) * grid.voxel_size
    near = np.linalg.norm(centers - np.asarray(points, np.float64)[:, None], axis=2) <= radius
    near[:, len(offsets) // 2] = True  # the point's own voxel
    p = grid.probability(centers.reshape(-1, 3)).reshape(near.shape)
    return np.where(near, p, 0.0).max(axis=1)
