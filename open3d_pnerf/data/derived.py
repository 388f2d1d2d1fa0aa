"""Sequences derived from others: frames chosen evenly, sequences joined one after another, each
frame's depth moved into its colour camera. Frames stay lazy: each is read from its source when
indexed."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..camera import reproject_depth
from ..errors import InputError
from .images import FrameReader
from .sequence import RGBDSequence, check_sequence


def evenly_spaced(n: int, k: int) -> np.ndarray:
    """Indices of min(k, n) items evenly spread over range(n), first and last included."""
    return np.unique(np.round(np.linspace(0, n - 1, min(k, n))).astype(int)) if n and k else np.zeros(0, int)


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
