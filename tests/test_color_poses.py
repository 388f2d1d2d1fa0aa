"""Colour cameras beside the depth cameras (tracking.color): the offsets' least squares on exact
relative poses, depth moved into another camera, and on the bundled sample colour images that
agree better from their own poses than from the depth cameras'."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from open3d_pnerf.camera import backproject, intrinsic_matrix, pinhole, project, reproject_depth
from open3d_pnerf.data import depth_in_color_cameras
from open3d_pnerf.errors import InputError
from open3d_pnerf.tracking import track
from open3d_pnerf.tracking.color import OFFSET_PRIOR, ColorOffsets


def rigid(rotvec, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def test_offsets_are_solved_from_exact_colour_relative_poses():
    """Known colour offsets (3 mrad, 5 mm) on a camera path turning 9 degrees a frame: the solved
    offsets reproduce the colour relative poses they imply (to the first-order model's accuracy);
    what relative poses cannot tell (where the set of colour cameras sits as a whole, six degrees
    of freedom) the prior settles to the smallest offsets, no larger than the true ones."""
    rng = np.random.default_rng(0)
    n = 8
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ rigid(rng.normal(0, 0.09, 3), rng.normal(0, 0.1, 3)))
    poses = np.stack(poses)
    truth = np.stack([rigid(rng.normal(0, 3e-3, 3), rng.normal(0, 5e-3, 3)) for _ in range(n)])
    offsets = ColorOffsets()
    color = {}
    for i in range(1, n):
        depth = np.linalg.inv(poses[i - 1]) @ poses[i]
        color[i] = np.linalg.inv(truth[i - 1]) @ depth @ truth[i]
        offsets.add(i, color[i], depth, 1e-12 * np.eye(6))
    solved = offsets.solve(poses)
    for i in range(1, n):
        implied = np.linalg.inv(solved[i - 1]) @ np.linalg.inv(poses[i - 1]) @ poses[i] @ solved[i]
        assert np.abs(implied - color[i]).max() < 1e-4, i
    def size(offsets):  # the prior's measure of a set of offsets
        twists = np.concatenate([Rotation.from_matrix(offsets[:, :3, :3]).as_rotvec(), offsets[:, :3, 3]], 1)
        return np.einsum("ni,ij,nj->", twists, np.linalg.inv(OFFSET_PRIOR), twists)

    assert size(solved) <= size(truth)


def test_an_implausible_colour_pose_is_not_used():
    offsets = ColorOffsets()
    offsets.add(1, rigid([0, 0, 0], [0.05, 0, 0]), np.eye(4), np.eye(6))  # 5 cm from the depth's
    offsets.add(2, np.full((4, 4), np.nan), np.eye(4), np.eye(6))
    assert offsets.measured == {}
    np.testing.assert_allclose(offsets.solve(np.stack([np.eye(4)] * 3)), np.stack([np.eye(4)] * 3), atol=1e-12)


def test_depth_moved_into_another_camera():
    """A wall 2 m away with a box 1.5 m away in front of its left part (f = 50 px): moved 10 cm
    towards it, the wall reads 1.9 m and the box 1.4 m; moved 20 cm to the right, the box shifts
    6.7 px left and the wall 5 px, so the box covers the wall where both land (the nearest surface
    is kept) and uncovers a hole on its right, and nothing lands on the last 5 columns (0 there)."""
    K = intrinsic_matrix(pinhole(80, 60, 50.0, 50.0, 39.5, 29.5))
    depth = np.full((60, 80), 2.0, np.float32)
    depth[20:40, 10:30] = 1.5
    np.testing.assert_array_equal(reproject_depth(depth, K, np.eye(4)), depth)
    closer = reproject_depth(depth, K, rigid([0, 0, 0], [0, 0, -0.1]))
    assert np.isclose(closer[30, 70], 1.9) and np.isclose(closer[30, 18], 1.4)
    moved = reproject_depth(depth, K, rigid([0, 0, 0], [-0.2, 0, 0]))[30]
    np.testing.assert_array_equal(moved[3:23], 1.5)  # the box's 20 columns, over the wall's at 3-4
    np.testing.assert_array_equal(moved[[23, 24, 75, 76, 77, 78, 79]], 0)
    np.testing.assert_array_equal(moved[25:75], 2.0)


def test_depth_in_color_cameras_checks_its_offsets(sample):
    with pytest.raises(InputError, match=r"offsets must be finite with shape \(11, 4, 4\)"):
        depth_in_color_cameras(sample, np.zeros((3, 4, 4)))


def test_the_sample_s_colour_images_agree_better_from_their_own_cameras(sample):
    """Each frame's colour, moved onto the previous frame by its depth and the poses, against the
    previous frame's colour: closer with the colour cameras' poses (and the depth moved into them)
    than with the depth cameras' (the sample's colour is taken up to 17 ms after its depth)."""
    traj = track(sample, progress=False)
    assert traj.color_offsets is not None and track(sample, progress=False, color_poses=False).color_offsets is None
    moved = depth_in_color_cameras(sample, traj.color_offsets)
    K, (h, w) = sample.K, sample.image_size

    def disagreement(seq, poses) -> float:
        errors = []
        for i in range(1, len(seq)):
            frame, before = seq[i], seq[i - 1]
            points, flat = backproject(frame.depth, K)
            relative = np.linalg.inv(poses[i - 1]) @ poses[i]
            u, v = project(K, points @ relative[:3, :3].T + relative[:3, 3])
            u, v = np.round(u).astype(int), np.round(v).astype(int)
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            seen = before.color[v[inside], u[inside]].astype(float)
            errors.append(np.abs(seen - frame.color.reshape(-1, 3)[flat[inside]].astype(float)).mean())
        return float(np.mean(errors))

    assert disagreement(moved, traj.color_poses) < 0.9 * disagreement(sample, traj.poses)
