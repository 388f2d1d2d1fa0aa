"""Pinhole cameras in the library's conventions, implemented once.

* Poses are camera-to-world (4, 4) float64 in metres, OpenCV camera axes (x right, y down,
  z forward). Open3D's ``extrinsic`` is world-to-camera: :func:`extrinsic_to_pose` and
  :func:`pose_to_extrinsic` convert at the boundary.
* Pixel (u, v) (u column, v row) has its centre at integer coordinates.
* Depth is z-depth in metres. The camera ray of pixel (u, v) is k = K^-1 [u, v, 1] (unit
  camera-z), so a point at z-depth z lies at z k and at Euclidean distance t = z ||k||
  along the unit ray k / ||k|| (:func:`ray_norms` holds ||k||).

The functions on arrays work on NumPy arrays and on torch tensors alike (the result has the
input's type); those on intrinsics take ``o3d.camera.PinholeCameraIntrinsic``.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from .errors import InputError, PoseError


# -- intrinsics ------------------------------------------------------------------------------
def pinhole(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> o3d.camera.PinholeCameraIntrinsic:
    """Shorthand for ``o3d.camera.PinholeCameraIntrinsic`` (image size in pixels)."""
    return o3d.camera.PinholeCameraIntrinsic(int(width), int(height), fx, fy, cx, cy)


def intrinsic_matrix(intrinsic: o3d.camera.PinholeCameraIntrinsic) -> np.ndarray:
    """(3, 3) float64 K of an intrinsic."""
    return np.array(intrinsic.intrinsic_matrix, dtype=np.float64)


def check_intrinsic(intrinsic, what: str = "intrinsic") -> o3d.camera.PinholeCameraIntrinsic:
    """Return `intrinsic` if it is a PinholeCameraIntrinsic with positive size and focal lengths
    and its principal point inside the image."""
    if not isinstance(intrinsic, o3d.camera.PinholeCameraIntrinsic):
        raise InputError(
            f"{what} must be an open3d.camera.PinholeCameraIntrinsic, got {type(intrinsic).__name__}"
        )
    fx, fy = intrinsic.get_focal_length()
    cx, cy = intrinsic.get_principal_point()
    w, h = intrinsic.width, intrinsic.height
    if w <= 0 or h <= 0 or not (fx > 0 and fy > 0):
        raise InputError(f"{what} must have positive width, height and focal lengths, got {w}x{h}, fx={fx}, fy={fy}")
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise InputError(
            f"{what}: principal point ({cx}, {cy}) lies outside the {w}x{h} image; is the intrinsic "
            "for another image size?"
        )
    return intrinsic


def scale_intrinsic(intrinsic: o3d.camera.PinholeCameraIntrinsic, scale: float) -> o3d.camera.PinholeCameraIntrinsic:
    """Intrinsic of the image resized by `scale` (pixel centres stay at integer coordinates)."""
    width, height = round(intrinsic.width * scale), round(intrinsic.height * scale)
    sx, sy = width / intrinsic.width, height / intrinsic.height
    fx, fy = intrinsic.get_focal_length()
    cx, cy = intrinsic.get_principal_point()
    return o3d.camera.PinholeCameraIntrinsic(
        width, height, fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5
    )


# -- poses -----------------------------------------------------------------------------------
def check_poses(poses, n: int | None = None, what: str = "poses", allow_missing: bool = False) -> np.ndarray:
    """Return poses as (N, 4, 4) float64 after checking they are finite rigid transforms.

    allow_missing: rows that are entirely NaN mark frames without a pose (ground truth that
    does not cover every frame) and pass; partly NaN or non-rigid rows still raise PoseError."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise PoseError(f"{what} must have shape (N, 4, 4), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise PoseError(f"{what} has {arr.shape[0]} poses for {n} frames")
    at = lambda bad: f" at frames {np.flatnonzero(bad)[:10].tolist()}" if len(arr) > 1 else ""  # noqa: E731
    missing = np.isnan(arr).all(axis=(1, 2)) if allow_missing else np.zeros(len(arr), bool)
    bad = ~np.isfinite(arr).all(axis=(1, 2)) & ~missing
    if bad.any():
        raise PoseError(f"{what} contain NaN/inf{at(bad)}")
    rot = np.where(missing[:, None, None], np.eye(4), arr)[:, :3, :3]
    ortho = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bottom = np.abs(np.where(missing[:, None], [0, 0, 0, 1], arr[:, 3]) - [0, 0, 0, 1]).max(axis=1)
    bad = (ortho > 1e-3) | (np.abs(det - 1) > 1e-3) | (bottom > 1e-9)
    if bad.any():
        raise PoseError(
            f"{what} are not rigid transforms (rotation not orthonormal, det != 1 or last row "
            f"not [0,0,0,1]){at(bad)}"
        )
    return arr


def missing_poses(poses: np.ndarray) -> np.ndarray:
    """(N,) bool: the frames whose pose row is NaN (no pose known)."""
    return np.isnan(np.asarray(poses, np.float64)).all(axis=(1, 2))


def pose_to_extrinsic(pose: np.ndarray) -> np.ndarray:
    """Open3D's world-to-camera extrinsic (4, 4) of a camera-to-world pose (4, 4) (or (N, 4, 4))."""
    return np.linalg.inv(np.asarray(pose, np.float64))


def extrinsic_to_pose(extrinsic: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (4, 4) (or (N, 4, 4)) of Open3D's world-to-camera extrinsic."""
    return np.linalg.inv(np.asarray(extrinsic, np.float64))


def camera_pose(pose, what: str = "pose") -> tuple[np.ndarray, o3d.camera.PinholeCameraIntrinsic | None]:
    """(camera-to-world pose (4, 4), intrinsic or None) of a (4, 4) camera-to-world matrix or an
    ``o3d.camera.PinholeCameraParameters`` (its world-to-camera extrinsic inverted; its intrinsic
    when set)."""
    if isinstance(pose, o3d.camera.PinholeCameraParameters):
        intrinsic = pose.intrinsic if pose.intrinsic.width > 0 else None
        return check_poses(extrinsic_to_pose(pose.extrinsic)[None], 1, f"{what}.extrinsic")[0], intrinsic
    return check_poses(np.asarray(pose)[None], 1, what)[0], None


def camera_poses(poses, n: int | None = None, what: str = "poses",
                 covariances=None) -> tuple[np.ndarray, np.ndarray]:
    """(poses (N, 4, 4) camera-to-world, covariances (N, 6, 6)), checked, of an (N, 4, 4) array of
    camera-to-world poses, an ``o3d.camera.PinholeCameraTrajectory`` (world-to-camera extrinsics,
    inverted) or a :class:`~open3d_pnerf.tracking.Trajectory` (its poses and covariances).
    covariances: those of the poses when given, else a Trajectory's own, else zeros."""
    carried = None
    if isinstance(poses, o3d.camera.PinholeCameraTrajectory):
        extrinsics = np.stack([p.extrinsic for p in poses.parameters]) if poses.parameters else np.zeros((0, 4, 4))
        poses = check_poses(extrinsic_to_pose(extrinsics), n, f"{what} (a PinholeCameraTrajectory)")
    elif hasattr(poses, "poses") and hasattr(poses, "covariances"):  # a Trajectory
        poses, carried = check_poses(poses.poses, n, f"{what}.poses"), poses.covariances
    else:
        poses = check_poses(poses, n, what)
    return poses, check_covariances(carried if covariances is None else covariances, len(poses))


# -- rigid motions: scipy's rotations, twists ordered [rotation, translation] -------------------
# (scipy rather than a tensor library: the tracker converts one small rotation at a time, and
# scipy does it in microseconds)
def rotation_matrix(rotvec) -> np.ndarray:
    """(..., 3, 3) rotation matrices exp([w]x) of rotation vectors w (..., 3) (radians)."""
    w = np.asarray(rotvec, np.float64)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(*w.shape[:-1], 3, 3)


def motion(T: np.ndarray) -> tuple[float, float]:
    """(translation in m, rotation angle in degrees) of a 4x4 rigid transform."""
    cos = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.arccos(cos)))


def rotation_vector(matrix) -> np.ndarray:
    """(..., 3) rotation vectors (radians) of rotation matrices (..., 3, 3): the inverse of
    :func:`rotation_matrix`."""
    R = np.asarray(matrix, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*R.shape[:-2], 3)


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform of a small twist xi (6,) [rotation rad, translation m]: the rotation
    exact, the translation to first order (the inverse of :func:`matrix_twist`)."""
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(xi[:3])
    T[:3, 3] = xi[3:]
    return T


def matrix_twist(T: np.ndarray) -> np.ndarray:
    """(6,) twist [rotation vector rad, translation m] of a near-identity 4x4 rigid transform (the
    translation to first order; the inverse of :func:`twist_matrix`)."""
    return np.concatenate([rotation_vector(T[:3, :3]), T[:3, 3]])


def quaternion_matrix(wxyz) -> np.ndarray:
    """(..., 3, 3) rotation matrices of quaternions (..., 4) (w, x, y, z), normalised first."""
    q = np.asarray(wxyz, np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(*q.shape[:-1], 3, 3)


def matrix_quaternion(matrix) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) of rotation matrices (..., 3, 3)."""
    R = np.asarray(matrix, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()[:, [3, 0, 1, 2]].reshape(*R.shape[:-2], 4)


def adjoint(T: np.ndarray) -> np.ndarray:
    """(6, 6) adjoint of a 4x4 rigid transform for twists [rotation, translation]:
    ``T exp(xi) T^-1 = exp(adjoint(T) @ xi)``, i.e. [[R, 0], [[t]x R, R]]."""
    R, t = T[:3, :3], T[:3, 3]
    skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    ad = np.zeros((6, 6))
    ad[:3, :3] = ad[3:, 3:] = R
    ad[3:, :3] = skew @ R
    return ad


# -- pixels and rays (NumPy or torch) ----------------------------------------------------------
def _backend(a):
    """The array module of `a`: numpy, or torch for a tensor."""
    if type(a).__module__.startswith("torch"):
        import torch

        return torch
    return np


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, v), each (H, W) int: the column and row of every pixel."""
    return np.meshgrid(np.arange(width), np.arange(height))


def pixel_coordinates(flat, width: int):
    """(u, v), each like `flat`: the column and row of flat pixel indices v * width + u (NumPy or torch)."""
    return flat % width, flat // width


def camera_rays(K, u, v):
    """(..., 3) camera-frame rays K^-1 [u, v, 1] (unit z) of pixels (u, v) (...).

    K: (3, 3), or (..., 3, 3) per pixel (torch)."""
    xp = _backend(u)
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    x = (u - cx) / fx
    y = (v - cy) / fy
    return xp.stack([x, y, xp.ones_like(x)], -1)


def ray_norms(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) float32 ||K^-1 [u, v, 1]||: metres along the ray per metre of z-depth at each pixel."""
    u, v = pixel_grid(height, width)
    return np.linalg.norm(camera_rays(K, u, v), axis=-1).astype(np.float32)


def unit_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, 3) unit camera-frame ray directions of every pixel."""
    u, v = pixel_grid(height, width)
    d = camera_rays(K, u, v)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def unproject(K, u, v, z):
    """(..., 3) camera-frame points of pixels (u, v) (...) at z-depths z (...) metres."""
    return camera_rays(K, u, v) * z[..., None]


def backproject(depth: np.ndarray, K: np.ndarray, pose: np.ndarray | None = None, mask: np.ndarray | None = None):
    """Points of the masked pixels of a z-depth map (H, W) metres, and their flat pixel indices.

    mask: (H, W) bool (default: depth > 0). pose: camera-to-world (4, 4) for world points, None
    for camera-frame points. Returns (M, 3) float64 points and (M,) indices v * W + u.
    """
    flat = np.flatnonzero(depth > 0 if mask is None else mask)
    u, v = pixel_coordinates(flat, depth.shape[1])
    pts = unproject(K, u, v, depth.ravel()[flat].astype(np.float64))
    if pose is not None:
        pts = pts @ pose[:3, :3].T + pose[:3, 3]
    return pts, flat


def project(K, points, radial: tuple[float, float] = (0.0, 0.0)):
    """Pixel coordinates (u, v), each (...), of camera-frame points (..., 3) with z > 0;
    radial: (k1, k2) distortion of the normalised coordinates by 1 + k1 r^2 + k2 r^4."""
    x, y = points[..., 0] / points[..., 2], points[..., 1] / points[..., 2]
    r2 = x * x + y * y
    f = 1 + radial[0] * r2 + radial[1] * r2 * r2
    return x * f * K[0, 0] + K[0, 2], y * f * K[1, 1] + K[1, 2]


def nearest_pixels(K: np.ndarray, points: np.ndarray, height: int, width: int):
    """Flat indices v * W + u (M,) of the pixels nearest to the projections of camera-frame
    points (M, 3) with z > 0, and the (M,) mask of those inside the image."""
    u, v = project(K, points)
    u, v = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    return v * width + u, (u >= 0) & (u < width) & (v >= 0) & (v < height)


def nearest_per_pixel(pix: np.ndarray, z: np.ndarray) -> np.ndarray:
    """A z-buffer: indices of the smallest z among entries sharing a flat pixel index, sorted by pixel."""
    order = np.lexsort((z, pix))
    first = np.unique(pix[order], return_index=True)[1]
    return order[first]


def reproject_depth(depth: np.ndarray, K: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """The z-depth image (H, W) m that a camera with the same intrinsic K would see after moving by
    `transform` (4, 4: points in the original camera -> points in the moved one): every pixel's
    point moved and kept at the pixel nearest to its projection, the nearest surface where several
    land on one pixel; 0 where none lands."""
    h, w = depth.shape
    points = backproject(depth, K)[0] @ transform[:3, :3].T + transform[:3, 3]
    points = points[points[:, 2] > 1e-6]
    pix, inside = nearest_pixels(K, points, h, w)
    pix, z = pix[inside], points[inside, 2]
    keep = nearest_per_pixel(pix, z)
    out = np.zeros(h * w, depth.dtype)
    out[pix[keep]] = z[keep]
    return out.reshape(h, w)


def check_covariances(covariances, n: int, what: str = "covariances") -> np.ndarray:
    """(n, 6, 6) float64 pose covariances (zeros for None), checked finite and of that shape."""
    covs = np.zeros((n, 6, 6)) if covariances is None else np.asarray(covariances, np.float64)
    if covs.shape != (n, 6, 6) or not np.isfinite(covs).all():
        raise InputError(f"{what} must be finite with shape ({n}, 6, 6), got shape {covs.shape}")
    return covs
