"""DepthTargets: per-pixel Gaussian depth targets, in RAM or in memory-mapped files."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

BYTES_PER_PIXEL = 11  # mean, sigma (float32), valid, support, filled (1 byte each)
RAM_MAX_BYTES = 512 * 2**20
"""Targets larger than this go to memory-mapped files (see :func:`storage_dir`)."""


def storage_dir(n: int, image_size: tuple[int, int], folder=None, name: str = "targets") -> Path | None:
    """Where the targets of n frames of image_size (H, W) pixels are kept: None (in RAM) up to
    RAM_MAX_BYTES, else memory-mapped files in folder/name (a new temporary folder without `folder`)."""
    if n * image_size[0] * image_size[1] * BYTES_PER_PIXEL <= RAM_MAX_BYTES:
        return None
    return Path(folder) / name if folder else Path(tempfile.mkdtemp(prefix="pnerf-targets-"))


@dataclasses.dataclass
class DepthTargets:
    """Per-pixel Gaussian depth targets for the N frames of a sequence, all (N, H, W).

    mean, sigma: float32 z-depth metres (0 where invalid). valid: bool. support: uint8
    number of observations fused (own depth counts as one). filled: bool, True where the
    frame had no own depth and the target comes from neighbours only.
    Sparse targets (SfM points) also have weight: float32 loss weight of each target (None:
    1 everywhere), and offset: (N, H, W, 2) float32 (du, dv) pixels from the pixel centre to
    where the target's point is seen (None: at the centres); its ray goes through that spot.
    """

    mean: np.ndarray
    sigma: np.ndarray
    valid: np.ndarray
    support: np.ndarray
    filled: np.ndarray
    weight: np.ndarray | None = None
    offset: np.ndarray | None = None

    def __len__(self) -> int:
        return self.mean.shape[0]

    @property
    def image_size(self) -> tuple[int, int]:
        return self.mean.shape[1:]

    def summary(self) -> dict:
        """Fractions of valid/filled pixels and sigma percentiles (mm) over valid pixels."""
        sig = self.sigma[self.valid]
        pct = np.percentile(sig, [5, 50, 95]) * 1000 if sig.size else [np.nan] * 3
        return {
            "valid_fraction": float(self.valid.mean()),
            "filled_fraction": float(self.filled.mean()),
            "sigma_mm_p5_p50_p95": [round(float(p), 2) for p in pct],
            "mean_support": float(self.support[self.valid].mean()) if sig.size else 0.0,
        }


def allocate(n: int, h: int, w: int, storage_dir=None, sparse: bool = False) -> DepthTargets:
    """Zeroed targets of n frames of h x w pixels: NumPy arrays, or .npy memory maps in
    storage_dir; sparse: with (zero) weight and offset arrays."""
    if storage_dir is None:
        make = lambda name, dtype, extra=(): np.zeros((n, h, w, *extra), dtype)  # noqa: E731
    else:
        folder = Path(storage_dir)
        folder.mkdir(parents=True, exist_ok=True)
        make = lambda name, dtype, extra=(): np.lib.format.open_memmap(  # noqa: E731
            folder / f"{name}.npy", mode="w+", dtype=dtype, shape=(n, h, w, *extra)
        )
    return DepthTargets(
        make("mean", np.float32),
        make("sigma", np.float32),
        make("valid", bool),
        make("support", np.uint8),
        make("filled", bool),
        make("weight", np.float32) if sparse else None,
        make("offset", np.float32, (2,)) if sparse else None,
    )
