"""Geometry out of a trained reconstruction (:func:`export_geometry`): point clouds with per-point
depth sigma, meshes with per-vertex depth sigma, PLY files; and the export's settings.

Both come from renders at the training views (fused with the sensor's depth where there is
one: :func:`open3d_pnerf.fusion.fuse_render_with_sensor`): points are back-projected depth
kept where opacity is high and depth_std small; the mesh is Open3D TSDF fusion of the
same depth and colour (the training images' colour where fused with the sensor), so no floater
outside the observed frustums survives (with geometry="sdf", the field's zero level set near
those points instead); each vertex takes the sigma of the nearest of those points, widened by its
distance to it. :func:`sensor_geometry` is the same export without the model, the comparison's
sensor-alone baseline.
"""

from __future__ import annotations

import dataclasses

import matplotlib
import numpy as np
import open3d as o3d
import plyfile
import torch
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from ._files import atomic_write
from .camera import backproject, intrinsic_matrix, scale_intrinsic
from .data.derived import evenly_spaced
from .data.sequence import RGBDSequence, check_sequence
from .fusion import fuse_render_with_sensor
from .settings import FLAG, Settings, count, number, setting
from .targets.noise import SensorNoise
from .tsdf import TSDFVolume, level_set_mesh


@dataclasses.dataclass
class ExportConfig(Settings):
    """Depth-sigma calibration and the mesh and point cloud made after training."""

    calibrate_depth_sigma: bool = setting(True, FLAG)
    """After training, fit how the model's depth spread becomes an error bar (a Student-t law
    by maximum likelihood on training views: Reconstruction.calibrate_depth_sigma)."""
    scale: float = setting(0.5, number(0, 1, low_open=True))
    """Resolution of the renders used for mesh and point-cloud export, relative to training,
    when there is no sensor depth to fuse with (image-only sequences, the model-only export)."""
    fused_scale: float = setting(0.25, number(0, 1, low_open=True))
    """Resolution of the renders fused with sensor depth, relative to training: the fused
    export works at the training resolution (the sensor keeps its own pixels, the render fills
    its holes)."""
    max_views: int = setting(48, count(1))
    """Render at most this many training views (evenly spaced): bounds export time and memory."""
    mesh_voxel_size: float = setting(0.01, number(0, low_open=True, unit="metres"))
    """Voxel size (m) of the TSDF that fuses rendered depth into the exported mesh."""
    mesh_trunc_voxels: float = setting(4.0, number(1, low_open=True))
    """Truncation of that TSDF, in voxels (compare_with_tsdf's TSDF baseline uses the same): more
    closes the slivers a mesh leaves at depth edges and where views' coverage ends, at some cost in
    accuracy where surfaces are thin or poses are off (docs/benchmarks.md measures 4 against 8)."""
    mesh_min_views: int = setting(1, count(1))
    """Keep mesh surfaces seen in at least this many export views: 1 keeps all (the most
    complete mesh); 2 drops surfaces seen once, where the sensor's noise is not averaged (more
    accurate, with holes where only one view looked)."""
    max_point_std: float = setting(0.1, number(0, low_open=True, unit="metres"))
    """Exported points whose rendered depth std exceeds this (m) are dropped."""
    min_opacity: float = setting(0.9, number(0, 1))
    """Exported points/mesh depth need at least this accumulated opacity."""
    depth_sigma_relative: float = setting(SensorNoise.relative, number(0, 1, high_open=True))
    """Systematic depth error of the sensor as a fraction of depth, in the exported sigma: added in
    quadrature wherever the sensor's depth is fused (the depth targets' own term,
    targets.depth_sigma_relative, is a training choice and wider)."""

    def sensor_noise(self) -> SensorNoise:
        """The sensor's noise model the export fuses with: random noise and this systematic term."""
        return SensorNoise(relative=self.depth_sigma_relative)


def point_cloud_from_renders(renders: list[dict], poses, K, min_opacity=0.9, max_std=0.05, voxel_size=0.005,
                             stride: int = 1):
    """Coloured point cloud and per-point depth sigma (m) from renders at `poses`.

    renders: dicts with color (H, W, 3), depth and depth_std (H, W) z metres, opacity (H, W).
    Every `stride`-th pixel along rows and columns gives a point; points are voxel-downsampled
    (voxel_size m), averaging colour and sigma. Returns (o3d.geometry.PointCloud, sigma (M,) float32).
    """
    pts, cols, sig = [], [], []
    for r, pose in zip(renders, poses):
        mask = (r["opacity"] >= min_opacity) & (r["depth_std"] <= max_std) & (r["depth"] > 0)
        mask[np.arange(mask.shape[0]) % stride != 0] = False
        mask[:, np.arange(mask.shape[1]) % stride != 0] = False
        pts.append(backproject(r["depth"], K, pose, mask)[0])
        cols.append(r["color"][mask])
        sig.append(r["depth_std"][mask])
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.concatenate(pts).astype(np.float32)))
    cloud.point.colors = o3d.core.Tensor(np.concatenate(cols).astype(np.float32))
    cloud.point.depth_sigma = o3d.core.Tensor(np.concatenate(sig).astype(np.float32)[:, None])
    if voxel_size > 0 and len(cloud.point.positions):
        cloud = cloud.voxel_down_sample(voxel_size)
    sigma = cloud.point.depth_sigma.numpy()[:, 0].copy()
    return cloud.to_legacy(), sigma


def mesh_from_renders(renders: list[dict], poses, K, voxel_size=0.01, min_opacity=0.9, max_std=0.05, depth_max=5.0,
                      min_views: int = 1, trunc_voxels: float = 4.0):
    """Coloured mesh: TSDF fusion (Open3D) of rendered depth/colour where confident, truncated at
    trunc_voxels voxels of voxel_size (m).

    Rendered depth is already filtered by opacity and depth_std, so by default (min_views 1)
    one view suffices per voxel; min_views 2 keeps only surfaces that at least two renders see.
    """
    volume = TSDFVolume(voxel_size, trunc_voxels * voxel_size, depth_max, weight_threshold=min_views - 0.5)
    for r, pose in zip(renders, poses):
        depth = np.where((r["opacity"] >= min_opacity) & (r["depth_std"] <= max_std), r["depth"], 0).astype(np.float32)
        color = (np.clip(r["color"], 0, 1) * 255).astype(np.uint8)
        volume.integrate(color, depth, K, pose)
    return volume.mesh()


def uncertainty_colors(sigma: np.ndarray, vmax: float | None = None, cmap: str = "viridis") -> np.ndarray:
    """(M, 3) float colours of sigma values (m); vmax defaults to the 95th percentile."""
    vmax = vmax or (float(np.percentile(sigma, 95)) if len(sigma) else 1.0)
    return matplotlib.colormaps[cmap](np.clip(sigma / max(vmax, 1e-9), 0, 1))[:, :3]


def vertex_sigma(mesh: o3d.geometry.TriangleMesh, points: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(V,) float32 sigma (m) of each mesh vertex: sqrt(s^2 + d^2), s the sigma of the nearest
    of `points` (M, 3) with `sigma` (M,) (the depth points the mesh was made from) and d the
    distance to it (a vertex away from every point is no better known than that); NaN without points."""
    vertices = np.asarray(mesh.vertices)
    if not len(points) or not len(vertices):
        return np.full(len(vertices), np.nan, np.float32)
    distance, nearest = cKDTree(points).query(vertices)
    return np.hypot(np.asarray(sigma, np.float64)[nearest], distance).astype(np.float32)


def sdf_surface(recon, cloud: o3d.geometry.PointCloud, voxel_size: float) -> o3d.geometry.TriangleMesh:
    """The zero level set of a reconstruction's signed distance (geometry="sdf") near the points of
    `cloud` (:func:`~open3d_pnerf.tsdf.level_set_mesh`), each vertex with the colour of the nearest
    point (the renders' colour, as the fused mesh has it)."""
    field, device = recon.field, recon.device

    @torch.no_grad()
    def signed_distance(points):
        return field.signed_distance(torch.as_tensor(points, device=device)).cpu().numpy()

    points = np.asarray(cloud.points)
    mesh = level_set_mesh(signed_distance, points, voxel_size)
    if mesh.has_vertices() and cloud.has_colors():
        nearest = cKDTree(points).query(np.asarray(mesh.vertices))[1]
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(cloud.colors)[nearest])
    return mesh


SIGMA_PROPERTIES = ("depth_sigma", "quality", "scalar_depth_sigma")
"""The PLY vertex properties that carry each point's or vertex's sigma (m), the same values under three
names: ``depth_sigma`` says what it is (Open3D's tensor reader, plyfile), ``quality`` is the one
per-vertex scalar MeshLab (and pymeshlab) reads, to colour or filter by, and CloudCompare loads a
``scalar_`` property as a scalar field by itself (``depth sigma``; its command line reads no other)."""


def write_mesh_ply(path, mesh: o3d.geometry.TriangleMesh, sigma: np.ndarray | None = None) -> None:
    """Write a mesh as binary PLY, atomically. Given `sigma` (V,) (m), each vertex also gets it as
    the float properties of :data:`SIGMA_PROPERTIES` beside x, y, z and uchar red, green, blue
    (Open3D's mesh writers drop extra vertex properties, so this one writes them with plyfile):
    Open3D's mesh readers, MeshLab, CloudCompare and trimesh read the mesh, ``o3d.t.io.read_point_cloud``,
    plyfile, MeshLab and CloudCompare the per-vertex sigma too."""
    if sigma is None:
        atomic_write(path, lambda p: o3d.io.write_triangle_mesh(p, mesh, write_ascii=False))
        return
    vertices = np.asarray(mesh.vertices, np.float32)
    sigma = np.asarray(sigma, np.float32)
    if sigma.shape != (len(vertices),):
        raise ValueError(f"sigma must have one value per vertex ({len(vertices)},), got {sigma.shape}")
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if mesh.has_vertex_colors():
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(vertices), fields + [(name, "f4") for name in SIGMA_PROPERTIES])
    for k, name in enumerate("xyz"):
        vertex[name] = vertices[:, k]
    if mesh.has_vertex_colors():
        rgb = (np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).round().astype(np.uint8)
        vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    for name in SIGMA_PROPERTIES:
        vertex[name] = sigma
    faces = np.empty(len(mesh.triangles), [("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = np.asarray(mesh.triangles, np.int32)
    data = plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")])
    atomic_write(path, lambda p: data.write(p))


def read_mesh_ply(path) -> tuple[o3d.geometry.TriangleMesh, np.ndarray | None]:
    """Read a mesh PLY (Open3D) and its per-vertex `depth_sigma` when it has one: (mesh, sigma or None)."""
    mesh = o3d.io.read_triangle_mesh(str(path))
    t = o3d.t.io.read_point_cloud(str(path))
    sigma = t.point.depth_sigma.numpy()[:, 0].copy() if "depth_sigma" in t.point else None
    return mesh, sigma


def write_point_cloud_ply(path, cloud: o3d.geometry.PointCloud, sigma: np.ndarray | None = None) -> None:
    """Write a point cloud as binary PLY, atomically: colours as uchar red/green/blue (what
    Open3D's readers, MeshLab, CloudCompare, trimesh and plyfile expect) and, given `sigma`
    (M,) (m), the float per-vertex properties of :data:`SIGMA_PROPERTIES`."""
    t = o3d.t.geometry.PointCloud.from_legacy(cloud)
    if cloud.has_colors():
        t.point.colors = o3d.core.Tensor((np.clip(np.asarray(cloud.colors), 0, 1) * 255).round().astype(np.uint8))
    if sigma is not None:
        for name in SIGMA_PROPERTIES:
            t.point[name] = o3d.core.Tensor(np.asarray(sigma, np.float32)[:, None])
    atomic_write(path, lambda p: o3d.t.io.write_point_cloud(p, t, write_ascii=False))


def read_point_cloud_ply(path) -> tuple[o3d.geometry.PointCloud, np.ndarray | None]:
    """Read a PLY written by :func:`write_point_cloud_ply`: (cloud, depth_sigma or None)."""
    t = o3d.t.io.read_point_cloud(str(path))
    sigma = t.point.depth_sigma.numpy()[:, 0].copy() if "depth_sigma" in t.point else None
    return t.to_legacy(), sigma


@dataclasses.dataclass
class Geometry:
    """A reconstruction's exported geometry: a coloured mesh with each vertex's depth sigma
    mesh_sigma (V,) m, a coloured point cloud with each point's point_sigma (M,) m (None where
    nothing was exported)."""

    mesh: o3d.geometry.TriangleMesh | None = None
    mesh_sigma: np.ndarray | None = None
    point_cloud: o3d.geometry.PointCloud | None = None
    point_sigma: np.ndarray | None = None


@dataclasses.dataclass
class ExportViews:
    """The per-view depth an export builds its geometry from: renders (dicts with color (H, W, 3),
    depth and depth_std (H, W) z metres, opacity (H, W)) at camera-to-world `poses` (V, 4, 4) with
    intrinsic matrix K (3, 3); `fused`: each render's depth fused with the sensor's (at the training
    resolution) and its colour the training image's (at the average exposure), else the model's alone
    (at ExportConfig.scale)."""

    poses: np.ndarray
    K: np.ndarray
    renders: list[dict]
    fused: bool


def export_views(recon, sequence: RGBDSequence | None = None, config: ExportConfig | None = None,
                 progress: bool = True) -> ExportViews:
    """The depth of :func:`export_geometry`'s views, before surfaces are made of it.

    Renders training views (at most config.max_views, evenly spaced) at config.scale of the
    training resolution (config.fused_scale when fused with sensor depth). sequence: the input
    sequence (all frames, as given to reconstruct()); when it has depth images, each view's
    rendered depth is fused per pixel with the sensor's depth at the training resolution (the
    render brought to it by nearest pixel) by :func:`~open3d_pnerf.fusion.fuse_render_with_sensor`,
    with the sensor's random sigma (:class:`~open3d_pnerf.targets.SensorNoise`); its systematic
    part (config.depth_sigma_relative) is common to both, the model having learned from this
    sensor, so it is added to the fused variance afterwards: observed surfaces keep the sensor's
    accuracy, the others come from the model, each with its fused sigma. The colour of a fused
    view is its training image's (registered to the depth, divided by the frame's colour gains to
    the average exposure the model renders), as TSDF fusion colours its mesh. config: the export
    settings (default: the reconstruction's).
    """
    cfg = config or recon.config.export
    frames, views = _export_views(recon, sequence, cfg)
    poses = recon.poses[frames]
    intr = scale_intrinsic(recon.intrinsic, cfg.scale) if views is None else \
        scale_intrinsic(views.intrinsic, cfg.fused_scale)
    renders = [recon.render(p, intr) for p in tqdm(poses, desc="export renders", disable=not progress, leave=False)]
    if views is None:
        return ExportViews(poses, intrinsic_matrix(intr), renders, fused=False)
    noise = cfg.sensor_noise()
    for k, r in enumerate(renders):
        z = _inside_box(views[k].depth, views.K, poses[k], recon.aabb)
        # the model learned from this sensor, so its systematic error is common to both: fuse the
        # independent (random) parts, then add the common part back; max_point_std applies to the
        # model's depth before the fusion
        fused = fuse_render_with_sensor(r, z, noise.sigma(z), cfg.min_opacity, cfg.max_point_std,
                                        recon.depth_sigma_dof)
        common = np.where(z > 0, noise.systematic_var(fused["depth"]), 0)
        fused["depth_std"] = np.sqrt(fused["depth_std"] ** 2 + common).astype(np.float32)
        # the colour the camera saw, at the average exposure (as the model renders it): sharper than a render
        image = views.color_on_depth_grid(views[k].color, views[k].depth) / 255.0
        fused["color"] = np.clip(image / recon.color_gains[frames[k]], 0, 1).astype(np.float32)
        renders[k] = fused
    return ExportViews(poses, views.K, renders, fused=True)


def export_geometry(recon, sequence: RGBDSequence | None = None, config: ExportConfig | None = None,
                    progress: bool = True) -> Geometry:
    """The mesh and point cloud of a Reconstruction, with their depth sigma, made of the depth of
    :func:`export_views` (the model's alone, filtered by config.max_point_std, without a sequence
    with depth images; fused with the sensor's otherwise). config: the export settings (default:
    the reconstruction's). :func:`sensor_geometry` is the same export without the model.
    """
    cfg = config or recon.config.export
    views = export_views(recon, sequence, cfg, progress)
    level_set = recon if getattr(recon.field, "sdf", None) is not None else None
    # the model alone: its depth filtered by max_point_std, every pixel; fused (at the sensor's resolution):
    # no filter, every pixel a render at the export scale would have
    max_std, stride = (np.inf, max(1, round(1 / cfg.scale))) if views.fused else (cfg.max_point_std, 1)
    return _geometry(views.renders, views.poses, views.K, cfg, max_std, stride, level_set)


def sensor_geometry(recon, sequence: RGBDSequence, config: ExportConfig | None = None) -> Geometry:
    """:func:`export_geometry` without the model: the sensor's own depth and colour in the same
    views at the training resolution, with its sigma (random and systematic), fused into a point
    cloud and a mesh exactly as the export fuses the model's and the sensor's (the ablation of the
    model: what the sensor alone gives). sequence: the input sequence, with depth images."""
    cfg = config or recon.config.export
    check_sequence(sequence, len(recon.poses), "sensor_geometry(): sequence", needs_depth=True)
    frames, views = _export_views(recon, sequence, cfg)
    poses = recon.poses[frames]
    noise, renders = cfg.sensor_noise(), []
    for k, pose in enumerate(poses):
        frame = views[k]
        z = _inside_box(frame.depth, views.K, pose, recon.aabb)
        sigma = np.sqrt(noise.sigma(z) ** 2 + noise.systematic_var(z))
        renders.append({"color": views.color_on_depth_grid(frame.color, frame.depth) / 255.0, "depth": z,
                        "depth_std": np.where(z > 0, sigma, np.inf).astype(np.float32),
                        "opacity": (z > 0).astype(np.float32)})
    return _geometry(renders, poses, views.K, cfg, np.inf, max(1, round(1 / cfg.scale)))


def _export_views(recon, sequence: RGBDSequence | None, cfg: ExportConfig):
    """(frame indices (V,), the sequence's frames at those views at the training resolution, or None
    without sensor depth) of the export views: at most cfg.max_views training frames, evenly spaced."""
    frames = recon.train_indices[evenly_spaced(len(recon.train_indices), cfg.max_views)]
    views = None
    if sequence is not None:
        check_sequence(sequence, len(recon.poses), "export_geometry(): sequence")
        if sequence.has_depth:
            views = sequence.select(frames).scaled_by(recon.config.image_scale)
    return frames, views


def _geometry(renders: list[dict], poses: np.ndarray, K: np.ndarray, cfg: ExportConfig, max_std: float,
              stride: int, level_set=None) -> Geometry:
    """The point cloud (every `stride`-th pixel) and mesh of renders (depth filtered by cfg's opacity
    and `max_std`), each point and vertex with its depth sigma. The mesh: TSDF fusion of the
    renders, or the zero level set of the reconstruction `level_set` (geometry="sdf") near the
    points, where its vertices' sigma is at most cfg.max_point_std."""
    cloud, point_sigma = point_cloud_from_renders(renders, poses, K, cfg.min_opacity, max_std,
                                                  voxel_size=cfg.mesh_voxel_size / 2, stride=stride)
    points = np.asarray(cloud.points)
    if level_set is None:
        mesh = mesh_from_renders(renders, poses, K, cfg.mesh_voxel_size, cfg.min_opacity, max_std,
                                 min_views=cfg.mesh_min_views, trunc_voxels=cfg.mesh_trunc_voxels)
        return Geometry(mesh, vertex_sigma(mesh, points, point_sigma), cloud, point_sigma)
    mesh = sdf_surface(level_set, cloud, cfg.mesh_voxel_size)
    sigma = vertex_sigma(mesh, points, point_sigma)
    mesh.remove_vertices_by_mask(~(sigma <= cfg.max_point_std))
    return Geometry(mesh, sigma[sigma <= cfg.max_point_std], cloud, point_sigma)


def _inside_box(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """A z-depth map (H, W) m with 0 where its point lies outside the scene box aabb (2, 3) (stray far
    returns the box left out)."""
    pts, flat = backproject(depth, K, pose)
    outside = flat[((pts < aabb[0]) | (pts > aabb[1])).any(1)]
    depth = depth.copy()
    depth.flat[outside] = 0
    return depth
