"""ScanNet's frames as its SensorData reader exports them: ``color/N.jpg`` (1296x968), ``depth/N.png``
(640x480, millimetres), ``pose/N.txt`` (camera-to-world 4x4, OpenCV axes, ``-inf`` where its
reconstruction lost the frame), ``intrinsic/intrinsic_depth.txt`` and ``intrinsic_color.txt`` (4x4)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..camera import check_intrinsic, pinhole
from ..errors import DatasetError
from .images import file_reader, image_files, natural_key, read_image
from .sequence import RGBDSequence
from .trajectories import read_matrix, read_pose_file

SCANNET_DEPTH_SCALE = 1000.0


def is_scannet(path: Path) -> bool:
    return ((path / "intrinsic" / "intrinsic_depth.txt").is_file() and (path / "pose").is_dir()
            and (path / "color").is_dir() and (path / "depth").is_dir())


def read_scannet(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                 color_intrinsic=None, image_scale: float = 1.0) -> RGBDSequence:
    """A ScanNet scene's exported frames, paired by frame number: the depth camera is the sequence's,
    the colour images keep their own camera (``intrinsic_color.txt``) and are resampled onto the depth
    grid through both intrinsics as they load; the poses are gt_poses (NaN rows, and a warning, for the
    frames ScanNet could not place)."""
    colors, depths = image_files(path / "color"), image_files(path / "depth")
    poses = sorted((path / "pose").glob("*.txt"), key=natural_key)
    if not (len(colors) == len(depths) == len(poses)) or not colors:
        raise DatasetError(f"{path}: {len(colors)} colour images, {len(depths)} depth images and {len(poses)} pose "
                           "files; ScanNet's export has one of each per frame")
    for kind, files in (("depth", depths), ("pose", poses)):
        if [f.stem for f in files] != [c.stem for c in colors]:
            raise DatasetError(f"{path}: the {kind} files are not numbered as the colour images")
    if intrinsic is None:
        intrinsic = _intrinsic(path / "intrinsic" / "intrinsic_depth.txt", read_image(depths[0]).shape)
    if color_intrinsic is None and (path / "intrinsic" / "intrinsic_color.txt").is_file():
        color_intrinsic = _intrinsic(path / "intrinsic" / "intrinsic_color.txt", read_image(colors[0]).shape)
    gt = np.stack([read_pose_file(p) for p in poses])
    lost = np.flatnonzero(np.isnan(gt).all(axis=(1, 2)))
    if lost.size:
        warnings.warn(f"{path}: {lost.size} of {len(gt)} frames have no valid pose (ScanNet's -inf: frames "
                      f"{lost[:10].tolist()}{' ...' if lost.size > 10 else ''}); their gt_poses rows are NaN")
    readers = [file_reader(c, d, depth_scale or SCANNET_DEPTH_SCALE) for c, d in zip(colors, depths)]
    stamps = np.array([float(c.stem) if c.stem.isdigit() else k for k, c in enumerate(colors)])
    return RGBDSequence(readers, intrinsic, stamps, gt, depth_trunc, color_intrinsic, path.name, image_scale)


def _intrinsic(file: Path, image_shape: tuple):
    """The pinhole camera of a ScanNet intrinsic file (a 4x4 whose top-left 3x3 is K) for images of
    `image_shape` (H, W, ...)."""
    K = read_matrix(file, (4, 4))
    return check_intrinsic(pinhole(image_shape[1], image_shape[0], K[0, 0], K[1, 1], K[0, 2], K[1, 2]), str(file))
