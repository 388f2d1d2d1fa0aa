"""The Reconstruction: a trained probabilistic scene model with its poses, and what it renders.

What else a reconstruction has lives beside it, each in its own module: the law of its depth
errors (:class:`~open3d_pnerf.error_law.DepthErrorLaw`), its exported mesh and point cloud
(:func:`open3d_pnerf.export.export_geometry`) and its folder on disk
(:mod:`open3d_pnerf.storage`); the methods here that reach them are one line each.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from . import occupancy, storage
from .camera import camera_pose, check_intrinsic, intrinsic_matrix, pose_to_extrinsic, unproject
from .config import ReconstructionConfig
from .data.nerfstudio import write_nerfstudio
from .data.sequence import RGBDSequence, check_sequence
from .error_law import DepthErrorLaw, depth_jump
from .errors import InputError
from .evaluation import training_depth_errors
from .export import Geometry
from .extension import extend
from .model import PNeRFModel
from .observed import ObservedSurface
from .occupancy import SensorModel
from .rendering import Rays


@dataclasses.dataclass(eq=False, repr=False)
class Reconstruction:
    """A trained probabilistic scene model with its poses.

    model: the :class:`~open3d_pnerf.model.PNeRFModel` (a bare field is given the config's
    sampling and loss). poses (N, 4, 4) camera-to-world and covariances (N, 6, 6) cover every
    frame of the input sequence; train_indices / holdout_indices say which trained; timestamps
    (N,) s. intrinsic: the training-resolution ``o3d.camera.PinholeCameraIntrinsic``.
    color_gains (N, 3): each frame's camera exposure as per-channel gains on the rendered colour
    (learned for training frames, interpolated in time for the others; ones without exposure
    compensation); see :meth:`render`. depth_error: how the model's depth spread becomes a
    calibrated 1-sigma error (:meth:`calibrate_depth_sigma`). observed: the surfaces the
    training frames' depth saw, and those views (None without depth): away from them, and where a
    training view saw past the rendered point, the law widens the rendered depth sigma
    (:meth:`render`). geometry: the exported mesh and point cloud with their per-vertex and
    per-point depth sigma (``recon.mesh``, ...). frames: the RGB-D frames it was
    built from (an :class:`~open3d_pnerf.RGBDSequence` of all N, read lazily; saved with it), which
    :meth:`extend` replays; None when not kept.
    """

    model: PNeRFModel
    config: ReconstructionConfig
    poses: np.ndarray
    covariances: np.ndarray
    intrinsic: o3d.camera.PinholeCameraIntrinsic
    train_indices: np.ndarray
    holdout_indices: np.ndarray
    timestamps: np.ndarray | None = None
    color_gains: np.ndarray | None = None
    depth_error: DepthErrorLaw = DepthErrorLaw()
    observed: ObservedSurface | None = None
    frames: RGBDSequence | None = None
    geometry: Geometry = dataclasses.field(default_factory=Geometry)
    stats: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.model, PNeRFModel):  # a bare field renders with the config's sampling
            self.model = PNeRFModel(self.model, self.config.sampling, self.config.loss)
        self.poses = np.asarray(self.poses, np.float64)
        self.covariances = np.asarray(self.covariances, np.float64)
        self.train_indices = np.asarray(self.train_indices, int)
        self.holdout_indices = np.asarray(self.holdout_indices, int)
        n = len(self.poses)
        self.timestamps = np.arange(n, dtype=float) if self.timestamps is None else np.asarray(self.timestamps)
        self.color_gains = np.ones((n, 3)) if self.color_gains is None else np.asarray(self.color_gains, np.float64)

    # -- what it is ------------------------------------------------------------------------
    @property
    def field(self) -> torch.nn.Module:
        """The trained scene field (the model's)."""
        return self.model.field

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def aabb(self) -> np.ndarray:
        """(2, 3) float32 scene box (m): min and max corner."""
        return self.field.aabb.cpu().numpy()

    @property
    def mesh(self) -> o3d.geometry.TriangleMesh | None:
        """The exported coloured mesh (None before export)."""
        return self.geometry.mesh

    @property
    def mesh_sigma(self) -> np.ndarray | None:
        """(V,) depth sigma (m) of each vertex of :attr:`mesh`."""
        return self.geometry.mesh_sigma

    @property
    def point_cloud(self) -> o3d.geometry.PointCloud | None:
        """The exported coloured point cloud (None before export)."""
        return self.geometry.point_cloud

    @property
    def point_sigma(self) -> np.ndarray | None:
        """(M,) depth sigma (m) of each point of :attr:`point_cloud`."""
        return self.geometry.point_sigma

    def __repr__(self) -> str:
        mesh = f"{len(self.mesh.triangles)} triangles" if self.mesh is not None else "no mesh"
        return f"Reconstruction({len(self.poses)} frames, {len(self.train_indices)} trained, {mesh})"

    def _repr_markdown_(self) -> str:
        """A summary table for Jupyter."""
        cfg, training, law = self.config, self.stats.get("training", {}), self.depth_error
        size = self.aabb[1] - self.aabb[0]
        rows = [
            ("frames", f"{len(self.poses)}: {len(self.train_indices)} trained, {len(self.holdout_indices)} held out"),
            ("method", f"loss `{cfg.loss}`, field `{cfg.field}`, {self.intrinsic.width}x{self.intrinsic.height} images"),
            ("training", f"{training['steps']} steps in {training['seconds']} s" if training else "-"),
            ("scene box (m)", " x ".join(f"{s:.2f}" for s in size)),
            ("mesh", f"{len(self.mesh.triangles)} triangles" if self.mesh is not None else "none"),
            ("point cloud", f"{len(self.point_cloud.points)} points with depth sigma" if self.point_cloud is not None
             else "none"),
            ("depth sigma", f"{law.scale:.3g} x spread, floor {100 * law.floor:.2g}% of depth, "
                            + ("Gaussian" if np.isinf(law.dof) else f"Student-t {law.dof:.3g} dof")),
        ]
        return "\n".join(["| Reconstruction | |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in rows]) + "\n"

    # -- renders -------------------------------------------------------------------------------
    def render(self, pose, intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None, chunk: int = 2048,
               frame: int | None = None) -> dict:
        """Render the field from a camera.

        pose: a camera-to-world (4, 4) matrix, or an ``o3d.camera.PinholeCameraParameters``
        (world-to-camera extrinsic, as Open3D stores it; its intrinsic is used when set and
        `intrinsic` is not given). intrinsic: an ``o3d.camera.PinholeCameraIntrinsic`` (default:
        the training one). A matrix that looks like a world-to-camera extrinsic (the camera far
        outside the scene box, its inverse inside) gives a warning.
        frame: index of one of the reconstruction's frames whose camera exposure the colour
        should have (``color_gains[frame]``); None gives the training frames' average exposure.
        Returns numpy arrays: color (H, W, 3) float32 in [0, 1], depth (H, W) z-depth m (the
        median of the ray's termination distribution; a signed-distance field's surface, its first
        zero crossing, where the ray meets one), depth_std (H, W) m (the spread of the
        model's depth distribution along each ray, made a calibrated 1-sigma error by
        :attr:`depth_error`; where the rendered point lies away
        from every surface the training frames' depth observed, :attr:`observed`, the law's
        unseen term widens it to a share of the depth, beside a depth edge its edge term to
        a share of the step, and where a training view saw past the rendered point its through
        term to the distance it saw), opacity (H, W) in [0, 1].
        """
        pose, carried = self._camera(pose)
        intrinsic = check_intrinsic(intrinsic or carried or self.intrinsic)
        h, w = intrinsic.height, intrinsic.width
        v, u = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device), indexing="ij")
        out = self.render_pixels(pose, intrinsic, u.reshape(-1).float(), v.reshape(-1).float(), chunk)
        unseen, through = None, None
        if self.observed is not None:
            points = self._points(pose, intrinsic_matrix(intrinsic), u.reshape(-1).cpu().numpy(),
                                  v.reshape(-1).cpu().numpy(), out["depth"])
            unseen, through = self.observed.distance(points), self.observed.seen_through(points, pose[:3, 3])
        jump = depth_jump(out["depth"].reshape(h, w)).reshape(-1)
        out["depth_std"] = self.depth_error.sigma(out["depth_std"], out["depth"], unseen, jump,
                                                  through).astype(np.float32)
        if frame is not None:
            if not (isinstance(frame, (int, np.integer)) and 0 <= frame < len(self.poses)):
                raise InputError(f"frame must be a frame index in [0, {len(self.poses)}), got {frame!r}")
            out["color"] = np.clip(out["color"] * self.color_gains[frame].astype(np.float32), 0, 1)
        return {k: a.reshape(h, w, *a.shape[1:]) for k, a in out.items()}

    def render_pixels(self, pose: np.ndarray, intrinsic, u: torch.Tensor, v: torch.Tensor, chunk: int = 2048) -> dict:
        """Numpy color (R, 3) in [0, 1], z-depth depth (of the median ray distance: see
        :attr:`~open3d_pnerf.rendering.RayRender.median`; a signed-distance field's surface where the
        ray meets it) and raw (uncalibrated) depth_std (R,) m (the spread of the ray's weights; a
        signed-distance field's about the depth it reports, so that weights that put the ray
        elsewhere than its surface widen it), opacity (R,) of pixels (u, v) (R,) of a
        camera-to-world pose (4, 4) with `intrinsic`."""
        rays = self._rays(pose, intrinsic, u, v)
        surface = ("surface", "depth") if getattr(self.field, "sdf", None) is not None else ()
        out = self.model.render(rays, chunk, keys=("color", "median", "depth_var", "opacity") + surface)
        depth, spread = out["median"], out["depth_var"]
        if surface:  # the weights' second moment about the surface
            depth = torch.where(out["surface"].isfinite(), out["surface"], out["median"])
            spread = spread + (out["depth"] - depth) ** 2
        return {"color": out["color"].clamp(0, 1).cpu().numpy(), "depth": (depth / rays.norms).cpu().numpy(),
                "depth_std": (spread.sqrt() / rays.norms).cpu().numpy(),
                "opacity": out["opacity"].cpu().numpy()}

    def unseen_distance(self, pose: np.ndarray, K: np.ndarray, u: np.ndarray, v: np.ndarray,
                        depth: np.ndarray) -> np.ndarray | None:
        """(R,) distance (m) from the points of pixels (u, v) (R,) at z-depths `depth` (R,) m of a
        camera-to-world pose (4, 4) with intrinsic matrix K (3, 3) to the surfaces the training
        frames' depth observed (:attr:`observed`); None without them."""
        if self.observed is None:
            return None
        return self.observed.distance(self._points(pose, K, u, v, depth))

    @staticmethod
    def _points(pose: np.ndarray, K: np.ndarray, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(R, 3) world points (m) of pixels (u, v) (R,) at z-depths `depth` (R,) m of a camera-to-world
        pose (4, 4) with intrinsic matrix K (3, 3)."""
        return unproject(K, u, v, depth) @ pose[:3, :3].T + pose[:3, 3]

    def depth_pdf(self, pose, pixels_uv, intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None) -> dict:
        """The model's depth distribution along the rays of R pixels, in z-depth metres.

        pixels_uv: (R, 2) pixel coordinates (u column, v row; centres at integers) of a camera
        at the camera-to-world `pose` (4, 4) with `intrinsic` (default: the training one); the
        samples are those of :meth:`render`. Returns numpy arrays: z (R, S) sample z-depths,
        edges (R, S + 1) their bin edges (z m), mass (R, S) normalised weights w / sum(w) (the
        paper's learned PDF D), pdf (R, S) = mass / bin width (1/m, comparable with a Gaussian
        density over z), opacity (R,) = sum(w).
        """
        uv = np.asarray(pixels_uv, np.float32)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise InputError(f"pixels_uv must be (R, 2) pixel coordinates (u, v), got shape {uv.shape}")
        uv = torch.as_tensor(uv, device=self.device)
        pose, carried = self._camera(pose)
        rays = self._rays(pose, check_intrinsic(intrinsic or carried or self.intrinsic), uv[:, 0], uv[:, 1])
        out = self.model.render(rays, keys=("t", "edges", "weights", "opacity"))
        norms = rays.norms[:, None]
        edges = out["edges"] / norms
        mass = out["weights"] / (out["opacity"][:, None] + 1e-10)
        pdf = mass / (edges[:, 1:] - edges[:, :-1]).clamp(min=1e-9)
        return {"z": (out["t"] / norms).cpu().numpy(), "edges": edges.cpu().numpy(), "mass": mass.cpu().numpy(),
                "pdf": pdf.cpu().numpy(), "opacity": out["opacity"].cpu().numpy()}

    def _rays(self, pose, intrinsic: o3d.camera.PinholeCameraIntrinsic, u: torch.Tensor, v: torch.Tensor) -> Rays:
        """Rays of pixels (u, v) (R,) from a camera-to-world pose (4, 4), clipped to the scene box."""
        return self.model.camera_rays(pose, intrinsic_matrix(intrinsic), u, v)

    def _camera(self, pose) -> tuple[np.ndarray, o3d.camera.PinholeCameraIntrinsic | None]:
        """(camera-to-world pose, intrinsic or None) of what render() accepts (see there)."""
        pose, intrinsic = camera_pose(pose)
        box = self.aabb.astype(np.float64)
        size = box[1] - box[0]
        outside = lambda c: ((c < box[0] - size) | (c > box[1] + size)).any()  # noqa: E731
        if outside(pose[:3, 3]) and not outside(pose_to_extrinsic(pose)[:3, 3]):
            warnings.warn("render(): the pose puts the camera far outside the scene box, while its inverse puts it "
                          "inside: is it an Open3D world-to-camera extrinsic? Poses are camera-to-world; pass "
                          "o3d.camera.PinholeCameraParameters to render it as Open3D means it", stacklevel=3)
        return pose, intrinsic

    # -- occupancy for a planner (open3d_pnerf.occupancy) --------------------------------------
    def occupancy(self, points, size: float = 0.05, sensor: SensorModel = SensorModel(),
                  pixel_stride: int = 8) -> np.ndarray:
        """(N,) probability that a cube of side `size` (m) at each world point (N, 3) m is occupied,
        from what the training views' rendered depth and its calibrated law say of it (every
        `pixel_stride` training pixels); 0.5 where no training view's ray reached. The derivation
        and the `sensor` model: :mod:`open3d_pnerf.occupancy.evidence`."""
        return occupancy.occupancy_at(self, points, size, sensor, pixel_stride)

    def occupancy_grid(self, voxel_size: float = 0.05, bounds=None, sensor: SensorModel = SensorModel(),
                       pixel_stride: int = 8) -> occupancy.OccupancyGrid:
        """The :class:`~open3d_pnerf.occupancy.OccupancyGrid` of :meth:`occupancy` at the centres of
        voxels of `voxel_size` (m) over `bounds` ((2, 3) min and max corner, m; None: the scene box)."""
        return occupancy.occupancy_grid(self, voxel_size, bounds, sensor, pixel_stride)

    # -- the depth-error law (open3d_pnerf.error_law) ----------------------------------------
    @property
    def depth_sigma_scale(self) -> float:
        """The law's scale of the model's depth spread (:attr:`depth_error`)."""
        return self.depth_error.scale

    @property
    def depth_sigma_floor(self) -> float:
        """The law's relative floor: a share of the z-depth (:attr:`depth_error`)."""
        return self.depth_error.floor

    @property
    def depth_sigma_dof(self) -> float:
        """The law's degrees of freedom (inf: a Gaussian; :attr:`depth_error`)."""
        return self.depth_error.dof

    def calibrated_sigma(self, spread: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The 1-sigma-equivalent depth error (m) of a raw depth spread (m) at z-depth `depth` (m)."""
        return self.depth_error.sigma(spread, depth)

    def depth_interval(self, probability: float) -> float:
        """Multiple of the rendered depth_std whose +- interval holds `probability` of the depth
        errors under the calibrated law (a Gaussian gives 1, 2, 3 for 0.683, 0.954, 0.997); e.g.
        a 95% error bar is depth_std * depth_interval(0.95)."""
        return self.depth_error.interval(probability)

    def calibrate_depth_sigma(self, sequence: RGBDSequence, coverage: float = 0.683, frames: int = 8,
                              pixels: int = 1024, method: str = "likelihood") -> float:
        """Fit :attr:`depth_error` on training frames only, and return its scale.

        sequence: the input sequence (all frames, as given to reconstruct()); up to `frames`
        training frames are read at the training resolution and `pixels` random pixels of each
        with sensor depth and opacity > 0.5 are rendered
        (:func:`~open3d_pnerf.evaluation.training_depth_errors`; held-out frames are never
        used). method: "likelihood" (a Student-t by maximum likelihood), "gaussian" or
        "quantile" with `coverage` (see :meth:`DepthErrorLaw.fit`).
        """
        if method not in ("likelihood", "gaussian", "quantile"):
            raise InputError(f"method must be 'likelihood', 'gaussian' or 'quantile', got {method!r}")
        check_sequence(sequence, len(self.poses), "calibrate_depth_sigma(): sequence", needs_depth=True)
        err, spread, z, unseen = training_depth_errors(self, sequence, frames, pixels)
        self.depth_error = DepthErrorLaw.fit(err, spread, z, method, coverage, unseen)
        return self.depth_error.scale

    # -- other formats and the folder on disk --------------------------------------------------
    def write_nerfstudio(self, path, sequence: RGBDSequence, progress: bool = False) -> Path:
        """Write the frames of `sequence` (the one reconstructed) with this reconstruction's poses
        (refined ones when refine_poses was on) as a nerfstudio folder, its training frames as
        nerfstudio's train split and its held-out frames as val/test: nerfstudio's methods then
        train and are scored on exactly these frames and poses (see
        :func:`open3d_pnerf.data.nerfstudio.write_nerfstudio`)."""
        check_sequence(sequence, what="write_nerfstudio(): sequence")
        if len(sequence) != len(self.poses):
            raise InputError(f"write_nerfstudio(): the sequence has {len(sequence)} frames, the reconstruction "
                             f"{len(self.poses)}")
        return write_nerfstudio(sequence, path, self.poses, self.train_indices,
                                self.holdout_indices if len(self.holdout_indices) else None, progress)

    def save(self, directory, frames: bool = True) -> Path:
        """Write the reconstruction's folder (:mod:`open3d_pnerf.storage`): weights, config, poses,
        covariances, trajectories, mesh.ply, point_cloud.ply and, unless frames=False (the folder
        then cannot be extended), the frames it was built from; atomically."""
        return storage.write_folder(self, directory, frames)

    @classmethod
    def load(cls, directory, device: str | None = None) -> "Reconstruction":
        """Load a folder written by :meth:`save`, every file checked (a crafted file cannot run code)."""
        return cls(**storage.read_folder(directory, device))

    # -- a map that grows ----------------------------------------------------------------------
    def extend(self, sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
               covariances=None) -> "Reconstruction":
        """A new reconstruction with the frames of `sequence` added to this one's (left unchanged).

        Without `poses`, the new frames are tracked onto the map (:func:`~open3d_pnerf.tracking.
        track_onto`: the first placed from this map's frames, never from identity; loop closures
        across old and new keyframes; covariances for all), else `poses` (N, 4, 4) camera-to-world
        in this map's world frame (or a trajectory, as :func:`~open3d_pnerf.reconstruct` takes
        them) are used. Every 'config.holdout_every'-th new frame is held out. The depth targets of
        all training frames are built again (the old frames fuse with the new), and training
        continues from this map's weights on all of them (the old frames replayed with the new
        ones; what they still lose is measured in benchmarks/bench_mapping.py). Where the new frames
        reach outside the scene box, the field grows a new block over the larger box (the old region
        encoded as before the growth). Then calibration and
        export, as :func:`~open3d_pnerf.reconstruct` does.

        sequence: RGB-D frames of the same size and intrinsic as this map's (InputError
        otherwise). config: default, this map's config with
        :data:`~open3d_pnerf.extension.EXTENSION_BUDGET` of its training budget at its learning
        rate; a config that changes the field type or its settings raises ConfigError. The new
        reconstruction's config keeps this map's budget and rate, so that each later extension's
        default is the same share. A segment that does not register to the map raises
        TrackingError. Needs :attr:`frames` (saved folders keep them).
        """
        return extend(self, sequence, config, poses, covariances)
