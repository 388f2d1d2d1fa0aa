"""Occupancy, free space and distance from the views' depth laws: analytic scenes (a plane, a sphere in a
room) whose depth maps are exact, the files OctoMap and Open3D read back, bad arguments, and the
real pipeline on a trained reconstruction."""

import numpy as np
import open3d as o3d
import pytest

from open3d_pnerf.error_law import DepthErrorLaw
from open3d_pnerf.errors import ConfigError, InputError
from open3d_pnerf.occupancy import OccupancyGrid, SensorModel, ViewEvidence, grid_frame, signed_distance

SENSOR = SensorModel(hit=1.5, miss=-0.5, grazing=0.0, low=-4.0, high=4.0)  # OctoMap's model: no grazing discount


def test_the_sensor_model_discounts_the_passes_of_a_voxel_views_end_in_and_clamps():
    sensor = SensorModel(hit=0.5, miss=-1.0, grazing=10.0, low=-2.0, high=2.0)
    hits, passes = np.array([0.0, 1.0, 0.2, 10.0, 0.0, 0.01]), np.array([2.0, 2.0, 0.0, 0.0, 5.0, 0.01])
    np.testing.assert_allclose(sensor.log_odds(hits, passes), [-2.0, 0.5 - 2.0 / 11, 0.1, 2.0, -2.0, 0.0],
                               rtol=1e-6)  # free, grazed, hit, clamped high and low, unseen (below MIN_EVIDENCE)


def look_at(eye, target) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`, world z up."""
    forward = np.asarray(target, float) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    pose[:3, 3] = eye
    return pose


def camera(width=40, height=30, f=30.0) -> np.ndarray:
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])


def views_of(depths, poses, K, sigma: float, law=DepthErrorLaw()) -> ViewEvidence:
    depths = np.asarray(depths, float)
    return ViewEvidence(np.asarray(poses), K, depths, np.full(depths.shape, sigma), np.ones(depths.shape), law)


def plane_grid(sigma: float, voxel: float = 0.1) -> OccupancyGrid:
    """One camera at the origin looking along +z at the plane z = 2.03 (inside the voxels [2.0, 2.1))."""
    K = camera()
    views = views_of([np.full((30, 40), 2.03)], [np.eye(4)], K, sigma)
    origin, shape = grid_frame(voxel, np.array([[-1.5, -1.5, 0.0], [1.5, 1.5, 3.0]]), None)
    return views.grid(origin, shape, voxel, SENSOR)


def test_a_plane_seen_by_one_camera_is_free_in_front_occupied_on_it_and_unknown_behind_and_aside():
    grid = plane_grid(sigma=0.005)
    axis = np.array([[0.05, 0.05, z] for z in (0.55, 1.05, 1.85, 2.05, 2.15, 2.55)])
    p = grid.probability(axis)
    np.testing.assert_allclose(p[:3], 1 / (1 + np.exp(0.5)), atol=1e-6)  # one view's pass: the miss weight
    np.testing.assert_allclose(p[3], 1 / (1 + np.exp(-1.5)), atol=1e-3)  # one view's hit: the hit weight
    np.testing.assert_array_equal(p[4:], 0.5)  # behind the plane: the view says nothing
    assert grid.probability(np.array([[1.45, 0.05, 0.55]]))[0] == 0.5  # outside the view (30 px over 30 f)
    assert grid.unknown()[14, 14, 25] and not grid.unknown()[15, 15, 20]
    assert grid.probability(np.array([[0.05, 0.05, 9.0]]))[0] == 0.5  # outside the grid


def test_a_wider_depth_law_makes_the_plane_less_certain_near_it_not_far_from_it():
    sure, unsure = plane_grid(sigma=0.005), plane_grid(sigma=0.15)
    near, far, on = np.array([[0.05, 0.05, 1.85]]), np.array([[0.05, 0.05, 0.55]]), np.array([[0.05, 0.05, 2.05]])
    assert sure.probability(near) < unsure.probability(near) < 0.5  # may be the surface: less free
    assert sure.probability(far) == pytest.approx(unsure.probability(far), abs=1e-6)
    assert 0.5 < unsure.probability(on) < sure.probability(on)
    # the law's own numbers: a Gaussian 15 cm wide puts Phi(0.05 / 0.15) - Phi(-0.05 / 0.15) = 0.26 of the
    # surface within the plane's voxel along the axis ray, at most
    hits, _ = views_of([np.full((30, 40), 2.03)], [np.eye(4)], camera(), 0.15).voxels(
        np.array([0.0, 0.0, 2.0]), (1, 1, 1), 0.1)
    assert hits[0] == pytest.approx(0.261, abs=0.01)


def sphere_room(radius=0.5, half=2.0, n_views=8):
    """Exact depth maps of a sphere at the origin inside a cube room of half-side `half` (m), seen by
    n_views cameras on a circle of 1.5 m looking at its centre."""
    K = camera(64, 48, 40.0)
    poses = [look_at(np.array([1.5 * np.cos(a), 1.5 * np.sin(a), 0.3]), np.zeros(3))
             for a in np.linspace(0, 2 * np.pi, n_views, endpoint=False)]
    v, u = np.mgrid[0:48, 0:64]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    depths = []
    for pose in poses:
        d = rays @ pose[:3, :3].T  # world directions, z-depth 1
        o = pose[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):  # the room's walls: the first plane each ray leaves by
            wall = np.min(np.where(d != 0, (np.sign(d) * half - o) / d, np.inf), axis=1)
        b, c = d @ o, o @ o - radius ** 2
        a = np.sum(d * d, 1)
        disc = b * b - a * c
        ball = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        depths.append(np.minimum(wall, ball).reshape(48, 64))
    return views_of(depths, poses, K, 0.005), radius


def test_a_sphere_in_a_room_gives_its_shell_occupied_space_around_it_free_and_its_inside_unknown():
    views, radius = sphere_room()
    voxel = 0.05
    grid = views.grid(*grid_frame(voxel, np.array([[-1.0, -1.0, -0.6], [1.0, 1.0, 0.6]]), None), voxel, SENSOR)
    centers = grid.centers().reshape(-1, 3)
    r = np.linalg.norm(centers, axis=1)
    p = grid.probabilities().reshape(-1)
    seen = ~grid.unknown().reshape(-1)
    # voxels the surface crosses near their centre, where the cameras (0.3 m up) see it: the cap below
    # z = -0.3 only grazing rays reach, which pass through its voxels' corners
    shell = seen & (np.abs(r - radius) < voxel / 4) & (centers[:, 2] > -0.3)
    assert shell.sum() > 100 and np.mean(p[shell] > 0.5) > 0.95
    around = seen & (r > radius + voxel * 1.8) & (r < 1.0)
    assert around.sum() > 1000 and np.mean(p[around] < 0.5) > 0.99
    inside = r < radius - voxel * 1.8
    assert inside.sum() > 100 and np.all(p[inside] == 0.5)  # no view sees into it
    # the distance field around the ball: centre to centre, within a voxel of the exact clearance
    esdf = grid.esdf()
    free = around & (p < 0.2) & (np.abs(centers[:, 2]) < 0.3)
    clearance = esdf.at(centers[free])
    assert np.abs(clearance["distance"] - (r[free] - radius)).max() < 1.5 * voxel
    assert np.all(clearance["lower"] <= clearance["distance"] + 1e-6)
    assert np.all(clearance["distance"] <= clearance["upper"] + 1e-6)
    # a path past the ball: certain of a collision where it grazes the ball, not where it keeps clear
    path = np.array([[0.0, -0.9, 0.0], [0.0, -radius - 0.08, 0.0]])
    risk = grid.collision_probability(path, 0.1)
    assert risk[0] < 0.2 < 0.8 < risk[1]


def test_the_signed_distance_of_a_slab_is_the_distance_to_it_in_metres():
    slab = np.zeros((10, 3, 3), bool)
    slab[4:6] = True
    d = signed_distance(slab, 0.1)
    np.testing.assert_allclose(d[:, 1, 1], [0.4, 0.3, 0.2, 0.1, -0.1, -0.1, 0.1, 0.2, 0.3, 0.4], atol=1e-6)
    assert np.isinf(signed_distance(np.zeros((2, 2, 2), bool), 0.1)).all()


# -- the grid's files ------------------------------------------------------------------------------
def small_grid() -> OccupancyGrid:
    log_odds = np.zeros((4, 5, 6), np.float32)
    log_odds[1, 2, 3], log_odds[0, 0, 0], log_odds[3, 4, 5], log_odds[2, 2, 2] = 2.5, -3.0, 0.3, -0.2
    return OccupancyGrid(log_odds, np.array([-0.1, 0.2, 1.0]), 0.05)


def test_octomap_reads_the_grid_back_with_its_probabilities(tmp_path):
    octomap = pytest.importorskip("octomap")
    grid = small_grid()
    tree = octomap.OcTree.read(str(grid.write_octomap(tmp_path / "map.ot")).encode())
    assert tree.getResolution() == pytest.approx(0.05)
    centers = grid.centers()
    for index in np.ndindex(grid.shape):
        try:
            value = tree.search(centers[index]).getLogOdds()
        except octomap.NullPointerException:
            value = None
        if grid.log_odds[index] == 0:
            assert value is None, index  # unknown: no node, as OctoMap leaves it
        else:
            assert value == pytest.approx(grid.log_odds[index], abs=1e-6), index
    binary = octomap.OcTree(0.05)
    assert binary.readBinary(str(grid.write_octomap(tmp_path / "map.bt")).encode())
    for index in zip(*np.nonzero(grid.log_odds)):
        node = binary.search(centers[index])
        assert binary.isNodeOccupied(node) == (grid.log_odds[index] > 0), index
    with pytest.raises(InputError, match="map.txt: an OctoMap file is .ot"):
        grid.write_octomap(tmp_path / "map.txt")


def test_open3d_opens_the_voxel_grid_and_numpy_the_saved_grid(tmp_path):
    grid = small_grid()
    voxels = grid.to_open3d()
    assert isinstance(voxels, o3d.geometry.VoxelGrid) and len(voxels.get_voxels()) == 2  # 2.5 and 0.3
    assert o3d.io.write_voxel_grid(str(tmp_path / "grid.ply"), voxels)
    assert len(o3d.io.read_voxel_grid(str(tmp_path / "grid.ply")).get_voxels()) == 2
    centers = np.asarray([voxels.get_voxel_center_coordinate(v.grid_index) for v in voxels.get_voxels()])
    assert np.all(grid.probability(centers) > 0.5)
    loaded = OccupancyGrid.load(grid.save(tmp_path / "occupancy.npz"))
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)
    np.testing.assert_array_equal(loaded.origin, grid.origin)
    np.save(tmp_path / "other.npy", np.zeros(3))
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(InputError, match="other.npz: not an occupancy grid"):
        OccupancyGrid.load(tmp_path / "other.npz")


# -- bad arguments -----------------------------------------------------------------------------------
@pytest.mark.parametrize("voxel_size", [0, -0.05, float("nan"), "5cm", True, None])
def test_a_bad_voxel_size_is_named(voxel_size):
    with pytest.raises(ConfigError, match="voxel_size must be a positive number of metres"):
        grid_frame(voxel_size, None, np.array([[0, 0, 0], [1, 1, 1.0]]))


@pytest.mark.parametrize("bounds", [np.zeros((3, 2)), [[0, 0, 0], [1, -1, 1]], [[0, 0, 0], [1, 1, np.inf]], "room"])
def test_bad_bounds_are_named(bounds):
    with pytest.raises(ConfigError, match="bounds must be"):
        grid_frame(0.05, bounds, np.array([[0, 0, 0], [1, 1, 1.0]]))


def test_a_grid_too_large_for_memory_is_refused_before_any_work():
    with pytest.raises(ConfigError, match="voxel_size 0.001 m makes"):
        grid_frame(0.001, [[0, 0, 0], [10, 10, 10]], None)


# -- the real pipeline -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def room():
    """The synthetic room's 16 noisy 160x120 frames reconstructed (the test preset trained 600 steps at
    full resolution, exact poses): enough for a depth sigma of centimetres."""
    from open3d_pnerf import ReconstructionConfig, reconstruct, synthetic_sequence

    data = synthetic_sequence(16, 160, 120, seed=0)
    config = ReconstructionConfig.preset("test", holdout_every=4, progress=False, max_steps=600, image_scale=1.0)
    return data, reconstruct(data.sequence, config, poses=data.sequence.gt_poses)


@pytest.mark.slow
def test_a_trained_room_is_occupied_on_its_surface_free_before_it_and_unknown_outside(room):
    data, recon = room
    seq = data.sequence
    surface = np.asarray(data.reference_points(stride=4).points)
    free = []
    for i in recon.train_indices:  # halfway along the training rays to the exact surface
        depth = data.scene.render(seq.gt_poses[i], seq.intrinsic)["depth"][::8, ::8]
        v, u = np.mgrid[0:120:8, 0:160:8]
        K = seq.K
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
        free.append((rays * depth[..., None] / 2).reshape(-1, 3) @ seq.gt_poses[i][:3, :3].T + seq.gt_poses[i][:3, 3])
    free = np.concatenate(free)
    grid = recon.occupancy_grid(0.1)
    assert np.mean(grid.probability(surface) > 0.5) > 0.8
    assert np.mean(grid.probability(free) < 0.5) > 0.95
    outside = np.array([[0.0, 0.0, 10.0], [20.0, 0.0, 1.0]])
    np.testing.assert_array_equal(recon.occupancy(outside, size=0.1), 0.5)
    # the same voxels asked one by one give the grid's probabilities
    some = np.concatenate([surface[::50], free[::50]])
    np.testing.assert_allclose(recon.occupancy(some, size=0.1), grid.probability(some), atol=1e-6)
    with pytest.raises(ConfigError, match="voxel_size must be"):
        recon.occupancy_grid(-0.1)
    with pytest.raises(InputError, match="points must be finite"):
        recon.occupancy(np.zeros((3, 2)))


@pytest.mark.slow
def test_the_command_line_writes_the_grid_octomap_and_the_distance_field(room, tmp_path, capsys):
    from open3d_pnerf.cli import EXIT_ERROR, EXIT_OK, main

    octomap = pytest.importorskip("octomap")
    _, recon = room
    saved = recon.save(tmp_path / "recon")
    assert main(["occupancy", str(saved), "--voxel", "0.1"]) == EXIT_OK
    grid = OccupancyGrid.load(saved / "occupancy.npz")
    assert grid.voxel_size == 0.1 and "occupied" in capsys.readouterr().out
    tree = octomap.OcTree.read(str(saved / "occupancy.ot").encode())
    known = np.argwhere(~grid.unknown())[::97]
    for index in known:
        value = tree.search(grid.centers()[tuple(index)]).getLogOdds()
        assert value == pytest.approx(grid.log_odds[tuple(index)], abs=1e-6)
    with np.load(saved / "esdf.npz") as esdf:
        assert esdf["distance"].shape == grid.shape
    assert octomap.OcTree(0.1).readBinary(str(saved / "occupancy.bt").encode())
    assert main(["occupancy", str(saved), "--voxel", "0", "--out", str(tmp_path / "bad")]) == EXIT_ERROR
    assert "--voxel 0.0: a voxel size must be a positive number" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


# -- scoring against held-out views ------------------------------------------------------------------
def test_a_held_out_view_of_a_plane_marks_its_voxels_free_up_to_the_plane_and_occupied_on_it(plane_scene):
    from conftest import tiny_reconstruction

    from open3d_pnerf.occupancy import heldout_voxels

    seq, _ = plane_scene(z0=2.03)
    recon = tiny_reconstruction()  # frame 0 held out, at x = -0.04
    centers, occupied = heldout_voxels(recon, seq, voxel_size=0.1, stride=2)
    np.testing.assert_allclose(centers[occupied][:, 2], 2.05)
    assert centers[~occupied][:, 2].max() == pytest.approx(1.95) and centers[~occupied][:, 2].min() == pytest.approx(0.05)
    # the plane's voxels span the view's footprint on it: 64 px of 50 px focal length at 2.03 m
    width = np.ptp(centers[occupied][:, 0]) + 0.1
    assert width == pytest.approx(64 / 50 * 2.03, abs=0.2)
    with pytest.raises(InputError, match="2 depth maps for 1 held-out frames"):
        heldout_voxels(recon, seq, 0.1, depths=[np.ones((48, 64))] * 2)


def test_calibration_scores_by_hand():
    from open3d_pnerf.occupancy import calibration

    p = np.array([0.1] * 10 + [0.9] * 10)
    y = np.array([True] + [False] * 9 + [True] * 8 + [False] * 2)
    scores = calibration(p, y)
    assert scores["brier"] == pytest.approx((0.81 + 9 * 0.01 + 8 * 0.01 + 2 * 0.81) / 20)
    assert scores["ece"] == pytest.approx(0.5 * abs(0.1 - 0.1) + 0.5 * abs(0.9 - 0.8))
    assert scores["occupied_called_free"] == pytest.approx(1 / 9)
    assert scores["free_called_occupied"] == pytest.approx(2 / 11) and scores["decided"] == 1.0
    assert scores["reliability"]["count"][1] == 10 and scores["reliability"]["occupied_share"][9] == pytest.approx(0.8)
    assert scores["reliability"]["mean_probability"][5] is None
