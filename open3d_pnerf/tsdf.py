"""Open3D TSDF fusion (tensor VoxelBlockGrid, CPU or CUDA): the baseline users already have, and
how the model's rendered depth becomes a mesh."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from tqdm.auto import tqdm

from .camera import camera_poses, pose_to_extrinsic
from .data.sequence import RGBDSequence, check_sequence
from .errors import InputError
from .raycast import MeshRaycaster

OPEN3D_WEIGHT_THRESHOLD = 3.0
"""Open3D's default weight threshold of a TSDF's surface: voxels observed more than 3 times."""


class TSDFVolume:
    """A coloured TSDF volume (Open3D ``t.geometry.VoxelBlockGrid``).

    voxel_size and sdf_trunc in metres; depth beyond depth_max (m) is ignored. Poses are
    camera-to-world (N, 4, 4); Open3D's world-to-camera extrinsic is derived here, once.
    Surfaces (mesh, points, renders) keep voxels whose fused weight (number of
    observations) exceeds weight_threshold: 3.0 is Open3D's default; use 0.5 to keep
    everything seen once.
    """

    def __init__(
        self,
        voxel_size: float = 0.01,
        sdf_trunc: float = 0.04,
        depth_max: float = 3.0,
        block_count: int = 4_000,
        device: str = "CPU:0",
        weight_threshold: float = 3.0,
    ):
        if not (voxel_size > 0 and sdf_trunc > voxel_size and depth_max > 0):
            raise InputError(
                f"need voxel_size > 0, sdf_trunc > voxel_size and depth_max > 0; got "
                f"voxel_size={voxel_size}, sdf_trunc={sdf_trunc}, depth_max={depth_max}"
            )
        self.voxel_size = voxel_size
        self.depth_max = depth_max
        self.weight_threshold = weight_threshold
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
        self._raycaster = None

    def _tensor(self, array, dtype=o3d.core.float64):
        return o3d.core.Tensor(np.ascontiguousarray(array), dtype, self.device)

    def integrate(self, color: np.ndarray, depth: np.ndarray, K: np.ndarray, pose: np.ndarray):
        """Fuse one frame: colour uint8 (H, W, 3) on the depth grid, depth float32 metres, camera-to-world pose.

        A frame without valid depth (0 < depth <= depth_max) is skipped.
        """
        if not ((depth > 0) & (depth <= self.depth_max)).any():
            return
        depth_img = o3d.t.geometry.Image(self._tensor(depth, o3d.core.float32))
        color_img = o3d.t.geometry.Image(self._tensor(color.astype(np.float32) / 255.0, o3d.core.float32))
        intr = self._tensor(K)
        extr = self._tensor(pose_to_extrinsic(pose))
        try:
            coords = self.grid.compute_unique_block_coordinates(
                depth_img, intr, extr, 1.0, self.depth_max, self.trunc_multiplier
            )
        except RuntimeError as exc:  # too few valid pixels to touch a block: nothing to fuse
            if "No block is touched" in str(exc):
                return
            raise
        # Open3D reads a voxel's depth from pixel floor(u) (pixel i spans [i, i + 1)); with pixel
        # centres at integers the nearest pixel is floor(u + 0.5): shift the principal point by half
        # a pixel (else oblique surfaces move by half a pixel's depth change, ~1 cm at 160x120)
        half = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
        intr_centred = self._tensor(np.asarray(K, np.float64) + half)
        self._raycaster = None  # the cached ray-casting mesh is stale now
        self.grid.integrate(
            coords, depth_img, color_img, intr_centred, intr_centred, extr, 1.0, self.depth_max, self.trunc_multiplier
        )

    def mesh(self, weight_threshold: float | None = None) -> o3d.geometry.TriangleMesh:
        """Marching-cubes surface with vertex colours, as a legacy Open3D mesh (empty if nothing
        fused), of the voxels observed more often than weight_threshold (default: the volume's)."""
        if self.grid.hashmap().size() == 0:
            return o3d.geometry.TriangleMesh()
        threshold = self.weight_threshold if weight_threshold is None else weight_threshold
        mesh = self.grid.extract_triangle_mesh(weight_threshold=threshold).to_legacy()
        mesh.compute_vertex_normals()
        return mesh

    def point_cloud(self) -> o3d.geometry.PointCloud:
        """Zero-crossing points with colours, as a legacy Open3D point cloud (empty if nothing fused)."""
        if self.grid.hashmap().size() == 0:
            return o3d.geometry.PointCloud()
        return self.grid.extract_point_cloud(weight_threshold=self.weight_threshold).to_legacy()

    def render(self, pose: np.ndarray, K: np.ndarray, width: int, height: int) -> dict:
        """Ray-cast the fused surface from a camera-to-world pose (pixel centres at integers).

        Casts against the extracted mesh (:class:`~open3d_pnerf.raycast.MeshRaycaster`; the
        VoxelBlockGrid's own ray_cast hangs on its second call in open3d 0.19 on CPU) and
        interpolates vertex colours. Returns color (H, W, 3) float32 in [0, 1], depth (H, W) float32 z metres
        (0 = miss) and hit (H, W) bool.
        """
        if self._raycaster is None:
            self._raycaster = MeshRaycaster(self.mesh())
        return self._raycaster.render(pose, K, width, height, self.depth_max)


def tsdf_fusion(
    sequence: RGBDSequence,
    poses: np.ndarray,
    voxel_size: float = 0.01,
    sdf_trunc: float = 0.04,
    depth_max: float = 3.0,
    device: str = "CPU:0",
    return_volume: bool = False,
    progress: bool = True,
    weight_threshold: float = 3.0,
):
    """Open3D TSDF fusion of every frame of `sequence` at camera-to-world `poses` (N, 4, 4) (or an
    ``o3d.camera.PinholeCameraTrajectory`` or a Trajectory).

    Returns the coloured ``o3d.geometry.TriangleMesh``; with return_volume=True returns the
    :class:`TSDFVolume` instead (for ``.point_cloud()`` and ``.render(pose, K, w, h)``).
    weight_threshold: surfaces keep voxels observed more often than this (see TSDFVolume).
    """
    n = len(check_sequence(sequence, what="tsdf_fusion(): sequence", needs_depth=True))
    poses = camera_poses(poses, n, "poses")[0]
    volume = TSDFVolume(voxel_size, sdf_trunc, depth_max, device=device, weight_threshold=weight_threshold)
    K = sequence.K
    for i in tqdm(range(len(sequence)), desc="TSDF fusion", disable=not progress, leave=False):
        frame = sequence[i]
        volume.integrate(sequence.color_on_depth_grid(frame.color, frame.depth), frame.depth, K, poses[i])
    return volume if return_volume else volume.mesh()


def level_set_mesh(signed_distance, near_points: np.ndarray, voxel_size: float, block_resolution: int = 8,
                   chunk: int = 1 << 18) -> o3d.geometry.TriangleMesh:
    """The zero level set of a signed distance as a triangle mesh, by Open3D's marching cubes.

    signed_distance: a callable from (M, 3) float32 world points (m) to (M,) signed distances
    (m, positive in free space), called on at most `chunk` points at a time. It is evaluated at
    the voxels (edge voxel_size m) of the blocks of `block_resolution` voxels that hold
    `near_points` (P, 3) m and of their 26 neighbours: the surface is extracted there only.
    Returns an uncoloured legacy mesh (empty without points or without a zero crossing).
    """
    near_points = np.asarray(near_points, np.float64).reshape(-1, 3)
    near_points = near_points[np.isfinite(near_points).all(1)]
    if not len(near_points):
        return o3d.geometry.TriangleMesh()
    block = voxel_size * block_resolution
    keys = np.unique(np.floor(near_points / block).astype(np.int64), axis=0)
    neighbours = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = np.unique((keys[:, None] + neighbours[None]).reshape(-1, 3), axis=0).astype(np.int32)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3d.core.float32, o3d.core.float32), attr_channels=((1), (1)),
        voxel_size=voxel_size, block_resolution=block_resolution, block_count=len(keys))
    grid.hashmap().activate(o3d.core.Tensor(keys))
    coords, index = grid.voxel_coordinates_and_flattened_indices()
    coords = coords.numpy().astype(np.float32)
    sdf = np.concatenate([np.asarray(signed_distance(coords[i:i + chunk]), np.float32).reshape(-1)
                          for i in range(0, len(coords), chunk)])
    if not ((sdf < 0).any() and (sdf > 0).any()):  # no zero crossing (Open3D's extraction fails on none)
        return o3d.geometry.TriangleMesh()
    trunc = 3 * voxel_size  # marching cubes reads sdf / trunc in [-1, 1]
    grid.attribute("tsdf").reshape((-1, 1))[index] = o3d.core.Tensor(np.clip(sdf / trunc, -1, 1)[:, None])
    grid.attribute("weight").reshape((-1, 1))[index] = o3d.core.Tensor(np.ones((len(sdf), 1), np.float32))
    return grid.extract_triangle_mesh(weight_threshold=0.5).to_legacy()
