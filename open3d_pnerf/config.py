"""ReconstructionConfig: every setting of a reconstruction, assembled from one sub-config per concern.

The method and its budget are top-level fields (``loss``, ``field``, ``max_steps``, ...); the
rest lives in sub-configs, each declared beside the component it configures and validating
itself: one per field type (``hashgrid``, ``grid``, ``vanilla``: open3d_pnerf.fields),
``sampling`` (rendering), ``objective`` (losses), ``optimizer`` and ``runtime`` (training),
``targets``, ``tracking`` and ``export``. Presets and overrides take dotted names::

    ReconstructionConfig.preset("fast", holdout_every=4, **{"sampling.n_coarse": 32})
    config.replace(**{"hashgrid.levels": 12})
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import torch

from .errors import ConfigError
from .export import ExportConfig
from .fields import (FIELD_CONFIGS, EncodedField, GridConfig, HashGridConfig, ProposalField, SDFConfig, VanillaConfig,
                     block_table_size, grow)
from .losses import LOSSES, ObjectiveConfig
from .rendering.volume import SamplingConfig
from .settings import FLAG, Rule, Settings, count, number, one_of, optional, section, setting
from .targets import TargetsConfig
from .tracking import TrackingConfig
from .training import OptimizerConfig, RuntimeConfig


@dataclasses.dataclass
class MappingConfig(Settings):
    """How the streaming :class:`~open3d_pnerf.mapper.Mapper` picks keyframes and shares its time between frames."""

    keyframe_every: int = setting(5, count(1))
    """Every k-th frame is a keyframe (kept and trained on); the frame halfway between two is kept
    as a held-out frame (scored, never trained on) when holdout_every > 0."""
    keyframe_distance_m: float = setting(0.1, number(0, low_open=True, unit="m"))
    """A frame is also a keyframe when the camera moved this far from the last keyframe ..."""
    keyframe_angle_deg: float = setting(10.0, number(0, low_open=True, unit="degrees"))
    """... or turned this far."""
    train_s_per_frame: float = setting(0.05, number(0, unit="seconds"))
    """Seconds of training after each frame is tracked: the per-frame compute budget (0: none). A
    training step is never cut short: the time a frame's last step runs past its budget is taken
    from the next frames', so that the stream trains this long per frame on average."""
    finish_s: float = setting(60.0, number(0, unit="seconds"))
    """Training seconds on every keyframe that :meth:`Mapper.finish` gives the map, with the
    learning rate decaying as in an offline reconstruction."""
    loops_per_keyframe: int = setting(1, count(0))
    """Loop closures tried for each new keyframe (the nearest earlier keyframes not linked yet;
    with tracking.loop_closure)."""
    grow_pad: float = setting(0.25, number(0))
    """When a keyframe's surfaces leave the scene box, the field grows to the union padded by this
    share of its size (fewer, larger growths)."""


@dataclasses.dataclass
class ReconstructionConfig(Settings):
    """Settings of :func:`open3d_pnerf.reconstruct`. The defaults are the "fast" preset, which
    ``reconstruct(sequence)`` uses; others: ``ReconstructionConfig.preset("quality")``."""

    loss: str = setting("pnerf", one_of(LOSSES))
    """"pnerf" (colour + depth-PDF + depth L1), "photometric" (colour only) or "dsnerf"."""
    field: str = setting("hashgrid", one_of(FIELD_CONFIGS))
    """"hashgrid" (Instant-NGP hash grid: the sharpest renders at equal time on a CPU, dense
    sequences and 10 sparse views alike), "grid" (dense grids 16..192: coarser, 3x the memory,
    about half the steps per second with 10 views; better for refine_poses) or "vanilla" (the
    paper's 8x256 MLP, slow, for comparison); its settings are the sub-config of the same name."""
    geometry: str = setting("density", one_of(("density", "sdf")))
    """"density": the field's density is free (NeRF); "sdf": it is derived from a learned signed
    distance (VolSDF), trained with an eikonal term (objective.weights.eikonal) and, with depth
    targets, fitted to them directly (objective.weights.sdf_surface, sdf_free), whose zero level
    set is a surface and whose depth is that surface; a grid field (hashgrid or grid) only. Its
    settings: the sub-config sdf."""
    ndc: str = setting("auto", one_of(("auto", "on", "off")))
    """The field's input coordinates: "on" normalized device coordinates of the training
    frames' mean camera (NeRF's for forward-facing captures: resolution that follows the image at
    every depth, coarse samples even in disparity; open3d_pnerf.fields.ndc), "off" the scene box;
    "auto" NDC for a forward-facing image-only sequence with SfM depth bounds (an LLFF folder),
    the box otherwise."""
    max_steps: int = setting(1500, count(1))
    """Optimiser steps; the learning-rate schedule is laid over this many steps."""
    time_budget_s: float | None = setting(150.0, optional(number(0, low_open=True, unit="seconds")))
    """Stop training after this many seconds (None = no limit). With a budget the schedule
    follows max(step / max_steps, elapsed / budget), so runs are not bit-reproducible."""
    image_scale: float = setting(0.5, number(0, 1, low_open=True))
    """Training/evaluation image size relative to the sequence's frames, in (0, 1]."""
    holdout_every: int = setting(0, count(0))
    """Keep every k-th frame (0, k, 2k, ...) out of training for evaluation; 0 = none."""
    train_views: int = setting(0, Rule("0 (all) or an int >= 2", lambda v: v == 0 or count(2).holds(v)))
    """Train on only this many of the non-held-out frames, evenly spaced (sparse-view
    experiments); 0 = all of them."""
    seed: int = setting(0, count(0))
    """Seed of every random choice (rays, samples, initialisation)."""
    device: str = setting("cpu", Rule('"cpu", "cuda" or "cuda:N"', lambda v: isinstance(v, str)
                                      and v.split(":")[0] in ("cpu", "cuda", "mps")))
    """Torch device for the model: "cpu", "cuda", "cuda:1", ... Launched by torchrun with
    several ranks, any CUDA device means each rank's own GPU, cuda:LOCAL_RANK."""
    refine_poses: bool = setting(False, FLAG)
    """Optimise a rigid correction of each training pose jointly with the field, held by a
    Gaussian prior from the pose covariances (open3d_pnerf.pose_refinement): uncertain poses
    move, certain ones stay (zero covariance: fixed). The Reconstruction's poses are the refined
    ones; held-out frames are moved by the rigid shift that best fits the training frames'
    refinement. Use it with field="grid" (benchmarks/bench_pose_refinement.py)."""
    exposure_compensation: bool = setting(True, FLAG)
    """Learn a colour gain per training frame and channel (the auto-exposure and white balance
    of real cameras; open3d_pnerf.rendering.exposure). Held-out frames get gains interpolated in
    time (Reconstruction.render(..., frame=i)); renders without a frame show the average exposure."""
    progress: bool = setting(True, FLAG)
    """Show progress bars."""
    hashgrid: HashGridConfig = section(HashGridConfig)
    grid: GridConfig = section(GridConfig)
    vanilla: VanillaConfig = section(VanillaConfig)
    sdf: SDFConfig = section(SDFConfig)
    sampling: SamplingConfig = section(SamplingConfig)
    objective: ObjectiveConfig = section(ObjectiveConfig)
    optimizer: OptimizerConfig = section(OptimizerConfig)
    targets: TargetsConfig = section(TargetsConfig)
    tracking: TrackingConfig = section(TrackingConfig)
    export: ExportConfig = section(ExportConfig)
    runtime: RuntimeConfig = section(RuntimeConfig)
    mapping: MappingConfig = section(MappingConfig)

    PRESETS = {
        "fast": {},  # the defaults: a couple of minutes on a laptop CPU
        "quality": {"max_steps": 20000, "time_budget_s": None, "image_scale": 1.0, "optimizer.rays_per_batch": 2048,
                    "sampling.n_coarse": 48, "sampling.n_fine": 48, "sampling.n_guided": 24,
                    "grid.resolutions": (16, 32, 64, 128, 256, 384)},
        # images only, from cameras that look one way (LLFF): sparse SfM targets guide ~1% of the rays,
        # so the coarse pass places most fine samples; 32 coarse samples chosen on Fern's tuning split,
        # with the coarse terms (Fern's figures were measured with them; their default went off on RGB-D)
        "forward_facing": {"max_steps": 14000, "time_budget_s": 600.0, "sampling.n_coarse": 32,
                           "objective.coarse_terms": True},
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
        "forward_facing": image-only captures that look one way (LLFF), ten minutes; "test": tiny
        smoke runs) with overrides (dotted names for sub-config fields)."""
        if name not in cls.PRESETS:
            raise ConfigError(f"unknown preset {name!r}; expected one of {sorted(cls.PRESETS)}")
        return cls.from_dict({**cls.PRESETS[name], **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any], prefix: str = "") -> "ReconstructionConfig":
        """Build from a dict, applied in order over the defaults: nested sub-config dicts (as
        to_dict() and saved run_config.json files have them), dotted names
        ("sampling.n_coarse") and top-level fields. Unknown names raise ConfigError."""
        if not isinstance(values, dict):
            raise ConfigError(f"a config must be a dict of settings, got {type(values).__name__}")
        tree: dict = {}
        for key, value in values.items():
            _merge(tree, key.split("."), value)
        config = super().from_dict(tree, prefix)
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

    def build_field(self, aabb, blocks=None, tables=None, warp=None):
        """The chosen field over the scene box aabb (2, 3) metres, on `device`, initialised from `seed`;
        blocks: the (K, 2, 3) boxes of a field that grew (see fields.grow), the last one aabb; tables:
        a grown hash grid's log2 table size per block (default: the config's for the first block,
        fields.block_table_size for the others, as :meth:`grow_field` makes them); warp: an NDCWarp
        (fields.ndc) the field's input goes through, or None."""
        torch.manual_seed(self.seed)
        try:
            field = self._build(aabb if blocks is None else blocks[0], None if tables is None else tables[0])
            field.warp = warp
            if self.sampling.n_proposal > 0:
                field.proposal = ProposalField(self.hashgrid.backend)
            if blocks is not None:
                if not isinstance(field, EncodedField):
                    raise ConfigError(f"config field field={self.field!r}: only a grid field can grow its box")
                for k in range(1, len(blocks)):
                    self.grow_field(field, blocks[k], None if tables is None else tables[k])
            return field.to(torch.device(self.device))
        except (RuntimeError, AssertionError) as exc:
            raise ConfigError(f"config field device={self.device!r} is not usable here ({exc})") from None

    def grow_field(self, field: EncodedField, box, log2_table_size: int | None = None) -> EncodedField:
        """`field` grown over the larger box `box` (2, 3) m by a fresh block of the chosen encoding,
        initialised from `seed` (fields.grow; in place, returned); a hash grid's block gets a table
        sized to the volume it adds (fields.block_table_size) unless log2_table_size says otherwise."""
        torch.manual_seed(self.seed)
        size = log2_table_size
        if self.field == "hashgrid" and size is None:
            size = block_table_size(self.hashgrid.log2_table_size, field.aabb.cpu(), box)
        return grow(field, box, self._build(box, size).encoding)

    def _build(self, aabb, log2_table_size: int | None = None):
        """The chosen field over aabb (2, 3) m (a hash grid with 2^log2_table_size rows per level when given)."""
        settings = self.field_config
        if log2_table_size is not None:
            settings = dataclasses.replace(settings, log2_table_size=int(log2_table_size))
        sdf = {"sdf": self.sdf} if self.geometry == "sdf" else {}
        return settings.build(torch.as_tensor(aabb), bf16=self.runtime.bf16_mlp, **sdf)

    # -- validation --------------------------------------------------------------------------
    def validate(self, prefix: str = "") -> None:
        """Raise ConfigError naming the first field with a bad value or type (each sub-config
        checks its own), or settings that do not go together."""
        super().validate(prefix)
        if self.geometry == "sdf" and self.field == "vanilla":
            raise ConfigError("config field geometry='sdf' needs a grid field (field 'hashgrid' or 'grid'): the "
                              "vanilla MLP's finite-difference eikonal term would cost six extra MLP passes per point")
        if self.geometry == "sdf" and self.sdf.max_sharpness < self.sdf.sharpness:
            raise ConfigError(f"config field sdf.max_sharpness={self.sdf.max_sharpness!r} is below sdf.sharpness="
                              f"{self.sdf.sharpness!r}, the initial sharpness")
        if self.optimizer.coarse_to_fine > 0 and self.field == "vanilla":
            raise ConfigError(f"config field optimizer.coarse_to_fine={self.optimizer.coarse_to_fine!r} needs a grid "
                              "field (field 'hashgrid' or 'grid'): the vanilla MLP has no encoding levels")
        if self.field == "hashgrid" and self.hashgrid.backend == "kernel" and self.device.split(":")[0] != "cpu":
            raise ConfigError(f"config field hashgrid.backend='kernel' is a CPU kernel, but device={self.device!r}; "
                              "use backend 'auto' (the PyTorch path on other devices) or 'torch'")


def _merge(tree: dict, path: list[str], value) -> None:
    """Set tree[path[0]][path[1]]... = value, merging a dict (or a sub-config) into what is there."""
    for part in path[:-1]:
        node = tree.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"config field {'.'.join(path)}: {part!r} is not a sub-config")
        tree = node
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict) and isinstance(tree.get(path[-1]), dict):
        for key, sub in value.items():
            _merge(tree[path[-1]], [key], sub)
    else:
        tree[path[-1]] = value


def overrides(pairs: list[str], option: str = "--set") -> dict[str, Any]:
    """Config overrides from KEY=VALUE strings (the command line's and the benchmarks' --set): VALUE
    read as JSON (numbers, true/false, null, lists as tuples), else taken as a string."""
    out = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"{option} {pair!r}: expected KEY=VALUE, e.g. {option} sampling.n_coarse=32")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        out[key] = tuple(value) if isinstance(value, list) else value
    return out
