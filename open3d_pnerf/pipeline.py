"""The reconstruction pipeline, stage by stage: poses, depth targets and scene box, the model,
training, and the finished Reconstruction with its calibration and exported geometry.

``reconstruct()``, the command line, ``compare_with_tsdf`` and the benchmarks all go through
these functions, so a stage's settings are decided in one place (tracking: :func:`track_sequence`).
"""

from __future__ import annotations

import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .batches import RayBatcher
from .camera import backproject, camera_poses, check_covariances, pixel_coordinates
from .config import ReconstructionConfig
from .data.sequence import RGBDSequence, check_sequence, evenly_spaced
from .distributed import DistributedContext, distributed_session
from .errors import InputError, TrainingInterrupted
from .export import export_geometry
from .model import PNeRFModel, build_model
from .pose_refinement import follow_refinement
from .reconstruction import Reconstruction
from .rendering import Rays
from .rendering.exposure import interpolate_gains
from .targets import DepthTargets, depth_targets
from .targets.storage import BYTES_PER_PIXEL
from .tracking import Trajectory, track
from .training import Trainer, read_checkpoint

TARGETS_IN_RAM_MAX_BYTES = 512 * 2**20  # larger targets go to memory-mapped files


# -- frames --------------------------------------------------------------------------------------
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


def training_frames(sequence: RGBDSequence, indices: np.ndarray, config: ReconstructionConfig) -> RGBDSequence:
    """The frames `indices` of a sequence at the training resolution (config.image_scale of it)."""
    return sequence.select(indices).scaled_by(config.image_scale)


# -- poses ---------------------------------------------------------------------------------------
def track_sequence(sequence: RGBDSequence, config: ReconstructionConfig) -> Trajectory:
    """open3d_pnerf.track with the config's tracking settings: the one place that decides them."""
    return track(sequence, loop_closure=config.tracking.loop_closure, progress=config.progress)


def given_poses(poses, covariances, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(poses (n, 4, 4), covariances (n, 6, 6)) of given poses: an (n, 4, 4) camera-to-world array,
    an ``o3d.camera.PinholeCameraTrajectory`` or a Trajectory (whose covariances are used unless
    `covariances` is given); covariances zero if none is known."""
    poses, carried = camera_poses(poses, n, "poses")
    return poses, check_covariances(carried if covariances is None else covariances, n)


def resolve_poses(sequence: RGBDSequence, config: ReconstructionConfig, poses=None, covariances=None):
    """(poses (N, 4, 4), covariances (N, 6, 6)): the given ones (see :func:`given_poses`), else the
    sequence's own (structure from motion, or the capture's), else :func:`track_sequence`'s."""
    if poses is None and sequence.sfm is not None:
        poses, covariances = sequence.sfm.poses, sequence.sfm.covariances
    if poses is None:
        trajectory = track_sequence(sequence, config)
        return trajectory.poses, trajectory.covariances
    return given_poses(poses, covariances, len(sequence))


# -- targets and the scene box ---------------------------------------------------------------------
def scene_box(targets: DepthTargets, poses: np.ndarray, K: np.ndarray, pad: float = 0.1, stride: int = 4) -> np.ndarray:
    """(2, 3) axis-aligned box (m) holding the camera centres and the targets' surface points.

    Uses the 0.5-99.5 percentiles of back-projected target depths (every `stride`-th pixel)
    to ignore stray far points, then pads by `pad` times the size plus 5 cm.
    """
    pts = [poses[:, :3, 3]]
    for i in range(len(targets)):
        valid = np.zeros_like(targets.valid[i])
        valid[::stride, ::stride] = targets.valid[i][::stride, ::stride]
        pts.append(backproject(targets.mean[i], K, poses[i], valid)[0])
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


def build_targets(train_seq: RGBDSequence, config: ReconstructionConfig, poses: np.ndarray, covariances: np.ndarray,
                  storage_dir=None) -> DepthTargets:
    """The depth targets of the training frames (dense fusion, or the SfM points of an image-only
    sequence). Built for every loss: they also bound the scene box."""
    return depth_targets(train_seq, poses=poses, covariances=covariances,
                         sensor=config.targets.sensor_noise(), storage_dir=storage_dir,
                         progress=config.progress)


NEAR_MARGIN = 0.9  # depth_range's near plane: 0.9 x the nearest SfM bound, as DS-NeRF (no NDC) and NeRF's LLFF loader


def depth_range(train_seq: RGBDSequence) -> np.ndarray | None:
    """(2,) z-depth [near, far] for every ray of an image-only sequence with SfM bounds:
    [0.9 x the training frames' smallest near bound, their largest far bound]; None otherwise."""
    if train_seq.has_depth or train_seq.sfm is None or train_seq.sfm.bounds is None:
        return None
    bounds = train_seq.sfm.bounds
    return np.array([NEAR_MARGIN * bounds[:, 0].min(), bounds[:, 1].max()])


def training_box(train_seq: RGBDSequence, targets: DepthTargets, poses: np.ndarray) -> np.ndarray:
    """(2, 3) scene box of the training frames: around their targets' surfaces and cameras; for an
    image-only sequence with SfM bounds, the camera frusta within :func:`depth_range` (so no ray
    leaves the box before its far bound)."""
    rng = depth_range(train_seq)
    if rng is None:
        return scene_box(targets, poses, train_seq.K)
    if not targets.valid.any():
        warnings.warn(f"{train_seq.name}: no SfM point gives a depth target in the training views")
    return frustum_box(train_seq.K, train_seq.image_size, poses, np.tile(rng, (len(poses), 1)))


def targets_storage(train_seq: RGBDSequence, checkpoint_dir, dist: DistributedContext) -> Path | None:
    """Where long sequences keep their targets in memory-mapped files (None: in RAM)."""
    h, w = train_seq.image_size
    if len(train_seq) * h * w * BYTES_PER_PIXEL <= TARGETS_IN_RAM_MAX_BYTES:
        return None
    folder = f"targets-rank{dist.rank}" if dist.enabled else "targets"  # ranks may share checkpoint_dir
    return Path(checkpoint_dir) / folder if checkpoint_dir else Path(tempfile.mkdtemp(prefix="pnerf-targets-"))


# -- training ------------------------------------------------------------------------------------
def heldout_rays(model: PNeRFModel, sequence: RGBDSequence, hold_idx: np.ndarray, poses: np.ndarray,
                 config: ReconstructionConfig, n_rays: int = 2048):
    """A fixed random subset of held-out pixels (Rays, rgb) for periodic evaluation, or None."""
    if len(hold_idx) == 0:
        return None
    seq = training_frames(sequence, hold_idx, config)
    h, w = seq.image_size
    rng = np.random.default_rng(config.seed + 1)
    per = max(1, n_rays // len(hold_idx))
    rays, rgbs = [], []
    for k, i in enumerate(hold_idx):
        pix = rng.choice(h * w, min(per, h * w), replace=False)
        color = seq.color_on_depth_grid(seq[k].color).reshape(-1, 3)[pix] / 255.0
        u, v = (torch.as_tensor(c, dtype=torch.float32) for c in pixel_coordinates(pix, w))
        rays.append(model.camera_rays(poses[i], seq.K, u.to(model.device), v.to(model.device)))
        rgbs.append(torch.as_tensor(color, dtype=torch.float32, device=model.device))
    return Rays.cat(rays), torch.cat(rgbs)


def run(sequence: RGBDSequence, config: ReconstructionConfig, poses=None, covariances=None, checkpoint_dir=None,
        resume: bool = False, dist: DistributedContext | None = None, export: bool = True) -> Reconstruction:
    """All stages on one rank of `dist` (a single process by default); see :func:`reconstruct`.
    export=False stops after training (no calibration, mesh or point cloud)."""
    dist = dist or DistributedContext()
    n = len(sequence)
    if not dist.is_main:
        config = config.replace(progress=False)
    if dist.enabled:
        config = config.replace(device=dist.device(config.device))
    train_idx, hold_idx = split_frames(n, config.holdout_every, config.train_views)
    if poses is not None:  # fail before minutes of work
        poses, covariances = given_poses(poses, covariances, n)
    checkpoint = None
    if resume:  # read it now, not after minutes of tracking
        if not checkpoint_dir:
            raise InputError("resume=True needs checkpoint_dir")
        checkpoint = read_checkpoint(Path(checkpoint_dir) / "checkpoint.pt")
    stages = tqdm(total=4, desc="reconstruct", disable=not config.progress, dynamic_ncols=True)
    timings = {}
    t0 = time.perf_counter()

    stages.set_postfix_str("tracking")
    poses, covariances = resolve_poses(sequence, config, poses, covariances)
    if dist.enabled:  # every rank trains on rank 0's trajectory, bit for bit
        poses = dist.broadcast_array(poses, "the poses' broadcast", config.device)
        covariances = dist.broadcast_array(covariances, "the covariances' broadcast", config.device)
    timings["tracking_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)

    stages.set_postfix_str("depth targets")
    t1 = time.perf_counter()
    train_seq = training_frames(sequence, train_idx, config)
    storage = targets_storage(train_seq, checkpoint_dir, dist)
    targets = build_targets(train_seq, config, poses[train_idx], covariances[train_idx], storage)
    box = training_box(train_seq, targets, poses[train_idx])
    aabb = dist.broadcast_array(box, "the scene box's broadcast", config.device)
    timings["targets_s"] = round(time.perf_counter() - t1, 2)
    stages.update(1)

    stages.set_postfix_str("training")
    model = build_model(config, aabb, poses[train_idx], train_seq.K, covariances[train_idx], depth_range(train_seq))
    batcher = RayBatcher(train_seq, targets, model.device, config.seed, config.runtime.cache_frames,
                         target_share=config.optimizer.target_ray_share)
    eval_rays = heldout_rays(model, sequence, hold_idx, poses, config) if dist.is_main else None
    trainer = Trainer(model, batcher, config, eval_rays, checkpoint_dir, dist)
    if checkpoint is not None:
        trainer.load_checkpoint(Path(checkpoint_dir) / "checkpoint.pt", checkpoint)
    try:
        train_stats = trainer.train()
        history = trainer.history
        if train_stats["interrupted"]:  # Ctrl-C: keep the work, then stop like any interrupted call
            raise TrainingInterrupted(trainer.step, _interrupted_checkpoint(trainer, dist))
    finally:
        targets_summary = targets.summary()
        if storage is not None:  # the model has learned them; do not leave gigabytes behind
            del batcher, trainer, targets
            shutil.rmtree(storage, ignore_errors=True)
    stages.update(1)
    poses = _refined_poses(model, poses, train_idx, hold_idx)
    recon = Reconstruction(model, config, poses, covariances, train_seq.intrinsic, train_idx, hold_idx,
                           timestamps=sequence.timestamps,
                           color_gains=_frame_gains(model, sequence.timestamps, train_idx, hold_idx),
                           stats={"training": train_stats, "history": history, "targets": targets_summary,
                                  "timings": timings})
    if not (dist.is_main and export):  # rank 0 calibrates and exports
        stages.close()
        return recon

    stages.set_postfix_str("export")
    t2 = time.perf_counter()
    finish(recon, sequence)
    timings["export_s"] = round(time.perf_counter() - t2, 2)
    timings["total_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)
    stages.close()
    return recon


def _interrupted_checkpoint(trainer: Trainer, dist: DistributedContext) -> Path | None:
    """The checkpoint of an interrupted training run: the one in checkpoint_dir, or (rank 0,
    without a checkpoint_dir) one written now to a new temporary folder."""
    if trainer.checkpoint_dir is None and dist.is_main:
        trainer.checkpoint_dir = Path(tempfile.mkdtemp(prefix="pnerf-interrupted-"))
        trainer.save_checkpoint()
    return trainer.checkpoint_path


def _refined_poses(model: PNeRFModel, poses: np.ndarray, train_idx, hold_idx) -> np.ndarray:
    """The poses after training: refined training poses, and held-out frames moved by the shift
    that the refinement gave the training frames (unchanged without pose refinement)."""
    if model.pose_corrections is None:
        return poses
    refined = model.pose_corrections.corrected(poses[train_idx])
    poses = poses.copy()
    poses[hold_idx] = follow_refinement(poses[train_idx], refined, poses[hold_idx])
    poses[train_idx] = refined
    return poses


def _frame_gains(model: PNeRFModel, timestamps: np.ndarray, train_idx, hold_idx) -> np.ndarray:
    """(N, 3) exposure gains of every frame: learned for the training frames, interpolated in
    time for the held-out ones (ones without exposure compensation)."""
    gains = np.ones((len(timestamps), 3))
    if model.exposure is not None:
        gains[train_idx] = model.exposure.gains().detach().double().cpu().numpy()
        gains[hold_idx] = interpolate_gains(timestamps[train_idx], gains[train_idx], timestamps[hold_idx])
    return gains


def finish(recon: Reconstruction, sequence: RGBDSequence) -> Reconstruction:
    """Calibrate the depth sigma on the training frames (when the sequence has depth and the
    config asks for it) and export the mesh and point cloud."""
    if recon.config.export.calibrate_depth_sigma and sequence.has_depth:
        recon.calibrate_depth_sigma(sequence)
    recon.geometry = export_geometry(recon, sequence, progress=recon.config.progress)
    return recon


def reconstruct(rgbd_sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                covariances=None, checkpoint_dir=None, resume: bool = False) -> Reconstruction:
    """Reconstruct a probabilistic scene model from an RGB-D sequence.

    Stages: poses (tracking, skipped when `poses` are given: (N, 4, 4) camera-to-world, an Open3D
    ``PinholeCameraTrajectory`` or a Trajectory),
    per-pixel depth targets, training the model, exporting mesh and point cloud. An image-only
    sequence (an LLFF folder: ``has_depth`` False) brings its SfM poses and covariances and
    trains on its sparse points' targets; its depth spread is not calibrated (no sensor depth).
    config: a ReconstructionConfig (default: ReconstructionConfig(), the "fast" preset).
    checkpoint_dir: where training checkpoints go; resume=True continues from its checkpoint.pt.

    Launched by torchrun with several ranks, training is data-parallel (see
    :mod:`open3d_pnerf.distributed`): every rank tracks and builds depth targets itself and
    takes rank 0's poses, covariances and scene box; rank 0 shows progress, writes the
    checkpoints, calibrates and exports. The other ranks return the same trained field
    without calibration or export (no mesh or point cloud). Resuming reads checkpoint_dir
    on every rank: it must be the same checkpoint on every machine.

    Ctrl-C (or interrupting a notebook cell) stops training after the current step, writes the
    checkpoint (to checkpoint_dir, or a new temporary folder) and raises
    :class:`~open3d_pnerf.errors.TrainingInterrupted`, a KeyboardInterrupt naming it. Resume
    with the same sequence and config; to export what the checkpoint has without training
    further, resume with ``config.replace(max_steps=1)``.
    """
    check_sequence(rgbd_sequence, 2, "reconstruct(): rgbd_sequence")
    config = checked_config(config)
    with distributed_session(config.device, config.runtime.dist_backend, config.runtime.dist_timeout_s) as dist:
        return run(rgbd_sequence, config, poses, covariances, checkpoint_dir, resume, dist)


def checked_config(config: ReconstructionConfig | None) -> ReconstructionConfig:
    """`config` validated (the defaults for None); InputError for anything else."""
    config = ReconstructionConfig() if config is None else config
    if not isinstance(config, ReconstructionConfig):
        raise InputError(f"config must be a ReconstructionConfig, got {type(config).__name__}")
    config.validate()
    return config
