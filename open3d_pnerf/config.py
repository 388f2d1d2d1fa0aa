"""ReconstructionConfig: every setting of a reconstruction, with presets and validation."""

from __future__ import annotations

import dataclasses
from typing import Any

from .distributed import BACKENDS
from .errors import ConfigError
from .fields import FIELDS
from .losses import LOSSES, LossGains
from .targets import SensorNoise


@dataclasses.dataclass
class ReconstructionConfig:
    """Settings of :func:`open3d_pnerf.reconstruct`. Presets: ``ReconstructionConfig.preset("fast")``."""

    loss: str = "pnerf"
    """"pnerf" (colour + depth-PDF + depth L1), "photometric" (colour only) or "dsnerf"."""
    field: str = "hashgrid"
    """"hashgrid" (Instant-NGP multi-resolution hash grid, 8 levels 16..2048: the sharpest
    renders of dense sequences at equal time on a CPU), "grid" (dense grids 16..192: as fast,
    coarser, 3x the memory; better with a few sparse views and for refine_poses) or "vanilla"
    (the paper's 8x256 MLP, slow, for comparison)."""
    max_steps: int = 2000
    """Optimiser steps; the learning-rate schedule is laid over this many steps."""
    time_budget_s: float | None = None
    """Stop training after this many seconds (None = no limit). With a budget the schedule
    follows max(step / max_steps, elapsed / budget), so runs are not bit-reproducible."""
    image_scale: float = 0.5
    """Training/evaluation image size relative to the sequence's frames, in (0, 1]."""
    holdout_every: int = 0
    """Keep every k-th frame (0, k, 2k, ...) out of training for evaluation; 0 = none."""
    train_views: int = 0
    """Train on only this many of the non-held-out frames, evenly spaced (sparse-view
    experiments); 0 = all of them."""
    seed: int = 0
    """Seed of every random choice (rays, samples, initialisation)."""
    device: str = "cpu"
    """Torch device for the field: "cpu", "cuda", "cuda:1", ... Launched by torchrun with
    several ranks, any CUDA device means each rank's own GPU, cuda:LOCAL_RANK."""
    dist_backend: str = "auto"
    """torch.distributed backend when launched by torchrun with several ranks: "auto" (NCCL
    on CUDA, gloo on CPU), "gloo" or "nccl". Unused in a single process."""
    dist_timeout_s: float = 600.0
    """Seconds any rank waits in a collective (joining, broadcasts, the per-step gradient sum)
    before raising DistributedError: a dead or hung rank gives an error, not a hang. Must
    exceed the longest gap between ranks (rank 0 writing a checkpoint, uneven tracking)."""
    rays_per_batch: int = 512
    """Rays per optimiser step; with several ranks, the whole batch, split between them."""
    n_coarse: int = 16
    """Stratified samples per ray (coarse pass)."""
    n_fine: int = 8
    """Importance samples per ray drawn from the coarse weights (fine pass)."""
    n_guided: int = 16
    """Samples in mean +- 3 sigma of the depth target (extra importance samples without one)."""
    depth_guided_sampling: bool = True
    """Place the n_guided samples around the depth target (False: extra importance samples)."""
    lr: float = 1e-2
    """Initial Adam learning rate."""
    lr_final_factor: float = 0.05
    """The learning rate decays exponentially to lr * lr_final_factor at the end."""
    adam_beta2: float = 0.99
    """Adam's second-moment decay (Instant-NGP's 0.99). PyTorch's 0.999 remembers the large
    early depth-loss gradients for ~1000 steps, which can hold back colour fitting after the
    depth gains have decayed; 0.99 gave the pnerf loss higher held-out PSNR on TUM fr1/xyz in
    exploratory runs (benchmarks/bench_nerf.py also runs photometric with 0.999 to compare)."""
    gains: LossGains = dataclasses.field(default_factory=LossGains)
    """Loss gains Kc, Kd, Kz (and the DS-NeRF gain)."""
    depth_gain_final_factor: float = 0.01
    """The PNeRF depth gains Kd and Kz decay exponentially over training to this fraction
    of `gains` (1.0 = constant): geometry first, colour refined late (0.01 was chosen over 0.1 in
    exploratory runs on TUM fr1/xyz at the `fast` preset: same depth error). Compare with
    `gains={"density": 0.05, "depth": 0.05}, depth_gain_final_factor=1.0` (the old default)."""
    exposure_compensation: bool = True
    """Learn a colour gain per training frame and channel (the auto-exposure and white balance
    of real cameras; open3d_pnerf.rendering.exposure). Held-out frames get gains interpolated in
    time from the training frames around them (Reconstruction.render(..., frame=i));
    renders without a frame show the training frames' average exposure."""
    refine_poses: bool = False
    """Optimise a rigid correction of each training pose jointly with the field, held by a
    Gaussian prior from the pose covariances (open3d_pnerf.pose_refinement): uncertain poses
    move, certain ones stay (zero covariance: fixed). The Reconstruction's poses are the refined
    ones; held-out frames are moved by the rigid shift that best fits the training frames' refinement.
    Use it with field="grid": the hash grid's fine levels partly fit the misaligned views instead,
    poses move less and held-out PSNR does not improve (benchmarks/bench_pose_refinement.py)."""
    pose_lr: float = 1e-3
    """Initial Adam learning rate of the pose corrections (rad or m per step; same decay as lr)."""
    pose_prior_weight: float = 1e-3
    """Weight of the pose prior (mean over frames of 0.5 xi^T Sigma^-1 xi) in the loss."""
    coarse_loss: bool = True
    """Add the coarse-render terms (the paper's coarse + fine losses)."""
    grid_resolutions: tuple = (16, 32, 64, 128, 192)
    """Resolutions of the dense grid levels across the scene box (field="grid")."""
    grid_features: int = 2
    """Features per dense grid level (memory: sum R^3 * features floats, x4 with Adam)."""
    hash_levels: int = 8
    """Hash-grid levels."""
    hash_log2_table_size: int = 19
    """log2 of the hash table size per level (memory: levels * 2^size * 2 floats)."""
    hash_max_resolution: int = 2048
    """Finest hash-grid resolution across the scene box."""
    eval_every: int = 250
    """Steps between held-out evaluations (a fixed subset of held-out pixels)."""
    checkpoint_every: int = 500
    """Steps between checkpoints (when a checkpoint directory is given)."""
    cache_frames: int = 64
    """Training frames kept decoded in memory at once (long sequences rotate through)."""
    point_noise_m: float = 2.0
    """Noise scale of the pose-graph covariances in tracking (see tracking.DEFAULT_POINT_NOISE_M:
    2.0 matches the covariances to the measured pose errors on TUM fr1/xyz)."""
    depth_sigma_relative: float = SensorNoise.relative
    """Systematic depth error of the sensor as a fraction of depth (SensorNoise.relative):
    widens every depth target by relative * z in quadrature, after multi-view fusion
    (calibration and registration errors are shared by all views). 0 = random noise only."""
    calibrate_depth_sigma: bool = True
    """After training, scale the model's depth spread so that 68.3% of training-view depth
    errors fall within 1 sigma (Reconstruction.calibrate_depth_sigma)."""
    export_scale: float = 0.5
    """Resolution of the renders used for mesh and point-cloud export, relative to training."""
    export_max_views: int = 48
    """Render at most this many training views (evenly spaced) for export: bounds its time
    and memory on long sequences."""
    mesh_voxel_size: float = 0.01
    """Voxel size (m) of the TSDF that fuses rendered depth into the exported mesh."""
    max_point_std: float = 0.1
    """Exported points whose rendered depth std exceeds this (m) are dropped."""
    min_opacity: float = 0.9
    """Exported points/mesh depth need at least this accumulated opacity."""
    progress: bool = True
    """Show progress bars."""

    PRESETS = {
        "fast": dict(max_steps=1500, time_budget_s=150.0),
        "quality": dict(max_steps=20000, time_budget_s=None, image_scale=1.0, rays_per_batch=2048,
                        n_coarse=48, n_fine=48, n_guided=24, grid_resolutions=(16, 32, 64, 128, 256, 384)),
        "test": dict(max_steps=60, time_budget_s=None, rays_per_batch=256, n_coarse=16, n_fine=16,
                     n_guided=8, grid_resolutions=(16, 32, 64, 128), hash_log2_table_size=15, hash_levels=8,
                     hash_max_resolution=256, eval_every=30, export_scale=0.5,
                     max_point_std=0.25),  # smoke runs: a few hundred steps leave depth std ~0.1-0.2 m
    }

    @classmethod
    def preset(cls, name: str, **overrides) -> "ReconstructionConfig":
        """A preset ("fast": a couple of minutes on a laptop CPU; "quality"; "test") with overrides."""
        if name not in cls.PRESETS:
            raise ConfigError(f"unknown preset {name!r}; expected one of {sorted(cls.PRESETS)}")
        return cls.from_dict({**cls.PRESETS[name], **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "ReconstructionConfig":
        """Build from a dict (e.g. a saved config.json), rejecting unknown fields."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(f"unknown config field(s) {unknown}; valid fields: {sorted(names)}")
        values = dict(values)
        if isinstance(values.get("gains"), dict):
            gain_names = {f.name for f in dataclasses.fields(LossGains)}
            bad = sorted(set(values["gains"]) - gain_names)
            if bad:
                raise ConfigError(f"unknown loss gain(s) {bad}; valid: {sorted(gain_names)}")
            values["gains"] = LossGains(**values["gains"])
        if "grid_resolutions" in values:  # JSON gives lists
            values["grid_resolutions"] = tuple(values["grid_resolutions"])
        config = cls(**values)
        config.validate()
        return config

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes) -> "ReconstructionConfig":
        """A validated copy with some fields changed."""
        return self.from_dict({**self.to_dict(), **changes})

    def validate(self) -> None:
        """Raise ConfigError naming the first field with a bad value or type."""
        number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
        count = lambda v, low=1: isinstance(v, int) and not isinstance(v, bool) and v >= low  # noqa: E731
        checks = [
            ("loss", lambda v: v in LOSSES, f"one of {LOSSES}"),
            ("field", lambda v: v in FIELDS, f"one of {tuple(FIELDS)}"),
            ("max_steps", count, "an int >= 1"),
            ("time_budget_s", lambda v: v is None or (number(v) and v > 0), "None or > 0 seconds"),
            ("image_scale", lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"),
            ("holdout_every", lambda v: count(v, 0), "an int >= 0"),
            ("train_views", lambda v: v == 0 or count(v, 2), "0 (all) or an int >= 2"),
            ("seed", lambda v: count(v, 0), "an int >= 0"),
            ("rays_per_batch", count, "an int >= 1"),
            ("n_coarse", lambda v: count(v, 2), "an int >= 2"),
            ("n_fine", lambda v: count(v, 0), "an int >= 0"),
            ("n_guided", lambda v: count(v, 0), "an int >= 0"),
            ("lr", lambda v: number(v) and v > 0, "a number > 0"),
            ("lr_final_factor", lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"),
            ("adam_beta2", lambda v: number(v) and 0 <= v < 1, "a number in [0, 1)"),
            ("pose_lr", lambda v: number(v) and v > 0, "a number > 0"),
            ("pose_prior_weight", lambda v: number(v) and v >= 0, "a number >= 0"),
            ("gains", lambda v: isinstance(v, LossGains) and all(number(g) and g >= 0 for g in dataclasses.astuple(v)),
             "LossGains with numbers >= 0"),
            ("depth_gain_final_factor", lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"),
            ("grid_resolutions", lambda v: len(v) >= 1 and all(count(r, 2) for r in v), "a non-empty tuple of ints >= 2"),
            ("grid_features", count, "an int >= 1"),
            ("hash_levels", count, "an int >= 1"),
            ("hash_log2_table_size", lambda v: count(v, 4) and v <= 26, "an int in [4, 26]"),
            ("hash_max_resolution", lambda v: count(v, 16), "an int >= 16"),
            ("eval_every", count, "an int >= 1"),
            ("checkpoint_every", count, "an int >= 1"),
            ("cache_frames", count, "an int >= 1"),
            ("point_noise_m", lambda v: number(v) and v > 0, "a number > 0"),
            ("depth_sigma_relative", lambda v: number(v) and 0 <= v < 1, "a number in [0, 1)"),
            ("export_scale", lambda v: number(v) and 0 < v <= 1, "a number in (0, 1]"),
            ("export_max_views", count, "an int >= 1"),
            ("mesh_voxel_size", lambda v: number(v) and v > 0, "a number > 0 (metres)"),
            ("max_point_std", lambda v: number(v) and v > 0, "a number > 0 (metres)"),
            ("min_opacity", lambda v: number(v) and 0 <= v <= 1, "a number in [0, 1]"),
            *[(name, lambda v: isinstance(v, bool), "True or False")
              for name in ("depth_guided_sampling", "coarse_loss", "calibrate_depth_sigma", "progress",
                           "refine_poses", "exposure_compensation")],
            ("dist_backend", lambda v: v in BACKENDS, f"one of {BACKENDS}"),
            ("dist_timeout_s", lambda v: number(v) and v > 0, "a number > 0 (seconds)"),
            ("device", lambda v: isinstance(v, str) and v.split(":")[0] in ("cpu", "cuda", "mps"),
             '"cpu", "cuda" or "cuda:N"'),
        ]
        for name, ok, expected in checks:
            value = getattr(self, name)
            try:
                good = bool(ok(value))
            except TypeError:
                good = False
            if not good:
                raise ConfigError(f"config field {name}={value!r} is invalid: expected {expected}")
