"""TUM RGB-D folders: ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``; depth scale 5000."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..camera import pinhole, quaternion_matrix, rotation_matrix, rotation_vector
from ..errors import DatasetError
from .images import file_reader
from .sequence import RGBDSequence

# TUM calibration of the (registered) colour camera, per Kinect. Lens distortion is ignored:
# undistorting the fr1 colour with TUM's published coefficients made colour agree worse across
# views of the shared fr1/xyz frames (depth warped by the mocap poses), so the depth is taken
# to be registered to an undistorted colour image already.
TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
PRIMESENSE_DEFAULT = (525.0, 525.0, 319.5, 239.5)
TUM_MAX_DT = 0.02  # seconds, as TUM's associate.py


def is_tum(path: Path) -> bool:
    return (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()


def read_tum(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
             color_intrinsic=None, image_scale: float = 1.0, color_extrinsic=None,
             gt_time_offset: float = 0.0) -> RGBDSequence:
    """A TUM RGB-D folder: colour and depth associated one to one within TUM_MAX_DT, the
    intrinsic by the folder's Kinect name, ground truth slerped at the depth timestamps.

    The ground truth is taken at the depth image's time, not the colour's: the depth places the
    frame's geometry (tracking registers it, the depth targets fuse it), and TUM's colour and depth
    are up to 20 ms apart (about 6 mm at fr1/xyz's speed; with the GT at the colour time, tracked
    consecutive-frame translations disagreed with it by 5.6 mm RMS along the optical axis, at the
    depth time by 0.8 mm). ``timestamps`` are the depth's too, so that a trajectory written with
    them (:func:`~open3d_pnerf.write_tum_trajectory`) reads back as the same poses.

    gt_time_offset (s) is added to the depth timestamps where the ground truth is read, as the
    ``--offset`` of TUM's evaluation tools, for a motion capture whose clock disagrees with the
    camera's (fr1/xyz's rotations agree with tracked ones best about 25 ms early:
    benchmarks/results/tracking_tuning.md)."""
    rgb_t, rgb_f = _timestamped_files(path / "rgb.txt")
    dep_t, dep_f = _timestamped_files(path / "depth.txt")
    pairs = associate(rgb_t, dep_t, TUM_MAX_DT)
    if not pairs:
        raise DatasetError(
            f"{path}: no timestamps of rgb.txt and depth.txt within {TUM_MAX_DT} s of each other; "
            "cannot associate colour with depth"
        )
    missing = [str(f) for i, j in pairs for f in (rgb_f[i], dep_f[j]) if not f.is_file()]
    if missing:
        raise DatasetError(
            f"{path}: {len(missing)} image file(s) listed in rgb.txt/depth.txt do not exist: {missing[:3]}"
        )
    scale = depth_scale or 5000.0
    readers = [file_reader(rgb_f[i], dep_f[j], scale) for i, j in pairs]
    stamps = np.array([dep_t[j] for _, j in pairs])
    poses = None
    gt = path / "groundtruth.txt"
    if gt.is_file():
        poses = interpolate_groundtruth(gt, stamps + gt_time_offset)
    if intrinsic is None:
        known = [k for k in TUM_INTRINSICS if k in path.name]
        params = TUM_INTRINSICS[known[0]] if known else PRIMESENSE_DEFAULT
        if not known:
            warnings.warn(f"{path}: unknown TUM camera, using the default 525/319.5/239.5 intrinsic")
        intrinsic = pinhole(640, 480, *params)
    return RGBDSequence(readers, intrinsic, stamps, poses, depth_trunc, color_intrinsic, path.name, image_scale,
                        color_extrinsic=color_extrinsic)


def read_list(path: Path) -> list[list[str]]:
    """The whitespace-split lines of a TUM text file, without comments and blank lines."""
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        rows.append(line.split())
    if not rows:
        raise DatasetError(f"{path} lists no entries")
    return rows


def _timestamped_files(path: Path) -> tuple[np.ndarray, list[Path]]:
    rows = read_list(path)
    try:
        if any(len(r) < 2 for r in rows):
            raise ValueError("a line has no filename")
        stamps = np.array([float(r[0]) for r in rows])
    except ValueError as exc:
        raise DatasetError(f"{path}: expected 'timestamp filename' lines ({exc})") from None
    return stamps, [path.parent / r[1] for r in rows]


def associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """One-to-one nearest-timestamp matches (i, j) with |a_i - b_j| < max_dt, as TUM's tool."""
    diff = np.abs(a[:, None] - b[None, :])
    cand = np.argwhere(diff < max_dt)
    order = np.argsort(diff[cand[:, 0], cand[:, 1]], kind="stable")
    used_a, used_b, pairs = set(), set(), []
    for i, j in cand[order]:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((int(i), int(j)))
    return sorted(pairs)


def interpolate_groundtruth(path: Path, stamps: np.ndarray) -> np.ndarray:
    """(N, 4, 4) ground-truth poses at the frames' timestamps, interpolated between the lines
    around each frame; a frame up to TUM_MAX_DT (TUM's associate.py tolerance) before the first
    line or after the last one gets that line's pose; frames farther out get NaN rows, and a
    warning says how many."""
    try:
        rows = np.array([[float(x) for x in r] for r in read_list(path)])
    except ValueError as exc:
        raise DatasetError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != 8:
        raise DatasetError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines")
    if not np.isfinite(rows).all() or (np.linalg.norm(rows[:, 4:8], axis=1) < 1e-6).any():
        raise DatasetError(f"{path}: NaN/inf values or a zero quaternion (qx qy qz qw)")
    t = rows[:, 0]
    if (np.diff(t) <= 0).any():
        raise DatasetError(f"{path}: timestamps must increase from line to line")
    covered = (stamps >= t[0] - TUM_MAX_DT) & (stamps <= t[-1] + TUM_MAX_DT)
    at = np.clip(stamps, t[0], t[-1])
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    rotations = quaternion_matrix(np.roll(rows[:, 4:8], 1, axis=1))  # (x, y, z, w) -> (w, x, y, z)
    if len(t) == 1:
        poses[:, :3, :3] = rotations[0]
    else:  # slerp between the lines a, b around each frame: R_a exp(s log(R_a^T R_b))
        b = np.clip(np.searchsorted(t, at, side="right"), 1, len(t) - 1)
        a = b - 1
        s = (at - t[a]) / (t[b] - t[a])
        step = rotation_vector(rotations[a].transpose(0, 2, 1) @ rotations[b])
        poses[:, :3, :3] = rotations[a] @ rotation_matrix(s[:, None] * step)
    for k in range(3):
        poses[:, k, 3] = np.interp(at, t, rows[:, 1 + k])
    poses[~covered] = np.nan
    if not covered.all():
        missing = np.flatnonzero(~covered)
        warnings.warn(f"{path}: {len(missing)} of {len(stamps)} frames lie more than {TUM_MAX_DT} s outside the "
                      f"ground truth (frames {missing[:10].tolist()}{' ...' if len(missing) > 10 else ''}); their gt_poses rows "
                      "are NaN (sequence.gt_valid)")
    return poses
