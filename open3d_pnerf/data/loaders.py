"""Readers for RGB-D dataset folders: TUM RGB-D, 7-Scenes, Open3D/Redwood.

`load_sequence(path)` detects the layout; each reader returns an :class:`RGBDSequence`
whose frames load lazily from the files.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation, Slerp

from .._files import atomic_write
from ..errors import DatasetError, InputError
from .sequence import RGBDSequence, check_first_frame, check_intrinsic, check_poses, file_reader

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


def pinhole(width: int, height: int, fx: float, fy: float, cx: float, cy: float):
    """Shorthand for ``o3d.camera.PinholeCameraIntrinsic``."""
    return o3d.camera.PinholeCameraIntrinsic(int(width), int(height), fx, fy, cx, cy)


def load_sequence(
    path,
    intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None,
    depth_scale: float | None = None,
    depth_trunc: float = 0.0,
    stride: int = 1,
    max_frames: int | None = None,
    image_scale: float = 1.0,
    color_intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None,
) -> RGBDSequence:
    """Read an RGB-D dataset folder, detecting its layout.

    Layouts: TUM RGB-D (``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``; depth
    scale 5000), 7-Scenes (``frame-XXXXXX.{color.png|color.jpg,depth.png,pose.txt}``,
    ``camera-intrinsics.txt``; depth scale 1000), Open3D/Redwood (``color|rgb|image/`` and
    ``depth/``, optional intrinsic ``*.json`` and ``*.log`` trajectory; depth scale 1000),
    and LLFF-style image folders (``poses_bounds.npy``, ``images_N/``, COLMAP ``sparse/0/``),
    which give an image-only :class:`~open3d_pnerf.data.llff.ImageSequence` with SfM poses
    and sparse points (see :func:`~open3d_pnerf.data.llff.read_llff`; the smallest images).

    intrinsic / color_intrinsic / depth_scale override what the folder says. depth_trunc
    (m, 0 = none) drops farther depth. stride keeps every stride-th frame, max_frames caps
    the count after striding. image_scale in (0, 1] resizes frames on load.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path must be a folder path (str or pathlib.Path), got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset folder not found: {path}")
    if not path.is_dir():
        raise DatasetError(f"dataset path must be a folder, got a file: {path}")
    if not isinstance(stride, int) or stride < 1:
        raise InputError(f"stride must be an integer >= 1, got {stride!r}")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"max_frames must be >= 1 or None, got {max_frames!r}")
    if depth_scale is not None and not depth_scale > 0:
        raise InputError(f"depth_scale must be > 0 (raw units per metre), got {depth_scale!r}")
    if intrinsic is not None:
        check_intrinsic(intrinsic)

    if (path / "poses_bounds.npy").is_file():
        from .llff import read_llff  # llff builds on this module's helpers

        given = {"intrinsic": intrinsic, "depth_scale": depth_scale, "color_intrinsic": color_intrinsic,
                 "depth_trunc": depth_trunc or None}
        unused = [k for k, v in given.items() if v is not None]
        if unused:
            raise InputError(f"{path} is an LLFF image folder (no depth, camera from poses_bounds.npy): "
                             f"{', '.join(unused)} do not apply")
        seq = read_llff(path, image_scale=image_scale)
        return seq.select(np.arange(0, len(seq), stride)[:max_frames])
    if (path / "rgb.txt").is_file() and (path / "depth.txt").is_file():
        readers, ts, poses, intr, cintr, name = _tum(path, intrinsic, depth_scale)
    elif list(path.glob("frame-*.depth.png")):
        readers, ts, poses, intr, cintr, name = _seven_scenes(path, intrinsic, depth_scale)
    elif (path / "depth").is_dir():
        readers, ts, poses, intr, cintr, name = _redwood(path, intrinsic, depth_scale)
    else:
        raise DatasetError(
            f"{path}: not a known layout. Expected TUM (rgb.txt + depth.txt), 7-Scenes "
            "(frame-XXXXXX.color.png/.depth.png), Open3D/Redwood (color/ + depth/) or LLFF "
            "(poses_bounds.npy + images_N/) folders"
        )
    keep = np.arange(0, len(readers), stride)[:max_frames]
    seq = RGBDSequence(
        [readers[i] for i in keep],
        intr,
        ts[keep],
        None if poses is None else poses[keep],
        depth_trunc,
        color_intrinsic or cintr,
        name,
        image_scale,
    )
    check_first_frame(seq)
    return seq


# -- TUM RGB-D ------------------------------------------------------------------------------
def _read_list(path: Path) -> list[list[str]]:
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
    rows = _read_list(path)
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


def _tum(path: Path, intrinsic, depth_scale):
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
    stamps = np.array([rgb_t[i] for i, _ in pairs])
    poses = None
    gt = path / "groundtruth.txt"
    if gt.is_file():
        poses = _interpolate_tum_groundtruth(gt, stamps)
    if intrinsic is None:
        known = [k for k in TUM_INTRINSICS if k in path.name]
        params = TUM_INTRINSICS[known[0]] if known else PRIMESENSE_DEFAULT
        if not known:
            warnings.warn(f"{path}: unknown TUM camera, using the default 525/319.5/239.5 intrinsic")
        intrinsic = pinhole(640, 480, *params)
    return readers, stamps, poses, intrinsic, None, path.name


def _interpolate_tum_groundtruth(path: Path, stamps: np.ndarray) -> np.ndarray | None:
    try:
        rows = np.array([[float(x) for x in r] for r in _read_list(path)])
    except ValueError as exc:
        raise DatasetError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != 8:
        raise DatasetError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines")
    if not np.isfinite(rows).all() or (np.linalg.norm(rows[:, 4:8], axis=1) < 1e-6).any():
        raise DatasetError(f"{path}: NaN/inf values or a zero quaternion (qx qy qz qw)")
    t = rows[:, 0]
    if (np.diff(t) <= 0).any():
        raise DatasetError(f"{path}: timestamps must increase from line to line")
    inside = (stamps >= t[0]) & (stamps <= t[-1])
    if not inside.all():
        warnings.warn(f"{path}: ground truth does not cover every frame; gt_poses left out")
        return None
    rot = Slerp(t, Rotation.from_quat(rows[:, 4:8]))(stamps)
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3] = rot.as_matrix()
    for k in range(3):
        poses[:, k, 3] = np.interp(stamps, t, rows[:, 1 + k])
    return poses


# -- 7-Scenes -------------------------------------------------------------------------------
def _seven_scenes(path: Path, intrinsic, depth_scale):
    depth_files = sorted(path.glob("frame-*.depth.png"))
    readers, poses = [], []
    scale = depth_scale or 1000.0
    for d in depth_files:
        stem = d.name[: -len(".depth.png")]
        color = next((c for c in (path / f"{stem}.color.png", path / f"{stem}.color.jpg") if c.is_file()), None)
        if color is None:
            raise DatasetError(f"{path}: {stem}.color.png/.jpg missing for {d.name}")
        readers.append(file_reader(color, d, scale, invalid_raw=65535))  # 7-Scenes' invalid-depth mark
        pose_file = path / f"{stem}.pose.txt"
        poses.append(_read_pose(pose_file) if pose_file.is_file() else None)
    gt = np.stack(poses) if all(p is not None for p in poses) else None
    intr_file = path / "camera-intrinsics.txt"
    if intrinsic is None:
        if intr_file.is_file():
            k = _read_matrix(intr_file, (3, 3))
            intrinsic = check_intrinsic(pinhole(640, 480, k[0, 0], k[1, 1], k[0, 2], k[1, 2]), str(intr_file))
        else:
            intrinsic = pinhole(640, 480, 585.0, 585.0, 320.0, 240.0)
    # 7-Scenes colour is not registered to depth: measured colour = 0.905 x depth image,
    # shifted -7 px in x (shared/data/7scenes_redkitchen/SOURCE.md).
    fx, fy = intrinsic.get_focal_length()
    cx, cy = intrinsic.get_principal_point()
    color_intr = pinhole(intrinsic.width, intrinsic.height, fx * 0.905, fy * 0.905, cx - 7.0, cy)
    stamps = np.array([float(re.sub(r"\D", "", d.name) or i) for i, d in enumerate(depth_files)])
    return readers, stamps, gt, intrinsic, color_intr, path.name


def _read_pose(path: Path) -> np.ndarray:
    return check_poses(_read_matrix(path, (4, 4))[None], 1, str(path))[0]


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a {shape[0]}x{shape[1]} matrix of numbers ({exc})") from None
    if m.shape != shape:
        raise DatasetError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got shape {m.shape}")
    return m


# -- Open3D / Redwood reconstruction-system folders ----------------------------------------
IMAGE_EXT = {".png", ".jpg", ".jpeg"}


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT)


def _redwood(path: Path, intrinsic, depth_scale):
    color_dir = next((path / n for n in ("color", "rgb", "image") if (path / n).is_dir()), None)
    if color_dir is None:
        raise DatasetError(f"{path}: has depth/ but no color/, rgb/ or image/ folder")
    colors, depths = _image_files(color_dir), _image_files(path / "depth")
    if len(colors) != len(depths) or not depths:
        raise DatasetError(
            f"{path}: {len(colors)} colour images in {color_dir.name}/ but {len(depths)} in depth/"
        )
    json_intrinsic, json_scale = _find_intrinsic_json(path, warn=intrinsic is None)
    scale = depth_scale or json_scale or 1000.0
    readers = [file_reader(c, d, scale) for c, d in zip(colors, depths)]
    intrinsic = intrinsic or json_intrinsic
    logs = sorted(path.glob("*.log"))
    poses = check_poses(read_log_trajectory(logs[0]), what=str(logs[0])) if logs else None
    if poses is not None and len(poses) != len(readers):
        warnings.warn(f"{logs[0]}: {len(poses)} poses for {len(readers)} frames; gt_poses left out")
        poses = None
    return readers, np.arange(len(readers), dtype=float), poses, intrinsic, None, path.name


def _find_intrinsic_json(path: Path, warn: bool = True):
    """(intrinsic, depth_scale or None) from the folder's Open3D intrinsic JSON."""
    for f in sorted(path.glob("*.json")):
        try:
            data = json.loads(f.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue
        if isinstance(data, dict) and "intrinsic_matrix" in data:
            expected = f"{f}: expected integer width, height, a 9-value intrinsic_matrix and depth_scale > 0 (optional)"
            try:
                k = np.asarray(data["intrinsic_matrix"], dtype=float).reshape(3, 3).T  # Open3D stores it column-major
                intr = pinhole(data["width"], data["height"], k[0, 0], k[1, 1], k[0, 2], k[1, 2])
                scale = None if data.get("depth_scale") is None else float(data["depth_scale"])
                if scale is not None and not scale > 0:
                    raise ValueError(scale)
            except (KeyError, TypeError, ValueError):
                raise DatasetError(expected) from None
            return check_intrinsic(intr, str(f)), scale
    if warn:
        warnings.warn(f"{path}: no intrinsic JSON found, using the PrimeSense default 525/319.5/239.5")
    return pinhole(640, 480, *PRIMESENSE_DEFAULT), None


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
    quats = Rotation.from_matrix(np.asarray(poses)[:, :3, :3]).as_quat()
    lines = [
        f"{t:.6f} " + " ".join(f"{v:.7f}" for v in (*p[:3, 3], *q))
        for t, p, q in zip(timestamps, poses, quats)
    ]
    text = "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n"
    atomic_write(path, lambda p: Path(p).write_text(text))


def write_sequence(sequence: RGBDSequence, path, depth_scale: float = 1000.0, progress: bool = False) -> Path:
    """Write a sequence as an Open3D/Redwood folder that :func:`load_sequence` reads back.

    Layout: ``color/NNNNNN.png`` (colour on the depth grid), ``depth/NNNNNN.png`` (uint16,
    metres * depth_scale), ``intrinsic.json`` (Open3D format plus depth_scale) and, when the
    sequence has ground truth, ``groundtruth.log``. Frames are read one at a time.
    """
    import cv2
    from tqdm.auto import tqdm

    from .sequence import check_sequence

    check_sequence(sequence, what="write_sequence(): sequence", needs_depth=True)
    path = Path(path)
    for sub in ("color", "depth"):
        (path / sub).mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(len(sequence)), desc="write frames", disable=not progress, leave=False):
        frame = sequence[i]
        depth = np.round(frame.depth * depth_scale)
        if depth.max(initial=0) > 65535:
            raise InputError(f"frame {i}: depth {frame.depth.max():.1f} m overflows 16 bits at depth_scale {depth_scale}")
        color = cv2.cvtColor(sequence.color_on_depth_grid(frame.color), cv2.COLOR_RGB2BGR)
        atomic_write(path / "color" / f"{i:06d}.png", lambda p: cv2.imwrite(p, color))
        atomic_write(path / "depth" / f"{i:06d}.png", lambda p: cv2.imwrite(p, depth.astype(np.uint16)))
    intr = sequence.intrinsic
    meta = {"width": intr.width, "height": intr.height, "depth_scale": depth_scale,
            "intrinsic_matrix": np.asarray(intr.intrinsic_matrix).T.reshape(-1).tolist()}  # column-major
    atomic_write(path / "intrinsic.json", lambda p: Path(p).write_text(json.dumps(meta, indent=1)))
    if sequence.gt_poses is not None:
        write_log_trajectory(path / "groundtruth.log", sequence.gt_poses)
    return path
