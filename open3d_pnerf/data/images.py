"""Image decoding shared by every reader: checked image reads, depth files and units, frame readers."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import open3d as o3d

from ..errors import DatasetError, InputError

FrameReader = Callable[[], tuple[np.ndarray, np.ndarray]]
"""Zero-argument callable returning (colour uint8 HxWx3, depth float32 HxW metres); an
optional ``source`` attribute (str) names where the frame comes from in error messages."""

IMAGE_EXT = {".png", ".jpg", ".jpeg"}
DEPTH_EXT = IMAGE_EXT | {".tif", ".tiff", ".exr", ".npy"}


def read_image(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Read an image file with OpenCV, raising DatasetError naming the file if it is missing,
    unreadable or truncated (OpenCV decodes a truncated JPEG silently: its end marker is checked)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"image file not found: {path}") from None
    except OSError as exc:
        raise DatasetError(f"cannot read image file {path} ({exc})") from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    truncated_jpeg = data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-4096:]
    if image is None or image.size == 0 or truncated_jpeg:
        raise DatasetError(f"cannot decode image (unreadable or truncated): {path}")
    return image


def read_color(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour image file (DatasetError naming the file if unreadable)."""
    return cv2.cvtColor(read_image(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def image_files(folder: Path, suffixes=IMAGE_EXT) -> list[Path]:
    """The files of a folder with one of `suffixes` (PNG and JPEG images by default), in natural order:
    the numbers in their names compared as numbers (0.jpg, 1.jpg, ..., 10.jpg; zero-padded names sort
    as they are)."""
    return sorted((p for p in Path(folder).iterdir() if p.suffix.lower() in suffixes), key=natural_key)


def natural_key(path: Path) -> tuple:
    """Sort key of a file name with its digit runs as numbers: frame2 before frame10."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", Path(path).name))


def depth_in_metres(raw: np.ndarray, depth_scale: float, what: str) -> np.ndarray:
    """Depth as float32 metres: uint16 is raw sensor units (divided by depth_scale), float is metres.

    Any other type (8-bit or multi-channel images, other integers) raises DatasetError naming `what`.
    """
    raw = np.asarray(raw)
    if raw.ndim == 2 and raw.dtype == np.uint16:
        return raw.astype(np.float32) / np.float32(depth_scale)
    if raw.ndim == 2 and raw.dtype in (np.float32, np.float64):
        return raw.astype(np.float32)
    raise DatasetError(
        f"{what}: depth must be single-channel uint16 (raw units, divided by depth_scale) or "
        f"float32/float64 metres, got {raw.dtype} with shape {raw.shape}"
    )


def read_depth(path: Path, unit: float) -> np.ndarray:
    """(H, W) float32 metres of a depth file times `unit` (metres per stored unit): a 16-bit or
    float image (PNG, TIFF; OpenEXR, as phone captures store it) or a ``.npy`` array; DatasetError
    naming the file for anything else."""
    path = Path(path)
    if path.suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"cannot read depth file {path} ({exc})") from None
    else:
        if path.suffix.lower() == ".exr":  # OpenCV decodes OpenEXR only when asked to (untrusted files' risk)
            os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
        raw = read_image(path, cv2.IMREAD_UNCHANGED)
    raw = np.squeeze(raw)
    if raw.ndim == 3 and path.suffix.lower() == ".exr":  # an EXR with the depth in its first channel
        raw = raw[..., 0]
    if raw.ndim != 2 or not (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)):
        raise DatasetError(f"{path}: depth must be a single-channel image or array, got {raw.dtype} {raw.shape}")
    return raw.astype(np.float32) * np.float32(unit)


def resized_depth(depth: np.ndarray, size: tuple[int, int], path: Path) -> np.ndarray:
    """Depth (h, w) brought to `size` (W, H) by the nearest pixel (a phone's depth is smaller than its
    colour); DatasetError naming `path` unless it has that size or its aspect ratio (within a pixel)."""
    (h, w), (iw, ih) = depth.shape, size
    if (w, h) == (iw, ih):
        return depth
    if abs(h * iw / w - ih) > max(1.0, iw / w):
        raise DatasetError(f"{path}: the depth image is {w}x{h}, neither the {iw}x{ih} colour images' size nor "
                           "their aspect ratio")
    return cv2.resize(depth, (iw, ih), interpolation=cv2.INTER_NEAREST)


def file_reader(color_path: Path, depth_path: Path, depth_scale: float, invalid_raw: int | None = None) -> FrameReader:
    """A reader for a colour image file and a depth image (see :func:`depth_in_metres`).

    Raw depth values >= invalid_raw (e.g. 7-Scenes' 65535) are set to 0 (invalid). The
    reader's ``source`` names both files, so errors about the frame can name them.
    """

    def read() -> tuple[np.ndarray, np.ndarray]:
        color = read_color(color_path)
        raw = read_image(depth_path, cv2.IMREAD_UNCHANGED)
        depth = depth_in_metres(raw, depth_scale, str(depth_path))
        if invalid_raw is not None:
            depth[raw >= invalid_raw] = 0
        return color, depth

    read.source = f"{color_path}, {depth_path}"
    return read


def color_only_reader(path: Path, height: int, width: int) -> FrameReader:
    """A reader of a colour image file without depth: (colour uint8 RGB, all-zero depth (H, W))."""

    def read():
        return read_color(path), np.zeros((height, width), np.float32)

    read.source = str(path)
    return read


def constant_reader(color: np.ndarray, depth: np.ndarray, source: str) -> FrameReader:
    """A reader of a frame held in memory."""

    def read():
        return color, depth

    read.source = source
    return read


def memory_readers(images, depth_scale: float) -> list[FrameReader]:
    """Readers of frames held in memory: `images` a list of ``o3d.geometry.RGBDImage`` (depth in
    metres, colour kept: ``convert_rgb_to_intensity=False``) or of ``(color, depth)`` numpy pairs,
    colour uint8 (H, W, 3), depth uint16 (divided by `depth_scale`, raw units per metre) or
    float32/64 metres; InputError names the first image that is neither."""
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
    return readers
