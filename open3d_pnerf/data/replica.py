"""Replica as NICE-SLAM (and most neural RGB-D SLAM papers since) distribute it: a scene folder with
``results/frameNNNNNN.jpg`` and ``results/depthNNNNNN.png`` (depth 6553.5 units per metre),
``traj.txt`` (one row-major camera-to-world 4x4 a line, OpenCV camera axes: the renders' exact poses,
the ground truth) and the camera in ``cam_params.json`` beside the scene folders."""

from __future__ import annotations

import warnings
from pathlib import Path

from .._files import read_json_object
from ..camera import check_intrinsic, check_poses, pinhole
from ..errors import DatasetError
from .images import file_reader, image_files
from .sequence import RGBDSequence
from .trajectories import read_pose_rows

REPLICA_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}
"""The published camera of NICE-SLAM's Replica renders (its ``cam_params.json``)."""


def is_replica(path: Path) -> bool:
    return (path / "traj.txt").is_file() and (path / "results").is_dir() and any((path / "results").glob("frame*.jpg"))


def read_replica(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                 image_scale: float = 1.0) -> RGBDSequence:
    """A Replica scene folder: frames paired by their order, ``traj.txt`` as gt_poses, the camera from
    ``cam_params.json`` in the folder or the one above it (the dataset's root), else the published
    one with a warning."""
    results = path / "results"
    colors = [p for p in image_files(results) if p.name.startswith("frame")]
    depths = [p for p in image_files(results) if p.name.startswith("depth")]
    if len(colors) != len(depths):
        raise DatasetError(f"{results}: {len(colors)} frame*.jpg colour images but {len(depths)} depth*.png")
    poses = read_pose_rows(path / "traj.txt")
    if len(poses) != len(colors):
        raise DatasetError(f"{path / 'traj.txt'}: {len(poses)} poses for {len(colors)} frames in {results}")
    camera = _camera(path)
    scale = depth_scale or float(camera["scale"])
    if intrinsic is None:
        intrinsic = check_intrinsic(pinhole(camera["w"], camera["h"], camera["fx"], camera["fy"], camera["cx"],
                                            camera["cy"]), "Replica's camera")
    readers = [file_reader(c, d, scale) for c, d in zip(colors, depths)]
    return RGBDSequence(readers, intrinsic, None, check_poses(poses, what=str(path / "traj.txt")), depth_trunc,
                        name=path.name, image_scale=image_scale)


def _camera(path: Path) -> dict:
    """{w, h, fx, fy, cx, cy, scale} of ``cam_params.json`` (``{"camera": {...}}``) in the folder or its
    parent; the published camera, with a warning, when there is none."""
    for file in (path / "cam_params.json", path.parent / "cam_params.json"):
        if file.is_file():
            camera = read_json_object(file, DatasetError).get("camera")
            keys = tuple(REPLICA_CAMERA)
            if not isinstance(camera, dict) or any(not isinstance(camera.get(k), (int, float)) for k in keys):
                raise DatasetError(f"{file}: expected {{\"camera\": {{{', '.join(keys)}}}}} with numbers")
            return camera
    warnings.warn(f"{path}: no cam_params.json beside it; using Replica's published camera {REPLICA_CAMERA}")
    return REPLICA_CAMERA
