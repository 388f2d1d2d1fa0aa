"""Metrics: image (PSNR, SSIM), depth (L1, RMSE, relative), depth calibration, and a
held-out comparison of the model with the TSDF baseline on the same frames."""

from __future__ import annotations

import numpy as np
import torch

from .baselines import TSDFVolume
from .data.sequence import RGBDSequence


def psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images in [0, 1] (H, W, 3), over `mask` (H, W) pixels if given; inf if equal."""
    err = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2
    mse = err[mask].mean() if mask is not None else err.mean()
    return float("inf") if mse == 0 else float(-10 * np.log10(mse))


def ssim(pred: np.ndarray, target: np.ndarray, window: int = 11) -> float:
    """Mean SSIM (kornia) of images in [0, 1] (H, W, 3)."""
    from kornia.metrics import ssim as kornia_ssim

    to = lambda a: torch.as_tensor(np.asarray(a, np.float32)).permute(2, 0, 1)[None]  # noqa: E731
    return float(kornia_ssim(to(pred), to(target), window).mean())


def depth_errors(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """L1, RMSE (m) and mean relative error of z-depth maps over valid sensor pixels (gt > 0)."""
    mask = (gt > 0) & np.isfinite(pred) if valid is None else valid & (gt > 0)
    d = pred[mask] - gt[mask]
    if d.size == 0:
        return {"l1": float("nan"), "rmse": float("nan"), "rel": float("nan"), "pixels": 0}
    return {
        "l1": float(np.abs(d).mean()),
        "rmse": float(np.sqrt((d**2).mean())),
        "rel": float((np.abs(d) / gt[mask]).mean()),
        "pixels": int(mask.sum()),
    }


def depth_calibration(pred: np.ndarray, std: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """How well predicted depth sigmas explain the errors on valid pixels.

    within_k: fraction of |pred - gt| <= k * std for k = 1, 2, 3 (a calibrated Gaussian
    gives 0.683, 0.954, 0.997); nll: mean Gaussian negative log-likelihood (nats).
    """
    mask = (gt > 0) if valid is None else valid & (gt > 0)
    err = np.abs(pred[mask] - gt[mask])
    s = np.maximum(std[mask], 1e-6)
    if err.size == 0:
        return {"within_1": float("nan"), "within_2": float("nan"), "within_3": float("nan"), "nll": float("nan")}
    out = {f"within_{k}": float((err <= k * s).mean()) for k in (1, 2, 3)}
    out["nll"] = float(np.mean(0.5 * (err / s) ** 2 + np.log(s) + 0.5 * np.log(2 * np.pi)))
    return out


def heldout_scores(recon, sequence: RGBDSequence, tsdf: TSDFVolume | None = None, scale: float | None = None) -> dict:
    """Score a Reconstruction (and optionally a TSDF volume) on its held-out frames.

    Renders both at the held-out poses at the training resolution (or `scale` of the
    sequence) and compares with the frames' colour (on the depth grid) and sensor depth.
    Returns {"model": {...}, "tsdf": {...}} of means over held-out frames; TSDF colour is
    scored over all pixels and over the pixels its ray cast hits ("psnr_hits").
    """
    scale = scale or recon.config.image_scale
    seq = sequence.select(recon.holdout_indices)
    seq = seq.rescaled(seq.image_scale * scale)
    K, (h, w) = seq.K, seq.image_size
    rows: dict[str, list[dict]] = {"model": [], "tsdf": []}
    for k, i in enumerate(recon.holdout_indices):
        frame = seq[k]
        color = seq.color_on_depth_grid(frame.color) / 255.0
        out = recon.render(recon.poses[i], seq.intrinsic)
        rows["model"].append({
            "psnr": psnr(out["color"], color), "ssim": ssim(out["color"], color),
            **{f"depth_{m}": v for m, v in depth_errors(out["depth"], frame.depth).items()},
            **depth_calibration(out["depth"], out["depth_std"], frame.depth),
        })
        if tsdf is not None:
            t = tsdf.render(recon.poses[i], K, w, h)
            rows["tsdf"].append({
                "psnr": psnr(t["color"], color), "psnr_hits": psnr(t["color"], color, t["hit"]),
                "ssim": ssim(t["color"], color), "hit_fraction": float(t["hit"].mean()),
                **{f"depth_{m}": v for m, v in depth_errors(t["depth"], frame.depth, t["hit"]).items()},
            })
    return {name: _mean_rows(r) for name, r in rows.items() if r}


def _mean_rows(rows: list[dict]) -> dict:
    return {k: round(float(np.mean([r[k] for r in rows])), 5) for k in rows[0]}
