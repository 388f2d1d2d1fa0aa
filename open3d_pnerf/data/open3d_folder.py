"""Open3D reconstruction-system / Redwood folders: ``color|rgb|image/`` and ``depth/`` images,
an optional Open3D intrinsic ``*.json`` (with ``depth_scale``) and ``*.log`` trajectory."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np

from .._files import atomic_write
from ..camera import check_intrinsic, check_poses, intrinsic_matrix, pinhole
from ..errors import DatasetError, InputError
from .images import file_reader, image_files
from .sequence import RGBDSequence, check_sequence
from .trajectories import read_log_trajectory, write_log_trajectory
from .tum import PRIMESENSE_DEFAULT


def is_open3d_folder(path: Path) -> bool:
    return (path / "depth").is_dir()


def read_open3d_folder(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                       color_intrinsic=None, image_scale: float = 1.0, color_extrinsic=None) -> RGBDSequence:
    """An Open3D/Redwood folder: images paired by sorted name, depth scale from the JSON (default
    1000), the first ``*.log`` as ground truth when it has a pose per frame."""
    color_dir = next((path / n for n in ("color", "rgb", "image") if (path / n).is_dir()), None)
    if color_dir is None:
        raise DatasetError(f"{path}: has depth/ but no color/, rgb/ or image/ folder")
    colors, depths = image_files(color_dir), image_files(path / "depth")
    if len(colors) != len(depths) or not depths:
        raise DatasetError(
            f"{path}: {len(colors)} colour images in {color_dir.name}/ but {len(depths)} in depth/"
        )
    json_intrinsic, json_scale = _find_intrinsic_json(path, warn=intrinsic is None)
    scale = depth_scale or json_scale or 1000.0
    readers = [file_reader(c, d, scale) for c, d in zip(colors, depths)]
    intrinsic = intrinsic or json_intrinsic
    logs = sorted(path.glob("*.log"))
    poses = check_poses(read_log_trajectory(logs[0]), what=str(logs[0]), allow_missing=True) if logs else None
    if poses is not None and len(poses) != len(readers):
        warnings.warn(f"{logs[0]}: {len(poses)} poses for {len(readers)} frames; gt_poses left out")
        poses = None
    return RGBDSequence(readers, intrinsic, np.arange(len(readers), dtype=float), poses, depth_trunc,
                        color_intrinsic, path.name, image_scale, color_extrinsic=color_extrinsic)


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


def write_sequence(sequence: RGBDSequence, path, depth_scale: float = 1000.0, progress: bool = False) -> Path:
    """Write a sequence as an Open3D/Redwood folder that :func:`load_sequence` reads back.

    Layout: ``color/NNNNNN.png`` (colour on the depth grid), ``depth/NNNNNN.png`` (uint16,
    metres * depth_scale), ``intrinsic.json`` (Open3D format plus depth_scale) and, when the
    sequence has ground truth, ``groundtruth.log``. Frames are read one at a time.
    """
    from tqdm.auto import tqdm

    check_sequence(sequence, what="write_sequence(): sequence", needs_depth=True)
    path = Path(path)
    for sub in ("color", "depth"):
        (path / sub).mkdir(parents=True, exist_ok=True)
    for i in tqdm(range(len(sequence)), desc="write frames", disable=not progress, leave=False):
        frame = sequence[i]
        depth = np.round(frame.depth * depth_scale)
        if depth.max(initial=0) > 65535:
            raise InputError(f"frame {i}: depth {frame.depth.max():.1f} m overflows 16 bits at depth_scale {depth_scale}")
        color = cv2.cvtColor(sequence.color_on_depth_grid(frame.color, frame.depth), cv2.COLOR_RGB2BGR)
        atomic_write(path / "color" / f"{i:06d}.png", lambda p: cv2.imwrite(p, color))
        atomic_write(path / "depth" / f"{i:06d}.png", lambda p: cv2.imwrite(p, depth.astype(np.uint16)))
    intr = sequence.intrinsic
    meta = {"width": intr.width, "height": intr.height, "depth_scale": depth_scale,
            "intrinsic_matrix": intrinsic_matrix(intr).T.reshape(-1).tolist()}  # column-major
    atomic_write(path / "intrinsic.json", lambda p: Path(p).write_text(json.dumps(meta, indent=1)))
    if sequence.gt_poses is not None:
        write_log_trajectory(path / "groundtruth.log", sequence.gt_poses)
    return path
