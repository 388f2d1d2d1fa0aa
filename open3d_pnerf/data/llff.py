"""LLFF-style scenes (NeRF's ``nerf_llff_data``): image-only sequences with SfM poses and points.

Layout: ``poses_bounds.npy`` (N, 17), ``images_<factor>/`` (N images, sorted by name),
optional COLMAP model ``sparse/0/{cameras.bin, images.bin, points3D.bin}``.

Each poses_bounds row is a 3x5 matrix [R | t | (H, W, f)] flattened row by row, then the
near and far depth bounds. R's columns are the camera's down, right and backward axes in
the world (LLFF's convention); H, W, f are the full-resolution image size and focal length
(pixels). The world frame is COLMAP's, so points3D.bin needs no transform. COLMAP's units
are arbitrary: :func:`read_llff` rescales them (see its `scale`).

Rows follow the images sorted by name (LLFF writes them so). Matching COLMAP image ids to
rows: with images.bin the ids map to the rank of their image name; without it (LLFF
releases often leave it out) image id k is taken to be row k - 1, i.e. COLMAP numbered the
images 1..N in name order, as its feature extractor does for a folder and as LLFF's own
``imgs2poses`` assumed when it computed the bounds from the points' tracks.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import cv2
import numpy as np

from ..camera import check_poses, intrinsic_matrix, pinhole
from ..errors import DatasetError, InputError
from .colmap import read_cameras_binary, read_images_binary, read_points3d_binary
from .images import color_only_reader, image_files, read_image
from .sequence import RGBDSequence
from .sfm import SfMData, SparsePoints, sfm_pose_covariances

POSES_FILE = "poses_bounds.npy"
NEAR_SCALE = 0.75  # read_llff's default scale puts the nearest bound at 1 / 0.75 units, as NeRF's loader


def image_factors(path: Path) -> list[int]:
    """The N of the folder's ``images_N/`` subfolders, ascending."""
    found = (re.fullmatch(r"images_(\d+)", p.name) for p in Path(path).iterdir() if p.is_dir())
    return sorted(int(m.group(1)) for m in found if m and int(m.group(1)) > 0)


def read_llff(path, factor: int | None = None, scale: float | None = None, image_scale: float = 1.0) -> RGBDSequence:
    """Read an LLFF scene folder as an image-only sequence of the images of ``images_<factor>/``.

    factor: the image folder (default: the largest N with an ``images_N/``, i.e. the smallest
    images). The focal length of poses_bounds.npy is scaled by the loaded/full image size; the
    principal point is cameras.bin's when present, else the image centre. scale: scene units
    per COLMAP unit (poses, points, bounds); default 1 / (0.75 * nearest bound) as NeRF's
    loader, which makes a room-sized scene span a few units. Pose covariances come from the
    points (:func:`sfm_pose_covariances`). Without ``sparse/0/points3D.bin`` the scene has no
    points (a warning says so) and unit covariances.
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"LLFF scene folder not found: {path}")
    poses_file = path / POSES_FILE
    if not poses_file.is_file():
        raise DatasetError(f"{path}: {POSES_FILE} not found; not an LLFF scene")
    if factor is None:
        factors = image_factors(path)
        if not factors:
            raise DatasetError(f"{path}: no images_<N>/ folder (LLFF's downscaled images) found")
        factor = factors[-1]
    if not isinstance(factor, int) or factor < 1:
        raise InputError(f"factor must be an integer >= 1 (images_<factor>/), got {factor!r}")
    try:
        rows = np.load(poses_file, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{poses_file}: not a readable .npy array ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != 17 or not np.isfinite(rows).all() or not (rows[:, 15:] > 0).all():
        raise DatasetError(f"{poses_file}: expected finite (N, 17) rows [3x5 pose|hwf, near > 0, far > 0], "
                           f"got {rows.shape}")
    if scale is None:
        scale = 1.0 / (NEAR_SCALE * rows[:, 15].min())
    if not scale > 0:
        raise InputError(f"scale must be > 0 (scene units per COLMAP unit), got {scale!r}")
    mats = rows[:, :15].reshape(-1, 3, 5)
    height_full, width_full, focal_full = mats[0, :, 4]

    image_dir = path / f"images_{factor}"
    if not image_dir.is_dir():
        raise DatasetError(f"{path}: images_{factor}/ not found for factor {factor}")
    image_paths = image_files(image_dir)
    if len(image_paths) != len(rows):
        raise DatasetError(f"{image_dir}: {len(image_paths)} images but {poses_file} has {len(rows)} poses")
    height, width = read_image(image_paths[0], cv2.IMREAD_COLOR).shape[:2]
    sx, sy = width / width_full, height / height_full
    if abs(sx * factor - 1) > 0.01 or abs(sy * factor - 1) > 0.01:
        raise DatasetError(
            f"{image_paths[0]}: {width}x{height} is not 1/{factor} of the {width_full:.0f}x{height_full:.0f} "
            f"in {poses_file}"
        )

    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    down, right, backward = mats[:, :, 0], mats[:, :, 1], mats[:, :, 2]
    poses[:, :3, :3] = np.stack([right, down, -backward], axis=2)
    poses[:, :3, 3] = mats[:, :, 3] * scale
    poses = check_poses(poses, what=str(poses_file))

    model = path / "sparse" / "0"
    cx, cy = width_full / 2, height_full / 2  # COLMAP pixels (top-left pixel centre at 0.5)
    radial = (0.0, 0.0)
    if (model / "cameras.bin").is_file():
        cameras = read_cameras_binary(model / "cameras.bin")
        if len(cameras) != 1:
            raise DatasetError(f"{model / 'cameras.bin'}: expected one camera, got {len(cameras)}")
        camera = next(iter(cameras.values()))
        if (camera.width, camera.height) != (round(width_full), round(height_full)):
            raise DatasetError(
                f"{model / 'cameras.bin'}: the camera is {camera.width}x{camera.height} but {poses_file} says "
                f"{width_full:.0f}x{height_full:.0f}"
            )
        cx, cy = camera.principal_point
        radial = camera.radial_distortion
    intrinsic = pinhole(width, height, focal_full * sx, focal_full * sy, cx * sx - 0.5, cy * sy - 0.5)
    found = _sparse_points(model, image_paths, len(rows))
    points = SparsePoints(found.xyz * scale, found.error * sx, found.observed)
    K = intrinsic_matrix(intrinsic)
    if len(points):
        covariances = sfm_pose_covariances(poses, K, points.xyz, points.error, points.observed)
    else:
        covariances = np.tile(np.eye(6), (len(rows), 1, 1))
    sfm = SfMData(poses, covariances, points, rows[:, 15:17] * scale, scale, radial)
    readers = [color_only_reader(p, intrinsic.height, intrinsic.width) for p in image_paths]
    return RGBDSequence(readers, intrinsic, name=path.name, image_scale=image_scale, has_depth=False, sfm=sfm)


def _sparse_points(model: Path, image_paths: list[Path], n: int) -> SparsePoints:
    """The points of points3D.bin (error in full-resolution pixels, COLMAP units) seen by the n images."""
    points_file = model / "points3D.bin"
    if not points_file.is_file():
        warnings.warn(f"{points_file} not found: the scene has no sparse points")
        return SparsePoints.empty(n)
    points = read_points3d_binary(points_file)
    if (model / "images.bin").is_file():
        images = read_images_binary(model / "images.bin")
        names = sorted(im.name for im in images.values())
        if len(names) != n:
            raise DatasetError(f"{model / 'images.bin'}: {len(names)} images but {n} in {image_paths[0].parent}")
        image_rows = {im.id: names.index(im.name) for im in images.values()}
    else:
        image_rows = {k + 1: k for k in range(n)}
    try:
        observed = points.observed(image_rows, n)
    except InputError as exc:
        raise DatasetError(f"{points_file}: {exc}") from None
    return SparsePoints(points.xyz, points.error, observed)


def is_llff(path: Path) -> bool:
    return (path / POSES_FILE).is_file()
