"""Trajectory accuracy against ground truth."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.stats import chi2

from ..camera import check_poses, missing_poses, rotation_vector
from ..errors import PoseError


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform (no scale) minimising sum ||T @ source_i - target_i||^2 over
    corresponding points source, target (N, 3): Open3D's point-to-point estimation."""
    clouds = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, np.float64))) for p in (source, target)]
    pairs = o3d.utility.Vector2iVector(np.repeat(np.arange(len(source), dtype=np.int32)[:, None], 2, 1))
    estimate = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=False)
    return np.asarray(estimate.compute_transformation(*clouds, pairs))


def absolute_trajectory_error(estimate, ground_truth) -> dict:
    """Absolute trajectory error of camera positions after a rigid alignment (TUM's ATE).

    estimate, ground_truth: (N, 4, 4) camera-to-world poses of the same frames (metres);
    ground-truth rows that are NaN (frames the ground truth does not cover, see
    RGBDSequence.gt_valid) are left out. The estimate is aligned to the ground truth by the
    rigid transform (rotation and translation, no scale) that best fits the camera centres.
    Returns a dict with the position error statistics ``rmse``, ``mean``, ``max`` (metres)
    over the ``frames`` scored, and the ``alignment`` (4x4) applied to the estimate.
    """
    est = check_poses(estimate, what="estimate")
    gt = check_poses(ground_truth, len(est), what="ground_truth", allow_missing=True)
    keep = ~missing_poses(gt)
    if not keep.any():
        raise PoseError("ATE needs at least one frame with both an estimate and a ground-truth pose")
    est, gt = est[keep], gt[keep]
    align = rigid_alignment(est[:, :3, 3], gt[:, :3, 3])
    aligned = est[:, :3, 3] @ align[:3, :3].T + align[:3, 3]
    err = np.linalg.norm(aligned - gt[:, :3, 3], axis=1)
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(err.mean()),
        "max": float(err.max()),
        "frames": int(keep.sum()),
        "alignment": align,
    }


def pose_errors(estimate, ground_truth) -> np.ndarray:
    """(N, 6) errors [rotation vector (rad), translation (m)] of estimated camera-to-world poses:
    the right perturbations xi_i with gt_i = estimate_i exp(xi_i) (first order), the ground
    truth re-anchored so that frame 0 coincides with the estimate's (frame 0 is the fixed
    reference of track()). Rows of frames without ground truth are NaN."""
    est = check_poses(estimate, what="estimate")
    gt = check_poses(ground_truth, len(est), what="ground_truth", allow_missing=True)
    if missing_poses(gt)[0]:
        raise PoseError("pose errors are anchored at frame 0, which has no ground-truth pose")
    anchored = est[0] @ np.linalg.inv(gt[0]) @ gt
    delta = np.linalg.inv(est) @ anchored
    rotations = np.where(np.isnan(delta[:, :3, :3]), np.eye(3), delta[:, :3, :3])  # NaN rows: identity here
    errors = np.concatenate([rotation_vector(rotations), delta[:, :3, 3]], 1)
    errors[missing_poses(gt)] = np.nan
    return errors


def covariance_consistency(estimate, covariances, ground_truth) -> dict:
    """Whether pose covariances (N, 6, 6) are honest error bars of the estimate (N, 4, 4) against
    ground truth: :func:`consistency_of_errors` of the :func:`pose_errors` of the frames after
    frame 0 that have ground truth, plus their number ``frames``."""
    errors = pose_errors(estimate, ground_truth)
    keep = np.flatnonzero(np.isfinite(errors).all(1))
    keep = keep[keep > 0]
    if len(keep) == 0:
        raise PoseError("no frame after frame 0 has a ground-truth pose")
    return {"frames": int(len(keep)), **consistency_of_errors(errors[keep], np.asarray(covariances, np.float64)[keep])}


def consistency_of_errors(errors: np.ndarray, covariances: np.ndarray, independent: int | None = None) -> dict:
    """Whether covariances (M, 6, 6) are honest error bars of errors (M, 6) ([rotation rad,
    translation m]).

    nees_per_dof: mean of xi^T Sigma^-1 xi / 6 (1 for consistent Gaussian errors), with
    nees_band the chi-square 95% interval of that mean over `independent` independent errors
    (default M; pass fewer when the errors are correlated, e.g. the draws of a Monte Carlo run
    whose frames share a trajectory); z_std: standard deviation of the per-axis z-scores
    xi_k / sqrt(Sigma_kk) (1 ideal); within_1 / within_2: shares of those with |z| <= 1 and <= 2
    (0.683 and 0.954 for a Gaussian).
    """
    xi, cov = np.asarray(errors, np.float64), np.asarray(covariances, np.float64)
    nees = np.einsum("ni,ni->n", xi, np.linalg.solve(cov, xi[..., None])[..., 0]) / 6
    z = (xi / np.sqrt(np.diagonal(cov, axis1=1, axis2=2))).ravel()
    dof = 6 * (len(xi) if independent is None else independent)
    return {"nees_per_dof": float(nees.mean()),
            "nees_band": [float(chi2.ppf(0.025, dof) / dof), float(chi2.ppf(0.975, dof) / dof)],
            "z_std": float(z.std()), "within_1": float((np.abs(z) <= 1).mean()),
            "within_2": float((np.abs(z) <= 2).mean())}
