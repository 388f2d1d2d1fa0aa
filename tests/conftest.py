"""Shared fixtures: the ../shared/data location, the bundled sample, a synthetic plane scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

# Same location as tests/test_tracking.py uses (the repository's sibling folder shared/data).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def sample():
    """The bundled 11-frame TUM fr1/xyz sample (loaded once; frames stay lazy)."""
    from open3d_pnerf.data import load_sample

    return load_sample()


# -- a fronto-parallel plane seen by cameras translated along x -------------------------
PLANE_W, PLANE_H, PLANE_F = 64, 48, 50.0
PLANE_CX, PLANE_CY = 32.0, 24.0  # integer principal point: the centre pixel's ray is (0, 0, 1)


def plane_intrinsic() -> o3d.camera.PinholeCameraIntrinsic:
    return o3d.camera.PinholeCameraIntrinsic(PLANE_W, PLANE_H, PLANE_F, PLANE_F, PLANE_CX, PLANE_CY)


def make_plane_scene(z0: float = 2.0, shifts=(-0.04, 0.0, 0.04), color=(200, 100, 50)):
    """(depths, colors, poses) of the world plane z = z0 seen by identity-rotation cameras at
    x = shifts. With the defaults a step of 0.04 m moves the plane by fx * 0.04 / z0 = 1 px."""
    poses = np.tile(np.eye(4), (len(shifts), 1, 1))
    poses[:, 0, 3] = shifts
    depths = [np.full((PLANE_H, PLANE_W), z0, np.float32) for _ in shifts]
    colors = [np.full((PLANE_H, PLANE_W, 3), color, np.uint8) for _ in shifts]
    return depths, colors, poses


@pytest.fixture(scope="session")
def plane_scene():
    """Factory: plane_scene(z0=..., shifts=..., depths=None) -> (RGBDSequence, poses).

    `edit(depths)` may modify the list of float32 depth maps before the sequence is built."""
    from open3d_pnerf.data import RGBDSequence

    def build(z0: float = 2.0, shifts=(-0.04, 0.0, 0.04), edit=None, color=(200, 100, 50)):
        depths, colors, poses = make_plane_scene(z0, shifts, color)
        if edit is not None:
            edit(depths)
        seq = RGBDSequence.from_rgbd_images(list(zip(colors, depths)), plane_intrinsic(), gt_poses=poses)
        return seq, poses

    return build


def tiny_reconstruction(shift: float = 0.0):
    """An untrained Reconstruction of the plane scene's 3 frames with a small mesh and point cloud,
    cheap to save and load. shift changes every saved file (poses, box, geometry, weights, gains)."""
    import torch

    from open3d_pnerf import Reconstruction, ReconstructionConfig
    from open3d_pnerf.export import Geometry
    from open3d_pnerf.observed import ObservedSurface

    config = ReconstructionConfig.preset("test", field="grid", progress=False, **{"grid.resolutions": (8, 16)})
    aabb = np.array([[-1, -1, 0], [1, 1, 3]], np.float32) + shift
    field = config.build_field(aabb)
    with torch.no_grad():
        for p in field.parameters():
            p.add_(shift)
    poses = make_plane_scene()[2]
    poses[:, 2, 3] += shift
    points = np.random.default_rng(0).random((10, 3)) + shift
    covariances = np.tile(shift * np.eye(6), (3, 1, 1))
    geometry = Geometry(mesh=o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((0, 0, shift)),
                        point_cloud=o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)),
                        point_sigma=np.full(10, 0.01))
    return Reconstruction(field, config, poses, covariances, plane_intrinsic(), [1, 2], [0], geometry=geometry,
                          color_gains=np.full((3, 3), 1 + shift), observed=ObservedSurface(0.01, points))
