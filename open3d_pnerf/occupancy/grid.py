"""The occupancy grid: voxels with the log-odds that they are occupied, for a planner, Open3D and OctoMap."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.special import expit

from ..errors import ConfigError, InputError
from .distance import DistanceField, collision_probability, distance_field

FREE_BELOW = 0.2
OCCUPIED_ABOVE = 0.8
"""A voxel is called free below this probability of being occupied, occupied above that one, and
undecided between them."""

MAX_VOXELS = 20_000_000
"""The largest grid built (80 MB of log-odds, a few times that while building: a 20 x 20 x 3 m floor at 5 cm)."""


@dataclasses.dataclass(eq=False)
class OccupancyGrid:
    """log_odds (X, Y, Z) float32 that each voxel is occupied (0: unknown, probability 0.5);
    voxel (i, j, k) spans origin + voxel_size * [i, i+1) x [j, j+1) x [k, k+1) (m, world frame).
    The origin is a multiple of voxel_size, so the voxels are OctoMap's at that resolution."""

    log_odds: np.ndarray
    origin: np.ndarray
    voxel_size: float

    def __post_init__(self):
        self.log_odds = np.asarray(self.log_odds, np.float32)
        self.origin = np.asarray(self.origin, np.float64).reshape(3)
        if self.log_odds.ndim != 3:
            raise InputError(f"log_odds must be a (X, Y, Z) array, got shape {self.log_odds.shape}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.log_odds.shape

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner (m)."""
        return np.stack([self.origin, self.origin + self.voxel_size * np.array(self.shape)])

    def centers(self) -> np.ndarray:
        """(X, Y, Z, 3) voxel centres (m)."""
        axes = [self.origin[d] + self.voxel_size * (np.arange(n) + 0.5) for d, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)

    def probabilities(self) -> np.ndarray:
        """(X, Y, Z) probability that each voxel is occupied."""
        return expit(self.log_odds.astype(np.float64))

    def probability(self, points) -> np.ndarray:
        """(N,) probability that the voxel of each point (N, 3) m is occupied; 0.5 outside the grid."""
        index, inside = self._index(points)
        out = np.full(len(index), 0.5)
        out[inside] = expit(self.log_odds[tuple(index[inside].T)].astype(np.float64))
        return out

    def free(self, points, threshold: float = FREE_BELOW) -> np.ndarray:
        """(N,) bool: the point's voxel is occupied with probability below `threshold`."""
        return self.probability(points) < threshold

    def occupied(self, points, threshold: float = OCCUPIED_ABOVE) -> np.ndarray:
        """(N,) bool: the point's voxel is occupied with probability above `threshold`."""
        return self.probability(points) > threshold

    def unknown(self) -> np.ndarray:
        """(X, Y, Z) bool: the voxels no training view's ray reached (probability 0.5)."""
        return self.log_odds == 0

    def _index(self, points) -> tuple[np.ndarray, np.ndarray]:
        points = np.asarray(points, np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"points must be (N, 3) in metres, got shape {points.shape}")
        index = np.floor((points - self.origin) / self.voxel_size).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.shape)), axis=1)
        return index, inside

    # -- for a planner ----------------------------------------------------------------------
    def esdf(self) -> DistanceField:
        """The Euclidean signed distance to occupied space with its uncertainty (a
        :class:`~open3d_pnerf.occupancy.DistanceField`: distance, lower, upper)."""
        return distance_field(self.probabilities(), self.origin, self.voxel_size, FREE_BELOW, OCCUPIED_ABOVE)

    def collision_probability(self, points, radius: float) -> np.ndarray:
        """(N,) probability that a sphere of `radius` (m) at each point (N, 3) of a path touches
        occupied space (see :func:`~open3d_pnerf.occupancy.distance.collision_probability`)."""
        return collision_probability(self, points, radius)

    # -- other tools' formats ---------------------------------------------------------------
    def to_open3d(self, threshold: float = 0.5) -> o3d.geometry.VoxelGrid:
        """An ``o3d.geometry.VoxelGrid`` of the voxels occupied with probability above
        `threshold`, coloured by that probability (matplotlib's viridis, 0.5 to 1)."""
        from matplotlib import colormaps

        p = self.probabilities()
        keep = p > threshold
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.centers()[keep]))
        cloud.colors = o3d.utility.Vector3dVector(colormaps["viridis"](np.clip(2 * p[keep] - 1, 0, 1))[:, :3])
        lo, hi = self.bounds
        return o3d.geometry.VoxelGrid.create_from_point_cloud_within_bounds(cloud, self.voxel_size, lo, hi)

    def write_octomap(self, path) -> Path:
        """Write the grid as an OctoMap octree: ``.ot`` keeps each known voxel's log-odds (as
        float32), ``.bt`` (OctoMap's compact binary) only whether it is free or occupied. Unknown
        voxels are left out, as OctoMap leaves them. Read by OctoMap's library (octomap-python's
        ``OcTree.read``, ``readBinary``) and so by ROS's octomap_server."""
        try:
            import octomap
        except ImportError as exc:
            raise ImportError("write_octomap() needs octomap-python (`pip install octomap-python`; it has "
                              "no wheel for Linux on ARM)") from exc
        path = Path(path)
        if path.suffix not in (".ot", ".bt"):
            raise InputError(f"{path}: an OctoMap file is .ot (probabilities) or .bt (free or occupied)")
        tree = octomap.OcTree(self.voxel_size)
        lo, hi = float(self.log_odds.min(initial=0)), float(self.log_odds.max(initial=0))
        tree.setClampingThresMin(min(expit(lo), 0.5) * 0.999)  # keep every value as it is
        tree.setClampingThresMax(1 - (1 - max(expit(hi), 0.5)) * 0.999)
        known = ~self.unknown()
        for center, value in zip(self.centers()[known], self.log_odds[known]):
            tree.updateNode(center, float(value), lazy_eval=True)
        tree.updateInnerOccupancy()
        path.parent.mkdir(parents=True, exist_ok=True)
        if not (tree.write(str(path).encode()) if path.suffix == ".ot" else tree.writeBinary(str(path).encode())):
            raise OSError(f"OctoMap could not write {path}")
        return path

    # -- on disk ----------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write log_odds, origin and voxel_size to an ``.npz`` (NumPy)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, log_odds=self.log_odds, origin=self.origin, voxel_size=self.voxel_size)
        return path

    @classmethod
    def load(cls, path) -> "OccupancyGrid":
        """The grid :meth:`save` wrote."""
        with np.load(path) as data:
            missing = {"log_odds", "origin", "voxel_size"} - set(data.files)
            if missing:
                raise InputError(f"{path}: not an occupancy grid (no {', '.join(sorted(missing))})")
            return cls(data["log_odds"], data["origin"], float(data["voxel_size"]))


def grid_frame(voxel_size, bounds, default_bounds: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """(origin (3,), shape) of the grid of `voxel_size` (m) covering `bounds` ((2, 3) min and max
    corner, m; None: `default_bounds`), its origin a multiple of the voxel size. ConfigError names
    the argument when either is not what it should be."""
    if isinstance(voxel_size, bool) or not isinstance(voxel_size, (int, float, np.floating, np.integer)) \
            or not np.isfinite(voxel_size) or voxel_size <= 0:
        raise ConfigError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    box = np.asarray(default_bounds if bounds is None else bounds, np.float64) if not isinstance(bounds, str) else None
    if box is None or box.shape != (2, 3) or not np.isfinite(box).all() or not (box[1] > box[0]).all():
        raise ConfigError(f"bounds must be (2, 3): a min and a max corner (m), min < max on every axis, "
                          f"got {bounds!r}")
    origin = np.floor(box[0] / voxel_size) * voxel_size
    shape = tuple(int(n) for n in np.maximum(np.ceil((box[1] - origin) / voxel_size - 1e-9), 1))
    if np.prod(shape, dtype=np.int64) > MAX_VOXELS:
        raise ConfigError(f"voxel_size {voxel_size} m makes {np.prod(shape, dtype=np.int64):,} voxels over the "
                          f"bounds (more than {MAX_VOXELS:,}): choose a larger voxel_size or smaller bounds")
    return origin, shape
