"""What the training views say about occupancy, through the calibrated depth law.

Each training view (at most export.max_views, evenly spaced) gives every pixel a z-depth mu (m)
with its error law F (the reconstruction's calibrated :class:`~open3d_pnerf.error_law.DepthErrorLaw`,
1-sigma equivalent s) and an opacity a (the probability that its ray ends in the scene box): with
the reconstruction's frames, the export's views (the sensor's depth fused with the model's, at the
training resolution, :func:`~open3d_pnerf.export.export_views`); without, the model's renders every
`pixel_stride` training pixels. A pixel without depth says nothing. For a voxel of side v:

- hit: each ray (every k-th pixel, k as large as keeps neighbouring rays half a voxel apart at
  the view's median depth) is walked in half-voxel steps through mu +- (3 s + v/2); the probability that its
  surface lies on its path through the voxel is the sum of a (F(z + v/4 - mu) - F(z - v/4 - mu))
  over its steps there. The view's hit h is the largest over its rays.
- passed: the voxel's centre, at z-depth z in the view (a voxel the image's edge crosses takes its
  nearest pixel), goes with the ray through it on beyond the voxel with probability
  m = 1 - a F(z + v/2 - mu); behind the surface this is about 0: the view says nothing there.

As in OctoMap, one update per voxel and view, and a voxel the view's rays end in is not also free in
it: the view adds h to the voxel's hits H and (1 - h) m to its passes M. The log-odds are
clip(hit H + miss M / (1 + grazing H), low, high) (:class:`SensorModel`): OctoMap's inverse sensor
model with each outcome as uncertain as the depth law says, and the passes of a voxel that views end
in discounted (other views' rays cross the free part of a voxel a surface only clips). The weights
are not one view's likelihood ratios, since views of one surface are not independent: they and the
clamp are chosen on one scene (``benchmarks/bench_occupancy.py --tune``) for calibrated
probabilities. A voxel no view says anything of (H + M below MIN_EVIDENCE) stays unknown: log-odds
0, probability 0.5.
"""

from __future__ import annotations

import dataclasses
import functools
import weakref

import numpy as np
from scipy.special import expit

from ..error_law import DepthErrorLaw
from ..errors import ConfigError, InputError
from ..export import export_views
from .grid import OccupancyGrid, grid_frame

MIN_EVIDENCE = 0.05
"""Hits plus passes (in views) below which a voxel counts as unseen."""
RAYS_AT_ONCE = 8192
VOXELS_AT_ONCE = 1 << 20


@dataclasses.dataclass(frozen=True)
class SensorModel:
    """How hits H and passes M become log-odds: clip(hit H + miss M / (1 + grazing H), low, high),
    with hit > 0 > miss and low < 0 < high. `grazing` >= 0 discounts the passes of a voxel that views
    end in: other views' rays cross the free part of a voxel a surface clips. Defaults chosen on
    7-Scenes redkitchen's held-out frames by ``benchmarks/bench_occupancy.py --tune`` (the lowest Brier
    score of 5 cm voxels that calls at most 1% of the occupied ones free), reported on other scenes."""

    hit: float = 0.2
    miss: float = -1.6
    grazing: float = 10.0
    low: float = -8.0
    high: float = 8.0

    def __post_init__(self):
        if not (self.hit > 0 > self.miss and self.low < 0 < self.high and self.grazing >= 0):
            raise ConfigError(f"a sensor model needs hit > 0 > miss, grazing >= 0 and low < 0 < high, got {self}")

    def log_odds(self, hits: np.ndarray, passes: np.ndarray) -> np.ndarray:
        """(N,) float32 log-odds of voxels with hits and passes (N,) summed over the views; 0 where unseen."""
        value = np.clip(self.hit * hits + self.miss * passes / (1 + self.grazing * hits), self.low, self.high)
        return np.where(hits + passes >= MIN_EVIDENCE, value, 0.0).astype(np.float32)

    def probability(self, hits: np.ndarray, passes: np.ndarray) -> np.ndarray:
        """(N,) probability that each voxel is occupied: the logistic of :meth:`log_odds`."""
        return expit(self.log_odds(hits, passes).astype(np.float64))


@dataclasses.dataclass(eq=False)
class ViewEvidence:
    """The training views as occupancy reads them: poses (F, 4, 4) camera-to-world, K (3, 3) of
    their rendered images, depth, sigma (F, h, w) z-depth and calibrated 1-sigma (m), opacity
    (F, h, w), the law of the depth errors, and fine: the rays per rendered pixel and axis near
    the surfaces (the training pixels each rendered one stands for: their depth is the rendered one)."""

    poses: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    sigma: np.ndarray
    opacity: np.ndarray
    law: DepthErrorLaw
    fine: int = 1

    def voxels(self, origin: np.ndarray, shape: tuple[int, int, int], voxel_size: float,
               wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(hits, passes) summed over the views, of the voxels of the grid of `shape` voxels of
        `voxel_size` (m) from corner `origin` (3,) m: every voxel (flat, C order), or those of the
        sorted flat indices `wanted`."""
        size = int(np.prod(shape)) if wanted is None else len(wanted)
        hits, passes = np.zeros(size, np.float32), np.zeros(size, np.float32)
        h, w = self.depth.shape[1:]
        sub = (np.arange(self.fine) + 0.5) / self.fine - 0.5  # the training pixels within each rendered one
        fine = self._rays((np.arange(w)[:, None] + sub).reshape(-1), (np.arange(h)[:, None] + sub).reshape(-1))
        fine_of = np.arange(h * w).reshape(h, w).repeat(self.fine, 0).repeat(self.fine, 1).reshape(-1)
        cdf = _tabulated_cdf(self.law)
        for pose, depth, sigma, opacity in zip(self.poses, self.depth, self.sigma, self.opacity):
            mu, s, a = depth.reshape(-1), sigma.reshape(-1), opacity.reshape(-1)
            hit = np.zeros(size, np.float32)
            grid = (pose, origin, shape, voxel_size, wanted)
            rays = np.flatnonzero((mu[fine_of] > 0) & self._walked(fine_of, mu, voxel_size))
            for chunk in np.array_split(rays, max(1, len(rays) // RAYS_AT_ONCE)):
                of = fine_of[chunk]
                self._walk(grid, fine[chunk], mu[of], s[of], a[of], hit)
            for start in range(0, size, VOXELS_AT_ONCE):  # free space: every voxel the view holds
                flat = np.arange(start, min(start + VOXELS_AT_ONCE, size))
                index = np.stack(np.unravel_index(flat if wanted is None else wanted[flat], shape), -1)
                centers = origin + (index + 0.5) * voxel_size
                passes[flat] += (1 - hit[flat]) * self._passes(pose, depth, sigma, opacity, centers, voxel_size, cdf)
            hits += hit
        return hits.astype(np.float64), passes.astype(np.float64)

    def _walked(self, fine_of: np.ndarray, mu: np.ndarray, voxel_size: float) -> np.ndarray:
        """(len(fine_of),) bool: the rays one view walks near its surfaces, every k-th training pixel
        in each direction, k as large as keeps neighbouring rays within half a voxel of each other
        at the view's median depth (a pixel without depth is never walked: it says nothing)."""
        has = mu > 0
        if not has.any():
            return np.zeros(len(fine_of), bool)
        h, w = self.depth.shape[1] * self.fine, self.depth.shape[2] * self.fine
        focal = self.K[0, 0] * self.fine  # of the training pixels
        k = max(1, int(focal * voxel_size / 2 / np.median(mu[has])))
        v, u = np.divmod(np.arange(h * w), w)
        return (v % k == 0) & (u % k == 0)

    def _passes(self, pose, depth, sigma, opacity, centers, voxel_size, cdf) -> np.ndarray:
        """(N,) probability that one view's ray through each voxel centre (N, 3) m goes on beyond the
        voxel (its surface more than half a voxel behind the centre, or none); 0 outside the view (a
        voxel the image's edge crosses, near the camera above all, takes its nearest pixel's ray)."""
        cam = (centers - pose[:3, 3]) @ pose[:3, :3]
        z = cam[:, 2]
        h, w = depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(self.K[0, 0] * cam[:, 0] / z + self.K[0, 2])
            v = np.rint(self.K[1, 1] * cam[:, 1] / z + self.K[1, 2])
        reach = self.K[0, 0] * voxel_size / 2 / np.maximum(z, 1e-6)  # half the voxel, in pixels
        seen = np.flatnonzero((z > 0) & (u >= -reach) & (u < w + reach) & (v >= -reach) & (v < h + reach))
        ui = np.clip(u[seen], 0, w - 1).astype(np.int64)  # a voxel the image's edge crosses: the nearest pixel
        vi = np.clip(v[seen], 0, h - 1).astype(np.int64)
        has = depth[vi, ui] > 0  # a pixel without depth says nothing
        seen, ui, vi = seen[has], ui[has], vi[has]
        out = np.zeros(len(centers), np.float32)
        out[seen] = 1 - opacity[vi, ui] * cdf((z[seen] + voxel_size / 2 - depth[vi, ui]) / sigma[vi, ui])
        return out

    def at(self, points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
        """(hits, passes) (N,) of the voxels of `voxel_size` (m; origin at a multiple of it, as a grid's)
        that hold the points (N, 3) m."""
        origin = np.floor(points.min(0) / voxel_size) * voxel_size
        index = np.floor((points - origin) / voxel_size).astype(np.int64)
        shape = tuple(int(n) for n in index.max(0) + 1)
        wanted, inverse = np.unique(np.ravel_multi_index(index.T, shape), return_inverse=True)
        hits, passes = self.voxels(origin, shape, voxel_size, wanted)
        return hits[inverse.reshape(-1)], passes[inverse.reshape(-1)]

    def _rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(len(v) * len(u), 3) rays (camera axes, z = 1) of the pixels at columns u and rows v."""
        uu, vv = np.meshgrid(u, v)
        return np.stack([(uu - self.K[0, 2]) / self.K[0, 0], (vv - self.K[1, 2]) / self.K[1, 1],
                         np.ones(uu.shape)], -1).reshape(-1, 3)

    def _walk(self, grid, rays, mu, s, a, hit) -> None:
        """Walks rays (R, 3) of one view (their depth law mu, s, a (R,)) in steps of half a voxel from
        mu - 3 s - half a voxel to mu + 3 s + half a voxel, and raises each voxel's `hit` (flat, as in
        :meth:`voxels`) to the largest probability, over the rays, that a ray's surface lies on its
        path through the voxel (the sum over the ray's steps in it)."""
        pose, origin, shape, voxel_size, wanted = grid
        step = voxel_size / 2 / np.linalg.norm(rays, axis=1)  # half a voxel along each ray, in z
        start = np.floor(np.maximum(mu - 3 * s - voxel_size / 2, 0) / step)
        count = (np.ceil((mu + 3 * s + voxel_size / 2) / step) - start).astype(np.int64)
        ray = np.repeat(np.arange(len(mu)), count)
        z = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + start[ray] + 0.5) * step[ray]
        directions = rays @ pose[:3, :3].T / voxel_size  # world, in voxels per metre of z
        index = np.floor((pose[:3, 3] - origin) / voxel_size + directions[ray] * z[:, None]).astype(np.int64)
        inside = np.all((index >= 0) & (index < shape), axis=1)
        index, ray, z = index[inside], ray[inside], z[inside]
        flat = (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]
        if wanted is not None:
            at = np.clip(np.searchsorted(wanted, flat), 0, len(wanted) - 1)
            keep = wanted[at] == flat
            flat, ray, z = at[keep], ray[keep], z[keep]
        if not len(flat):
            return
        cdf = _tabulated_cdf(self.law)
        half = step[ray] / 2
        chance = a[ray] * (cdf((z + half - mu[ray]) / s[ray]) - cdf((z - half - mu[ray]) / s[ray]))
        runs = np.flatnonzero(np.r_[True, (flat[1:] != flat[:-1]) | (ray[1:] != ray[:-1])])  # a ray's steps in a voxel
        np.maximum.at(hit, flat[runs], np.add.reduceat(chance, runs).astype(np.float32))

    def grid(self, origin: np.ndarray, shape: tuple[int, int, int], voxel_size: float,
             sensor: SensorModel) -> OccupancyGrid:
        """The :class:`OccupancyGrid` of `shape` voxels of `voxel_size` (m) from corner `origin` (3,) m
        (see :func:`~open3d_pnerf.occupancy.grid_frame`)."""
        log_odds = sensor.log_odds(*self.voxels(origin, shape, voxel_size))
        return OccupancyGrid(log_odds.reshape(shape), origin, float(voxel_size))


@functools.lru_cache(maxsize=8)
def _tabulated_cdf(law: DepthErrorLaw, reach: float = 60.0, points: int = 24001):
    """The law's CDF of errors in 1-sigma equivalents, tabulated over +-`reach` and linearly
    interpolated (within 1e-5 for 2 or more degrees of freedom, 2e-3 for fewer): scipy's Student-t CDF is too slow for
    the millions of points a grid's rays walk through."""
    x = np.linspace(-reach, reach, points)
    table = law.cdf(x, np.ones_like(x))
    spacing = x[1] - x[0]

    def cdf(standardized: np.ndarray) -> np.ndarray:
        at = (np.clip(standardized, -reach, reach) + reach) / spacing
        i = np.minimum(at.astype(np.int64), points - 2)
        return table[i] + (at - i) * (table[i + 1] - table[i])

    return cdf


_VIEWS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # each reconstruction's last rendered views


def view_evidence(recon, pixel_stride: int = 8) -> ViewEvidence:
    """The reconstruction's training views as occupancy reads them (at most export.max_views, evenly
    spaced), kept with the reconstruction until its poses or depth law change. With its frames'
    depth (``recon.frames``): the export's views (:func:`~open3d_pnerf.export.export_views`), the
    sensor's depth fused with the model's rendered every `pixel_stride` pixels, at the training
    resolution; without: the model's renders every `pixel_stride` training pixels."""
    if isinstance(pixel_stride, bool) or not (isinstance(pixel_stride, (int, np.integer)) and pixel_stride >= 1):
        raise ConfigError(f"pixel_stride must be a whole number of pixels >= 1, got {pixel_stride!r}")
    key = (int(pixel_stride), recon.depth_error, recon.poses.tobytes())
    if key in _VIEWS.get(recon, {}):
        return _VIEWS[recon][key]
    frames = recon.frames if recon.frames is not None and recon.frames.has_depth else None
    config = dataclasses.replace(recon.config.export, fused_scale=1 / pixel_stride, scale=1 / pixel_stride)
    views = export_views(recon, frames, config, progress=False)
    depth = np.stack([r["depth"] for r in views.renders]).astype(np.float64)
    sigma = np.stack([r["depth_std"] for r in views.renders]).astype(np.float64)
    opacity = np.stack([r["opacity"] for r in views.renders]).astype(np.float64)
    ok = np.isfinite(depth) & np.isfinite(sigma) & (depth > 0)  # elsewhere the view says nothing
    evidence = ViewEvidence(views.poses, views.K, np.where(ok, depth, 0.0), np.where(ok, np.maximum(sigma, 1e-4), 1.0),
                            np.where(ok, np.clip(opacity, 0, 1), 0.0), recon.depth_error,
                            1 if views.fused else int(pixel_stride))
    _VIEWS[recon] = {key: evidence}
    return evidence


def occupancy_at(recon, points, size: float = 0.05, sensor: SensorModel = SensorModel(),
                 pixel_stride: int = 8) -> np.ndarray:
    """(N,) probability that the voxel of side `size` (m) holding each point (N, 3) m is occupied
    (the voxels of the grid whose origin is a multiple of `size`, as :func:`occupancy_grid`'s)."""
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all() or not len(points):
        raise InputError(f"points must be finite (N, 3) in metres, N >= 1, got an array of shape {points.shape}")
    if isinstance(size, bool) or not isinstance(size, (int, float, np.floating, np.integer)) or not size > 0:
        raise ConfigError(f"size must be a positive number of metres, got {size!r}")
    hits, passes = view_evidence(recon, pixel_stride).at(points, size)
    return sensor.probability(hits, passes)


def occupancy_grid(recon, voxel_size: float = 0.05, bounds=None, sensor: SensorModel = SensorModel(),
                   pixel_stride: int = 8) -> OccupancyGrid:
    """The :class:`OccupancyGrid` of `voxel_size` (m) over `bounds` ((2, 3) min and max corner, m;
    None: the reconstruction's scene box)."""
    origin, shape = grid_frame(voxel_size, bounds, recon.aabb)
    return view_evidence(recon, pixel_stride).grid(origin, shape, voxel_size, sensor)
