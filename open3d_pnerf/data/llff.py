"""Reader of LLFF-style scenes (NeRF's ``nerf_llff_data``): images, poses, bounds, SfM points.

Layout: ``poses_bounds.npy`` (N, 17), ``images_<factor>/`` (N images, sorted by name),
optional COLMAP model ``sparse/0/{cameras.bin, images.bin, points3D.bin}``.

Each poses_bounds row is a 3x5 matrix [R | t | (H, W, f)] flattened row by row, then the
near and far depth bounds. R's columns are the camera's down, right and backward axes in
the world (LLFF's convention); H, W, f are the full-resolution image size and focal length
(pixels). The world frame is COLMAP's, so points3D.bin needs no transform. Units are those
of the COLMAP reconstruction (arbitrary scale, not metres).

Rows follow the images sorted by name (LLFF writes them so). Matching COLMAP image ids to
rows: with images.bin the ids map to the rank of their image name; without it (LLFF
releases often leave it out) image id k is taken to be row k - 1, i.e. COLMAP numbered the
images 1..N in name order, as its feature extractor does for a folder and as LLFF's own
``imgs2poses`` assumed when it computed the bounds from the points' tracks.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from ..errors import DatasetError, InputError
from .colmap import read_cameras_binary, read_images_binary, read_points3d_binary
from .loaders import _image_files, pinhole
from .sequence import check_poses, read_image

POSES_FILE = "poses_bounds.npy"


@dataclasses.dataclass
class LLFFScene:
    """An LLFF scene at one image factor; images load lazily (:meth:`image`).

    intrinsic: pinhole ``o3d.camera.PinholeCameraIntrinsic`` of the loaded images (pixel
    centres at integer coordinates, lens distortion ignored as in LLFF/NeRF). poses: (N, 4, 4)
    float64 camera-to-world, OpenCV axes (x right, y down, z forward). bounds: (N, 2) near/far
    z-depth. xyz: (M, 3) SfM points (world); point_error: (M,) their mean reprojection error in
    pixels of the loaded images; observed: (M, N) bool, point k is in image i's track.
    """

    image_paths: list[Path]
    intrinsic: o3d.camera.PinholeCameraIntrinsic
    poses: np.ndarray
    bounds: np.ndarray
    xyz: np.ndarray
    point_error: np.ndarray
    observed: np.ndarray
    name: str

    def __len__(self) -> int:
        return len(self.image_paths)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array(self.intrinsic.intrinsic_matrix, dtype=np.float64)

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the loaded images."""
        return self.intrinsic.height, self.intrinsic.width

    @property
    def track_length(self) -> np.ndarray:
        """(M,) number of images observing each point."""
        return self.observed.sum(1)

    def image(self, index: int) -> np.ndarray:
        """Image `index` as uint8 (H, W, 3) RGB."""
        return cv2.cvtColor(read_image(self.image_paths[index], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def read_llff(path, factor: int = 8) -> LLFFScene:
    """Read an LLFF scene folder with the images of ``images_<factor>/``.

    The focal length of poses_bounds.npy is scaled by the loaded/full image size; the
    principal point is cameras.bin's when present, else the image centre. Without
    ``sparse/0/points3D.bin`` the scene has no points (a warning says so).
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"LLFF scene folder not found: {path}")
    if not isinstance(factor, int) or factor < 1:
        raise InputError(f"factor must be an integer >= 1 (images_<factor>/), got {factor!r}")
    poses_file = path / POSES_FILE
    if not poses_file.is_file():
        raise DatasetError(f"{path}: {POSES_FILE} not found; not an LLFF scene")
    try:
        rows = np.load(poses_file, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{poses_file}: not a readable .npy array ({exc})") from None
    if rows.ndim != 2 or rows.shape[1] != 17 or not np.isfinite(rows).all():
        raise DatasetError(f"{poses_file}: expected finite (N, 17) rows [3x5 pose|hwf, near, far], got {rows.shape}")
    mats = rows[:, :15].reshape(-1, 3, 5)
    height_full, width_full, focal_full = mats[0, :, 4]

    image_dir = path / f"images_{factor}"
    if not image_dir.is_dir():
        raise DatasetError(f"{path}: images_{factor}/ not found for factor {factor}")
    image_paths = _image_files(image_dir)
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
    poses[:, :3, 3] = mats[:, :, 3]
    poses = check_poses(poses, what=str(poses_file))

    model = path / "sparse" / "0"
    cx, cy = width_full / 2, height_full / 2  # COLMAP pixels (top-left pixel centre at 0.5)
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
    intrinsic = pinhole(width, height, focal_full * sx, focal_full * sy, cx * sx - 0.5, cy * sy - 0.5)
    xyz, error, observed = _sparse_points(model, image_paths, len(rows))
    return LLFFScene(image_paths, intrinsic, poses, rows[:, 15:17].copy(), xyz, error * sx, observed, path.name)


def _sparse_points(model: Path, image_paths: list[Path], n: int):
    """(xyz (M, 3), error (M,) full-resolution pixels, observed (M, n)) from points3D.bin."""
    points_file = model / "points3D.bin"
    if not points_file.is_file():
        warnings.warn(f"{points_file} not found: the scene has no sparse points")
        return np.empty((0, 3)), np.empty(0), np.zeros((0, n), bool)
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
    return points.xyz, points.error, observed
