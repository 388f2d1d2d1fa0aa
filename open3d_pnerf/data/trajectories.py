"""Trajectory files: Open3D/Redwood ``.log``, TUM ``timestamp tx ty tz qx qy qz qw`` text, a matrix per
line (Replica, posed folders) and a matrix per file (7-Scenes, ScanNet)."""

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


def read_pose_file(path: Path) -> np.ndarray:
    """The 4x4 camera-to-world pose of a frame's pose file (7-Scenes, ScanNet); NaN for a missing file
    or one with inf/NaN entries (7-Scenes and ScanNet mark frames where their tracking was lost so)."""
    if not path.is_file():
        return np.full((4, 4), np.nan)
    pose = read_matrix(path, (4, 4))
    if not np.isfinite(pose).all():
        return np.full((4, 4), np.nan)
    return check_poses(pose[None], 1, str(path))[0]


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A whitespace-separated text matrix of the given shape (DatasetError naming the file)."""
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a {shape[0]}x{shape[1]} matrix of numbers ({exc})") from None
    if m.shape != shape:
        raise DatasetError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got shape {m.shape}")
    return m


def read_pose_rows(path: Path) -> np.ndarray:
    """(N, 4, 4) matrices of a text file with one per line (16 numbers row-major, or 12: the top 3x4) or
    one per 4 lines (4 numbers each); the bottom row checked to be [0, 0, 0, 1], nothing else about
    rigidity (the caller checks the poses it builds); DatasetError naming the file otherwise."""
    path = Path(path)
    try:
        rows = [[float(x) for x in line.split()] for line in path.read_text().splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DatasetError(f"{path}: not a text file of numbers ({exc})") from None
    widths = {len(r) for r in rows}
    if not rows or len(widths) != 1 or widths.pop() not in (4, 12, 16) or (len(rows[0]) == 4 and len(rows) % 4):
        raise DatasetError(f"{path}: expected a pose a line (16 numbers, a row-major 4x4, or 12, its top 3x4) or "
                           "a pose every 4 lines of 4 numbers")
    values = np.asarray(rows, np.float64)
    if values.shape[1] == 12:
        values = np.hstack([values, np.tile([0.0, 0, 0, 1], (len(values), 1))])
    matrices = values.reshape(-1, 4, 4)
    bad = np.flatnonzero(np.abs(matrices[:, 3] - [0, 0, 0, 1]).max(1) > 1e-9)
    if bad.size:
        raise DatasetError(f"{path}: pose {int(bad[0])} does not end with the row 0 0 0 1 (not a 4x4 rigid transform)")
    return matrices
