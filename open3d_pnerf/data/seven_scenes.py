"""7-Scenes folders: ``frame-XXXXXX.{color.png|color.jpg, depth.png, pose.txt}`` and
``camera-intrinsics.txt``; depth scale 1000, 65535 marks missing depth."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ..camera import check_intrinsic, pinhole
from ..errors import DatasetError
from .images import file_reader
from .sequence import RGBDSequence
from .trajectories import read_matrix, read_pose_file


# The colour camera of 7-Scenes' Kinect against its depth camera, registered at the plane at
# infinity (colour edges matched to depth edges): focal length ratio and principal-point shift (px
# at 640x480). The rig fitted with a baseline by benchmarks/bench_color_registration.py (shift
# (3, -1) px, 3.5 cm to the side: load_sequence's color_intrinsic= and color_extrinsic=) aligns the
# edges better, but with it tracking 7-Scenes every 10th frame failed tests/test_tracking.py's
# frame-87 case, so it is not the default yet.
COLOR_FOCAL_RATIO = 0.905
COLOR_CENTRE_SHIFT = (-7.0, 0.0)


def is_seven_scenes(path: Path) -> bool:
    return any(path.glob("frame-*.depth.png"))


def read_seven_scenes(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                      color_intrinsic=None, image_scale: float = 1.0, color_extrinsic=None) -> RGBDSequence:
    """A 7-Scenes folder; its colour camera is not registered to the depth camera: unless
    color_intrinsic or color_extrinsic is given, the Kinect's (the constants above)."""
    depth_files = sorted(path.glob("frame-*.depth.png"))
    readers, poses = [], []
    scale = depth_scale or 1000.0
    for d in depth_files:
        stem = d.name[: -len(".depth.png")]
        color = next((c for c in (path / f"{stem}.color.png", path / f"{stem}.color.jpg") if c.is_file()), None)
        if color is None:
            raise DatasetError(f"{path}: {stem}.color.png/.jpg missing for {d.name}")
        readers.append(file_reader(color, d, scale, invalid_raw=65535))  # 7-Scenes' invalid-depth mark
        poses.append(read_pose_file(path / f"{stem}.pose.txt"))
    gt = np.stack(poses) if any(np.isfinite(p).all() for p in poses) else None
    if gt is not None and np.isnan(gt).any():
        missing = np.flatnonzero(np.isnan(gt).all(axis=(1, 2)))
        warnings.warn(f"{path}: {len(missing)} of {len(gt)} frames have no usable frame-*.pose.txt (frames "
                      f"{missing[:10].tolist()}{' ...' if len(missing) > 10 else ''}); their gt_poses rows are NaN "
                      "(sequence.gt_valid)")
    intr_file = path / "camera-intrinsics.txt"
    if intrinsic is None:
        if intr_file.is_file():
            k = read_matrix(intr_file, (3, 3))
            intrinsic = check_intrinsic(pinhole(640, 480, k[0, 0], k[1, 1], k[0, 2], k[1, 2]), str(intr_file))
        else:
            intrinsic = pinhole(640, 480, 585.0, 585.0, 320.0, 240.0)
    if color_intrinsic is None and color_extrinsic is None:
        fx, fy = intrinsic.get_focal_length()
        cx, cy = intrinsic.get_principal_point()
        color_intrinsic = pinhole(intrinsic.width, intrinsic.height, fx * COLOR_FOCAL_RATIO, fy * COLOR_FOCAL_RATIO,
                                  cx + COLOR_CENTRE_SHIFT[0], cy + COLOR_CENTRE_SHIFT[1])
    stamps = np.array([float(re.sub(r"\D", "", d.name) or i) for i, d in enumerate(depth_files)])
    return RGBDSequence(readers, intrinsic, stamps, gt, depth_trunc, color_intrinsic, path.name, image_scale,
                        color_extrinsic=color_extrinsic)
