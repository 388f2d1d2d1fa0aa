"""Dense depth targets of an RGB-D sequence: sensor noise, pose uncertainty, multi-view fusion.

For every pixel of every frame the target is a Gaussian over depth, N(mean, sigma^2), in
**z-depth metres**. The pixel's ray meets depth z at Euclidean distance t = z ||k|| with
k = K^-1 [u, v, 1], so the ray-distance target is (mean, sigma) * ||k|| (camera.ray_norms).

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
A reconstruction's settings of the targets are its TargetsConfig.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ..camera import backproject, camera_poses, nearest_per_pixel, nearest_pixels, unit_rays
from ..data.sequence import RGBDSequence, check_sequence
from ..errors import InputError
from ..settings import Settings, number, setting
from .noise import SensorNoise
from .sparse import sparse_depth_targets
from .storage import DepthTargets, allocate


@dataclasses.dataclass
class TargetsConfig(Settings):
    """How a reconstruction builds its depth targets (see :func:`depth_targets`)."""

    depth_sigma_relative: float = setting(0.04, number(0, 1, high_open=True))
    """Systematic term of the targets as a fraction of depth: widens every depth target by
    relative * z in quadrature, after multi-view fusion (calibration and registration errors are
    shared by all views). Twice the sensor's own (SensorNoise.relative, which the exported sigma
    uses: export.depth_sigma_relative): chosen for held-out colour at a user's budget on TUM's
    tuning split (docs/benchmarks.md). 0 = random noise only."""

    def sensor_noise(self) -> SensorNoise:
        """The noise model the targets assume: the sensor's random noise and this systematic term."""
        return SensorNoise(relative=self.depth_sigma_relative)

    def build(self, sequence: RGBDSequence, poses: np.ndarray, covariances: np.ndarray, storage_dir=None,
              progress: bool = True) -> DepthTargets:
        """:func:`depth_targets` of the frames of `sequence` at `poses` with these settings."""
        return depth_targets(sequence, poses=poses, covariances=covariances, sensor=self.sensor_noise(),
                             storage_dir=storage_dir, progress=progress)


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

    A sequence without depth images (``sequence.has_depth`` False, e.g. an LLFF folder) gets
    the targets of its sparse SfM points instead (:func:`sparse_depth_targets`); its own poses
    and covariances are used unless others are given, and the dense-fusion options (sensor,
    neighbors, consistency_sigmas, fill_min_views, progress) do not apply.
    """
    n = len(check_sequence(sequence, what="depth_targets(): sequence"))
    if trajectory is not None:
        poses, covariances = trajectory.poses, trajectory.covariances
    sfm = sequence.sfm
    if poses is None and sfm is not None:
        poses, covariances = sfm.poses, sfm.covariances
    if poses is None:
        raise InputError("depth_targets() needs a trajectory or poses=(N, 4, 4) camera-to-world")
    poses, covs = camera_poses(poses, n, "poses", covariances)
    if not sequence.has_depth:
        pts = sfm.points
        return sparse_depth_targets(poses, sequence.K, sequence.image_size, pts.xyz, pts.error, pts.observed,
                                    covariances=covs, radial=sfm.radial, storage_dir=storage_dir)
    if neighbors < 0 or consistency_sigmas <= 0 or fill_min_views < 1:
        raise InputError("need neighbors >= 0, consistency_sigmas > 0 and fill_min_views >= 1")
    if not (isinstance(sensor, SensorNoise) and min(sensor.a, sensor.b, sensor.relative) >= 0):
        raise InputError(f"sensor must be a SensorNoise with a, b, relative >= 0, got {sensor!r}")

    h, w = sequence.image_size
    K = sequence.K
    rays = unit_rays(K, h, w)
    out = allocate(n, h, w, storage_dir)
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


def _own_pose_var(rays: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(H, W) z-unit variance of a frame's translation covariance along its own unit rays."""
    return (rays @ cov[3:, 3:] * rays).sum(-1) * rays[..., 2] ** 2


def reproject(depth_j, var_j, pose_j, cov_j, pose_i, K, shape_i):
    """Reproject frame j's depth into frame i (z-buffered).

    Returns (z, var) maps of frame i's shape, NaN where nothing lands: z in frame i's
    z-depth metres; var = var_j (sensor) + frame j's pose variance on frame i's ray.
    """
    h, w = shape_i
    p_j, flat_j = backproject(depth_j, K)
    rel = np.linalg.inv(pose_i) @ pose_j
    q = p_j @ rel[:3, :3].T + rel[:3, 3]
    front = q[:, 2] > 1e-6
    q, p_j, flat_j = q[front], p_j[front], flat_j[front]
    pix, inside = nearest_pixels(K, q, h, w)
    q, p_j, flat_j, pix = q[inside], p_j[inside], flat_j[inside], pix[inside]
    keep = nearest_per_pixel(pix, q[:, 2])
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
