"""Per-pixel fusion of two depth estimates: the sensor's measured depth and the model's rendered
depth, each with its error law (a 1-sigma equivalent and degrees of freedom: a Gaussian or the
model's Student-t, :mod:`open3d_pnerf.error_law`), before surfaces are extracted (export).

Where both exist and agree, they are weighted by their inverse variances (the best linear
combination; a Student-t's variance is wider than its 1-sigma equivalent, and an estimate whose
variance does not exist, dof <= 2, gets no weight) and the fused sigma narrows; where only one
exists (the sensor saw nothing there, or the model is not confident) that one is kept as it is;
where they disagree beyond what their laws allow (an outlier, a floater, an occlusion edge one
of them blurs), averaging would put the surface where neither saw it, so the more certain one
is kept. The gate rejects at most `reject` of consistent pairs, whatever the two laws' tails.
"""

from __future__ import annotations

import cv2
import numpy as np

from .error_law import standard_deviation, standardized_multiple
from .errors import InputError

GATE_REJECT = 0.0027
"""Share of consistent pairs the fusion's gate may take for disagreeing: a Gaussian pair's 3 sigma."""


def consistent(mean_a, sd_a, mean_b, sd_b, dof: float = np.inf, reject: float = GATE_REJECT) -> np.ndarray:
    """Where two estimates agree: |a - b| <= k * sqrt(sd_a^2 + sd_b^2), their standard deviations
    (inf: always agrees), k the standardized multiple of the heavier-tailed law (`dof`, the smaller
    of the two; inf: both Gaussian) that holds 1 - `reject`. The difference of a Student-t and a
    Gaussian error has lighter tails than the Student-t alone, so at most `reject` of consistent
    pairs fail (tests/test_fusion.py draws them). All arrays broadcast to one shape."""
    if not 0 < reject < 1:
        raise InputError(f"reject must be in (0, 1) (a share of consistent pairs), got {reject!r}")
    k = standardized_multiple(1 - reject, dof) if dof > 2 else np.inf
    with np.errstate(invalid="ignore"):
        return np.abs(np.asarray(mean_a) - mean_b) <= k * np.hypot(sd_a, sd_b)


def fuse_depths(mean_a, sigma_a, mean_b, sigma_b, dof_a: float = np.inf, dof_b: float = np.inf,
                reject: float = GATE_REJECT) -> tuple[np.ndarray, np.ndarray]:
    """Fuse two depth estimates element by element.

    Estimate a: means `mean_a`, 1-sigma equivalents `sigma_a` of a law with `dof_a` degrees of
    freedom (inf: a Gaussian); b likewise. All broadcast to one shape (any units, the same for
    all). An estimate is missing where its mean is not finite or its sigma is not a finite number
    > 0. Returns (mean, sigma): where both exist and are :func:`consistent`, the inverse-variance
    weighted mean and its standard deviation (1 / wa + 1 / wb)^-1/2 (w = 1 / sd^2, 0 for an infinite
    variance); the estimate with the smaller standard deviation where both exist but disagree; the
    one that exists where only one does (with its own sigma); NaN (both) where neither does.
    """
    a, sa, b, sb = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (mean_a, sigma_a, mean_b, sigma_b)))
    has_a = np.isfinite(a) & np.isfinite(sa) & (sa > 0)
    has_b = np.isfinite(b) & np.isfinite(sb) & (sb > 0)
    da, db = standard_deviation(np.where(has_a, sa, 1.0), dof_a), standard_deviation(np.where(has_b, sb, 1.0), dof_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        wa, wb = np.where(has_a, 1 / da**2, 0.0), np.where(has_b, 1 / db**2, 0.0)
        fused = (np.where(wa > 0, a, 0) * wa + np.where(wb > 0, b, 0) * wb) / (wa + wb)
        fused_sigma = 1 / np.sqrt(wa + wb)
    agree = consistent(a, da, b, db, min(dof_a, dof_b), reject)
    a_better = da <= db
    both = has_a & has_b
    take_a = (has_a & ~has_b) | (both & ~agree & a_better)
    take_b = (has_b & ~has_a) | (both & ~agree & ~a_better)
    mean = np.where(take_a, a, np.where(take_b, b, np.where(both, fused, np.nan)))
    sigma = np.where(take_a, sa, np.where(take_b, sb, np.where(both, fused_sigma, np.nan)))
    return mean, sigma


def fuse_render_with_sensor(render: dict, depth: np.ndarray, depth_sigma: np.ndarray, min_opacity: float,
                            max_std: float, dof: float = np.inf) -> dict:
    """A render's depth fused per pixel with the sensor's (:func:`fuse_depths`).

    render: color (h, w, 3), depth and depth_std (h, w) z metres, opacity (h, w) (as
    :meth:`Reconstruction.render` returns; depth_std the 1-sigma equivalent of a law with `dof`
    degrees of freedom, the reconstruction's depth_sigma_dof); its depth counts where opacity >=
    min_opacity and depth_std <= max_std. depth: (H, W) sensor z-depth metres (0 = none); depth_sigma:
    its (H, W) Gaussian sigma (m). A render smaller than the sensor's image (the same camera at a
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
    mean, sigma = fuse_depths(np.where(confident, render["depth"], np.nan), render["depth_std"],
                              np.where(depth > 0, depth, np.nan), depth_sigma, dof_a=dof)
    has = np.isfinite(mean)
    return {**render, "depth": np.where(has, mean, 0).astype(np.float32),
            "depth_std": np.where(has, sigma, np.inf).astype(np.float32), "opacity": has.astype(np.float32)}


def nearest_upsample(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`image` (h, w) or (h, w, C <= 4) at `size` (H, W) >= (h, w) by nearest pixel centre: pixel
    (u, v) takes the pixel of the small image whose centre is nearest to its own (pixel centres
    at integer coordinates, as :func:`~open3d_pnerf.camera.scale_intrinsic` scales an intrinsic;
    OpenCV's INTER_NEAREST_EXACT, not INTER_NEAREST, which is off by up to half a pixel)."""
    return cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_NEAREST_EXACT)
