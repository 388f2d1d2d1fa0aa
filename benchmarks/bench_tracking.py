"""Benchmark open3d_pnerf.track() against ground truth on the shared real RGB-D data.

For TUM fr1/xyz (32 associated frames, mocap GT) and 7-Scenes redkitchen frames 150-199
(50 frames, KinectFusion GT), both 640x480: ATE RMSE after rigid alignment for
frame-to-frame odometry only and for the full pipeline (loop closures + global
optimisation), time per frame, the end frame's predicted pose standard deviations against
its actual error, and a calibration of ``point_noise_m`` (the value that makes the
frames' pose errors against GT match their predicted covariances). Also
counts the failures detected on 7-Scenes every-10th-frame data, where odometry fails.

Run: ``.venv/bin/python benchmarks/bench_tracking.py``; writes benchmarks/results/tracking.json.
"""

from __future__ import annotations

import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from open3d_pnerf.data import load_sequence
from open3d_pnerf.tracking import DEFAULT_POINT_NOISE_M, absolute_trajectory_error, track

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DATASETS = {
    "tum_fr1_xyz": DATA / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz",
    "7scenes_redkitchen_150-199": DATA / "7scenes_redkitchen" / "frames_150-199",
}
FAILURE_DATASET = DATA / "7scenes_redkitchen" / "every10th_0-990"
FAILURE_FRAMES = 30
RESULTS = Path(__file__).resolve().parent / "results" / "tracking.json"


def twist_error(T: np.ndarray) -> np.ndarray:
    """[rotation vector (rad), translation (m)] of a near-identity 4x4 transform."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def pose_errors(poses: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(N, 6) right-perturbation errors xi with gt_i = pose_i exp(xi), GT re-anchored at frame 0."""
    gt_rel = np.linalg.inv(gt[0]) @ gt
    return np.stack([twist_error(np.linalg.inv(p) @ g) for p, g in zip(poses, gt_rel)])


def fitted_point_noise(trajectory, gt: np.ndarray, point_noise_m: float) -> float:
    """point_noise_m that makes the frames' errors against GT match their covariances.

    With covariances S_i computed at `point_noise_m`, the mean chi-square per degree of
    freedom of xi_i^T S_i^-1 xi_i over frames 1..N-1 is (s_fit / point_noise_m)^2.
    """
    errors = pose_errors(trajectory.poses, gt)[1:]
    chi2 = [e @ np.linalg.solve(c, e) for e, c in zip(errors, trajectory.covariances[1:])]
    return float(point_noise_m * np.sqrt(np.mean(chi2) / 6.0))


def run(seq, loop_closure: bool) -> dict:
    """Track `seq` once; ATE, timing and end-frame uncertainty against the GT."""
    start = time.perf_counter()
    traj = track(seq, loop_closure=loop_closure, progress=False)
    elapsed = time.perf_counter() - start
    ate = absolute_trajectory_error(traj.poses, seq.gt_poses)
    end_error = pose_errors(traj.poses, seq.gt_poses)[-1]
    cov = traj.covariances[-1]
    return {
        "ate_rmse_mm": 1000 * ate["rmse"],
        "ate_mean_mm": 1000 * ate["mean"],
        "ate_max_mm": 1000 * ate["max"],
        "ms_per_frame": 1000 * elapsed / len(seq),
        "failed_frames": traj.failed_frames,
        "loop_closures_kept": sum(e.kind == "loop" and e.success for e in traj.edges),
        "loop_closures_tried": sum(e.kind == "loop" for e in traj.edges),
        "end_cov_trace": float(np.trace(cov)),
        "end_std_rot_deg": np.degrees(np.sqrt(np.diag(cov)[:3])).round(4).tolist(),
        "end_std_trans_mm": (1000 * np.sqrt(np.diag(cov)[3:])).round(3).tolist(),
        "end_error_rot_deg": float(np.degrees(np.linalg.norm(end_error[:3]))),
        "end_error_trans_mm": float(1000 * np.linalg.norm(end_error[3:])),
        "fitted_point_noise_m": fitted_point_noise(traj, seq.gt_poses, DEFAULT_POINT_NOISE_M),
    }


def machine_info() -> dict:
    import torch

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS", "unset"),
        "python": platform.python_version(),
        "open3d": o3d.__version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
    }


def main() -> None:
    if not DATA.is_dir():
        raise SystemExit(f"shared data not found at {DATA}")
    results = {"machine": machine_info(), "point_noise_m": DEFAULT_POINT_NOISE_M, "datasets": {}}
    for name, path in DATASETS.items():
        seq = load_sequence(path)
        results["datasets"][name] = {
            "frames": len(seq),
            "resolution": list(seq.image_size[::-1]),
            "odometry_only": run(seq, loop_closure=False),
            "full_pipeline": run(seq, loop_closure=True),
        }
    seq = load_sequence(FAILURE_DATASET).select(range(FAILURE_FRAMES))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        failure = run(seq, loop_closure=False)
    results["failure_detection_7scenes_every10th"] = {
        "frames": len(seq),
        "failed_frames": failure["failed_frames"],
        "ate_rmse_mm": failure["ate_rmse_mm"],
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print_table(results)
    print(f"saved {RESULTS}")


def print_table(results: dict) -> None:
    print(f"machine: {results['machine']}")
    print(f"point_noise_m = {results['point_noise_m']}")
    header = f"{'dataset':28s} {'mode':14s} {'ATE rmse mm':>11s} {'ms/frame':>9s} {'loops':>7s} " \
             f"{'end std mm / deg':>18s} {'end err mm / deg':>18s} {'fit s':>6s}"
    print(header)
    for name, r in results["datasets"].items():
        for mode in ("odometry_only", "full_pipeline"):
            m = r[mode]
            std_mm = np.linalg.norm(m["end_std_trans_mm"])
            std_deg = np.linalg.norm(m["end_std_rot_deg"])
            print(
                f"{name:28s} {mode:14s} {m['ate_rmse_mm']:11.1f} {m['ms_per_frame']:9.0f} "
                f"{m['loop_closures_kept']:>3d}/{m['loop_closures_tried']:<3d} "
                f"{std_mm:9.1f} / {std_deg:5.2f} "
                f"{m['end_error_trans_mm']:9.1f} / {m['end_error_rot_deg']:5.2f} "
                f"{m['fitted_point_noise_m']:6.2f}"
            )
    f = results["failure_detection_7scenes_every10th"]
    print(f"7-Scenes every 10th frame ({f['frames']} frames): failed frames {f['failed_frames']}")


if __name__ == "__main__":
    main()
