"""Sparse structure from motion as an optional part of a sequence: camera poses with their
covariances, sparse 3D points with reprojection errors and tracks, and near/far bounds.

A sequence without depth images (an LLFF folder, a nerfstudio capture without depth) carries
an :class:`SfMData`; ``reconstruct()`` then trains on its poses and on its points as sparse
depth targets (:func:`~open3d_pnerf.targets.sparse_depth_targets`).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ..camera import check_poses
from ..errors import InputError


@dataclasses.dataclass
class SparsePoints:
    """SfM points of an image sequence.

    xyz: (M, 3) float64 world points (scene units); error: (M,) mean reprojection error in
    pixels of the sequence's images; observed: (M, N) bool, point k is in frame i's track.
    """

    xyz: np.ndarray
    error: np.ndarray
    observed: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def track_length(self) -> np.ndarray:
        """(M,) number of the sequence's frames observing each point."""
        return self.observed.sum(1)

    @classmethod
    def empty(cls, n_frames: int) -> "SparsePoints":
        """No points, for N frames."""
        return cls(np.empty((0, 3)), np.empty(0), np.zeros((0, n_frames), bool))


@dataclasses.dataclass
class SfMData:
    """Camera poses and sparse points from structure from motion, for the N frames of a sequence.

    poses: (N, 4, 4) camera-to-world, OpenCV axes; covariances: (N, 6, 6) of those poses
    ([rotation, translation], right perturbation; see :func:`sfm_pose_covariances`); points:
    :class:`SparsePoints` (error in pixels of the images the sequence reads at image scale 1);
    bounds: (N, 2) near/far z-depth, or None when unknown; scale: scene units per SfM unit;
    radial: (k1, k2) radial distortion of the images (normalised image coordinates, COLMAP's
    SIMPLE_RADIAL / RADIAL): a point at normalised (x, y) is seen at (x, y) (1 + k1 r^2 + k2 r^4).
    The images are used as they are (as pinhole images, as NeRF does); sparse targets' rays go
    through where the images show their points.
    """

    poses: np.ndarray
    covariances: np.ndarray
    points: SparsePoints
    bounds: np.ndarray | None = None
    scale: float = 1.0
    radial: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def from_poses(cls, poses: np.ndarray, bounds: np.ndarray | None = None) -> "SfMData":
        """The poses a capture brings (a device's own tracking, a capture app's): (N, 4, 4)
        camera-to-world, with zero covariances (not known: reconstruct() takes them as they are) and no
        points; bounds: (N, 2) near/far z-depth of an image-only capture, or None."""
        poses = np.asarray(poses, np.float64)
        return cls(poses, np.zeros((len(poses), 6, 6)), SparsePoints.empty(len(poses)), bounds)

    def check(self, n: int, what: str) -> "SfMData":
        """Return self after checking its shapes against n frames (InputError naming `what`)."""
        self.poses = check_poses(self.poses, n, f"{what}: poses")
        self.covariances = np.asarray(self.covariances, np.float64)
        if self.covariances.shape != (n, 6, 6) or not np.isfinite(self.covariances).all():
            raise InputError(f"{what}: need finite (N, 6, 6) covariances for {n} images, got {self.covariances.shape}")
        if self.bounds is not None:
            self.bounds = np.asarray(self.bounds, np.float64)
            if self.bounds.shape != (n, 2) or not np.isfinite(self.bounds).all():
                raise InputError(f"{what}: need finite (N, 2) bounds for {n} images, got {self.bounds.shape}")
        if self.points.observed.shape != (len(self.points), n):
            raise InputError(f"{what}: points.observed must be (M, {n}), got {self.points.observed.shape}")
        return self

    def select(self, idx: np.ndarray) -> "SfMData":
        """The data of frames `idx` (the points keep only those frames' observations)."""
        points = dataclasses.replace(self.points, observed=self.points.observed[:, idx])
        bounds = None if self.bounds is None else self.bounds[idx]
        return dataclasses.replace(self, poses=self.poses[idx], covariances=self.covariances[idx], points=points,
                                   bounds=bounds)

    def at_pixel_scale(self, factor: float) -> "SfMData":
        """The same data with reprojection errors in pixels of images resized by `factor`."""
        return dataclasses.replace(self, points=dataclasses.replace(self.points, error=self.points.error * factor))


def sfm_pose_covariances(poses: np.ndarray, K: np.ndarray, xyz: np.ndarray, error: np.ndarray,
                         observed: np.ndarray, min_error: float = 0.01) -> np.ndarray:
    """(N, 6, 6) covariance of each camera pose from the SfM points it observes.

    poses: (N, 4, 4) camera-to-world; K: (3, 3); xyz: (M, 3); error: (M,) reprojection error
    (pixels of K's images, floored at `min_error`), taken as the standard deviation of each
    observation; observed: (M, N) bool. With the points held fixed, the Gauss-Newton
    information of frame i is sum_k J_k^T J_k / e_k^2, J_k (2, 6) the derivative of point k's
    projection with respect to a right perturbation [rotation, translation] of the pose (as
    the tracker's covariances); the covariance is its inverse. Holding the points fixed
    ignores their own uncertainty, so these are lower bounds. A frame seeing fewer than 3
    points, or points that do not fix its pose, gets an effectively unbounded covariance (1e6
    on its diagonal) and a warning.
    """
    poses = check_poses(poses, what="sfm_pose_covariances(): poses")
    fx, fy = K[0, 0], K[1, 1]
    var = np.maximum(np.asarray(error, np.float64), min_error) ** 2
    out = np.empty((len(poses), 6, 6))
    for i, pose in enumerate(poses):
        idx = np.flatnonzero(observed[:, i])
        q = (xyz[idx] - pose[:3, 3]) @ pose[:3, :3]  # camera frame
        front = q[:, 2] > 1e-9
        idx, q = idx[front], q[front]
        if len(idx) < 3:
            warnings.warn(f"frame {i} observes {len(idx)} SfM point(s): its pose covariance is unbounded")
            out[i] = np.eye(6) * 1e6
            continue
        x, y, z = q.T
        proj = np.zeros((len(q), 2, 3))  # d(u, v) / dq
        proj[:, 0, 0], proj[:, 0, 2] = fx / z, -fx * x / z**2
        proj[:, 1, 1], proj[:, 1, 2] = fy / z, -fy * y / z**2
        dq = np.zeros((len(q), 3, 6))  # q' = exp(-xi) q ~ q + q x w - rho
        dq[:, 0, 1], dq[:, 0, 2] = -z, y
        dq[:, 1, 0], dq[:, 1, 2] = z, -x
        dq[:, 2, 0], dq[:, 2, 1] = -y, x
        dq[:, :, 3:] = -np.eye(3)
        jac = proj @ dq
        info = np.einsum("kai,kaj,k->ij", jac, jac, 1.0 / var[idx])
        if np.linalg.cond(info) > 1e12:  # e.g. coincident or collinear points
            warnings.warn(f"frame {i}: its {len(idx)} SfM points do not fix its pose (degenerate "
                          "geometry): its pose covariance is unbounded")
            out[i] = np.eye(6) * 1e6
            continue
        out[i] = np.linalg.inv(info)
    return out
