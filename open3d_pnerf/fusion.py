"""Per-pixel fusion of two Gaussian depth estimates: the sensor's measured depth and the
model's rendered depth, each with its sigma, before surfaces are extracted (export).

Where both exist and agree, the product of the two Gaussians (inverse-variance weighting)
keeps the more certain one's accuracy and narrows the sigma; where only one exists (the
sensor saw nothing there, or the model is not confident) that one is kept as it is; where
they disagree beyond what their sigmas allow (an outlier, a floater, an occlusion edge one of
them blurs), averaging would put the surface where neither saw it, so the more certain one
is kept.
"""

from __future__ import annotations

import cv2
import numpy as np

from .errors import InputError


def fuse_gaussians(mean_a, sigma_a, mean_b, sigma_b, gate: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Fuse N(mean_a, sigma_a^2) and N(mean_b, sigma_b^2) element by element.

    All inputs broadcast to one shape (any units, the same for all). An estimate is missing
    where its mean is not finite or its sigma is not a finite number > 0. Returns (mean,
    sigma): mean = (a / sa^2 + b / sb^2) / (1 / sa^2 + 1 / sb^2) and sigma = (1 / sa^2 +
    1 / sb^2)^-1/2 where both exist and |a - b| <= gate * sqrt(sa^2 + sb^2); the estimate with
    the smaller sigma where both exist but disagree by more; the one that exists where only one
    does; NaN (both) where neither does.
    """
    if not gate > 0:
        raise InputError(f"gate must be > 0 (sigmas of disagreement), got {gate!r}")
    a, sa, b, sb = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (mean_a, sigma_a, mean_b, sigma_b)))
    has_a = np.isfinite(a) & np.isfinite(sa) & (sa > 0)
    has_b = np.isfinite(b) & np.isfinite(sb) & (sb > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        wa, wb = np.where(has_a, 1 / sa**2, 0.0), np.where(has_b, 1 / sb**2, 0.0)
        fused = (np.where(has_a, a, 0) * wa + np.where(has_b, b, 0) * wb) / (wa + wb)
        fused_sigma = 1 / np.sqrt(wa + wb)
        agree = np.abs(a - b) <= gate * np.sqrt(sa**2 + sb**2)
    a_better = sa <= sb
    both = has_a & has_b
    take_a = (has_a & ~has_b) | (both & ~agree & a_better)
    take_b = (has_b & ~has_a) | (both & ~agree & ~a_better)
    mean = np.where(take_a, a, np.where(take_b, b, np.where(both, fused, np.nan)))
    sigma = np.where(take_a, sa, np.where(take_b, sb, np.where(both, fused_sigma, np.nan)))
    return mean, sigma


def fuse_render_with_sensor(render: dict, depth: np.ndarray, depth_sigma: np.ndarray, min_opacity: float,
                            max_std: float) -> dict:
    """A render's depth fused per pixel with the sensor's (:func:`fuse_gaussians`).

    render: color (h, w, 3), depth and depth_std (h, w) z metres, opacity (h, w) (as
    :meth:`Reconstruction.render` returns); its depth counts where opacity >= min_opacity
    and depth_std <= max_std. depth: (H, W) sensor z-depth metres (0 = none); depth_sigma:
    its (H, W) sigma (m). A render smaller than the sensor's image (the same camera at a
    lower resolution, h <= H and w <= W) is first brought to (H, W) by :func:`nearest_upsample`:
    the sensor keeps its resolution and the model fills its holes. Returns a new dict at
    (H, W) with the fused depth and depth_std (0 and inf where neither has one) and opacity
    1 where the fused depth exists, 0 elsewhere; colour as rendered.
    """
    (h, w), (H, W) = render["depth"].shape, depth.shape
    if depth_sigma.shape != depth.shape or h > H or w > W:
        raise InputError(f"sensor depth {depth.shape} and sigma {depth_sigma.shape} must match, and the render "
                         f"{render['depth'].shape} must not be larger")
    render = {k: nearest_upsample(v, (H, W)) if isinstance(v, np.ndarray) and v.shape[:2] == (h, w) else v
              for k, v in render.items()}
    confident = (render["opacity"] >= min_opacity) & (render["depth_std"] <= max_std)
    mean, sigma = fuse_gaussians(np.where(confident, render["depth"], np.nan), render["depth_std"],
                                 np.where(depth > 0, depth, np.nan), depth_sigma)
    has = np.isfinite(mean)
    return {**render, "depth": np.where(has, mean, 0).astype(np.float32),
            "depth_std": np.where(has, sigma, np.inf).astype(np.float32), "opacity": has.astype(np.float32)}


def nearest_upsample(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`image` (h, w) or (h, w, C <= 4) at `size` (H, W) >= (h, w) by nearest pixel centre: pixel
    (u, v) takes the pixel of the small image whose centre is nearest to its own (pixel centres
    at integer coordinates, as :func:`~open3d_pnerf.camera.scale_intrinsic` scales an intrinsic;
    OpenCV's INTER_NEAREST_EXACT, not INTER_NEAREST, which is off by up to half a pixel)."""
    return cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_NEAREST_EXACT)
