"""COLMAP binary models and LLFF scenes (issue 7): exact round trips through files written here
in COLMAP's documented format, bad files named in errors, and the shared LLFF fern scene."""

from __future__ import annotations

import json
import struct

import cv2
import numpy as np
import pytest
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import open3d_pnerf as pn
from open3d_pnerf import cli
from open3d_pnerf.data import load_sequence, read_llff, sfm_pose_covariances, write_sequence
from open3d_pnerf.data.colmap import read_cameras_binary, read_images_binary, read_points3d_binary
from open3d_pnerf.errors import DatasetError, InputError
from open3d_pnerf.evaluation import heldout_scores
from open3d_pnerf.model import build_model


# -- writers of COLMAP's binary format (colmap.github.io/format.html) -------------------------
def write_cameras(path, cameras):
    """cameras: [(id, model id, width, height, params)]."""
    data = struct.pack("<Q", len(cameras))
    for cam_id, model_id, width, height, params in cameras:
        data += struct.pack("<iiQQ", cam_id, model_id, width, height) + struct.pack(f"<{len(params)}d", *params)
    path.write_bytes(data)


def write_images(path, images):
    """images: [(id, qvec wxyz, tvec, camera id, name, [(x, y, point3D id)])]."""
    data = struct.pack("<Q", len(images))
    for image_id, q, t, cam_id, name, points in images:
        data += struct.pack("<idddddddi", image_id, *q, *t, cam_id) + name.encode() + b"\0"
        data += struct.pack("<Q", len(points)) + b"".join(struct.pack("<ddq", *p) for p in points)
    path.write_bytes(data)


def write_points(path, points):
    """points: [(id, xyz, rgb, error, [(image id, point2D index)])]."""
    data = struct.pack("<Q", len(points))
    for point_id, xyz, rgb, error, track in points:
        data += struct.pack("<QdddBBBd", point_id, *xyz, *rgb, error) + struct.pack("<Q", len(track))
        data += b"".join(struct.pack("<ii", *t) for t in track)
    path.write_bytes(data)


POINTS = [
    (7, (1.5, -2.0, 30.25), (255, 0, 17), 0.75, [(1, 0), (2, 5)]),
    (9, (0.0, 1.0, 2.0), (1, 2, 3), 1.25, [(2, 1), (1, 3), (3, 0)]),
    (12, (-4.0, 0.5, 8.0), (9, 9, 9), 0.0, []),
]


def test_colmap_binary_round_trip(tmp_path):
    write_cameras(tmp_path / "cameras.bin", [(1, 2, 4032, 3024, [3260.5, 2016.0, 1512.0, 0.02]),
                                              (3, 1, 640, 480, [500.0, 510.0, 320.5, 240.25])])
    cams = read_cameras_binary(tmp_path / "cameras.bin")
    assert sorted(cams) == [1, 3]
    assert (cams[1].model, cams[1].width, cams[1].height) == ("SIMPLE_RADIAL", 4032, 3024)
    np.testing.assert_array_equal(cams[1].params, [3260.5, 2016.0, 1512.0, 0.02])
    assert cams[1].principal_point == (2016.0, 1512.0)
    assert cams[3].model == "PINHOLE" and cams[3].principal_point == (320.5, 240.25)

    q = Rotation.from_euler("z", 90, degrees=True).as_quat()  # x, y, z, w
    write_images(tmp_path / "images.bin", [
        (4, (q[3], *q[:3]), (1.0, 2.0, 3.0), 1, "IMG_2.JPG", [(10.5, 20.25, 7), (3.0, 4.0, -1)]),
        (2, (1.0, 0, 0, 0), (0.0, 0.0, 0.0), 3, "IMG_1.JPG", []),
    ])
    images = read_images_binary(tmp_path / "images.bin")
    assert list(images) == [4, 2] and images[4].name == "IMG_2.JPG" and images[2].camera_id == 3
    np.testing.assert_array_equal(images[4].xys, [[10.5, 20.25], [3.0, 4.0]])
    np.testing.assert_array_equal(images[4].point3d_ids, [7, -1])
    assert images[2].xys.shape == (0, 2) and images[2].point3d_ids.shape == (0,)
    # world-to-camera x_c = R x_w + t with R a +90 deg turn about z: the camera centre is -R^T t
    pose = images[4].camera_to_world()
    rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(pose[:3, :3], rz.T, atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], -rz.T @ [1.0, 2.0, 3.0], atol=1e-12)

    write_points(tmp_path / "points3D.bin", POINTS)
    pts = read_points3d_binary(tmp_path / "points3D.bin")
    assert len(pts) == 3
    np.testing.assert_array_equal(pts.ids, [7, 9, 12])
    np.testing.assert_array_equal(pts.xyz, [p[1] for p in POINTS])
    np.testing.assert_array_equal(pts.rgb, [p[2] for p in POINTS])
    assert pts.rgb.dtype == np.uint8
    np.testing.assert_array_equal(pts.error, [0.75, 1.25, 0.0])
    np.testing.assert_array_equal(pts.track_lengths, [2, 3, 0])
    np.testing.assert_array_equal(pts.track_image_ids, [1, 2, 2, 1, 3])
    np.testing.assert_array_equal(pts.track_point2d, [0, 5, 1, 3, 0])
    # image ids -> rows: 1 -> 2, 2 -> 0, 3 -> 1
    np.testing.assert_array_equal(pts.observed({1: 2, 2: 0, 3: 1}, 3), [[1, 0, 1], [1, 1, 1], [0, 0, 0]])
    with pytest.raises(InputError, match=r"image ids \[3\]"):
        pts.observed({1: 0, 2: 1}, 2)


@pytest.mark.parametrize("cut", [0, 5, 8 + 20, 8 + 51 + 8 + 4, -1])
def test_truncated_points_file_is_named(tmp_path, cut):
    write_points(tmp_path / "points3D.bin", POINTS)
    data = (tmp_path / "points3D.bin").read_bytes()
    (tmp_path / "points3D.bin").write_bytes(data[:cut])
    with pytest.raises(DatasetError, match=r"points3D\.bin: truncated"):
        read_points3d_binary(tmp_path / "points3D.bin")


def test_bad_colmap_files_are_named(tmp_path):
    write_points(tmp_path / "points3D.bin", POINTS)
    (tmp_path / "points3D.bin").write_bytes((tmp_path / "points3D.bin").read_bytes() + b"\0")
    with pytest.raises(DatasetError, match=r"points3D\.bin: 1 unexpected bytes"):
        read_points3d_binary(tmp_path / "points3D.bin")
    write_cameras(tmp_path / "cameras.bin", [(1, 42, 10, 10, [])])
    with pytest.raises(DatasetError, match=r"cameras\.bin: camera 1 has unknown model id 42"):
        read_cameras_binary(tmp_path / "cameras.bin")
    write_images(tmp_path / "images.bin", [(1, (1.0, 0, 0, 0), (0.0, 0, 0), 1, "a.png", [])])
    (tmp_path / "images.bin").write_bytes((tmp_path / "images.bin").read_bytes()[:-12])  # into the name
    with pytest.raises(DatasetError, match=r"images\.bin: truncated"):
        read_images_binary(tmp_path / "images.bin")
    with pytest.raises(DatasetError, match="COLMAP file not found: .*nothing.bin"):
        read_cameras_binary(tmp_path / "nothing.bin")


# -- a small LLFF folder ----------------------------------------------------------------------
FULL_H, FULL_W, FULL_F = 12, 16, 20.0


def opencv_poses() -> np.ndarray:
    """Three camera-to-world poses (OpenCV axes): identity, shifted in x, turned about y."""
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[1, :3, 3] = [0.5, 0.0, 0.0]
    poses[2, :3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    poses[2, :3, 3] = [-0.5, 0.1, 0.2]
    return poses


def make_llff(root, n_images: int = 3, factor: int = 2, points=None, images_bin=None, cameras=True):
    """An LLFF folder with `n_images` PNGs in images_<factor>/ and the poses of opencv_poses()."""
    root.mkdir()
    rows = []
    for pose in opencv_poses():
        right, down, forward, t = pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3]
        mat = np.stack([down, right, -forward, t, [FULL_H, FULL_W, FULL_F]], axis=1)  # LLFF's columns
        rows.append(np.concatenate([mat.ravel(), [1.0, 9.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    (root / f"images_{factor}").mkdir()
    for i in range(n_images):
        cv2.imwrite(str(root / f"images_{factor}" / f"image{i:03d}.png"),
                    np.full((FULL_H // factor, FULL_W // factor, 3), 40 * i, np.uint8))
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    if cameras:
        write_cameras(model / "cameras.bin", [(1, 0, FULL_W, FULL_H, [FULL_F, 8.5, 6.0])])
    write_points(model / "points3D.bin", POINTS if points is None else points)
    if images_bin is not None:
        write_images(model / "images.bin", images_bin)
    return root


def test_llff_reader_converts_poses_intrinsic_and_tracks(tmp_path):
    scene = read_llff(make_llff(tmp_path / "scene"), factor=2, scale=1.0)
    assert len(scene) == 3 and scene.image_size == (6, 8) and scene.name == "scene"
    np.testing.assert_allclose(scene.sfm.poses, opencv_poses(), atol=1e-12)
    # focal scaled by 1/2; COLMAP's principal point (8.5, 6.0) in pixels with centres at +0.5
    np.testing.assert_allclose(scene.K, [[10, 0, 8.5 / 2 - 0.5], [0, 10, 6.0 / 2 - 0.5], [0, 0, 1]])
    np.testing.assert_array_equal(scene.sfm.bounds, [[1.0, 9.0]] * 3)
    np.testing.assert_array_equal(scene.sfm.points.xyz, [p[1] for p in POINTS])
    np.testing.assert_allclose(scene.sfm.points.error, [0.375, 0.625, 0.0])  # pixels of the loaded images
    # no images.bin: image id k is row k - 1
    np.testing.assert_array_equal(scene.sfm.points.observed, [[1, 1, 0], [1, 1, 1], [0, 0, 0]])
    np.testing.assert_array_equal(scene.sfm.points.track_length, [2, 3, 0])
    frame = scene[2]
    assert frame.color.shape == (6, 8, 3) and frame.color.dtype == np.uint8 and (frame.color == 80).all()
    assert frame.depth.shape == (6, 8) and not frame.depth.any() and not scene.has_depth


def test_llff_reader_maps_image_ids_by_name_when_images_bin_exists(tmp_path):
    # ids in reverse name order: id 1 is image002 (row 2), id 3 is image000 (row 0)
    images = [(k, (1.0, 0, 0, 0), (0.0, 0, 0), 1, f"image{3 - k:03d}.png", []) for k in (1, 2, 3)]
    scene = read_llff(make_llff(tmp_path / "scene", images_bin=images), factor=2, scale=1.0)
    np.testing.assert_array_equal(scene.sfm.points.observed, [[0, 1, 1], [1, 1, 1], [0, 0, 0]])
    # without cameras.bin the principal point is the image centre
    scene = read_llff(make_llff(tmp_path / "centre", cameras=False), factor=2)
    np.testing.assert_allclose(scene.K[:2, 2], [3.5, 2.5])


def test_llff_bad_inputs_name_the_culprit(tmp_path):
    root = make_llff(tmp_path / "missing_poses")
    (root / "poses_bounds.npy").unlink()
    with pytest.raises(DatasetError, match="poses_bounds.npy not found"):
        read_llff(root, factor=2)

    root = make_llff(tmp_path / "shape")
    np.save(root / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy: expected finite \(N, 17\)"):
        read_llff(root, factor=2)

    root = make_llff(tmp_path / "no_images")
    with pytest.raises(DatasetError, match="images_4/ not found"):
        read_llff(root, factor=4)

    root = make_llff(tmp_path / "count", n_images=2)
    with pytest.raises(DatasetError, match=r"images_2: 2 images but .*poses_bounds\.npy has 3 poses"):
        read_llff(root, factor=2)

    root = make_llff(tmp_path / "truncated")
    points_file = root / "sparse" / "0" / "points3D.bin"
    points_file.write_bytes(points_file.read_bytes()[:-3])
    with pytest.raises(DatasetError, match=r"points3D\.bin: truncated"):
        read_llff(root, factor=2)

    root = make_llff(tmp_path / "bad_track", points=[(1, (0.0, 0, 1), (0, 0, 0), 1.0, [(1, 0), (4, 0)])])
    with pytest.raises(DatasetError, match=r"points3D\.bin: tracks observe image ids \[4\]"):
        read_llff(root, factor=2)

    root = make_llff(tmp_path / "camera_size")
    write_cameras(root / "sparse" / "0" / "cameras.bin", [(1, 0, 160, 120, [FULL_F, 80, 60])])
    with pytest.raises(DatasetError, match=r"cameras\.bin: the camera is 160x120"):
        read_llff(root, factor=2)

    with pytest.raises(InputError, match="factor must be an integer >= 1"):
        read_llff(make_llff(tmp_path / "factor"), factor=0)


# -- the shared LLFF fern scene (skipped when ../shared/data is absent) -------------------------
@pytest.fixture(scope="module")
def fern(shared_data):
    return read_llff(fern_folder(shared_data), factor=8, scale=1.0)


def fern_folder(shared_data):  # noqa: N802
    return shared_data / "llff_fern" / "nerf_llff_data" / "fern"


@pytest.mark.data
def test_fern_scene(fern, shared_data):
    rows = np.load(fern_folder(shared_data) / "poses_bounds.npy")
    assert len(fern) == 20 and fern.image_size == (378, 504)
    assert fern[0].color.shape == (378, 504, 3)
    np.testing.assert_allclose(fern.K[0, 0], rows[0, 14] / 8)
    assert fern.K[0, 0] == pytest.approx(3260.53 / 8, abs=0.01)
    np.testing.assert_allclose(fern.K[:2, 2], [251.5, 188.5])  # COLMAP's (2016, 1512) at 1/8
    rot = fern.sfm.poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-6)
    assert len(fern.sfm.points) == 10091 and fern.sfm.points.observed.any(1).all()
    assert np.median(fern.sfm.points.error) < 1.0  # pixels at 1/8


@pytest.mark.data
def test_fern_points_project_into_their_images_and_reproduce_the_llff_bounds(fern):
    """Checks the id -> row assumption (no images.bin in fern): LLFF computed each row's near/far
    bounds as the 0.1 / 99.9 percentiles of the depths of the points whose tracks include that
    image, so the right mapping reproduces them; a shifted mapping does not."""
    forward, centres = fern.sfm.poses[:, :3, 2], fern.sfm.poses[:, :3, 3]
    depth = np.einsum("mnk,nk->mn", fern.sfm.points.xyz[:, None] - centres[None], forward)  # (M, N) z-depths
    h, w = fern.image_size

    def bounds(observed):
        return np.array([np.percentile(depth[observed[:, i], i], [0.1, 99.9]) for i in range(len(fern))])

    np.testing.assert_allclose(bounds(fern.sfm.points.observed), fern.sfm.bounds, rtol=1e-9)  # exactly, in fact
    shifted = np.roll(fern.sfm.points.observed, 1, axis=1)
    assert np.abs(bounds(shifted) / fern.sfm.bounds - 1).max() > 0.03  # 7-8 % off
    # every observation lies in front of its camera and inside its image
    pts, cams = np.nonzero(fern.sfm.points.observed)
    q = np.einsum("mk,mkj->mj", fern.sfm.points.xyz[pts] - centres[cams], fern.sfm.poses[cams, :3, :3])
    assert (q[:, 2] > 0).all()
    u = q[:, 0] / q[:, 2] * fern.K[0, 0] + fern.K[0, 2]
    v = q[:, 1] / q[:, 2] * fern.K[1, 1] + fern.K[1, 2]
    inside = (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5)
    assert inside.mean() > 0.99


# -- LLFF folders as image-only sequences ------------------------------------------------------
# points in view of all three cameras of opencv_poses() (the fixture's POINTS mostly are not)
VISIBLE = [(k + 1, (x, y, 3.0), (200, 100, 50), 0.5, [(1, 0), (2, 0), (3, 0)])
           for k, (x, y) in enumerate([(0.0, 0.0), (0.3, -0.2), (-0.4, 0.3), (0.1, 0.4)])]


@pytest.mark.filterwarnings("ignore:frame 2 observes")
def test_load_sequence_reads_an_llff_folder_as_an_image_sequence(tmp_path):
    root = make_llff(tmp_path / "scene")
    seq = load_sequence(root)
    assert seq.sfm is not None and not seq.has_depth and len(seq) == 3
    assert seq.sfm.scale == pytest.approx(1 / 0.75)  # nearest bound (1.0) at 1 / 0.75 units, as NeRF
    np.testing.assert_allclose(seq.sfm.poses[:, :3, 3], opencv_poses()[:, :3, 3] / 0.75, atol=1e-12)
    np.testing.assert_allclose(seq.sfm.bounds, [[1 / 0.75, 9 / 0.75]] * 3)
    np.testing.assert_allclose(seq.sfm.points.xyz, np.array([p[1] for p in POINTS]) / 0.75)
    assert "3 images" in repr(seq) and "3 SfM points" in repr(seq)
    # select and rescale keep poses, covariances and the points' observations of the chosen frames
    sub = load_sequence(root, stride=2, image_scale=0.5)
    assert sub.sfm is not None and len(sub) == 2 and sub.image_size == (3, 4)
    np.testing.assert_array_equal(sub.sfm.points.observed, seq.sfm.points.observed[:, [0, 2]])
    np.testing.assert_allclose(sub.sfm.points.error, seq.sfm.points.error / 2)  # pixels of the smaller images
    np.testing.assert_array_equal(sub.sfm.poses, seq.sfm.poses[[0, 2]])
    np.testing.assert_array_equal(sub.sfm.covariances, seq.sfm.covariances[[0, 2]])
    assert sub[1].color.shape == (3, 4, 3)
    np.testing.assert_array_equal(sub.timestamps, [0, 2])  # frame numbers of the folder, as for RGB-D
    with pytest.raises(InputError, match=r"LLFF image folder .*depth_scale, depth_trunc do not apply"):
        load_sequence(root, depth_scale=5000, depth_trunc=3.0)


def test_image_sequences_are_refused_where_depth_is_needed_and_give_sparse_targets(tmp_path):
    seq = load_sequence(make_llff(tmp_path / "scene", points=VISIBLE))
    for call in (lambda: pn.track(seq), lambda: pn.tsdf_fusion(seq, seq.sfm.poses),
                 lambda: write_sequence(seq, tmp_path / "copy")):
        with pytest.raises(InputError, match="scene has no depth images .* sequence.sfm.poses"):
            call()
    targets = pn.depth_targets(seq, progress=False)  # the SfM poses and points
    pts = seq.sfm.points
    expected = pn.sparse_depth_targets(seq.sfm.poses, seq.K, seq.image_size, pts.xyz, pts.error, pts.observed,
                                       covariances=seq.sfm.covariances)
    for name in ("mean", "sigma", "valid", "support"):
        np.testing.assert_array_equal(getattr(targets, name), getattr(expected, name))
    assert targets.valid.any()


def test_sfm_pose_covariance_matches_the_scatter_of_re_estimated_poses():
    """Monte Carlo: observe 60 known points with Gaussian pixel noise of known sigma (0.5-2 px),
    re-estimate the pose by least squares over a right perturbation, 400 times: the scatter of
    the estimates is the predicted covariance (whitened, its eigenvalues are close to 1)."""
    rng = np.random.default_rng(3)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix()
    pose[:3, 3] = [0.3, -0.2, 1.0]
    q = np.stack([rng.uniform(-1, 1, 60), rng.uniform(-0.8, 0.8, 60), rng.uniform(2, 6, 60)], 1)
    xyz = q @ pose[:3, :3].T + pose[:3, 3]
    sigma = rng.uniform(0.5, 2.0, 60)
    cov = sfm_pose_covariances(pose[None], K, xyz, sigma, np.ones((60, 1), bool))[0]

    def project(xi):
        rot = pose[:3, :3] @ Rotation.from_rotvec(xi[:3]).as_matrix()
        cam = (xyz - pose[:3, 3] - pose[:3, :3] @ xi[3:]) @ rot
        return (cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]).ravel()

    clean = project(np.zeros(6))
    estimates = []
    for _ in range(400):
        observed = clean + rng.normal(0, np.repeat(sigma, 2))
        fit = least_squares(lambda xi: (project(xi) - observed) / np.repeat(sigma, 2), np.zeros(6))
        estimates.append(fit.x)
    scatter = np.cov(np.array(estimates).T)
    white = np.linalg.inv(np.linalg.cholesky(cov))
    eig = np.linalg.eigvalsh(white @ scatter @ white.T)
    assert 0.7 < eig.min() and eig.max() < 1.35, eig
    # twice the pixel noise: four times the covariance
    np.testing.assert_allclose(sfm_pose_covariances(pose[None], K, xyz, 2 * sigma, np.ones((60, 1), bool))[0],
                               4 * cov, rtol=1e-9)


def test_reconstruct_trains_on_an_image_sequence_with_its_sfm_poses(tmp_path):
    seq = load_sequence(make_llff(tmp_path / "scene", points=VISIBLE))
    cfg = pn.ReconstructionConfig.preset("test", max_steps=4, image_scale=1.0, progress=False)
    recon = pn.reconstruct(seq, cfg)
    np.testing.assert_array_equal(recon.poses, seq.sfm.poses)
    np.testing.assert_array_equal(recon.covariances, seq.sfm.covariances)
    assert recon.stats["timings"]["tracking_s"] < 0.1 and recon.stats["targets"]["valid_fraction"] > 0
    assert recon.depth_sigma_scale == 1.0  # no sensor depth to calibrate against
    with pytest.raises(InputError, match="calibrate_depth_sigma\\(\\): sequence: scene has no depth images"):
        recon.calibrate_depth_sigma(seq)
    # every ray lies between 0.9 x the nearest SfM bound and the farthest, in z-depth, inside the box
    near, far = 0.9 * seq.sfm.bounds[:, 0].min(), seq.sfm.bounds[:, 1].max()
    np.testing.assert_allclose(recon.model.depth_range.numpy(), [near, far], rtol=1e-6)
    u, v = torch.meshgrid(torch.arange(0.0, seq.image_size[1], 3), torch.arange(0.0, seq.image_size[0], 3),
                          indexing="xy")
    rays = recon.model.camera_rays(seq.sfm.poses[1], seq.K, u.reshape(-1), v.reshape(-1))
    np.testing.assert_allclose((rays.near / rays.norms).numpy(), near, rtol=1e-5)
    np.testing.assert_allclose((rays.far / rays.norms).numpy(), far, rtol=1e-5)  # the box holds the frusta
    recon.save(tmp_path / "saved")
    np.testing.assert_allclose(pn.Reconstruction.load(tmp_path / "saved").model.depth_range.numpy(), [near, far])


def test_cli_reconstructs_and_evaluates_an_llff_folder(tmp_path, capsys):
    root = make_llff(tmp_path / "scene", points=VISIBLE)
    out = tmp_path / "out"
    assert cli.main(["--quiet", "reconstruct", str(root), "--out", str(out), "--preset", "test", "--max-steps", "4",
                     "--holdout-every", "3"]) == cli.EXIT_OK
    report = json.loads((out / "report.json").read_text())
    assert set(report["scores"]) == {"model"} and "depth_l1" not in report["scores"]["model"]
    assert "No depth images" in (out / "report.md").read_text() and (out / "compare_frame_0000.png").is_file()
    np.testing.assert_allclose(np.load(out / "poses.npy"), load_sequence(root).sfm.poses)
    assert cli.main(["--quiet", "evaluate", str(out)]) == cli.EXIT_OK
    assert "No depth images" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.data
def test_reconstruct_learns_the_held_out_fern_views_from_ten_images(shared_data):
    """The paper's protocol at a smoke-test size: every 8th image held out, 10 training views."""
    seq = load_sequence(fern_folder(shared_data), image_scale=0.25)
    covs = seq.sfm.covariances
    assert (np.linalg.eigvalsh(covs) > 0).all() and np.sqrt(covs[:, [0, 1, 2], [0, 1, 2]]).max() < 1e-3  # rad
    cfg = pn.ReconstructionConfig.preset("test", holdout_every=8, train_views=10, max_steps=150, image_scale=1.0,
                                         progress=False)
    recon = pn.reconstruct(seq, cfg)
    assert recon.holdout_indices.tolist() == [0, 8, 16] and len(recon.train_indices) == 10
    trained = heldout_scores(recon, seq)["model"]
    recon.model = build_model(cfg, recon.aabb, depth_range=recon.model.depth_range)
    untrained = heldout_scores(recon, seq)["model"]
    print(f"fern held-out PSNR {trained['psnr']:.2f} dB (untrained {untrained['psnr']:.2f})")
    assert trained["psnr"] > untrained["psnr"] + 4 and trained["ssim"] > untrained["ssim"] + 0.2


def test_sfm_pose_covariance_of_a_frame_whose_points_do_not_fix_it_is_unbounded():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    xyz = np.array([[0.0, 0, 2]] * 3 + [[0.1, 0.1, 2], [-0.2, 0.1, 3], [0.3, -0.1, 2.5], [0.0, 0.2, 4]])
    observed = np.array([[1, 0]] * 3 + [[0, 1]] * 4, bool)  # frame 0 sees one point three times
    with pytest.warns(UserWarning, match="frame 0: its 3 SfM points do not fix its pose"):
        cov = sfm_pose_covariances(np.tile(np.eye(4), (2, 1, 1)), K, xyz, np.full(7, 0.5), observed)
    np.testing.assert_array_equal(cov[0], np.eye(6) * 1e6)
    assert np.linalg.eigvalsh(cov[1]).max() < 1e-2


def test_reconstruct_without_sfm_points_boxes_the_camera_frusta(tmp_path):
    seq = load_sequence(make_llff(tmp_path / "scene", points=[]))
    cfg = pn.ReconstructionConfig.preset("test", max_steps=2, image_scale=1.0, progress=False)
    with pytest.warns(UserWarning, match="no SfM point gives a depth target"):
        recon = pn.reconstruct(seq, cfg)
    far = seq.sfm.poses[:, :3, 3] + seq.sfm.poses[:, :3, 2] * seq.sfm.bounds[:, 1:]  # optical axis at the far bound
    assert ((far >= recon.aabb[0] - 1e-5) & (far <= recon.aabb[1] + 1e-5)).all()
