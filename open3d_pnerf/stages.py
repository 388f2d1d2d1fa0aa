"""The stages of a reconstruction, shared by :func:`~open3d_pnerf.reconstruct`, a growing map
(:meth:`~open3d_pnerf.Reconstruction.extend`) and the streaming mapper: the frames' split, the poses
(given, the sequence's own, or tracked), the depth targets, scene box and training of the model
(:func:`fit`), then calibration and export (:func:`finish`). Each stage takes its settings from its
own sub-config of the ReconstructionConfig (``config.tracking.track``, ``config.targets.build``, ...).
"""

from __future__ import annotations

import copy
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from ._files import atomic_write_all
from .batches import RayBatcher, heldout_rays
from .camera import camera_poses
from .config import ReconstructionConfig
from .data.derived import depth_in_color_cameras, evenly_spaced
from .data.sequence import RGBDSequence
from .distributed import DistributedContext
from .errors import CheckpointError, InputError, TrainingInterrupted
from .export import export_geometry
from .fields import EncodedField
from .model import build_model
from .observed import ObservedSurface
from .scene import BOX_MARGIN, depth_range, ndc_warp, training_box
from .targets.storage import storage_dir
from .tracking import absolute_trajectory_error
from .training import Trainer


def split_frames(n: int, holdout_every: int, train_views: int = 0, min_train: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(train, holdout) frame indices: every holdout_every-th frame (0, k, 2k, ...) held out;
    train_views > 0 keeps that many of the others, evenly spaced (the held-out set is unchanged);
    InputError when fewer than `min_train` frames train."""
    idx = np.arange(n)
    hold = idx % holdout_every == 0 if holdout_every > 0 else np.zeros(n, bool)
    train = idx[~hold]
    if len(train) < min_train:
        raise InputError(f"holdout_every={holdout_every} leaves fewer than {min_train} training frames of {n}")
    if train_views:
        if train_views > len(train):
            raise InputError(f"train_views={train_views} but only {len(train)} frames are not held out")
        train = train[evenly_spaced(len(train), train_views)]
    return train, idx[hold]


# -- poses ---------------------------------------------------------------------------------------
def resolve_poses(sequence: RGBDSequence, config: ReconstructionConfig, poses=None, covariances=None, cache=None,
                  reuse: bool = False, write: bool = True) -> tuple[RGBDSequence, np.ndarray, np.ndarray, dict]:
    """(sequence, poses (N, 4, 4), covariances (N, 6, 6), tracking): the given poses, checked (an
    (N, 4, 4) camera-to-world array, an ``o3d.camera.PinholeCameraTrajectory`` or a Trajectory,
    whose covariances are used unless `covariances` is given; zeros if none is known),
    else the sequence's own (structure from motion, or the capture's), else tracked with the
    config's tracking settings. Tracked frames whose colour cameras were placed
    (Trajectory.color_offsets) come back as those cameras see them: the colour images' poses, and
    the sequence with each depth image moved into its colour camera
    (:func:`~open3d_pnerf.data.derived.depth_in_color_cameras`); otherwise the sequence is returned
    as it is. Tracked poses are kept in the folder `cache` (when `write`) and taken from it when
    `reuse` (a resumed run keeps the poses it trained on). tracking: {"tracked": bool, and when
    tracked on a sequence with ground truth "ate_rmse_m" (of the depth cameras)}."""
    if poses is None and sequence.sfm is not None:
        poses, covariances = sequence.sfm.poses, sequence.sfm.covariances
    if poses is not None:
        return (sequence, *camera_poses(poses, len(sequence), "poses", covariances), {"tracked": False})
    names = ("poses", "covariances", "color_offsets")
    files = {} if cache is None else {name: Path(cache) / f"{name}.npy" for name in names}
    if reuse and files and all(files[name].is_file() for name in names[:2]):
        poses, covariances = camera_poses(_cached_array(files["poses"]), len(sequence), "tracked poses",
                                          _cached_array(files["covariances"]))
        offsets = _cached_array(files["color_offsets"]) if files["color_offsets"].is_file() else None
    else:
        trajectory = config.tracking.track(sequence, config.progress)
        poses, covariances, offsets = trajectory.poses, trajectory.covariances, trajectory.color_offsets
        if files and write:
            arrays = {"poses": poses, "covariances": covariances, "color_offsets": offsets}
            files["color_offsets"].unlink(missing_ok=True)
            atomic_write_all({files[name]: (lambda p, a=array: np.save(p, a))
                              for name, array in arrays.items() if array is not None})
    tracking = {"tracked": True}
    if sequence.gt_poses is not None and sequence.gt_valid.any():
        tracking["ate_rmse_m"] = absolute_trajectory_error(poses, sequence.gt_poses)["rmse"]
    if offsets is not None:
        sequence, poses = depth_in_color_cameras(sequence, offsets), poses @ offsets
    return sequence, poses, covariances, tracking


def _cached_array(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CheckpointError(f"{path}: corrupt tracked poses ({exc}); remove it to track again") from None


# -- the model -----------------------------------------------------------------------------------
def fit(sequence: RGBDSequence, config: ReconstructionConfig, poses: np.ndarray, covariances: np.ndarray,
        train_idx: np.ndarray, hold_idx: np.ndarray, tracking: dict, timings: dict, stages,
        checkpoint_dir=None, checkpoint: dict | None = None, dist: DistributedContext | None = None,
        base=None) -> dict:
    """The stages after the poses, up to a trained model: depth targets and the scene box, training,
    on the frames train_idx of `sequence` with `poses` (N, 4, 4) and `covariances` (N, 6, 6).
    Returns the keyword arguments of a :class:`~open3d_pnerf.Reconstruction` (before calibration and
    export: :func:`finish`). base: a reconstruction whose field training continues (its box grown by
    a new block when the frames reach outside it); None trains a new field. stages: the tqdm bar of
    the caller (4 stages: poses, targets, training, export), timings: its stage durations (s)."""
    dist = dist or DistributedContext()
    stages.set_postfix_str("depth targets")  # built for every loss: they also bound the scene box
    t1 = time.perf_counter()
    train_seq = sequence.select(train_idx).scaled_by(config.image_scale)
    storage = storage_dir(len(train_seq), train_seq.image_size, checkpoint_dir,  # ranks may share checkpoint_dir
                          f"targets-rank{dist.rank}" if dist.enabled else "targets")
    targets = config.targets.build(train_seq, poses[train_idx], covariances[train_idx], storage, config.progress)
    box = training_box(train_seq, targets, poses[train_idx])
    field, warp = None, None
    if base is not None:
        box, field = continued_field(base, box, config)
    else:
        warp = ndc_warp(train_seq, poses[train_idx], config.ndc)
    aabb = dist.broadcast_array(box, "the scene box's broadcast", config.device)
    observed = None
    if train_seq.has_depth:  # what the sensor saw: the model's depth is widened away from it
        observed = ObservedSurface.from_depths(targets.mean, targets.valid, train_seq.K, poses[train_idx],
                                               config.export.mesh_voxel_size, aabb)
    timings["targets_s"] = round(time.perf_counter() - t1, 2)
    stages.update(1)

    stages.set_postfix_str("training")
    model = build_model(config, aabb, poses[train_idx], train_seq.K, covariances[train_idx], depth_range(train_seq),
                        field=field, warp=warp)
    if base is not None and model.exposure is not None:  # the old frames keep the exposure they were given
        with torch.no_grad():
            model.exposure.log_gains[: len(base.train_indices)] = torch.as_tensor(
                np.log(base.color_gains[base.train_indices]), dtype=torch.float32)
    batcher = RayBatcher(train_seq, targets, model.device, config.seed, config.runtime.cache_frames,
                         target_share=config.optimizer.target_ray_share)
    eval_rays = None
    if dist.is_main and len(hold_idx):
        eval_rays = heldout_rays(model, sequence.select(hold_idx).scaled_by(config.image_scale), poses[hold_idx],
                                 config.seed)
    trainer = Trainer(model, batcher, config, eval_rays, checkpoint_dir, dist)
    if checkpoint is not None:
        trainer.load_checkpoint(Path(checkpoint_dir) / "checkpoint.pt", checkpoint)
    try:
        train_stats = trainer.train()
        history = trainer.history
        if train_stats["interrupted"]:  # Ctrl-C: keep the work, then stop like any interrupted call
            raise TrainingInterrupted(trainer.step, trainer.interrupted_checkpoint())
    finally:
        targets_summary = targets.summary()
        if storage is not None:  # the model has learned them; do not leave gigabytes behind
            del batcher, trainer, targets
            shutil.rmtree(storage, ignore_errors=True)
    stages.update(1)
    poses, gains = model.frames_after_training(poses, sequence.timestamps, train_idx, hold_idx)
    stats = {"tracking": tracking, "training": train_stats, "history": history, "targets": targets_summary,
             "timings": timings}
    if base is not None:
        stats["extended"] = [*base.stats.get("extended", []),
                             {"frames_before": len(base.poses), "frames_added": len(poses) - len(base.poses),
                              "box_grown": bool((aabb != base.aabb).any()), "max_steps": config.max_steps,
                              "lr": config.optimizer.lr}]
    return dict(model=model, config=config, poses=poses, covariances=covariances, intrinsic=train_seq.intrinsic,
                train_indices=train_idx, holdout_indices=hold_idx, timestamps=sequence.timestamps, color_gains=gains,
                observed=observed, frames=sequence if sequence.has_depth else None,  # what extend() replays
                stats=stats)


def finish(recon, sequence: RGBDSequence, timings: dict, stages, t0: float, export: bool = True,
           dist: DistributedContext | None = None) -> None:
    """The last stage, in place: rank 0 of `dist` calibrates `recon`'s depth sigma on its training
    frames of `sequence` (config.export.calibrate_depth_sigma) and exports its mesh and point cloud;
    export=False skips both. Closes the caller's progress bar `stages` and records the export's and
    the whole call's durations (since `t0`, s) in `timings`."""
    dist = dist or DistributedContext()
    config = recon.config
    if dist.is_main and export:
        stages.set_postfix_str("export")
        t2 = time.perf_counter()
        if config.export.calibrate_depth_sigma and sequence.has_depth:
            recon.calibrate_depth_sigma(sequence)
        recon.geometry = export_geometry(recon, sequence, progress=config.progress)
        timings["export_s"] = round(time.perf_counter() - t2, 2)
        timings["total_s"] = round(time.perf_counter() - t0, 2)
        stages.update(1)
    stages.close()


def continued_field(base, box: np.ndarray, config: ReconstructionConfig):
    """(scene box, field) to train the field of `base` (a Reconstruction) further on frames whose own scene box is `box` (2, 3):
    base's box and a copy of its field when the box pokes out of it by at most the box's margin
    (scene.BOX_MARGIN), else the union of both with the copy grown by a new block
    (:meth:`ReconstructionConfig.grow_field`: the old region encoded as before the growth)."""
    field = copy.deepcopy(base.field).to(torch.device(config.device))
    old = base.aabb
    if (box[0] >= old[0] - BOX_MARGIN).all() and (box[1] <= old[1] + BOX_MARGIN).all():
        return old.copy(), field
    if not isinstance(field, EncodedField):
        raise InputError(f"extend(): the new frames reach outside the map's box {old.tolist()} and a "
                         f"{config.field!r} field cannot grow (a grid field can: 'hashgrid' or 'grid')")
    union = np.stack([np.minimum(old[0], box[0]), np.maximum(old[1], box[1])]).astype(np.float32)
    return union, config.grow_field(field, union)


def checked_config(config: ReconstructionConfig | None) -> ReconstructionConfig:
    """`config` validated (the defaults for None); InputError for anything else."""
    config = ReconstructionConfig() if config is None else config
    if not isinstance(config, ReconstructionConfig):
        raise InputError(f"config must be a ReconstructionConfig, got {type(config).__name__}")
    config.validate()
    return config
