"""Tests of open3d_pnerf.tsdf: Open3D TSDF fusion on a synthetic plane and the sample."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from open3d_pnerf.errors import InputError, PoseError
from open3d_pnerf.tsdf import TSDFVolume, tsdf_fusion

Z0 = 1.0
VOXEL = 0.02
COLOR = (200, 100, 50)
SHIFTS = (-0.06, -0.02, 0.02, 0.06)  # 4 views: above Open3D's default weight threshold 3
OFFSET = np.array([0.3, -0.2, 0.513])  # cameras' world offset (plane kept off the voxel layers)
WORLD_Z = Z0 + OFFSET[2]  # the plane in world coordinates


def plane_sequence(plane_scene, n: int = len(SHIFTS)):
    """The plane z = Z0 (camera frame) seen by n identity-rotation cameras shifted along x."""
    seq, poses = plane_scene(Z0, SHIFTS[:n], color=COLOR)
    poses = poses.copy()
    poses[:, :3, 3] += OFFSET  # camera frame != world frame
    return seq, poses


@pytest.fixture(scope="module")
def plane_volume(plane_scene):
    seq, poses = plane_sequence(plane_scene)
    volume = tsdf_fusion(seq, poses, voxel_size=VOXEL, sdf_trunc=3 * VOXEL, return_volume=True, progress=False)
    return volume, seq, poses


def test_plane_mesh(plane_volume):
    volume, _, _ = plane_volume
    assert isinstance(volume, TSDFVolume)
    mesh = volume.mesh()
    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    vertices = np.asarray(mesh.vertices)
    assert len(vertices) > 100 and len(mesh.triangles) > 100
    err = np.abs(vertices[:, 2] - WORLD_Z)
    assert np.median(err) < VOXEL / 4 and np.percentile(err, 95) < VOXEL
    # the surface spans the field of view around the cameras' x (0.3 m) and y (-0.2 m)
    assert vertices[:, 0].min() < 0.3 - 0.4 and vertices[:, 0].max() > 0.3 + 0.4
    assert vertices[:, 1].min() < -0.2 - 0.3 and vertices[:, 1].max() > -0.2 + 0.3
    assert mesh.has_vertex_colors() and mesh.has_vertex_normals()
    np.testing.assert_allclose(np.median(np.asarray(mesh.vertex_colors), 0), np.array(COLOR) / 255, atol=0.01)
    # a lower weight threshold keeps the less observed rim: more vertices
    volume.weight_threshold = 1.0
    assert len(volume.mesh().vertices) > len(vertices)


def test_plane_point_cloud(plane_volume):
    volume, _, _ = plane_volume
    cloud = volume.point_cloud()
    assert isinstance(cloud, o3d.geometry.PointCloud)
    points = np.asarray(cloud.points)
    assert len(points) > 100
    assert np.median(np.abs(points[:, 2] - WORLD_Z)) < VOXEL / 4
    assert cloud.has_colors()
    np.testing.assert_allclose(np.median(np.asarray(cloud.colors), 0), np.array(COLOR) / 255, atol=0.01)


def test_plane_render_at_training_pose(plane_volume):
    volume, seq, poses = plane_volume
    h, w = seq.image_size
    out = volume.render(poses[1], seq.K, w, h)
    assert out["depth"].shape == (h, w) and out["color"].shape == (h, w, 3) and out["hit"].shape == (h, w)
    assert out["depth"].dtype == np.float32 and out["color"].dtype == np.float32 and out["hit"].dtype == bool
    hit = out["hit"]
    assert hit.mean() > 0.7
    assert hit[h // 2, w // 2] and hit[h // 2 - 10 : h // 2 + 10, w // 2 - 10 : w // 2 + 10].all()
    assert np.all(out["depth"][~hit] == 0) and np.all(out["color"][~hit] == 0)
    # z-depth of the plane (not the ray length, which grows towards the corners): constant z0
    np.testing.assert_allclose(out["depth"][hit], Z0, atol=VOXEL / 4)
    assert out["color"].min() >= 0 and out["color"].max() <= 1
    np.testing.assert_allclose(out["color"][hit], np.broadcast_to(np.array(COLOR) / 255, (hit.sum(), 3)), atol=0.02)
    # a camera 0.2 m further back sees the plane 0.2 m deeper
    back = poses[1].copy()
    back[2, 3] -= 0.2
    far = volume.render(back, seq.K, w, h)
    np.testing.assert_allclose(far["depth"][far["hit"]], Z0 + 0.2, atol=VOXEL / 4)


def test_render_follows_new_integrations(plane_scene):
    seq, poses = plane_sequence(plane_scene)
    volume = TSDFVolume(voxel_size=0.04, sdf_trunc=0.12)
    h, w = seq.image_size
    for i in range(len(seq)):
        volume.integrate(seq[i].color, seq[i].depth, seq.K, poses[i])
    first = volume.render(poses[1], seq.K, w, h)
    assert first["hit"].mean() > 0.5
    # fuse the same 4 views again with a nearer plane: the surface moves towards it
    for i in range(len(seq)):
        volume.integrate(seq[i].color, np.full((h, w), 0.9, np.float32), seq.K, poses[i])
    second = volume.render(poses[1], seq.K, w, h)
    assert np.median(second["depth"][second["hit"]]) < np.median(first["depth"][first["hit"]]) - 0.02


def test_mesh_is_returned_by_default(plane_scene):
    seq, poses = plane_sequence(plane_scene)
    mesh = tsdf_fusion(seq, poses, voxel_size=0.04, sdf_trunc=0.12, progress=False)
    assert isinstance(mesh, o3d.geometry.TriangleMesh) and len(mesh.vertices) > 0
    assert np.median(np.abs(np.asarray(mesh.vertices)[:, 2] - WORLD_Z)) < 0.01


def test_empty_volume():
    volume = TSDFVolume(voxel_size=0.05, sdf_trunc=0.15, block_count=16)
    assert len(volume.mesh().vertices) == 0
    assert len(volume.point_cloud().points) == 0
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    # frames with no depth in (0, depth_max] are skipped: still empty
    volume.integrate(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32), K, np.eye(4))
    volume.integrate(np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 5.0, np.float32), K, np.eye(4))
    assert isinstance(volume.mesh(), o3d.geometry.TriangleMesh) and len(volume.mesh().vertices) == 0
    assert isinstance(volume.point_cloud(), o3d.geometry.PointCloud) and len(volume.point_cloud().points) == 0
    out = volume.render(np.eye(4), K, 64, 48)
    assert not out["hit"].any() and np.all(out["depth"] == 0) and np.all(out["color"] == 0)


@pytest.mark.parametrize("threshold, empty", [(1.5, False), (2.0, True)])
def test_mesh_keeps_voxels_observed_more_often_than_the_threshold(plane_scene, threshold, empty):
    seq, poses = plane_sequence(plane_scene, n=2)
    volume = tsdf_fusion(seq, poses, voxel_size=0.04, sdf_trunc=0.12, return_volume=True, progress=False,
                         weight_threshold=threshold)
    assert (len(volume.mesh().vertices) == 0) == empty


def test_short_fusion_gives_points_and_hits(plane_scene):
    seq, poses = plane_sequence(plane_scene, n=3)
    volume = tsdf_fusion(seq, poses, voxel_size=0.04, sdf_trunc=0.12, return_volume=True, progress=False,
                         weight_threshold=0.5)
    assert len(volume.point_cloud().points) > 0
    h, w = seq.image_size
    assert volume.render(poses[1], seq.K, w, h)["hit"].any()


@pytest.mark.parametrize(
    "kwargs",
    [{"voxel_size": 0.05, "sdf_trunc": 0.04}, {"voxel_size": 0.05, "sdf_trunc": 0.05},
     {"voxel_size": 0.0, "sdf_trunc": 0.04}, {"voxel_size": 0.01, "sdf_trunc": 0.04, "depth_max": 0.0}],
)
def test_bad_parameters(kwargs):
    with pytest.raises(InputError, match="sdf_trunc > voxel_size") as info:
        TSDFVolume(**kwargs)
    assert f"voxel_size={kwargs['voxel_size']}" in str(info.value)


def test_fusion_checks_poses(plane_scene):
    seq, poses = plane_sequence(plane_scene)
    with pytest.raises(PoseError, match="3 poses for 4 frames"):
        tsdf_fusion(seq, poses[:3], progress=False)
    bad = poses.copy()
    bad[2, :3, :3] *= 1.5
    with pytest.raises(PoseError, match="not rigid"):
        tsdf_fusion(seq, bad, progress=False)
    with pytest.raises(InputError, match="sdf_trunc"):
        tsdf_fusion(seq, poses, voxel_size=0.05, sdf_trunc=0.01, progress=False)


# -- real data: the bundled sample with its GT poses ------------------------------------------
@pytest.fixture(scope="module")
def sample_volume(sample):
    volume = tsdf_fusion(sample, sample.gt_poses, voxel_size=0.01, sdf_trunc=0.04, return_volume=True, progress=False)
    return volume, sample


def test_sample_tsdf_render_matches_input_depth(sample_volume):
    volume, seq = sample_volume
    h, w = seq.image_size
    for i in (0, 5):
        frame = seq[i]
        out = volume.render(seq.gt_poses[i], seq.K, w, h)
        valid = (frame.depth > 0) & (frame.depth < volume.depth_max)
        both = valid & out["hit"]
        assert both.sum() > 0.6 * valid.sum()
        assert np.median(np.abs(out["depth"][both] - frame.depth[both])) < 0.015
        assert 0 <= out["color"].min() and out["color"].max() <= 1
        color_err = np.abs(out["color"][both] - frame.color[both] / 255.0).mean(-1)
        assert np.median(color_err) < 0.08


def test_sample_tsdf_mesh(sample_volume):
    volume, seq = sample_volume
    mesh = volume.mesh()
    vertices = np.asarray(mesh.vertices)
    assert len(vertices) > 5000 and mesh.has_vertex_colors()
    colors = np.asarray(mesh.vertex_colors)
    assert colors.min() >= 0 and colors.max() <= 1 and colors.std() > 0.05
    # the surface lies in front of camera 0 within the depth range of the frames
    cam = (vertices - seq.gt_poses[0, :3, 3]) @ seq.gt_poses[0, :3, :3]
    assert np.percentile(cam[:, 2], 5) > 0.3 and np.percentile(cam[:, 2], 95) < 3.5
