"""The reconstruction pipeline, the one orchestrator of ``reconstruct()``, the command line,
``compare_with_tsdf`` and the benchmarks: poses, depth targets and the scene box, the model and
its training, then the Reconstruction with its calibration and exported geometry; and for the
command line a run folder, with the config, checkpoints, saved reconstruction, comparison with
TSDF fusion and report. Each stage takes its settings from its own sub-config of the
ReconstructionConfig (``config.tracking.track``, ``config.targets.build``, ...).
"""

from __future__ import annotations

import copy
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ._files import atomic_write, atomic_write_all, read_json_object
from .batches import RayBatcher, heldout_rays
from .camera import camera_poses
from .comparison import Comparison, compare
from .config import ReconstructionConfig
from .data.sequence import RGBDSequence, check_sequence, concatenate, depth_in_color_cameras, evenly_spaced
from .distributed import DistributedContext, distributed_session
from .errors import CheckpointError, ConfigError, InputError, TrainingInterrupted
from .export import export_geometry
from .fields import EncodedField
from .model import build_model
from .observed import ObservedSurface
from .reconstruction import Reconstruction
from .report import report_markdown
from .scene import BOX_MARGIN, depth_range, ndc_depth_range, ndc_warp, training_box
from .targets.storage import storage_dir
from .tracking import absolute_trajectory_error
from .training import Trainer, read_checkpoint

RUN_CONFIG = "run_config.json"


# -- frames --------------------------------------------------------------------------------------
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
    (:func:`~open3d_pnerf.data.sequence.depth_in_color_cameras`); otherwise the sequence is returned
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


# -- every stage ---------------------------------------------------------------------------------
def run(sequence: RGBDSequence, config: ReconstructionConfig, poses=None, covariances=None, checkpoint_dir=None,
        resume: bool = False, dist: DistributedContext | None = None, export: bool = True) -> Reconstruction:
    """All stages on one rank of `dist` (a single process by default); see :func:`reconstruct`.
    export=False stops after training (no calibration, mesh or point cloud)."""
    dist = dist or DistributedContext()
    if not dist.is_main:
        config = config.replace(progress=False)
    if dist.enabled:
        config = config.replace(device=dist.device(config.device))
    train_idx, hold_idx = split_frames(len(sequence), config.holdout_every, config.train_views)
    ndc_depth_range(sequence, config.ndc)  # ndc="on" on a sequence that cannot have it fails before any work
    checkpoint = None
    if resume:  # read it now, not after minutes of tracking
        if not checkpoint_dir:
            raise InputError("resume=True needs checkpoint_dir")
        checkpoint = read_checkpoint(Path(checkpoint_dir) / "checkpoint.pt")
    stages = tqdm(total=4, desc="reconstruct", disable=not config.progress, dynamic_ncols=True)
    timings = {}
    t0 = time.perf_counter()

    stages.set_postfix_str("tracking")  # given poses are checked first, before any work
    sequence, poses, covariances, tracking = resolve_poses(sequence, config, poses, covariances, checkpoint_dir,
                                                           resume, write=dist.is_main)
    if dist.enabled:  # every rank trains on rank 0's trajectory, bit for bit
        poses = dist.broadcast_array(poses, "the poses' broadcast", config.device)
        covariances = dist.broadcast_array(covariances, "the covariances' broadcast", config.device)
    timings["tracking_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)

    return fit(sequence, config, poses, covariances, train_idx, hold_idx, tracking, timings, stages, t0,
               checkpoint_dir=checkpoint_dir, checkpoint=checkpoint, dist=dist, export=export)


def fit(sequence: RGBDSequence, config: ReconstructionConfig, poses: np.ndarray, covariances: np.ndarray,
        train_idx: np.ndarray, hold_idx: np.ndarray, tracking: dict, timings: dict, stages, t0: float,
        checkpoint_dir=None, checkpoint: dict | None = None, dist: DistributedContext | None = None,
        export: bool = True, base: Reconstruction | None = None) -> Reconstruction:
    """The stages after the poses: depth targets and the scene box, training, calibration and export,
    on the frames train_idx of `sequence` with `poses` (N, 4, 4) and `covariances` (N, 6, 6).
    base: a reconstruction whose field training continues (its box grown by a new block when the
    frames reach outside it); None trains a new field. stages: the tqdm bar of :func:`run`."""
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
    recon = Reconstruction(model, config, poses, covariances, train_seq.intrinsic, train_idx, hold_idx,
                           timestamps=sequence.timestamps, color_gains=gains, observed=observed,
                           frames=sequence if sequence.has_depth else None, stats=stats)  # what extend() replays
    if dist.is_main and export:  # rank 0 calibrates the depth sigma on training frames and exports
        stages.set_postfix_str("export")
        t2 = time.perf_counter()
        if config.export.calibrate_depth_sigma and sequence.has_depth:
            recon.calibrate_depth_sigma(sequence)
        recon.geometry = export_geometry(recon, sequence, progress=config.progress)
        timings["export_s"] = round(time.perf_counter() - t2, 2)
        timings["total_s"] = round(time.perf_counter() - t0, 2)
        stages.update(1)
    stages.close()
    return recon


def reconstruct(rgbd_sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                covariances=None, checkpoint_dir=None, resume: bool = False) -> Reconstruction:
    """Reconstruct a probabilistic scene model from an RGB-D sequence.

    Stages: poses (tracking, skipped when `poses` are given: (N, 4, 4) camera-to-world, an Open3D
    ``PinholeCameraTrajectory`` or a Trajectory), per-pixel depth targets, training the model,
    exporting mesh and point cloud. An image-only sequence (an LLFF folder: ``has_depth`` False)
    brings its SfM poses and covariances and trains on its sparse points' targets; its depth
    spread is not calibrated (no sensor depth).
    config: a ReconstructionConfig (default: ReconstructionConfig(), the "fast" preset).
    checkpoint_dir: where training checkpoints (and tracked poses) go; resume=True continues from
    its checkpoint.pt with the poses tracked before.

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


# -- extending a map --------------------------------------------------------------------------------
EXTENSION_BUDGET = 0.5
"""An extension's default training budget: this share of the map's own max_steps and time_budget_s,
at the map's learning rate (the field starts trained; the old frames are replayed with the new ones).
Chosen on TUM fr1/xyz (benchmarks/README.md)."""


def extend(base: Reconstruction, sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
           covariances=None) -> Reconstruction:
    """A new reconstruction: `base` with the frames of `sequence` added (see :meth:`Reconstruction.extend`).
    `base` is left as it was."""
    check_sequence(sequence, 2, "extend(): sequence", needs_depth=True)
    if base.frames is None:
        raise InputError("extend(): this reconstruction does not keep the frames it was built from (saved with "
                         "frames=False, or by an earlier version): there is nothing to replay; reconstruct anew")
    config = extension_config(base, config)
    combined = concatenate([base.frames, sequence])  # InputError when the size or intrinsic differs
    n_old = len(base.poses)
    new_train, new_hold = split_frames(len(sequence), config.holdout_every, config.train_views, min_train=1)
    train_idx = np.concatenate([base.train_indices, n_old + new_train])
    hold_idx = np.concatenate([base.holdout_indices, n_old + new_hold])
    stages = tqdm(total=4, desc="extend", disable=not config.progress, dynamic_ncols=True)
    timings, t0 = {}, time.perf_counter()
    stages.set_postfix_str("tracking")
    if poses is not None:
        new_poses, new_covariances = camera_poses(poses, len(sequence), "poses", covariances)
        poses = np.concatenate([base.poses, new_poses])
        covariances = np.concatenate([base.covariances, new_covariances])
        tracking = {"tracked": False}
    else:
        trajectory = config.tracking.track_onto(combined, base.poses, base.covariances, config.progress)
        poses, covariances, tracking = trajectory.poses, trajectory.covariances, {"tracked": True}
        if sequence.gt_poses is not None and sequence.gt_valid.any():
            tracking["ate_rmse_m"] = absolute_trajectory_error(poses[n_old:], sequence.gt_poses)["rmse"]
    timings["tracking_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)
    recon = fit(combined, config, poses, covariances, train_idx, hold_idx, tracking, timings, stages, t0, base=base)
    recon.config = map_config(base, config)
    return recon


def extension_config(base: Reconstruction, config: ReconstructionConfig | None) -> ReconstructionConfig:
    """The config of an extension of `base`: `config` checked to keep base's field (ConfigError), or
    for None base's own with EXTENSION_BUDGET of its training budget."""
    old = base.config
    if config is None:
        budget = None if old.time_budget_s is None else EXTENSION_BUDGET * old.time_budget_s
        config = old.replace(max_steps=max(1, round(EXTENSION_BUDGET * old.max_steps)), time_budget_s=budget)
    config = checked_config(config)
    if (config.field, config.geometry, config.field_config) != (old.field, old.geometry, old.field_config):
        raise ConfigError(f"extend(): the config changes the map's field (field={old.field!r}, geometry="
                          f"{old.geometry!r}, {old.field}: {old.field_config}) to field={config.field!r}, geometry="
                          f"{config.geometry!r}, {config.field}: {config.field_config}; a map keeps its field "
                          "(reconstruct anew to change it)")
    return config


def map_config(base: Reconstruction, config: ReconstructionConfig) -> ReconstructionConfig:
    """The config an extension of `base` trained with `config` keeps as its own: `config` with base's
    training schedule (max_steps, time_budget_s, optimizer.lr), so that the next extension's default
    is again a share of the map's budget and rate, not of the last extension's (which would shrink
    at every extension: 1500, 750, 375 steps)."""
    old = base.config
    return config.replace(max_steps=old.max_steps, time_budget_s=old.time_budget_s,
                          **{"optimizer.lr": old.optimizer.lr})


def continued_field(base: Reconstruction, box: np.ndarray, config: ReconstructionConfig):
    """(scene box, field) to train base's field further on frames whose own scene box is `box` (2, 3):
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


def compare_with_tsdf(sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                      covariances=None, reconstruction: Reconstruction | None = None, reference=None,
                      figure_frames: int = 2, voxel_size: float = 0.01, weight_threshold: float | None = None,
                      progress: bool = True) -> Comparison:
    """Train (or take) a model and fuse the TSDF baseline on the same frames; compare them.

    sequence: the RGB-D sequence the model was (or is to be) trained on. config: for
    training (default: the "fast" preset holding out every 4th frame); ignored when a
    trained `reconstruction` of this sequence is given. poses/covariances: as for
    reconstruct(). reference: a ground-truth ``o3d.geometry.TriangleMesh`` or
    ``PointCloud`` (world frame of the poses) for geometry metrics. voxel_size: TSDF voxel
    (m), truncation 4 voxels. weight_threshold: the TSDF keeps voxels seen by more training
    frames than this; None = the exported mesh's own threshold (export.mesh_min_views - 0.5),
    so both keep the same surfaces; Open3D's default (3) is a second, labelled row. Every
    method is rendered at the held-out poses at the training resolution, against the frames the
    model was built from (``reconstruction.frames``: tracked frames have their depth moved into
    their colour cameras, see :func:`resolve_poses`). An image-only sequence (no depth images, e.g.
    an LLFF folder) has no TSDF to fuse: the model is scored alone (colour metrics). See
    :func:`open3d_pnerf.comparison.compare`.
    """
    if not isinstance(sequence, RGBDSequence):
        raise InputError(f"sequence must be an RGBDSequence, got {type(sequence).__name__}")
    if reconstruction is None:
        config = config or ReconstructionConfig.preset("fast", holdout_every=4, progress=progress)
        reconstruction = reconstruct(sequence, config, poses=poses, covariances=covariances)
    elif not isinstance(reconstruction, Reconstruction):
        raise InputError(f"reconstruction must be a Reconstruction, got {type(reconstruction).__name__}")
    frames = sequence if reconstruction.frames is None else reconstruction.frames
    return compare(reconstruction, frames, reference, figure_frames, voxel_size, weight_threshold, progress)


# -- a run folder (the command line's) -------------------------------------------------------------
def reconstruct_folder(sequence: RGBDSequence, config: ReconstructionConfig, out, poses=None, covariances=None,
                       resume: bool = False, inputs: dict | None = None) -> dict | None:
    """:func:`reconstruct` into the folder `out`: run_config.json (the config and `inputs`, what
    names the data, for resuming and evaluating), checkpoints/ (with the tracked poses), the saved
    reconstruction, its comparison with TSDF fusion on the held-out frames (figures,
    tsdf_mesh.ply) and report.json / report.md. resume=True continues the run in `out` from its
    checkpoint. Returns the report; under torchrun every rank trains, rank 0 writes every file
    and the other ranks return None."""
    check_sequence(sequence, 2, "reconstruct(): rgbd_sequence")
    config, out = checked_config(config), Path(out)
    with distributed_session(config.device, config.runtime.dist_backend, config.runtime.dist_timeout_s) as dist:
        if dist.is_main and not resume:
            write_run_config(out, config, inputs or {})
        recon = run(sequence, config, poses, covariances, out / "checkpoints", resume, dist)
    if not dist.is_main:
        return None
    return write_outputs(recon, sequence if recon.frames is None else recon.frames, out, config.progress)


def extend_folder(base_dir, sequence: RGBDSequence, out, overrides: dict | None = None, poses=None,
                  inputs: dict | None = None) -> dict:
    """:meth:`Reconstruction.extend` of the saved reconstruction in `base_dir` (unchanged) into the
    folder `out`, with run_config.json, the saved reconstruction, its comparison with TSDF fusion
    on the held-out frames of all segments and report.json / report.md. overrides: config fields
    changed from the extension's default config (:func:`extension_config`). Returns the report."""
    base = Reconstruction.load(base_dir, (overrides or {}).get("device"))
    config = extension_config(base, None).replace(**overrides) if overrides else None
    recon = extend(base, sequence, config, poses)
    # the frames of all segments are saved with it: evaluate reads those (no "data" recorded)
    write_run_config(Path(out), recon.config, {"extends": str(Path(base_dir).resolve()), "added": inputs or {}})
    return write_outputs(recon, recon.frames, Path(out), recon.config.progress)


def write_outputs(recon: Reconstruction, sequence: RGBDSequence, out: Path, progress: bool) -> dict:
    """Save `recon` (built from `sequence`) into `out` with its comparison with TSDF fusion on the
    held-out frames (figures, tsdf_mesh.ply) and report.json / report.md; returns the report."""
    recon.save(out)
    scores, figures = {}, []
    if len(recon.holdout_indices):  # TSDF of the same training frames and poses; writes tsdf_mesh.ply, figures
        comparison = compare(recon, sequence, progress=progress)
        comparison.save(out)
        scores, figures = comparison.table, [f"compare_frame_{i:04d}.png" for i in comparison.frames]
    report = {"sequence": repr(sequence), "frames": len(sequence), "ate_rmse_m": recon.stats["tracking"].get("ate_rmse_m"),
              "scores": scores, "figures": figures, **recon.stats}
    atomic_write_all({out / "report.json": lambda p: Path(p).write_text(json.dumps(report, indent=1, default=float)),
                      out / "report.md": lambda p: Path(p).write_text(report_markdown(report, recon))})
    return report


def write_run_config(out: Path, config: ReconstructionConfig, inputs: dict) -> None:
    """run_config.json in the run folder `out`: the config and the inputs (what names the data)."""
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"config": config.to_dict(), **inputs}, indent=1, default=float)
    atomic_write(out / RUN_CONFIG, lambda p: Path(p).write_text(text))


def read_run_config(out: Path, what: str) -> dict:
    """The run_config.json of a run folder (CheckpointError naming `what` if it is not one)."""
    path = Path(out) / RUN_CONFIG
    if not path.is_file():
        raise CheckpointError(f"{what} {out}: no {RUN_CONFIG} there (not a reconstruct output folder)")
    return read_json_object(path, CheckpointError)
