"""Metrics: image (PSNR, SSIM), depth (L1, RMSE, relative), depth calibration, geometry
against a reference surface, and a held-out comparison of the model with the TSDF
baseline on the same frames."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from .camera import pixel_coordinates
from .data.sequence import RGBDSequence, evenly_spaced
from .error_law import GAUSSIAN_SHARES, depth_nll, sigma_multiple
from .errors import InputError
from .tsdf import TSDFVolume

__all__ = ["GAUSSIAN_SHARES", "depth_calibration", "depth_errors", "depth_nll", "geometry_metrics", "heldout_renders",
           "heldout_scores", "mse_to_psnr", "psnr", "score_renders", "sigma_multiple", "ssim", "training_depth_errors"]


def mse_to_psnr(mse):
    """PSNR (dB) of a mean squared error of images in [0, 1]: a float (inf for 0), or a tensor
    (clamped at 100 dB, so that training statistics stay finite)."""
    if isinstance(mse, torch.Tensor):
        return -10 * torch.log10(mse.clamp(min=1e-10))
    return float("inf") if mse == 0 else float(-10 * np.log10(mse))


def psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images in [0, 1] (H, W, 3), over `mask` (H, W) pixels if given; inf if equal."""
    err = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2
    return mse_to_psnr(err[mask].mean() if mask is not None else err.mean())


def ssim(pred: np.ndarray, target: np.ndarray, window: int = 11) -> float:
    """Mean SSIM (kornia, Gaussian `window`) of images in [0, 1] (H, W, 3); images smaller than
    the window use the largest odd window that fits."""
    from kornia.metrics import ssim as kornia_ssim

    window = min(window, (min(np.shape(pred)[:2]) - 1) | 1)
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


def depth_calibration(pred: np.ndarray, std: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None,
                      dof: float = np.inf) -> dict:
    """How well predicted depth sigmas explain the errors on valid pixels.

    std: 1-sigma-equivalent errors (m) of the law with `dof` degrees of freedom (inf: a
    Gaussian; see :func:`~open3d_pnerf.error_law.sigma_multiple`). within_k: fraction of |pred - gt| inside the law's
    central interval that a Gaussian's k sigma would be (0.683, 0.954, 0.997 of it) for k =
    1, 2, 3: a calibrated law gives those shares; nll: its mean negative log-likelihood (nats).
    """
    mask = (gt > 0) if valid is None else valid & (gt > 0)
    err = np.abs(pred[mask] - gt[mask])
    s = np.maximum(std[mask], 1e-6)
    if err.size == 0:
        return {"within_1": float("nan"), "within_2": float("nan"), "within_3": float("nan"), "nll": float("nan")}
    multiple = {k: k if np.isinf(dof) else sigma_multiple(GAUSSIAN_SHARES[k], dof) for k in (1, 2, 3)}
    out = {f"within_{k}": float((err <= multiple[k] * s).mean()) for k in (1, 2, 3)}
    out["nll"] = float(np.mean(depth_nll(err, s, dof)))
    return out


def _surface_points(geometry, n_points: int, what: str) -> o3d.geometry.PointCloud:
    """Points on a legacy TriangleMesh (area-uniform samples) or the points of a PointCloud."""
    if isinstance(geometry, o3d.geometry.TriangleMesh):
        if not geometry.has_triangles():
            raise InputError(f"{what}: the mesh has no triangles")
        o3d.utility.random.seed(0)  # reproducible samples
        return geometry.sample_points_uniformly(n_points)
    if isinstance(geometry, o3d.geometry.PointCloud):
        if not geometry.has_points():
            raise InputError(f"{what}: the point cloud is empty")
        return geometry
    raise InputError(f"{what} must be an open3d.geometry.TriangleMesh or PointCloud, got {type(geometry).__name__}")


def _distances(points: o3d.geometry.PointCloud, to, to_points: o3d.geometry.PointCloud) -> np.ndarray:
    """Distance (m) from each point to the surface `to` (exact for meshes, nearest point otherwise)."""
    if isinstance(to, o3d.geometry.TriangleMesh):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(to))
        query = o3d.core.Tensor(np.asarray(points.points, np.float32))
        return scene.compute_distance(query).numpy().astype(np.float64)
    return np.asarray(points.compute_point_cloud_distance(to_points))


def geometry_metrics(pred, reference, thresholds=(0.02, 0.05), n_points: int = 200_000) -> dict:
    """Accuracy, completeness, Chamfer and F-score of a reconstructed surface (m).

    pred, reference: legacy ``o3d.geometry.TriangleMesh`` or ``PointCloud`` in the same
    world frame; meshes are sampled with `n_points` points. accuracy: mean distance from
    pred to reference; completeness: mean distance from reference to pred; chamfer: their
    mean; for each threshold t: precision_<t>, recall_<t>, fscore_<t> (t in mm in the key),
    the fractions within t and their harmonic mean.
    """
    pred_pts = _surface_points(pred, n_points, "pred")
    ref_pts = _surface_points(reference, n_points, "reference")
    d_pred = _distances(pred_pts, reference, ref_pts)
    d_ref = _distances(ref_pts, pred, pred_pts)
    out = {"accuracy": float(d_pred.mean()), "completeness": float(d_ref.mean())}
    out["chamfer"] = (out["accuracy"] + out["completeness"]) / 2
    for t in thresholds:
        p, r = float((d_pred <= t).mean()), float((d_ref <= t).mean())
        key = f"{t * 1000:g}mm"
        out.update({f"precision_{key}": p, f"recall_{key}": r, f"fscore_{key}": 2 * p * r / (p + r) if p + r else 0.0})
    return out


def heldout_renders(recon, sequence: RGBDSequence, tsdf: TSDFVolume | None = None, scale: float | None = None):
    """Yield, per held-out frame of a Reconstruction, the inputs and both renders.

    Renders at the training resolution (or `scale` of the sequence). Each item is a dict:
    index (frame), color (H, W, 3) in [0, 1] on the depth grid, depth (H, W) sensor z-depth
    m, model (Reconstruction.render output at the frame's own exposure), depth_dof (the
    degrees of freedom of its depth-error law), tsdf
    (TSDFVolume.render output or None).
    """
    scale = scale or recon.config.image_scale
    seq = sequence.select(recon.holdout_indices)
    seq = seq.scaled_by(scale)
    K, (h, w) = seq.K, seq.image_size
    for k, i in enumerate(recon.holdout_indices):
        frame = seq[k]
        yield {
            "index": int(i), "color": seq.color_on_depth_grid(frame.color) / 255.0, "depth": frame.depth,
            "model": recon.render(recon.poses[i], seq.intrinsic, frame=int(i)), "depth_dof": recon.depth_error.dof,
            "tsdf": None if tsdf is None else tsdf.render(recon.poses[i], K, w, h),
        }


def score_renders(renders) -> dict:
    """{"model": {...}, "tsdf": {...}}: means over frames of image, depth and calibration
    metrics (items as yielded by :func:`heldout_renders`). TSDF colour is scored over all
    pixels ("psnr") and over the pixels its ray cast hits ("psnr_hits"). Without sensor depth
    in any frame (image-only sequences) only image metrics are given."""
    renders = list(renders)
    with_depth = any(r["depth"].any() for r in renders)
    rows: dict[str, list[dict]] = {"model": [], "tsdf": []}
    for r in renders:
        color, depth, out, t = r["color"], r["depth"], r["model"], r["tsdf"]
        row = {"psnr": psnr(out["color"], color), "ssim": ssim(out["color"], color)}
        if with_depth:
            row.update({f"depth_{m}": v for m, v in depth_errors(out["depth"], depth).items()})
            row.update(depth_calibration(out["depth"], out["depth_std"], depth, dof=r.get("depth_dof", np.inf)))
        rows["model"].append(row)
        if t is not None:
            rows["tsdf"].append({
                "psnr": psnr(t["color"], color), "psnr_hits": psnr(t["color"], color, t["hit"]),
                "ssim": ssim(t["color"], color), "hit_fraction": float(t["hit"].mean()),
                **{f"depth_{m}": v for m, v in depth_errors(t["depth"], depth, t["hit"]).items()},
            })
    return {name: _mean_rows(r) for name, r in rows.items() if r}


def training_depth_errors(recon, sequence: RGBDSequence, frames: int = 8,
                          pixels: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(err, spread, z), each (M,) metres: a Reconstruction's depth errors against the sensor on
    its training frames, the raw spread of its depth distribution there (at least 1 um) and the
    sensor's z-depth. Up to `frames` training frames (evenly spaced) at the training resolution,
    `pixels` random pixels of each with sensor depth (drawn from config.seed + 2), kept where the
    model's opacity exceeds 0.5; held-out frames are never read."""
    train = recon.train_indices[evenly_spaced(len(recon.train_indices), frames)]
    seq = sequence.select(train).scaled_by(recon.config.image_scale)
    rng = np.random.default_rng(recon.config.seed + 2)
    errors, spreads, depths = [], [], []
    for k, i in enumerate(train):
        depth = seq[k].depth.reshape(-1)
        pix = rng.choice(np.flatnonzero(depth > 0), min(pixels, int((depth > 0).sum())), replace=False)
        u, v = (torch.as_tensor(c, dtype=torch.float32, device=recon.device)
                for c in pixel_coordinates(pix, seq.image_size[1]))
        out = recon.render_pixels(recon.poses[i], seq.intrinsic, u, v)
        ok = out["opacity"] > 0.5
        errors.append(np.abs(out["depth"] - depth[pix])[ok])
        spreads.append(np.maximum(out["depth_std"][ok], 1e-6))
        depths.append(depth[pix][ok])
    return tuple(np.concatenate(a) if a else np.zeros(0) for a in (errors, spreads, depths))


def heldout_scores(recon, sequence: RGBDSequence, tsdf: TSDFVolume | None = None, scale: float | None = None) -> dict:
    """Score a Reconstruction (and optionally a TSDF volume) on its held-out frames:
    :func:`score_renders` of :func:`heldout_renders`."""
    return score_renders(heldout_renders(recon, sequence, tsdf, scale))


def _mean_rows(rows: list[dict]) -> dict:
    """Per metric, the mean over the rows that have it."""
    keys = dict.fromkeys(k for r in rows for k in r)
    return {k: round(float(np.mean([r[k] for r in rows if k in r])), 5) for k in keys}
