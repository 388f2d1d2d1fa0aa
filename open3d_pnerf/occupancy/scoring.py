"""How right an occupancy map is on views it did not see: the voxels held-out frames' rays reach, and
the calibration of probabilities against them."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .grid import FREE_BELOW, OCCUPIED_ABOVE


def heldout_voxels(recon, sequence, voxel_size: float = 0.05, stride: int = 4,
                   depths: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(centres (M, 3) m, occupied (M,) bool) of the voxels (of `voxel_size`, origin at a multiple of
    it) that the reconstruction's held-out frames' rays reach, every `stride`-th pixel of `sequence`
    (the one reconstructed): occupied where a ray ends, free where one passes (sampled every quarter
    voxel) before its depth. depths: the held-out frames' depth maps (m) to use instead of the
    sequence's (e.g. exact renders)."""
    hold = recon.holdout_indices
    if not len(hold):
        raise InputError("heldout_voxels(): the reconstruction has no held-out frames (holdout_every)")
    if depths is not None and len(depths) != len(hold):
        raise InputError(f"heldout_voxels(): {len(depths)} depth maps for {len(hold)} held-out frames")
    h, w = sequence.image_size
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    K = sequence.K
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)
    ends, passes = [], []
    for k, i in enumerate(hold):
        z = (sequence[i].depth if depths is None else depths[k])[::stride, ::stride].reshape(-1)
        ok = z > 0
        pose, r, z = recon.poses[i], rays[ok], z[ok]
        ends.append(voxel_codes((r * z[:, None]) @ pose[:3, :3].T + pose[:3, 3], voxel_size))
        length = z * np.linalg.norm(r, axis=1)
        count = np.floor(length / (voxel_size / 4)).astype(int)
        ray = np.repeat(np.arange(len(z)), count)
        along = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)) * (voxel_size / 4) / length[ray]
        points = (r[ray] * (z[ray] * along)[:, None]) @ pose[:3, :3].T + pose[:3, 3]
        passes.append(np.unique(voxel_codes(points, voxel_size)))
    hit = np.unique(np.concatenate(ends))
    codes = np.union1d(hit, np.concatenate(passes))
    return voxel_centers(codes, voxel_size), np.isin(codes, hit)


_OFFSET, _BITS = 1 << 20, 21


def voxel_codes(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N,) int64 code of each point's voxel (of `voxel_size`, origin at 0; within 50,000 voxels of it)."""
    k = np.floor(np.asarray(points) / voxel_size).astype(np.int64) + _OFFSET
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


def voxel_centers(codes: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N, 3) centres (m) of the voxels of :func:`voxel_codes`."""
    mask = (1 << _BITS) - 1
    k = np.stack([codes >> (2 * _BITS), (codes >> _BITS) & mask, codes & mask], -1) - _OFFSET
    return (k + 0.5) * voxel_size


def calibration(probability: np.ndarray, occupied: np.ndarray, bins: int = 10) -> dict:
    """Scores of occupancy probabilities (M,) against the truth (M,) bool: Brier (all, occupied, free
    voxels), expected calibration error over `bins` equal bins, the shares of occupied voxels called
    free (P < FREE_BELOW), of free ones called occupied (P > OCCUPIED_ABOVE) and of voxels decided
    (either); and the reliability diagram: per bin the mean probability, the occupied share and the
    count."""
    p, y = np.asarray(probability, np.float64), np.asarray(occupied, bool)
    if p.shape != y.shape or p.ndim != 1 or not len(p):
        raise InputError(f"calibration(): probability {p.shape} and occupied {y.shape} must be one (M,) shape")
    which = np.clip((p * bins).astype(int), 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore"):
        mean = np.bincount(which, p, bins) / count
        observed = np.bincount(which, y.astype(float), bins) / count
    filled = count > 0
    return {"brier": float(np.mean((p - y) ** 2)),
            "brier_occupied": float(np.mean((p[y] - 1) ** 2)) if y.any() else float("nan"),
            "brier_free": float(np.mean(p[~y] ** 2)) if (~y).any() else float("nan"),
            "ece": float(np.sum(np.abs(mean - observed)[filled] * count[filled]) / len(p)),
            "occupied_called_free": float(np.mean(p[y] < FREE_BELOW)) if y.any() else float("nan"),
            "free_called_occupied": float(np.mean(p[~y] > OCCUPIED_ABOVE)) if (~y).any() else float("nan"),
            "decided": float(np.mean((p < FREE_BELOW) | (p > OCCUPIED_ABOVE))), "voxels": int(len(p)),
            "occupied_share": float(y.mean()),
            "reliability": {"mean_probability": [float(m) if c else None for m, c in zip(mean, count)],
                            "occupied_share": [float(o) if c else None for o, c in zip(observed, count)],
                            "count": count.tolist()}}
