"""What the sensor saw: the surfaces behind a reconstruction's depth targets, kept as occupied
voxels, so that the model's depth can say how far it is from anything observed.

A rendered depth whose point lies on an observed surface is what the model learned from; one far
from every observed surface is the model's guess (a hole it filled, a wall no training view
reached), and its error bar must say so: :meth:`ObservedSurface.distance` is the widening term of
the depth-error law (:class:`~open3d_pnerf.error_law.DepthErrorLaw`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy.spatial import cKDTree

from .camera import backproject
from .errors import InputError


_KEY_BITS = 21
"""Bits per axis of a packed voxel key: voxels within 2^20 of the origin (10 km at 1 cm)."""


def _packed(keys: np.ndarray) -> np.ndarray:
    """(M, 3) integer voxel keys -> (M',) int64 packed keys, one number per voxel (distinct voxels
    are then found by sorting numbers, not rows); keys out of range are left out."""
    half = 1 << (_KEY_BITS - 1)
    keys = keys[(np.abs(keys) < half).all(1)].astype(np.int64) + half
    return (keys[:, 0] << (2 * _KEY_BITS)) | (keys[:, 1] << _KEY_BITS) | keys[:, 2]


def _distinct(values: np.ndarray) -> np.ndarray:
    """The sorted distinct values of a 1-D array: a sort and a comparison (numpy 2.4's np.unique
    hashes, which is slower on millions of voxel keys)."""
    values = np.sort(values)
    return values[np.concatenate([[True], values[1:] != values[:-1]])] if len(values) else values


def _unpacked(packed: np.ndarray) -> np.ndarray:
    """(M,) packed keys -> (M, 3) int64 voxel keys."""
    mask = (1 << _KEY_BITS) - 1
    return np.stack([packed >> (2 * _KEY_BITS), (packed >> _KEY_BITS) & mask, packed & mask], 1) - (1 << (_KEY_BITS - 1))


@dataclasses.dataclass(frozen=True, eq=False)
class ObservedSurface:
    """Voxels of edge `voxel_size` (m) holding at least one observed surface point.

    centres: (M, 3) float32 voxel centres (m, world frame).
    """

    voxel_size: float
    centres: np.ndarray

    def __post_init__(self):
        centres = np.asarray(self.centres, np.float32)
        if centres.ndim != 2 or centres.shape[1] != 3 or not np.isfinite(centres).all():
            raise InputError(f"ObservedSurface: centres must be finite (M, 3) points, got shape {centres.shape}")
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"ObservedSurface: voxel_size must be > 0 m, got {self.voxel_size!r}")
        object.__setattr__(self, "centres", centres)

    @classmethod
    def from_depths(cls, depths: np.ndarray, valid: np.ndarray, K: np.ndarray, poses: np.ndarray,
                    voxel_size: float, aabb: np.ndarray | None = None) -> "ObservedSurface":
        """The voxels holding the points of N depth maps: depths (N, H, W) z metres where `valid`
        (N, H, W) bool, K (3, 3), poses (N, 4, 4) camera-to-world; points outside the box aabb
        (2, 3) (stray far returns), or more than 2^20 voxels from the origin, are left out."""
        keys = []
        for depth, mask, pose in zip(depths, valid, poses):
            pts = backproject(depth, K, pose, mask & (depth > 0))[0]
            if aabb is not None:
                pts = pts[((pts >= aabb[0]) & (pts <= aabb[1])).all(1)]
            keys.append(_distinct(_packed(np.floor(pts / voxel_size))))
        keys = _unpacked(_distinct(np.concatenate(keys))) if keys else np.zeros((0, 3), np.int64)
        return cls(float(voxel_size), (keys + 0.5) * voxel_size)

    def __len__(self) -> int:
        return len(self.centres)

    @functools.cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.centres)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(...) distance (m) from points (..., 3) to the nearest observed voxel: 0 inside one
        (within half its diagonal of its centre), inf when nothing was observed; NaN for points
        that are not finite."""
        points = np.asarray(points, np.float64)
        out = np.full(points.shape[:-1], np.nan)
        finite = np.isfinite(points).all(-1)
        if not len(self):
            out[finite] = np.inf
        elif finite.any():
            d = self._tree.query(points[finite])[0]
            out[finite] = np.maximum(d - np.sqrt(3) / 2 * self.voxel_size, 0)
        return out
