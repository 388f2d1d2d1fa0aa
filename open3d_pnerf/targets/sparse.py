"""Sparse depth targets from structure from motion (image-only sequences such as LLFF).

Each SfM point observed by a frame gives the pixel it projects to a Gaussian along that
pixel's ray: the point's uncertainty ellipsoid (reprojection error, triangulation angle, the
camera's pose covariance) restricted to the ray (:func:`gaussian_along_ray`), in the same
:class:`~open3d_pnerf.targets.DepthTargets` as dense RGB-D targets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import camera_rays, check_covariances, check_poses, nearest_per_pixel, project
from ..errors import InputError
from .storage import DepthTargets, allocate


def gaussian_along_ray(origin, direction, mean, cov):
    """The Gaussian N(mean, cov) restricted to the ray origin + t direction: (t*, var) in t.

    Along the line, (o + t d - p)^T S^-1 (o + t d - p) is quadratic in t with curvature
    a = d^T S^-1 d and minimum at t* = d^T S^-1 (p - o) / a, so the density on the ray is
    proportional to N(t; t*, 1/a). With a unit d, t* and sqrt(var) are distances along the
    ray in the units of `mean`. origin, direction, mean: (..., 3); cov: (..., 3, 3) positive
    definite; returns t* and var, each (...).
    """
    origin, direction, mean = (np.asarray(a, np.float64) for a in (origin, direction, mean))
    solved = np.linalg.solve(np.asarray(cov, np.float64), np.stack([direction, mean - origin], -1))
    a = (direction * solved[..., 0]).sum(-1)
    return (direction * solved[..., 1]).sum(-1) / a, 1.0 / a


def sparse_depth_targets(
    poses: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    xyz: np.ndarray,
    error: np.ndarray,
    observed: np.ndarray,
    *,
    covariances: np.ndarray | None = None,
    radial: tuple[float, float] = (0.0, 0.0),
    min_angle_deg: float = 1.0,
    min_error: float = 0.01,
    storage_dir: str | Path | None = None,
) -> DepthTargets:
    """Per-pixel Gaussian depth targets (z-depth mean and sigma) from sparse SfM points.

    poses: (N, 4, 4) camera-to-world; K: (3, 3); image_size: (H, W); xyz: (M, 3) world points;
    error: (M,) their reprojection error in pixels of K's images, floored at `min_error` so that
    an exact fit keeps a nonzero sigma; observed: (M, N) bool, point k is in frame i's track;
    covariances: (N, 6, 6) pose covariances ([rotation, translation], right perturbation),
    zeros if None; radial: the images' (k1, k2) (:class:`~open3d_pnerf.data.sfm.SfMData`).
    Units of length are those of the poses and points.

    Each point k observed in frame i, in front of it and seen inside the image, gives a target
    on the ray through the exact (distorted, sub-pixel) spot (u, v) where the image shows it,
    stored at the pixel that spot rounds to (the nearest point where several do), with
    offset = (u, v) - that pixel's centre:
      * point covariance, from its track: lateral sigma s_lat = e_k z / fx (e_k pixels at
        z-depth z) across the viewing direction v = (p - c_i) / |p - c_i|, depth sigma
        s_dep = s_lat / sin(theta) along v, theta the angle between v and another observing
        camera's direction to p with the largest sine (two rays at angle theta turn a lateral
        error into one 1/sin(theta) larger along each other): S_p = s_lat^2 (I - v v^T) + s_dep^2 v v^T;
      * pose: S = S_p + R_i S_i[3:, 3:] R_i^T, the camera centre's world covariance (rotation
        about the centre does not move points along the camera's own rays);
      * the unit ray d through (u, v) meets N(p, S) in the Gaussian (t*, var) of
        :func:`gaussian_along_ray`; z-depth mean = t* d_z, sigma = sqrt(var) d_z with d_z the
        ray's camera-frame z (z = t d_z);
      * weight w_k = exp(-(e_k / mean(e))^2) (DS-NeRF's) weights the target's loss terms.
    Points seen under theta < min_angle_deg give no target. support: the point's track
    length (capped at 255); filled: False (the frame observes the point itself). storage_dir:
    as :func:`depth_targets`.
    """
    poses = check_poses(poses, what="sparse_depth_targets(): poses")
    n = len(poses)
    covs = check_covariances(covariances, n)
    K, (h, w) = np.asarray(K, np.float64), (int(s) for s in image_size)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0) or h <= 0 or w <= 0:
        raise InputError(f"K must be a (3, 3) intrinsic with positive focal lengths and image_size (H, W) positive, "
                         f"got K of shape {K.shape} and image_size {tuple(image_size)}")
    xyz, error, observed = np.asarray(xyz, np.float64), np.asarray(error, np.float64), np.asarray(observed)
    m = len(xyz)
    if xyz.shape != (m, 3) or error.shape != (m,) or not (np.isfinite(xyz).all() and np.isfinite(error).all()):
        raise InputError(f"xyz must be finite (M, 3) and error finite (M,), got {xyz.shape} and {error.shape}")
    if observed.shape != (m, n) or observed.dtype != bool:
        raise InputError(f"observed must be a bool (M, N) = ({m}, {n}) array, got {observed.dtype} {observed.shape}")
    if (error < 0).any() or min_error <= 0 or not 0 <= min_angle_deg < 90:
        raise InputError("need error >= 0, min_error > 0 and 0 <= min_angle_deg < 90")
    if len(radial) != 2 or not np.isfinite(radial).all():
        raise InputError(f"radial must be finite (k1, k2), got {radial!r}")

    error = np.maximum(error, min_error)
    weight = np.exp(-((error / (error.mean() if m else 1.0)) ** 2))
    track = np.minimum(observed.sum(1), 255).astype(np.uint8)
    centres = poses[:, :3, 3]
    out = allocate(n, h, w, storage_dir, sparse=True)
    for i in range(n):
        idx = np.flatnonzero(observed[:, i])
        rot = poses[i, :3, :3]
        q = (xyz[idx] - centres[i]) @ rot  # camera frame
        idx, q = idx[q[:, 2] > 0], q[q[:, 2] > 0]
        u, v = project(K, q, radial)
        col, row = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        idx, q, u, v, col, row = idx[inside], q[inside], u[inside], v[inside], col[inside], row[inside]
        # viewing directions of every camera to these points, (M_i, N, 3), and theta
        view = xyz[idx, None] - centres[None]
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        vdir = view[:, i]
        sin_theta = np.where(observed[idx], np.linalg.norm(np.cross(vdir[:, None], view), axis=-1), 0).max(1)
        keep = (sin_theta > 0) & (sin_theta >= np.sin(np.radians(min_angle_deg)))
        idx, q, vdir, sin_theta = idx[keep], q[keep], vdir[keep], sin_theta[keep]
        u, v, col, row = u[keep], v[keep], col[keep], row[keep]
        s_lat = error[idx] * q[:, 2] / K[0, 0]
        s_dep = s_lat / sin_theta
        vv = vdir[:, :, None] * vdir[:, None, :]
        cov = s_lat[:, None, None] ** 2 * (np.eye(3) - vv) + s_dep[:, None, None] ** 2 * vv
        cov += rot @ covs[i, 3:, 3:] @ rot.T
        d_cam = camera_rays(K, u, v)
        d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
        t, var = gaussian_along_ray(centres[i], d_cam @ rot.T, xyz[idx], cov)
        z, sigma = t * d_cam[:, 2], np.sqrt(var) * d_cam[:, 2]
        pix = row * w + col
        best = nearest_per_pixel(pix, z)
        out.mean[i].flat[pix[best]] = z[best]
        out.sigma[i].flat[pix[best]] = sigma[best]
        out.valid[i].flat[pix[best]] = True
        out.support[i].flat[pix[best]] = track[idx[best]]
        out.weight[i].flat[pix[best]] = weight[idx[best]]
        out.offset[i].reshape(-1, 2)[pix[best]] = np.stack([u - col, v - row], -1)[best]
    return out
