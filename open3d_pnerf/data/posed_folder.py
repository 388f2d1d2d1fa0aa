"""A plain posed RGB-D folder, the layout many capture tools and MVS datasets write: colour images in
``images/``, ``color/`` or ``rgb/``, depth images in ``depth/`` (16-bit, millimetres unless
``depth_scale`` says otherwise, or float metres), the camera in ``K.txt`` / ``intrinsics.txt`` (a 3x3 or
4x4 matrix, or the four numbers fx fy cx cy) or ``intrinsics.json`` (``fx``, ``fy``, ``cx``, ``cy``, or
Open3D's ``intrinsic_matrix``), and the capture's poses in ``poses.txt`` (a 4x4 per line, row-major,
or per 4 lines) or ``pose/`` (a 4x4 text file per frame)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..camera import check_intrinsic, check_poses, pinhole
from ..errors import DatasetError, InputError
from .images import file_reader, image_files, natural_key, read_image
from .sequence import RGBDSequence
from .sfm import SfMData
from .trajectories import read_matrix, read_pose_rows

COLOR_DIRS = ("images", "color", "rgb")
INTRINSIC_FILES = ("K.txt", "intrinsics.txt", "intrinsics.json")
POSE_CONVENTIONS = ("opencv", "opengl", "opencv-world-to-camera", "opengl-world-to-camera")
"""How a posed folder's poses are written: camera-to-world with OpenCV camera axes (x right, y down, z
forward; the default) or OpenGL's (x right, y up, z backward: nerfstudio, ARKit, Blender), or their
inverses, world-to-camera."""
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes, either way


def is_posed_folder(path: Path) -> bool:
    """Colour and depth folders with poses beside them (the camera file is checked on reading, so that a
    missing one is named)."""
    return ((path / "depth").is_dir() and any((path / d).is_dir() for d in COLOR_DIRS)
            and ((path / "poses.txt").is_file() or (path / "pose").is_dir()))


def read_posed_folder(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                      image_scale: float = 1.0, pose_convention: str | None = None) -> RGBDSequence:
    """A posed folder: colour and depth images paired by their order (natural: frame2 before frame10),
    the capture's poses in ``sequence.sfm`` (reconstruct() uses them instead of tracking), converted
    from `pose_convention` (one of POSE_CONVENTIONS; default "opencv", camera-to-world)."""
    convention = pose_convention or "opencv"
    if convention not in POSE_CONVENTIONS:
        raise InputError(f"pose_convention must be one of {POSE_CONVENTIONS}, got {pose_convention!r}")
    color_dir = next(path / d for d in COLOR_DIRS if (path / d).is_dir())
    colors, depths = image_files(color_dir), image_files(path / "depth", {".png", ".tif", ".tiff"})
    if len(colors) != len(depths) or not colors:
        raise DatasetError(f"{path}: {len(colors)} colour images in {color_dir.name}/ but {len(depths)} in depth/")
    poses = _poses(path, len(colors))
    if convention.endswith("world-to-camera"):
        poses = np.linalg.inv(poses)
    if convention.startswith("opengl"):
        poses = poses @ OPENGL_TO_OPENCV
    where = path / "poses.txt" if (path / "poses.txt").is_file() else path / "pose"
    poses = check_poses(poses, what=f"{where} (read as {convention})")
    if intrinsic is None:
        height, width = read_image(depths[0]).shape[:2]
        intrinsic = _intrinsic(path, width, height)
    readers = [file_reader(c, d, depth_scale or 1000.0) for c, d in zip(colors, depths)]
    return RGBDSequence(readers, intrinsic, None, None, depth_trunc, name=path.name, image_scale=image_scale,
                        sfm=SfMData.from_poses(poses))


def _poses(path: Path, n: int) -> np.ndarray:
    """(n, 4, 4) matrices of ``poses.txt`` or ``pose/*.txt`` (DatasetError naming it when there are not n)."""
    if (path / "poses.txt").is_file():
        poses, where = read_pose_rows(path / "poses.txt"), path / "poses.txt"
    else:
        files = sorted((path / "pose").glob("*.txt"), key=natural_key)
        poses, where = np.stack([read_matrix(f, (4, 4)) for f in files]) if files else np.zeros((0, 4, 4)), path / "pose"
    if len(poses) != n:
        raise DatasetError(f"{where}: {len(poses)} poses for {n} frames")
    return poses


def _intrinsic(path: Path, width: int, height: int):
    """The folder's camera for images of width x height: the first of INTRINSIC_FILES it has."""
    file = next((path / f for f in INTRINSIC_FILES if (path / f).is_file()), None)
    if file is None:
        raise DatasetError(f"{path}: a posed folder needs its camera in {' or '.join(INTRINSIC_FILES)} (or pass "
                           "intrinsic=)")
    if file.suffix == ".json":
        try:
            data = json.loads(file.read_text())
            if "intrinsic_matrix" in data:  # Open3D's PinholeCameraIntrinsic, column-major
                K = np.asarray(data["intrinsic_matrix"], np.float64).reshape(3, 3).T
                fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            else:
                fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError, AttributeError):
            raise DatasetError(f"{file}: expected fx, fy, cx, cy or Open3D's intrinsic_matrix") from None
    else:
        try:
            values = np.loadtxt(file, dtype=np.float64)
        except ValueError as exc:
            raise DatasetError(f"{file}: not a matrix of numbers ({exc})") from None
        if values.shape in ((3, 3), (4, 4)):
            fx, fy, cx, cy = values[0, 0], values[1, 1], values[0, 2], values[1, 2]
        elif values.shape == (4,):
            fx, fy, cx, cy = values
        else:
            raise DatasetError(f"{file}: expected a 3x3 or 4x4 matrix, or fx fy cx cy, got shape {values.shape}")
    return check_intrinsic(pinhole(width, height, fx, fy, cx, cy), str(file))
