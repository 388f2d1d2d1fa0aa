"""The scene's extent: the axis-aligned box a field covers, and the depth range of image-only scenes.

An RGB-D scene's box holds the cameras and the depth targets' surfaces; an image-only scene with
structure-from-motion bounds (LLFF) has every ray clipped to a z-depth range, and its box holds
the camera frusta over that range.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from .camera import backproject, camera_rays
from .data.sequence import RGBDSequence
from .errors import InputError
from .fields.ndc import NDCWarp
from .targets import DepthTargets

BOX_MARGIN = 0.05  # m: what scene_box adds on every side beyond its relative padding
BOX_PERCENTILE = 0.01  # %: the share of target points scene_box may leave out on each side of each axis
NEAR_MARGIN = 0.9  # depth_range's near plane: 0.9 x the nearest SfM bound, as DS-NeRF (no NDC) and NeRF's LLFF loader


def scene_box(targets: DepthTargets, poses: np.ndarray, K: np.ndarray, pad: float = 0.1, stride: int = 4) -> np.ndarray:
    """(2, 3) axis-aligned box (m) holding the camera centres and the targets' surface points.

    Uses the BOX_PERCENTILE and 100 - BOX_PERCENTILE percentiles of the back-projected target
    depths (every `stride`-th pixel), which ignore a few stray points but keep every surface the
    sensor saw (a surface outside the box cannot be rendered: its rays end at the box), then pads
    by `pad` times the size plus BOX_MARGIN.
    """
    pts = [poses[:, :3, 3]]
    for i in range(len(targets)):
        valid = np.zeros_like(targets.valid[i])
        valid[::stride, ::stride] = targets.valid[i][::stride, ::stride]
        pts.append(backproject(targets.mean[i], K, poses[i], valid)[0])
    pts = np.concatenate(pts)
    lo, hi = np.percentile(pts, BOX_PERCENTILE, axis=0), np.percentile(pts, 100 - BOX_PERCENTILE, axis=0)
    lo, hi = np.minimum(lo, poses[:, :3, 3].min(0)), np.maximum(hi, poses[:, :3, 3].max(0))
    margin = pad * (hi - lo) + BOX_MARGIN
    return np.stack([lo - margin, hi + margin]).astype(np.float32)


def frustum_corners(K: np.ndarray, image_size: tuple[int, int], poses: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(8 N, 3) world corners of each camera's view frustum between its near and far z-depth
    bounds (N, 2); K (3, 3), image_size (H, W), poses (N, 4, 4) camera-to-world."""
    h, w = image_size
    rays = camera_rays(K, np.array([-0.5, w - 0.5, -0.5, w - 0.5]), np.array([-0.5, -0.5, h - 0.5, h - 0.5]))
    pts = [(rays[None] * z[:, None, None]) @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
           for z in np.asarray(bounds).T]
    return np.concatenate(pts).reshape(-1, 3)


def frustum_box(K: np.ndarray, image_size: tuple[int, int], poses: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(2, 3) axis-aligned box holding each camera's view frustum between its near and far
    z-depth bounds (N, 2); K (3, 3), image_size (H, W), poses (N, 4, 4) camera-to-world."""
    pts = frustum_corners(K, image_size, poses, bounds)
    return np.stack([pts.min(0), pts.max(0)]).astype(np.float32)


def depth_range(sequence: RGBDSequence) -> np.ndarray | None:
    """(2,) z-depth [near, far] for every ray of an image-only sequence with SfM bounds:
    [0.9 x the frames' smallest near bound, their largest far bound]; None otherwise."""
    if sequence.has_depth or sequence.sfm is None or sequence.sfm.bounds is None:
        return None
    bounds = sequence.sfm.bounds
    return np.array([NEAR_MARGIN * bounds[:, 0].min(), bounds[:, 1].max()])


def training_box(train_seq: RGBDSequence, targets: DepthTargets, poses: np.ndarray) -> np.ndarray:
    """(2, 3) scene box of the training frames: around their targets' surfaces and cameras; for an
    image-only sequence with SfM bounds, the camera frusta within :func:`depth_range` (so no ray
    leaves the box before its far bound)."""
    rng = depth_range(train_seq)
    if rng is None:
        return scene_box(targets, poses, train_seq.K)
    if not targets.valid.any():
        warnings.warn(f"{train_seq.name}: no SfM point gives a depth target in the training views")
    return frustum_box(train_seq.K, train_seq.image_size, poses, np.tile(rng, (len(poses), 1)))


def ndc_depth_range(sequence: RGBDSequence, mode: str) -> np.ndarray | None:
    """:func:`depth_range` where the ndc setting `mode` may give NDC, None where it cannot ("off",
    or "auto" without SfM bounds); an InputError for "on" without SfM bounds (checked before any work)."""
    rng = None if mode == "off" else depth_range(sequence)
    if rng is None and mode == "on":
        raise InputError(f"{sequence.name}: ndc='on' needs an image-only sequence with SfM depth bounds "
                         "(an LLFF folder's poses_bounds.npy)")
    return rng


def ndc_warp(train_seq: RGBDSequence, poses: np.ndarray, mode: str = "auto") -> NDCWarp | None:
    """The field's NDC warp (fields.ndc) for training frames with poses (N, 4, 4), or None.

    mode "auto": NDC for a forward-facing image-only sequence with SfM bounds (LLFF), None for
    others; "on": NDC, an InputError without SfM bounds or where a frame's frustum reaches behind
    the reference camera (not a forward-facing capture); "off": None. The reference camera sits
    at the frames' mean centre with their mean orientation (as NeRF's LLFF loader recentres), NDC
    near at :func:`depth_range`'s near, and the box holds every frame's frustum over that range."""
    rng = ndc_depth_range(train_seq, mode)
    if rng is None:
        return None
    poses = np.asarray(poses, np.float64)
    reference = np.eye(4)
    reference[:3, :3] = Rotation.from_matrix(poses[:, :3, :3]).mean().as_matrix()  # the chordal mean
    reference[:3, 3] = poses[:, :3, 3].mean(0)
    corners = frustum_corners(train_seq.K, train_seq.image_size, poses, np.tile(rng, (len(poses), 1)))
    if ((corners - reference[:3, 3]) @ reference[:3, 2] <= 0.1 * rng[0]).any():
        if mode == "auto":
            return None
        raise InputError(f"{train_seq.name}: its frames' views reach behind their mean camera, so it is not a "
                         "forward-facing capture; set ndc='off'")
    return NDCWarp.around(reference, train_seq.K, train_seq.image_size, float(rng[0]), corners)
