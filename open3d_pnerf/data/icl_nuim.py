"""ICL-NUIM's TUM-compatible release: ``rgb/`` and ``depth/`` PNGs (depth 5000 units per metre),
``associations.txt`` pairing them, the ground truth as a TUM trajectory (``*.gt.freiburg``).

Its published camera has a negative focal length in y: (fx, fy, cx, cy) = (481.20, -480.00, 319.5,
239.5), i.e. the renderer's camera has y pointing up the image while the trajectory's camera frame is
right-handed with z forward. Read with a positive fy, the frames would lie mirrored against the
trajectory. Here each frame's rows are flipped (colour and depth alike) on load: the flipped image is
what an OpenCV camera (y down) at the same pose sees, with fy = +480 and cy = H - 1 - 239.5, so the
ground-truth poses and the scene's own frame stay exactly as published (frames look upside down
beside the files).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import pinhole
from ..errors import DatasetError
from .images import FrameReader, file_reader, read_image
from .sequence import RGBDSequence
from .tum import interpolate_groundtruth, read_list

ICL_INTRINSIC = (481.20, -480.0, 319.5, 239.5)
"""The published (fx, fy, cx, cy) of ICL-NUIM's renders (pixels at 640x480)."""
ICL_DEPTH_SCALE = 5000.0


def is_icl_nuim(path: Path) -> bool:
    return ((path / "associations.txt").is_file() and (path / "rgb").is_dir() and (path / "depth").is_dir()
            and any(path.glob("*.gt.freiburg")))


def read_icl_nuim(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                  image_scale: float = 1.0) -> RGBDSequence:
    """An ICL-NUIM folder: frames in the order of ``associations.txt`` (each line a depth and a colour
    image with their timestamps, in either order), rows flipped (see the module docstring), the
    ground truth of the first ``*.gt.freiburg`` at the frames' timestamps. intrinsic: the camera of the
    flipped frames (default: the published one, made positive)."""
    assoc = path / "associations.txt"
    stamps, colors, depths = [], [], []
    for row in read_list(assoc):
        if len(row) < 4:
            raise DatasetError(f"{assoc}: expected 'timestamp file timestamp file' lines, got {' '.join(row)!r}")
        files = {Path(row[1]).parent.name: (row[0], row[1]), Path(row[3]).parent.name: (row[2], row[3])}
        if set(files) != {"rgb", "depth"}:
            raise DatasetError(f"{assoc}: a line pairs files of {sorted(files)}, expected one of rgb/ and one of depth/")
        try:
            stamps.append(float(files["depth"][0]))
        except ValueError:
            raise DatasetError(f"{assoc}: timestamp {files['depth'][0]!r} is not a number") from None
        colors.append(path / files["rgb"][1])
        depths.append(path / files["depth"][1])
    missing = [str(f) for f in colors + depths if not f.is_file()]
    if missing:
        raise DatasetError(f"{assoc}: {len(missing)} listed image(s) do not exist: {missing[:3]}")
    height, width = read_image(depths[0]).shape[:2]
    if intrinsic is None:
        fx, fy, cx, cy = ICL_INTRINSIC
        intrinsic = pinhole(width, height, fx, -fy, cx, height - 1 - cy)
    scale = depth_scale or ICL_DEPTH_SCALE
    readers = [_flipped(file_reader(c, d, scale)) for c, d in zip(colors, depths)]
    stamps = np.array(stamps)
    gt = interpolate_groundtruth(sorted(path.glob("*.gt.freiburg"))[0], stamps)
    return RGBDSequence(readers, intrinsic, stamps, gt, depth_trunc, name=path.name, image_scale=image_scale)


def _flipped(read: FrameReader) -> FrameReader:
    """`read` with its frame's rows in reverse order (colour and depth)."""

    def flipped():
        color, depth = read()
        return np.ascontiguousarray(color[::-1]), np.ascontiguousarray(depth[::-1])

    flipped.source = read.source
    return flipped
