"""Tests of open3d_pnerf.data: the RGBDSequence model and the TUM / 7-Scenes / Redwood readers."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

import open3d_pnerf.data.images as images_module
from open3d_pnerf.data import (
    RGBDSequence,
    check_poses,
    load_sample,
    load_sequence,
    read_log_trajectory,
    write_log_trajectory,
    write_tum_trajectory,
)
from open3d_pnerf.errors import InputError, PoseError
from open3d_pnerf.tracking import absolute_trajectory_error


# -- helpers --------------------------------------------------------------------------------
def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image (OpenCV wants BGR)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def write_depth(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert raw.dtype == np.uint16
    assert cv2.imwrite(str(path), raw)


def rigid(rotvec, t) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = t
    return pose


def pinhole(w, h, fx, fy, cx, cy):
    return o3d.camera.PinholeCameraIntrinsic(w, h, fx, fy, cx, cy)


# -- tiny TUM folder ------------------------------------------------------------------------
TUM_W, TUM_H = 640, 480  # the TUM reader assumes the Kinect's 640x480
TUM_RGB = [1.0, 1.25, 1.5, 2.0]  # 1.25 has no depth within 0.02 s: dropped by association
TUM_DEPTH = [1.004, 1.512, 1.996, 3.0]  # 3.0 has no colour: dropped as well
TUM_RAW = {1.0: 5000, 1.5: 7500, 2.0: 10000}  # depth PNG values of the matched frames (x/5000 m)


def make_tum(root: Path, groundtruth: str | None = None) -> Path:
    for k, t in enumerate(TUM_RGB):
        write_rgb(root / "rgb" / f"{t:.6f}.png", np.full((TUM_H, TUM_W, 3), (10 * (k + 1), 0, 255), np.uint8))
    for t_d in TUM_DEPTH:
        t_rgb = min(TUM_RAW, key=lambda t: abs(t - t_d))
        raw = TUM_RAW[t_rgb] if abs(t_rgb - t_d) < 0.02 else 1234
        write_depth(root / "depth" / f"{t_d:.6f}.png", np.full((TUM_H, TUM_W), raw, np.uint16))
    (root / "rgb.txt").write_text(
        "# color images\n# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in TUM_RGB)
    )
    (root / "depth.txt").write_text("# depth maps\n" + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in TUM_DEPTH))
    if groundtruth is not None:
        (root / "groundtruth.txt").write_text(groundtruth)
    return root


GT_POSE_A = rigid([0, 0, 0], [0.0, 0.0, 0.0])
GT_POSE_B = rigid([0, 0, np.pi / 2], [1.0, 2.0, 3.0])


def gt_text(poses, stamps) -> str:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, p in zip(stamps, poses):
        q = Rotation.from_matrix(p[:3, :3]).as_quat()
        lines.append(f"{t} " + " ".join(f"{v:.9f}" for v in (*p[:3, 3], *q)))
    return "\n".join(lines) + "\n"


@pytest.fixture
def tum_dir(tmp_path) -> Path:
    return make_tum(tmp_path / "rgbd_dataset_freiburg1_tiny", gt_text([GT_POSE_A, GT_POSE_B], [0.5, 2.5]))


def test_tum_association_depth_scale_and_intrinsic(tum_dir):
    seq = load_sequence(tum_dir)
    assert len(seq) == 3  # 1.25 (no depth) and depth 3.0 (no colour) are not associated
    np.testing.assert_array_equal(seq.timestamps, [1.004, 1.512, 1.996])  # the depth images' timestamps
    for i, (t_rgb, t) in enumerate(zip([1.0, 1.5, 2.0], [1.004, 1.512, 1.996])):
        frame = seq[i]
        assert frame.index == i and frame.timestamp == t
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (TUM_H, TUM_W)
        # 16-bit PNG / 5000 = metres, exactly for these values
        assert np.all(frame.depth == TUM_RAW[t_rgb] / 5000.0)
        assert frame.color.dtype == np.uint8 and frame.color.shape == (TUM_H, TUM_W, 3)
    # colour is RGB (written as BGR by OpenCV) and belongs to the associated file
    assert tuple(seq[0].color[0, 0]) == (10, 0, 255)
    assert tuple(seq[1].color[0, 0]) == (30, 0, 255)  # rgb k=2 (1.5), not k=1 (1.25)
    # "freiburg1" in the folder name selects the fr1 calibration
    fx, fy = seq.intrinsic.get_focal_length()
    assert (fx, fy) == pytest.approx((517.3, 516.5))
    assert seq.intrinsic.get_principal_point() == pytest.approx((318.6, 255.3))
    assert seq.image_size == (480, 640)


def test_tum_groundtruth_is_interpolated_at_depth_timestamps(tum_dir):
    seq = load_sequence(tum_dir)
    assert seq.gt_poses.shape == (3, 4, 4)
    # depth timestamps 1.004, 1.512, 1.996 (colour 1.0, 1.5, 2.0) between gt 0.5 and 2.5: fractions (t - 0.5) / 2
    for pose, s in zip(seq.gt_poses, [0.252, 0.506, 0.748]):
        np.testing.assert_allclose(pose[:3, 3], s * np.array([1.0, 2.0, 3.0]), atol=1e-9)
        expected = Rotation.from_rotvec([0, 0, s * np.pi / 2]).as_matrix()  # slerp
        np.testing.assert_allclose(pose[:3, :3], expected, atol=1e-7)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])


def test_tum_groundtruth_time_offset_reads_the_poses_that_many_seconds_away(tum_dir):
    seq = load_sequence(tum_dir, gt_time_offset=-0.25)
    assert seq.timestamps.tolist() == [1.004, 1.512, 1.996]  # the frames keep their own time
    # read at 0.754, 1.262, 1.746 between gt 0.5 and 2.5: fractions (t - 0.25 - 0.5) / 2
    for pose, s in zip(seq.gt_poses, [0.127, 0.381, 0.623]):
        np.testing.assert_allclose(pose[:3, 3], s * np.array([1.0, 2.0, 3.0]), atol=1e-9)
        np.testing.assert_allclose(pose[:3, :3], Rotation.from_rotvec([0, 0, s * np.pi / 2]).as_matrix(), atol=1e-7)
    for bad in (float("nan"), 2.0, "0.03", True):
        with pytest.raises(InputError, match="gt_time_offset"):
            load_sequence(tum_dir, gt_time_offset=bad)


def test_a_ground_truth_time_offset_does_not_apply_to_a_folder_without_timestamps(tmp_path):
    root, _ = make_seven_scenes(tmp_path / "kitchen")
    with pytest.raises(InputError, match="gt_time_offset do not apply"):
        load_sequence(root, gt_time_offset=0.01)


def test_tum_groundtruth_starting_just_after_the_first_frame_is_kept(tmp_path):
    """TUM fr2/desk: the first frame is 19 microseconds before the first groundtruth line.
    Within TUM's 20 ms tolerance the frame takes the first line's pose; no ground truth is lost."""
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_x", gt_text([GT_POSE_A, GT_POSE_B], [1.004019, 2.5]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_sequence(root)
    assert seq.gt_valid.all()
    np.testing.assert_allclose(seq.gt_poses[0], GT_POSE_A, atol=1e-9)
    assert "with GT poses)" in repr(seq)


def test_tum_groundtruth_not_covering_frames_keeps_the_covered_ones(tmp_path):
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_x", gt_text([GT_POSE_A, GT_POSE_B], [1.2, 2.5]))
    with pytest.warns(UserWarning, match=r"groundtruth.txt: 1 of 3 frames .* \(frames \[0\]\).* NaN"):
        seq = load_sequence(root)
    np.testing.assert_array_equal(seq.gt_valid, [False, True, True])
    assert np.isnan(seq.gt_poses[0]).all() and np.isfinite(seq.gt_poses[1:]).all()
    np.testing.assert_allclose(seq.gt_poses[1][:3, 3], (1.512 - 1.2) / 1.3 * np.array([1.0, 2.0, 3.0]), atol=1e-9)
    assert "GT poses for 2 of them" in repr(seq)
    # a sub-sequence keeps the rows of its frames; ATE leaves the frame without ground truth out
    assert seq[1:].gt_valid.all() and not seq.select([0, 2]).gt_valid[0]
    estimate = seq.gt_poses.copy()
    estimate[0] = np.eye(4)
    ate = absolute_trajectory_error(estimate, seq.gt_poses)
    assert ate["frames"] == 2 and ate["rmse"] < 1e-9
    with pytest.raises(PoseError, match="NaN"):  # an estimate must still be complete
        absolute_trajectory_error(seq.gt_poses, estimate)


def test_tum_unknown_camera_warns_default_and_explicit_intrinsic_wins(tmp_path):
    root = make_tum(tmp_path / "mystery_camera")
    with pytest.warns(UserWarning, match="unknown TUM camera"):
        seq = load_sequence(root)
    assert seq.intrinsic.get_focal_length() == pytest.approx((525.0, 525.0))
    assert seq.intrinsic.get_principal_point() == pytest.approx((319.5, 239.5))
    assert seq.gt_poses is None  # no groundtruth.txt
    mine = pinhole(640, 480, 600.0, 610.0, 300.0, 200.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_sequence(root, intrinsic=mine)
    np.testing.assert_allclose(seq.K, [[600, 0, 300], [0, 610, 200], [0, 0, 1]])


def test_tum_trajectory_round_trip_through_groundtruth(tmp_path):
    # write_tum_trajectory -> groundtruth.txt -> the TUM reader interpolates at the exact
    # stamps -> the same poses (to the 7 written decimals)
    poses = np.stack([rigid([0.1, -0.2, 0.3], [0.5, -1.0, 2.0]), rigid([-0.4, 0.2, 1.0], [1.5, 0.25, -0.5]),
                      rigid([0.0, 0.0, -2.5], [0.0, 0.0, 1.0])])
    stamps = np.array(TUM_DEPTH[:3])  # the frames' (depth) timestamps
    root = make_tum(tmp_path / "rgbd_dataset_freiburg1_rt")
    write_tum_trajectory(root / "groundtruth.txt", poses, stamps)
    text = (root / "groundtruth.txt").read_text().splitlines()
    assert text[0].startswith("#") and len(text) == 4
    first = np.array(text[1].split(), dtype=float)
    assert first[0] == 1.004 and np.allclose(first[1:4], [0.5, -1.0, 2.0])
    # quaternion is x y z w (TUM order)
    q = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_quat()
    assert np.allclose(first[4:], q, atol=1e-6) or np.allclose(first[4:], -q, atol=1e-6)
    seq = load_sequence(root)
    np.testing.assert_allclose(seq.gt_poses, poses, atol=1e-6)


# -- tiny 7-Scenes folder -------------------------------------------------------------------
def make_seven_scenes(root: Path, n: int = 2) -> tuple[Path, np.ndarray]:
    root.mkdir(parents=True)
    poses = []
    for k in range(n):
        raw = np.full((480, 640), 1500 + 500 * k, np.uint16)
        raw[:10, :20] = 65535  # 7-Scenes' invalid marker
        write_depth(root / f"frame-{k:06d}.depth.png", raw)
        write_rgb(root / f"frame-{k:06d}.color.png", np.full((480, 640, 3), (0, 50 * k, 100), np.uint8))
        pose = rigid([0.0, 0.1 * k, 0.0], [0.2 * k, 0.0, -0.1])
        np.savetxt(root / f"frame-{k:06d}.pose.txt", pose)
        poses.append(pose)
    np.savetxt(root / "camera-intrinsics.txt", [[580.0, 0, 321.0], [0, 590.0, 239.0], [0, 0, 1]])
    return root, np.stack(poses)


def test_seven_scenes_reader(tmp_path):
    root, poses = make_seven_scenes(tmp_path / "kitchen")
    seq = load_sequence(root)
    assert len(seq) == 2
    np.testing.assert_allclose(seq.gt_poses, poses, atol=1e-12)
    np.testing.assert_allclose(seq.K, [[580, 0, 321], [0, 590, 239], [0, 0, 1]])
    for k in range(2):
        depth = seq[k].depth
        assert np.all(depth[:10, :20] == 0)  # 65535 -> invalid
        assert np.all(depth[10:] == (1500 + 500 * k) / 1000.0)  # depth scale 1000
        assert tuple(seq[k].color[100, 100]) == (0, 50 * k, 100)
    np.testing.assert_array_equal(seq.timestamps, [0.0, 1.0])  # frame numbers
    # colour is not registered to depth: the Kinect's colour camera, its own intrinsic (0.905 x focal, -7 px)
    ci = seq.color_intrinsic
    assert ci.get_focal_length() == pytest.approx((580 * 0.905, 590 * 0.905))
    assert ci.get_principal_point() == pytest.approx((321 - 7.0, 239))
    assert not seq.color_registered
    # to_open3d resamples colour onto the depth grid (uniform colour stays uniform inside)
    rgbd = seq.to_open3d(1)
    assert np.asarray(rgbd.color).shape == (480, 640, 3)
    assert tuple(np.asarray(rgbd.color)[240, 320]) == (0, 50, 100)
    assert np.asarray(rgbd.depth)[240, 320] == pytest.approx(2.0)


def offset_colour_camera(baseline: float, depth: np.ndarray) -> RGBDSequence:
    """One 64x48 frame whose colour pixel (u, v) holds u and v, from a colour camera `baseline` m
    along x from the depth camera (same intrinsic: f = 50, centre (32, 24))."""
    K = o3d.camera.PinholeCameraIntrinsic(64, 48, 50.0, 50.0, 32.0, 24.0)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    color = np.stack([u, v, np.zeros_like(u)], -1).astype(np.uint8)
    extrinsic = np.eye(4)
    extrinsic[0, 3] = -baseline  # depth-camera points -> colour-camera points
    return RGBDSequence([images_module.constant_reader(color, depth, "memory")], K, color_extrinsic=extrinsic)


def test_colour_camera_beside_the_depth_camera_is_registered_through_each_pixels_depth():
    depth = np.full((48, 64), 1.0, np.float32)
    depth[:, 32:] = 2.0
    depth[20, 10] = 0.0  # a hole takes its nearest neighbour's depth
    seq = offset_colour_camera(0.1, depth)
    frame = seq[0]
    grid = seq.color_on_depth_grid(frame.color, frame.depth).astype(float)
    # a point at depth z seen at column u sits f * b / z columns to the left in the colour camera
    assert grid[10, 20, 0] == pytest.approx(20 - 50 * 0.1 / 1.0, abs=0.5)
    assert grid[10, 50, 0] == pytest.approx(50 - 50 * 0.1 / 2.0, abs=0.5)
    assert grid[20, 10, 0] == pytest.approx(10 - 5.0, abs=0.5)
    np.testing.assert_allclose(grid[5:40, 10:60, 1], np.arange(5, 40)[:, None] * np.ones((1, 50)), atol=0.5)
    assert not seq.color_registered
    # a frame without any depth falls back to the plane at infinity: no shift at all
    empty = offset_colour_camera(0.1, np.zeros((48, 64), np.float32))
    assert empty.color_on_depth_grid(empty[0].color, empty[0].depth)[10, 20, 0] == 20
    # the same rig at half the image size shifts by half as many pixels
    half = seq.scaled_by(0.5)
    small = half.color_on_depth_grid(half[0].color, half[0].depth).astype(float)
    assert small[5, 10, 0] == pytest.approx(20 - 5.0 + 0.5, abs=1.0)  # colour values are full-size columns


def test_colour_camera_beside_the_depth_camera_needs_the_depth_and_a_rigid_offset():
    depth = np.full((48, 64), 1.0, np.float32)
    seq = offset_colour_camera(0.1, depth)
    with pytest.raises(InputError, match="needs the frame's depth.*color_extrinsic"):
        seq.color_on_depth_grid(seq[0].color)
    with pytest.raises(InputError, match="depth 32x24, expected the depth grid's 64x48"):
        seq.color_on_depth_grid(seq[0].color, depth[::2, ::2])
    K = o3d.camera.PinholeCameraIntrinsic(64, 48, 50.0, 50.0, 32.0, 24.0)
    with pytest.raises(PoseError, match="color_extrinsic"):
        RGBDSequence([images_module.constant_reader(seq[0].color, depth, "memory")], K, color_extrinsic=np.eye(4) * 2)


def test_colour_camera_turned_but_not_moved_needs_no_depth():
    seq = offset_colour_camera(0.0, np.full((48, 64), 1.0, np.float32))
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.0, np.arctan(2 / 50), 0.0]).as_matrix()  # 2 px at f = 50
    turned = RGBDSequence([images_module.constant_reader(seq[0].color, seq[0].depth, "memory")], seq.intrinsic,
                          color_extrinsic=turn)
    grid = turned.color_on_depth_grid(turned[0].color).astype(float)
    assert grid[24, 32, 0] == pytest.approx(34, abs=0.5)  # the centre pixel's ray, 2 px right in the colour camera


def test_load_sequence_places_the_colour_camera_and_seven_scenes_overrides_drop_the_kinects(tmp_path):
    root, _ = make_redwood(tmp_path / "rw")
    rig = np.eye(4)
    rig[0, 3] = -0.02
    np.testing.assert_array_equal(load_sequence(root, color_extrinsic=rig).color_extrinsic, rig)
    assert load_sequence(root).color_extrinsic is None
    kitchen, _ = make_seven_scenes(tmp_path / "kitchen")
    own = load_sequence(kitchen, color_intrinsic=load_sequence(kitchen).intrinsic)
    assert own.color_extrinsic is None and own.color_registered  # the given intrinsic, at the depth camera
    moved = load_sequence(kitchen, color_extrinsic=rig)
    np.testing.assert_allclose(np.asarray(moved.color_intrinsic.intrinsic_matrix), moved.K)
    np.testing.assert_array_equal(moved.color_extrinsic, rig)


def test_seven_scenes_missing_or_lost_poses_leave_only_their_frames_out(tmp_path):
    root, poses = make_seven_scenes(tmp_path / "kitchen", n=3)
    (root / "frame-000000.pose.txt").unlink()
    (root / "frame-000002.pose.txt").write_text("inf inf inf inf\n" * 4)  # 7-Scenes' mark of lost tracking
    with pytest.warns(UserWarning, match=r"2 of 3 frames .* \[0, 2\]"):
        seq = load_sequence(root)
    np.testing.assert_array_equal(seq.gt_valid, [False, True, False])
    np.testing.assert_allclose(seq.gt_poses[1], poses[1], atol=1e-12)


# -- tiny Open3D / Redwood folder ---------------------------------------------------------
RW_W, RW_H = 40, 30


def make_redwood(root: Path, n: int = 3, depth_scale: float | None = 2000.0, raw=3000) -> tuple[Path, np.ndarray]:
    for k in range(n):
        write_rgb(root / "color" / f"{k:05d}.png", np.full((RW_H, RW_W, 3), (k, 2 * k, 3 * k), np.uint8))
        write_depth(root / "depth" / f"{k:05d}.png", np.full((RW_H, RW_W), raw, np.uint16))
    K = np.array([[45.0, 0, 19.5], [0, 47.0, 14.0], [0, 0, 1]])
    data = {"width": RW_W, "height": RW_H, "intrinsic_matrix": K.T.ravel().tolist()}  # column-major
    if depth_scale is not None:
        data["depth_scale"] = depth_scale
    (root / "camera.json").write_text(json.dumps(data))
    poses = np.stack([rigid([0.05 * k, 0.1, -0.2 * k], [k, 0.5, -0.25 * k]) for k in range(n)])
    write_log_trajectory(root / "traj.log", poses)
    return root, poses


def test_redwood_reader(tmp_path):
    root, poses = make_redwood(tmp_path / "rw")
    seq = load_sequence(root)
    assert len(seq) == 3 and seq.image_size == (RW_H, RW_W)
    # column-major JSON: cx, cy land in the last column, not the last row
    np.testing.assert_allclose(seq.K, [[45.0, 0, 19.5], [0, 47.0, 14.0], [0, 0, 1]])
    assert np.all(seq[1].depth == 1.5)  # 3000 / depth_scale 2000 from the JSON
    assert tuple(seq[2].color[0, 0]) == (2, 4, 6)
    np.testing.assert_allclose(seq.gt_poses, poses, atol=1e-9)
    np.testing.assert_array_equal(seq.timestamps, [0, 1, 2])
    # registered: the colour intrinsic is the depth one
    np.testing.assert_array_equal(np.asarray(seq.color_intrinsic.intrinsic_matrix), seq.K)


def test_redwood_depth_scale_default_and_override(tmp_path):
    root, _ = make_redwood(tmp_path / "rw", depth_scale=None, raw=1500)
    assert np.all(load_sequence(root)[0].depth == 1.5)  # default 1000
    assert np.all(load_sequence(root, depth_scale=3000)[0].depth == 0.5)  # explicit wins


def test_redwood_log_length_mismatch_warns(tmp_path):
    root, poses = make_redwood(tmp_path / "rw")
    write_log_trajectory(root / "traj.log", poses[:2])
    with pytest.warns(UserWarning, match="2 poses for 3 frames"):
        seq = load_sequence(root)
    assert seq.gt_poses is None


def test_redwood_no_warning_when_intrinsic_given(tmp_path):
    root, _ = make_redwood(tmp_path / "rw")
    (root / "camera.json").unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_sequence(root, intrinsic=pinhole(RW_W, RW_H, 40.0, 40.0, 19.5, 14.5))
    assert seq.intrinsic.get_focal_length() == pytest.approx((40.0, 40.0))


def test_log_trajectory_round_trip(tmp_path):
    poses = np.stack([rigid([0.3, -0.1, 0.2], [1.25, -2.5, 0.125]), rigid([0, 0, 0], [0, 0, 0])])
    write_log_trajectory(tmp_path / "t.log", poses)
    lines = (tmp_path / "t.log").read_text().splitlines()
    assert len(lines) == 10 and lines[0].split() == ["0", "0", "1"] and lines[5].split() == ["1", "1", "2"]
    np.testing.assert_allclose(read_log_trajectory(tmp_path / "t.log"), poses, atol=1e-10)


# -- the bundled sample ---------------------------------------------------------------------
def test_sample(sample):
    assert len(sample) == 11
    assert sample.image_size == (240, 320)
    assert sample.gt_poses.shape == (11, 4, 4)
    check_poses(sample.gt_poses)
    # fr1 calibration at half resolution, pixel centres at integers
    assert sample.K[0, 0] == pytest.approx(517.3 / 2) and sample.K[0, 2] == pytest.approx((318.6 + 0.5) / 2 - 0.5)
    frame = sample[0]
    assert frame.color.shape == (240, 320, 3) and frame.color.dtype == np.uint8
    valid = frame.depth[frame.depth > 0]
    assert valid.size > 0.5 * frame.depth.size
    assert 0.5 < np.median(valid) < 3.0 and valid.min() > 0.3 and valid.max() < 6.0
    # fr1/xyz moves a few cm between the 11 frames (1.2 s), not metres
    steps = np.linalg.norm(np.diff(sample.gt_poses[:, :3, 3], axis=0), axis=1)
    assert 0 < steps.max() < 0.2


def test_overrides_stride_and_max_frames(sample):
    seq = load_sample(stride=3)
    assert len(seq) == 4
    np.testing.assert_array_equal(seq.gt_poses, sample.gt_poses[::3])
    np.testing.assert_array_equal(seq[1].depth, sample[3].depth)
    np.testing.assert_array_equal(seq.timestamps, [0, 3, 6, 9])
    seq = load_sample(stride=3, max_frames=2)
    assert len(seq) == 2
    np.testing.assert_array_equal(seq.gt_poses, sample.gt_poses[[0, 3]])


def test_override_depth_trunc(sample):
    full = sample[0].depth
    seq = load_sample(depth_trunc=1.0)
    depth = seq[0].depth
    assert depth.max() <= 1.0
    assert ((full > 1.0) & (depth == 0)).sum() == (full > 1.0).sum() > 0  # far depth zeroed
    near = full <= 1.0
    np.testing.assert_array_equal(depth[near], full[near])  # the rest untouched


def test_override_image_scale(sample):
    seq = load_sample(image_scale=0.5)
    assert seq.image_size == (120, 160)
    frame = seq[0]
    assert frame.depth.shape == (120, 160) and frame.color.shape == (120, 160, 3)
    K0, K = sample.K, seq.K
    assert K[0, 0] == pytest.approx(K0[0, 0] / 2) and K[1, 1] == pytest.approx(K0[1, 1] / 2)
    # pixel centres at integers: (c + 0.5) * s - 0.5
    assert K[0, 2] == pytest.approx((K0[0, 2] + 0.5) * 0.5 - 0.5)
    assert K[1, 2] == pytest.approx((K0[1, 2] + 0.5) * 0.5 - 0.5)
    # nearest-neighbour depth: every value comes from its 2x2 block at full resolution
    full = sample[0].depth
    blocks = full.reshape(120, 2, 160, 2).transpose(0, 2, 1, 3).reshape(120, 160, 4)
    assert (blocks == frame.depth[..., None]).any(-1).all()
    # area-averaged colour: mean colour preserved
    assert np.abs(frame.color.mean((0, 1)) - sample[0].color.mean((0, 1))).max() < 1.0
    np.testing.assert_array_equal(seq.gt_poses, sample.gt_poses)
    # at_scale() on the sequence gives the same
    np.testing.assert_array_equal(sample.at_scale(0.5)[0].depth, frame.depth)


def test_override_intrinsic(sample):
    mine = pinhole(320, 240, 250.0, 251.0, 160.0, 120.0)
    seq = load_sample(intrinsic=mine)
    np.testing.assert_allclose(seq.K, [[250, 0, 160], [0, 251, 120], [0, 0, 1]])


# -- poses -------------------------------------------------------------------------------
def test_check_poses():
    poses = np.stack([rigid([0.1, 0.2, 0.3], [1, 2, 3]), np.eye(4)])
    out = check_poses(poses.tolist())
    assert out.dtype == np.float64 and out.shape == (2, 4, 4)
    nan = poses.copy()
    nan[1, 0, 3] = np.nan
    with pytest.raises(PoseError, match=r"NaN/inf at frames \[1\]"):
        check_poses(nan)
    scaled = poses.copy()
    scaled[0, :3, :3] *= 2.0
    with pytest.raises(PoseError, match=r"not rigid.*\[0\]"):
        check_poses(scaled)
    reflect = poses.copy()
    reflect[1, :3, :3] = np.diag([1.0, 1.0, -1.0])  # orthonormal but det = -1
    with pytest.raises(PoseError, match=r"not rigid.*\[1\]"):
        check_poses(reflect)
    bottom = poses.copy()
    bottom[0, 3, 0] = 0.5
    with pytest.raises(PoseError, match="not rigid"):
        check_poses(bottom)
    with pytest.raises(PoseError, match=r"shape \(N, 4, 4\)"):
        check_poses(np.eye(4))
    with pytest.raises(PoseError, match="my_poses has 2 poses for 3 frames"):
        check_poses(poses, 3, "my_poses")


# -- RGBDSequence in memory ---------------------------------------------------------------
def small_intrinsic():
    return pinhole(8, 6, 5.0, 5.0, 3.5, 2.5)


def test_from_rgbd_images_numpy_pairs_with_depth_scale():
    color = np.zeros((6, 8, 3), np.uint8)
    color[..., 0] = 200
    raw = np.full((6, 8), 7500, np.uint16)
    raw[0, 0] = 0
    poses = np.stack([np.eye(4), rigid([0, 0, 0], [0.1, 0, 0])])
    seq = RGBDSequence.from_rgbd_images([(color, raw), (color, raw.astype(np.float32) / 5000)],
                                        small_intrinsic(), gt_poses=poses, depth_scale=5000.0)
    assert len(seq) == 2
    for frame in seq:
        assert frame.depth.dtype == np.float32
        assert frame.depth[0, 0] == 0 and np.all(frame.depth.ravel()[1:] == 1.5)
        assert tuple(frame.color[0, 0]) == (200, 0, 0)
    np.testing.assert_array_equal(seq.timestamps, [0, 1])
    np.testing.assert_array_equal(seq.gt_poses, poses)


def test_from_rgbd_images_open3d():
    color = np.full((6, 8, 3), (1, 2, 3), np.uint8)
    raw = np.full((6, 8), 2500, np.uint16)
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(color), o3d.geometry.Image(raw), depth_scale=1000.0, depth_trunc=10.0,
        convert_rgb_to_intensity=False)
    seq = RGBDSequence.from_rgbd_images([rgbd, rgbd], small_intrinsic(), timestamps=[3.0, 4.0])
    assert np.all(seq[1].depth == 2.5)
    assert tuple(seq[1].color[5, 7]) == (1, 2, 3)
    assert seq[1].timestamp == 4.0


def test_to_open3d_gives_metres():
    color = np.full((6, 8, 3), (10, 20, 30), np.uint8)
    raw = np.full((6, 8), 6000, np.uint16)
    raw[2, 3] = 20000
    seq = RGBDSequence.from_rgbd_images([(color, raw)], small_intrinsic(), depth_scale=5000.0, depth_trunc=3.0)
    rgbd = seq.to_open3d(0)
    assert isinstance(rgbd, o3d.geometry.RGBDImage)
    depth = np.asarray(rgbd.depth)
    assert depth.dtype == np.float32 and depth.shape == (6, 8)
    assert depth[0, 0] == pytest.approx(1.2) and depth[2, 3] == 0  # 4 m > depth_trunc 3 m
    assert tuple(np.asarray(rgbd.color)[1, 1]) == (10, 20, 30)


def test_select_and_indexing():
    pairs = [(np.full((6, 8, 3), k, np.uint8), np.full((6, 8), 1.0 + k, np.float32)) for k in range(5)]
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 2, 3] = np.arange(5)
    seq = RGBDSequence.from_rgbd_images(pairs, small_intrinsic(), timestamps=np.arange(5) * 0.1, gt_poses=poses)
    sub = seq.select([4, 1])
    assert len(sub) == 2
    assert np.all(sub[0].depth == 5.0) and np.all(sub[1].depth == 2.0)
    np.testing.assert_array_equal(sub.gt_poses[:, 2, 3], [4, 1])
    np.testing.assert_allclose(sub.timestamps, [0.4, 0.1])
    assert sub[0].index == 0  # indices are local to the sub-sequence
    masked = seq.select(np.array([True, False, True, False, False]))
    np.testing.assert_array_equal(masked.gt_poses[:, 2, 3], [0, 2])
    assert len(seq.select(range(1, 5, 2))) == 2
    assert seq[-1].index == 4 and np.all(seq[-1].depth == 5.0)
    with pytest.raises(IndexError):
        seq[5]
    with pytest.raises(InputError, match="select"):
        seq["1"]
    sliced = seq[1:5:2]  # a slice is a sub-sequence, as select(range(1, 5, 2))
    assert isinstance(sliced, RGBDSequence) and len(sliced) == 2
    np.testing.assert_array_equal(sliced.gt_poses[:, 2, 3], [1, 3])
    assert np.all(sliced[1].depth == 4.0) and len(seq[-2:]) == 2
    with pytest.raises(InputError, match="no frames"):
        seq[3:1]
    assert "5 frames" in repr(seq) and "8x6" in repr(seq)


def test_select_nothing_raises_input_error():
    pair = (np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.float32))
    seq = RGBDSequence.from_rgbd_images([pair, pair], small_intrinsic())
    with pytest.raises(InputError, match="no frames selected"):
        seq.select([])


def test_select_empty_mask_raises_input_error():
    pair = (np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.float32))
    seq = RGBDSequence.from_rgbd_images([pair, pair], small_intrinsic())
    with pytest.raises(InputError, match="no frames selected"):
        seq.select(np.array([False, False]))


# -- laziness -----------------------------------------------------------------------------
def test_sequence_is_lazy():
    calls = []

    def reader(k):
        def read():
            calls.append(k)
            return np.zeros((6, 8, 3), np.uint8), np.full((6, 8), 1.0 + k, np.float32)
        return read

    seq = RGBDSequence([reader(k) for k in range(2000)], small_intrinsic())
    assert calls == [] and len(seq) == 2000
    sub = seq.select(range(0, 2000, 10)).at_scale(0.5)
    assert calls == [] and len(sub) == 200
    frame = seq[1234]
    assert calls == [1234] and np.all(frame.depth == 1235.0)
    assert np.all(sub[3].depth == 31.0)
    assert calls == [1234, 30]


def test_load_sequence_reads_only_frame_0(tmp_path, monkeypatch):
    root, _ = make_redwood(tmp_path / "rw", n=4)
    read = []
    original = images_module.read_image
    monkeypatch.setattr(images_module, "read_image", lambda path, *a: read.append(Path(path).name) or original(path, *a))
    seq = load_sequence(root)
    assert sorted(read) == ["00000.png", "00000.png"]  # colour + depth of frame 0 (check_first_frame)
    read.clear()
    seq[2]
    assert read == ["00002.png", "00002.png"]


# -- shared real data (skipped when ../shared/data is absent) -------------------------------
@pytest.mark.data
def test_shared_tum(shared_data):
    seq = load_sequence(shared_data / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz")
    assert len(seq) > 30 and seq.image_size == (480, 640)
    assert seq.intrinsic.get_focal_length() == pytest.approx((517.3, 516.5))
    assert seq.gt_poses is not None and seq.gt_poses.shape == (len(seq), 4, 4)
    assert np.all(np.diff(seq.timestamps) > 0)
    valid = seq[0].depth[seq[0].depth > 0]
    assert 0.5 < np.median(valid) < 3.0


@pytest.mark.data
def test_shared_seven_scenes(shared_data):
    seq = load_sequence(shared_data / "7scenes_redkitchen" / "every10th_0-990")
    assert len(seq) == 100 and seq.image_size == (480, 640)
    np.testing.assert_allclose(seq.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    assert seq.gt_poses is not None
    np.testing.assert_array_equal(seq.timestamps[:3], [0, 10, 20])
    depth = seq[0].depth
    assert depth.max() < 10.0  # 65535 raw marks are gone
    assert 0.5 < np.median(depth[depth > 0]) < 4.0


@pytest.mark.data
def test_shared_redwood(shared_data):
    seq = load_sequence(shared_data / "redwood_livingroom1_open3d")
    assert len(seq) == 5 and seq.image_size == (480, 640)
    np.testing.assert_allclose(seq.K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(seq.gt_poses[0, :3, 3], [2, 2, -0.3], atol=1e-6)
    depth = seq[0].depth
    assert depth[depth > 0].min() == pytest.approx(0.96, abs=0.02)
    assert depth.max() == pytest.approx(2.70, abs=0.02)


def test_write_sequence_round_trips_through_load_sequence(tmp_path):
    from open3d_pnerf.data import write_sequence
    from open3d_pnerf.synthetic import synthetic_sequence

    seq = synthetic_sequence(3, 64, 48).sequence
    folder = write_sequence(seq, tmp_path / "seq", depth_scale=1000.0)
    back = load_sequence(folder)
    assert len(back) == 3 and back.image_size == (48, 64)
    np.testing.assert_allclose(back.K, seq.K)
    np.testing.assert_allclose(back.gt_poses, seq.gt_poses, atol=1e-9)
    for i in range(3):
        np.testing.assert_allclose(back[i].depth, seq[i].depth, atol=0.5e-3 + 1e-6)  # 1 mm steps
        np.testing.assert_array_equal(back[i].color, seq[i].color)


def test_write_sequence_refuses_depth_that_overflows_16_bits(tmp_path):
    from open3d_pnerf.data import write_sequence
    from open3d_pnerf.synthetic import synthetic_sequence

    with pytest.raises(InputError, match="overflows 16 bits"):
        write_sequence(synthetic_sequence(1, 64, 48).sequence, tmp_path / "seq", depth_scale=50000.0)
