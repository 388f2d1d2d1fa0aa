"""Trajectory files: Open3D/Redwood ``.log`` and TUM ``timestamp tx ty tz qx qy qz qw`` text."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..camera import check_poses, matrix_quaternion, pose_to_extrinsic
from ..errors import DatasetError, InputError


def read_log_trajectory(path) -> np.ndarray:
    """Read a Redwood/Open3D ``.log`` trajectory: per pose a 'i j n' line and a 4x4 matrix."""
    path = Path(path)
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    if len(rows) % 5:
        raise DatasetError(f"{path}: a .log trajectory has 5 lines per pose, got {len(rows)} lines")
    try:
        mats = [np.array(rows[i + 1 : i + 5], dtype=np.float64) for i in range(0, len(rows), 5)]
    except ValueError as exc:
        raise DatasetError(f"{path}: malformed .log trajectory ({exc})") from None
    if any(m.shape != (4, 4) for m in mats):
        raise DatasetError(f"{path}: each pose in a .log trajectory must be a 4x4 matrix")
    return np.stack(mats)


def write_log_trajectory(path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) camera-to-world poses as a Redwood/Open3D ``.log`` trajectory, atomically."""
    lines = []
    for i, pose in enumerate(np.asarray(poses)):
        lines.append(f"{i} {i} {i + 1}")
        lines += [" ".join(f"{v:.10f}" for v in row) for row in pose]
    atomic_write(path, lambda p: Path(p).write_text("\n".join(lines) + "\n"))


def write_tum_trajectory(path, poses: np.ndarray, timestamps: np.ndarray) -> None:
    """Write (N, 4, 4) camera-to-world poses as TUM 'timestamp tx ty tz qx qy qz qw' lines, atomically."""
    quats = np.roll(matrix_quaternion(np.asarray(poses)[:, :3, :3]), -1, axis=1)  # (w, x, y, z) -> (x, y, z, w)
    lines = [
        f"{t:.6f} " + " ".join(f"{v:.7f}" for v in (*p[:3, 3], *q))
        for t, p, q in zip(timestamps, poses, quats)
    ]
    text = "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n"
    atomic_write(path, lambda p: Path(p).write_text(text))


def write_open3d_trajectory(path, poses: np.ndarray, intrinsic) -> None:
    """Write (N, 4, 4) camera-to-world poses as an Open3D ``PinholeCameraTrajectory`` (world-to-camera
    extrinsics with `intrinsic`, an ``o3d.camera.PinholeCameraIntrinsic``), atomically: JSON for a
    ``.json`` path, the Redwood ``.log`` form for ``.log``; ``o3d.io.read_pinhole_camera_trajectory``
    reads both, and Open3D's reconstruction system and RGBD integration take them."""
    import open3d as o3d

    path = Path(path)
    if path.suffix not in (".json", ".log"):
        raise InputError(f"{path}: an Open3D trajectory file ends in .json or .log")
    trajectory = o3d.camera.PinholeCameraTrajectory()
    parameters = []
    for pose in check_poses(poses, what="poses"):
        p = o3d.camera.PinholeCameraParameters()
        p.intrinsic, p.extrinsic = intrinsic, pose_to_extrinsic(pose)
        parameters.append(p)
    trajectory.parameters = parameters
    atomic_write(path, lambda p: o3d.io.write_pinhole_camera_trajectory(p, trajectory))
