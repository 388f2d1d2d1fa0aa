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
smaller and their refinement longer: 40.7 against 37.1 ms a frame with 0.15 on 7-Scenes 150-199 at
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
        frame.samples, frame.depth_normals  # what every registration uses, computed now (prefetching: off the main thread)
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
    def depth_normals(self) -> np.ndarray:
        """(H * W, 4): each pixel's depth (zero where it has no normal) and normal, for one look-up
        of a bilinear cell's corners."""
        n = self.normals
        has_normal = (n[..., 0] != 0) | (n[..., 1] != 0) | (n[..., 2] != 0)
        return np.concatenate([(self.depth * has_normal)[..., None], self.normals], 2).reshape(-1, 4)

    def surface_at(self, q: np.ndarray, max_step: float):
        """The surface under camera-frame points q (M, 3), bilinearly interpolated at each point's
        sub-pixel projection, for those points whose four neighbouring pixels all have depth and
        normals, within max_step (m) or JUMP times the depth of each other (not across a depth
        discontinuity): their indices into q (K,), points m and unit normals n (K, 3); `along`
        (K, 3), the derivative of n . (q - m) with respect to q when m follows the interpolated
        surface (n itself on a plane that the normals describe exactly); the (K,) sum of the squared
        interpolation weights (1 on a pixel, 1/4 between four: how much of one pixel's noise the
        interpolated depth keeps)."""
        h, w = self.depth.shape
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        z = q[:, 2]
        ahead = z > 1e-6
        u = np.divide(q[:, 0], z, out=np.zeros_like(z), where=ahead) * fx + cx
        v = np.divide(q[:, 1], z, out=np.zeros_like(z), where=ahead) * fy + cy
        u0, v0 = np.floor(u), np.floor(v)
        index = np.flatnonzero(ahead & (u0 >= 0) & (u0 < w - 1) & (v0 >= 0) & (v0 < h - 1))
        corner = (v0[index] * w + u0[index]).astype(np.int64)
        # (4 channels [depth, n], 4 corners (u, v), (u + 1, v), (u, v + 1), (u + 1, v + 1), K)
        cell = np.take(self.depth_normals, corner + np.array([0, 1, w, w + 1])[:, None], axis=0).transpose(2, 0, 1).copy()
        d = cell[0]
        low = np.minimum(np.minimum(d[0], d[1]), np.minimum(d[2], d[3]))
        high = np.maximum(np.maximum(d[0], d[1]), np.maximum(d[2], d[3]))
        good = np.flatnonzero((low > 0) & (high - low < np.maximum(max_step, JUMP * low)))
        index, cell = index[good], cell[:, :, good]
        d, q, z, u, v = cell[0], q[index], z[index], u[index], v[index]
        a, b = u - u0[index], v - v0[index]
        weights = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])  # (4 corners, K)
        depth, *normal = (cell * weights).sum(1)
        ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], 1)
        m = ray * depth[:, None]
        n = np.stack(normal, 1)
        n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-12)[:, None]
        n_ray = np.einsum("ij,ij->i", n, ray)
        slope_u = n_ray * ((d[1] - d[0]) * (1 - b) + (d[3] - d[2]) * b) + n[:, 0] * depth / fx  # n . dm/du
        slope_v = n_ray * ((d[2] - d[0]) * (1 - a) + (d[3] - d[1]) * a) + n[:, 1] * depth / fy  # n . dm/dv
        along = n.copy()  # n - (n . dm/du) du/dq - (n . dm/dv) dv/dq
        along[:, 0] -= slope_u * fx / z
        along[:, 1] -= slope_v * fy / z
        along[:, 2] += (slope_u * fx * q[:, 0] + slope_v * fy * q[:, 1]) / z**2
        return index, m, n, along, (weights**2).sum(0)


def _correspondences(points: np.ndarray, target: DepthFrame, transformation: np.ndarray, inlier_distance: float):
    """Inlier correspondences of source points (M, 3) moved by `transformation`: (index into points,
    residuals r (K,), Jacobians J (K, 6) of the point-to-plane residual against the plane (m, n),
    G (K, 6), the residual's derivative along the interpolated surface itself, and weights (K,),
    the inverse of each residual's variance under the sensor's random noise)."""
    q = points @ transformation[:3, :3].T + transformation[:3, 3]
    index, m, n, along, kept = target.surface_at(q, inlier_distance)
    q = q[index]
    d = q - m
    close = np.flatnonzero(np.einsum("ij,ij->i", d, d) < inlier_distance**2)
    index, q, m, n, d, along, kept = index[close], q[close], m[close], n[close], d[close], along[close], kept[close]
    ray = np.abs(np.einsum("ij,ij->i", n, q)) / q[:, 2]  # the residual per unit of axial (z) noise
    sigma_q, sigma_m = SENSOR.sigma(q[:, 2]), SENSOR.sigma(m[:, 2])
    weight = 1.0 / (ray**2 * (sigma_q**2 + kept * sigma_m**2))
    return (index, np.einsum("ij,ij->i", d, n), np.concatenate([np.cross(q, n), n], 1),
            np.concatenate([np.cross(q, along), along], 1), weight)


def _residuals(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float) -> dict:
    """Point-to-plane residuals of `transformation` both ways: source points against the target
    surface and target points against the source surface (the two snap to pixels in opposite
    directions, so their sub-pixel biases cancel), all with respect to a perturbation exp(xi) X
    in the target camera's frame. Returns a dict: r (K,), J (K, 6), G (K, 6), w (weights, K),
    tile (each residual's tile of the image it was sampled in, K); `forward` (the source
    points' residuals, m), `depth` (their source depths, m) and `samples` (the source samples' count)."""
    out = {key: [] for key in ("r", "J", "G", "w", "tile")}
    for a, b, T, sign in ((source, target, transformation, 1.0), (target, source, np.linalg.inv(transformation), -1.0)):
        points, flat = a.samples
        keep, r, jac, along, weight = _correspondences(points, b, T, inlier_distance)
        if sign > 0:
            out.update(forward=r, depth=points[keep, 2], samples=len(points))
        else:  # back into the target frame: d r / d xi = -[p x R a, R a] for p in the target frame
            R = transformation[:3, :3]
            p = points[keep]
            nrm, alg = jac[:, 3:] @ R.T, along[:, 3:] @ R.T
            jac = -np.concatenate([np.cross(p, nrm), nrm], 1)
            along = -np.concatenate([np.cross(p, alg), alg], 1)
        h, w = a.depth.shape
        v, u = np.divmod(flat[keep], w)
        for key, value in zip(("r", "J", "G", "w", "tile"),
                              (r, jac, along, weight, (v * TILES[1] // h) * TILES[0] + u * TILES[0] // w)):
            out[key].append(value)
    return {key: np.concatenate(value) if isinstance(value, list) else value for key, value in out.items()}


def refine(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
           misregistration_rad: float = 0.0, misregistration_per_motion: float = 0.0, iterations: int = 6,
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
        result = _fit(T, res, misregistration_rad, misregistration_per_motion, frame_steps)
        if k == iterations or not result.usable:
            break
        step = -result.bread @ (res["J"].T @ (res["w"] * res["r"]))
        if np.all(np.abs(step) < STOP_FRACTION * np.sqrt(np.diag(result.covariance))):
            break
        if previous is not None:
            rho = float(step @ previous / (previous @ previous))
            step = step / (1 - rho) if 0 < rho < MAX_RATIO else step
        T = twist_matrix(step) @ T
        previous = step
    return result


def fit(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
        misregistration_rad: float = 0.0, misregistration_per_motion: float = 0.0,
        frame_steps: list[np.ndarray] | None = None) -> Fit:
    """The :class:`Fit` of `transformation` (4, 4, source camera -> target camera) between two
    frames, as it is (:func:`refine` without a step)."""
    return refine(source, target, transformation, inlier_distance, misregistration_rad, misregistration_per_motion,
                  iterations=0, frame_steps=frame_steps)


def misregistration_covariance(rad: float, depth: float) -> np.ndarray:
    """(6, 6) diagonal covariance [rotation, translation] of a misregistration of `rad` about each
    axis and that angle times `depth` (m) along each axis."""
    return np.diag([rad**2] * 3 + [(rad * depth) ** 2] * 3)


def motion_rad(transformation: np.ndarray, depth: float) -> float:
    """How far a (4, 4) relative pose moves the image, as an angle (rad): its rotation angle plus
    its translation over the scene's `depth` (m)."""
    moved_m, turned_deg = motion(transformation)
    return float(np.radians(turned_deg) + moved_m / depth)


def _fit(transformation: np.ndarray, res: dict, misregistration_rad: float, misregistration_per_motion: float,
         frame_steps: list[np.ndarray] | None) -> Fit:
    """The Fit of `transformation` from its residuals (:func:`_residuals`).

    Its covariance is RESIDUAL_INFLATION^2 times the sandwich estimate of the root of
    sum_i w_i J_i r_i = 0 (what :func:`refine` solves), A^-1 B A^-T with A = sum_i w_i J_i G_i^T
    (G_i: the residual's derivative with m following the interpolated surface; J_i alone would
    take the noisy normals for the surface's slope), plus the misregistration floor: rotation
    std `misregistration_rad + misregistration_per_motion * m` about each axis and translation
    std that angle times the median inlier depth (what a real sensor's calibration leaves, and
    its colour/depth timing and rolling shutter, which grow with the camera's motion while it
    takes the frames: no residual shows them). m is the mean :func:`motion_rad` of the relative
    poses in `frame_steps` (each frame's step from the frame before it: for frames that are not
    consecutive, a loop closure), or of `transformation` itself (None or empty: the frames' step
    when they are consecutive, a bound when they are not)."""
    inliers = len(res["forward"])
    overlap = inliers / max(res["samples"], 1)
    failed = np.full((6, 6), np.inf)
    if inliers < MIN_INLIERS:
        return Fit(transformation, overlap, np.inf, inliers, failed, failed, failed)
    rms = float(np.sqrt(np.mean(res["forward"]**2)))
    terms = res["J"] * (res["w"] * res["r"])[:, None]
    used, tile = np.unique(res["tile"], return_inverse=True)
    scores = np.stack([np.bincount(tile, terms[:, j], len(used)) for j in range(6)], 1)
    meat = scores.T @ scores * len(used) / max(len(used) - 1, 1)
    try:
        bread = np.linalg.inv(res["J"].T @ (res["G"] * res["w"][:, None]))
    except np.linalg.LinAlgError:
        return Fit(transformation, overlap, rms, inliers, failed, failed, failed)
    residual_covariance = RESIDUAL_INFLATION**2 * (bread @ meat @ bread.T)
    residual_covariance = 0.5 * (residual_covariance + residual_covariance.T)
    depth = float(np.median(res["depth"]))
    steps = frame_steps or [transformation]
    rad = misregistration_rad + misregistration_per_motion * float(np.mean([motion_rad(T, depth) for T in steps]))
    covariance = residual_covariance + misregistration_covariance(rad, depth)
    return Fit(transformation, overlap, rms, inliers, covariance, bread, residual_covariance, depth)
