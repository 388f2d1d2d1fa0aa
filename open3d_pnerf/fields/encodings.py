"""Input encodings: the multi-resolution hash grid (a fused CPU kernel, or plain PyTorch), dense
feature grids and the frequency encoding."""

from __future__ import annotations

import math

import torch
from torch import nn

from . import native

BACKENDS = ("auto", "kernel", "torch")
# Spatial-hash primes of Instant-NGP (Mueller et al. 2022); the first is 1 for coherence.
_PRIMES = (1, 2654435761, 805459861)


class HashGridEncoding(nn.Module):
    """Multi-resolution hash grid (Instant-NGP) with trilinear interpolation.

    Input x: (B, 3) in [0, 1]. Output: (B, levels * features), level by level. Level l has
    R_l = floor(base_resolution * growth^l) cells per axis, growth set so that the last
    level has max_resolution. A level whose (R + 1)^3 vertices fit in a table of
    2^log2_table_size rows is stored densely, as a :class:`DenseGridEncoding` level of R + 1
    vertices per axis (fused ``grid_sample`` kernels); the finer levels share one table of
    2^log2_table_size rows each, indexed by the spatial hash of the cell corners and
    interpolated by one fused gather (:class:`_HashedTrilinear`). On a CPU, the fused kernel of
    :mod:`~open3d_pnerf.fields.native` computes all levels at once (backend "auto" where it can
    be built, "kernel" insisting; "torch": the PyTorch path, the kernel's reference). This is
    Instant-NGP's encoding (its coarse levels are indexed densely too) laid out for speed on a
    CPU. resolutions: the cells per axis of each level.
    """

    def __init__(
        self,
        levels: int = 8,
        features: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        backend: str = "auto",
    ):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.levels, self.features, self.backend = levels, features, backend
        self.table_size = 2**log2_table_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        self.resolutions = [int(math.floor(base_resolution * growth**level)) for level in range(levels)]
        self.n_dense = sum((r + 1) ** 3 <= self.table_size for r in self.resolutions)  # resolutions grow
        dense, hashed = self.resolutions[: self.n_dense], self.resolutions[self.n_dense:]
        self.dense = DenseGridEncoding([r + 1 for r in dense], features) if dense else None
        self.register_buffer("hashed_resolution", torch.tensor(hashed, dtype=torch.float32), persistent=False)
        self.register_buffer("offset", torch.arange(len(hashed)) * self.table_size, persistent=False)
        self.register_buffer("primes", torch.tensor(_PRIMES), persistent=False)
        if hashed:
            self.table = nn.Parameter(torch.empty(len(hashed) * self.table_size, features).uniform_(-1e-4, 1e-4))
        else:
            self.register_parameter("table", None)
        if backend == "kernel" and not native.available():
            raise RuntimeError(f"HashGridEncoding(backend='kernel'): the fused kernel cannot run here "
                               f"({native.unavailable_reason()}); use backend 'auto' or 'torch'")
        self._kernel_spec = (self.resolutions, [int(i < self.n_dense) for i in range(levels)], self.table_size,
                             features)

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def uses_kernel(self, x: torch.Tensor) -> bool:
        """Whether forward(x) runs the fused CPU kernel (:mod:`~open3d_pnerf.fields.native`): backend
        "kernel", or "auto" where the kernel runs (one warning where it cannot), for CPU points."""
        if self.backend == "torch" or x.device.type != "cpu" or self.levels > native.MAX_LEVELS:
            return False
        if not native.available():
            native.warn_fallback()
            return False
        return True

    def forward(self, x: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        """(B, levels * features) encoding of points x (B, 3) in [0, 1]: a coordinate outside is
        clamped onto the box (no gradient along it), a point with a NaN or infinite coordinate
        encodes to 0 (and gets no gradient). known: the encoding of x's last rows, computed before
        (values only): the kernel copies it instead of recomputing (its backward still covers those
        rows); the PyTorch path recomputes it, as its gradient needs the computation."""
        if self.uses_kernel(x):
            params = [*(self.dense.grids if self.dense is not None else []),
                      *([self.table] if self.table is not None else [])]
            return native.hashgrid_encode(x, params, *self._kernel_spec, known)
        finite = torch.isfinite(x).all(-1, keepdim=True)
        x = torch.where(finite, x, 0.0).clamp(0, 1)
        parts = [self.dense(x)] if self.dense is not None else []
        if self.table is not None:
            rows, weights = self.hashed_corners(x)
            parts.append(_HashedTrilinear.apply(self.table, rows, weights).reshape(x.shape[0], -1))
        return torch.cat(parts, 1) * finite

    def hashed_corners(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Table rows (B, L, 8) of the 8 cell corners of points x (B, 3) in [0, 1] on the L
        hashed levels, and their trilinear weights (B, L, 8); corner c = 4 dz + 2 dy + dx."""
        res = self.hashed_resolution[None, :, None]
        pos = x[:, None, :] * res  # (B, L, 3)
        base = pos.floor().clamp(max=res - 1)  # x = 1 uses the last cell
        frac = pos - base
        lo_hi = torch.stack([base.long(), base.long() + 1], -1) * self.primes[:, None]  # (B, L, 3, 2)
        rows = _corners(lo_hi, torch.bitwise_xor) & (self.table_size - 1)
        weights = _corners(torch.stack([1 - frac, frac], -1), torch.mul)
        return rows + self.offset[None, :, None], weights


class _HashedTrilinear(torch.autograd.Function):
    """out (B, L, F) = sum_c weights[b, l, c] * table[rows[b, l, c]].

    One gather forward and one ``index_add_`` backward, without autograd keeping the gathered
    (B, L, 8, F) corner features. The weights' gradient (and through them the sample positions',
    for pose refinement) is computed only when they require one, by gathering the corners again.
    """

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        corners = table.index_select(0, rows.reshape(-1)).view(*rows.shape, table.shape[1])
        ctx.save_for_backward(table, rows, weights)
        return (corners * weights[..., None]).sum(2)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        table, rows, weights = ctx.saved_tensors
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            per_corner = (weights[..., None] * grad[:, :, None, :]).reshape(-1, grad.shape[-1])
            grad_table = torch.zeros_like(table).index_add_(0, rows.reshape(-1), per_corner)
        if ctx.needs_input_grad[2]:
            corners = table.index_select(0, rows.reshape(-1)).view(*rows.shape, table.shape[1])
            grad_weights = (corners * grad[:, :, None, :]).sum(-1)
        return grad_table, None, grad_weights


def _corners(terms: torch.Tensor, combine) -> torch.Tensor:
    """(B, L, 3, 2) per-axis terms for offsets {0, 1} -> (B, L, 8) over the cube corners."""
    tx, ty, tz = terms[:, :, 0], terms[:, :, 1], terms[:, :, 2]
    out = combine(combine(tz[:, :, :, None, None], ty[:, :, None, :, None]), tx[:, :, None, None, :])
    return out.reshape(*terms.shape[:2], 8)


class DenseGridEncoding(nn.Module):
    """Multi-resolution dense feature grids, trilinearly interpolated with ``grid_sample``.

    Input x: (B, 3) in [0, 1]. Output: (B, len(resolutions) * features). Each level is a
    (features, R, R, R) volume of R vertices per axis, vertex i at i / (R - 1); PyTorch's
    fused grid_sample kernels make it fast on CPU, at the cost of memory (192^3 x 2 floats
    = 57 MB for the finest level). The coarse levels give the coarse-to-fine behaviour a
    single dense grid lacks. :class:`HashGridEncoding` stores its coarse levels this way.
    """

    def __init__(self, resolutions=(16, 32, 64, 128, 256), features: int = 2):
        super().__init__()
        self.features = features
        self.grids = nn.ParameterList(
            nn.Parameter(torch.empty(1, features, r, r, r).uniform_(-1e-4, 1e-4)) for r in resolutions
        )

    @property
    def out_dim(self) -> int:
        return len(self.grids) * self.features

    def forward(self, x: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        """Features of points x (B, 3) in [0, 1] (clamped onto the box); `known` (the encoding of
        x's last rows) is recomputed, as its gradient needs the computation."""
        g = (x.clamp(0, 1) * 2 - 1).view(1, -1, 1, 1, 3)
        feats = [
            nn.functional.grid_sample(grid, g, mode="bilinear", align_corners=True).view(self.features, -1)
            for grid in self.grids
        ]
        return torch.cat(feats, 0).T


class FrequencyEncoding(nn.Module):
    """NeRF positional encoding [x, sin(2^k pi x), cos(2^k pi x)] for k < n_frequencies."""

    def __init__(self, in_dim: int, n_frequencies: int, include_input: bool = True):
        super().__init__()
        self.in_dim, self.include_input = in_dim, include_input
        self.register_buffer("freqs", (2.0 ** torch.arange(n_frequencies)) * math.pi, persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * len(self.freqs) + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scaled = (x[..., None] * self.freqs).flatten(-2)
        parts = [torch.sin(scaled), torch.cos(scaled)]
        return torch.cat(([x] if self.include_input else []) + parts, -1)


class BlockEncoding(nn.Module):
    """The encoding of a field whose box grew: one encoding (block) per box, the first box the
    field's original one, the last the field's current box (holding all the others).

    Input u: (B, 3) points in the field's box coordinates ([0, 1] over the last box). A point is
    encoded by the first block whose box holds it, in that block's own box coordinates: points of
    the original box encode exactly as before the growth. boxes: (K, 2, 3) world boxes (m) of the
    K blocks (same encoding type and output size).
    """

    def __init__(self, blocks: list[nn.Module], boxes):
        super().__init__()
        if len(blocks) != len(boxes) or len({b.out_dim for b in blocks}) != 1:
            raise ValueError("BlockEncoding: one box per block, and blocks of one output size")
        self.blocks = nn.ModuleList(blocks)
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(len(blocks), 2, 3)
        size = boxes[:, 1] - boxes[:, 0]
        self.register_buffer("boxes", boxes, persistent=False)
        self.register_buffer("scale", size[-1] / size, persistent=False)  # field coordinates -> block k's
        self.register_buffer("shift", (boxes[-1, 0] - boxes[:, 0]) / size, persistent=False)

    @property
    def out_dim(self) -> int:
        return self.blocks[0].out_dim

    @property
    def features(self) -> int:
        return self.blocks[0].features

    def forward(self, u: torch.Tensor, known: torch.Tensor | None = None) -> torch.Tensor:
        """(B, out_dim) encoding of points u (B, 3) in the last box's coordinates; `known` is not
        reused (each block recomputes its rows)."""
        out = u.new_zeros(u.shape[0], self.out_dim)
        left = torch.ones(u.shape[0], dtype=torch.bool, device=u.device)
        for k, block in enumerate(self.blocks):
            v = u * self.scale[k] + self.shift[k]
            mine = left if k == len(self.blocks) - 1 else left & ((v >= 0) & (v <= 1)).all(-1)
            rows = mine.nonzero().squeeze(1)
            if rows.numel():
                out = out.index_copy(0, rows, block(v[rows]))
            left = left & ~mine
        return out
