"""ObservedSurface: the voxels the training frames' depth saw, and distances to them."""

import numpy as np
import pytest

from open3d_pnerf.errors import InputError
from open3d_pnerf.observed import ObservedSurface

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


def test_the_voxels_of_two_views_are_each_occupied_voxel_once_in_every_octant():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (2, 48, 64))
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, :3, 3] = [-1.3, 0.7, -2.2]  # the second view's points straddle the origin: negative keys too
    observed = ObservedSurface.from_depths(depth, depth > 0, K, poses, 0.05)
    rows, cols = np.mgrid[:48, :64]
    points = []
    for d, pose in zip(depth, poses):  # the pinhole back-projection written out
        cam = np.stack([(cols - K[0, 2]) / K[0, 0] * d, (rows - K[1, 2]) / K[1, 1] * d, d], -1).reshape(-1, 3)
        points.append(cam @ pose[:3, :3].T + pose[:3, 3])
    expected = (np.unique(np.floor(np.concatenate(points) / 0.05), axis=0) + 0.5) * 0.05
    np.testing.assert_allclose(observed.centres, expected, atol=1e-6)
    assert (expected < 0).any() and (expected > 0).any()


@pytest.mark.parametrize("voxel, centres", [(0.0, np.zeros((1, 3))), (-1.0, np.zeros((1, 3))),
                                            (0.02, np.zeros((3,))), (0.02, np.full((1, 3), np.nan))])
def test_bad_observed_surfaces_are_refused(voxel, centres):
    with pytest.raises(InputError, match="ObservedSurface"):
        ObservedSurface(voxel, centres)
