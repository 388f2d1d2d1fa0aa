"""`reconstruct()`: tracking -> depth targets -> training -> export, and the Reconstruction.

A saved reconstruction is a folder: ``reconstruction.json`` (format version, config, box,
intrinsic, frame split), ``model.pt`` (weights only), ``poses.npy``, ``covariances.npy``,
``mesh.ply``, ``point_cloud.ply`` (with per-point ``depth_sigma``), and the trajectory as
``trajectory_tum.txt`` and ``trajectory.log``.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from tqdm.auto import tqdm

from ._files import atomic_write_all
from .config import ReconstructionConfig
from .data.loaders import write_log_trajectory, write_tum_trajectory
from .data.sequence import RGBDSequence, check_intrinsic, check_poses, check_sequence, scale_intrinsic
from .distributed import DistributedContext, distributed_session
from .pose_refinement import PoseCorrections, follow_refinement
from .errors import CheckpointError, ConfigError, InputError
from .export import (
    backproject,
    mesh_from_renders,
    point_cloud_from_renders,
    read_point_cloud_ply,
    write_mesh_ply,
    write_point_cloud_ply,
)
from .fields import make_field
from .rendering import Rays, make_rays
from .rendering.exposure import interpolate_gains
from .targets import DepthTargets, SensorNoise, check_covariances, depth_targets
from .training import RayBatcher, Trainer, read_checkpoint, render_field, safe_torch_load, sampling_of

FORMAT_VERSION = 1
TARGET_BYTES_PER_PIXEL = 11  # DepthTargets: mean, sigma (float32), valid, support, filled (1 byte)
TARGETS_IN_RAM_MAX_BYTES = 512 * 2**20
META_KEYS = ("format_version", "config", "aabb", "intrinsic", "train_indices", "holdout_indices", "timestamps")


def scene_box(targets: DepthTargets, poses: np.ndarray, K: np.ndarray, pad: float = 0.1, stride: int = 4) -> np.ndarray:
    """(2, 3) axis-aligned box (m) holding the camera centres and the targets' surface points.

    Uses the 0.5-99.5 percentiles of back-projected target depths (every `stride`-th pixel)
    to ignore stray far points, then pads by `pad` times the size plus 5 cm.
    """
    pts = [poses[:, :3, 3]]
    for i in range(len(targets)):
        valid = np.zeros_like(targets.valid[i])
        valid[::stride, ::stride] = targets.valid[i][::stride, ::stride]
        pts.append(backproject(targets.mean[i], K, poses[i], valid))
    pts = np.concatenate(pts)
    lo, hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
    lo, hi = np.minimum(lo, poses[:, :3, 3].min(0)), np.maximum(hi, poses[:, :3, 3].max(0))
    margin = pad * (hi - lo) + 0.05
    return np.stack([lo - margin, hi + margin]).astype(np.float32)


def frustum_box(K: np.ndarray, image_size: tuple[int, int], poses: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(2, 3) axis-aligned box holding each camera's view frustum between its near and far
    z-depth bounds (N, 2); K (3, 3), image_size (H, W), poses (N, 4, 4) camera-to-world."""
    h, w = image_size
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1]])
    rays = corners @ np.linalg.inv(K).T  # z = 1
    pts = [(rays[None] * z[:, None, None]) @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
           for z in bounds.T]
    pts = np.concatenate(pts).reshape(-1, 3)
    return np.stack([pts.min(0), pts.max(0)]).astype(np.float32)


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """Indices of min(k, n) items evenly spread over range(n), first and last included."""
    return np.unique(np.round(np.linspace(0, n - 1, min(k, n))).astype(int)) if n and k else np.zeros(0, int)


def split_frames(n: int, holdout_every: int, train_views: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(train, holdout) frame indices: every holdout_every-th frame (0, k, 2k, ...) held out;
    train_views > 0 keeps that many of the others, evenly spaced (the held-out set is unchanged)."""
    idx = np.arange(n)
    hold = idx % holdout_every == 0 if holdout_every > 0 else np.zeros(n, bool)
    train = idx[~hold]
    if len(train) < 2:
        raise InputError(f"holdout_every={holdout_every} leaves fewer than 2 training frames of {n}")
    if train_views:
        if train_views > len(train):
            raise InputError(f"train_views={train_views} but only {len(train)} frames are not held out")
        train = train[evenly_spaced(len(train), train_views)]
    return train, idx[hold]


class Reconstruction:
    """A trained probabilistic scene model with its poses and exported geometry.

    poses (N, 4, 4) camera-to-world and covariances (N, 6, 6) cover every frame of the
    input sequence; train_indices / holdout_indices say which trained. intrinsic is the
    training-resolution ``o3d.camera.PinholeCameraIntrinsic``. depth_sigma_scale turns the
    model's depth spread into a calibrated 1-sigma error (see calibrate_depth_sigma).
    color_gains (N, 3): each frame's camera exposure as per-channel gains on the rendered
    colour (learned for training frames, interpolated in time for the others; ones without
    exposure compensation); see :meth:`render`.
    """

    def __init__(self, field, config: ReconstructionConfig, poses, covariances, intrinsic, aabb,
                 train_indices, holdout_indices, timestamps=None, mesh=None, point_cloud=None,
                 point_sigma=None, stats=None, depth_sigma_scale: float = 1.0, color_gains=None):
        self.field = field
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
        self.stats = stats or {}
        self.depth_sigma_scale = float(depth_sigma_scale)
        self.color_gains = np.ones((len(self.poses), 3)) if color_gains is None else np.asarray(color_gains, np.float64)

    @property
    def device(self) -> torch.device:
        return self.field.aabb.device

    def __repr__(self) -> str:
        mesh = f"{len(self.mesh.triangles)} triangles" if self.mesh is not None else "no mesh"
        return f"Reconstruction({len(self.poses)} frames, {len(self.train_indices)} trained, {mesh})"

    def render(self, pose, intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None, chunk: int = 2048,
               frame: int | None = None) -> dict:
        """Render the field from a camera-to-world pose (4, 4).

        intrinsic: an ``o3d.camera.PinholeCameraIntrinsic`` (default: the training one).
        frame: index of one of the reconstruction's frames whose camera exposure the colour
        should have (``color_gains[frame]``); None gives the training frames' average exposure.
        Returns numpy arrays: color (H, W, 3) float32 in [0, 1], depth (H, W) z-depth m,
        depth_std (H, W) m (the spread of the model's depth distribution along each ray,
        times depth_sigma_scale: a calibrated 1-sigma error), opacity (H, W) in [0, 1].
        """
        intrinsic = check_intrinsic(intrinsic or self.intrinsic)
        h, w = intrinsic.height, intrinsic.width
        v, u = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device), indexing="ij")
        out = self._render_pixels(pose, intrinsic, u.reshape(-1).float(), v.reshape(-1).float(), chunk)
        out["depth_std"] *= self.depth_sigma_scale
        if frame is not None:
            if not (isinstance(frame, (int, np.integer)) and 0 <= frame < len(self.poses)):
                raise InputError(f"frame must be a frame index in [0, {len(self.poses)}), got {frame!r}")
            out["color"] = np.clip(out["color"] * self.color_gains[frame].astype(np.float32), 0, 1)
        return {k: a.reshape(h, w, *a.shape[1:]) for k, a in out.items()}

    def _render_pixels(self, pose, intrinsic, u: torch.Tensor, v: torch.Tensor, chunk: int = 2048) -> dict:
        """Numpy color (R, 3) in [0, 1], z-depth depth and raw (uncalibrated) depth_std (R,) m,
        opacity (R,) of pixels (u, v) (R,)."""
        rays = self._rays(pose, intrinsic, u, v)
        out = render_field(self.field, rays, sampling_of(self.config), chunk)
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
        rays = self._rays(pose, check_intrinsic(intrinsic or self.intrinsic), uv[:, 0], uv[:, 1])
        out = render_field(self.field, rays, sampling_of(self.config), keys=("t", "edges", "weights", "opacity"))
        norms = rays.norms[:, None]
        edges = out["edges"] / norms
        mass = out["weights"] / (out["opacity"][:, None] + 1e-10)
        pdf = mass / (edges[:, 1:] - edges[:, :-1]).clamp(min=1e-9)
        return {"z": (out["t"] / norms).cpu().numpy(), "edges": edges.cpu().numpy(), "mass": mass.cpu().numpy(),
                "pdf": pdf.cpu().numpy(), "opacity": out["opacity"].cpu().numpy()}

    def calibrate_depth_sigma(self, sequence: RGBDSequence, coverage: float = 0.683, frames: int = 8,
                              pixels: int = 1024) -> float:
        """Fit depth_sigma_scale so that `coverage` of training-view depth errors lie within 1 sigma.

        The raw spread of the weights along a ray is set as much by sample spacing and grid
        blur as by the data, so it is not an error bar by itself; one scale fitted on the
        training frames makes it one (held-out frames are never used). sequence: the input
        sequence (all frames, as given to reconstruct()); up to `frames` training frames are
        read at the training resolution and `pixels` random pixels of each with sensor depth
        and opacity > 0.5 are rendered. Sets and returns depth_sigma_scale (1.0 if no pixel).
        """
        check_sequence(sequence, len(self.poses), "calibrate_depth_sigma(): sequence", needs_depth=True)
        train = self.train_indices[evenly_spaced(len(self.train_indices), frames)]
        seq = sequence.select(train)
        seq = seq.rescaled(seq.image_scale * self.config.image_scale)
        rng = np.random.default_rng(self.config.seed + 2)
        ratios = []
        for k, i in enumerate(train):
            depth = seq[k].depth.reshape(-1)
            pix = np.flatnonzero(depth > 0)
            pix = rng.choice(pix, min(pixels, len(pix)), replace=False)
            w = seq.image_size[1]
            uv = torch.as_tensor(np.stack([pix % w, pix // w], 1), dtype=torch.float32, device=self.device)
            out = self._render_pixels(self.poses[i], seq.intrinsic, uv[:, 0], uv[:, 1])
            ok = out["opacity"] > 0.5
            ratios.append(np.abs(out["depth"] - depth[pix])[ok] / np.maximum(out["depth_std"][ok], 1e-6))
        ratios = np.concatenate(ratios) if ratios else np.zeros(0)
        self.depth_sigma_scale = float(np.quantile(ratios, coverage)) if ratios.size else 1.0
        return self.depth_sigma_scale

    def _rays(self, pose, intrinsic: o3d.camera.PinholeCameraIntrinsic, u: torch.Tensor, v: torch.Tensor) -> Rays:
        """Rays of pixels (u, v) (R,) from a camera-to-world pose (4, 4), clipped to the scene box."""
        pose = check_poses(np.asarray(pose)[None], 1, "pose")[0]
        K = torch.as_tensor(np.array(intrinsic.intrinsic_matrix), dtype=torch.float32, device=self.device)
        return make_rays(torch.as_tensor(pose, dtype=torch.float32, device=self.device), K, u, v, self.field.aabb)

    def export_geometry(self, progress: bool = True) -> None:
        """Render training views (at most export_max_views, evenly spaced) at export_scale and
        rebuild .mesh, .point_cloud, .point_sigma."""
        cfg = self.config
        intr = scale_intrinsic(self.intrinsic, cfg.export_scale)
        K = np.asarray(intr.intrinsic_matrix)
        poses = self.poses[self.train_indices[evenly_spaced(len(self.train_indices), cfg.export_max_views)]]
        renders = [self.render(p, intr) for p in tqdm(poses, desc="export renders", disable=not progress, leave=False)]
        self.point_cloud, self.point_sigma = point_cloud_from_renders(
            renders, poses, K, cfg.min_opacity, cfg.max_point_std, voxel_size=cfg.mesh_voxel_size / 2
        )
        self.mesh = mesh_from_renders(renders, poses, K, cfg.mesh_voxel_size, cfg.min_opacity, cfg.max_point_std)

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
            "intrinsic": {"width": intr.width, "height": intr.height,
                          "K": np.asarray(intr.intrinsic_matrix).tolist()},
            "train_indices": self.train_indices.tolist(),
            "holdout_indices": self.holdout_indices.tolist(),
            "timestamps": self.timestamps.tolist(),
            "stats": self.stats,
            "depth_sigma_scale": self.depth_sigma_scale,
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
        }
        empty = []
        for name, geometry, write in (
            ("mesh.ply", self.mesh, lambda p: write_mesh_ply(p, self.mesh)),
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
            intr = check_intrinsic(o3d.camera.PinholeCameraIntrinsic(
                int(meta["intrinsic"]["width"]), int(meta["intrinsic"]["height"]), K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            timestamps = np.asarray(meta["timestamps"], np.float64).reshape(-1)
            n = len(timestamps)
            indices = [np.asarray(meta[k], int).reshape(-1) for k in ("train_indices", "holdout_indices")]
            if any(((i < 0) | (i >= n)).any() for i in indices):
                raise ValueError(f"frame indices outside [0, {n})")
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{meta_path}: malformed metadata ({exc})") from None
        if device:
            config = config.replace(device=device)
        field = build_field(config, aabb)
        state = safe_torch_load(d / "model.pt")
        try:
            field.load_state_dict(state)
        except (RuntimeError, KeyError, TypeError) as exc:
            raise CheckpointError(f"{d / 'model.pt'}: weights do not match the config ({exc})") from None
        mesh = _read_ply(d / "mesh.ply", lambda p: o3d.io.read_triangle_mesh(str(p)))
        cloud, sigma = _read_ply(d / "point_cloud.ply", read_point_cloud_ply) or (None, None)
        gains = _load_array(d / "color_gains.npy", (n, 3)) if (d / "color_gains.npy").is_file() else None
        if gains is not None and not (gains > 0).all():
            raise CheckpointError(f"{d / 'color_gains.npy'}: colour gains must be > 0")
        return cls(field, config, _load_array(d / "poses.npy", (n, 4, 4)), _load_array(d / "covariances.npy", (n, 6, 6)),
                   intr, aabb, *indices, timestamps, mesh, cloud, sigma, meta.get("stats"),
                   float(meta.get("depth_sigma_scale", 1.0)), gains)


def _read_meta(path: Path) -> dict:
    """The JSON object of a saved reconstruction, checked for its format version and keys."""
    if not path.is_file():
        raise CheckpointError(f"{path.parent}: not a saved reconstruction (reconstruction.json missing)")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path}: corrupt JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: expected a JSON object, got {type(meta).__name__}")
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


def build_field(config: ReconstructionConfig, aabb: np.ndarray):
    """The field named by config.field, on config.device, seeded by config.seed."""
    torch.manual_seed(config.seed)
    kwargs = {}
    if config.field == "grid":
        kwargs = dict(resolutions=config.grid_resolutions, features=config.grid_features)
    elif config.field == "hashgrid":
        kwargs = dict(levels=config.hash_levels, log2_table_size=config.hash_log2_table_size,
                      max_resolution=config.hash_max_resolution)
    try:
        device = torch.device(config.device)
        return make_field(config.field, torch.as_tensor(aabb), **kwargs).to(device)
    except (RuntimeError, AssertionError) as exc:
        raise ConfigError(f"config field device={config.device!r} is not usable here ({exc})") from None


def reconstruct(rgbd_sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                covariances=None, checkpoint_dir=None, resume: bool = False) -> Reconstruction:
    """Reconstruct a probabilistic scene model from an RGB-D sequence.

    Stages: tracking (skipped when `poses` (N, 4, 4) camera-to-world are given), per-pixel
    depth targets, training the field, exporting mesh and point cloud. An image-only
    sequence (an LLFF folder: ``has_depth`` False) brings its SfM poses and covariances and
    trains on its sparse points' targets; its depth spread is not calibrated (no sensor depth).
    config: a ReconstructionConfig (default: the "fast" preset). checkpoint_dir: where
    training checkpoints go; resume=True continues from its checkpoint.pt.

    Launched by torchrun with several ranks, training is data-parallel (see
    :mod:`open3d_pnerf.distributed`): every rank tracks and builds depth targets itself and
    takes rank 0's poses, covariances and scene box; rank 0 shows progress, writes the
    checkpoints, calibrates and exports. The other ranks return the same trained field
    without calibration or export (no mesh or point cloud). Resuming reads checkpoint_dir
    on every rank: it must be the same checkpoint on every machine.
    """
    check_sequence(rgbd_sequence, 2, "reconstruct(): rgbd_sequence")
    config = config or ReconstructionConfig.preset("fast")
    if not isinstance(config, ReconstructionConfig):
        raise InputError(f"config must be a ReconstructionConfig, got {type(config).__name__}")
    config.validate()
    with distributed_session(config.device, config.dist_backend, config.dist_timeout_s) as dist:
        return _reconstruct(rgbd_sequence, config, poses, covariances, checkpoint_dir, resume, dist)


def _reconstruct(rgbd_sequence: RGBDSequence, config: ReconstructionConfig, poses, covariances, checkpoint_dir,
                 resume: bool, dist: DistributedContext) -> Reconstruction:
    """reconstruct() on one rank of `dist` (a single process by default)."""
    n = len(rgbd_sequence)
    if not dist.is_main:
        config = config.replace(progress=False)
    if dist.enabled:
        config = config.replace(device=dist.device(config.device))
    train_idx, hold_idx = split_frames(n, config.holdout_every, config.train_views)
    if poses is None and not rgbd_sequence.has_depth:
        poses, covariances = rgbd_sequence.poses, rgbd_sequence.covariances
    if poses is not None:
        poses, covariances = check_poses(poses, n, "poses"), check_covariances(covariances, n)
    checkpoint = None
    if resume:  # read it now, not after minutes of tracking
        if not checkpoint_dir:
            raise InputError("resume=True needs checkpoint_dir")
        checkpoint = read_checkpoint(Path(checkpoint_dir) / "checkpoint.pt")
    stages = tqdm(total=4, desc="reconstruct", disable=not config.progress, dynamic_ncols=True)
    timings = {}
    t0 = time.perf_counter()

    stages.set_postfix_str("tracking")
    if poses is None:
        from .tracking import track

        trajectory = track(rgbd_sequence, point_noise_m=config.point_noise_m, progress=config.progress)
        poses, covariances = trajectory.poses, trajectory.covariances
    if dist.enabled:  # every rank trains on rank 0's trajectory, bit for bit
        poses = dist.broadcast_array(poses, "the poses' broadcast", config.device)
        covariances = dist.broadcast_array(covariances, "the covariances' broadcast", config.device)
    timings["tracking_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)

    stages.set_postfix_str("depth targets")
    t1 = time.perf_counter()
    train_seq = rgbd_sequence.select(train_idx)
    train_seq = train_seq.rescaled(train_seq.image_scale * config.image_scale)
    # built for every loss: they also bound the scene box (photometric ignores them in the loss)
    h, w = train_seq.image_size
    storage = None  # long sequences keep their targets in memory-mapped files, not in RAM
    if len(train_idx) * h * w * TARGET_BYTES_PER_PIXEL > TARGETS_IN_RAM_MAX_BYTES:
        folder = f"targets-rank{dist.rank}" if dist.enabled else "targets"  # ranks may share checkpoint_dir
        storage = Path(checkpoint_dir) / folder if checkpoint_dir else Path(tempfile.mkdtemp(prefix="pnerf-targets-"))
    targets = depth_targets(train_seq, poses=poses[train_idx], covariances=covariances[train_idx],
                            sensor=SensorNoise(relative=config.depth_sigma_relative), storage_dir=storage,
                            progress=config.progress)
    K = train_seq.K
    box = scene_box(targets, poses[train_idx], K)
    if not rgbd_sequence.has_depth and not targets.valid.any():  # no SfM point in view: the bounds' frusta
        warnings.warn(f"{rgbd_sequence.name}: no SfM point gives a depth target in the training views; "
                      "the scene box is the camera frusta between the near/far bounds")
        box = frustum_box(train_seq.K, train_seq.image_size, poses[train_idx], train_seq.bounds)
    aabb = dist.broadcast_array(box, "the scene box's broadcast", config.device)
    timings["targets_s"] = round(time.perf_counter() - t1, 2)
    stages.update(1)

    stages.set_postfix_str("training")
    field = build_field(config, aabb)
    device = field.aabb.device
    corrections = PoseCorrections(covariances[train_idx], device) if config.refine_poses else None
    batcher = RayBatcher(train_seq, poses[train_idx], targets, field.aabb, device, config.seed, config.cache_frames,
                         pose_corrections=corrections)
    eval_rays = _holdout_rays(rgbd_sequence, hold_idx, poses, config, field.aabb, device) if dist.is_main else None
    trainer = Trainer(field, batcher, config, eval_rays, checkpoint_dir, dist)
    if checkpoint is not None:
        trainer.load_checkpoint(Path(checkpoint_dir) / "checkpoint.pt", checkpoint)
    exposure = trainer.exposure
    try:
        train_stats = trainer.train()
        history = trainer.history
    finally:
        targets_summary = targets.summary()
        if storage is not None:  # the model has learned them; do not leave gigabytes behind
            del batcher, trainer, targets
            shutil.rmtree(storage, ignore_errors=True)
    stages.update(1)
    if corrections is not None:  # held-out frames follow the shift the refinement gave the training frames
        refined = corrections.corrected(poses[train_idx])
        poses = poses.copy()
        poses[hold_idx] = follow_refinement(poses[train_idx], refined, poses[hold_idx])
        poses[train_idx] = refined
    gains = np.ones((n, 3))
    if exposure is not None:  # held-out frames: the exposure of the training frames around them
        gains[train_idx] = exposure.gains().detach().double().cpu().numpy()
        times = rgbd_sequence.timestamps
        gains[hold_idx] = interpolate_gains(times[train_idx], gains[train_idx], times[hold_idx])
    recon = Reconstruction(field, config, poses, covariances, train_seq.intrinsic, aabb, train_idx, hold_idx,
                           rgbd_sequence.timestamps,
                           stats={"training": train_stats, "history": history, "targets": targets_summary,
                                  "timings": timings}, color_gains=gains)
    if not dist.is_main:  # rank 0 calibrates and exports
        stages.close()
        return recon

    stages.set_postfix_str("export")
    t2 = time.perf_counter()
    if config.calibrate_depth_sigma and rgbd_sequence.has_depth:
        recon.calibrate_depth_sigma(rgbd_sequence)
    recon.export_geometry(progress=config.progress)
    timings["export_s"] = round(time.perf_counter() - t2, 2)
    timings["total_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)
    stages.close()
    return recon


def _holdout_rays(sequence, hold_idx, poses, config, aabb, device, n_rays: int = 2048):
    """A fixed random subset of held-out pixels (Rays, rgb) for periodic evaluation."""
    if len(hold_idx) == 0:
        return None
    seq = sequence.select(hold_idx)
    seq = seq.rescaled(seq.image_scale * config.image_scale)
    h, w = seq.image_size
    rng = np.random.default_rng(config.seed + 1)
    per = max(1, n_rays // len(hold_idx))
    K = torch.as_tensor(seq.K, dtype=torch.float32, device=device)
    rays, rgbs = [], []
    for k, i in enumerate(hold_idx):
        pix = rng.choice(h * w, min(per, h * w), replace=False)
        color = seq.color_on_depth_grid(seq[k].color).reshape(-1, 3)[pix] / 255.0
        u, v = torch.as_tensor(pix % w, dtype=torch.float32), torch.as_tensor(pix // w, dtype=torch.float32)
        pose = torch.as_tensor(poses[i], dtype=torch.float32, device=device)
        rays.append(make_rays(pose, K, u.to(device), v.to(device), aabb))
        rgbs.append(torch.as_tensor(color, dtype=torch.float32, device=device))
    return Rays.cat(rays), torch.cat(rgbs)
