"""ReconstructionConfig: every setting of a reconstruction, one sub-config per concern.

The method and its budget are top-level fields (``loss``, ``field``, ``max_steps``, ...); the
rest lives in sub-configs: one per field type (``hashgrid``, ``grid``, ``vanilla``, each with
its own ``build()``), ``sampling``, ``objective``, ``optimizer``, ``targets``, ``tracking``,
``export`` and ``runtime``. Presets and overrides take dotted names::

    ReconstructionConfig.preset("fast", holdout_every=4, **{"sampling.n_coarse": 32})
    config.replace(**{"hashgrid.levels": 12})

This module is longer than most on purpose: it is the one reference of every setting, each
with its docstring, range check and default.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import torch

from .distributed import BACKENDS
from .errors import ConfigError
from .fields import GridField, HashGridField, VanillaNeRFField
from .fields import native
from .fields.encodings import BACKENDS as HASHGRID_BACKENDS
from .losses import LOSSES, LossWeights
from .rendering.volume import SamplingConfig
from .targets.noise import SensorNoise

Check = tuple[str, Callable[[Any], bool], str]  # field name, predicate, what was expected


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _count(v, low: int = 1) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= low


def _flag(v) -> bool:
    return isinstance(v, bool)


# -- one sub-config per field type --------------------------------------------------------------
@dataclasses.dataclass
class HashGridConfig:
    """Instant-NGP multi-resolution hash grid (field="hashgrid")."""

    levels: int = 8
    """Hash-grid levels, resolutions spaced geometrically from 16 to max_resolution."""
    features: int = 2
    """Features per level."""
    log2_table_size: int = 19
    """log2 of the hash table size per level (memory: levels * 2^size * features floats)."""
    max_resolution: int = 2048
    """Finest hash-grid resolution across the scene box."""
    backend: str = "auto"
    """"auto": the fused CPU kernel (open3d_pnerf.fields.native) where it can be built, else the
    pure-PyTorch path; "kernel" insists on the kernel; "torch": the pure-PyTorch path (also on GPUs)."""

    def checks(self) -> list[Check]:
        return [("levels", _count, "an int >= 1"), ("features", _count, "an int >= 1"),
                ("log2_table_size", lambda v: _count(v, 4) and v <= 26, "an int in [4, 26]"),
                ("max_resolution", lambda v: _count(v, 16), "an int >= 16"),
                ("backend", lambda v: v in HASHGRID_BACKENDS, f"one of {HASHGRID_BACKENDS}")]

    def build(self, aabb, bf16: bool = False) -> HashGridField:
        return HashGridField(aabb, self.levels, self.features, self.log2_table_size, self.max_resolution,
                             self.backend, bf16=bf16)


@dataclasses.dataclass
class GridConfig:
    """Multi-resolution dense grids (field="grid")."""

    resolutions: tuple = (16, 32, 64, 128, 192)
    """Resolutions of the dense grid levels across the scene box."""
    features: int = 2
    """Features per level (memory: sum R^3 * features floats, x4 with Adam)."""

    def checks(self) -> list[Check]:
        return [("resolutions", lambda v: isinstance(v, tuple) and len(v) >= 1 and all(_count(r, 2) for r in v),
                 "a non-empty tuple of ints >= 2"), ("features", _count, "an int >= 1")]

    def build(self, aabb, bf16: bool = False) -> GridField:
        return GridField(aabb, resolutions=self.resolutions, features=self.features, bf16=bf16)


@dataclasses.dataclass
class VanillaConfig:
    """The paper's NeRF MLP (field="vanilla")."""

    width: int = 256
    """Hidden units per layer."""
    depth: int = 8
    """Hidden layers (a skip connection at layer 4)."""

    def checks(self) -> list[Check]:
        return [("width", _count, "an int >= 1"), ("depth", lambda v: _count(v, 5), "an int >= 5")]

    def build(self, aabb, bf16: bool = False) -> VanillaNeRFField:
        return VanillaNeRFField(aabb, width=self.width, depth=self.depth, bf16=bf16)


FIELD_CONFIGS = {"hashgrid": HashGridConfig, "grid": GridConfig, "vanilla": VanillaConfig}


# -- the other concerns -------------------------------------------------------------------------
def _sampling_checks(s: SamplingConfig) -> list[Check]:
    return [("n_coarse", lambda v: _count(v, 2), "an int >= 2"), ("n_fine", lambda v: _count(v, 0), "an int >= 0"),
            ("n_guided", lambda v: _count(v, 0), "an int >= 0"), ("depth_guided", _flag, "True or False")]


@dataclasses.dataclass
class ObjectiveConfig:
    """What training minimises besides the choice of loss."""

    weights: LossWeights = dataclasses.field(default_factory=LossWeights)
    """Loss weights Kc, Kd, Kz (and the DS-NeRF weight)."""
    depth_weight_final_factor: float = 0.01
    """The depth terms' weights (Kd, Kz, and the DS-NeRF weight, so compared losses share one
    schedule) decay exponentially over training to this fraction (1.0 = constant): geometry
    first, colour refined late (0.01 was chosen over 0.1 in exploratory runs on TUM fr1/xyz at
    the `fast` preset: same depth error)."""
    coarse_terms: bool = True
    """Add the coarse-render terms (the paper's coarse + fine losses)."""
    pose_prior_weight: float = 1e-3
    """Weight of the pose prior (mean over frames of 0.5 xi^T Sigma^-1 xi), with refine_poses."""

    def checks(self) -> list[Check]:
        return [("weights", lambda v: isinstance(v, LossWeights)
                 and all(_number(g) and g >= 0 for g in dataclasses.astuple(v)), "LossWeights with numbers >= 0"),
                ("depth_weight_final_factor", lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
                ("coarse_terms", _flag, "True or False"),
                ("pose_prior_weight", lambda v: _number(v) and v >= 0, "a number >= 0")]


@dataclasses.dataclass
class OptimizerConfig:
    """Adam and its schedule."""

    rays_per_batch: int = 512
    """Rays per optimiser step; with several ranks, the whole batch, split between them."""
    lr: float = 1e-2
    """Initial Adam learning rate."""
    lr_final_factor: float = 0.05
    """The learning rate decays exponentially to lr * lr_final_factor at the end."""
    adam_beta2: float = 0.99
    """Adam's second-moment decay (Instant-NGP's 0.99). PyTorch's 0.999 remembers the large
    early depth-loss gradients for ~1000 steps, which can hold back colour fitting after the
    depth weights have decayed; 0.99 gave the pnerf loss higher held-out PSNR on TUM fr1/xyz in
    exploratory runs (benchmarks/bench_nerf.py also runs photometric with 0.999 to compare)."""
    pose_lr: float = 1e-3
    """Initial learning rate of the pose corrections (rad or m per step; same decay as lr)."""
    target_ray_share: float = 0.5
    """Share of each batch's rays drawn among pixels with a depth target when targets are
    sparser than that (SfM points: ~1% of the pixels); 0 = every ray uniform over the pixels.
    DS-NeRF's setting (half its rays are depth rays); dense RGB-D targets already exceed it."""

    def checks(self) -> list[Check]:
        return [("rays_per_batch", _count, "an int >= 1"), ("lr", lambda v: _number(v) and v > 0, "a number > 0"),
                ("lr_final_factor", lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
                ("adam_beta2", lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
                ("pose_lr", lambda v: _number(v) and v > 0, "a number > 0"),
                ("target_ray_share", lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)")]


@dataclasses.dataclass
class TargetsConfig:
    """How depth targets are built."""

    depth_sigma_relative: float = SensorNoise.relative
    """Systematic depth error of the sensor as a fraction of depth (SensorNoise.relative):
    widens every depth target by relative * z in quadrature, after multi-view fusion
    (calibration and registration errors are shared by all views). 0 = random noise only."""

    def sensor_noise(self) -> SensorNoise:
        """The sensor noise model with this systematic term (targets and export use it)."""
        return SensorNoise(relative=self.depth_sigma_relative)

    def checks(self) -> list[Check]:
        return [("depth_sigma_relative", lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)")]


@dataclasses.dataclass
class TrackingConfig:
    """How poses are estimated when none are given (see open3d_pnerf.track)."""

    loop_closure: bool = True
    """Register keyframes that see the same place and optimise the pose graph."""

    def checks(self) -> list[Check]:
        return [("loop_closure", _flag, "True or False")]


@dataclasses.dataclass
class ExportConfig:
    """Depth-sigma calibration and the mesh and point cloud made after training."""

    calibrate_depth_sigma: bool = True
    """After training, fit how the model's depth spread becomes an error bar (a Student-t law
    by maximum likelihood on training views: Reconstruction.calibrate_depth_sigma)."""
    scale: float = 0.5
    """Resolution of the renders used for mesh and point-cloud export, relative to training,
    when there is no sensor depth to fuse with (image-only sequences, the model-only export)."""
    fused_scale: float = 0.25
    """Resolution of the renders fused with sensor depth, relative to training: the fused
    export works at the training resolution (the sensor keeps its own pixels, the render fills
    its holes). Chosen on the synthetic room with all views: the same mesh and held-out depth
    as 0.5 in half the export time (benchmarks/results/tuning_fused_scale_*.md)."""
    max_views: int = 48
    """Render at most this many training views (evenly spaced): bounds export time and memory."""
    mesh_voxel_size: float = 0.01
    """Voxel size (m) of the TSDF that fuses rendered depth into the exported mesh."""
    mesh_min_views: int = 1
    """Keep mesh surfaces seen in at least this many export views: 1 keeps all (the most
    complete mesh); 2 drops surfaces seen once, where the sensor's noise is not averaged (more
    accurate, with holes where only one view looked)."""
    max_point_std: float = 0.1
    """Exported points whose rendered depth std exceeds this (m) are dropped."""
    min_opacity: float = 0.9
    """Exported points/mesh depth need at least this accumulated opacity."""

    def checks(self) -> list[Check]:
        return [("calibrate_depth_sigma", _flag, "True or False"),
                ("scale", lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
                ("fused_scale", lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
                ("max_views", _count, "an int >= 1"),
                ("mesh_voxel_size", lambda v: _number(v) and v > 0, "a number > 0 (metres)"),
                ("mesh_min_views", _count, "an int >= 1"),
                ("max_point_std", lambda v: _number(v) and v > 0, "a number > 0 (metres)"),
                ("min_opacity", lambda v: _number(v) and 0 <= v <= 1, "a number in [0, 1]")]


@dataclasses.dataclass
class RuntimeConfig:
    """Evaluation, checkpoints, memory and data-parallel settings."""

    eval_every: int = 250
    """Steps between held-out evaluations (a fixed subset of held-out pixels)."""
    checkpoint_every: int = 500
    """Steps between checkpoints (when a checkpoint directory is given)."""
    cache_frames: int = 64
    """Training frames kept decoded in memory at once (long sequences rotate through)."""
    dist_backend: str = "auto"
    """torch.distributed backend when launched by torchrun with several ranks: "auto" (NCCL
    on CUDA, gloo on CPU), "gloo" or "nccl". Unused in a single process."""
    dist_timeout_s: float = 600.0
    """Seconds any rank waits in a collective before raising DistributedError: a dead or hung
    rank gives an error, not a hang. Must exceed the longest gap between ranks."""
    bf16_mlp: bool = True
    """Run the fields' MLP matrix products in bfloat16 (autocast; parameters, encodings, colours
    and densities stay float32): about twice as fast MLPs on CPUs with bf16 instructions, and no
    loss of held-out quality at equal steps (benchmarks/bench_speed.py). False: all float32."""

    def checks(self) -> list[Check]:
        return [("eval_every", _count, "an int >= 1"), ("checkpoint_every", _count, "an int >= 1"),
                ("cache_frames", _count, "an int >= 1"), ("dist_backend", lambda v: v in BACKENDS, f"one of {BACKENDS}"),
                ("dist_timeout_s", lambda v: _number(v) and v > 0, "a number > 0 (seconds)"),
                ("bf16_mlp", _flag, "True or False")]


SUB_CONFIGS = {"hashgrid": HashGridConfig, "grid": GridConfig, "vanilla": VanillaConfig, "sampling": SamplingConfig,
               "objective": ObjectiveConfig, "optimizer": OptimizerConfig, "targets": TargetsConfig,
               "tracking": TrackingConfig, "export": ExportConfig, "runtime": RuntimeConfig}
NESTED = {("objective", "weights"): LossWeights}  # dataclasses inside sub-configs
TUPLES = {("grid", "resolutions")}  # JSON gives lists

@dataclasses.dataclass
class ReconstructionConfig:
    """Settings of :func:`open3d_pnerf.reconstruct`. The defaults are the "fast" preset, which
    ``reconstruct(sequence)`` uses; others: ``ReconstructionConfig.preset("quality")``."""

    loss: str = "pnerf"
    """"pnerf" (colour + depth-PDF + depth L1), "photometric" (colour only) or "dsnerf"."""
    field: str = "hashgrid"
    """"hashgrid" (Instant-NGP hash grid: the sharpest renders of dense sequences at equal time on
    a CPU), "grid" (dense grids 16..192: as fast, coarser, 3x the memory; better with a few sparse
    views and for refine_poses) or "vanilla" (the paper's 8x256 MLP, slow, for comparison); its
    settings are the sub-config of the same name."""
    max_steps: int = 1500
    """Optimiser steps; the learning-rate schedule is laid over this many steps."""
    time_budget_s: float | None = 150.0
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
    """Torch device for the model: "cpu", "cuda", "cuda:1", ... Launched by torchrun with
    several ranks, any CUDA device means each rank's own GPU, cuda:LOCAL_RANK."""
    refine_poses: bool = False
    """Optimise a rigid correction of each training pose jointly with the field, held by a
    Gaussian prior from the pose covariances (open3d_pnerf.pose_refinement): uncertain poses
    move, certain ones stay (zero covariance: fixed). The Reconstruction's poses are the refined
    ones; held-out frames are moved by the rigid shift that best fits the training frames'
    refinement. Use it with field="grid" (benchmarks/bench_pose_refinement.py)."""
    exposure_compensation: bool = True
    """Learn a colour gain per training frame and channel (the auto-exposure and white balance
    of real cameras; open3d_pnerf.rendering.exposure). Held-out frames get gains interpolated in
    time (Reconstruction.render(..., frame=i)); renders without a frame show the average exposure."""
    progress: bool = True
    """Show progress bars."""
    hashgrid: HashGridConfig = dataclasses.field(default_factory=HashGridConfig)
    grid: GridConfig = dataclasses.field(default_factory=GridConfig)
    vanilla: VanillaConfig = dataclasses.field(default_factory=VanillaConfig)
    sampling: SamplingConfig = dataclasses.field(default_factory=SamplingConfig)
    objective: ObjectiveConfig = dataclasses.field(default_factory=ObjectiveConfig)
    optimizer: OptimizerConfig = dataclasses.field(default_factory=OptimizerConfig)
    targets: TargetsConfig = dataclasses.field(default_factory=TargetsConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    export: ExportConfig = dataclasses.field(default_factory=ExportConfig)
    runtime: RuntimeConfig = dataclasses.field(default_factory=RuntimeConfig)

    PRESETS = {
        "fast": {},  # the defaults: a couple of minutes on a laptop CPU
        "quality": {"max_steps": 20000, "time_budget_s": None, "image_scale": 1.0, "optimizer.rays_per_batch": 2048,
                    "sampling.n_coarse": 48, "sampling.n_fine": 48, "sampling.n_guided": 24,
                    "grid.resolutions": (16, 32, 64, 128, 256, 384)},
        "test": {"max_steps": 60, "time_budget_s": None, "optimizer.rays_per_batch": 256, "sampling.n_coarse": 16,
                 "sampling.n_fine": 16, "sampling.n_guided": 8, "grid.resolutions": (16, 32, 64, 128),
                 "hashgrid.log2_table_size": 15, "hashgrid.max_resolution": 256, "runtime.eval_every": 30,
                 # smoke runs: a few hundred steps leave depth std ~0.1-0.2 m
                 "export.max_point_std": 0.25},
    }

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def preset(cls, name: str, **overrides) -> "ReconstructionConfig":
        """A preset ("fast": the defaults, a couple of minutes on a laptop CPU; "quality";
        "test": tiny smoke runs) with overrides (dotted names for sub-config fields)."""
        if name not in cls.PRESETS:
            raise ConfigError(f"unknown preset {name!r}; expected one of {sorted(cls.PRESETS)}")
        return cls.from_dict({**cls.PRESETS[name], **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "ReconstructionConfig":
        """Build from a dict, applied in order over the defaults: nested sub-config dicts (as
        to_dict() and saved run_config.json files have them), dotted names
        ("sampling.n_coarse") and top-level fields. Unknown names raise ConfigError."""
        if not isinstance(values, dict):
            raise ConfigError(f"a config must be a dict of settings, got {type(values).__name__}")
        tree = dataclasses.asdict(cls())
        for key, value in values.items():
            path = key.split(".")
            if len(path) == 1 and key in SUB_CONFIGS and isinstance(value, dict):
                for sub_key, sub_value in value.items():
                    _set(tree, [key, sub_key], sub_value)
            else:
                _set(tree, path, value)
        config = cls(**{k: (_build(k, v) if k in SUB_CONFIGS else v) for k, v in tree.items()})
        config.validate()
        return config

    def to_dict(self) -> dict[str, Any]:
        """Nested plain dict (JSON-ready apart from tuples) that from_dict() turns back into this config."""
        return dataclasses.asdict(self)

    def replace(self, **changes) -> "ReconstructionConfig":
        """A validated copy with some fields changed (dotted names for sub-config fields)."""
        return self.from_dict({**self.to_dict(), **changes})

    # -- derived -----------------------------------------------------------------------------
    @property
    def field_config(self):
        """The sub-config of the chosen field type (HashGridConfig, GridConfig or VanillaConfig)."""
        return getattr(self, self.field)

    def build_field(self, aabb):
        """The chosen field over the scene box aabb (2, 3) metres, on `device`, initialised from `seed`."""
        torch.manual_seed(self.seed)
        try:
            field = self.field_config.build(torch.as_tensor(aabb), bf16=self.runtime.bf16_mlp)
            return field.to(torch.device(self.device))
        except (RuntimeError, AssertionError) as exc:
            raise ConfigError(f"config field device={self.device!r} is not usable here ({exc})") from None

    # -- validation --------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise ConfigError naming the first field with a bad value or type."""
        checks: list[tuple[str, Any, Callable, str]] = [
            (name, getattr(self, name), ok, expected) for name, ok, expected in [
                ("loss", lambda v: v in LOSSES, f"one of {LOSSES}"),
                ("field", lambda v: v in FIELD_CONFIGS, f"one of {tuple(FIELD_CONFIGS)}"),
                ("max_steps", _count, "an int >= 1"),
                ("time_budget_s", lambda v: v is None or (_number(v) and v > 0), "None or > 0 seconds"),
                ("image_scale", lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]"),
                ("holdout_every", lambda v: _count(v, 0), "an int >= 0"),
                ("train_views", lambda v: v == 0 or _count(v, 2), "0 (all) or an int >= 2"),
                ("seed", lambda v: _count(v, 0), "an int >= 0"),
                ("device", lambda v: isinstance(v, str) and v.split(":")[0] in ("cpu", "cuda", "mps"),
                 '"cpu", "cuda" or "cuda:N"'),
                *[(name, _flag, "True or False") for name in ("refine_poses", "exposure_compensation", "progress")],
            ]]
        for name, cls in SUB_CONFIGS.items():
            sub = getattr(self, name)
            if not isinstance(sub, cls):
                raise ConfigError(f"config field {name}={sub!r} is invalid: expected a {cls.__name__}")
            sub_checks = _sampling_checks(sub) if cls is SamplingConfig else sub.checks()
            checks += [(f"{name}.{field}", getattr(sub, field), ok, expected) for field, ok, expected in sub_checks]
        for name, value, ok, expected in checks:
            try:
                good = bool(ok(value))
            except TypeError:
                good = False
            if not good:
                raise ConfigError(f"config field {name}={value!r} is invalid: expected {expected}")
        if self.field == "hashgrid" and self.hashgrid.backend == "kernel":
            if self.device.split(":")[0] != "cpu":
                raise ConfigError(f"config field hashgrid.backend='kernel' is a CPU kernel, but device={self.device!r}; "
                                  "use backend 'auto' (the PyTorch path on other devices) or 'torch'")
            if not native.available():
                raise ConfigError(f"config field hashgrid.backend='kernel': the fused kernel cannot run here "
                                  f"({native.unavailable_reason()}); use backend 'auto' or 'torch'")


def _set(tree: dict, path: list[str], value) -> None:
    """Set tree[path[0]][path[1]]... = value, raising ConfigError for a name the config does not have."""
    node = tree
    for depth, part in enumerate(path):
        if not isinstance(node, dict) or part not in node:
            where = ".".join(path[:depth])
            valid = sorted(node) if isinstance(node, dict) else []
            raise ConfigError(f"unknown config field(s) {['.'.join(path)]}" + (f" in {where!r}" if where else "")
                              + f"; valid fields: {valid}")
        if depth == len(path) - 1:
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = dataclasses.asdict(value)
            if isinstance(node[part], dict):  # a sub-config (or nested dataclass) given as a dict
                if not isinstance(value, dict):
                    raise ConfigError(f"config field {'.'.join(path)}={value!r} is invalid: expected a dict of its "
                                      f"fields {sorted(node[part])} or the dataclass itself")
                for key, sub_value in value.items():
                    _set(node, [part, key], sub_value)
            else:
                node[part] = value
        node = node[part]


def _build(name: str, values: dict):
    """The sub-config `name` from its plain dict."""
    cls = SUB_CONFIGS[name]
    values = dict(values)
    for (sub, field), nested in NESTED.items():
        if sub == name:
            values[field] = nested(**values[field])
    for sub, field in TUPLES:
        if sub == name and isinstance(values[field], list):
            values[field] = tuple(values[field])
    return cls(**values)
