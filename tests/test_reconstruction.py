"""Tests of open3d_pnerf.reconstruction and open3d_pnerf.export.

The end-to-end tests share one short real training run on the bundled sample (the "test"
preset, 150 steps, ~20 s on one core).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import open3d as o3d
import plyfile
import pytest
import torch

from open3d_pnerf import Reconstruction, ReconstructionConfig, reconstruct
from open3d_pnerf.camera import backproject, scale_intrinsic
from open3d_pnerf.data import load_sample
from open3d_pnerf.errors import CheckpointError, InputError, TrainingInterrupted
from open3d_pnerf.export import (
    export_geometry,
    mesh_from_renders,
    point_cloud_from_renders,
    read_mesh_ply,
    read_point_cloud_ply,
    sensor_geometry,
    uncertainty_colors,
    write_mesh_ply,
    write_point_cloud_ply,
)
from open3d_pnerf.stages import split_frames
from open3d_pnerf.scene import scene_box
from open3d_pnerf import stages
from open3d_pnerf.error_law import DepthErrorLaw
from open3d_pnerf.storage import FORMAT_VERSION
from open3d_pnerf.training import Trainer, read_checkpoint
from open3d_pnerf.targets import DepthTargets, depth_targets

TRAIN_STEPS = 150  # enough for a confident surface to export (opacity >= 0.9, std <= 5 cm)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


def intrinsic(w=40, h=30, f=30.0):
    return o3d.camera.PinholeCameraIntrinsic(w, h, f, f, (w - 1) / 2, (h - 1) / 2)


# -- split_frames / scene_box ------------------------------------------------------------------
def test_split_frames_holds_out_every_kth_frame():
    train, hold = split_frames(11, 4)
    np.testing.assert_array_equal(hold, [0, 4, 8])
    np.testing.assert_array_equal(train, [1, 2, 3, 5, 6, 7, 9, 10])
    train, hold = split_frames(5, 0)
    np.testing.assert_array_equal(train, np.arange(5))
    assert hold.size == 0
    with pytest.raises(InputError, match="holdout_every=1"):
        split_frames(10, 1)
    with pytest.raises(InputError, match="fewer than 2"):
        split_frames(3, 2)  # holds out 0 and 2, leaves one frame


def synthetic_targets(poses, K, h=12, w=16, z=2.0):
    n = len(poses)
    mean = np.full((n, h, w), z, np.float32)
    valid = np.ones((n, h, w), bool)
    return DepthTargets(mean, np.full_like(mean, 0.01), valid, np.ones((n, h, w), np.uint8),
                        np.zeros((n, h, w), bool))


def test_scene_box_holds_camera_centres_and_surface_points():
    K = np.array([[10.0, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0, 0, 0], [1.0, 0, -0.5], [-0.5, 0.3, 0]]
    targets = synthetic_targets(poses, K)
    box = scene_box(targets, poses, K, stride=1)
    assert box.shape == (2, 3) and box.dtype == np.float32
    assert (box[0] <= poses[:, :3, 3]).all() and (poses[:, :3, 3] <= box[1]).all()
    # the surface at z = 2 (plus camera z offsets) is inside, with a margin of >= 5 cm
    assert box[1, 2] >= 2.0 + 0.05 and box[0, 2] <= -0.5 - 0.05
    # back-projected image corners of frame 0 at z = 2: x in 2 * [-0.75, 0.75]
    assert box[0, 0] <= -1.5 and box[1, 0] >= 1.0 + 1.5


def test_scene_box_on_the_sample_contains_all_camera_centres():
    seq = load_sample().at_scale(0.25)
    targets = depth_targets(seq, poses=seq.gt_poses, progress=False)
    box = scene_box(targets, seq.gt_poses, seq.K)
    centres = seq.gt_poses[:, :3, 3]
    assert (box[0] < centres).all() and (centres < box[1]).all()
    # and most target points (the desk, 0.5-2.5 m away) lie inside it
    K = seq.K
    inside = []
    for i in range(len(seq)):
        v, u = np.nonzero(targets.valid[i])
        z = targets.mean[i][v, u]
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        world = cam @ seq.gt_poses[i][:3, :3].T + seq.gt_poses[i][:3, 3]
        inside.append(((world >= box[0]) & (world <= box[1])).all(1))
    assert np.concatenate(inside).mean() > 0.98


# -- export ------------------------------------------------------------------------------------
def test_backproject_pinhole_geometry():
    K = np.array([[100.0, 0, 20], [0, 50.0, 10], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    depth = np.zeros((21, 41), np.float32)
    depth[10, 20] = 2.0  # principal point
    depth[10, 40] = 4.0  # 20 px right: x = 20 / 100 * 4
    pts, _ = backproject(depth, K, pose)
    np.testing.assert_allclose(pts, [[1, 2, 5.0], [1.8, 2, 7.0]], atol=1e-6)


def plane_renders(n=2, h=30, w=40, z=1.5):
    renders, poses = [], []
    for i in range(n):
        pose = np.eye(4)
        pose[0, 3] = 0.05 * i
        op = np.ones((h, w), np.float32)
        std = np.full((h, w), 0.01, np.float32)
        op[:, :5] = 0.5  # low opacity: dropped
        std[:5, :] = 0.2  # too uncertain: dropped
        renders.append({"color": np.full((h, w, 3), 0.25, np.float32), "depth": np.full((h, w), z, np.float32),
                        "depth_std": std, "opacity": op})
        poses.append(pose)
    return renders, np.stack(poses)


def test_point_cloud_from_renders_keeps_confident_points_with_their_sigma():
    renders, poses = plane_renders()
    K = np.asarray(intrinsic().intrinsic_matrix)
    cloud, sigma = point_cloud_from_renders(renders, poses, K, min_opacity=0.9, max_std=0.05, voxel_size=0)
    assert isinstance(cloud, o3d.geometry.PointCloud)
    pts = np.asarray(cloud.points)
    assert len(pts) == len(sigma) == 2 * (30 - 5) * (40 - 5)
    np.testing.assert_allclose(pts[:, 2], 1.5, atol=1e-6)
    np.testing.assert_allclose(sigma, 0.01, atol=1e-7)
    np.testing.assert_allclose(np.asarray(cloud.colors), 0.25, atol=1e-6)
    # voxel downsampling keeps colour and sigma attached
    down, s2 = point_cloud_from_renders(renders, poses, K, voxel_size=0.05)
    assert 0 < len(down.points) == len(s2) < len(pts)
    np.testing.assert_allclose(s2, 0.01, atol=1e-6)
    # every 2nd pixel: rows 6, 8, .., 28 (12) and columns 6, .., 38 (17) of the confident 25 x 35 of each
    strided, s3 = point_cloud_from_renders(renders, poses, K, voxel_size=0, stride=2)
    assert len(strided.points) == len(s3) == 2 * 12 * 17


def test_point_cloud_ply_round_trip_keeps_depth_sigma(tmp_path):
    rng = np.random.default_rng(0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.random((50, 3))))
    cloud.colors = o3d.utility.Vector3dVector(rng.random((50, 3)))
    sigma = rng.random(50).astype(np.float32) * 0.01
    path = tmp_path / "sub" / "cloud.ply"
    write_point_cloud_ply(path, cloud, sigma)
    back, s = read_point_cloud_ply(path)
    np.testing.assert_allclose(np.asarray(back.points), np.asarray(cloud.points), atol=1e-6)
    np.testing.assert_allclose(s, sigma)
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".tmp")]
    write_point_cloud_ply(tmp_path / "plain.ply", cloud)
    plain, s_none = read_point_cloud_ply(tmp_path / "plain.ply")
    assert s_none is None and len(plain.points) == 50


def test_point_cloud_ply_reads_the_same_in_open3d_and_other_ply_readers(tmp_path):
    """Colours as uchar (Open3D's legacy reader divides any colour by 255: float colours came out
    black), depth_sigma as an extra float property every reader keeps."""
    rng = np.random.default_rng(1)
    colors = rng.integers(0, 256, (40, 3)) / 255.0
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.random((40, 3))))
    cloud.colors = o3d.utility.Vector3dVector(colors)
    sigma = rng.random(40).astype(np.float32)
    path = tmp_path / "cloud.ply"
    write_point_cloud_ply(path, cloud, sigma)
    legacy = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(legacy.colors), colors, atol=1e-6)
    tensor = o3d.t.io.read_point_cloud(str(path))
    assert tensor.point.colors.dtype == o3d.core.uint8
    np.testing.assert_array_equal(tensor.point.colors.numpy(), np.round(colors * 255))
    np.testing.assert_array_equal(tensor.point.depth_sigma.numpy()[:, 0], sigma)
    vertex = plyfile.PlyData.read(str(path))["vertex"].data
    assert vertex.dtype["red"] == np.uint8 and vertex.dtype["depth_sigma"] == np.float32
    np.testing.assert_array_equal(np.stack([vertex["red"], vertex["green"], vertex["blue"]], 1), np.round(colors * 255))
    np.testing.assert_array_equal(vertex["depth_sigma"], sigma)
    np.testing.assert_allclose(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), np.asarray(cloud.points),
                               atol=1e-6)


def write_sigma_plys(folder: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """A coloured sphere written as mesh.ply and cloud.ply (its vertices) with a random sigma per vertex:
    (sigma (V,) m, colours (V, 3) in [0, 1], the mesh's face count)."""
    rng = np.random.default_rng(2)
    mesh = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=8)
    colors = rng.integers(0, 256, (len(mesh.vertices), 3)) / 255.0
    mesh.vertex_colors = o3d.utility.Vector3dVector(colors)
    sigma = rng.random(len(mesh.vertices)).astype(np.float32) * 0.05
    cloud = o3d.geometry.PointCloud(mesh.vertices)
    cloud.colors = mesh.vertex_colors
    write_mesh_ply(folder / "mesh.ply", mesh, sigma)
    write_point_cloud_ply(folder / "cloud.ply", cloud, sigma)
    return sigma, colors, len(mesh.triangles)


def test_meshlab_reads_the_sigma_of_every_vertex_and_point(tmp_path):
    """pymeshlab (MeshLab's own reader) takes one per-vertex scalar, from a property named quality:
    the mesh's and the cloud's sigma come back there, beside their colours."""
    import pymeshlab

    sigma, colors, n_faces = write_sigma_plys(tmp_path)
    for name, faces in (("mesh.ply", n_faces), ("cloud.ply", 0)):
        meshes = pymeshlab.MeshSet()
        meshes.load_new_mesh(str(tmp_path / name))
        read = meshes.current_mesh()
        assert read.vertex_number() == len(sigma) and read.face_number() == faces
        assert read.has_vertex_scalar(), name
        np.testing.assert_allclose(read.vertex_scalar_array(), sigma, rtol=1e-6)
        np.testing.assert_allclose(read.vertex_color_matrix()[:, :3], colors, atol=1e-6)
    assert read_mesh_ply(tmp_path / "mesh.ply")[1] == pytest.approx(sigma)


CLOUDCOMPARE = shutil.which("CloudCompare")


@pytest.mark.skipif(CLOUDCOMPARE is None, reason="no CloudCompare (Debian's cloudcompare) to read the PLYs with")
def test_cloudcompare_reads_the_sigma_as_a_scalar_field(tmp_path):
    """CloudCompare's command line loads the mesh and the cloud, and its export of their vertices
    carries the sigma as the scalar field "depth sigma", beside the colours."""
    sigma, colors, _ = write_sigma_plys(tmp_path)
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    for name, extract in (("mesh.ply", ["-EXTRACT_VERTICES"]), ("cloud.ply", [])):
        out = tmp_path / f"{name}.txt"
        subprocess.run([CLOUDCOMPARE, "-SILENT", "-AUTO_SAVE", "OFF", "-O", str(tmp_path / name), *extract,
                        "-C_EXPORT_FMT", "ASC", "-SEP", "SEMICOLON", "-ADD_HEADER", "-SAVE_CLOUDS", "FILE", str(out)],
                       env=env, cwd=tmp_path, capture_output=True, timeout=120, check=True)
        lines = out.read_text().splitlines()
        assert lines[0] == "//X;Y;Z;R;G;B;depth sigma", name
        table = np.array([line.split(";") for line in lines[1:]], float)
        np.testing.assert_allclose(table[:, 6], sigma, rtol=1e-6)
        np.testing.assert_allclose(table[:, 3:6] / 255.0, colors, atol=1e-6)


def test_mesh_from_renders_fuses_a_plane(tmp_path):
    renders, poses = plane_renders(5, 60, 80)
    K = np.asarray(intrinsic(80, 60, 60.0).intrinsic_matrix)
    mesh = mesh_from_renders(renders, poses, K, voxel_size=0.02)
    assert isinstance(mesh, o3d.geometry.TriangleMesh) and len(mesh.triangles) > 100
    np.testing.assert_allclose(np.asarray(mesh.vertices)[:, 2], 1.5, atol=0.02)
    write_mesh_ply(tmp_path / "mesh.ply", mesh)
    back = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(back.triangles) == len(mesh.triangles)


def test_mesh_from_renders_of_three_confident_views_is_not_empty():
    renders, poses = plane_renders(3, 60, 80)
    K = np.asarray(intrinsic(80, 60, 60.0).intrinsic_matrix)
    mesh = mesh_from_renders(renders, poses, K, voxel_size=0.02)
    assert len(mesh.triangles) > 100


def test_mesh_from_renders_with_min_views_2_keeps_only_what_two_renders_see():
    """Two renders of the plane z = 1.5 m: the second has depth only in its left half. With
    min_views 2 the mesh spans the overlap only (x from -0.95 to ~0.05 m,
    where the second one looks, less a voxel); with 1 both views reach (x from -1 to 1)."""
    renders, poses = plane_renders(2, 60, 80)
    for r in renders:
        r["opacity"][:], r["depth_std"][:] = 1.0, 0.01
    renders[1]["depth"][:, 40:] = 0  # the second sees the left half only
    K = np.asarray(intrinsic(80, 60, 60.0).intrinsic_matrix)
    x_all = np.asarray(mesh_from_renders(renders, poses, K, voxel_size=0.02).vertices)[:, 0]
    x_two = np.asarray(mesh_from_renders(renders, poses, K, voxel_size=0.02, min_views=2).vertices)[:, 0]
    assert x_all.max() > 0.9 and -0.06 < x_two.max() < 0.1
    assert x_all.min() == pytest.approx(-1.0, abs=0.03) and x_two.min() == pytest.approx(-0.95, abs=0.03)  # the overlap


def test_mesh_trunc_voxels_sets_how_far_a_depth_step_is_bridged():
    """One render of a 10 cm depth step (left half at z = 1.0 m, right half at 1.1 m), 1 cm voxels:
    behind the foreground's edge the TSDF reaches back as far as its truncation, so the wall the
    mesh draws down from the edge ends about trunc_voxels voxels behind it (4: 1.04 m, 8: 1.08 m)
    and the rest of the step stays open."""
    depth = np.full((60, 80), 1.0, np.float32)
    depth[:, 40:] = 1.1
    render = {"color": np.full((60, 80, 3), 0.5, np.float32), "depth": depth,
              "depth_std": np.full((60, 80), 0.01, np.float32), "opacity": np.ones((60, 80), np.float32)}
    K = np.asarray(intrinsic(80, 60, 60.0).intrinsic_matrix)

    def wall_bottom(trunc_voxels):
        v = np.asarray(mesh_from_renders([render], np.eye(4)[None], K, voxel_size=0.01,
                                         trunc_voxels=trunc_voxels).vertices)
        wall = v[(np.abs(v[:, 0]) < 0.03) & (v[:, 2] > 1.015) & (v[:, 2] < 1.095)]
        return wall[:, 2].max()

    assert wall_bottom(4) == pytest.approx(1.04, abs=0.011)
    assert wall_bottom(8) == pytest.approx(1.08, abs=0.011)


def test_uncertainty_colors_map_sigma_to_a_colormap():
    sigma = np.array([0.0, 0.005, 0.01, 1.0])
    c = uncertainty_colors(sigma, vmax=0.01)
    assert c.shape == (4, 3) and (c >= 0).all() and (c <= 1).all()
    np.testing.assert_allclose(c[2], c[3])  # clipped at vmax
    assert not np.allclose(c[0], c[2])
    assert uncertainty_colors(np.zeros(0)).shape == (0, 3)


# -- Reconstruction.render on an analytic field ------------------------------------------------------
class WallField(torch.nn.Module):
    """Opaque half-space z >= z0 (world) with constant colour, inside the box `aabb`."""

    def __init__(self, aabb, z0=1.2, color=(0.1, 0.6, 0.3)):
        super().__init__()
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32))
        self.z0, self.color_value = z0, torch.tensor(color)

    def encode(self, x, known=None):
        return x

    def geometry(self, x, encoded=None):
        return torch.where(x[:, 2] >= self.z0, 1e3, 0.0), torch.zeros(len(x), 1)

    def color(self, features, d):
        return self.color_value.expand(features.shape[0], 3)


def wall_reconstruction(z0=1.2):
    aabb = np.array([[-2, -2, 0.8], [2, 2, 1.8]], np.float32)
    # 128 coarse samples over ~1 m: a step in density is located to within half a bin (4 mm)
    cfg = ReconstructionConfig.preset("test", progress=False, **{"sampling.n_coarse": 128})
    return Reconstruction(WallField(aabb, z0), cfg, np.eye(4)[None], np.zeros((1, 6, 6)), intrinsic(), [0], [])


def test_render_of_an_analytic_wall_has_the_right_shapes_colour_and_opacity():
    recon = wall_reconstruction()
    out = recon.render(np.eye(4))
    assert set(out) == {"color", "depth", "depth_std", "opacity"}
    assert out["color"].shape == (30, 40, 3)
    for k in ("depth", "depth_std", "opacity"):
        assert out[k].shape == (30, 40) and out[k].dtype == np.float32
    np.testing.assert_allclose(out["opacity"], 1.0, atol=1e-4)
    np.testing.assert_allclose(out["color"], np.broadcast_to([0.1, 0.6, 0.3], (30, 40, 3)), atol=1e-4)
    # at the principal point ||d|| = 1: depth is the wall's z-depth whatever the convention
    assert abs(out["depth"][14:16, 19:21].mean() - 1.2) < 0.01
    assert (out["depth_std"] < 0.01).all()
    # a different intrinsic gives a render of its size
    small = recon.render(np.eye(4), intrinsic(8, 6, 6.0))
    assert small["color"].shape == (6, 8, 3)


def test_render_depth_of_an_analytic_wall_is_its_z_depth_everywhere():
    recon = wall_reconstruction(1.2)
    out = recon.render(np.eye(4))
    np.testing.assert_allclose(out["depth"], 1.2, atol=0.01)
    # a rotated camera (looking along world +z through a tilted axis) sees the same plane
    angle = 0.3
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
    out = recon.render(pose)
    K = np.asarray(intrinsic().intrinsic_matrix)
    v, u = np.mgrid[0:30, 0:40]
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    world_dz = d_cam @ pose[:3, :3].T
    expected = 1.2 / world_dz[..., 2]  # camera z-depth at which the pixel's ray meets z = 1.2
    np.testing.assert_allclose(out["depth"], expected, rtol=0.01)


def test_depth_pdf_of_an_analytic_wall_peaks_at_its_z_depth():
    recon = wall_reconstruction(1.2)
    pixels = np.array([[19.5, 14.5], [0, 0], [39, 29], [5, 20]])  # centre and corners: ||K^-1 [u, v, 1]|| up to 1.3
    pdf = recon.depth_pdf(np.eye(4), pixels)
    sampling = recon.config.sampling.for_render()  # what render() samples
    s = sampling.n_coarse + sampling.n_fine + sampling.n_guided
    assert pdf["z"].shape == pdf["mass"].shape == pdf["pdf"].shape == (4, s) and pdf["edges"].shape == (4, s + 1)
    assert (np.diff(pdf["edges"], axis=1) >= 0).all() and (pdf["z"] >= pdf["edges"][:, :-1] - 1e-6).all()
    np.testing.assert_allclose(pdf["mass"].sum(1), 1.0, atol=1e-4)
    np.testing.assert_allclose((pdf["pdf"] * np.diff(pdf["edges"], axis=1)).sum(1), 1.0, atol=1e-4)
    np.testing.assert_allclose(pdf["opacity"], 1.0, atol=1e-4)
    # z-depth, not ray distance: the mode is the wall's z-depth for every pixel, as in render()
    np.testing.assert_allclose(pdf["z"][np.arange(4), pdf["mass"].argmax(1)], 1.2, atol=0.01)
    # render()'s depth is the median of that distribution (each bin's mass spread over the bin)
    depth = recon.render(np.eye(4))["depth"]
    cdf = np.concatenate([np.zeros((4, 1)), np.cumsum(pdf["mass"], 1)], 1)
    expected = [np.interp(0.5, c, e) for c, e in zip(cdf, pdf["edges"])]
    np.testing.assert_allclose(expected[1:], depth[pixels[1:, 1].astype(int), pixels[1:, 0].astype(int)], atol=1e-4)
    with pytest.raises(InputError, match="pixels_uv"):
        recon.depth_pdf(np.eye(4), [1, 2, 3])


class SlabField(WallField):
    """Opaque slab z0 - half <= z <= z0 + half (world), thinner than the training sampling's coarse spacing."""

    def __init__(self, aabb, z0, half):
        super().__init__(aabb, z0)
        self.half = half

    def geometry(self, x, encoded=None):
        return torch.where((x[:, 2] - self.z0).abs() <= self.half, 1e3, 0.0), torch.zeros(len(x), 1)


def test_renders_find_a_slab_thinner_than_the_training_coarse_spacing():
    aabb = np.array([[-2, -2, 0.8], [2, 2, 1.8]], np.float32)  # the centre ray crosses 1 m of the box
    cfg = ReconstructionConfig.preset("test", progress=False)
    assert cfg.sampling.n_coarse == 16 and cfg.sampling.n_coarse_render == 32
    half = 1.1 / 32 / 2  # 1.1x the spacing of 32 samples over 1 m, 0.55x that of 16: they step over it

    def centre_ray(config, z0):
        recon = Reconstruction(SlabField(aabb, z0, half), config, np.eye(4)[None], np.zeros((1, 6, 6)), intrinsic(),
                               [0], [])
        K = np.asarray(intrinsic().intrinsic_matrix)
        rays = recon.model.camera_rays(np.eye(4), K, torch.tensor([19.5]), torch.tensor([14.5]))  # ||K^-1 uv1|| = 1
        out = recon.model.render(rays, keys=("opacity", "median"))
        return float(out["opacity"][0]), float(out["median"][0])

    centres = np.linspace(0.85, 1.75, 37)
    found = [centre_ray(cfg, z0) for z0 in centres]  # wider than the 32 render samples' spacing: always sampled
    assert all(opacity > 0.99 and abs(depth - z0) <= half for (opacity, depth), z0 in zip(found, centres))
    training_like = cfg.replace(**{"sampling.n_coarse_render": 16})
    assert min(centre_ray(training_like, z0)[0] for z0 in centres) < 0.5  # what renders did before


# -- end to end on the sample ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def sample():
    return load_sample()


@pytest.fixture(scope="module")
def recon(sample):
    cfg = ReconstructionConfig.preset("test", holdout_every=4, max_steps=TRAIN_STEPS, progress=False)
    return reconstruct(sample, cfg, poses=sample.gt_poses)


@pytest.fixture(scope="module")
def saved(recon, tmp_path_factory):
    return recon.save(tmp_path_factory.mktemp("recon") / "out")


@pytest.mark.slow
def test_reconstruct_returns_a_complete_reconstruction(recon, sample):
    assert isinstance(recon, Reconstruction)
    np.testing.assert_array_equal(recon.train_indices, [1, 2, 3, 5, 6, 7, 9, 10])
    np.testing.assert_array_equal(recon.holdout_indices, [0, 4, 8])
    np.testing.assert_allclose(recon.poses, sample.gt_poses)
    assert recon.covariances.shape == (11, 6, 6) and not recon.covariances.any()
    assert (recon.intrinsic.width, recon.intrinsic.height) == (160, 120)  # image_scale 0.5
    assert isinstance(recon.mesh, o3d.geometry.TriangleMesh) and len(recon.mesh.triangles) > 0
    assert isinstance(recon.point_cloud, o3d.geometry.PointCloud)
    n = len(recon.point_cloud.points)
    assert n > 100 and recon.point_sigma.shape == (n,)
    assert np.isfinite(recon.point_sigma).all() and (recon.point_sigma >= 0).all()
    # fused with the sensor: the model's depth counts up to max_point_std, the sensor's with its own
    # sigma, and both carry the sensor's systematic part
    noise, z_max = recon.config.export.sensor_noise(), float(np.linalg.norm(recon.aabb[1] - recon.aabb[0]))
    bound = np.hypot(max(recon.config.export.max_point_std, noise.sigma(z_max)), noise.relative * z_max)
    assert recon.point_sigma.max() <= bound + 1e-6
    pts = np.asarray(recon.point_cloud.points)
    assert ((pts >= recon.aabb[0] - 1e-3) & (pts <= recon.aabb[1] + 1e-3)).all()
    stats = recon.stats
    assert stats["training"]["steps"] == TRAIN_STEPS and not stats["training"]["interrupted"]
    assert stats["history"][-1]["step"] == TRAIN_STEPS and "eval_psnr" in stats["history"][-1]
    assert {"tracking_s", "targets_s", "export_s", "total_s"} <= set(stats["timings"])
    assert "Reconstruction(11 frames, 8 trained" in repr(recon)


@pytest.mark.slow
def test_exported_sigma_takes_the_sensors_systematic_term_not_the_targets(recon, sample):
    """The targets' systematic term (4%) is a training choice; the exported sigma carries the
    sensor's (export.depth_sigma_relative, 2%): without it, only the random part is left."""
    assert recon.config.targets.depth_sigma_relative == 0.04 and recon.config.export.depth_sigma_relative == 0.02

    def sorted_sigma(config=None):  # the points' order is not fixed; the same points are
        return np.sort(sensor_geometry(recon, sample, config).point_sigma)

    export = recon.config.export
    sigma = {r: sorted_sigma(dataclasses.replace(export, depth_sigma_relative=r)) for r in (0.0, 0.02, 0.04)}
    np.testing.assert_array_equal(sorted_sigma(), sigma[0.02])
    assert (sigma[0.04] > sigma[0.02]).all() and (sigma[0.02] > sigma[0.0]).all()
    z_max = float(np.linalg.norm(recon.aabb[1] - recon.aabb[0]))
    assert sigma[0.0].max() <= export.sensor_noise().sigma(z_max)


@pytest.mark.slow
def test_render_returns_images_of_the_training_size(recon):
    out = recon.render(recon.poses[4])
    assert set(out) == {"color", "depth", "depth_std", "opacity"}
    assert out["color"].shape == (120, 160, 3) and out["color"].dtype == np.float32
    for k in ("depth", "depth_std", "opacity"):
        assert out[k].shape == (120, 160)
        assert np.isfinite(out[k]).all()
    assert (out["color"] >= 0).all() and (out["color"] <= 1).all()
    assert (out["opacity"] >= 0).all() and (out["opacity"] <= 1 + 1e-5).all()
    assert (out["depth_std"] >= 0).all()
    # deterministic: two renders are identical (at a quarter of the size, to save time)
    quarter = scale_intrinsic(recon.intrinsic, 0.25)
    a, b = recon.render(recon.poses[4], quarter), recon.render(recon.poses[4], quarter)
    assert a["color"].shape == (30, 40, 3)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


@pytest.mark.slow
def test_exposure_gains_follow_the_cameras_auto_exposure(recon):
    # TUM's camera darkens as fr1/xyz goes on: the sample's frames 5-7 record the same desk
    # darker than frame 1
    g = recon.color_gains
    assert g.shape == (11, 3) and np.isfinite(g).all() and (g > 0).all()
    assert g[[5, 6, 7]].mean() < 0.95 * g[1].mean()
    # held-out frames take the exposure of the training frames around them
    from open3d_pnerf.rendering.exposure import interpolate_gains

    t = recon.timestamps
    np.testing.assert_allclose(g[recon.holdout_indices],
                               interpolate_gains(t[recon.train_indices], g[recon.train_indices], t[recon.holdout_indices]))
    quarter = scale_intrinsic(recon.intrinsic, 0.25)
    average, as_seen = recon.render(recon.poses[5], quarter), recon.render(recon.poses[5], quarter, frame=5)
    np.testing.assert_allclose(as_seen["color"], np.clip(average["color"] * g[5].astype(np.float32), 0, 1), atol=1e-6)
    np.testing.assert_array_equal(as_seen["depth"], average["depth"])
    for bad in (11, -1, 2.0):
        with pytest.raises(InputError, match="frame must be a frame index"):
            recon.render(recon.poses[5], quarter, frame=bad)


@pytest.mark.slow
def test_training_beats_an_untrained_model_on_held_out_frames(recon, sample):
    untrained = Reconstruction(recon.config.build_field(recon.aabb), recon.config, recon.poses,
                               recon.covariances, recon.intrinsic, recon.train_indices, recon.holdout_indices)
    small = sample.at_scale(0.5)
    gains = []
    for i in (4, 8):  # held-out frames inside the trajectory (0 is its end)
        assert i in recon.holdout_indices
        gt = small[int(i)].color.astype(np.float32) / 255.0
        trained = psnr(recon.render(recon.poses[i])["color"], gt)
        before = psnr(untrained.render(recon.poses[i])["color"], gt)
        gains.append(trained - before)
        assert trained > before + 2.0, (int(i), trained, before)
    assert np.mean(gains) > 4.0


@pytest.mark.slow
def test_save_writes_every_file(saved, recon):
    names = {p.name for p in saved.iterdir()}
    expected = {"mesh.ply", "point_cloud.ply", "model.pt", "reconstruction.json", "poses.npy",
                "covariances.npy", "color_gains.npy", "observed.npy", "observed_depths.npy", "trajectory_tum.txt",
                "trajectory.log"}
    assert expected <= names
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    meta = json.loads((saved / "reconstruction.json").read_text())
    assert meta["format_version"] == FORMAT_VERSION
    assert meta["intrinsic"]["width"] == 160 and meta["train_indices"] == recon.train_indices.tolist()
    assert ReconstructionConfig.from_dict(meta["config"]) == recon.config
    cloud, sigma = read_point_cloud_ply(saved / "point_cloud.ply")
    np.testing.assert_allclose(np.asarray(cloud.points), np.asarray(recon.point_cloud.points), atol=1e-6)
    np.testing.assert_allclose(sigma, recon.point_sigma, rtol=1e-6)
    state = torch.load(saved / "model.pt", weights_only=True)
    assert set(state) == set(recon.field.state_dict())
    np.testing.assert_allclose(np.load(saved / "poses.npy"), recon.poses)
    tum = [ln for ln in (saved / "trajectory_tum.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(tum) == 11 and len(tum[0].split()) == 8
    assert len((saved / "trajectory.log").read_text().split("\n")) >= 55
    mesh = o3d.io.read_triangle_mesh(str(saved / "mesh.ply"))
    assert len(mesh.triangles) == len(recon.mesh.triangles)


@pytest.mark.slow
def test_load_renders_the_same_image(saved, recon):
    loaded = Reconstruction.load(saved)
    assert loaded.config == recon.config
    np.testing.assert_allclose(loaded.aabb, recon.aabb)
    np.testing.assert_array_equal(loaded.holdout_indices, recon.holdout_indices)
    np.testing.assert_allclose(loaded.poses, recon.poses)
    np.testing.assert_allclose(loaded.color_gains, recon.color_gains)
    assert loaded.observed.voxel_size == recon.observed.voxel_size
    np.testing.assert_array_equal(loaded.observed.centres, recon.observed.centres)
    np.testing.assert_array_equal(loaded.observed.depths, recon.observed.depths)
    np.testing.assert_allclose(loaded.observed.poses, recon.observed.poses)
    assert len(loaded.point_cloud.points) == len(recon.point_cloud.points)
    np.testing.assert_allclose(loaded.point_sigma, recon.point_sigma, rtol=1e-6)
    K_a = np.asarray(loaded.intrinsic.intrinsic_matrix)
    np.testing.assert_allclose(K_a, np.asarray(recon.intrinsic.intrinsic_matrix))
    half = scale_intrinsic(recon.intrinsic, 0.5)
    a, b = loaded.render(recon.poses[8], half), recon.render(recon.poses[8], half)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-5, rtol=1e-5)


def copy_of(saved, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(saved, dst)
    return dst


@pytest.mark.slow
def test_load_rejects_a_tampered_format_version(saved, tmp_path):
    d = copy_of(saved, tmp_path)
    meta = json.loads((d / "reconstruction.json").read_text())
    meta["format_version"] = FORMAT_VERSION + 1
    (d / "reconstruction.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="format version"):
        Reconstruction.load(d)


@pytest.mark.slow
def test_load_rejects_broken_folders(saved, tmp_path):
    with pytest.raises(CheckpointError, match="reconstruction.json missing"):
        Reconstruction.load(tmp_path / "nothing")
    d = copy_of(saved, tmp_path)
    (d / "reconstruction.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="corrupt JSON"):
        Reconstruction.load(d)
    shutil.copy(saved / "reconstruction.json", d / "reconstruction.json")
    meta = json.loads((d / "reconstruction.json").read_text())
    meta["config"]["hashgrid"]["levels"] = 4  # weights no longer match the config
    (d / "reconstruction.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="do not match"):
        Reconstruction.load(d)
    meta["config"]["bogus"] = 1
    (d / "reconstruction.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="bogus"):
        Reconstruction.load(d)


class Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(self.marker)}",))


@pytest.mark.slow
def test_load_rejects_a_malicious_model_file(saved, tmp_path):
    d = copy_of(saved, tmp_path)
    marker = tmp_path / "pwned"
    torch.save({"x": Payload(marker)}, d / "model.pt")
    with pytest.raises(CheckpointError, match="model.pt"):
        Reconstruction.load(d)
    assert not marker.exists()


# -- depth-sigma calibration ---------------------------------------------------------------------
@pytest.mark.slow
def test_depth_std_is_the_scaled_model_spread_with_a_relative_floor(recon):
    pose = recon.poses[recon.train_indices[0]]
    law, observed = recon.depth_error, recon.observed
    try:
        recon.observed = None  # the law alone
        recon.depth_error = DepthErrorLaw(1.0, 0.0, edge=0.0)
        raw = recon.render(pose)
        recon.depth_error = DepthErrorLaw(2.5, 0.0, edge=0.0)
        scaled = recon.render(pose)
        recon.depth_error = DepthErrorLaw(2.5, 0.01, edge=0.0)
        floored = recon.render(pose)
        recon.depth_error = DepthErrorLaw(2.5, 0.01, edge=0.2)
        edged = recon.render(pose)
        recon.observed, recon.depth_error = observed, law
        widened = recon.render(pose)
    finally:
        recon.depth_error, recon.observed = law, observed
    np.testing.assert_allclose(scaled["depth_std"], 2.5 * raw["depth_std"], rtol=1e-5)
    np.testing.assert_allclose(floored["depth_std"], np.hypot(2.5 * raw["depth_std"], 0.01 * raw["depth"]), rtol=1e-5)
    np.testing.assert_array_equal(scaled["depth"], raw["depth"])
    # beside a depth edge, a share of the step: the range of the rendered depth within 2 px at 320 px
    width = raw["depth"].shape[1]
    r = max(1, round(2 / 320 * width))
    padded = np.pad(raw["depth"], r, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * r + 1, 2 * r + 1))
    jump = windows.max((-2, -1)) - windows.min((-2, -1))
    np.testing.assert_allclose(edged["depth_std"], np.hypot(floored["depth_std"], 0.2 * jump), rtol=1e-5)
    step = jump > 0.1
    assert step.any() and (edged["depth_std"][step] > floored["depth_std"][step]).all()
    # away from what the training frames' depth saw, sigma is at least the distance to it
    K = np.asarray(recon.intrinsic.intrinsic_matrix)
    points = backproject(widened["depth"], K, pose, np.ones_like(widened["depth"], bool))[0]
    distance = recon.observed.distance(points).reshape(widened["depth"].shape)
    through = recon.observed.seen_through(points, pose[:3, 3]).reshape(widened["depth"].shape)
    np.testing.assert_allclose(widened["depth_std"], law.sigma(raw["depth_std"], raw["depth"], distance, jump,
                                                               through), rtol=1e-5)
    far = distance >= law.unseen_ramp
    assert far.any() and (distance == 0).any()  # a briefly trained model: some pixels on what it saw, some off
    assert (widened["depth_std"][far] >= law.unseen * raw["depth"][far] * (1 - 1e-6)).all()


def test_the_unseen_term_widens_sigma_to_a_share_of_the_depth_away_from_observed_surfaces():
    law = DepthErrorLaw(2.0, 0.01, 3.0, unseen=0.5, unseen_ramp=0.02)
    spread, z = np.full(4, 0.01), np.full(4, 2.0)
    seen = np.hypot(2.0 * 0.01, 0.01 * 2.0)
    np.testing.assert_allclose(law.sigma(spread, z), seen)
    np.testing.assert_allclose(law.sigma(spread, z, np.zeros(4)), seen)
    d = np.array([0.0, 0.01, 0.02, 5.0])  # on it, half-way up the ramp, at its end, far beyond
    np.testing.assert_allclose(law.sigma(spread, z, d), np.hypot(seen, 0.5 * 2.0 * np.array([0, 0.5, 1, 1])))


def test_the_edge_term_widens_sigma_by_a_share_of_the_local_depth_step():
    from open3d_pnerf.error_law import EDGE, depth_jump

    depth = np.full((6, 640), 2.0)
    depth[:, 320:] = 3.0  # a 1 m step between columns 319 and 320
    jump = depth_jump(depth)  # radius 2 / 320 of the width: 4 px at 640 px
    np.testing.assert_array_equal(np.flatnonzero(jump[0]), np.arange(316, 324))
    np.testing.assert_allclose(jump[:, 316:324], 1.0)
    np.testing.assert_array_equal(np.flatnonzero(depth_jump(depth[:, ::2])[0]), np.arange(158, 162))  # 2 px at 320
    law = DepthErrorLaw(2.0, 0.01, 3.0)
    spread, z = np.full(3, 0.01), np.full(3, 2.0)
    seen = law.sigma(spread, z)
    np.testing.assert_allclose(law.sigma(spread, z, None, np.array([0.0, 0.5, 1.0])),
                               np.hypot(seen, EDGE * np.array([0.0, 0.5, 1.0])))
    np.testing.assert_allclose(law.sigma(spread, z, None, np.zeros(3)), seen)


def test_the_through_term_puts_the_surface_a_view_saw_beyond_the_point_at_the_99_7_percent_interval():
    from scipy import stats

    law = DepthErrorLaw(2.0, 0.01, 3.0)
    spread, z, gap = np.full(3, 0.01), np.full(3, 2.0), np.array([0.0, 0.5, 1.0])
    seen = law.sigma(spread, z)
    k = stats.t(3).ppf((1 + 0.9973002039367398) / 2) / stats.t(3).ppf((1 + 0.6826894921370859) / 2)
    assert k > 3  # 3 degrees of freedom: wider than a Gaussian's 3 sigma
    np.testing.assert_allclose(law.sigma(spread, z, None, None, gap), np.hypot(seen, gap / k))
    alone = DepthErrorLaw(1.0, 0.0, np.inf).sigma(np.zeros(3), z, None, None, gap)
    np.testing.assert_allclose(3 * alone, gap)  # a Gaussian's 99.73% interval: 3 sigma, reaching the surface


def test_likelihood_fit_recovers_the_scale_floor_and_tails_of_known_errors():
    """1-sigma-equivalent sigma = hypot(s spread, f z) with s = 2.5, f = 1%: a Gaussian fit finds
    s and f from Gaussian errors (dof inf); the Student-t fit finds them and 3 dof from Student-t
    errors, and a large dof from Gaussian ones."""
    from scipy import stats

    from open3d_pnerf.error_law import _likelihood_fit

    rng = np.random.default_rng(0)
    spread = rng.uniform(0.001, 0.05, 20000)
    z = rng.uniform(0.5, 4.0, 20000)
    sigma = np.hypot(2.5 * spread, 0.01 * z)
    err = np.abs(rng.normal(0, sigma))
    s, f, dof = _likelihood_fit(err, spread, z, scale0=1.0, fit_dof=False)
    assert s == pytest.approx(2.5, rel=0.03) and f == pytest.approx(0.01, rel=0.05) and dof == np.inf
    assert _likelihood_fit(err, spread, z, scale0=1.0)[2] > 30
    heavy = np.abs(rng.standard_t(3, spread.shape)) * sigma / stats.t(3).ppf(0.8413447460685429)
    s, f, dof = _likelihood_fit(heavy, spread, z, scale0=1.0)
    assert s == pytest.approx(2.5, rel=0.05) and f == pytest.approx(0.01, rel=0.1) and dof == pytest.approx(3, rel=0.15)


@pytest.mark.slow
def test_calibration_fits_on_training_frames_and_quantile_puts_68_percent_within_one_sigma(recon, sample):
    law = recon.depth_error
    try:
        with pytest.raises(InputError, match="method must be"):
            recon.calibrate_depth_sigma(sample, method="bogus")
        recon.calibrate_depth_sigma(sample)  # the default: maximum likelihood, Student-t
        assert 0 < recon.depth_sigma_scale < 10 and 0 <= recon.depth_sigma_floor < 0.2
        assert 1 <= recon.depth_sigma_dof <= 1000 and recon.depth_interval(0.954) > 2
        recon.calibrate_depth_sigma(sample, method="gaussian")
        assert recon.depth_sigma_dof == np.inf and recon.depth_interval(0.9545) == pytest.approx(2, abs=1e-3)
        fitted = recon.calibrate_depth_sigma(sample, method="quantile")
        assert fitted == recon.depth_sigma_scale and 0 < fitted < 10 and recon.depth_sigma_floor == 0
        train = sample.select(recon.train_indices).at_scale(recon.config.image_scale)
        inside = []
        for k, i in enumerate(recon.train_indices):  # every pixel, not only the fitted subset
            out, depth = recon.render(recon.poses[i]), train[k].depth
            ok = (depth > 0) & (out["opacity"] > 0.5)
            inside.append(np.abs(out["depth"] - depth)[ok] <= out["depth_std"][ok])
        assert abs(np.concatenate(inside).mean() - 0.683) < 0.05
    finally:
        recon.depth_error = law


@pytest.mark.slow
def test_saved_reconstruction_keeps_its_calibration(recon, saved):
    assert recon.depth_sigma_scale != 1.0  # reconstruct() calibrates by default
    loaded = Reconstruction.load(saved)
    assert loaded.depth_sigma_scale == pytest.approx(recon.depth_sigma_scale)
    assert loaded.depth_sigma_floor == pytest.approx(recon.depth_sigma_floor)
    assert loaded.depth_sigma_dof == pytest.approx(recon.depth_sigma_dof)


@pytest.mark.slow
def test_mesh_ply_carries_a_per_vertex_sigma_that_open3d_and_plyfile_read(recon, saved):
    assert recon.mesh_sigma.shape == (len(recon.mesh.vertices),) and (recon.mesh_sigma > 0).all()
    mesh = o3d.io.read_triangle_mesh(str(saved / "mesh.ply"))  # Open3D still reads the mesh and colours
    assert len(mesh.triangles) == len(recon.mesh.triangles) and mesh.has_vertex_colors()
    t = o3d.t.io.read_point_cloud(str(saved / "mesh.ply"))
    np.testing.assert_allclose(t.point.depth_sigma.numpy()[:, 0], recon.mesh_sigma)
    ply = plyfile.PlyData.read(str(saved / "mesh.ply"))
    np.testing.assert_allclose(ply["vertex"]["depth_sigma"], recon.mesh_sigma)
    np.testing.assert_allclose(Reconstruction.load(saved).mesh_sigma, recon.mesh_sigma)


@pytest.mark.slow
def test_export_fused_with_the_sensor_keeps_its_accuracy_where_it_saw(recon, sample):
    """reconstruct() fuses each export view's rendered depth with the sensor's: the exported
    points lie closer to the sensor's own surface than the model-only export's, and every
    point carries the fused sigma (no wider than the sensor's or the model's)."""
    from scipy.spatial import cKDTree

    train = sample.select(recon.train_indices).at_scale(recon.config.image_scale * recon.config.export.scale)
    sensor = np.concatenate([backproject(train[k].depth, train.K, recon.poses[i], train[k].depth > 0)[0]
                             for k, i in enumerate(recon.train_indices)])
    tree = cKDTree(sensor)
    fused = np.asarray(recon.point_cloud.points)  # reconstruct() exported with the sequence
    fused_sigma = recon.point_sigma.copy()
    observed, recon.observed = recon.observed, None  # the model's own depth, without the unseen term's gate
    try:
        model_only = np.asarray(export_geometry(recon, progress=False).point_cloud.points)
    finally:
        recon.observed = observed
    np.testing.assert_allclose(np.sort(export_geometry(recon, sample, progress=False).point_sigma),
                               np.sort(fused_sigma))  # the same export again (voxel order varies)
    d_fused, d_model = tree.query(fused)[0], tree.query(model_only)[0]
    print(f"median distance to the sensor's points: fused {1000 * np.median(d_fused):.1f} mm, "
          f"model only {1000 * np.median(d_model):.1f} mm")
    # 4.5 vs 5.2 mm (the model's median depth; 6.6 mm when training scored the coarse render, with fog in front)
    assert np.median(d_fused) < np.median(d_model)
    assert len(fused) >= len(model_only)  # the sensor adds what the model is not sure of
    assert np.isfinite(fused_sigma).all() and (fused_sigma > 0).all()


# -- long sequences: memory-mapped targets, bounded export ---------------------------------------
@pytest.mark.slow
def test_large_targets_go_to_memory_mapped_files_that_are_removed_after_training(sample, tmp_path, monkeypatch):
    import open3d_pnerf.targets.dense as dense
    import open3d_pnerf.targets.storage as storage

    used = []
    real = dense.depth_targets

    def spy(*args, storage_dir=None, **kwargs):
        used.append(storage_dir)
        targets = real(*args, storage_dir=storage_dir, **kwargs)
        assert isinstance(targets.mean, np.memmap)
        return targets

    monkeypatch.setattr(storage, "RAM_MAX_BYTES", 0)
    monkeypatch.setattr(dense, "depth_targets", spy)
    cfg = ReconstructionConfig.preset("test", max_steps=5, progress=False, **{"export.calibrate_depth_sigma": False})
    result = reconstruct(sample.select(range(4)), cfg, poses=sample.gt_poses[:4], checkpoint_dir=tmp_path / "ckpt")
    assert used == [tmp_path / "ckpt" / "targets"]
    assert not used[0].exists()
    assert result.stats["targets"]  # the summary was taken before the files went


@pytest.mark.slow
def test_export_renders_at_most_export_max_views(recon, monkeypatch):
    calls = []
    real = Reconstruction.render
    monkeypatch.setattr(Reconstruction, "render", lambda self, pose, *a, **k: calls.append(pose) or real(self, pose, *a, **k))
    export_geometry(recon, config=dataclasses.replace(recon.config.export, max_views=3), progress=False)
    export_geometry(recon, progress=False)
    assert len(calls) == 3 + len(recon.train_indices)
    train = recon.train_indices
    np.testing.assert_allclose(np.stack(calls[:3]), recon.poses[train[[0, len(train) // 2, -1]]])


def test_a_saved_folder_loads_and_renders_as_the_version_that_wrote_it_did():
    """tests/data/saved_reconstruction (a grid field, its weights written by an earlier version)
    and that version's render of frame 1: loading and rendering do not drift. (Its depth_std was
    rewritten when the law gained its edge term, the only change; colour, depth and opacity are
    the earlier version's.)"""
    folder = Path(__file__).parent / "data" / "saved_reconstruction"
    recon = Reconstruction.load(folder)
    assert recon.config.field == "grid" and recon.config.grid.resolutions == (8, 16)
    assert recon.config.sampling.n_fine == 16 and recon.config.max_steps == 60  # the old "test" preset
    expected = np.load(folder / "expected_render_frame1.npz")
    out = recon.render(recon.poses[1], frame=1)
    assert set(out) == set(expected.files)
    for key in expected.files:
        np.testing.assert_allclose(out[key], expected[key], rtol=1e-6, atol=1e-6)


def interrupt_training_at(monkeypatch, step: int) -> None:
    """Make every Trainer see a Ctrl-C when it reaches `step` (as a real SIGINT mid-step does)."""
    real = Trainer.train_step

    def train_step(self):
        if self.step == step:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(Trainer, "train_step", train_step)


def test_ctrl_c_stops_reconstruct_after_writing_a_checkpoint_it_resumes_from(sample, tmp_path, monkeypatch):
    """Before: reconstruct() swallowed the KeyboardInterrupt and went on to calibrate and export."""
    seq = sample.select(range(4))
    cfg = ReconstructionConfig.preset("test", max_steps=10, progress=False)
    interrupt_training_at(monkeypatch, 3)
    exports = []
    monkeypatch.setattr(stages, "export_geometry", lambda recon, *a, **k: exports.append(recon))
    with pytest.raises(KeyboardInterrupt) as info:
        reconstruct(seq, cfg, poses=seq.gt_poses, checkpoint_dir=tmp_path / "ckpt")
    assert isinstance(info.value, TrainingInterrupted) and info.value.step == 3 and not exports
    assert info.value.checkpoint == tmp_path / "ckpt" / "checkpoint.pt" and "resume=True" in str(info.value)
    assert read_checkpoint(info.value.checkpoint)["step"] == 3
    # without a checkpoint_dir the work goes to a new temporary folder that the error names
    with pytest.raises(TrainingInterrupted) as info:
        reconstruct(seq, cfg, poses=seq.gt_poses)
    assert read_checkpoint(info.value.checkpoint)["step"] == 3 and "pnerf-interrupted-" in str(info.value)
    shutil.rmtree(info.value.checkpoint.parent)
    # "stop training now and export what you have": resume with no step left
    monkeypatch.undo()
    recon = reconstruct(seq, cfg.replace(max_steps=1), poses=seq.gt_poses, checkpoint_dir=tmp_path / "ckpt",
                        resume=True)
    assert recon.stats["training"]["steps"] == 3 and recon.point_cloud is not None


@pytest.mark.slow
def test_a_resumed_run_trains_on_the_poses_it_tracked_before(sample, tmp_path, monkeypatch):
    """Tracked poses are kept beside the checkpoint: resuming (from Python as from the command
    line) neither tracks again nor trains on other poses; a run that is not resumed tracks anew."""
    import open3d_pnerf.tracking.tracker as tracker

    seq = sample.select(range(4))
    cfg = ReconstructionConfig.preset("test", max_steps=10, progress=False, **{"export.calibrate_depth_sigma": False})
    interrupt_training_at(monkeypatch, 3)
    with pytest.raises(TrainingInterrupted):
        reconstruct(seq, cfg, checkpoint_dir=tmp_path / "ckpt")
    tracked = np.load(tmp_path / "ckpt" / "poses.npy")
    offsets = np.load(tmp_path / "ckpt" / "color_offsets.npy")  # the colour cameras beside the depth ones
    assert tracked.shape == offsets.shape == (4, 4, 4) and (tmp_path / "ckpt" / "covariances.npy").is_file()
    monkeypatch.undo()
    calls = []
    real = tracker.track
    monkeypatch.setattr(tracker, "track", lambda *a, **k: calls.append(1) or real(*a, **k))
    recon = reconstruct(seq, cfg, checkpoint_dir=tmp_path / "ckpt", resume=True)
    assert not calls and recon.stats["training"]["steps"] == 10 and recon.stats["tracking"]["tracked"] is True
    np.testing.assert_array_equal(recon.poses, tracked @ offsets)  # the colour images' poses
    assert recon.stats["tracking"]["ate_rmse_m"] < 0.02  # tracked, and scored against the sample's ground truth
    reconstruct(seq, cfg.replace(max_steps=2), checkpoint_dir=tmp_path / "fresh")
    assert calls == [1]
