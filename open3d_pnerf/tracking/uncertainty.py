"""Point-to-plane refinement of a registration, how well it fits and how uncertain it is, from
the two frames' depth images and the residuals themselves.

Open3D's RGB-D odometry associates a source pixel with the target pixel nearest to its projection.
That snapping leaves each registration up to a fraction of a pixel off in a way no residual shows
(on the synthetic room at 320x240 the answers of one frame pair under independent noise draws
fall in two clusters 2.4 mrad apart, ten times the spread the noise explains). :func:`refine`
therefore finishes every registration with Gauss-Newton steps of a point-to-plane alignment that
interpolates the target depth and normals at the projection's sub-pixel position, and scores the
answer the same way. (The colour images get their own cameras: see tracking.color.)

Open3D's information matrix ``G^T G`` counts correspondences as independent measurements, so
its covariance shrinks as 1 / (number of pixels) although neighbouring pixels' depth errors are
far from independent, and it says nothing about how well the frames actually fit. Here the
covariance is the cluster-robust ("sandwich", Huber-White) estimate of the point-to-plane
alignment at its answer:

    Cov(xi) = A^-1 B A^-T,  A = sum_i w_i J_i G_i^T,  B = G / (G - 1) sum_g s_g s_g^T,  s_g = sum_{i in g} w_i J_i r_i

over the inlier correspondences i (a source pixel's point q_i moved by the transformation,
against the target surface m_i, n_i where it projects), r_i = n_i . (q_i - m_i) their
point-to-plane residuals, J_i = [q_i x n_i, n_i] (the residual's derivative with respect to
a perturbation exp(xi) X, [rotation, translation], in the target camera's frame: the frame of
the pose graph's edge residual, see covariance.py) and G_i the same with m_i following the
interpolated surface. The clusters g are tiles of the source image (a fixed grid, so the
estimate does not depend on the processing resolution): residuals that are correlated within a
tile (smooth depth-sensor errors, calibration, blur) count as one measurement per tile, and a
misfit (a wrong registration) inflates B and the covariance. About SAMPLES pixels are sampled
on a regular grid, whatever the image's size.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np


from ..camera import backproject, motion, twist_matrix
from ..targets.noise import SensorNoise

TILES = (16, 12)  # columns x rows of the source image's clusters
SAMPLES = 10_000
"""At most about this many pixels of each image are samples, on a regular grid: stride 6 at 640x480
and 3 at 320x240 (8,560 samples), 2 at 160x120 (4,800); the cost of a refinement is then about
the same at any resolution from 320x240 up (the previous grid took 19,200 at 320x240). Fewer
samples were tried (a stride of 4 or 5 at 320x240): the covariances no longer held on the
synthetic room's noise draws, and at 3,072 samples one frame of its 100-frame seed 3 went 1.7 cm
wrong and took 56 frames outside their covariances (benchmarks/README.md)."""
MIN_INLIERS = 200
SENSOR = SensorNoise()  # the random depth noise that weighs each point-to-plane residual
RESIDUAL_INFLATION = 1.3
"""The sandwich covariance's standard deviations times this: the sub-pixel association leaves a
bias that no residual shows."""
JUMP = 0.05  # neighbouring depths further apart than this fraction of the depth: a discontinuity
STOP_FRACTION = 0.15
"""refine stops before a step below this fraction of the answer's standard deviation on every axis.
0.1 until the misregistration floor grew with the motion, which made the floor of slow frames
smaller and their refinement longer: 59.1 against 52.3 ms a frame with 0.15 on 7-Scenes 150-199 at
320x240 (results/tracking_tuning.md; benchmarks/README.md)."""
MAX_RATIO = 0.8  # steps are extrapolated (refine) when each is 0 to this fraction of the one before


@dataclasses.dataclass(frozen=True)
class Fit:
    """How a transformation aligns two frames.

    transformation: (4, 4) source camera -> target camera that the fit is of;
    overlap: fraction of the source's valid sampled pixels with an inlier correspondence;
    residual_rms: RMS point-to-plane residual of the inliers (m); inliers: their number;
    covariance: (6, 6) covariance of the transformation ([rotation, translation], left
    perturbation in the target camera frame): the sandwich estimate plus the misregistration
    floor (:func:`_fit`), infinite diagonal when degenerate.
    """

    transformation: np.ndarray
    overlap: float
    residual_rms: float
    inliers: int
    covariance: np.ndarray
    bread: np.ndarray = dataclasses.field(repr=False, default=None)
    """(6, 6) A^-1, the inverse of the Newton matrix (refine's steps)."""
    residual_covariance: np.ndarray = dataclasses.field(repr=False, default=None)
    """(6, 6) the part of `covariance` the residuals show (before the misregistration floor)."""
    depth: float = np.nan
    """Median depth of the inlier correspondences (m): the misregistration floor's lever arm."""

    @property
    def usable(self) -> bool:
        return self.inliers >= MIN_INLIERS and bool(np.isfinite(self.covariance).all())


def surface_normals(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals of a z-depth image (H, W) m with intrinsic K, pointing towards the
    camera, zero where a neighbour has no depth: from central differences of the depth,
    n ~ (fx z_u, fy z_v, -(z + (u - cx) z_u + (v - cy) z_v)) (the cross product of the two
    tangents of the back-projected surface)."""
    h, w = depth.shape
    z_u, z_v = _central_differences(depth)
    valid = depth > 0
    valid[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
    valid[1:-1] &= valid[2:] & valid[:-2]
    valid[[0, -1]] = False
    valid[:, [0, -1]] = False
    u = np.arange(w) - K[0, 2]
    v = (np.arange(h) - K[1, 2])[:, None]
    n = np.stack([K[0, 0] * z_u, K[1, 1] * z_v, -(depth + u * z_u + v * z_v)], -1)
    norm = np.sqrt(np.einsum("...i,...i->...", n, n))[..., None]
    return np.where(valid[..., None], n / np.maximum(norm, 1e-12), 0.0)


def _central_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d image / du and d image / dv (H, W) by central differences, zero on the border."""
    d_u, d_v = np.zeros_like(image), np.zeros_like(image)
    d_u[:, 1:-1] = (image[:, 2:] - image[:, :-2]) / 2
    d_v[1:-1] = (image[2:] - image[:-2]) / 2
    return d_u, d_v


def point_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of a z-depth image (zeros where depth is 0)."""
    h, w = depth.shape
    pts, flat = backproject(depth, K)
    out = np.zeros((h * w, 3))
    out[flat] = pts
    return out.reshape(h, w, 3)


@dataclasses.dataclass(frozen=True)
class DepthFrame:
    """One frame's geometry for point-to-plane alignment: z-depth (H, W) m, its unit normals
    (H, W, 3) (surface_normals), intrinsic K (3, 3) and the depth beyond which it is ignored (m)."""

    depth: np.ndarray
    normals: np.ndarray
    K: np.ndarray
    max_depth: float

    @classmethod
    def of(cls, depth: np.ndarray, K: np.ndarray, max_depth: float) -> "DepthFrame":
        depth = np.where((depth > 0) & (depth < max_depth), depth, 0.0)
        frame = cls(depth, surface_normals(depth, K), np.asarray(K, np.float64), float(max_depth))
        # what every registration uses, computed now (prefetching: off the main thread)
        frame.sample_tiles, frame.corner_depths, frame.corner_normals
        return frame

    @functools.cached_property
    def points(self) -> np.ndarray:
        """(H, W, 3) camera-frame points (point_image)."""
        return point_image(self.depth, self.K)

    @functools.cached_property
    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (M, 3) of the valid pixels on a regular grid of about SAMPLES pixels,
        and their flat pixel indices (M,)."""
        stride = max(1, int(np.ceil(np.sqrt(self.depth.size / SAMPLES))))
        mask = np.zeros(self.depth.shape, bool)
        mask[stride // 2::stride, stride // 2::stride] = True
        return backproject(self.depth, self.K, mask=mask & (self.depth > 0))

    @functools.cached_property
    def sample_tiles(self) -> np.ndarray:
        """(M,) the tile (cluster, TILES) of the image that each sample lies in."""
        h, w = self.depth.shape
        v, u = np.divmod(self.samples[1], w)
        return (v * TILES[1] // h) * TILES[0] + u * TILES[0] // w

    @functools.cached_property
    def corner_depths(self) -> np.ndarray:
        """(H * W,) each pixel's depth, zero where it has no normal: what a bilinear cell's corners read."""
        n = self.normals
        return (self.depth * ((n[..., 0] != 0) | (n[..., 1] != 0) | (n[..., 2] != 0))).ravel()

    @functools.cached_property
    def corner_normals(self) -> np.ndarray:
        """(3, H * W) each pixel's normal, a row per axis."""
        return np.ascontiguousarray(self.normals.reshape(-1, 3).T)

    def surface_at(self, q: np.ndarray, inlier_distance: float):
        """The surface under camera-frame points q (M, 3), bilinearly interpolated at each point's
        sub-pixel projection, for those points whose four neighbouring pixels all have depth and
        normals, within inlier_distance (m) or JUMP times the depth of each other (not across a
        depth discontinuity), and that lie within inlier_distance of the interpolated surface
        point. Returns their indices into q (K,); as (3, K) rows of x, y, z: the points q[index],
        the surface points m and unit normals n, and `along`, the derivative of n . (q - m) with
        respect to q when m follows the interpolated surface (n itself on a plane that the normals
        describe exactly); and the (K,) sum of the squared interpolation weights (1 on a pixel, 1/4
        between four: how much of one pixel's noise the interpolated depth keeps)."""
        h, w = self.depth.shape
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        z = q[:, 2]
        ahead = z > 1e-6
        u = np.divide(q[:, 0], z, out=np.zeros_like(z), where=ahead) * fx + cx
        v = np.divide(q[:, 1], z, out=np.zeros_like(z), where=ahead) * fy + cy
        u0, v0 = np.floor(u), np.floor(v)
        index = np.flatnonzero(ahead & (u0 >= 0) & (u0 < w - 1) & (v0 >= 0) & (v0 < h - 1))
        # (np.take and np.compress along an axis: several times faster than fancy indexing here)
        q, u, v, u0, v0 = np.take(q.T, index, axis=1), u[index], v[index], u0[index], v0[index]
        # a cell's corners (u, v), (u + 1, v), (u, v + 1), (u + 1, v + 1): (4, K)
        corner = (v0 * w + u0).astype(np.int64) + np.array([0, 1, w, w + 1])[:, None]
        d = self.corner_depths[corner]
        a, b = u - u0, v - v0
        weights = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
        depth = np.einsum("ck,ck->k", weights, d)
        m = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth])
        gap = q - m
        low, high = d.min(0), d.max(0)
        keep = ((low > 0) & (high - low < np.maximum(inlier_distance, JUMP * low))
                & (np.einsum("jk,jk->k", gap, gap) < inlier_distance**2))
        index, q, m, a, b, corner, d, weights = (np.compress(keep, x, axis=-1)
                                                 for x in (index, q, m, a, b, corner, d, weights))
        depth = m[2]
        n = np.einsum("ck,jck->jk", weights, np.take(self.corner_normals, corner, axis=1))
        n /= np.maximum(np.sqrt(np.einsum("jk,jk->k", n, n)), 1e-12)
        n_ray = (n[0] * m[0] + n[1] * m[1]) / depth + n[2]  # n . the ray (m / depth)
        slope_u = n_ray * ((d[1] - d[0]) * (1 - b) + (d[3] - d[2]) * b) + n[0] * depth / fx  # n . dm/du
        slope_v = n_ray * ((d[2] - d[0]) * (1 - a) + (d[3] - d[1]) * a) + n[1] * depth / fy  # n . dm/dv
        z = q[2]
        along = n.copy()  # n - (n . dm/du) du/dq - (n . dm/dv) dv/dq
        along[0] -= slope_u * fx / z
        along[1] -= slope_v * fy / z
        along[2] += (slope_u * fx * q[0] + slope_v * fy * q[1]) / z**2
        return index, q, m, n, along, np.einsum("ck,ck->k", weights, weights)


def _moment_jacobian(p: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(6, K) rows [p x direction, direction] of points p and directions, both (3, K) rows: the
    derivative of direction . X at X = p with respect to a perturbation exp(xi) X, [rotation, translation]."""
    out = np.empty((6, p.shape[1]))
    np.subtract(p[1] * direction[2], p[2] * direction[1], out=out[0])
    np.subtract(p[2] * direction[0], p[0] * direction[2], out=out[1])
    np.subtract(p[0] * direction[1], p[1] * direction[0], out=out[2])
    out[3:] = direction
    return out


def _correspondences(points: np.ndarray, target: DepthFrame, transformation: np.ndarray, inlier_distance: float):
    """Inlier correspondences of source points (M, 3) moved by `transformation`: (index into points,
    residuals r (K,), Jacobians J (6, K) of the point-to-plane residual against the plane (m, n),
    G (6, K), the residual's derivative along the interpolated surface itself, and weights (K,),
    the inverse of each residual's variance under the sensor's random noise)."""
    index, q, m, n, along, kept = target.surface_at(points @ transformation[:3, :3].T + transformation[:3, 3],
                                                    inlier_distance)
    ray = np.abs(np.einsum("jk,jk->k", n, q)) / q[2]  # the residual per unit of axial (z) noise
    sigma_q, sigma_m = SENSOR.sigma(q[2]), SENSOR.sigma(m[2])
    weight = 1.0 / (ray**2 * (sigma_q**2 + kept * sigma_m**2))
    return index, np.einsum("jk,jk->k", q - m, n), _moment_jacobian(q, n), _moment_jacobian(q, along), weight


def _residuals(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float) -> dict:
    """Point-to-plane residuals of `transformation` both ways: source points against the target
    surface and target points against the source surface (the two snap to pixels in opposite
    directions, so their sub-pixel biases cancel), all with respect to a perturbation exp(xi) X
    in the target camera's frame. Returns a dict: r (K,), J (6, K), G (6, K), w (weights, K),
    tile (each residual's tile of the image it was sampled in, K); `forward` (the source
    points' residuals, m), `depth` (their source depths, m) and `samples` (the source samples' count)."""
    out = {key: [] for key in ("r", "J", "G", "w", "tile")}
    for a, b, T, sign in ((source, target, transformation, 1.0), (target, source, np.linalg.inv(transformation), -1.0)):
        points, _ = a.samples
        keep, r, jac, along, weight = _correspondences(points, b, T, inlier_distance)
        if sign > 0:
            out.update(forward=r, depth=points[keep, 2], samples=len(points))
        else:  # back into the target frame: d r / d xi = -[p x R a, R a] for p in the target frame
            R, p = transformation[:3, :3], points[keep].T
            jac = -_moment_jacobian(p, R @ jac[3:])
            along = -_moment_jacobian(p, R @ along[3:])
        for key, value in zip(("r", "J", "G", "w", "tile"), (r, jac, along, weight, a.sample_tiles[keep])):
            out[key].append(value)
    return {key: np.concatenate(value, axis=-1) if isinstance(value, list) else value for key, value in out.items()}


def refine(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
           misregistration_rad: float = 0.0, misregistration_per_squared_motion: float = 0.0, iterations: int = 6,
           frame_steps: list[np.ndarray] | None = None) -> Fit:
    """`transformation` (4, 4, source camera -> target camera) refined by Newton steps of the
    weighted point-to-plane alignment both ways with sub-pixel association (the root of
    sum_i w_i J_i r_i = 0); stops before a step below STOP_FRACTION of the answer's own standard
    deviation on every axis (its covariance: see :func:`_fit`; `frame_steps` too).
    Returns the :class:`Fit` of the answer (iterations=0: of `transformation` itself, see :func:`fit`).

    On real depth the Newton matrix overstates the curvature (the slopes of the interpolated
    surface carry the pixels' noise), so successive steps point the same way, each a fraction rho
    of the one before; a step is then lengthened by 1 / (1 - rho) (Aitken's extrapolation of the
    geometric series), which reaches the root in about half the iterations."""
    T = np.asarray(transformation, np.float64).copy()
    previous = None
    for k in range(iterations + 1):
        res = _residuals(source, target, T, inlier_distance)
        result = _fit(T, res, misregistration_rad, misregistration_per_squared_motion, frame_steps)
        if k == iterations or not result.usable:
            break
        step = -result.bread @ (res["J"] @ (res["w"] * res["r"]))
        if np.all(np.abs(step) < STOP_FRACTION * np.sqrt(np.diag(result.covariance))):
            break
        if previous is not None:
            rho = float(step @ previous / (previous @ previous))
            step = step / (1 - rho) if 0 < rho < MAX_RATIO else step
        T = twist_matrix(step) @ T
        previous = step
    return result


def fit(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
        misregistration_rad: float = 0.0, misregistration_per_squared_motion: float = 0.0,
        frame_steps: list[np.ndarray] | None = None) -> Fit:
    """The :class:`Fit` of `transformation` (4, 4, source camera -> target camera) between two
    frames, as it is (:func:`refine` without a step)."""
    return refine(source, target, transformation, inlier_distance, misregistration_rad,
                  misregistration_per_squared_motion, iterations=0, frame_steps=frame_steps)


def misregistration_covariance(rad: float, depth: float) -> np.ndarray:
    """(6, 6) diagonal covariance [rotation, translation] of a misregistration of `rad` about each
    axis and that angle times `depth` (m) along each axis."""
    return np.diag([rad**2] * 3 + [(rad * depth) ** 2] * 3)


def motion_rad(transformation: np.ndarray, depth: float) -> float:
    """How far a (4, 4) relative pose moves the image, as an angle (rad): its rotation angle plus
    its translation over the scene's `depth` (m)."""
    moved_m, turned_deg = motion(transformation)
    return float(np.radians(turned_deg) + moved_m / depth)


def _fit(transformation: np.ndarray, res: dict, misregistration_rad: float, misregistration_per_squared_motion: float,
         frame_steps: list[np.ndarray] | None) -> Fit:
    """The Fit of `transformation` from its residuals (:func:`_residuals`).

    Its covariance is RESIDUAL_INFLATION^2 times the sandwich estimate of the root of
    sum_i w_i J_i r_i = 0 (what :func:`refine` solves), A^-1 B A^-T with A = sum_i w_i J_i G_i^T
    (G_i: the residual's derivative with m following the interpolated surface; J_i alone would
    take the noisy normals for the surface's slope), plus the misregistration floor: rotation
    std `misregistration_rad + misregistration_per_squared_motion * m^2` about each axis and
    translation std that angle times the median inlier depth (what a real sensor's calibration
    leaves, and its motion blur, rolling shutter and wrong minima, which grow faster than the
    camera's motion while it takes the frames: no residual shows them). m is the mean :func:`motion_rad` of the relative
    poses in `frame_steps` (each frame's step from the frame before it: for frames that are not
    consecutive, a loop closure), or of `transformation` itself (None or empty: the frames' step
    when they are consecutive, a bound when they are not)."""
    inliers = len(res["forward"])
    overlap = inliers / max(res["samples"], 1)
    failed = np.full((6, 6), np.inf)
    if inliers < MIN_INLIERS:
        return Fit(transformation, overlap, np.inf, inliers, failed, failed, failed)
    rms = float(np.sqrt(np.mean(res["forward"]**2)))
    tiles = TILES[0] * TILES[1]
    weighted = res["w"] * res["r"]
    scores = np.stack([np.bincount(res["tile"], row * weighted, tiles) for row in res["J"]])  # (6, tiles)
    used = np.count_nonzero(np.bincount(res["tile"], minlength=tiles))
    meat = scores @ scores.T * used / max(used - 1, 1)
    try:
        bread = np.linalg.inv((res["J"] * res["w"]) @ res["G"].T)
    except np.linalg.LinAlgError:
        return Fit(transformation, overlap, rms, inliers, failed, failed, failed)
    residual_covariance = RESIDUAL_INFLATION**2 * (bread @ meat @ bread.T)
    residual_covariance = 0.5 * (residual_covariance + residual_covariance.T)
    depth = float(np.median(res["depth"]))
    steps = frame_steps or [transformation]
    motion = float(np.mean([motion_rad(T, depth) for T in steps]))
    rad = misregistration_rad + misregistration_per_squared_motion * motion**2
    covariance = residual_covariance + misregistration_covariance(rad, depth)
    return Fit(transformation, overlap, rms, inliers, covariance, bread, residual_covariance, depth)
