"""Baselines to compare against: Open3D TSDF fusion (tensor VoxelBlockGrid, CPU or CUDA)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from tqdm.auto import tqdm

from .data.sequence import RGBDSequence, check_poses
from .errors import InputError


class TSDFVolume:
    """A coloured TSDF volume (Open3D ``t.geometry.VoxelBlockGrid``).

    voxel_size and sdf_trunc in metres; depth beyond depth_max (m) is ignored. Poses are
    camera-to-world (N, 4, 4); Open3D's world-to-camera extrinsic is derived here, once.
    """

    def __init__(
        self,
        voxel_size: float = 0.01,
        sdf_trunc: float = 0.04,
        depth_max: float = 3.0,
        block_count: int = 4_000,
        device: str = "CPU:0",
    ):
        if not (voxel_size > 0 and sdf_trunc > voxel_size and depth_max > 0):
            raise InputError(
                f"need voxel_size > 0, sdf_trunc > voxel_size and depth_max > 0; got "
                f"voxel_size={voxel_size}, sdf_trunc={sdf_trunc}, depth_max={depth_max}"
            )
        self.voxel_size = voxel_size
        self.depth_max = depth_max
        self.trunc_multiplier = sdf_trunc / voxel_size
        self.device = o3d.core.Device(device)
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=voxel_size,
            block_resolution=16,
            block_count=block_count,
            device=self.device,
        )

    def _tensor(self, array, dtype=o3d.core.float64):
        return o3d.core.Tensor(np.ascontiguousarray(array), dtype, self.device)

    def integrate(self, color: np.ndarray, depth: np.ndarray, K: np.ndarray, pose: np.ndarray, K_color=None):
        """Fuse one frame: colour uint8 (H, W, 3), depth float32 metres, camera-to-world pose.

        A frame without valid depth (0 < depth <= depth_max) is skipped.
        """
        if not ((depth > 0) & (depth <= self.depth_max)).any():
            return
        depth_img = o3d.t.geometry.Image(self._tensor(depth, o3d.core.float32))
        color_img = o3d.t.geometry.Image(self._tensor(color.astype(np.float32) / 255.0, o3d.core.float32))
        intr = self._tensor(K)
        extr = self._tensor(np.linalg.inv(pose))
        coords = self.grid.compute_unique_block_coordinates(
            depth_img, intr, extr, 1.0, self.depth_max, self.trunc_multiplier
        )
        intr_c = intr if K_color is None else self._tensor(K_color)
        self.grid.integrate(
            coords, depth_img, color_img, intr, intr_c, extr, 1.0, self.depth_max, self.trunc_multiplier
        )

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """Marching-cubes surface with vertex colours, as a legacy Open3D mesh (empty if nothing fused)."""
        if self.grid.hashmap().size() == 0:
            return o3d.geometry.TriangleMesh()
        mesh = self.grid.extract_triangle_mesh().to_legacy()
        mesh.compute_vertex_normals()
        return mesh

    def point_cloud(self) -> o3d.geometry.PointCloud:
        """Zero-crossing points with colours, as a legacy Open3D point cloud (empty if nothing fused)."""
        if self.grid.hashmap().size() == 0:
            return o3d.geometry.PointCloud()
        return self.grid.extract_point_cloud().to_legacy()

    def render(self, pose: np.ndarray, K: np.ndarray, width: int, height: int) -> dict:
        """Ray-cast the volume from a camera-to-world pose.

        Returns color (H, W, 3) float32 in [0, 1], depth (H, W) float32 z metres (0 = miss)
        and hit (H, W) bool.
        """
        intr, extr = self._tensor(K), self._tensor(np.linalg.inv(pose))
        keys = self.grid.hashmap().key_tensor()
        result = self.grid.ray_cast(
            keys, intr, extr, width, height, ["depth", "color"], 1.0, 0.1, self.depth_max,
            3.0, self.trunc_multiplier,
        )
        depth = result["depth"].cpu().numpy()[..., 0].astype(np.float32)
        color = np.clip(result["color"].cpu().numpy().astype(np.float32), 0, 1)
        hit = depth > 0
        color[~hit] = 0
        return {"color": color, "depth": depth, "hit": hit}


def tsdf_fusion(
    sequence: RGBDSequence,
    poses: np.ndarray,
    voxel_size: float = 0.01,
    sdf_trunc: float = 0.04,
    depth_max: float = 3.0,
    device: str = "CPU:0",
    return_volume: bool = False,
    progress: bool = True,
):
    """Open3D TSDF fusion of every frame of `sequence` at camera-to-world `poses` (N, 4, 4).

    Returns the coloured ``o3d.geometry.TriangleMesh``; with return_volume=True returns the
    :class:`TSDFVolume` instead (for ``.point_cloud()`` and ``.render(pose, K, w, h)``).
    """
    poses = check_poses(poses, len(sequence), "poses")
    volume = TSDFVolume(voxel_size, sdf_trunc, depth_max, device=device)
    K = sequence.K
    K_color = np.asarray(sequence.color_intrinsic.intrinsic_matrix)
    for i in tqdm(range(len(sequence)), desc="TSDF fusion", disable=not progress, leave=False):
        frame = sequence[i]
        volume.integrate(frame.color, frame.depth, K, poses[i], K_color)
    return volume if return_volume else volume.mesh()
