"""Metrics on arrays: image (PSNR, SSIM), depth (L1, RMSE, relative), depth calibration (shares
within the error law's intervals, NLL, AUCE, AUSE), the coverage of sigmas, and geometry against a
reference surface (accuracy, completeness, F-score). :mod:`open3d_pnerf.evaluation` scores a
reconstruction with them."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from .error_law import GAUSSIAN_SHARES, depth_nll, sigma_multiple
from .errors import InputError


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


MIN_AUSE_PIXELS = 100  # an image with fewer scored pixels has no sparsification curve of 100 ratios
CALIBRATION_LEVELS = np.round(np.arange(0.05, 0.951, 0.05), 2)
"""The claimed shares over which :func:`auce` averages the calibration error (5, 10, ..., 95%)."""


def auce(err: np.ndarray, sigma: np.ndarray, dof: float = np.inf) -> float:
    """Area under the calibration error curve: the mean over p in CALIBRATION_LEVELS of |share of
    |err| inside the law's central p-interval - p|, for depth errors `err` (M,) m and
    1-sigma-equivalent `sigma` (M,) m of the law with `dof` degrees of freedom (inf: a Gaussian).
    0 for a calibrated law at every level; nan without errors."""
    err, sigma = np.abs(np.asarray(err, np.float64)), np.asarray(sigma, np.float64)
    if err.size == 0:
        return float("nan")
    return float(np.mean([abs(np.mean(err <= sigma_multiple(p, dof) * sigma) - p) for p in CALIBRATION_LEVELS]))


def sparsification(err: np.ndarray, order_by: np.ndarray, ratios: int = 100) -> dict:
    """The sparsification curves of errors `err` (M,) removed largest `order_by` first: {"rmse": (ratios,),
    "mae": (ratios,)}, the RMSE and MAE of what is left after removing the share k / ratios, k < ratios."""
    err = np.abs(np.asarray(err, np.float64))[np.argsort(np.asarray(order_by, np.float64), kind="stable")]
    kept = np.ceil(len(err) * (1 - np.arange(ratios) / ratios)).astype(int)  # the smallest-key pixels left
    squares, absolute = np.cumsum(err**2), np.cumsum(err)
    return {"rmse": np.sqrt(squares[kept - 1] / kept), "mae": absolute[kept - 1] / kept}


def ause(err: np.ndarray, sigma: np.ndarray, ratios: int = 100) -> dict:
    """Area under the sparsification error of one image (the Bayes' Rays protocol): pixels removed
    most uncertain first (`sigma` (M,)) against the oracle order (largest error `err` (M,) first), at
    `ratios` removal shares, both curves divided by their common maximum, the area between them
    over the removed share (trapezoids): {"ause_rmse", "ause_mae"}. 0 when sigma ranks the errors
    as they are; nan for an image without errors."""
    err = np.abs(np.asarray(err, np.float64))
    if err.size == 0:
        return {"ause_rmse": float("nan"), "ause_mae": float("nan")}
    by_sigma, oracle = sparsification(err, sigma, ratios), sparsification(err, err, ratios)
    share = np.arange(ratios) / ratios
    out = {}
    for metric in ("rmse", "mae"):
        top = max(by_sigma[metric].max(), oracle[metric].max())
        gap = (by_sigma[metric] - oracle[metric]) / top if top > 0 else np.zeros(ratios)
        out[f"ause_{metric}"] = float(np.sum((gap[1:] + gap[:-1]) / 2 * np.diff(share)))
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


def distances_to(points: o3d.geometry.PointCloud, to, to_points: o3d.geometry.PointCloud) -> np.ndarray:
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
    d_pred = distances_to(pred_pts, reference, ref_pts)
    d_ref = distances_to(ref_pts, pred, pred_pts)
    out = {"accuracy": float(d_pred.mean()), "completeness": float(d_ref.mean())}
    out["chamfer"] = (out["accuracy"] + out["completeness"]) / 2
    for t in thresholds:
        p, r = float((d_pred <= t).mean()), float((d_ref <= t).mean())
        key = f"{t * 1000:g}mm"
        out.update({f"precision_{key}": p, f"recall_{key}": r, f"fscore_{key}": 2 * p * r / (p + r) if p + r else 0.0})
    return out


def sigma_coverage(err: np.ndarray, sigma: np.ndarray) -> dict:
    """Shares of errors `err` (any shape, m) inside k `sigma` (the same shape, m), k = 1, 2, 3, as
    within_1..3 (a Gaussian sigma claims 0.683, 0.954, 0.997), and their count; nan without errors."""
    err, sigma = np.abs(np.asarray(err, np.float64)).ravel(), np.asarray(sigma, np.float64).ravel()
    shares = {f"within_{k}": float(np.mean(err <= k * sigma)) if err.size else float("nan") for k in (1, 2, 3)}
    return {**shares, "count": int(err.size)}
