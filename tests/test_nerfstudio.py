"""nerfstudio's transforms.json in and out, and Open3D's camera types at the API."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import open3d as o3d
import pytest

import open3d_pnerf as pn
from open3d_pnerf.data import load_sequence, write_nerfstudio
from open3d_pnerf.errors import DatasetError, InputError, PoseError


@pytest.fixture(scope="module")
def room():
    """Six frames of the synthetic room at 64x48 with exact poses (the sequence's ground truth)."""
    return pn.synthetic_sequence(6, 64, 48, seed=0).sequence


def project_opencv(point, pose, K):
    """Pixel (u, v) of a world point: our convention (OpenCV axes, pixel centres at integers)."""
    q = np.linalg.inv(pose)[:3] @ np.append(point, 1.0)
    return np.array([K[0, 0] * q[0] / q[2] + K[0, 2], K[1, 1] * q[1] / q[2] + K[1, 2]])


def project_nerfstudio(point, frame, meta):
    """Pixel (u, v) of a world point the way nerfstudio reads transforms.json: OpenGL camera axes
    (x right, y up, z backward) and pixel centres at +0.5."""
    q = np.linalg.inv(np.asarray(frame["transform_matrix"]))[:3] @ np.append(point, 1.0)
    return np.array([meta["fl_x"] * q[0] / -q[2] + meta["cx"], meta["fl_y"] * -q[1] / -q[2] + meta["cy"]])


def test_written_folder_projects_points_to_the_same_pixels_and_reads_back(room, tmp_path):
    folder = write_nerfstudio(room, tmp_path / "ns", poses=room.gt_poses)
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["depth_unit_scale_factor"] == 0.001
    frame0 = room[0]
    v, u = 20, 30
    point = (room.gt_poses[0] @ np.append(np.array([(u - room.K[0, 2]) / room.K[0, 0],
                                                    (v - room.K[1, 2]) / room.K[1, 1], 1.0]) * frame0.depth[v, u], 1))[:3]
    for i in range(len(room)):
        ours = project_opencv(point, room.gt_poses[i], room.K)
        theirs = project_nerfstudio(point, meta["frames"][i], meta)
        np.testing.assert_allclose(theirs, ours + 0.5, atol=1e-9)  # the same pixel in either convention
    seq = load_sequence(folder)
    assert seq.has_depth and len(seq) == 6 and seq.sfm is not None
    np.testing.assert_allclose(seq.sfm.poses, room.gt_poses, atol=1e-9)
    np.testing.assert_allclose(seq.K, room.K, atol=1e-9)
    for i in (0, 5):
        np.testing.assert_array_equal(seq[i].color, room[i].color)
        np.testing.assert_allclose(seq[i].depth, room[i].depth, atol=5e-4)  # millimetre PNGs
    # reconstruct() takes the capture's poses instead of tracking
    recon = pn.reconstruct(seq, pn.ReconstructionConfig.preset("test", max_steps=2, progress=False))
    np.testing.assert_array_equal(recon.poses, seq.sfm.poses)


def test_a_reconstruction_writes_its_poses_and_split_for_nerfstudio(room, tmp_path):
    cfg = pn.ReconstructionConfig.preset("test", max_steps=2, holdout_every=3, progress=False)
    recon = pn.reconstruct(room, cfg, poses=room.gt_poses)
    folder = recon.write_nerfstudio(tmp_path / "ns", room)
    meta = json.loads((folder / "transforms.json").read_text())
    assert meta["train_filenames"] == [f"images/frame_{i:05d}.png" for i in recon.train_indices]
    assert meta["val_filenames"] == meta["test_filenames"] == [f"images/frame_{i:05d}.png" for i in (0, 3)]
    np.testing.assert_allclose(load_sequence(folder).sfm.poses, recon.poses, atol=1e-9)
    with pytest.raises(InputError, match="has 5 frames"):
        recon.write_nerfstudio(tmp_path / "other", room.select(range(5)))


def make_phone_capture(root, room, depth: bool = True, distortion: float = 0.0):
    """A folder in the layout ns-process-data writes for a phone capture: JPEG images/, top-level
    OPENCV intrinsics with nerfstudio's +0.5 pixel centres, an applied_transform, and depth maps
    (16-bit millimetres) at half the image resolution, as a phone's depth sensor gives them."""
    (root / "images").mkdir(parents=True)
    (root / "depth").mkdir()
    K = room.K
    meta = {"w": 64, "h": 48, "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5,
            "k1": distortion, "k2": 0.0, "p1": 0.0, "p2": 0.0, "camera_model": "OPENCV",
            "applied_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "frames": []}
    for i in range(len(room)):
        frame = room[i]
        name = f"frame_{i + 1:05d}"
        cv2.imwrite(str(root / "images" / f"{name}.jpg"), cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 98])
        entry = {"file_path": f"images/{name}.jpg",
                 "transform_matrix": (room.gt_poses[i] @ np.diag([1.0, -1, -1, 1])).tolist()}
        if depth:
            small = cv2.resize(frame.depth, (32, 24), interpolation=cv2.INTER_NEAREST)
            cv2.imwrite(str(root / "depth" / f"{name}.png"), np.round(small * 1000).astype(np.uint16))
            entry["depth_file_path"] = f"depth/{name}.png"
        meta["frames"].append(entry)
    meta["frames"].reverse()  # nerfstudio sorts frames by file name; so must we
    (root / "transforms.json").write_text(json.dumps(meta, indent=2))
    return root


def test_a_phone_capture_in_ns_process_data_layout_loads_and_reconstructs(room, tmp_path):
    seq = load_sequence(make_phone_capture(tmp_path / "capture", room))
    assert seq.has_depth and seq.image_size == (48, 64)  # depth resized to the colour images
    np.testing.assert_allclose(seq.sfm.poses, room.gt_poses, atol=1e-9)
    depth = seq[2].depth
    assert depth.shape == (48, 64) and (depth > 0).mean() > 0.5
    np.testing.assert_allclose(np.median(depth[depth > 0]), np.median(room[2].depth[room[2].depth > 0]), rtol=0.05)
    cfg = pn.ReconstructionConfig.preset("test", max_steps=30, holdout_every=3, progress=False)
    recon = pn.reconstruct(seq, cfg)
    assert recon.stats["targets"]["valid_fraction"] > 0.3 and recon.stats["training"]["steps"] == 30


def test_an_image_only_capture_loads_with_bounds_and_reconstructs(room, tmp_path):
    root = make_phone_capture(tmp_path / "capture", room, depth=False)
    with pytest.warns(UserWarning, match="no depth images and no sparse points"):
        seq = load_sequence(root)
    assert not seq.has_depth and seq.sfm.bounds.shape == (6, 2)
    recon = pn.reconstruct(seq, pn.ReconstructionConfig.preset("test", max_steps=2, progress=False))
    assert (recon.aabb[1] - recon.aabb[0] > 1.0).all()  # the frusta, not a box around the cameras alone
    # sparse points in ply_file_path (ns-process-data's sparse_pc.ply) give the bounds instead
    points = room.gt_poses[0][:3, 3] + np.random.default_rng(0).normal(0, 0.5, (200, 3)) + [0, 0, 0]
    o3d.io.write_point_cloud(str(root / "sparse_pc.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.concatenate([pn.synthetic.room_scene(0).mesh.sample_points_uniformly(2000).points, points]))))
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "ply_file_path": "sparse_pc.ply"}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_sequence(root)
    near, far = seq.sfm.bounds.T
    assert (near > 0).all() and (far < 8).all() and (near < far).all()


def test_distorted_frames_are_undistorted_on_load(room, tmp_path):
    straight = load_sequence(make_phone_capture(tmp_path / "a", room))
    bent = load_sequence(make_phone_capture(tmp_path / "b", room, distortion=-0.2))
    # the same files, read as distorted: the centre stays, the corners move inward
    np.testing.assert_allclose(bent[0].color[24, 32], straight[0].color[24, 32], atol=3)
    assert np.abs(bent[0].color.astype(int) - straight[0].color.astype(int))[:5, :5].mean() > 3


def broken(tmp_path, room, edit):
    root = make_phone_capture(tmp_path / "capture", room)
    meta = json.loads((root / "transforms.json").read_text())
    edit(root, meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize("edit, error, names", [
    (lambda r, m: m.pop("fl_x"), DatasetError, ("transforms.json", "'fl_x' missing")),
    (lambda r, m: m["frames"][0].pop("transform_matrix"), DatasetError, ("transforms.json", "'transform_matrix'")),
    (lambda r, m: (r / m["frames"][1]["file_path"]).unlink(), DatasetError, ("file_path", "does not exist")),
    (lambda r, m: m["frames"][2].__setitem__("transform_matrix", np.diag([2.0, 1, 1, 1]).tolist()), PoseError,
     ("transform_matrix of frame images/frame_", "not rigid")),
    (lambda r, m: cv2.imwrite(str(r / m["frames"][0]["depth_file_path"]), np.zeros((20, 32), np.uint16)),
     DatasetError, ("depth image is 32x20", "aspect ratio")),
    (lambda r, m: m["frames"][3].pop("depth_file_path"), DatasetError, ("has no depth_file_path",)),
    (lambda r, m: m.__setitem__("camera_model", "OPENCV_FISHEYE"), DatasetError, ("OPENCV_FISHEYE",)),
    (lambda r, m: m["frames"][1].__setitem__("fl_x", 99.0), DatasetError, ("other intrinsics",)),
])
def test_bad_nerfstudio_folders_raise_errors_naming_the_field_or_file(room, tmp_path, edit, error, names):
    root = broken(tmp_path, room, edit)
    with pytest.raises(error) as info:
        seq = load_sequence(root)
        for i in range(len(seq)):  # a frame's files are read when it is used
            seq[i]
    for name in names:
        assert name in str(info.value), (name, str(info.value))


def test_open3d_camera_types_are_converted_at_the_api(room, tmp_path):
    cfg = pn.ReconstructionConfig.preset("test", max_steps=2, progress=False)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    parameters = []
    for pose in room.gt_poses:
        p = o3d.camera.PinholeCameraParameters()
        p.intrinsic, p.extrinsic = room.intrinsic, np.linalg.inv(pose)  # Open3D stores world-to-camera
        parameters.append(p)
    trajectory.parameters = parameters
    recon = pn.reconstruct(room, cfg, poses=trajectory)
    np.testing.assert_allclose(recon.poses, room.gt_poses, atol=1e-9)
    # render() takes PinholeCameraParameters (and its intrinsic) like a camera-to-world matrix
    a, b = recon.render(parameters[3]), recon.render(room.gt_poses[3], room.intrinsic)
    np.testing.assert_allclose(a["depth"], b["depth"], atol=1e-5)  # the pose inverted twice: equal to rounding
    # in a world far from its origin, a world-to-camera extrinsic passed as a pose is caught
    shift = np.eye(4)
    shift[:3, 3] = [20.0, -5.0, 3.0]
    moved = pn.reconstruct(room, cfg, poses=shift @ room.gt_poses)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        moved.render(moved.poses[3])
    with pytest.warns(UserWarning, match="world-to-camera extrinsic"):
        moved.render(np.linalg.inv(moved.poses[3]))
    # a Trajectory brings its covariances
    covariances = np.tile(np.diag([1e-6] * 3 + [1e-4] * 3), (len(room), 1, 1))
    traj = pn.Trajectory(room.gt_poses, covariances, o3d.pipelines.registration.PoseGraph(), [], [], room.timestamps)
    recon = pn.reconstruct(room, cfg, poses=traj)
    np.testing.assert_array_equal(recon.covariances, traj.covariances)
    # Open3D reads the trajectory files a reconstruction writes
    recon.save(tmp_path / "saved")
    back = o3d.io.read_pinhole_camera_trajectory(str(tmp_path / "saved" / "trajectory.json"))
    np.testing.assert_allclose(np.linalg.inv(np.stack([p.extrinsic for p in back.parameters])), recon.poses, atol=1e-6)
    assert back.parameters[0].intrinsic.width == recon.intrinsic.width
    log = o3d.io.read_pinhole_camera_trajectory(str(tmp_path / "saved" / "trajectory.log"))
    np.testing.assert_allclose(np.linalg.inv(np.stack([p.extrinsic for p in log.parameters])), recon.poses, atol=1e-6)


def test_notebook_representations(room):
    cfg = pn.ReconstructionConfig.preset("test", max_steps=2, holdout_every=3, progress=False)
    recon = pn.reconstruct(room, cfg, poses=room.gt_poses)
    md = recon._repr_markdown_()
    assert "| frames | 6: 4 trained, 2 held out |" in md and "loss `pnerf`" in md
    comparison = pn.compare_with_tsdf(room, reconstruction=recon, progress=False)
    assert comparison._repr_markdown_() == comparison.markdown() and "| PSNR, whole frame (dB) |" in comparison.markdown()
