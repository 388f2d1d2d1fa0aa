"""The Reconstruction: a trained probabilistic scene model with its poses and exported geometry,
its renders, its depth-sigma calibration, and its folder on disk.

A saved reconstruction is a folder: ``reconstruction.json`` (format version, config, box,
intrinsic, frame split), ``model.pt`` (the field's weights only), ``poses.npy``,
``covariances.npy``, ``color_gains.npy``, ``mesh.ply`` (with per-vertex ``depth_sigma``),
``point_cloud.ply`` (with per-point ``depth_sigma``), and the trajectory as ``trajectory_tum.txt``, ``trajectory.log`` and Open3D's
``trajectory.json`` (a PinholeCameraTrajectory with the training intrinsic).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from tqdm.auto import tqdm

from ._files import atomic_write_all, read_json_object
from .camera import backproject, camera_pose, check_intrinsic, intrinsic_matrix, pinhole, pose_to_extrinsic, scale_intrinsic
from .config import ReconstructionConfig
from .data.nerfstudio import write_nerfstudio
from .data.sequence import RGBDSequence, check_sequence
from .data.trajectories import write_log_trajectory, write_open3d_trajectory, write_tum_trajectory
from .errors import CheckpointError, ConfigError, InputError
from .evaluation import depth_nll, sigma_multiple
from .export import (
    mesh_from_renders,
    point_cloud_from_renders,
    read_mesh_ply,
    read_point_cloud_ply,
    vertex_sigma,
    write_mesh_ply,
    write_point_cloud_ply,
)
from .fusion import fuse_render_with_sensor
from .model import PNeRFModel, build_model
from .rendering import Rays
from .training import safe_torch_load

FORMAT_VERSION = 1
META_KEYS = ("format_version", "config", "aabb", "intrinsic", "train_indices", "holdout_indices", "timestamps")


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """Indices of min(k, n) items evenly spread over range(n), first and last included."""
    return np.unique(np.round(np.linspace(0, n - 1, min(k, n))).astype(int)) if n and k else np.zeros(0, int)


class Reconstruction:
    """A trained probabilistic scene model with its poses and exported geometry.

    poses (N, 4, 4) camera-to-world and covariances (N, 6, 6) cover every frame of the
    input sequence; train_indices / holdout_indices say which trained. intrinsic is the
    training-resolution ``o3d.camera.PinholeCameraIntrinsic``. depth_sigma_scale and
    depth_sigma_floor turn the model's depth spread into a calibrated 1-sigma-equivalent error,
    and depth_sigma_dof (inf: a Gaussian) says how heavy the tails of its law are (see
    calibrate_depth_sigma, depth_interval). mesh_sigma (V,) and point_sigma (M,): the exported mesh's
    per-vertex and point cloud's per-point depth sigma (m).
    color_gains (N, 3): each frame's camera exposure as per-channel gains on the rendered
    colour (learned for training frames, interpolated in time for the others; ones without
    exposure compensation); see :meth:`render`.
    """

    def __init__(self, model, config: ReconstructionConfig, poses, covariances, intrinsic, aabb,
                 train_indices, holdout_indices, timestamps=None, mesh=None, point_cloud=None,
                 point_sigma=None, stats=None, depth_sigma_scale: float = 1.0, color_gains=None, mesh_sigma=None,
                 depth_sigma_floor: float = 0.0, depth_sigma_dof: float = np.inf):
        if not isinstance(model, PNeRFModel):  # a bare field renders with the config's sampling
            model = PNeRFModel(model, config.sampling, config.loss)
        self.model = model
        self.config = config
        self.poses = np.asarray(poses, np.float64)
        self.covariances = np.asarray(covariances, np.float64)
        self.intrinsic = intrinsic
        self.aabb = np.asarray(aabb, np.float32)
        self.train_indices = np.asarray(train_indices, int)
        self.holdout_indices = np.asarray(holdout_indices, int)
        self.timestamps = np.arange(len(self.poses), dtype=float) if timestamps is None else np.asarray(timestamps)
        self.mesh = mesh
        self.point_cloud = point_cloud
        self.point_sigma = point_sigma
        self.mesh_sigma = mesh_sigma
        self.stats = stats or {}
        self.depth_sigma_scale = float(depth_sigma_scale)
        self.depth_sigma_floor = float(depth_sigma_floor)
        self.depth_sigma_dof = float(depth_sigma_dof)
        self.color_gains = np.ones((len(self.poses), 3)) if color_gains is None else np.asarray(color_gains, np.float64)

    @property
    def field(self) -> torch.nn.Module:
        """The trained scene field (the model's)."""
        return self.model.field

    @property
    def device(self) -> torch.device:
        return self.model.device

    def __repr__(self) -> str:
        mesh = f"{len(self.mesh.triangles)} triangles" if self.mesh is not None else "no mesh"
        return f"Reconstruction({len(self.poses)} frames, {len(self.train_indices)} trained, {mesh})"

    def _repr_markdown_(self) -> str:
        """A summary table for Jupyter."""
        cfg, training = self.config, self.stats.get("training", {})
        size = self.aabb[1] - self.aabb[0]
        rows = [
            ("frames", f"{len(self.poses)}: {len(self.train_indices)} trained, {len(self.holdout_indices)} held out"),
            ("method", f"loss `{cfg.loss}`, field `{cfg.field}`, {self.intrinsic.width}x{self.intrinsic.height} images"),
            ("training", f"{training['steps']} steps in {training['seconds']} s" if training else "-"),
            ("scene box (m)", " x ".join(f"{s:.2f}" for s in size)),
            ("mesh", f"{len(self.mesh.triangles)} triangles" if self.mesh is not None else "none"),
            ("point cloud", f"{len(self.point_cloud.points)} points with depth sigma" if self.point_cloud is not None
             else "none"),
            ("depth sigma", f"{self.depth_sigma_scale:.3g} x spread, floor {100 * self.depth_sigma_floor:.2g}% of depth, "
                            + ("Gaussian" if np.isinf(self.depth_sigma_dof) else f"Student-t {self.depth_sigma_dof:.3g} dof")),
        ]
        return "\n".join(["| Reconstruction | |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in rows]) + "\n"

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
        Returns numpy arrays: color (H, W, 3) float32 in [0, 1], depth (H, W) z-depth m,
        depth_std (H, W) m (the spread of the model's depth distribution along each ray, made
        a calibrated 1-sigma error by :meth:`calibrated_sigma`), opacity (H, W) in [0, 1].
        """
        pose, carried = self._camera(pose)
        intrinsic = check_intrinsic(intrinsic or carried or self.intrinsic)
        h, w = intrinsic.height, intrinsic.width
        v, u = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device), indexing="ij")
        out = self._render_pixels(pose, intrinsic, u.reshape(-1).float(), v.reshape(-1).float(), chunk)
        out["depth_std"] = self.calibrated_sigma(out["depth_std"], out["depth"])
        if frame is not None:
            if not (isinstance(frame, (int, np.integer)) and 0 <= frame < len(self.poses)):
                raise InputError(f"frame must be a frame index in [0, {len(self.poses)}), got {frame!r}")
            out["color"] = np.clip(out["color"] * self.color_gains[frame].astype(np.float32), 0, 1)
        return {k: a.reshape(h, w, *a.shape[1:]) for k, a in out.items()}

    def _render_pixels(self, pose, intrinsic, u: torch.Tensor, v: torch.Tensor, chunk: int = 2048) -> dict:
        """Numpy color (R, 3) in [0, 1], z-depth depth and raw (uncalibrated) depth_std (R,) m,
        opacity (R,) of pixels (u, v) (R,)."""
        rays = self._rays(pose, intrinsic, u, v)
        out = self.model.render(rays, chunk)
        return {"color": out["color"].clamp(0, 1).cpu().numpy(), "depth": (out["depth"] / rays.norms).cpu().numpy(),
                "depth_std": (out["depth_var"].sqrt() / rays.norms).cpu().numpy(),
                "opacity": out["opacity"].cpu().numpy()}

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

    def calibrated_sigma(self, spread: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The 1-sigma-equivalent depth error (m: the half-width of the central 68.3% interval of
        the error law) of a raw depth spread (m) at z-depth `depth` (m):
        sqrt((depth_sigma_scale * spread)^2 + (depth_sigma_floor * depth)^2)."""
        return np.sqrt((self.depth_sigma_scale * spread) ** 2 + (self.depth_sigma_floor * depth) ** 2)

    def depth_interval(self, probability: float) -> float:
        """Multiple of the rendered depth_std whose +- interval holds `probability` of the depth
        errors under the calibrated law (Student-t with depth_sigma_dof degrees of freedom; a
        Gaussian gives 1, 2, 3 for 0.683, 0.954, 0.997). E.g. a 95% error bar is
        depth_std * depth_interval(0.95)."""
        return sigma_multiple(probability, self.depth_sigma_dof)

    def calibrate_depth_sigma(self, sequence: RGBDSequence, coverage: float = 0.683, frames: int = 8,
                              pixels: int = 1024, method: str = "likelihood") -> float:
        """Fit how the model's depth spread becomes an error bar, on training frames only.

        The raw spread of the weights along a ray is set as much by sample spacing and grid
        blur as by the data, so it is not an error bar by itself. method "likelihood" (default)
        fits depth_sigma_scale s and depth_sigma_floor f of sigma = sqrt((s spread)^2 + (f z)^2)
        and the degrees of freedom depth_sigma_dof of a Student-t law of the depth errors, by
        maximum likelihood: a predictive distribution right across its range, not at one
        quantile. Depth errors are heavy-tailed (most pixels within millimetres, a few on the
        wrong side of an edge), which a Gaussian can only meet by widening every sigma; the
        relative floor covers errors the spread does not see (e.g. a surface between the
        samples). method "gaussian": the same fit with a Gaussian law (dof inf). method
        "quantile": a Gaussian, f = 0 and s such that `coverage` of the errors lie within 1
        sigma (exact at that one quantile only). sigma is the 1-sigma equivalent (the half-width
        of the law's central 68.3%); :meth:`depth_interval` gives the other intervals.
        sequence: the input sequence (all frames, as given to reconstruct()); up to `frames`
        training frames are read at the training resolution and `pixels` random pixels of each
        with sensor depth and opacity > 0.5 are rendered (held-out frames are never used).
        Sets depth_sigma_scale, depth_sigma_floor and depth_sigma_dof; returns the scale (1.0,
        floor 0, Gaussian if no pixel).
        """
        if method not in ("likelihood", "gaussian", "quantile"):
            raise InputError(f"method must be 'likelihood', 'gaussian' or 'quantile', got {method!r}")
        check_sequence(sequence, len(self.poses), "calibrate_depth_sigma(): sequence", needs_depth=True)
        train = self.train_indices[evenly_spaced(len(self.train_indices), frames)]
        seq = sequence.select(train)
        seq = seq.scaled_by(self.config.image_scale)
        rng = np.random.default_rng(self.config.seed + 2)
        errors, spreads, depths = [], [], []
        for k, i in enumerate(train):
            depth = seq[k].depth.reshape(-1)
            pix = np.flatnonzero(depth > 0)
            pix = rng.choice(pix, min(pixels, len(pix)), replace=False)
            w = seq.image_size[1]
            uv = torch.as_tensor(np.stack([pix % w, pix // w], 1), dtype=torch.float32, device=self.device)
            out = self._render_pixels(self.poses[i], seq.intrinsic, uv[:, 0], uv[:, 1])
            ok = out["opacity"] > 0.5
            errors.append(np.abs(out["depth"] - depth[pix])[ok])
            spreads.append(np.maximum(out["depth_std"][ok], 1e-6))
            depths.append(depth[pix][ok])
        err, spread, z = (np.concatenate(a) if a else np.zeros(0) for a in (errors, spreads, depths))
        self.depth_sigma_scale, self.depth_sigma_floor, self.depth_sigma_dof = 1.0, 0.0, np.inf
        if err.size:
            self.depth_sigma_scale = float(np.quantile(err / spread, coverage))
            if method != "quantile":
                self.depth_sigma_scale, self.depth_sigma_floor, self.depth_sigma_dof = _likelihood_fit(
                    err, spread, z, self.depth_sigma_scale, fit_dof=method == "likelihood")
        return self.depth_sigma_scale

    def _in_box(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """A z-depth map (H, W) m with 0 where its point lies outside the scene box (stray far
        returns the box left out)."""
        pts, flat = backproject(depth, K, pose)
        outside = flat[((pts < self.aabb[0]) | (pts > self.aabb[1])).any(1)]
        depth = depth.copy()
        depth.flat[outside] = 0
        return depth

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

    def export_geometry(self, progress: bool = True, sequence: RGBDSequence | None = None) -> None:
        """Render training views (at most export.max_views, evenly spaced) at export.scale (at
        export.fused_scale when fused with sensor depth) and rebuild .mesh, .mesh_sigma,
        .point_cloud, .point_sigma.

        sequence: the input sequence (all frames, as given to reconstruct()); when it has depth
        images, each view's rendered depth is fused per pixel with the sensor's depth at the
        training resolution (the render brought to it by nearest pixel) by
        :func:`~open3d_pnerf.fusion.fuse_render_with_sensor`, with the sensor's random sigma
        (:class:`~open3d_pnerf.targets.SensorNoise`); its systematic part (targets.
        depth_sigma_relative) is common to both, the model having learned from this sensor,
        so it is added to the fused variance afterwards: observed surfaces keep the sensor's
        accuracy, the others come from the model, each with its fused sigma.
        """
        cfg = self.config.export
        frames = self.train_indices[evenly_spaced(len(self.train_indices), cfg.max_views)]
        poses = self.poses[frames]
        views = None
        if sequence is not None:
            check_sequence(sequence, len(self.poses), "export_geometry(): sequence")
            if sequence.has_depth:
                views = sequence.select(frames).scaled_by(self.config.image_scale)
        intr = scale_intrinsic(self.intrinsic, cfg.scale) if views is None else \
            scale_intrinsic(views.intrinsic, cfg.fused_scale)
        K = intrinsic_matrix(intr)
        renders = [self.render(p, intr) for p in tqdm(poses, desc="export renders", disable=not progress, leave=False)]
        max_std, stride = cfg.max_point_std, 1  # max_std applies to the model's depth, before any fusion
        if views is not None:  # fused at the training resolution (the sensor's own), points as dense as export.scale's
            K, max_std, stride = views.K, np.inf, max(1, round(1 / cfg.scale))
            noise = self.config.targets.sensor_noise()
            for k, r in enumerate(renders):
                z = self._in_box(views[k].depth, K, poses[k])
                # the model learned from this sensor, so its systematic error is common to both:
                # fuse the independent (random) parts, then add the common part back
                fused = fuse_render_with_sensor(r, z, noise.sigma(z), cfg.min_opacity, cfg.max_point_std)
                common = np.where(z > 0, noise.systematic_var(fused["depth"]), 0)
                fused["depth_std"] = np.sqrt(fused["depth_std"] ** 2 + common).astype(np.float32)
                renders[k] = fused
        self.point_cloud, self.point_sigma = point_cloud_from_renders(
            renders, poses, K, cfg.min_opacity, max_std, voxel_size=cfg.mesh_voxel_size / 2, stride=stride
        )
        self.mesh = mesh_from_renders(renders, poses, K, cfg.mesh_voxel_size, cfg.min_opacity, max_std,
                                      min_views=cfg.mesh_min_views)
        self.mesh_sigma = vertex_sigma(self.mesh, np.asarray(self.point_cloud.points), self.point_sigma)

    def write_nerfstudio(self, path, sequence: RGBDSequence, progress: bool = False) -> Path:
        """Write the frames of `sequence` (the one reconstructed) with this reconstruction's poses
        (refined ones when refine_poses was on) as a nerfstudio folder, with its training frames as
        nerfstudio's train split and its held-out frames as val/test: nerfstudio's methods then
        train and are scored on exactly these frames and poses. See
        :func:`open3d_pnerf.data.nerfstudio.write_nerfstudio`."""
        check_sequence(sequence, what="write_nerfstudio(): sequence")
        if len(sequence) != len(self.poses):
            raise InputError(f"write_nerfstudio(): the sequence has {len(sequence)} frames, the reconstruction "
                             f"{len(self.poses)}")
        return write_nerfstudio(sequence, path, self.poses, self.train_indices,
                                self.holdout_indices if len(self.holdout_indices) else None, progress)

    # -- persistence -------------------------------------------------------------------
    def save(self, directory) -> Path:
        """Write weights, config, poses, covariances, trajectories, mesh.ply, point_cloud.ply.

        Every file goes to a temporary first and all are renamed at the end, so a failure or
        Ctrl-C while saving leaves the folder's previous files intact.
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        intr = self.intrinsic
        meta = {
            "format_version": FORMAT_VERSION,
            "config": self.config.to_dict(),
            "aabb": self.aabb.tolist(),
            "depth_range": None if self.model.depth_range is None else self.model.depth_range.tolist(),
            "intrinsic": {"width": intr.width, "height": intr.height,
                          "K": intrinsic_matrix(intr).tolist()},
            "train_indices": self.train_indices.tolist(),
            "holdout_indices": self.holdout_indices.tolist(),
            "timestamps": self.timestamps.tolist(),
            "stats": self.stats,
            "depth_sigma_scale": self.depth_sigma_scale,
            "depth_sigma_floor": self.depth_sigma_floor,
            "depth_sigma_dof": None if np.isinf(self.depth_sigma_dof) else self.depth_sigma_dof,  # null: Gaussian
        }
        weights = {k: v.cpu() for k, v in self.field.state_dict().items()}
        writes = {
            d / "model.pt": lambda p: torch.save(weights, p),
            d / "reconstruction.json": lambda p: Path(p).write_text(json.dumps(meta, indent=1)),
            d / "poses.npy": lambda p: np.save(p, self.poses),
            d / "covariances.npy": lambda p: np.save(p, self.covariances),
            d / "color_gains.npy": lambda p: np.save(p, self.color_gains),
            d / "trajectory_tum.txt": lambda p: write_tum_trajectory(p, self.poses, self.timestamps),
            d / "trajectory.log": lambda p: write_log_trajectory(p, self.poses),
            d / "trajectory.json": lambda p: write_open3d_trajectory(p, self.poses, self.intrinsic),
        }
        empty = []
        for name, geometry, write in (
            ("mesh.ply", self.mesh, lambda p: write_mesh_ply(p, self.mesh, self.mesh_sigma)),
            ("point_cloud.ply", self.point_cloud, lambda p: write_point_cloud_ply(p, self.point_cloud, self.point_sigma)),
        ):
            if geometry is not None and not geometry.is_empty():
                writes[d / name] = write
            else:
                empty.append(name)
        atomic_write_all(writes)
        for name in empty:
            (d / name).unlink(missing_ok=True)  # never leave a stale file from an earlier run
            warnings.warn(f"{name} not written: the model has no confident surface yet (train longer)")
        return d

    @classmethod
    def load(cls, directory, device: str | None = None) -> "Reconstruction":
        """Load a folder written by :meth:`save` (weights_only: a crafted file cannot run code)."""
        d = Path(directory)
        meta_path = d / "reconstruction.json"
        meta = _read_meta(meta_path)
        try:
            config = ReconstructionConfig.from_dict(meta["config"])
        except (ConfigError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{meta_path}: incompatible config ({exc})") from None
        try:
            aabb = np.asarray(meta["aabb"], np.float32).reshape(2, 3)
            if not (np.isfinite(aabb).all() and (aabb[0] < aabb[1]).all()):
                raise ValueError(f"aabb {meta['aabb']} is not a finite [min, max] box")
            K = np.asarray(meta["intrinsic"]["K"], np.float64).reshape(3, 3)
            intr = check_intrinsic(pinhole(meta["intrinsic"]["width"], meta["intrinsic"]["height"],
                                           K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            timestamps = np.asarray(meta["timestamps"], np.float64).reshape(-1)
            n = len(timestamps)
            indices = [np.asarray(meta[k], int).reshape(-1) for k in ("train_indices", "holdout_indices")]
            if any(((i < 0) | (i >= n)).any() for i in indices):
                raise ValueError(f"frame indices outside [0, {n})")
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{meta_path}: malformed metadata ({exc})") from None
        if device:
            config = config.replace(device=device)
        model = build_model(config, aabb, depth_range=_depth_range(meta.get("depth_range"), meta_path))
        field = model.field
        state = safe_torch_load(d / "model.pt")
        try:
            field.load_state_dict(state)
        except (RuntimeError, KeyError, TypeError) as exc:
            raise CheckpointError(f"{d / 'model.pt'}: weights do not match the config ({exc})") from None
        mesh, mesh_sigma = _read_ply(d / "mesh.ply", read_mesh_ply) or (None, None)
        cloud, sigma = _read_ply(d / "point_cloud.ply", read_point_cloud_ply) or (None, None)
        gains = _load_array(d / "color_gains.npy", (n, 3)) if (d / "color_gains.npy").is_file() else None
        if gains is not None and not (gains > 0).all():
            raise CheckpointError(f"{d / 'color_gains.npy'}: colour gains must be > 0")
        return cls(model, config, _load_array(d / "poses.npy", (n, 4, 4)), _load_array(d / "covariances.npy", (n, 6, 6)),
                   intr, aabb, *indices, timestamps, mesh, cloud, sigma, meta.get("stats"),
                   float(meta.get("depth_sigma_scale", 1.0)), gains, mesh_sigma,
                   float(meta.get("depth_sigma_floor", 0.0)), _dof(meta.get("depth_sigma_dof"), d / "reconstruction.json"))


def _dof(value, meta_path: Path) -> float:
    """depth_sigma_dof as saved: a number > 0, or null (or absent: older saves) for a Gaussian."""
    if value is None:
        return np.inf
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise CheckpointError(f"{meta_path}: depth_sigma_dof must be a number > 0 or null, got {value!r}")
    return float(value)


def _read_meta(path: Path) -> dict:
    """The JSON object of a saved reconstruction, checked for its format version and keys."""
    if not path.is_file():
        raise CheckpointError(f"{path.parent}: not a saved reconstruction (reconstruction.json missing)")
    meta = read_json_object(path, CheckpointError)
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {meta.get('format_version')!r}, this library reads {FORMAT_VERSION}")
    missing = [k for k in META_KEYS if k not in meta]
    if missing or not isinstance(meta["config"], dict):
        raise CheckpointError(f"{path}: incomplete, missing {missing or ['config (an object)']}")
    return meta


def _load_array(path: Path, shape: tuple) -> np.ndarray:
    """A finite .npy array of the given shape (never unpickled)."""
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CheckpointError(f"{path}: missing or corrupt ({exc})") from None
    if arr.shape != shape or not np.isfinite(arr).all():
        raise CheckpointError(f"{path}: expected finite values of shape {shape}, got shape {arr.shape}")
    return arr


def _read_ply(path: Path, read):
    """read(path), or None without the file; a saved PLY that reads as empty is corrupt."""
    if not path.is_file():
        return None
    out = read(path)
    if (out[0] if isinstance(out, tuple) else out).is_empty():
        raise CheckpointError(f"{path}: unreadable or empty PLY (save never writes an empty one)")
    return out


def _depth_range(value, meta_path) -> np.ndarray | None:
    """A saved depth_range: None, or finite [near, far] with 0 < near < far."""
    if value is None:
        return None
    rng = np.asarray(value, np.float64) if isinstance(value, list) else np.full(2, np.nan)
    if rng.shape != (2,) or not (np.isfinite(rng).all() and 0 < rng[0] < rng[1]):
        raise CheckpointError(f"{meta_path}: malformed metadata (depth_range {value!r} is not [near, far], "
                              "0 < near < far)")
    return rng


def _likelihood_fit(err: np.ndarray, spread: np.ndarray, z: np.ndarray, scale0: float,
                    fit_dof: bool = True) -> tuple[float, float, float]:
    """(s, f, dof) minimising the mean negative log-likelihood of errors `err` under the law of
    1-sigma-equivalent sigma = sqrt((s spread)^2 + (f z)^2) (:func:`~open3d_pnerf.evaluation.depth_nll`):
    a Student-t with dof in [1, 1000] degrees of freedom, or a Gaussian (dof inf) unless
    `fit_dof`; all (M,) metres; starts from s = scale0, f = 0.1%, dof 4."""
    from scipy.optimize import minimize

    def unpack(x):
        dof = float(np.clip(np.exp(x[2]), 1.0, 1000.0)) if fit_dof else np.inf
        return np.exp(x[0]), np.exp(x[1]), dof

    def nll(x):
        s, f, dof = unpack(x)
        sigma = np.sqrt((s * spread) ** 2 + (f * z) ** 2) + 1e-9
        return float(np.mean(depth_nll(err, sigma, dof)))

    start = np.log([max(scale0, 1e-6), 1e-3, 4.0][: 3 if fit_dof else 2])
    best = minimize(nll, start, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 3000})
    s, f, dof = unpack(best.x if best.fun <= nll(start) else start)
    return float(s), float(f), dof