"""Sparse SfM points as uncertain depth targets (issue 7): the ray-restricted Gaussian on closed-form
cases, sparse_depth_targets on three cameras with analytic sigmas, and the shared LLFF fern scene.

Scene: 64x48 pixels, fx = fy = 50, principal point (32, 24) on a pixel; identity-rotation
cameras at x = 0, +0.2, -0.2. Every point below projects exactly onto a pixel centre, so the
pixel's ray passes through it and the expected sigma has a closed form.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from open3d_pnerf.data import read_llff
from open3d_pnerf.errors import InputError, PoseError
from open3d_pnerf.targets import gaussian_along_ray, sparse_depth_targets


def test_gaussian_along_ray_isotropic_is_the_projection_with_the_same_sigma():
    rng = np.random.default_rng(0)
    origin, point = rng.normal(size=(5, 3)), rng.normal(size=(5, 3)) * 3
    d = rng.normal(size=(5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = np.array([0.1, 0.5, 1.0, 2.0, 3.0])
    t, var = gaussian_along_ray(origin, d, point, s[:, None, None] ** 2 * np.eye(3))
    np.testing.assert_allclose(t, ((point - origin) * d).sum(1), rtol=1e-12)
    np.testing.assert_allclose(var, s**2, rtol=1e-12)


@pytest.mark.parametrize("phi_deg", [0.0, 20.0, 60.0, 90.0])
def test_gaussian_along_ray_elongated_along_z_seen_by_a_tilted_ray(phi_deg):
    """S = diag(a^2, a^2, b^2); the ray d = (sin phi, 0, cos phi) passes p + (delta, 0, 0) at t0:
    1/var = sin^2 phi / a^2 + cos^2 phi / b^2 and t* = t0 - delta sin(phi) / a^2 * var."""
    a, b, t0, delta = 0.1, 2.0, 5.0, 0.03
    phi = np.radians(phi_deg)
    d = np.array([np.sin(phi), 0.0, np.cos(phi)])
    p = np.array([0.3, -0.2, 7.0])
    origin = p + [delta, 0, 0] - t0 * d
    t, var = gaussian_along_ray(origin, d, p, np.diag([a * a, a * a, b * b]))
    expected_var = 1 / (np.sin(phi) ** 2 / a**2 + np.cos(phi) ** 2 / b**2)
    assert var == pytest.approx(expected_var, rel=1e-12)
    assert t == pytest.approx(t0 - delta * np.sin(phi) / a**2 * expected_var, rel=1e-12)
    if phi_deg == 0:  # along the long axis: the depth sigma itself
        assert var == pytest.approx(b * b) and t == pytest.approx(t0)


# -- three cameras, seven points ----------------------------------------------------------------
K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
H, W = 48, 64
CAMERA_X = [0.0, 0.2, -0.2]
POINTS = {  # name: (xyz, reprojection error px, observing cameras)
    "A": ((0.0, 0.0, 2.0), 0.5, [0, 1, 2]),  # centre pixel of camera 0
    "C": ((0.4, 0.0, 2.0), 1.0, [0, 1]),  # pixel (42, 24) of camera 0, (37, 24) of camera 1
    "D": ((0.0, 0.0, 4.0), 0.5, [0, 1]),  # behind A on camera 0's centre pixel
    "E": ((0.0, 0.0, -1.0), 0.5, [0, 1]),  # behind the cameras
    "F": ((5.0, 0.0, 2.0), 0.5, [0, 1]),  # outside the images
    "G": ((0.0, 0.2, 2.0), 0.5, [0]),  # seen by one camera only: no triangulation angle
    "H": ((-0.2, 0.2, 2.0), 0.5, [1, 2]),  # pixel (27, 29) of camera 0, which does not observe it
}


def scene():
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = CAMERA_X
    xyz = np.array([p[0] for p in POINTS.values()])
    error = np.array([p[1] for p in POINTS.values()])
    observed = np.zeros((len(POINTS), 3), bool)
    for k, (_, _, cams) in enumerate(POINTS.values()):
        observed[k, cams] = True
    return poses, xyz, error, observed


def pose_covariances():
    """Camera 0: rotation variance (moves no point along its own rays) and an anisotropic
    camera-frame translation covariance; camera 1: isotropic translation; camera 2: none."""
    covs = np.zeros((3, 6, 6))
    covs[0, :3, :3] = 1e-2 * np.eye(3)
    covs[0, 3:, 3:] = np.diag([0.02, 0.03, 0.05]) ** 2
    covs[1, 3:, 3:] = 0.04**2 * np.eye(3)
    return covs


def test_sparse_targets_analytic_sigma_weight_and_visibility():
    poses, xyz, error, observed = scene()
    t = sparse_depth_targets(poses, K, (H, W), xyz, error, observed, covariances=pose_covariances())
    assert len(t) == 3 and t.image_size == (H, W)
    assert t.mean.dtype == np.float32 and t.sigma.dtype == np.float32 and not t.filled.any()
    weight = np.exp(-((error / error.mean()) ** 2))  # DS-NeRF's, kept as a weight: sigma is not widened

    # camera 0: A (nearest on the centre pixel, D behind it) and C; E, F, G and H give nothing
    assert sorted(zip(*np.nonzero(t.valid[0]))) == [(24, 32), (24, 42)]
    sin_a = 0.2 / np.hypot(0.2, 2.0)  # either other camera, seen from A
    s_dep_a = 0.5 * 2.0 / 50 / sin_a
    assert t.mean[0, 24, 32] == pytest.approx(2.0, rel=1e-6)
    assert t.sigma[0, 24, 32] == pytest.approx(np.sqrt(s_dep_a**2 + 0.05**2), rel=1e-5)
    assert t.support[0, 24, 32] == 3 and t.support[0, 24, 42] == 2
    assert t.mean[0, 24, 42] == pytest.approx(2.0, rel=1e-6)

    # camera 1 sees C on pixel (37, 24): angle to camera 0 is atan(0.2) - atan(0.1); isotropic pose cov
    sin_c = np.sin(np.arctan(0.2) - np.arctan(0.1))
    s_dep_c = 1.0 * 2.0 / 50 / sin_c
    d_z = 2.0 / np.hypot(0.2, 2.0)
    assert t.mean[1, 24, 37] == pytest.approx(2.0, rel=1e-6)
    assert t.sigma[1, 24, 37] == pytest.approx(np.sqrt(s_dep_c**2 + 0.04**2) * d_z, rel=1e-5)
    # H is a target in cameras 1 and 2 (which observe it), at its pixel
    assert t.valid[1, 29, 22] and t.valid[2, 29, 32] and not t.valid[0, 29, 27]
    # the badly fitting point C (error 1.0 vs mean 0.57) gets the smaller weight
    assert t.weight[0, 24, 32] == pytest.approx(weight[0]) and t.weight[0, 24, 42] == pytest.approx(weight[1])
    assert t.weight[1, 24, 37] == pytest.approx(weight[1]) and weight[1] < 0.25 * weight[0]
    assert (t.weight[~t.valid] == 0).all()
    # the points project onto pixel centres, but D in camera 1 (u = 32 - 0.2 / 4 * 50 = 29.5)
    np.testing.assert_allclose(t.offset[1, 24, 30], [-0.5, 0.0])
    t.offset[1, 24, 30] = 0
    assert np.abs(t.offset).max() < 1e-9


def test_sparse_target_rays_go_through_the_exact_distorted_projection():
    """A point projecting between pixel centres, with radial distortion: its target sits at the
    pixel its distorted projection rounds to, with that projection's offset, and the ray through
    the exact spot gives the point's z-depth (the pixel centre's ray would miss it)."""
    poses, _, _, _ = scene()
    xyz = np.array([[0.31, -0.17, 2.0], [-0.23, 0.21, 2.5]])
    observed = np.ones((2, 3), bool)
    k1, k2 = -0.1, 0.02
    t = sparse_depth_targets(poses, K, (H, W), xyz, np.array([0.5, 0.5]), observed, radial=(k1, k2))
    for k, p in enumerate(xyz):
        x, y = p[0] / p[2], p[1] / p[2]
        f = 1 + k1 * (x * x + y * y) + k2 * (x * x + y * y) ** 2
        u, v = 50 * x * f + 32, 50 * y * f + 24
        col, row = round(u), round(v)
        assert t.valid[0, row, col], (k, u, v)
        np.testing.assert_allclose(t.offset[0, row, col], [u - col, v - row], atol=1e-5)
        assert abs(u - col) > 0.05 or abs(v - row) > 0.05  # really off-centre
        assert t.mean[0, row, col] == pytest.approx(p[2], abs=0.05)  # near the point's depth
    assert t.valid.sum() == 6


def test_sparse_targets_do_not_depend_on_the_world_frame():
    """Moving the world by a rigid G (poses G T, points G p) leaves every target unchanged: the
    camera-frame pose covariances must be rotated into the world, not used as they are."""
    poses, xyz, error, observed = scene()
    g = np.eye(4)
    g[:3, :3] = Rotation.from_euler("xyz", [30, -50, 70], degrees=True).as_matrix()
    g[:3, 3] = [1.0, -2.0, 0.5]
    t = sparse_depth_targets(poses, K, (H, W), xyz, error, observed, covariances=pose_covariances())
    moved = sparse_depth_targets(g @ poses, K, (H, W), xyz @ g[:3, :3].T + g[:3, 3], error, observed,
                                 covariances=pose_covariances())
    np.testing.assert_array_equal(moved.valid, t.valid)
    np.testing.assert_allclose(moved.mean, t.mean, rtol=1e-5)
    np.testing.assert_allclose(moved.sigma, t.sigma, rtol=1e-5)


def test_sparse_targets_min_angle_and_bad_input():
    poses, xyz, error, observed = scene()
    # A's angle is 5.7 deg, C's (seen from camera 1) 5.6 deg: a 6 deg minimum drops both
    t = sparse_depth_targets(poses, K, (H, W), xyz, error, observed, min_angle_deg=6.0)
    assert not t.valid[0].any() and not t.valid[1, 24, 37]
    with pytest.raises(InputError, match=r"observed must be a bool \(M, N\) = \(7, 3\)"):
        sparse_depth_targets(poses, K, (H, W), xyz, error, observed[:, :2])
    with pytest.raises(InputError, match="error >= 0"):
        sparse_depth_targets(poses, K, (H, W), xyz, -error, observed)
    with pytest.raises(InputError, match=r"xyz must be finite \(M, 3\)"):
        sparse_depth_targets(poses, K, (H, W), xyz[:, :2], error, observed)
    bad = poses.copy()
    bad[1, :3, :3] *= 2
    with pytest.raises(PoseError, match="sparse_depth_targets\\(\\): poses are not rigid"):
        sparse_depth_targets(bad, K, (H, W), xyz, error, observed)


@pytest.mark.data
def test_fern_sparse_targets(shared_data):
    fern = read_llff(shared_data / "llff_fern" / "nerf_llff_data" / "fern", factor=8, scale=1.0)
    pts = fern.sfm.points
    t = sparse_depth_targets(fern.sfm.poses, fern.K, fern.image_size, pts.xyz, pts.error, pts.observed)
    assert t.image_size == (378, 504) and len(t) == 20
    per_image = t.valid.sum((1, 2))
    assert (per_image > 0.5 * pts.observed.sum(0)).all()  # most points get their own pixel
    for i in range(len(t)):
        z = t.mean[i][t.valid[i]]
        near, far = fern.sfm.bounds[i]
        assert np.mean((z > 0.9 * near) & (z < 1.1 * far)) > 0.99
    relative = t.sigma[t.valid] / t.mean[t.valid]
    assert np.isfinite(relative).all() and (relative > 0).all()
    assert 1e-4 < np.median(relative) < 0.05
    # COLMAP's SIMPLE_RADIAL k1 is read, and the targets sit off the pixel centres where their points are seen
    k1, k2 = fern.sfm.radial
    assert k2 == 0 and k1 != 0 and abs(k1) < 0.1
    offset = np.abs(t.offset[t.valid])
    assert offset.max() <= 0.5 + 1e-6 and np.median(offset) > 0.1
    assert ((t.weight[t.valid] > 0) & (t.weight[t.valid] <= 1)).all()
