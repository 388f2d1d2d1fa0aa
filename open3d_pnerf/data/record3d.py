"""Record3D's "EXR + JPG" export of an iPhone or iPad capture: ``rgb/N.jpg``, ``depth/N.exr`` (the LiDAR
depth in metres, smaller than the colour images), ``metadata.json`` with the colour camera ``K``
(column-major 3x3), its size ``w``, ``h`` and the device's own tracking ``poses`` (a ``[qx, qy, qz, qw,
tx, ty, tz]`` camera-to-world per frame, ARKit's camera axes: x right, y up, z backward)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .._files import read_json_object
from ..camera import check_intrinsic, check_poses, pinhole
from ..errors import DatasetError
from .images import DEPTH_EXT, FrameReader, image_files, read_color, read_depth, resized_depth
from .sequence import RGBDSequence
from .sfm import SfMData

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes, either way


def is_record3d(path: Path) -> bool:
    return (path / "metadata.json").is_file() and (path / "rgb").is_dir() and (path / "depth").is_dir()


def read_record3d(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                  image_scale: float = 1.0) -> RGBDSequence:
    """A Record3D export: the colour camera is the sequence's, the depth brought to the colour images'
    size by the nearest pixel, the device's poses (converted to OpenCV axes) in ``sequence.sfm``, which
    reconstruct() uses instead of tracking. ARKit's principal point counts from the image's corner:
    half a pixel is taken off it (pixel centres at integers here). depth_scale: stored units per metre
    (default 1: the EXR files hold metres)."""
    file = path / "metadata.json"
    meta = read_json_object(file, DatasetError)
    try:
        K = np.asarray(meta["K"], np.float64).reshape(3, 3).T
        width, height = int(meta["w"]), int(meta["h"])
        raw = np.asarray(meta["poses"], np.float64).reshape(-1, 7)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{file}: expected K (9 numbers), w, h and poses ([qx, qy, qz, qw, tx, ty, tz] a frame)") \
            from None
    colors, depths = image_files(path / "rgb"), image_files(path / "depth", DEPTH_EXT)
    if not (len(colors) == len(depths) == len(raw)) or not colors:
        raise DatasetError(f"{path}: {len(colors)} colour images, {len(depths)} depth images and {len(raw)} poses in "
                           f"{file}; a Record3D export has one of each per frame")
    if not (np.isfinite(raw).all() and (np.linalg.norm(raw[:, :4], axis=1) > 1e-6).all()):
        raise DatasetError(f"{file}: poses with NaN/inf values or a zero quaternion")
    poses = np.tile(np.eye(4), (len(raw), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(raw[:, :4]).as_matrix()
    poses[:, :3, 3] = raw[:, 4:]
    if intrinsic is None:
        intrinsic = check_intrinsic(pinhole(width, height, K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5), str(file))
    unit = 1.0 / depth_scale if depth_scale else 1.0
    readers = [_reader(c, d, unit, (intrinsic.width, intrinsic.height)) for c, d in zip(colors, depths)]
    sfm = SfMData.from_poses(check_poses(poses @ OPENGL_TO_OPENCV, what=f"{file}: poses"))
    fps = meta.get("fps")
    stamps = np.arange(len(raw)) / float(fps) if isinstance(fps, (int, float)) and fps > 0 else None
    return RGBDSequence(readers, intrinsic, stamps, None, depth_trunc, name=path.name, image_scale=image_scale,
                        sfm=sfm)


def _reader(color: Path, depth: Path, unit: float, size: tuple[int, int]) -> FrameReader:
    def read():
        return read_color(color), resized_depth(read_depth(depth, unit), size, depth)

    read.source = f"{color}, {depth}"
    return read
