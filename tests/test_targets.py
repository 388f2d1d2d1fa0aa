"""Tests of open3d_pnerf.targets on a fronto-parallel plane seen by sideways-shifted cameras.

Scene (tests/conftest.py): 64x48 pixels, fx = fy = 50, principal point (32, 24) exactly on a
pixel, the world plane z = z0 = 2 m, three identity-rotation cameras at x = -0.04, 0, +0.04.
One 0.04 m step shifts the plane by fx * 0.04 / z0 = 1 pixel, so neighbours reproject onto
whole pixels at exactly z0 and every expected value below is analytic.
"""

from __future__ import annotations

import types

import numpy as np
import pytest

from open3d_pnerf.camera import ray_norms
from open3d_pnerf.errors import InputError, PoseError
from open3d_pnerf.targets import DepthTargets, SensorNoise, TargetsConfig, depth_targets

Z0 = 2.0
CENTRE = (24, 32)  # (row, col) of the principal point
S = SensorNoise().sigma(Z0)  # sensor sigma at z0
RANDOM_ONLY = SensorNoise(relative=0.0)  # the fusion algebra below is exact without the systematic term


def targets(seq, poses, **kw) -> DepthTargets:
    kw.setdefault("progress", False)
    kw.setdefault("sensor", RANDOM_ONLY)
    return depth_targets(seq, poses=poses, **kw)


def test_sensor_noise_model():
    noise = SensorNoise()
    assert noise.sigma(np.float64(0.4)) == pytest.approx(0.0012)
    assert noise.sigma(np.float64(1.4)) == pytest.approx(0.0012 + 0.0019)
    np.testing.assert_allclose(SensorNoise(a=0.0, b=1.0, c=0.0).sigma(np.array([[1.0, 2.0]])), [[1.0, 4.0]])
    np.testing.assert_allclose(SensorNoise(relative=0.02).systematic_var(np.array([1.0, 2.0])), [0.02**2, 0.04**2])


def test_systematic_error_is_added_after_fusion(plane_scene):
    """Random noise averages over the fused views (S^2 / support); the systematic part, the
    same in every view, does not: sigma^2 = S^2 / support + (relative z0)^2 exactly."""
    seq, poses = plane_scene(Z0)
    t = targets(seq, poses, sensor=SensorNoise(relative=0.01))
    support = t.support.astype(float)
    assert support.max() == 3
    np.testing.assert_allclose(t.sigma, np.sqrt(S**2 / support + (0.01 * Z0) ** 2), rtol=1e-5)
    np.testing.assert_allclose(t.mean, Z0, atol=1e-4)  # the mean does not move
    default = depth_targets(seq, poses=poses, progress=False)  # SensorNoise() has relative = 0.02
    np.testing.assert_allclose(default.sigma, np.sqrt(S**2 / support + (0.02 * Z0) ** 2), rtol=1e-5)
    # a reconstruction's targets are twice as wide in that term (TargetsConfig, a training choice)
    wide = TargetsConfig().build(seq, poses, np.zeros((len(poses), 6, 6)), progress=False)
    np.testing.assert_allclose(wide.sigma, np.sqrt(S**2 / support + (0.04 * Z0) ** 2), rtol=1e-5)


def test_ray_norms():
    K = np.array([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]])
    n = ray_norms(K, 48, 64)
    assert n.shape == (48, 64) and n.dtype == np.float32
    assert n[24, 32] == 1.0
    for v, u in [(0, 0), (47, 63), (24, 0), (5, 32)]:
        x, y = (u - 32.0) / 50.0, (v - 24.0) / 40.0
        assert n[v, u] == pytest.approx(np.sqrt(x * x + y * y + 1), rel=1e-6)
    assert n.min() == 1.0


def test_plane_mean_support_and_sigma_without_pose_uncertainty(plane_scene):
    seq, poses = plane_scene(Z0)
    t = targets(seq, poses)
    assert len(t) == 3 and t.image_size == (48, 64)
    assert t.valid.all() and not t.filled.any()
    np.testing.assert_allclose(t.mean, Z0, atol=1e-4)
    # support per column: frame 0 (x=-0.04) gets frame 1 shifted by 1 px and frame 2 by 2 px
    np.testing.assert_array_equal(t.support[0, 0, :4], [1, 2, 3, 3])
    np.testing.assert_array_equal(t.support[0, 0, -2:], [3, 3])
    np.testing.assert_array_equal(t.support[1, 0, [0, 1, 62, 63]], [2, 3, 3, 2])
    assert (t.support[:, :, :] == t.support[:, :1, :]).all()  # no vertical shift
    # equal variances fused by inverse variance: sigma / sqrt(support)
    np.testing.assert_allclose(t.sigma, S / np.sqrt(t.support.astype(float)), rtol=1e-5)
    assert t.mean.dtype == np.float32 and t.sigma.dtype == np.float32 and t.support.dtype == np.uint8
    summary = t.summary()
    assert summary["valid_fraction"] == 1.0 and summary["filled_fraction"] == 0.0
    assert 2.9 < summary["mean_support"] < 3.0


def test_no_neighbours_gives_the_sensor_sigma(plane_scene):
    seq, poses = plane_scene(Z0)
    t = targets(seq, poses, neighbors=0)
    assert (t.support == 1).all()
    np.testing.assert_allclose(t.sigma, S, rtol=1e-6)
    assert t.summary()["sigma_mm_p5_p50_p95"] == pytest.approx([S * 1000] * 3, abs=0.01)


def test_trajectory_argument_equals_poses(plane_scene):
    seq, poses = plane_scene(Z0)
    covs = np.zeros((3, 6, 6))
    covs[:, 5, 5] = 1e-4
    a = targets(seq, poses, covariances=covs)
    trajectory = types.SimpleNamespace(poses=poses, covariances=covs)
    b = depth_targets(seq, trajectory, sensor=RANDOM_ONLY, progress=False)
    for name in ("mean", "sigma", "valid", "support", "filled"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_own_pose_term_is_translation_along_the_ray(plane_scene):
    seq, poses = plane_scene(Z0)
    S_t = np.array([[4e-4, 1e-4, 2e-5], [1e-4, 9e-4, -3e-5], [2e-5, -3e-5, 1e-4]])
    covs = np.zeros((3, 6, 6))
    covs[:, 3:, 3:] = S_t
    covs[:, :3, :3] = np.diag([0.1, 0.2, 0.3])  # own rotation: no effect along own rays
    t = targets(seq, poses, covariances=covs, neighbors=0)
    K = seq.K
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    r = d / np.linalg.norm(d, axis=-1, keepdims=True)
    pose_var = np.einsum("hwi,ij,hwj->hw", r, S_t, r) * r[..., 2] ** 2
    np.testing.assert_allclose(t.sigma[1] ** 2, S**2 + pose_var, rtol=1e-5)
    # at the centre pixel r = (0, 0, 1): r^T S_tt r r_z^2 = S[5, 5]
    assert t.sigma[1][CENTRE] ** 2 == pytest.approx(S**2 + 1e-4, rel=1e-5)
    np.testing.assert_allclose(t.mean, Z0, atol=1e-4)


def test_pose_covariance_enlarges_sigma_analytically(plane_scene):
    seq, poses = plane_scene(Z0)
    base = targets(seq, poses)
    s55 = 1e-4  # 1 cm translation std along z for every frame
    covs = np.zeros((3, 6, 6))
    covs[:, 5, 5] = s55
    t = targets(seq, poses, covariances=covs)
    assert (t.sigma > base.sigma).all()
    np.testing.assert_allclose(t.mean, Z0, atol=1e-4)
    np.testing.assert_array_equal(t.support, base.support)
    # centre of frame 1: own obs var S^2, each neighbour S^2 + s55 (its pose along the ray),
    # fused by inverse variance, then the own pose term s55 added once
    fused = 1.0 / (1.0 / S**2 + 2.0 / (S**2 + s55))
    assert t.sigma[1][CENTRE] ** 2 == pytest.approx(fused + s55, rel=1e-5)


def test_neighbour_rotation_covariance_is_projected_with_the_lever_arm(plane_scene):
    seq, poses = plane_scene(Z0)
    covs = np.zeros((3, 6, 6))
    covs[:, 1, 1] = 0.01  # rotation about y: moves a point at x = +-0.04 m along z by x * dtheta
    t = targets(seq, poses, covariances=covs)
    nb = S**2 + 0.01 * 0.04**2  # the neighbour's point sits 0.04 m off its optical axis
    fused = 1.0 / (1.0 / S**2 + 2.0 / nb)
    assert t.sigma[1][CENTRE] ** 2 == pytest.approx(fused, rel=1e-5)  # own rotation adds nothing


def test_outlier_neighbour_is_rejected(plane_scene):
    def edit(depths):
        depths[2][:] = Z0 + 0.5

    seq, poses = plane_scene(Z0, edit=edit)
    clean = targets(*plane_scene(Z0))
    t = targets(seq, poses)
    np.testing.assert_allclose(t.mean[1], Z0, atol=1e-4)
    assert t.valid[1].all()
    # frame 1 keeps only its own depth and frame 0's
    assert (t.support[1, :, 1:63] == 2).all() and (clean.support[1, :, 1:63] == 3).all()
    np.testing.assert_allclose(t.sigma[1], S / np.sqrt(t.support[1].astype(float)), rtol=1e-5)
    # frame 2 keeps its own (wrong) depth: both neighbours disagree with it
    np.testing.assert_allclose(t.mean[2], Z0 + 0.5, atol=1e-4)
    assert (t.support[2] == 1).all()


def test_holes_are_filled_from_two_neighbours(plane_scene):
    hole = (slice(22, 27), slice(30, 35))

    def edit(depths):
        depths[1][hole] = 0

    seq, poses = plane_scene(Z0, edit=edit)
    t = targets(seq, poses)
    assert t.filled[1][hole].all() and t.valid[1][hole].all()
    assert t.filled.sum() == 25  # only the hole
    np.testing.assert_allclose(t.mean[1][hole], Z0, atol=1e-4)
    assert (t.support[1][hole] == 2).all()
    # no own measurement: sigma above that of the neighbouring pixels with own depth
    np.testing.assert_allclose(t.sigma[1][hole], S / np.sqrt(2), rtol=1e-5)
    assert t.sigma[1][CENTRE] > t.sigma[1][CENTRE[0], 40] == pytest.approx(S / np.sqrt(3), rel=1e-5)
    # requiring three views leaves the hole empty
    strict = targets(seq, poses, fill_min_views=3)
    assert not strict.valid[1][hole].any() and not strict.filled.any()
    assert (strict.mean[1][hole] == 0).all() and (strict.sigma[1][hole] == 0).all()
    assert (strict.support[1][hole] == 0).all()


def test_storage_dir_memmaps_equal_in_memory(plane_scene, tmp_path):
    seq, poses = plane_scene(Z0)
    ram = targets(seq, poses)
    disk = targets(seq, poses, storage_dir=tmp_path / "targets")
    for name in ("mean", "sigma", "valid", "support", "filled"):
        arr = getattr(disk, name)
        assert isinstance(arr, np.memmap)
        np.testing.assert_array_equal(arr, getattr(ram, name))
        assert arr.dtype == getattr(ram, name).dtype
        np.testing.assert_array_equal(np.load(tmp_path / "targets" / f"{name}.npy"), getattr(ram, name))


def test_bad_inputs(plane_scene):
    seq, poses = plane_scene(Z0)
    with pytest.raises(InputError, match="poses"):
        depth_targets(seq, progress=False)
    with pytest.raises(InputError, match=r"covariances.*\(3, 6, 6\).*\(3, 3, 3\)"):
        targets(seq, poses, covariances=np.zeros((3, 3, 3)))
    nan = np.zeros((3, 6, 6))
    nan[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="covariances"):
        targets(seq, poses, covariances=nan)
    with pytest.raises(PoseError, match="2 poses for 3 frames"):
        targets(seq, poses[:2])
    with pytest.raises(InputError, match="neighbors"):
        targets(seq, poses, neighbors=-1)
    with pytest.raises(InputError, match="fill_min_views"):
        targets(seq, poses, fill_min_views=0)
    with pytest.raises(InputError, match="relative >= 0"):
        targets(seq, poses, sensor=SensorNoise(relative=-0.01))
    with pytest.raises(InputError, match="SensorNoise"):
        targets(seq, poses, sensor=0.02)


def test_rotated_cameras_reproject_with_camera_to_world_poses(plane_scene):
    # toe-in cameras at x = -0.2, 0, 0.2 all looking at (0, 0, z0): the rotated ones see the
    # plane tilted. Neighbour points lie on the plane, so in the unrotated middle camera they
    # reproject to exactly z0, and only with the right pose convention.
    seq0, _ = plane_scene(Z0)
    K = seq0.K
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    poses, pairs = [], []
    for x in (-0.2, 0.0, 0.2):
        th = np.arctan2(-x, Z0)  # rotation about y turning the optical axis towards x = 0
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]]
        pose[0, 3] = x
        world_dz = d @ pose[:3, :3].T
        depth = (Z0 - pose[2, 3]) / world_dz[..., 2]  # ray-plane intersection, z-depth
        poses.append(pose)
        pairs.append((np.zeros((48, 64, 3), np.uint8), depth.astype(np.float32)))
    poses = np.stack(poses)
    assert np.allclose(poses[0, :3, :3] @ [0, 0, 1], [0.2, 0, 2] / np.hypot(0.2, 2))  # looks at the centre
    from open3d_pnerf.data import RGBDSequence

    seq = RGBDSequence.from_rgbd_images(pairs, seq0.intrinsic)
    t = targets(seq, poses)
    block = (slice(8, 40), slice(16, 48))
    # forward splatting leaves a few gaps where a tilted neighbour's pixels spread out
    assert (t.support[1][block] >= 2).all() and (t.support[1][block] == 3).mean() > 0.8
    np.testing.assert_allclose(t.mean[1], Z0, atol=1e-5)
    for i in (0, 2):  # pixel rounding of reprojected points costs < 0.5 px x depth gradient
        assert (t.support[i][block] >= 2).all() and (t.support[i][block] == 3).mean() > 0.8
        np.testing.assert_allclose(t.mean[i][block], pairs[i][1][block], atol=3e-3)
    # the inverse convention (world-to-camera poses) makes the neighbours inconsistent
    wrong = targets(seq, np.linalg.inv(poses))
    assert (wrong.support[1][block] == 3).mean() < 0.1
