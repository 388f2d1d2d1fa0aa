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
from scipy import ndimage

from ..camera import check_intrinsic, check_poses, intrinsic_matrix, missing_poses, reproject_depth, scale_intrinsic
from ..errors import DatasetError, InputError
from .images import FrameReader, constant_reader, depth_in_metres
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
        """Resample a colour image (H_c, W_c, 3) onto the depth image's pixel grid (identity if registered).

        depth: the frame's depth (H, W) m, needed when the sequence's ``color_extrinsic`` moves the
        colour camera's centre: each depth pixel then takes the colour where its point projects in
        the colour camera (pixels without depth, or beyond ``depth_trunc``, take the depth of the
        nearest pixel with it; a frame without any, the plane at infinity). Occlusion is not tested:
        a point the colour camera cannot see takes the colour of what hides it. When the two cameras
        share a centre the depth is not needed.
        """
        if self.color_registered:
            return color
        translation = self._color_rig[:3, 3]
        if not translation.any():
            return cv2.remap(color, *self._plane_maps, cv2.INTER_LINEAR)
        if depth is None:
            raise InputError(f"{self.name}: color_on_depth_grid() needs the frame's depth: its colour camera "
                             "is offset from the depth camera (color_extrinsic)")
        depth = np.asarray(depth)
        h, w = self.image_size
        if depth.shape != (h, w):
            raise InputError(f"{self.name}: color_on_depth_grid() got depth {depth.shape[1]}x{depth.shape[0]}, "
                             f"expected the depth grid's {w}x{h}")
        if not (depth > 0).any():
            return cv2.remap(color, *self._plane_maps, cv2.INTER_LINEAR)
        nearest = ndimage.distance_transform_edt(depth <= 0, return_distances=False, return_indices=True)
        offset = translation / depth[tuple(nearest)][..., None]  # the camera's offset over each point's z
        return cv2.remap(color, *self._color_maps(offset), cv2.INTER_LINEAR)

    @property
    def _color_rig(self) -> np.ndarray:
        """(4, 4) depth-camera to colour-camera transform (the identity without color_extrinsic)."""
        return np.eye(4) if self.color_extrinsic is None else self.color_extrinsic

    def _color_maps(self, offset) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y) float32 (H, W): where each depth pixel's point lands in the colour image,
        the point being its ray at z = 1 turned into the colour camera plus `offset` ((3,) or
        (H, W, 3): the colour camera's offset over the point's depth-camera z)."""
        kd, kc = self.K, intrinsic_matrix(self.color_intrinsic)
        h, w = self.image_size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays = np.stack([(u - kd[0, 2]) / kd[0, 0], (v - kd[1, 2]) / kd[1, 1], np.ones_like(u)], -1)
        points = rays @ self._color_rig[:3, :3].T + offset
        map_x = kc[0, 0] * points[..., 0] / points[..., 2] + kc[0, 2]
        map_y = kc[1, 1] * points[..., 1] / points[..., 2] + kc[1, 2]
        return map_x.astype(np.float32), map_y.astype(np.float32)

    @functools.cached_property
    def _plane_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The colour maps of the plane at infinity: every frame's when the cameras share a centre
        (computed once per sequence, not on every frame load)."""
        return self._color_maps(np.zeros(3))

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
        if not depth_scale > 0:
            raise InputError(f"depth_scale must be > 0 (raw units per metre), got {depth_scale!r}")
        readers = []
        for i, image in enumerate(images):
            if isinstance(image, o3d.geometry.RGBDImage):
                color, depth = np.asarray(image.color), np.asarray(image.depth)
                if color.ndim == 2 or color.dtype != np.uint8:
                    raise InputError(
                        f"images[{i}]: the RGBDImage colour is grey/float; create it with "
                        "convert_rgb_to_intensity=False so that colour is kept"
                    )
            elif isinstance(image, (tuple, list)) and len(image) == 2:
                color, depth = (np.asarray(a) for a in image)
            else:
                raise InputError(
                    f"images[{i}] must be an o3d.geometry.RGBDImage or a (color, depth) pair, "
                    f"got {type(image).__name__}"
                )
            readers.append(constant_reader(np.array(color), depth_in_metres(depth, depth_scale, f"images[{i}]"),
                                           f"images[{i}]"))
        seq = cls(readers, intrinsic, timestamps, gt_poses, depth_trunc, name=name)
        for i in range(1, len(seq)):
            seq[i]  # validates the frame
        check_first_frame(seq)
        return seq


def concatenate(sequences: Sequence[RGBDSequence], name: str | None = None) -> RGBDSequence:
    """One sequence of the frames of `sequences` in order, each frame as its sequence gives it (at
    its image scale, colour on the depth grid), read lazily. The sequences must have depth images
    and the same image size and depth intrinsic (InputError naming the first that differs);
    ground-truth poses are kept where a sequence has them (NaN rows elsewhere)."""
    if not sequences:
        raise InputError("concatenate(): no sequences")
    first = check_sequence(sequences[0], what="concatenate(): sequences[0]", needs_depth=True)
    readers, gt = [], []
    for k, seq in enumerate(sequences):
        check_sequence(seq, what=f"concatenate(): sequences[{k}]", needs_depth=True)
        if seq.image_size != first.image_size or not np.allclose(seq.K, first.K, rtol=1e-6, atol=1e-6):
            raise InputError(f"{seq.name}: frames of {seq.image_size[1]}x{seq.image_size[0]} with intrinsic "
                             f"{np.round(seq.K[[0, 1, 0, 1], [0, 1, 2, 2]], 3).tolist()} (fx, fy, cx, cy) do not "
                             f"match {first.name}'s {first.image_size[1]}x{first.image_size[0]} with "
                             f"{np.round(first.K[[0, 1, 0, 1], [0, 1, 2, 2]], 3).tolist()}")
        readers += [_registered_reader(seq, i) for i in range(len(seq))]
        gt.append(seq.gt_poses if seq.gt_poses is not None else np.full((len(seq), 4, 4), np.nan))
    gt_poses = np.concatenate(gt) if any(seq.gt_poses is not None for seq in sequences) else None
    return RGBDSequence(readers, first.intrinsic, np.concatenate([seq.timestamps for seq in sequences]), gt_poses,
                        name=name or "+".join(dict.fromkeys(seq.name for seq in sequences)))


def depth_in_color_cameras(sequence: RGBDSequence, offsets: np.ndarray) -> RGBDSequence:
    """`sequence` with each frame's depth moved into its colour camera, which sits at offsets[i]
    (N, 4, 4) in the depth camera's frame (:func:`~open3d_pnerf.camera.reproject_depth`): the frames
    of the colour images' poses (Trajectory.color_poses), colour on the depth grid, read lazily."""
    offsets = np.asarray(offsets, np.float64)
    if offsets.shape != (len(sequence), 4, 4) or not np.isfinite(offsets).all():
        raise InputError(f"offsets must be finite with shape ({len(sequence)}, 4, 4), got {offsets.shape}")
    readers = []
    for i, offset in enumerate(offsets):
        read = _registered_reader(sequence, i)
        readers.append(_moved_reader(read, sequence.K, np.linalg.inv(offset)))
    return RGBDSequence(readers, sequence.intrinsic, sequence.timestamps, sequence.gt_poses, name=sequence.name)


def _moved_reader(read: FrameReader, K: np.ndarray, transform: np.ndarray) -> FrameReader:
    def moved():
        color, depth = read()
        return color, reproject_depth(depth, K, transform)

    moved.source = read.source
    return moved


def _registered_reader(sequence: RGBDSequence, index: int) -> FrameReader:
    """A reader of frame `index` of `sequence` as it gives it, its colour on the depth grid."""

    def read():
        frame = sequence[index]
        return sequence.color_on_depth_grid(frame.color, frame.depth), frame.depth

    read.source = sequence._describe(index)
    return read


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """Indices of min(k, n) items evenly spread over range(n), first and last included."""
    return np.unique(np.round(np.linspace(0, n - 1, min(k, n))).astype(int)) if n and k else np.zeros(0, int)


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
