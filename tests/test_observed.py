"""ObservedSurface: the voxels the training frames' depth saw, distances to them, and what the views saw through."""

import numpy as np
import pytest

from open3d_pnerf.errors import InputError
from open3d_pnerf.observed import MERGE_EVERY, ObservedSurface

K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])


def wall(z: float = 2.0, shape=(48, 64)) -> ObservedSurface:
    """A camera at the origin looking down +z at a wall z metres away, in 2 cm voxels."""
    depth = np.full((1, *shape), z)
    return ObservedSurface.from_depths(depth, depth > 0, K, np.eye(4)[None], 0.02)


def test_points_on_the_observed_wall_are_at_distance_zero_and_off_it_at_their_distance():
    observed = wall()
    assert len(observed) > 100
    assert np.abs(observed.centres[:, 2] - 2.01).max() < 0.011  # one layer of voxels at z = 2
    on = np.array([[0.0, 0.0, 2.0], [0.2, -0.1, 2.005]])
    np.testing.assert_array_equal(observed.distance(on), 0.0)
    off = np.array([[0.0, 0.0, 2.5], [0.0, 0.0, 1.0]])
    # 0.5 m and 1 m to the wall, within a voxel (the nearest centre, less half its diagonal)
    np.testing.assert_allclose(observed.distance(off), [0.5, 1.0], atol=0.02 * np.sqrt(3))
    assert (observed.distance(off) <= [0.5, 1.0]).all()  # never more than the distance to the wall
    beside = np.array([[3.0, 0.0, 2.0]])  # 3 m sideways from the wall's centre, beyond its edge
    edge = 0.32 * 2.0 / 1.0  # the wall's half-width: 32 pixels at f = 100 px, 2 m away
    assert observed.distance(beside)[0] == pytest.approx(3.0 - edge, abs=0.03)


def test_distances_keep_the_points_shape_and_flag_what_cannot_be_said():
    observed = wall()
    points = np.zeros((2, 3, 3))
    points[1, 2] = np.nan
    d = observed.distance(points)
    assert d.shape == (2, 3) and np.isnan(d[1, 2]) and np.isfinite(d[0]).all()
    nothing = ObservedSurface(0.02, np.zeros((0, 3)))
    assert np.isinf(nothing.distance(np.zeros((4, 3)))).all()


def test_points_outside_the_box_and_invalid_pixels_are_not_observed():
    depth = np.full((1, 48, 64), 2.0)
    valid = np.zeros_like(depth, bool)
    valid[0, :, :32] = True  # the left half only
    half = ObservedSurface.from_depths(depth, valid, K, np.eye(4)[None], 0.02)
    assert (half.centres[:, 0] < 0.01).all()
    boxed = ObservedSurface.from_depths(depth, depth > 0, K, np.eye(4)[None], 0.02,
                                        aabb=np.array([[-5, -5, 0], [5, 5, 1.5]]))
    assert len(boxed) == 0


@pytest.mark.parametrize("views", [2, 2 * MERGE_EVERY + 3])  # the keys merged once, and in batches
def test_the_voxels_of_the_views_are_each_occupied_voxel_once_in_every_octant(views):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (views, 48, 64))
    poses = np.stack([np.eye(4)] * views)
    poses[:, 0, 3] = 0.3 * np.arange(views)  # each view adds voxels of its own
    poses[1::2, :3, 3] += [-1.3, 0.7, -2.2]  # every other view's points straddle the origin: negative keys too
    observed = ObservedSurface.from_depths(depth, depth > 0, K, poses, 0.05)
    rows, cols = np.mgrid[:48, :64]
    points = []
    for d, pose in zip(depth, poses):  # the pinhole back-projection written out
        cam = np.stack([(cols - K[0, 2]) / K[0, 0] * d, (rows - K[1, 2]) / K[1, 1] * d, d], -1).reshape(-1, 3)
        points.append(cam @ pose[:3, :3].T + pose[:3, 3])
    expected = (np.unique(np.floor(np.concatenate(points) / 0.05), axis=0) + 0.5) * 0.05
    np.testing.assert_allclose(observed.centres, expected, atol=1e-6)
    assert (expected < 0).any() and (expected > 0).any()


def test_a_point_a_view_saw_past_is_seen_through_by_the_distance_to_what_it_saw():
    observed = wall()  # a wall 2 m in front of the camera, 64 x 48 px at f = 100 px
    points = np.array([[0.0, 0.0, 1.0], [0.2, 0.1, 1.5], [0.0, 0.0, 1.95], [0.0, 0.0, 2.5], [0.0, 0.0, -1.0],
                       [5.0, 0.0, 1.0]])
    # in front: the distance to the wall; within the margin, behind it, behind the camera, outside the image: 0
    np.testing.assert_allclose(observed.seen_through(points), [1.0, 0.5, 0, 0, 0, 0], atol=1e-3)
    grid = np.zeros((2, 3, 3))
    grid[..., 2] = 1.2
    grid[1, 2] = np.nan
    gaps = observed.seen_through(grid)
    assert gaps.shape == (2, 3) and np.isnan(gaps[1, 2]) and np.allclose(gaps[0], 0.8, atol=1e-3)
    assert (ObservedSurface(0.02, observed.centres).seen_through(points) == 0).all()  # views not kept


def test_what_a_view_saw_through_is_the_nearest_surface_around_the_pixel_and_the_largest_over_views():
    depth = np.full((1, 48, 64), 2.0)
    depth[0, :, 30:34] = 1.0  # a post 1 m away in columns 30-33
    post = ObservedSurface.from_depths(depth, depth > 0, K, np.eye(4)[None], 0.02)
    column = lambda u, z: [(u - K[0, 2]) / K[0, 0] * z, 0.0, z]  # noqa: E731  the point of column u at z
    points = np.array([column(29, 1.5), column(34, 1.5), column(35, 1.5), column(31, 0.5)])
    # beside the post (a neighbour saw it at 1 m) not seen through; two columns off by 0.5 m; in front of it 0.5 m
    np.testing.assert_allclose(post.seen_through(points), [0, 0, 0.5, 0.5], atol=1e-3)
    moved = np.eye(4)
    moved[2, 3] = -1.0  # a second view 1 m further back saw a farther wall, 3.5 m from it (z = 2.5)
    depths = np.stack([np.full((48, 64), 2.0), np.full((48, 64), 3.5)])
    both = ObservedSurface.from_depths(depths, depths > 0, K, np.stack([np.eye(4), moved]), 0.02)
    np.testing.assert_allclose(both.seen_through(np.array([[0.0, 0.0, 1.0]])), [1.5], atol=1e-3)  # 1 m and 1.5 m
    holes = ObservedSurface.from_depths(depth, np.zeros_like(depth, bool), K, np.eye(4)[None], 0.02)
    assert holes.seen_through(points).max() == 0  # no depth: nothing seen through


def test_given_the_camera_only_the_views_nearest_to_it_are_asked():
    from open3d_pnerf.observed import SEEN_THROUGH_VIEWS

    n = SEEN_THROUGH_VIEWS + 6
    depths, poses = np.full((n, 48, 64), 0.4), np.tile(np.eye(4), (n, 1, 1))  # walls 0.4 m away: behind the point
    poses[-1, 2, 3], depths[-1] = -10.0, 12.0  # one view 10 m back saw through it to z = 2
    observed = ObservedSurface.from_depths(depths, depths > 0, K, poses, 0.05)
    point = np.array([[0.0, 0.0, 0.5]])
    np.testing.assert_allclose(observed.seen_through(point), [1.5], atol=1e-2)  # every view asked
    np.testing.assert_array_equal(observed.seen_through(point, np.zeros(3)), [0.0])  # the far one is not


def test_bad_views_are_refused():
    with pytest.raises(InputError, match="ObservedSurface: depths"):
        ObservedSurface(0.02, np.zeros((1, 3)), np.ones((2, 4, 4)), K, np.eye(4)[None])


@pytest.mark.parametrize("voxel, centres", [(0.0, np.zeros((1, 3))), (-1.0, np.zeros((1, 3))),
                                            (0.02, np.zeros((3,))), (0.02, np.full((1, 3), np.nan))])
def test_bad_observed_surfaces_are_refused(voxel, centres):
    with pytest.raises(InputError, match="ObservedSurface"):
        ObservedSurface(voxel, centres)
