"""A map that grows: a reconstruction extended by new frames, tracked onto its map and trained on
from its weights with the old frames replayed (what :meth:`~open3d_pnerf.Reconstruction.extend`
runs), and the budget an extension trains with."""

from __future__ import annotations

import time

import numpy as np
from tqdm.auto import tqdm

from .camera import camera_poses
from .config import ReconstructionConfig
from .data.derived import concatenate
from .data.sequence import RGBDSequence, check_sequence
from .errors import ConfigError, InputError
from .stages import checked_config, finish, fit, split_frames
from .tracking import absolute_trajectory_error

EXTENSION_BUDGET = 0.5
"""An extension's default training budget: this share of the map's own max_steps and time_budget_s,
at the map's learning rate (the field starts trained; the old frames are replayed with the new ones).
Chosen on TUM fr1/xyz (benchmarks/README.md)."""


def extend(base, sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None, covariances=None):
    """A new reconstruction of base's type: `base` (a :class:`~open3d_pnerf.Reconstruction`) with the
    frames of `sequence` added (see :meth:`~open3d_pnerf.Reconstruction.extend`); `base` is left as it
    was."""
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
    recon = type(base)(**fit(combined, config, poses, covariances, train_idx, hold_idx, tracking, timings, stages,
                             base=base))
    finish(recon, combined, timings, stages, t0)
    recon.config = map_config(base, config)
    return recon


def extension_config(base, config: ReconstructionConfig | None) -> ReconstructionConfig:
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


def map_config(base, config: ReconstructionConfig) -> ReconstructionConfig:
    """The config an extension of `base` trained with `config` keeps as its own: `config` with base's
    training schedule (max_steps, time_budget_s, optimizer.lr), so that the next extension's default
    is again a share of the map's budget and rate, not of the last extension's (which would shrink
    at every extension: 1500, 750, 375 steps)."""
    old = base.config
    return config.replace(max_steps=old.max_steps, time_budget_s=old.time_budget_s,
                          **{"optimizer.lr": old.optimizer.lr})
