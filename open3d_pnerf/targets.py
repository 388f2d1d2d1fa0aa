"""Uncertain per-pixel depth targets: sensor noise, pose uncertainty, multi-view fusion.

For every pixel of every frame the target is a Gaussian over depth, N(mean, sigma^2), in
**z-depth metres**. The pixel's ray meets depth z at Euclidean distance t = z ||k|| with
k = K^-1 [u, v, 1], so the ray-distance target is (mean, sigma) * ||k|| (see :func:`ray_norms`).

Variance of a pixel's target, built per frame i:
  * sensor: sigma_z(z)^2 of the frame's own measurement (:class:`SensorNoise`), and after
    fusion the sensor's systematic variance at the fused depth (common to all views);
  * pose: frame i's 6x6 covariance S_i ([rotation, translation], right perturbation
    T exp(xi), camera frame) moves the ray origin; along the unit ray r the variance is
    r^T S_i[3:, 3:] r (the camera's own rotation does not move depth along its own ray).
    Expressed in z units it is multiplied by r_z^2;
  * fusion: neighbouring frames j are reprojected into frame i; an observation carries
    sigma_z(z_j)^2 plus frame j's pose variance projected on i's ray (a^T S_j a with
    a = J(p_j)^T R_ij^T r, J(p) = [-[p]x, I]). Observations within `consistency_sigmas`
    of the frame's own depth are fused by inverse variance; the others are rejected as
    outliers. Pixels without own depth take the fusion of >= `fill_min_views` mutually
    consistent neighbour observations (a larger sigma: no own measurement).
The frame's own pose variance and the sensor's systematic error are common to all
observations on its ray, so they are added after fusion rather than averaged away.

Image-only scenes (e.g. LLFF) get sparse targets from SfM points instead
(:func:`sparse_depth_targets`): the pixel ray restricted to the point's uncertainty
ellipsoid (:func:`gaussian_along_ray`), in the same :class:`DepthTargets`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from .data.sequence import RGBDSequence, check_poses, check_sequence
from .errors import InputError


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Depth noise of a sensor, in metres for z-depth z in metres.

    Random axial noise sigma_z(z) = a + b (z - c)^2 (Nguyen et al. 2012, Kinect): independent
    between frames, so fusing views averages it down. Systematic error sigma_sys(z) = relative * z
    (calibration, depth distortion, depth-to-colour registration): the same in every frame of
    the sensor, so fusion cannot average it away; it is added to each fused target. The default
    2% was picked in exploratory runs on TUM fr1/xyz (Kinect v1); benchmarks/bench_nerf.py
    compares it with 0 (run pnerf_without_systematic_sigma): lower held-out depth error.
    """

    a: float = 0.0012
    b: float = 0.0019
    c: float = 0.4
    relative: float = 0.02

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Random sigma_z (m) for z-depth `z` (m), any shape."""
        return self.a + self.b * (z - self.c) ** 2

    def systematic_var(self, z: np.ndarray) -> np.ndarray:
        """Variance (m^2) of the systematic error at z-depth `z` (m), any shape."""
        return (self.relative * z) ** 2


@dataclasses.dataclass
class DepthTargets:
    """Per-pixel Gaussian depth targets for the N frames of a sequence, all (N, H, W).

    mean, sigma: float32 z-depth metres (0 where invalid). valid: bool. support: uint8
    number of observations fused (own depth counts as one). filled: bool, True where the
    frame had no own depth and the target comes from neighbours only.
    """

    mean: np.ndarray
    sigma: np.ndarray
    valid: np.ndarray
    support: np.ndarray
    filled: np.ndarray

    def __len__(self) -> int:
        return self.mean.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        return self.mean.shape[1:]

    def summary(self) -> dict:
        """Fractions of valid/filled pixels and sigma percentiles (mm) over valid pixels."""
        sig = self.sigma[self.valid]
        pct = np.percentile(sig, [5, 50, 95]) * 1000 if sig.size else [np.nan] * 3
        return {
            "valid_fraction": float(self.valid.mean()),
            "filled_fraction": float(self.filled.mean()),
            "sigma_mm_p5_p50_p95": [round(float(p), 2) for p in pct],
            "mean_support": float(self.support[self.valid].mean()) if sig.size else 0.0,
        }


def ray_norms(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) float32 ||K^-1 [u, v, 1]||: metres along the ray per metre of z-depth at each pixel."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.sqrt(x * x + y * y + 1).astype(np.float32)


def _backproject(depth: np.ndarray, K: np.ndarray):
    """Valid pixels of `depth` as (M, 3) camera points and their flat pixel indices."""
    h, w = depth.shape
    flat = np.flatnonzero(depth > 0)
    v, u = np.divmod(flat, w)
    z = depth.ravel()[flat].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    return pts, flat


def _unit_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(H, W, 3) unit ray directions in the camera frame."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _own_pose_var(rays: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(H, W) z-unit variance of a frame's translation covariance along its own unit rays."""
    return (rays @ cov[3:, 3:] * rays).sum(-1) * rays[..., 2] ** 2


def _project(q: np.ndarray, K: np.ndarray, h: int, w: int):
    """Nearest pixels of camera-frame points q (M, 3), z > 0: flat indices v * w + u (M,) and
    the (M,) mask of those inside the h x w image."""
    u = np.round(q[:, 0] / q[:, 2] * K[0, 0] + K[0, 2]).astype(np.int64)
    v = np.round(q[:, 1] / q[:, 2] * K[1, 1] + K[1, 2]).astype(np.int64)
    return v * w + u, (u >= 0) & (u < w) & (v >= 0) & (v < h)


def _nearest_per_pixel(pix: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Indices of the smallest z among entries sharing a flat pixel index (a z-buffer), sorted by pixel."""
    order = np.lexsort((z, pix))
    first = np.unique(pix[order], return_index=True)[1]
    return order[first]


def reproject(depth_j, var_j, pose_j, cov_j, pose_i, K, shape_i):
    """Reproject frame j's depth into frame i (z-buffered).

    Returns (z, var) maps of frame i's shape, NaN where nothing lands: z in frame i's
    z-depth metres; var = var_j (sensor) + frame j's pose variance on frame i's ray.
    """
    h, w = shape_i
    p_j, flat_j = _backproject(depth_j, K)
    rel = np.linalg.inv(pose_i) @ pose_j
    q = p_j @ rel[:3, :3].T + rel[:3, 3]
    front = q[:, 2] > 1e-6
    q, p_j, flat_j = q[front], p_j[front], flat_j[front]
    pix, inside = _project(q, K, h, w)
    q, p_j, flat_j, pix = q[inside], p_j[inside], flat_j[inside], pix[inside]
    keep = _nearest_per_pixel(pix, q[:, 2])
    pix, q, p_j, flat_j = pix[keep], q[keep], p_j[keep], flat_j[keep]
    r = q / np.linalg.norm(q, axis=1, keepdims=True)
    # a = J(p_j)^T R_ij^T r with J = [-[p]x, I], i.e. [p_j x R_ij^T r, R_ij^T r]:
    # the sensitivity of the depth along r to frame j's pose perturbation xi_j
    rj = r @ rel[:3, :3]
    a = np.concatenate([np.cross(p_j, rj), rj], 1)
    pose_var_t = ((a @ cov_j) * a).sum(1)
    z = np.full(h * w, np.nan)
    var = np.full(h * w, np.nan)
    z[pix] = q[:, 2]
    var[pix] = var_j.ravel()[flat_j] + pose_var_t * r[:, 2] ** 2
    return z.reshape(h, w), var.reshape(h, w)


def check_covariances(covariances, n: int, what: str = "covariances") -> np.ndarray:
    """(n, 6, 6) float64 pose covariances (zeros for None), checked finite and of that shape."""
    covs = np.zeros((n, 6, 6)) if covariances is None else np.asarray(covariances, np.float64)
    if covs.shape != (n, 6, 6) or not np.isfinite(covs).all():
        raise InputError(f"{what} must be finite with shape ({n}, 6, 6), got shape {covs.shape}")
    return covs


def depth_targets(
    sequence: RGBDSequence,
    trajectory=None,
    *,
    poses: np.ndarray | None = None,
    covariances: np.ndarray | None = None,
    sensor: SensorNoise = SensorNoise(),
    neighbors: int = 2,
    consistency_sigmas: float = 3.0,
    fill_min_views: int = 2,
    storage_dir: str | Path | None = None,
    progress: bool = True,
) -> DepthTargets:
    """Per-pixel Gaussian depth targets (z-depth mean and sigma, metres) for every frame.

    trajectory: a :class:`~open3d_pnerf.tracking.Trajectory` (uses .poses, .covariances), or
    give `poses` ((N, 4, 4) camera-to-world) and optionally `covariances` ((N, 6, 6),
    [rotation, translation], right perturbation; zeros if omitted). neighbors: frames on
    each side reprojected into a frame. consistency_sigmas: outlier gate. storage_dir: keep
    the (N, H, W) arrays in .npy memory maps there instead of RAM (long sequences).

    An image-only sequence (``sequence.has_depth`` False, e.g. an LLFF folder) gets the
    targets of its sparse SfM points instead (:func:`sparse_depth_targets`); its own poses
    and covariances are used unless others are given, and the dense-fusion options (sensor,
    neighbors, consistency_sigmas, fill_min_views, progress) do not apply.
    """
    n = len(check_sequence(sequence, what="depth_targets(): sequence"))
    if trajectory is not None:
        poses, covariances = trajectory.poses, trajectory.covariances
    if poses is None and not sequence.has_depth:
        poses, covariances = sequence.poses, sequence.covariances
    if poses is None:
        raise InputError("depth_targets() needs a trajectory or poses=(N, 4, 4) camera-to-world")
    poses = check_poses(poses, n, "poses")
    covs = check_covariances(covariances, n)
    if not sequence.has_depth:
        pts = sequence.points
        return sparse_depth_targets(poses, sequence.K, sequence.image_size, pts.xyz, pts.error, pts.observed,
                                    covariances=covs, storage_dir=storage_dir)
    if neighbors < 0 or consistency_sigmas <= 0 or fill_min_views < 1:
        raise InputError("need neighbors >= 0, consistency_sigmas > 0 and fill_min_views >= 1")
    if not (isinstance(sensor, SensorNoise) and min(sensor.a, sensor.b, sensor.relative) >= 0):
        raise InputError(f"sensor must be a SensorNoise with a, b, relative >= 0, got {sensor!r}")

    h, w = sequence.image_size
    K = sequence.K
    rays = _unit_rays(K, h, w)
    out = _allocate(n, h, w, storage_dir)
    depths: dict[int, np.ndarray] = {}  # sliding window of loaded depth maps

    def depth_of(k: int) -> np.ndarray:
        if k not in depths:
            depths[k] = sequence[k].depth
        return depths[k]

    for i in tqdm(range(n), desc="depth targets", disable=not progress, leave=False):
        for k in [k for k in depths if k < i - neighbors]:
            del depths[k]
        z_i = depth_of(i).astype(np.float64)
        obs_z, obs_var = [np.where(z_i > 0, z_i, np.nan)], [sensor.sigma(z_i) ** 2]
        for j in range(max(0, i - neighbors), min(n, i + neighbors + 1)):
            if j == i:
                continue
            z_j = depth_of(j)
            z, var = reproject(z_j, sensor.sigma(z_j.astype(np.float64)) ** 2, poses[j], covs[j], poses[i], K, (h, w))
            obs_z.append(z)
            obs_var.append(var)
        mean, var, support = _fuse(np.stack(obs_z), np.stack(obs_var), consistency_sigmas, fill_min_views)
        valid = np.isfinite(mean)
        var = var + _own_pose_var(rays, covs[i]) + sensor.systematic_var(mean)
        out.mean[i] = np.where(valid, mean, 0)
        out.sigma[i] = np.where(valid, np.sqrt(var), 0)
        out.valid[i] = valid
        out.support[i] = support
        out.filled[i] = valid & ~(z_i > 0)
    return out


def _fuse(z: np.ndarray, var: np.ndarray, gate: float, fill_min_views: int):
    """Fuse (V, H, W) observations; index 0 is the frame's own depth (NaN = none).

    Returns mean (NaN where no target), variance and support count per pixel.
    """
    own, own_var = z[0], var[0]
    has_own = np.isfinite(own)
    # reference: own depth where present, else the median of neighbour observations
    ref = own.copy()
    holes = ~has_own & np.isfinite(z[1:]).any(0)
    ref[holes] = np.nanmedian(z[1:, holes], axis=0)
    with np.errstate(all="ignore"):
        ref_var = np.where(has_own, own_var, 0.0)
        ok = np.isfinite(z) & (np.abs(z - ref) <= gate * np.sqrt(var + ref_var))
        ok[0] = has_own
        inv = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
        support = ok.sum(0)
        total = inv.sum(0)
        mean = (np.where(ok, z, 0.0) * inv).sum(0) / total
        fused_var = 1.0 / total
    enough = has_own | (support >= fill_min_views)
    mean = np.where(enough & (total > 0), mean, np.nan)
    return mean, np.where(np.isfinite(mean), fused_var, np.nan), np.where(enough, support, 0).astype(np.uint8)


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
    min_angle_deg: float = 1.0,
    min_error: float = 0.01,
    storage_dir: str | Path | None = None,
) -> DepthTargets:
    """Per-pixel Gaussian depth targets (z-depth mean and sigma) from sparse SfM points.

    poses: (N, 4, 4) camera-to-world; K: (3, 3); image_size: (H, W); xyz: (M, 3) world points;
    error: (M,) their reprojection error in pixels of K's images, floored at `min_error` so that
    an exact fit keeps a nonzero sigma; observed: (M, N) bool, point k is in frame i's track;
    covariances: (N, 6, 6) pose covariances ([rotation, translation], right perturbation),
    zeros if None. Units of length are those of the poses and points.

    Each point k observed in frame i, in front of it and projecting inside the image, gives
    the target of the pixel it rounds to (the nearest point where several do):
      * point covariance, from its track: lateral sigma s_lat = e_k z / fx (e_k pixels at
        z-depth z) across the viewing direction v = (p - c_i) / |p - c_i|, depth sigma
        s_dep = s_lat / sin(theta) along v, theta the angle between v and another observing
        camera's direction to p with the largest sine (two rays at angle theta turn a lateral
        error into one 1/sin(theta) larger along each other): S_p = s_lat^2 (I - v v^T) + s_dep^2 v v^T;
      * pose: S = S_p + R_i S_i[3:, 3:] R_i^T, the camera centre's world covariance (rotation
        about the centre does not move points along the camera's own rays);
      * the pixel's unit ray d (through its integer centre) meets N(p, S) in the Gaussian
        (t*, var) of :func:`gaussian_along_ray`; z-depth mean = t* d_z, sigma = sqrt(var) d_z
        with d_z the ray's camera-frame z (z = t d_z);
      * weight w_k = exp(-(e_k / mean(e))^2) (DS-NeRF) down-weights badly fitting points.
        DepthTargets has no weight, so it is folded into sigma: sigma / sqrt(w_k) weights
        the squared residual of a Gaussian term by w_k.
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

    error = np.maximum(error, min_error)
    inv_sqrt_weight = np.exp(0.5 * (error / (error.mean() if m else 1.0)) ** 2)
    track = np.minimum(observed.sum(1), 255).astype(np.uint8)
    centres = poses[:, :3, 3]
    rays = _unit_rays(K, h, w).reshape(-1, 3)
    out = _allocate(n, h, w, storage_dir)
    for i in range(n):
        idx = np.flatnonzero(observed[:, i])
        rot = poses[i, :3, :3]
        q = (xyz[idx] - centres[i]) @ rot  # camera frame
        idx, q = idx[q[:, 2] > 0], q[q[:, 2] > 0]
        pix, inside = _project(q, K, h, w)
        idx, q, pix = idx[inside], q[inside], pix[inside]
        # viewing directions of every camera to these points, (M_i, N, 3), and theta
        view = xyz[idx, None] - centres[None]
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        v = view[:, i]
        sin_theta = np.where(observed[idx], np.linalg.norm(np.cross(v[:, None], view), axis=-1), 0).max(1)
        keep = (sin_theta > 0) & (sin_theta >= np.sin(np.radians(min_angle_deg)))
        idx, q, pix, v, sin_theta = idx[keep], q[keep], pix[keep], v[keep], sin_theta[keep]
        s_lat = error[idx] * q[:, 2] / K[0, 0]
        s_dep = s_lat / sin_theta
        vv = v[:, :, None] * v[:, None, :]
        cov = s_lat[:, None, None] ** 2 * (np.eye(3) - vv) + s_dep[:, None, None] ** 2 * vv
        cov += rot @ covs[i, 3:, 3:] @ rot.T
        d_cam = rays[pix]
        t, var = gaussian_along_ray(centres[i], d_cam @ rot.T, xyz[idx], cov)
        z, sigma = t * d_cam[:, 2], np.sqrt(var) * d_cam[:, 2] * inv_sqrt_weight[idx]
        best = _nearest_per_pixel(pix, z)
        pix, idx, z, sigma = pix[best], idx[best], z[best], sigma[best]
        out.mean[i].flat[pix] = z
        out.sigma[i].flat[pix] = sigma
        out.valid[i].flat[pix] = True
        out.support[i].flat[pix] = track[idx]
    return out


def _allocate(n: int, h: int, w: int, storage_dir) -> DepthTargets:
    if storage_dir is None:
        make = lambda name, dtype: np.zeros((n, h, w), dtype)  # noqa: E731
    else:
        folder = Path(storage_dir)
        folder.mkdir(parents=True, exist_ok=True)
        make = lambda name, dtype: np.lib.format.open_memmap(  # noqa: E731
            folder / f"{name}.npy", mode="w+", dtype=dtype, shape=(n, h, w)
        )
    return DepthTargets(
        make("mean", np.float32),
        make("sigma", np.float32),
        make("valid", bool),
        make("support", np.uint8),
        make("filled", bool),
    )
