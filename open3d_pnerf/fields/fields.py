"""Scene fields: world position (+ view direction) -> volume density and colour, and each
field type's settings (HashGridConfig, GridConfig, VanillaConfig: FIELD_CONFIGS).

The fields map points inside an axis-aligned box ``aabb`` ((2, 3) metres, min and max corner)
and return density sigma >= 0 (1/m) and colour in [0, 1].
"""

from __future__ import annotations

import dataclasses
import functools
import math

import torch
from torch import nn
from torch.profiler import record_function

from ..errors import ConfigError
from ..settings import Rule, Settings, count, one_of, setting
from . import native
from .encodings import BACKENDS, BlockEncoding, DenseGridEncoding, FrequencyEncoding, HashGridEncoding
from .sdf import SDFConfig, sdf_density


def _mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    dims = [in_dim] + [hidden] * layers
    mods: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        mods += [nn.Linear(a, b), nn.ReLU(inplace=True)]
    mods.append(nn.Linear(dims[-1], out_dim))
    return nn.Sequential(*mods)


def density_activation(raw: torch.Tensor) -> torch.Tensor:
    """exp with a clamped input: the 'truncated exponential' of Instant-NGP (1/m)."""
    return torch.exp(raw.clamp(max=15.0))


@functools.cache
def native_bf16(device_type: str) -> bool:
    """Whether `device_type` ("cpu" or "cuda") multiplies bfloat16 matrices natively: a GPU that
    torch says supports bfloat16, a CPU whose oneDNN does (x86 with AVX-512 or AMX, Arm with
    bf16). Elsewhere, an x86 CPU with AVX2 alone for one, bfloat16 products are emulated and the
    MLPs run several times slower than in float32 (benchmarks/README.md: runtime.bf16_mlp)."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    supported = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    return device_type == "cpu" and supported is not None and bool(supported())


class Field(nn.Module):
    """Common interface: ``encode(x)`` (the input encoding of points), ``geometry(x, encoded) ->
    (sigma, features)``, ``color(features, d) -> rgb``, ``forward(x, d) -> (sigma, rgb)`` (all at
    once) and ``density(x)``. The split lets a renderer encode every sample of a batch in one
    call and colour only the samples that show (see rendering.volume.render_rays).

    bf16: run the MLPs' matrix products in bfloat16 (torch.autocast on CPU or CUDA; outputs,
    activations and parameters stay float32): True always, False never, None where the device
    multiplies bfloat16 natively (:func:`native_bf16`).
    """

    encodes_in_one_pass = False
    """Whether training encodes every sample of a step in one call: for fields whose encoding's
    gradient is one dense tensor (grids), written once per step that way (see
    rendering.volume.render_rays)."""

    def __init__(self, aabb: torch.Tensor, bf16: bool | None = None):
        super().__init__()
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3))
        self.bf16 = bf16
        self.warp = None  # an NDCWarp (fields.ndc): the field's input is NDC instead of the box
        self.proposal = None  # a ProposalField (fields.proposal) that places the coarse samples

    def mlp_precision(self, x: torch.Tensor):
        """The autocast context of the MLPs for inputs on x's device: bfloat16 on CPU or CUDA when
        `bf16` says so (None: where the device multiplies it natively), else off."""
        device = x.device.type
        if device not in ("cpu", "cuda"):
            return torch.autocast("cpu", enabled=False)
        enabled = native_bf16(device) if self.bf16 is None else self.bf16
        return torch.autocast(device, dtype=torch.bfloat16, enabled=enabled)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """World points (B, 3) -> box coordinates in [0, 1]^3 (the NDC box's with a warp)."""
        if self.warp is not None:
            return self.warp.normalize(x)
        return (x - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) density of world points x (B, 3) (1/m); zero outside the box."""
        return self.geometry(x)[0]

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,) density and (B, 3) colour in [0, 1] of points x (B, 3) seen along unit directions d (B, 3)."""
        sigma, features = self.geometry(x)
        return sigma, self.color(features, d)

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) bool: whether world points x (B, 3) lie in the box."""
        u = self.normalize(x)
        return ((u >= 0) & (u <= 1)).all(-1)

    def encode(self, x: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        """(B, E) input encoding of world points x (B, 3). known: the encoding of x's last rows,
        computed before (values only), which the encoding may reuse rather than recompute."""
        raise NotImplementedError

    def geometry(self, x: torch.Tensor, encoded: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,) density of world points x (B, 3) (1/m; zero outside the box) and (B, C) features
        that color() turns into colour; encoded: encode(x), when already computed."""
        raise NotImplementedError

    def color(self, features: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """(B, 3) colour in [0, 1] of points with geometry `features` (B, C) seen along unit
        directions d (B, 3)."""
        raise NotImplementedError


class EncodedField(Field):
    """A grid encoding + small MLPs (Instant-NGP/nerfacto-sized heads).

    density = exp(MLP_sigma(enc(x))[0]); colour = sigmoid(MLP_rgb(geo_features, PE(d))).
    Given `sdf` (an SDFConfig), MLP_sigma's first output is a signed distance instead (m,
    positive in free space; :meth:`signed_distance`) and density = Psi_beta(-sdf) / beta with a
    learned sharpness 1 / beta (open3d_pnerf.fields.sdf).
    """

    encodes_in_one_pass = True

    def __init__(self, aabb, encoding: nn.Module, hidden: int = 64, geo_features: int = 15, bf16: bool | None = None,
                 sdf: SDFConfig | None = None):
        super().__init__(aabb, bf16)
        self.encoding = encoding
        self.sigma_net = _mlp(encoding.out_dim, hidden, 1, 1 + geo_features)
        self.dir_encoding = FrequencyEncoding(3, 4)
        self.color_net = _mlp(geo_features + self.dir_encoding.out_dim, hidden, 2, 3)
        self.sdf = sdf
        self.levels_on: float | None = None  # see enable_levels(); None: every level, no weighting
        if sdf is not None:  # log of the sharpness 1 / beta (1/m); free space (sdf > 0) to begin with
            self.log_sharpness = nn.Parameter(torch.tensor(float(sdf.sharpness)).log())
            with torch.no_grad():
                self.sigma_net[-1].bias[0] = 4 / sdf.sharpness

    @property
    def beta(self) -> torch.Tensor:
        """The SDF-to-density law's scale beta (m) = 1 / sharpness, the sharpness capped at sdf.max_sharpness."""
        return 1 / self.log_sharpness.exp().clamp(max=self.sdf.max_sharpness)

    def encode(self, x: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        with record_function("pnerf.encoding"):
            return self.encoding(self.normalize(x), known)

    def enable_levels(self, share: float | None) -> None:
        """Coarse-to-fine: weight the encoding's levels so that a `share` in [0, 1] of them is on,
        coarsest first, each joining smoothly (BARF's cosine ramp: level l of L gets
        (1 - cos(pi clamp(a - l, 0, 1))) / 2 with a = 1 + share (L - 1), so the coarsest level is
        always on); None (or 1): every level fully."""
        self.levels_on = None if share is None or share >= 1 else float(share)

    def level_weights(self, device) -> torch.Tensor | None:
        """(L,) weight of each encoding level (see enable_levels), or None when all are fully on."""
        if self.levels_on is None:
            return None
        levels = self.encoding.out_dim // self.encoding.features
        a = 1 + self.levels_on * (levels - 1)
        ramp = (a - torch.arange(levels, device=device, dtype=torch.float32)).clamp(0, 1)
        return (1 - torch.cos(math.pi * ramp)) / 2

    def _heads(self, x: torch.Tensor, encoded: torch.Tensor | None) -> torch.Tensor:
        encoded = self.encode(x) if encoded is None else encoded
        weights = self.level_weights(encoded.device)
        if weights is not None:  # `encoded` stays the raw encoding (a render may reuse it as known rows)
            encoded = encoded * weights.repeat_interleave(self.encoding.features)
        with record_function("pnerf.mlp"), self.mlp_precision(x):
            return self.sigma_net(encoded).float()

    def geometry(self, x: torch.Tensor, encoded: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        h = self._heads(x, encoded)
        density = density_activation(h[:, 0]) if self.sdf is None else sdf_density(h[:, 0], self.beta)
        return density * self.inside(x), h[:, 1:]

    def signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) signed distance (m, positive in free space) of world points x (B, 3); sdf fields only."""
        if self.sdf is None:
            raise TypeError("signed_distance(): this field has a density, not a signed distance (geometry='sdf')")
        return self._heads(x, None)[:, 0]

    def color(self, features: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        with record_function("pnerf.mlp"), self.mlp_precision(features):
            return torch.sigmoid(self.color_net(torch.cat([features, self.dir_encoding(d)], -1)).float())


def grow(field: EncodedField, box, block: nn.Module) -> EncodedField:
    """`field` over the larger box `box` (2, 3) m holding its own: its heads and its encoding kept for
    the points of its box (they render exactly as before), the fresh encoding `block` (of the same
    type) for the rest (:class:`BlockEncoding`). The field is changed in place and returned."""
    if field.warp is not None:
        raise ValueError("grow(): a field in NDC (a forward-facing capture) has no box to grow")
    if field.proposal is not None:
        raise ValueError("grow(): a field with a proposal network (sampling.n_proposal > 0) cannot grow its box")
    box = torch.as_tensor(box, dtype=torch.float32, device=field.aabb.device).reshape(2, 3)
    if (box[0] > field.aabb[0]).any() or (box[1] < field.aabb[1]).any():
        raise ValueError(f"grow(): the box {box.tolist()} does not hold the field's {field.aabb.tolist()}")
    old = field.encoding
    blocks, boxes = (list(old.blocks), list(old.boxes)) if isinstance(old, BlockEncoding) else ([old], [field.aabb])
    field.encoding = BlockEncoding(blocks + [block.to(box.device)], torch.stack(boxes + [box]))
    field.aabb = box
    return field


def block_boxes(field: nn.Module) -> list | None:
    """The (K, 2, 3) world boxes of a grown field's blocks as nested lists (None for a field that never grew)."""
    encoding = getattr(field, "encoding", None)
    return encoding.boxes.tolist() if isinstance(encoding, BlockEncoding) else None


def block_tables(field: nn.Module) -> list | None:
    """log2 of each hash-grid block's table size of a grown field (None for a field that never grew or
    whose blocks are not hash grids)."""
    encoding = getattr(field, "encoding", None)
    if not isinstance(encoding, BlockEncoding) or not isinstance(encoding.blocks[0], HashGridEncoding):
        return None
    return [int(block.table_size).bit_length() - 1 for block in encoding.blocks]


def block_table_size(log2_table_size: int, inner, box) -> int:
    """log2 of the hash table of a block grown over `box` (2, 3) m that encodes only the part outside
    `inner` (2, 3) m (the box before the growth, see :func:`grow`): the field's 2^log2_table_size rows
    scaled by that part's share of the box, rounded up to a power of two. Rows per cell of the region
    a block encodes are then those of the first block, and each growth adds parameters (and Adam and
    backward time per step) for its new volume only, not for a whole table."""
    inner, box = (torch.as_tensor(b, dtype=torch.float64).reshape(2, 3) for b in (inner, box))
    share = 1 - float((inner[1] - inner[0]).prod() / (box[1] - box[0]).prod())
    return int(min(log2_table_size, max(4, math.ceil(log2_table_size + math.log2(max(share, 1e-9))))))


class GridField(EncodedField):
    """Multi-resolution dense grids: resolutions per level, features each."""

    def __init__(self, aabb, resolutions=(16, 32, 64, 128, 256), features: int = 2, **heads):
        super().__init__(aabb, DenseGridEncoding(resolutions, features), **heads)


class HashGridField(EncodedField):
    """Instant-NGP multi-resolution hash grid (levels x features, 2^log2_table_size per level)."""

    def __init__(self, aabb, levels=8, features=2, log2_table_size=19, max_resolution=2048, backend="auto", **heads):
        super().__init__(aabb, HashGridEncoding(levels, features, log2_table_size, 16, max_resolution, backend),
                         **heads)


class VanillaNeRFField(Field):
    """The original NeRF MLP (8 x 256, skip at layer 4, PE 10/4 frequencies), as in nerf_pl."""

    def __init__(self, aabb, width: int = 256, depth: int = 8, skip: int = 4, bf16: bool | None = None):
        super().__init__(aabb, bf16)
        self.pos_encoding = FrequencyEncoding(3, 10)
        self.dir_encoding = FrequencyEncoding(3, 4)
        self.skip = skip
        in_dim = self.pos_encoding.out_dim
        self.layers = nn.ModuleList(
            nn.Linear(in_dim if i == 0 else width + (in_dim if i == skip else 0), width) for i in range(depth)
        )
        self.sigma_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.color_head = nn.Sequential(
            nn.Linear(width + self.dir_encoding.out_dim, width // 2), nn.ReLU(inplace=True), nn.Linear(width // 2, 3)
        )

    def encode(self, x: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        return self.pos_encoding(self.normalize(x) * 2 - 1)

    def geometry(self, x: torch.Tensor, encoded: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        e = self.encode(x) if encoded is None else encoded
        h = e
        with self.mlp_precision(x):
            for i, layer in enumerate(self.layers):
                if i == self.skip:
                    h = torch.cat([h, e], -1)
                h = torch.relu(layer(h))
            return torch.relu(self.sigma_head(h)[:, 0].float()) * self.inside(x), h

    def color(self, features: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        with self.mlp_precision(features):
            return torch.sigmoid(self.color_head(torch.cat([self.feature(features), self.dir_encoding(d)], -1)).float())


# -- the settings of each field type (a sub-config of ReconstructionConfig each) -------------------
@dataclasses.dataclass
class HashGridConfig(Settings):
    """Instant-NGP multi-resolution hash grid (field="hashgrid")."""

    levels: int = setting(8, count(1, native.MAX_LEVELS))
    """Hash-grid levels, resolutions spaced geometrically from 16 to max_resolution."""
    features: int = setting(2, count(1))
    """Features per level."""
    log2_table_size: int = setting(19, count(4, 26))
    """log2 of the hash table size per level (memory: levels * 2^size * features floats)."""
    max_resolution: int = setting(2048, count(16))
    """Finest hash-grid resolution across the scene box."""
    backend: str = setting("auto", one_of(BACKENDS))
    """"auto": the fused CPU kernel (open3d_pnerf.fields.native) where it can be built, else the
    pure-PyTorch path; "kernel" insists on the kernel (a ConfigError where it cannot run); "torch":
    the pure-PyTorch path (also on GPUs)."""

    def validate(self, prefix: str = "") -> None:
        super().validate(prefix)
        if self.backend == "kernel" and not native.available():
            raise ConfigError(f"config field {prefix}backend='kernel': the fused kernel cannot run here "
                              f"({native.unavailable_reason()}); use backend 'auto' or 'torch'")

    def build(self, aabb, bf16: bool | None = None, sdf: SDFConfig | None = None) -> HashGridField:
        return HashGridField(aabb, self.levels, self.features, self.log2_table_size, self.max_resolution,
                             self.backend, bf16=bf16, sdf=sdf)


@dataclasses.dataclass
class GridConfig(Settings):
    """Multi-resolution dense grids (field="grid")."""

    resolutions: tuple = setting((16, 32, 64, 128, 192), Rule(
        "a non-empty tuple of ints >= 2", lambda v: isinstance(v, tuple) and len(v) >= 1 and all(
            isinstance(r, int) and not isinstance(r, bool) and r >= 2 for r in v)))
    """Resolutions of the dense grid levels across the scene box."""
    features: int = setting(2, count(1))
    """Features per level (memory: sum R^3 * features floats, x4 with Adam)."""

    def build(self, aabb, bf16: bool | None = None, sdf: SDFConfig | None = None) -> GridField:
        return GridField(aabb, resolutions=self.resolutions, features=self.features, bf16=bf16, sdf=sdf)


@dataclasses.dataclass
class VanillaConfig(Settings):
    """The paper's NeRF MLP (field="vanilla")."""

    width: int = setting(256, count(1))
    """Hidden units per layer."""
    depth: int = setting(8, count(5))
    """Hidden layers (a skip connection at layer 4)."""

    def build(self, aabb, bf16: bool | None = None) -> VanillaNeRFField:
        return VanillaNeRFField(aabb, width=self.width, depth=self.depth, bf16=bf16)


FIELD_CONFIGS = {"hashgrid": HashGridConfig, "grid": GridConfig, "vanilla": VanillaConfig}
"""The field types by name (ReconstructionConfig.field), each its settings' class (with build())."""
