"""Point-to-plane refinement of a registration, how well it fits and how uncertain it is, from
the two frames' depth images and the residuals themselves.

Open3D's RGB-D odometry associates a source pixel with the target pixel nearest to its projection.
That snapping leaves each registration up to a fraction of a pixel off in a way no residual shows
(on the synthetic room at 320x240 the answers of one frame pair under independent noise draws
fall in two clusters 2.4 mrad apart, ten times the spread the noise explains). :func:`refine`
therefore finishes every registration with Gauss-Newton steps of a point-to-plane alignment that
interpolates the target depth and normals at the projection's sub-pixel position, and
:func:`fit` scores the result the same way.

Open3D's information matrix ``G^T G`` counts correspondences as independent measurements, so
its covariance shrinks as 1 / (number of pixels) although neighbouring pixels' depth errors are
far from independent, and it says nothing about how well the frames actually fit. Here the
covariance is the cluster-robust ("sandwich", Huber-White) estimate of the point-to-plane
alignment at its answer:

    Cov(xi) = H^-1 B H^-1,  H = sum_i J_i^T J_i,  B = G / (G - 1) sum_g s_g s_g^T,  s_g = sum_{i in g} J_i^T r_i

over the inlier correspondences i (a source pixel's point q_i moved by the transformation,
against the target surface m_i, n_i where it projects), r_i = n_i . (q_i - m_i) their
point-to-plane residuals and J_i = [q_i x n_i, n_i] (the residual's derivative with respect to
a perturbation exp(xi) X, [rotation, translation], in the target camera's frame: the frame of
the pose graph's edge residual, see covariance.py). The clusters g are tiles of the source
image (a fixed grid, so the estimate does not depend on the processing resolution): residuals
that are correlated within a tile (smooth depth-sensor errors, calibration, blur) count as one
measurement per tile, and a misfit (a wrong registration) inflates B and the covariance.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np


from ..camera import backproject, rotation_matrix
from ..targets.noise import SensorNoise

TILES = (16, 12)  # columns x rows of the source image's clusters
MAX_POINTS = 10_000  # pixels sampled per image (a regular grid)
MIN_INLIERS = 200
SENSOR = SensorNoise()  # the random depth noise that weighs each residual
RESIDUAL_INFLATION = 1.3
"""The sandwich covariance's standard deviations times this: the sub-pixel association leaves a
bias that no residual shows."""
JUMP = 0.05  # neighbouring depths further apart than this fraction of the depth: a discontinuity


@dataclasses.dataclass(frozen=True)
class Fit:
    """How a transformation aligns two depth images.

    overlap: fraction of the source's valid sampled pixels with an inlier correspondence;
    residual_rms: RMS point-to-plane residual of the inliers (m); inliers: their number;
    covariance: (6, 6) sandwich covariance of the transformation ([rotation, translation],
    left perturbation in the target camera frame), infinite diagonal when degenerate.
    """

    overlap: float
    residual_rms: float
    inliers: int
    covariance: np.ndarray

    @property
    def usable(self) -> bool:
        return self.inliers >= MIN_INLIERS and bool(np.isfinite(self.covariance).all())


def surface_normals(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals of a z-depth image (H, W) m with intrinsic K, pointing towards the
    camera, zero where a neighbour has no depth: from central differences of the depth,
    n ~ (fx z_u, fy z_v, -(z + (u - cx) z_u + (v - cy) z_v)) (the cross product of the two
    tangents of the back-projected surface)."""
    h, w = depth.shape
    z_u = np.zeros_like(depth)
    z_v = np.zeros_like(depth)
    z_u[:, 1:-1] = (depth[:, 2:] - depth[:, :-2]) / 2
    z_v[1:-1] = (depth[2:] - depth[:-2]) / 2
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


def point_image(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of a z-depth image (zeros where depth is 0)."""
    h, w = depth.shape
    pts, flat = backproject(depth, K)
    out = np.zeros((h * w, 3))
    out[flat] = pts
    return out.reshape(h, w, 3)


@dataclasses.dataclass(frozen=True)
class DepthFrame:
    """One frame's geometry for point-to-plane alignment: z-depth (H, W) m, its camera-frame
    points and unit normals (H, W, 3) (point_image, surface_normals), intrinsic K (3, 3) and the
    depth beyond which it is ignored (m)."""

    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    K: np.ndarray
    max_depth: float

    @classmethod
    def of(cls, depth: np.ndarray, K: np.ndarray, max_depth: float) -> "DepthFrame":
        depth = np.where((depth > 0) & (depth < max_depth), depth, 0.0)
        return cls(depth, point_image(depth, K), surface_normals(depth, K), np.asarray(K, np.float64), float(max_depth))

    @functools.cached_property
    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (M, 3) of a regular grid of at most MAX_POINTS valid pixels, and
        their flat pixel indices (M,)."""
        h, w = self.depth.shape
        stride = max(1, int(np.sqrt(h * w / MAX_POINTS)))
        mask = np.zeros((h, w), bool)
        mask[::stride, ::stride] = True
        return backproject(self.depth, self.K, mask=mask & (self.depth > 0))

    def surface_at(self, q: np.ndarray, max_step: float):
        """The surface under camera-frame points q (M, 3), bilinearly interpolated at each point's
        sub-pixel projection: points m and unit normals n (M, 3); the (M,) mask of those whose
        four neighbouring pixels all have depth and normals, within max_step (m) or JUMP times the
        depth of each other (not across a depth discontinuity); `along` (M, 3), the derivative of
        n . (q - m) with respect to q when m follows the interpolated surface (n itself on a plane
        that the normals describe exactly); and the (M,) sum of the squared interpolation weights
        (1 on a pixel, 1/4 between four: how much of one pixel's noise the interpolated depth keeps)."""
        h, w = self.depth.shape
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        ok = q[:, 2] > 1e-6
        z = np.where(ok, q[:, 2], 1.0)
        u, v = q[:, 0] / z * fx + cx, q[:, 1] / z * fy + cy
        u0, v0 = np.floor(u), np.floor(v)
        ok &= (u0 >= 0) & (u0 < w - 1) & (v0 >= 0) & (v0 < h - 1)
        corner = np.where(ok, v0 * w + u0, 0).astype(np.int64)
        corners = np.stack([corner, corner + 1, corner + w, corner + w + 1])  # (4, M): 00, 01 (u + 1), 10, 11
        a, b = np.where(ok, u - u0, 0.0), np.where(ok, v - v0, 0.0)
        weights = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
        d = self.depth.ravel()[corners]
        normals = self.normals.reshape(-1, 3)[corners]
        ok &= (d > 0).all(0) & (d.max(0) - d.min(0) < np.maximum(max_step, JUMP * d.min(0)))
        ok &= (np.abs(normals).sum(-1) > 0).all(0)
        depth = (weights * d).sum(0)
        ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], 1)
        m = ray * depth[:, None]
        n = (weights[..., None] * normals).sum(0)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n_ray = (n * ray).sum(1)
        slope_u = n_ray * ((d[1] - d[0]) * (1 - b) + (d[3] - d[2]) * b) + n[:, 0] * depth / fx  # n . dm/du
        slope_v = n_ray * ((d[2] - d[0]) * (1 - a) + (d[3] - d[1]) * a) + n[:, 1] * depth / fy  # n . dm/dv
        along = n.copy()  # n - (n . dm/du) du/dq - (n . dm/dv) dv/dq
        along[:, 0] -= slope_u * fx / z
        along[:, 1] -= slope_v * fy / z
        along[:, 2] += (slope_u * fx * q[:, 0] + slope_v * fy * q[:, 1]) / z**2
        return m, n, ok, along, (weights**2).sum(0)


def _correspondences(points: np.ndarray, target: DepthFrame, transformation: np.ndarray, inlier_distance: float):
    """Inlier correspondences of source points (M, 3) moved by `transformation`: (index into points,
    residuals r (K,), Jacobians J (K, 6) of the point-to-plane residual against the plane (m, n),
    G (K, 6), the residual's derivative along the interpolated surface itself, and weights (K,),
    the inverse of each residual's variance under the sensor's random noise)."""
    q = points @ transformation[:3, :3].T + transformation[:3, 3]
    m, n, ok, along, kept = target.surface_at(q, inlier_distance)
    d = q - m
    ok &= np.einsum("ij,ij->i", d, d) < inlier_distance**2
    keep = np.flatnonzero(ok)
    q, n, d, along = q[keep], n[keep], d[keep], along[keep]
    ray = np.abs((n * q).sum(1)) / q[:, 2]  # the residual per unit of axial (z) noise
    sigma_q, sigma_m = SENSOR.sigma(q[:, 2]), SENSOR.sigma(m[keep, 2])
    weight = 1.0 / (ray**2 * (sigma_q**2 + kept[keep] * sigma_m**2))
    return (keep, (d * n).sum(1), np.concatenate([np.cross(q, n), n], 1),
            np.concatenate([np.cross(q, along), along], 1), weight)


def _residuals(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float):
    """Point-to-plane residuals of `transformation` both ways: source points against the target
    surface and target points against the source surface (the two snap to pixels in opposite
    directions, so their sub-pixel biases cancel). Returns r (K,), J (K, 6), G (K, 6), weights (K,)
    and each residual's tile of the image it was sampled in (K,), all with respect to a
    perturbation exp(xi) X in the target camera's frame; and the source samples' count and overlap."""
    out = []
    for a, b, T, sign in ((source, target, transformation, 1.0), (target, source, np.linalg.inv(transformation), -1.0)):
        points, flat = a.samples
        keep, r, jac, along, weight = _correspondences(points, b, T, inlier_distance)
        if sign < 0:  # back into the target frame: d r / d xi = -[p x R a, R a] for p in the target frame
            R = transformation[:3, :3]
            p = points[keep]
            nrm, alg = jac[:, 3:] @ R.T, along[:, 3:] @ R.T
            jac = -np.concatenate([np.cross(p, nrm), nrm], 1)
            along = -np.concatenate([np.cross(p, alg), alg], 1)
        h, w = a.depth.shape
        v, u = np.divmod(flat[keep], w)
        out.append((r, jac, along, weight, (v * TILES[1] // h) * TILES[0] + u * TILES[0] // w, len(points),
                    points[keep, 2]))
    return out


def refine(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
           iterations: int = 6, tolerance: float = 1e-5) -> np.ndarray:
    """`transformation` (4, 4, source camera -> target camera) refined by Newton steps of the
    weighted point-to-plane alignment both ways with sub-pixel association (the root of
    sum_i w_i J_i r_i = 0), until a step is below `tolerance` (rad / m)."""
    T = np.asarray(transformation, np.float64).copy()
    for _ in range(iterations):
        parts = _residuals(source, target, T, inlier_distance)
        r, jac, along, weight = (np.concatenate([p[k] for p in parts]) for k in range(4))
        if len(r) < 2 * MIN_INLIERS:
            break
        try:
            step = -np.linalg.solve(jac.T @ (along * weight[:, None]), jac.T @ (weight * r))
        except np.linalg.LinAlgError:
            break
        T = _exp(step) @ T
        if np.abs(step).max() < tolerance:
            break
    return T


def _exp(xi: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform of a small twist [rotation, translation] (rotation exact, translation first order)."""
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(xi[:3])
    T[:3, 3] = xi[3:]
    return T


def fit(source: DepthFrame, target: DepthFrame, transformation: np.ndarray, inlier_distance: float,
        misregistration_rad: float = 0.0) -> Fit:
    """The :class:`Fit` of `transformation` (4, 4, source camera -> target camera) between two frames.

    Its covariance is RESIDUAL_INFLATION^2 times the sandwich estimate of the root of
    sum_i w_i J_i r_i = 0 (what :func:`refine` solves), A^-1 B A^-T with A = sum_i w_i J_i G_i^T
    (G_i: the residual's derivative with m following the interpolated surface; J_i alone would
    take the noisy normals for the surface's slope), plus the misregistration floor: rotation
    std `misregistration_rad` about each axis and translation std that angle times the median
    inlier depth (what a real sensor's calibration and colour/depth timing leave and no residual shows)."""
    parts = _residuals(source, target, transformation, inlier_distance)
    forward = parts[0]
    overlap = len(forward[0]) / max(forward[5], 1)
    r, jac, along, weight, tile = (np.concatenate([p[k] for p in parts]) for k in range(5))
    if len(forward[0]) < MIN_INLIERS:
        return Fit(overlap, np.inf, len(forward[0]), np.full((6, 6), np.inf))
    scores = np.zeros((TILES[0] * TILES[1], 6))
    np.add.at(scores, tile, jac * (weight * r)[:, None])
    used = np.unique(tile)
    meat = scores[used].T @ scores[used] * len(used) / max(len(used) - 1, 1)
    rms = float(np.sqrt(np.mean(forward[0]**2)))
    try:
        bread = np.linalg.inv(jac.T @ (along * weight[:, None]))
    except np.linalg.LinAlgError:
        return Fit(overlap, rms, len(forward[0]), np.full((6, 6), np.inf))
    covariance = RESIDUAL_INFLATION**2 * (bread @ meat @ bread.T)
    depth = float(np.median(forward[6]))
    covariance += np.diag([misregistration_rad**2] * 3 + [(misregistration_rad * depth) ** 2] * 3)
    return Fit(overlap, rms, len(forward[0]), 0.5 * (covariance + covariance.T))
