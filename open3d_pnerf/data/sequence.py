"""The sequence model: lazily loaded frames, one depth intrinsic, optional ground truth, and
for image-only sequences their structure from motion.

Inside the library depth is z-depth in metres (float32, 0 = invalid) and colour is uint8
(H, W, 3) RGB. Poses are camera-to-world 4x4 float64 in metres, OpenCV camera axes.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import cv2
import numpy as np
import open3d as o3d

from ..camera import check_intrinsic, check_poses, intrinsic_matrix, missing_poses, scale_intrinsic
from ..errors import DatasetError, InputError
from .color_registration import ColorRig
from .images import FrameReader, memory_readers
from .sfm import SfMData

MEDIAN_DEPTH_LIMIT = 20.0  # metres: an indoor RGB-D median beyond this means a wrong depth scale


@dataclasses.dataclass
class Frame:
    """One RGB-D frame: colour (H, W, 3) uint8 RGB, depth (H, W) float32 metres, 0 = invalid
    (all zero in a sequence without depth images)."""

    color: np.ndarray
    depth: np.ndarray
    timestamp: float
    index: int


class RGBDSequence:
    """A lazily loaded sequence of colour frames with depth images (or, for image-only
    sequences, with structure from motion instead).

    Frames are read from their source only when indexed, so a 2,000-frame sequence never
    sits in memory at once. ``seq[i]`` gives a :class:`Frame`; ``seq.intrinsic`` is the
    depth camera's ``o3d.camera.PinholeCameraIntrinsic`` (colour is registered to it unless
    ``color_intrinsic`` and ``color_extrinsic`` say otherwise); ``seq.gt_poses`` is (N, 4, 4) camera-to-world or None,
    with NaN rows for frames the ground truth does not cover (``seq.gt_valid`` says which have it).
    has_depth: False for image-only sequences (their frames' depth is all zero); those carry
    ``sfm`` (:class:`~open3d_pnerf.data.sfm.SfMData`: poses, covariances, sparse points).
    color_extrinsic: (4, 4) rigid transform from depth-camera to colour-camera coordinates (m) of
    a rig whose colour camera sits apart from its depth camera (None: they share a centre); the
    colour is then registered to each depth pixel through that pixel's depth.
    """

    def __init__(
        self,
        readers: Sequence[FrameReader],
        intrinsic: o3d.camera.PinholeCameraIntrinsic,
        timestamps: Sequence[float] | None = None,
        gt_poses: np.ndarray | None = None,
        depth_trunc: float = 0.0,
        color_intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None,
        name: str = "sequence",
        image_scale: float = 1.0,
        has_depth: bool = True,
        sfm: SfMData | None = None,
        color_extrinsic: np.ndarray | None = None,
    ):
        self._readers = list(readers)
        if not self._readers:
            raise InputError(f"{name}: the sequence has no frames")
        self._base_intrinsic = check_intrinsic(intrinsic)
        self._base_color_intrinsic = (
            check_intrinsic(color_intrinsic, "color_intrinsic") if color_intrinsic else None
        )
        self.color_extrinsic = None if color_extrinsic is None else check_poses(
            np.asarray(color_extrinsic, np.float64)[None], 1, f"{name}: color_extrinsic")[0]
        n = len(self._readers)
        self.timestamps = (
            np.arange(n, dtype=np.float64)
            if timestamps is None
            else np.asarray(timestamps, dtype=np.float64)
        )
        if self.timestamps.shape != (n,):
            raise InputError(f"{name}: {len(self.timestamps)} timestamps for {n} frames")
        self.gt_poses = None if gt_poses is None else check_poses(gt_poses, n, f"{name}: gt_poses",
                                                                  allow_missing=True)
        if depth_trunc < 0:
            raise InputError(f"depth_trunc must be >= 0 metres (0 = no truncation), got {depth_trunc}")
        if not (0 < image_scale <= 1):
            raise InputError(f"image_scale must be in (0, 1], got {image_scale}")
        if not has_depth and sfm is None:
            raise InputError(f"{name}: a sequence without depth images needs its structure from motion (sfm=)")
        self.depth_trunc = float(depth_trunc)
        self.image_scale = float(image_scale)
        self.name = name
        self.has_depth = bool(has_depth)
        self._base_sfm = None if sfm is None else sfm.check(n, name)

    # -- geometry ---------------------------------------------------------------------
    @property
    def intrinsic(self) -> o3d.camera.PinholeCameraIntrinsic:
        """Depth-camera intrinsic at the sequence's image scale."""
        return scale_intrinsic(self._base_intrinsic, self.image_scale)

    @property
    def color_intrinsic(self) -> o3d.camera.PinholeCameraIntrinsic:
        """Colour intrinsic at the sequence's image scale (the depth one when registered)."""
        base = self._base_color_intrinsic or self._base_intrinsic
        return scale_intrinsic(base, self.image_scale)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 depth intrinsic matrix at the sequence's image scale."""
        return intrinsic_matrix(self.intrinsic)

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the frames as returned by indexing."""
        return self.intrinsic.height, self.intrinsic.width

    @property
    def gt_valid(self) -> np.ndarray | None:
        """(N,) bool: the frames with a ground-truth pose (None without ground truth)."""
        return None if self.gt_poses is None else ~missing_poses(self.gt_poses)

    @property
    def sfm(self) -> SfMData | None:
        """The structure from motion of an image-only sequence (None for RGB-D), with
        reprojection errors in pixels at the sequence's image scale."""
        if self._base_sfm is None:
            return None
        return self._base_sfm.at_pixel_scale(self.intrinsic.width / self._base_intrinsic.width)

    # -- container protocol -----------------------------------------------------------
    def __len__(self) -> int:
        return len(self._readers)

    def __getitem__(self, index: int | slice) -> Frame | "RGBDSequence":
        """Frame `index`, or for a slice (``seq[10:40:2]``) the sub-sequence of those frames."""
        n = len(self)
        if isinstance(index, slice):
            return self.select(np.arange(n)[index])
        if not isinstance(index, (int, np.integer)):
            raise InputError(f"frame index must be an int or a slice, got {type(index).__name__}; use .select()")
        if not -n <= index < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        index = int(index) % n
        color, depth = self._readers[index]()
        return Frame(*self._finish(color, depth, self._describe(index)), float(self.timestamps[index]), index)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        h, w = self.image_size
        if not self.has_depth:
            return f"RGBDSequence({self.name!r}, {len(self)} images, {w}x{h}, no depth, {len(self.sfm.points)} SfM points)"
        if self.gt_poses is None:
            gt = "without GT poses"
        else:
            covered = int(self.gt_valid.sum())
            gt = "with GT poses" if covered == len(self) else f"with GT poses for {covered} of them"
        return f"RGBDSequence({self.name!r}, {len(self)} frames, {w}x{h}, {gt})"

    def _describe(self, index: int) -> str:
        """'<name> frame <i> (<source>)': the files (or images[i]) the frame comes from."""
        source = getattr(self._readers[index], "source", None)
        return f"{self.name} frame {index}" + (f" ({source})" if source else "")

    def _finish(self, color, depth, where: str):
        """Validate a raw frame, apply colour registration size, truncation and scale."""
        color = np.asarray(color)
        depth = np.asarray(depth)
        if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
            raise DatasetError(f"{where}: colour must be uint8 (H, W, 3), got {color.dtype} {color.shape}")
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise DatasetError(f"{where}: depth must be float (H, W) metres, got {depth.dtype} {depth.shape}")
        base = self._base_intrinsic
        if depth.shape != (base.height, base.width):
            raise DatasetError(
                f"{where}: depth is {depth.shape[1]}x{depth.shape[0]} but the intrinsic is "
                f"{base.width}x{base.height}"
            )
        color_base = self._base_color_intrinsic or base
        if color.shape[:2] != (color_base.height, color_base.width):
            raise DatasetError(
                f"{where}: colour is {color.shape[1]}x{color.shape[0]} but depth/intrinsic is "
                f"{color_base.width}x{color_base.height}"
            )
        depth = depth.astype(np.float32, copy=True)
        bad = ~np.isfinite(depth) | (depth < 0)
        if bad.any():
            raise DatasetError(
                f"{where}: depth has {bad.sum()} NaN/inf or negative values; depth must be >= 0 metres "
                "(0 marks missing depth)"
            )
        if self.depth_trunc > 0:
            depth[depth > self.depth_trunc] = 0
        if self.image_scale != 1.0:
            h, w = self.image_size
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
            ch, cw = self.color_intrinsic.height, self.color_intrinsic.width
            color = cv2.resize(color, (cw, ch), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(color), depth

    # -- derived sequences --------------------------------------------------------------
    def _derive(self, idx: np.ndarray, image_scale: float) -> "RGBDSequence":
        """The sequence of frames `idx` (indices into this one) at `image_scale`."""
        return RGBDSequence(
            [self._readers[i] for i in idx],
            self._base_intrinsic,
            self.timestamps[idx],
            None if self.gt_poses is None else self.gt_poses[idx],
            self.depth_trunc,
            self._base_color_intrinsic,
            self.name,
            image_scale,
            self.has_depth,
            None if self._base_sfm is None else self._base_sfm.select(idx),
            self.color_extrinsic,
        )

    def select(self, indices) -> "RGBDSequence":
        """Sub-sequence of the given frame indices (a list, range or boolean mask)."""
        sel = np.asarray(indices)
        if sel.size == 0:
            raise InputError(f"select(): no frames selected from {self.name}")
        try:
            idx = np.atleast_1d(np.arange(len(self))[sel if sel.dtype == bool else sel.astype(np.intp)])
        except (IndexError, ValueError, TypeError) as exc:
            raise InputError(f"select(): bad frame indices for {len(self)} frames of {self.name} ({exc})") from None
        if idx.size == 0:
            raise InputError(f"select(): no frames selected from {self.name}")
        return self._derive(idx, self.image_scale)

    def at_scale(self, image_scale: float) -> "RGBDSequence":
        """The same frames at `image_scale` (in (0, 1]) of the source images' size."""
        return self._derive(np.arange(len(self)), image_scale)

    def scaled_by(self, factor: float) -> "RGBDSequence":
        """The same frames resized by `factor` relative to this sequence's current size."""
        return self.at_scale(self.image_scale * factor)

    def to_open3d(self, index: int) -> o3d.geometry.RGBDImage:
        """Frame `index` as an ``o3d.geometry.RGBDImage`` (depth float metres, colour uint8).

        The colour is resampled onto the depth grid when the two cameras differ.
        """
        frame = self[index]
        color = self.color_on_depth_grid(frame.color, frame.depth)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(color),
            o3d.geometry.Image(frame.depth),
            depth_scale=1.0,
            depth_trunc=self.depth_trunc or 1e6,
            convert_rgb_to_intensity=False,
        )

    @property
    def color_registered(self) -> bool:
        """Whether the colour images are registered to the depth (same camera, pixel for pixel)."""
        same_intrinsic = self._base_color_intrinsic is None or np.allclose(
            self._base_color_intrinsic.intrinsic_matrix, self._base_intrinsic.intrinsic_matrix)
        return same_intrinsic and np.allclose(self._color_rig, np.eye(4))

    def color_on_depth_grid(self, color: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """Resample a colour image (H_c, W_c, 3) onto the depth image's pixel grid (identity if
        registered; see :meth:`~open3d_pnerf.data.color_registration.ColorRig.resample`). depth: the
        frame's depth (H, W) m, needed when the sequence's ``color_extrinsic`` moves the colour
        camera's centre."""
        if self.color_registered:
            return color
        return self._rig.resample(color, depth, self.name)

    @property
    def _color_rig(self) -> np.ndarray:
        """(4, 4) depth-camera to colour-camera transform (the identity without color_extrinsic)."""
        return np.eye(4) if self.color_extrinsic is None else self.color_extrinsic

    @functools.cached_property
    def _rig(self) -> ColorRig:
        """The colour camera against the depth grid (its maps computed once per sequence, not on every
        frame load)."""
        return ColorRig(self.K, intrinsic_matrix(self.color_intrinsic), self._color_rig, self.image_size)

    # -- construction from memory -------------------------------------------------------
    @classmethod
    def from_rgbd_images(
        cls,
        images: Sequence,
        intrinsic: o3d.camera.PinholeCameraIntrinsic,
        timestamps: Sequence[float] | None = None,
        gt_poses: np.ndarray | None = None,
        depth_scale: float = 1.0,
        depth_trunc: float = 0.0,
        name: str = "in-memory",
    ) -> "RGBDSequence":
        """Sequence from in-memory frames.

        images: list of ``o3d.geometry.RGBDImage`` (depth in metres, as made by
        ``create_from_color_and_depth(..., depth_scale=...)``) or of ``(color, depth)`` numpy
        pairs: colour uint8 (H, W, 3), depth uint16 (divided by `depth_scale`) or float32/64
        metres. intrinsic: the depth camera's ``o3d.camera.PinholeCameraIntrinsic``.
        The frames are in memory, so all are checked here (not when first used).
        """
        readers = memory_readers(images, depth_scale)
        seq = cls(readers, intrinsic, timestamps, gt_poses, depth_trunc, name=name)
        for i in range(1, len(seq)):
            seq[i]  # validates the frame
        check_first_frame(seq)
        return seq


def check_sequence(sequence, min_frames: int = 1, what: str = "sequence", needs_depth: bool = False) -> RGBDSequence:
    """Return `sequence` if it is an RGBDSequence of at least `min_frames` frames (with depth
    images if `needs_depth`)."""
    if not isinstance(sequence, RGBDSequence):
        raise InputError(f"{what} must be an RGBDSequence (see load_sequence), got {type(sequence).__name__}")
    if len(sequence) < min_frames:
        raise InputError(f"{what} has {len(sequence)} frame(s); at least {min_frames} frames are needed")
    if needs_depth and not sequence.has_depth:
        raise InputError(f"{what}: {sequence.name} has no depth images (an image-only sequence); this needs "
                         "RGB-D frames. Its camera poses come from SfM: sequence.sfm.poses")
    return sequence


def check_first_frame(seq: RGBDSequence) -> None:
    """Load frame 0 to fail early on mismatched sizes, empty depth or a wrong depth scale."""
    depth = seq[0].depth
    valid = depth[depth > 0]
    if valid.size == 0:
        raise DatasetError(f"{seq._describe(0)}: no valid depth (all zero)")
    median = float(np.median(valid))
    if median > MEDIAN_DEPTH_LIMIT or median < 0.05:
        raise DatasetError(
            f"{seq._describe(0)}: median depth is {median:.3g} m, implausible for an RGB-D camera; "
            "the depth scale is probably wrong (TUM uses 5000, 7-Scenes/Redwood 1000 raw units per "
            "metre): pass depth_scale="
        )
