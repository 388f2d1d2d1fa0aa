"""Ray casting triangle meshes with Open3D's RaycastingScene in the library's conventions
(camera-to-world poses, OpenCV axes, pixel centres at integer coordinates, z-depth)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .camera import camera_rays, pixel_grid


def pinhole_rays(pose: np.ndarray, K: np.ndarray, width: int, height: int) -> o3d.core.Tensor:
    """(H, W, 6) float32 rays of a pinhole camera: origin and direction R @ K^-1 [u, v, 1].

    The direction has unit camera-z, so a hit's t is its z-depth (m). Unlike Open3D's
    create_rays_pinhole (which casts through u + 0.5), pixel centres are integers.
    """
    pose = np.asarray(pose, np.float64)
    u, v = pixel_grid(height, width)
    d_world = camera_rays(K, u, v) @ pose[:3, :3].T
    origins = np.broadcast_to(pose[:3, 3], d_world.shape)
    return o3d.core.Tensor(np.concatenate([origins, d_world], -1).astype(np.float32))


class MeshRaycaster:
    """Renders a legacy ``o3d.geometry.TriangleMesh`` (with or without vertex colours)."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh):
        self.colors = np.asarray(mesh.vertex_colors, np.float32) if mesh.has_vertex_colors() else None
        self.triangles = np.asarray(mesh.triangles)
        self.scene = o3d.t.geometry.RaycastingScene()
        if not mesh.is_empty():
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def render(self, pose: np.ndarray, K: np.ndarray, width: int, height: int, depth_max: float = np.inf,
               shade: bool = False) -> dict:
        """color (H, W, 3) float32 in [0, 1] (interpolated vertex colours, grey without; times
        0.4 + 0.6 |cos| of the view angle if `shade`), depth (H, W) float32 z metres (0 = miss
        or beyond depth_max) and hit (H, W) bool."""
        rays = pinhole_rays(pose, K, width, height)
        info = self.scene.cast_rays(rays)
        t = info["t_hit"].numpy()
        hit = np.isfinite(t) & (t <= depth_max)
        color = np.zeros((height, width, 3), np.float32)
        if hit.any():
            color[hit] = 0.7
            if self.colors is not None:
                uv = info["primitive_uvs"].numpy()[hit]
                bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
                color[hit] = (self.colors[self.triangles[info["primitive_ids"].numpy()[hit]]] * bary[..., None]).sum(1)
            if shade:
                d = rays.numpy()[..., 3:][hit]
                cos = np.abs((info["primitive_normals"].numpy()[hit] * d).sum(1)) / np.linalg.norm(d, axis=1)
                color[hit] *= (0.4 + 0.6 * cos)[:, None]
        return {"color": np.clip(color, 0, 1), "depth": np.where(hit, t, 0).astype(np.float32), "hit": hit}
