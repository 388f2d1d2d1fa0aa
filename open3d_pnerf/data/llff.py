"""LLFF-style scenes (NeRF's ``nerf_llff_data``) as image-only sequences with SfM poses and points.

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

import dataclasses
import re
import warnings
from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError, InputError
from .colmap import read_cameras_binary, read_images_binary, read_points3d_binary
from .loaders import _image_files, pinhole
from .sequence import RGBDSequence, check_intrinsic, check_poses, read_image

POSES_FILE = "poses_bounds.npy"
NEAR_SCALE = 0.75  # read_llff's default scale puts the nearest bound at 1 / 0.75 units, as NeRF's loader


@dataclasses.dataclass
class SparsePoints:
    """SfM points of an image sequence.

    xyz: (M, 3) float64 world points (scene units); error: (M,) mean reprojection error in
    pixels of the sequence's images; observed: (M, N) bool, point k is in frame i's track.
    """

    xyz: np.ndarray
    error: np.ndarray
    observed: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def track_length(self) -> np.ndarray:
        """(M,) number of the sequence's frames observing each point."""
        return self.observed.sum(1)


class ImageSequence(RGBDSequence):
    """Colour images with SfM camera poses and sparse points, and no depth images.

    A sequence like any other (lazy frames, select, rescaled), whose frames' depth is all
    zero (invalid). poses: (N, 4, 4) camera-to-world, OpenCV axes, from SfM; covariances:
    (N, 6, 6) of those poses ([rotation, translation], right perturbation; see
    :func:`sfm_pose_covariances`); points: :class:`SparsePoints` (error in pixels at the
    current image scale); bounds: (N, 2) near/far z-depth; scale: scene units per SfM unit.
    ``reconstruct()`` uses the poses instead of tracking and the points as depth targets
    (:func:`~open3d_pnerf.targets.sparse_depth_targets`).
    """

    has_depth = False

    def __init__(self, image_paths, intrinsic, poses, covariances, points: SparsePoints, bounds,
                 scale: float = 1.0, name: str = "images", image_scale: float = 1.0, timestamps=None):
        self.image_paths = [Path(p) for p in image_paths]
        n = len(self.image_paths)
        check_intrinsic(intrinsic)
        readers = [_color_reader(p, intrinsic.height, intrinsic.width) for p in self.image_paths]
        super().__init__(readers, intrinsic, timestamps, name=name, image_scale=image_scale)
        self.poses = check_poses(poses, n, f"{name}: poses")
        self.covariances = np.asarray(covariances, np.float64)
        self.bounds = np.asarray(bounds, np.float64)
        if self.covariances.shape != (n, 6, 6) or self.bounds.shape != (n, 2):
            raise InputError(f"{name}: need (N, 6, 6) covariances and (N, 2) bounds for {n} images, got "
                             f"{self.covariances.shape} and {self.bounds.shape}")
        if not (np.isfinite(self.covariances).all() and np.isfinite(self.bounds).all()):
            raise InputError(f"{name}: covariances and bounds must be finite")
        if points.observed.shape != (len(points), n):
            raise InputError(f"{name}: points.observed must be (M, {n}), got {points.observed.shape}")
        self._points = points  # error in pixels of the files' images
        self.scale = float(scale)

    @property
    def points(self) -> SparsePoints:
        """The SfM points, reprojection error in pixels at the sequence's image scale."""
        sx = self.intrinsic.width / self._base_intrinsic.width
        return dataclasses.replace(self._points, error=self._points.error * sx)

    def __repr__(self) -> str:
        h, w = self.image_size
        return f"ImageSequence({self.name!r}, {len(self)} images, {w}x{h}, {len(self._points)} SfM points)"

    def _derive(self, idx: np.ndarray, image_scale: float) -> "ImageSequence":
        points = dataclasses.replace(self._points, observed=self._points.observed[:, idx])
        return ImageSequence([self.image_paths[i] for i in idx], self._base_intrinsic, self.poses[idx],
                             self.covariances[idx], points, self.bounds[idx], self.scale, self.name, image_scale,
                             self.timestamps[idx])


def _color_reader(path: Path, height: int, width: int):
    """Reader of an image file as (colour uint8 RGB, all-zero depth)."""

    def read():
        color = cv2.cvtColor(read_image(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return color, np.zeros((height, width), np.float32)

    read.source = str(path)
    return read


def image_factors(path: Path) -> list[int]:
    """The N of the folder's ``images_N/`` subfolders, ascending."""
    found = (re.fullmatch(r"images_(\d+)", p.name) for p in Path(path).iterdir() if p.is_dir())
    return sorted(int(m.group(1)) for m in found if m and int(m.group(1)) > 0)


def read_llff(path, factor: int | None = None, scale: float | None = None, image_scale: float = 1.0) -> ImageSequence:
    """Read an LLFF scene folder as an :class:`ImageSequence` of the images of ``images_<factor>/``.

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
    poses[:, :3, 3] = mats[:, :, 3] * scale
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
    points = SparsePoints(xyz * scale, error * sx, observed)
    K = np.asarray(intrinsic.intrinsic_matrix)
    if len(points):
        covariances = sfm_pose_covariances(poses, K, points.xyz, points.error, observed)
    else:
        covariances = np.tile(np.eye(6), (len(rows), 1, 1))
    return ImageSequence(image_paths, intrinsic, poses, covariances, points, rows[:, 15:17] * scale, scale,
                         path.name, image_scale)


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


def sfm_pose_covariances(poses: np.ndarray, K: np.ndarray, xyz: np.ndarray, error: np.ndarray,
                         observed: np.ndarray, min_error: float = 0.01) -> np.ndarray:
    """(N, 6, 6) covariance of each camera pose from the SfM points it observes.

    poses: (N, 4, 4) camera-to-world; K: (3, 3); xyz: (M, 3); error: (M,) reprojection error
    (pixels of K's images, floored at `min_error`), taken as the standard deviation of each
    observation; observed: (M, N) bool. With the points held fixed, the Gauss-Newton
    information of frame i is sum_k J_k^T J_k / e_k^2, J_k (2, 6) the derivative of point k's
    projection with respect to a right perturbation [rotation, translation] of the pose (as
    the tracker's covariances); the covariance is its inverse. Holding the points fixed
    ignores their own uncertainty, so these are lower bounds. A frame seeing fewer than 3
    points, or points that do not fix its pose, gets an effectively unbounded covariance (1e6
    on its diagonal) and a warning.
    """
    poses = check_poses(poses, what="sfm_pose_covariances(): poses")
    fx, fy = K[0, 0], K[1, 1]
    var = np.maximum(np.asarray(error, np.float64), min_error) ** 2
    out = np.empty((len(poses), 6, 6))
    for i, pose in enumerate(poses):
        idx = np.flatnonzero(observed[:, i])
        q = (xyz[idx] - pose[:3, 3]) @ pose[:3, :3]  # camera frame
        front = q[:, 2] > 1e-9
        idx, q = idx[front], q[front]
        if len(idx) < 3:
            warnings.warn(f"frame {i} observes {len(idx)} SfM point(s): its pose covariance is unbounded")
            out[i] = np.eye(6) * 1e6
            continue
        x, y, z = q.T
        proj = np.zeros((len(q), 2, 3))  # d(u, v) / dq
        proj[:, 0, 0], proj[:, 0, 2] = fx / z, -fx * x / z**2
        proj[:, 1, 1], proj[:, 1, 2] = fy / z, -fy * y / z**2
        dq = np.zeros((len(q), 3, 6))  # q' = exp(-xi) q ~ q + q x w - rho
        dq[:, 0, 1], dq[:, 0, 2] = -z, y
        dq[:, 1, 0], dq[:, 1, 2] = z, -x
        dq[:, 2, 0], dq[:, 2, 1] = -y, x
        dq[:, :, 3:] = -np.eye(3)
        jac = proj @ dq
        info = np.einsum("kai,kaj,k->ij", jac, jac, 1.0 / var[idx])
        if np.linalg.cond(info) > 1e12:  # e.g. coincident or collinear points
            warnings.warn(f"frame {i}: its {len(idx)} SfM points do not fix its pose (degenerate "
                          "geometry): its pose covariance is unbounded")
            out[i] = np.eye(6) * 1e6
            continue
        out[i] = np.linalg.inv(info)
    return out
