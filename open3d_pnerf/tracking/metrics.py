"""Trajectory accuracy against ground truth."""

from __future__ import annotations

import numpy as np

from ..camera import check_poses
from ..errors import PoseError


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform (no scale) minimising sum ||T @ source_i - target_i||^2.

    source, target: (N, 3) corresponding points (Kabsch / Umeyama without scale).
    """
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((target - mu_t).T @ (source - mu_s))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    T = np.eye(4)
    T[:3, :3] = u @ d @ vt
    T[:3, 3] = mu_t - T[:3, :3] @ mu_s
    return T


def absolute_trajectory_error(estimate, ground_truth) -> dict:
    """Absolute trajectory error of camera positions after a rigid alignment (TUM's ATE).

    estimate, ground_truth: (N, 4, 4) camera-to-world poses of the same frames (metres).
    The estimate is aligned to the ground truth by the rigid transform (rotation and
    translation, no scale) that best fits the camera centres. Returns a dict with the
    position error statistics ``rmse``, ``mean``, ``max`` (metres) and the ``alignment``
    (4x4) applied to the estimate.
    """
    est = check_poses(estimate, what="estimate")
    gt = check_poses(ground_truth, len(est), what="ground_truth")
    if len(est) == 0:
        raise PoseError("ATE needs at least one pose, got an empty estimate")
    align = rigid_alignment(est[:, :3, 3], gt[:, :3, 3])
    aligned = est[:, :3, 3] @ align[:3, :3].T + align[:3, 3]
    err = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(err.mean()),
        "max": float(err.max()),
        "alignment": align,
    }
