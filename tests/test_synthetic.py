"""Tests of open3d_pnerf.synthetic: exact renders of the room scene, the depth-noise model,
determinism, pose noise, look_at and the visible ground-truth surface.

Geometry of room_scene(seed=0) used below (room 4 x 5 x 2.6 m centred on the origin, floor
z = 0): the table spans x in [-0.48, 0.92], y in [-0.38, 0.43] (top at z = 0.775), the boxes
stand in the corners (x, y) ~ (-1.2, 1.5), (1.3, -1.4), (1.3, 1.7), the big sphere at
(-1.2, -1.4). The floor rectangle x in [-1.9, -0.6], y in [-1.0, 1.2] is free.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from open3d_pnerf.camera import check_poses
from open3d_pnerf.errors import InputError
from open3d_pnerf.synthetic import DepthNoise, look_at, room_scene, synthetic_sequence
from open3d_pnerf.targets import SensorNoise
from open3d_pnerf.tsdf import TSDFVolume

W, H = 320, 240
FREE_FLOOR = ((-1.9, -0.6), (-1.0, 1.2))  # (x range, y range) of floor free of furniture


def kinect_intrinsic(w=W, h=H) -> o3d.camera.PinholeCameraIntrinsic:
    """The intrinsic synthetic_sequence uses: focal 0.82 * width, centre (w - 1) / 2."""
    f = 0.82 * w
    return o3d.camera.PinholeCameraIntrinsic(w, h, f, f, (w - 1) / 2, (h - 1) / 2)


def camera_rays(intrinsic) -> np.ndarray:
    """(H, W, 3) K^-1 [u, v, 1] with pixel centres at integers (camera axes, unit z)."""
    K = np.asarray(intrinsic.intrinsic_matrix)
    v, u = np.mgrid[0:intrinsic.height, 0:intrinsic.width]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)


def distance_to(mesh: o3d.geometry.TriangleMesh, points: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()


@pytest.fixture(scope="module")
def scene():
    return room_scene(seed=0)


@pytest.fixture(scope="module")
def wall_view(scene):
    """Render of a camera at (0, 0, 1.3) looking along +x at the wall x = 2."""
    return scene.render(look_at((0, 0, 1.3), (1, 0, 1.3)), kinect_intrinsic())


# -- exact renders -----------------------------------------------------------------------------------
def test_upper_half_of_a_view_at_a_wall_has_its_exact_z_depth(wall_view):
    # Rays of the upper half rise at most 119.5 / 262.4 = 0.46 m per m: they reach the wall
    # x = 2 below z = 2.21 (ceiling 2.6) and within |y| <= 1.22 (walls at 2.5); nothing of
    # height >= 1.3 stands in the field of view. A plane perpendicular to the optical axis
    # has one z-depth everywhere: 2.0 m (not the ray length).
    depth, cos = wall_view["depth"], wall_view["cos_incidence"]
    assert depth.shape == (H, W) and depth.dtype == np.float32
    np.testing.assert_allclose(depth[:H // 2], 2.0, atol=1e-5)
    # the wall's normal is the optical axis: |cos| = 1 / ||K^-1 [u, v, 1]||
    rays = camera_rays(kinect_intrinsic())
    np.testing.assert_allclose(cos[:H // 2], 1 / np.linalg.norm(rays[:H // 2], axis=-1), atol=1e-5)
    color = wall_view["color"]
    assert color.shape == (H, W, 3) and color.dtype == np.float32
    assert 0 <= color.min() and color.max() <= 1 and color[:H // 2].std() > 0.01  # textured, not flat


def test_floor_seen_straight_down_has_the_camera_height_as_depth(scene):
    # straight down from 1.2 m the 58 x 45 deg view covers x in [-1.85, -0.75], y in [-0.6, 0.8]: free floor
    pose = look_at((-1.3, 0.1, 1.2), (-1.3, 0.1, 0.0), up=(1, 0, 0))
    out = scene.render(pose, kinect_intrinsic())
    np.testing.assert_allclose(out["depth"], 1.2, atol=1e-5)
    np.testing.assert_allclose(out["cos_incidence"], 1 / np.linalg.norm(camera_rays(kinect_intrinsic()), axis=-1),
                               atol=1e-5)


def test_oblique_floor_depth_follows_the_pixel_centre_convention(scene):
    # A slanted surface changes depth from pixel to pixel: a ray through (u + 0.5, v + 0.5)
    # instead of (u, v) (Open3D's own pinhole rays) would be off by ~1e-3 relative.
    pose = look_at((-1.3, 0.0, 1.2), (-1.3, 1.0, 0.0))
    intrinsic = kinect_intrinsic()
    d_world = camera_rays(intrinsic) @ pose[:3, :3].T
    t = np.where(d_world[..., 2] < 0, -1.2 / np.minimum(d_world[..., 2], -1e-9), np.inf)  # unit camera z: t = z-depth
    hit = pose[:3, 3] + d_world * t[..., None]
    (x0, x1), (y0, y1) = FREE_FLOOR
    free = (x0 < hit[..., 0]) & (hit[..., 0] < x1) & (y0 < hit[..., 1]) & (hit[..., 1] < y1)
    assert free.sum() > 20_000  # rays to free floor cannot be blocked: the furniture stands outside it
    depth = scene.render(pose, intrinsic)["depth"]
    np.testing.assert_allclose(depth[free], t[free], rtol=2e-5)


def test_frames_are_the_exact_render_without_noise(scene):
    data = synthetic_sequence(4, 64, 48, noise=DepthNoise.none(), color_noise=0.0)
    seq = data.sequence
    K = seq.K
    assert K[0, 0] == K[1, 1] == pytest.approx(0.82 * 64) and (K[0, 2], K[1, 2]) == (31.5, 23.5)
    for i in range(len(seq)):
        frame = seq[i]
        out = data.scene.render(seq.gt_poses[i], seq.intrinsic)
        exact = np.where((out["depth"] >= 0.4) & (out["depth"] <= 5.0), out["depth"], 0)  # range_m still applies
        np.testing.assert_array_equal(frame.depth, exact)
        np.testing.assert_array_equal(frame.color, (out["color"] * 255 + 0.5).astype(np.uint8))
    assert data.mesh.has_triangles() and len(data.scene.parts) == len(data.scene.albedo) == 12


# -- the depth-noise model -------------------------------------------------------------------------------
def test_noise_on_a_wall_is_unbiased_quantised_and_has_the_model_spread(wall_view):
    noise = DepthNoise()
    depth, cos = wall_view["depth"][:H // 2], wall_view["cos_incidence"][:H // 2]  # 38,400 pixels at 2.0 m
    out = noise.apply(depth, cos, np.random.default_rng(0))
    assert out.shape == depth.shape and out.dtype == np.float32
    valid = out > 0
    # no grazing pixels (|cos| >= 0.8) and no depth jumps on this plane: only random dropout
    assert abs((~valid).mean() - noise.dropout) < 0.003  # binomial std 0.0005
    err = out[valid] - 2.0
    sigma = float(noise.sigma(2.0))
    assert sigma == pytest.approx(0.0012 + 0.0019 * 1.6**2)
    q = 2.0**2 / noise.disparity_step  # quantisation step at 2 m: 12.7 mm
    assert abs(err.mean()) < 5e-4
    assert sigma <= err.std() <= 1.2 * np.sqrt(sigma**2 + q**2 / 12)
    disparity = noise.disparity_step / out[valid]  # every value is step / integer
    np.testing.assert_allclose(disparity, np.round(disparity), atol=1e-3)


@pytest.mark.parametrize("z", [1.0, 3.0])
def test_axial_noise_without_quantisation_has_std_sigma_z(z):
    noise = DepthNoise(disparity_step=0.0, dropout=0.0, edge_dropout=0.0)
    out = noise.apply(np.full((200, 200), z, np.float32), np.ones((200, 200)), np.random.default_rng(1))
    assert (out > 0).all()
    assert abs(out.mean() - z) < 3 * noise.sigma(z) / 200
    assert out.std() == pytest.approx(noise.sigma(z), rel=0.02)


def test_grazing_and_out_of_range_pixels_are_missing():
    noise = DepthNoise()
    depth = np.full((100, 100), 2.0, np.float32)
    cos = np.ones((100, 100))
    cos[:, :50] = 0.1  # below grazing_cos = 0.15
    out = noise.apply(depth, cos, np.random.default_rng(2))
    assert (out[:, :50] == 0).all()
    assert (out[:, 50:] > 0).mean() > 0.95
    # exact depth (DepthNoise.none()) still drops what the sensor cannot measure
    z = np.array([[0.3, 0.41, 2.0, 4.99, 5.2, 0.0]], np.float32)
    exact = DepthNoise.none().apply(z, np.ones((1, 6)), np.random.default_rng(0))
    np.testing.assert_array_equal(exact, z * [[0, 1, 1, 1, 0, 0]])
    # beyond range_m with the default noise
    far = noise.apply(np.full((20, 20), 6.0, np.float32), np.ones((20, 20)), np.random.default_rng(3))
    assert (far == 0).all()


def test_pixels_next_to_a_depth_jump_drop_out_with_edge_dropout():
    noise = DepthNoise(sensor=SensorNoise(a=0.0, b=0.0), disparity_step=0.0, grazing_cos=0.0, dropout=0.0, edge_dropout=0.5)
    depth = np.full((400, 40), 2.0, np.float32)
    depth[:, :20] = 1.0  # a 1 m jump between columns 19 and 20
    out = noise.apply(depth, np.ones_like(depth), np.random.default_rng(4))
    edge = np.zeros(depth.shape, bool)
    edge[:, 19:21] = True
    assert (out[~edge] == depth[~edge]).all()  # elsewhere exact
    assert abs((out[edge] == 0).mean() - 0.5) < 0.05  # 800 pixels, binomial std 0.018


def test_sequence_frames_miss_grazing_and_out_of_range_pixels():
    data = synthetic_sequence(6, 80, 60, seed=3)
    seq = data.sequence
    for i in range(len(seq)):
        out = data.scene.render(seq.gt_poses[i], seq.intrinsic)
        depth = seq[i].depth
        assert (depth[out["cos_incidence"] < 0.15] == 0).all()
        assert (depth[(out["depth"] < 0.3) | (out["depth"] > 5.5)] == 0).all()
        valid = depth > 0
        assert valid.mean() > 0.8
        # noise stays within a few sigma plus a quantisation step
        z = out["depth"][valid]
        assert (np.abs(depth[valid] - z) < 5 * DepthNoise().sigma(z) + z**2 / DepthNoise().disparity_step).all()


# -- determinism and poses -------------------------------------------------------------------------------
def test_frames_are_deterministic_per_seed():
    a, b = synthetic_sequence(6, 64, 48, seed=1), synthetic_sequence(6, 64, 48, seed=1)
    c = synthetic_sequence(6, 64, 48, seed=2)
    for i in (0, 5):
        f1, f2, f3 = a.sequence[i], a.sequence[i], b.sequence[i]
        np.testing.assert_array_equal(f1.depth, f2.depth)  # reading twice gives the same frame
        np.testing.assert_array_equal(f1.color, f2.color)
        np.testing.assert_array_equal(f1.depth, f3.depth)  # a second sequence with the same seed too
        np.testing.assert_array_equal(f1.color, f3.color)
        assert not np.array_equal(f1.depth, c.sequence[i].depth)
        assert not np.array_equal(f1.color, c.sequence[i].color)
    assert not np.array_equal(a.sequence[1].depth, a.sequence[2].depth)
    np.testing.assert_array_equal(a.sequence.gt_poses, b.sequence.gt_poses)


def test_camera_path_is_rigid_inside_the_room_and_looks_inwards():
    data = synthetic_sequence(40, 32, 24)
    gt = data.sequence.gt_poses
    check_poses(gt, 40)  # rigid, finite
    eyes = gt[:, :3, 3]
    assert (np.abs(eyes[:, 0]) < 2.0).all() and (np.abs(eyes[:, 1]) < 2.5).all()
    assert ((eyes[:, 2] > 1.2) & (eyes[:, 2] < 1.6)).all()
    assert (np.einsum("ni,ni->n", gt[:, :3, 2], -eyes * [1, 1, 0]) > 0).all()  # facing the room's centre
    np.testing.assert_allclose(np.diff(data.sequence.timestamps), 1 / 30)
    np.testing.assert_array_equal(data.poses, gt)  # pose_noise=(0, 0): poses are exact
    assert (data.covariances == 0).all() and data.covariances.shape == (40, 6, 6)


def test_pose_noise_has_the_requested_spread_and_covariance():
    rot_std, trans_std = 0.01, 0.02
    data = synthetic_sequence(500, 16, 12, pose_noise=(rot_std, trans_std))
    gt, poses = data.sequence.gt_poses, data.poses
    check_poses(poses, 500)
    rel_rot = np.transpose(gt[:, :3, :3], (0, 2, 1)) @ poses[:, :3, :3]  # right perturbation
    rotvec = Rotation.from_matrix(rel_rot).as_rotvec()
    trans = np.einsum("nji,nj->ni", gt[:, :3, :3], poses[:, :3, 3] - gt[:, :3, 3])  # in the camera frame
    for err, std in ((rotvec, rot_std), (trans, trans_std)):
        assert np.abs(err.mean(0)).max() < 4 * std / np.sqrt(500)
        np.testing.assert_allclose(err.std(0), std, rtol=0.25)
    expected = np.diag([rot_std**2] * 3 + [trans_std**2] * 3)
    assert data.covariances.shape == (500, 6, 6)
    np.testing.assert_allclose(data.covariances, np.broadcast_to(expected, (500, 6, 6)), rtol=1e-12)


# -- look_at ---------------------------------------------------------------------------------------------
def test_look_at_points_the_optical_axis_at_the_target_with_opencv_axes():
    eye, target = np.array([0.3, -0.2, 1.4]), np.array([1.0, 0.5, 0.7])
    pose = look_at(eye, target)
    R = pose[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], (target - eye) / np.linalg.norm(target - eye))
    assert R[2, 0] == pytest.approx(0.0, abs=1e-12)  # x axis horizontal
    assert R[2, 1] < 0  # y axis points down
    np.testing.assert_array_equal(pose[:3, 3], eye)
    np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
    # the target projects to the principal point; a point above it to a smaller row
    K = np.asarray(kinect_intrinsic().intrinsic_matrix)
    project = lambda p: (K @ (R.T @ (p - eye)))[:2] / (R.T @ (p - eye))[2]  # noqa: E731
    np.testing.assert_allclose(project(target), K[:2, 2], atol=1e-9)
    assert project(target + [0, 0, 0.1])[1] < K[1, 2]
    # looking along +x: x right is world -y
    np.testing.assert_allclose(look_at((0, 0, 1), (1, 0, 1))[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)


def test_look_at_rejects_degenerate_directions():
    with pytest.raises(InputError, match="parallel to up"):
        look_at((0, 0, 1), (0, 0, 0))  # straight down with up = z
    with pytest.raises(InputError, match="zero"):
        look_at((1, 2, 3), (1, 2, 3))
    assert np.isfinite(look_at((0, 0, 1), (0, 0, 0), up=(1, 0, 0))).all()


# -- visible ground-truth surface ----------------------------------------------------------------------
def test_visible_points_lie_on_the_mesh_and_only_where_cameras_look(scene):
    intrinsic = kinect_intrinsic(160, 120)
    wall = look_at((0, 0, 1.3), (1, 0, 1.3))
    oblique = look_at((0.5, 0.5, 1.5), (1.5, 1.8, 0.3))
    cloud = scene.visible_points(wall[None], intrinsic)
    pts = np.asarray(cloud.points)
    assert len(pts) > 5000
    assert distance_to(scene.mesh, pts).max() < 1e-4
    assert pts[:, 0].min() > 0  # the camera looks along +x with a 58 deg view: nothing behind it
    assert (np.abs(pts[:, 0] - 2.0) < 1e-4).sum() > 2000  # the wall in front is there
    # one exact hit point per 1 cm voxel
    cells = np.floor(pts / 0.01).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(pts)
    # a slanted view: points still exactly on the surface (pixel centres at integers)
    both = np.asarray(scene.visible_points(np.stack([wall, oblique]), intrinsic).points)
    assert distance_to(scene.mesh, both).max() < 1e-4
    assert len(both) > len(pts) + 2000
    assert len(np.unique(np.floor(both / 0.01).astype(np.int64), axis=0)) == len(both)


def test_tsdf_fusion_of_exact_synthetic_depth_renders_the_exact_depth():
    # Exact depth and poses: the fused surface renders within a fraction of a voxel of the
    # input depth. Open3D reads pixel floor(u) for a voxel projecting to u; without shifting
    # the principal point by half a pixel, oblique surfaces move by half a pixel's depth
    # change (median error 8.7 mm here instead of 1.6 mm).
    data = synthetic_sequence(4, 160, 120, noise=DepthNoise.none(), color_noise=0.0)
    seq = data.sequence
    volume = TSDFVolume(0.02, 0.08, 6.0, weight_threshold=0.5)
    for i in range(len(seq)):
        frame = seq[i]
        volume.integrate(frame.color, frame.depth, seq.K, seq.gt_poses[i])
    out = volume.render(seq.gt_poses[0], seq.K, 160, 120)
    exact = seq[0].depth
    both = out["hit"] & (exact > 0)
    assert both.mean() > 0.9
    assert np.median(np.abs(out["depth"][both] - exact[both])) < 0.004


# -- bad input -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, match", [
    (dict(n_frames=0), "n_frames"),
    (dict(width=4), "8x8"),
    (dict(pose_noise=(-0.01, 0.0)), "pose_noise"),
    (dict(pose_noise=(0.01,)), "pose_noise"),
    (dict(pose_noise=0.01), "pose_noise"),
    (dict(pose_noise=(0.01, float("nan"))), "pose_noise"),
])
def test_synthetic_sequence_rejects_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        synthetic_sequence(**{"n_frames": 4, **kwargs})
