"""What the sensor saw: the surfaces behind a reconstruction's depth targets, kept as occupied
voxels and as each training view's depth map, so that the model's depth can say how far it is
from anything observed and whether a view saw through it.

A rendered depth whose point lies on an observed surface is what the model learned from; one far
from every observed surface is the model's guess (a hole it filled, a wall no training view
reached), and its error bar must say so: :meth:`ObservedSurface.distance` is the unseen term of
the depth-error law (:class:`~open3d_pnerf.error_law.DepthErrorLaw`). A rendered point that a
training view saw through (its depth there lies well beyond the point) is an observed surface the
model put where the sensor saw free space, e.g. a foreground object's silhouette rendered too
wide: the surface behind may be the right answer, and :meth:`ObservedSurface.seen_through` is the
law's through term.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .camera import backproject, nearest_pixels
from .errors import InputError


SEEN_THROUGH_MARGIN = 0.1
"""How far (m) beyond a point a view's depth must lie for the view to have seen through it: well
above the sensor's noise at room depths. Of 0.03 and 0.1 on TUM fr1/xyz's held-out frames
(benchmarks/bench_unseen.py), 0.1 flags fewer pixels (2.5% against 5.9% where the sensor alone
also covers) at the same NLL."""

SEEN_THROUGH_VIEWS = 64
"""How many training views, the nearest to the camera, :meth:`ObservedSurface.seen_through` asks
when given the camera: a render's cost stays bounded on long sequences (every view of the scenes
in benchmarks/ is asked)."""

_KEY_BITS = 21
"""Bits per axis of a packed voxel key: voxels within 2^20 of the origin (10 km at 1 cm)."""

MERGE_EVERY = 64
"""Depth maps whose voxel keys are gathered before they join the distinct ones: most voxels are
seen again, so memory grows with the scene, not the number of views."""


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
    """Voxels of edge `voxel_size` (m) holding at least one observed surface point, and the views
    that saw them.

    centres: (M, 3) float32 voxel centres (m, world frame). depths: (N, H, W) float16 z-depth (m)
    of the nearest surface each of N training views saw over a pixel and its 8 neighbours (0:
    none), K (3, 3) their intrinsic matrix, poses (N, 4, 4) camera-to-world; None: not kept.
    """

    voxel_size: float
    centres: np.ndarray
    depths: np.ndarray | None = None
    K: np.ndarray | None = None
    poses: np.ndarray | None = None

    def __post_init__(self):
        centres = np.asarray(self.centres, np.float32)
        if centres.ndim != 2 or centres.shape[1] != 3 or not np.isfinite(centres).all():
            raise InputError(f"ObservedSurface: centres must be finite (M, 3) points, got shape {centres.shape}")
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"ObservedSurface: voxel_size must be > 0 m, got {self.voxel_size!r}")
        object.__setattr__(self, "centres", centres)
        if self.depths is not None:
            depths, K = np.asarray(self.depths, np.float16), np.asarray(self.K, np.float64)
            poses = np.asarray(self.poses, np.float64)
            if depths.ndim != 3 or not (np.isfinite(depths).all() and (depths >= 0).all()) or K.shape != (3, 3) \
                    or poses.shape != (len(depths), 4, 4):
                raise InputError(f"ObservedSurface: depths must be finite (N, H, W) z-depths >= 0 m with K (3, 3) and "
                                 f"poses (N, 4, 4), got {depths.shape}, {K.shape}, {poses.shape}")
            object.__setattr__(self, "depths", depths)
            object.__setattr__(self, "K", K)
            object.__setattr__(self, "poses", poses)

    @classmethod
    def from_depths(cls, depths: np.ndarray, valid: np.ndarray, K: np.ndarray, poses: np.ndarray,
                    voxel_size: float, aabb: np.ndarray | None = None) -> "ObservedSurface":
        """The voxels holding the points of N depth maps: depths (N, H, W) z metres where `valid`
        (N, H, W) bool, K (3, 3), poses (N, 4, 4) camera-to-world; points outside the box aabb
        (2, 3) (stray far returns), or more than 2^20 voxels from the origin, are left out. The
        views are kept for :meth:`seen_through`."""
        nearest = np.zeros(np.shape(depths), np.float16)  # the nearest surface around each pixel: 0 where none
        keys, pending = np.zeros(0, np.int64), []
        for k, (depth, mask, pose) in enumerate(zip(depths, valid, poses)):  # each map read once
            seen = mask & (depth > 0)
            around = ndimage.minimum_filter(np.where(seen, depth, np.inf), 3, mode="nearest")
            nearest[k] = np.where(np.isfinite(around), around, 0)
            pts = backproject(depth, K, pose, seen)[0]
            if aabb is not None:
                pts = pts[((pts >= aabb[0]) & (pts <= aabb[1])).all(1)]
            pending.append(_distinct(_packed(np.floor(pts / voxel_size))))
            if len(pending) == MERGE_EVERY:
                keys, pending = _distinct(np.concatenate([keys, *pending])), []
        keys = _unpacked(_distinct(np.concatenate([keys, *pending])))
        return cls(float(voxel_size), (keys + 0.5) * voxel_size, nearest, K, poses)

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

    def seen_through(self, points: np.ndarray, camera: np.ndarray | None = None,
                     margin: float = SEEN_THROUGH_MARGIN) -> np.ndarray:
        """(...) distance (m) by which a training view's depth saw past points (..., 3): the largest,
        over the views, z-distance from a point to the nearest surface its view saw around the pixel
        it projects to, where that lies more than `margin` (m) beyond the point; 0 where no view saw
        past it (or the views were not kept), NaN for points that are not finite. camera: the
        centre (3,) m of the camera the points were rendered from; then only the SEEN_THROUGH_VIEWS
        views nearest to it are asked."""
        points = np.asarray(points, np.float64)
        out = np.where(np.isfinite(points).all(-1), 0.0, np.nan)
        if self.depths is None or not np.isfinite(out).any():
            return out
        views = np.arange(len(self.depths))
        if camera is not None and len(views) > SEEN_THROUGH_VIEWS:
            views = np.argsort(np.linalg.norm(self.poses[:, :3, 3] - camera, axis=1))[:SEEN_THROUGH_VIEWS]
        flat, gap = points.reshape(-1, 3), np.zeros(out.size)
        h, w = self.depths.shape[1:]
        for k in views:  # one view at a time: indexing the stack by `views` would copy every map
            pose = self.poses[k]
            cam = (flat - pose[:3, 3]) @ pose[:3, :3]
            front = np.flatnonzero(cam[:, 2] > 1e-3)
            pix, inside = nearest_pixels(self.K, cam[front], h, w)
            front = front[inside]
            beyond = self.depths[k].reshape(-1)[pix[inside]] - cam[front, 2]  # no depth (0): negative
            seen = beyond > margin
            gap[front[seen]] = np.maximum(gap[front[seen]], beyond[seen])
        return np.where(np.isfinite(out), gap.reshape(out.shape), np.nan)
