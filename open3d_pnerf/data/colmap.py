"""Readers of COLMAP's binary sparse models: ``cameras.bin``, ``images.bin``, ``points3D.bin``.

The format is COLMAP's documented one (little-endian; see colmap.github.io/format.html):

* cameras.bin: uint64 count; per camera int32 id, int32 model id, uint64 width, uint64 height,
  then the model's float64 parameters (their number depends on the model).
* images.bin: uint64 count; per image int32 id, float64 qw qx qy qz (world-to-camera rotation),
  float64 tx ty tz, int32 camera id, the name as a NUL-terminated string, uint64 number of 2D
  points, then per 2D point float64 x, y and int64 point3D id (-1: none).
* points3D.bin: uint64 count; per point uint64 id, float64 x y z, uint8 r g b, float64 mean
  reprojection error (pixels), uint64 track length, then per track element int32 image id and
  int32 index of the 2D point in that image.

A file that ends early or carries bytes after its last record raises DatasetError naming it.
COLMAP's pixel coordinates put the centre of the top-left pixel at (0.5, 0.5).
"""

from __future__ import annotations

import dataclasses
import struct
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np

from ..camera import quaternion_matrix
from ..errors import DatasetError, InputError

# model id -> (name, number of parameters), as in COLMAP's src/colmap/sensor/models.h
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
# models whose parameters start with one focal length (f, cx, cy, ...); the others start fx, fy, cx, cy
SINGLE_FOCAL_MODELS = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}


@dataclasses.dataclass
class ColmapCamera:
    """One camera of cameras.bin: model name, image size (pixels) and its float64 parameters."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) in COLMAP pixels (top-left pixel centre at (0.5, 0.5))."""
        first = 1 if self.model in SINGLE_FOCAL_MODELS else 2
        return float(self.params[first]), float(self.params[first + 1])

    @property
    def radial_distortion(self) -> tuple[float, float]:
        """(k1, k2) of SIMPLE_RADIAL (k2 = 0) and RADIAL; (0, 0) for the pinhole models. Other
        models' distortion is not modelled: a warning says so and (0, 0) is returned."""
        if self.model in ("SIMPLE_RADIAL", "RADIAL"):
            return float(self.params[3]), float(self.params[4]) if self.model == "RADIAL" else 0.0
        if self.model not in ("SIMPLE_PINHOLE", "PINHOLE"):
            warnings.warn(f"COLMAP camera {self.id}: the {self.model} distortion is not modelled; its images are "
                          "used as pinhole images")
        return 0.0, 0.0


@dataclasses.dataclass
class ColmapImage:
    """One registered image of images.bin.

    qvec (4,) world-to-camera rotation quaternion (w, x, y, z), tvec (3,) world-to-camera
    translation, xys (P, 2) float64 keypoints in COLMAP pixels, point3d_ids (P,) int64 (-1: none).
    """

    id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray
    point3d_ids: np.ndarray

    def camera_to_world(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world pose (COLMAP's camera axes are OpenCV's)."""
        rot = quaternion_matrix(self.qvec)  # COLMAP stores (w, x, y, z)
        pose = np.eye(4)
        pose[:3, :3] = rot.T
        pose[:3, 3] = -rot.T @ self.tvec
        return pose


@dataclasses.dataclass
class ColmapPoints:
    """The M points of points3D.bin with their tracks in compressed form.

    ids (M,) int64; xyz (M, 3) float64 world coordinates; rgb (M, 3) uint8; error (M,) float64
    mean reprojection error in pixels of the images COLMAP ran on. Point k's track is
    ``track_image_ids[track_offsets[k]:track_offsets[k + 1]]`` (int32 image ids) with the
    matching ``track_point2d`` (int32 keypoint indices); track_offsets is (M + 1,) int64.
    """

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    track_offsets: np.ndarray
    track_image_ids: np.ndarray
    track_point2d: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def track_lengths(self) -> np.ndarray:
        """(M,) int64 number of observations of each point."""
        return np.diff(self.track_offsets)

    def observed(self, image_rows: Mapping[int, int], n: int) -> np.ndarray:
        """(M, n) bool: point k is observed in frame image_rows[image id] (ids -> rows 0..n-1).

        Raises InputError if a track names an image id missing from image_rows.
        """
        unknown = sorted(set(np.unique(self.track_image_ids).tolist()) - set(image_rows))
        if unknown:
            raise InputError(f"tracks observe image ids {unknown[:10]} that are not among the {n} images")
        lookup = np.zeros(max(image_rows, default=0) + 1, np.int64)
        lookup[list(image_rows)] = list(image_rows.values())
        point = np.repeat(np.arange(len(self)), self.track_lengths)
        out = np.zeros((len(self), n), bool)
        out[point, lookup[self.track_image_ids]] = True
        return out


class _BinaryFile:
    """Sequential little-endian reads over one file's bytes; reading past the end is a DatasetError."""

    def __init__(self, path):
        self.path = Path(path)
        try:
            self.data = self.path.read_bytes()
        except FileNotFoundError:
            raise DatasetError(f"COLMAP file not found: {self.path}") from None
        except OSError as exc:
            raise DatasetError(f"cannot read COLMAP file {self.path} ({exc})") from None
        self.pos = 0

    def _take(self, size: int) -> int:
        start = self.pos
        if start + size > len(self.data):
            raise DatasetError(
                f"{self.path}: truncated: a record needs {size} bytes at byte {start} but the file has {len(self.data)}"
            )
        self.pos += size
        return start

    def read(self, fmt: str) -> tuple:
        fmt = "<" + fmt
        return struct.unpack_from(fmt, self.data, self._take(struct.calcsize(fmt)))

    def array(self, dtype, count: int) -> np.ndarray:
        dtype = np.dtype(dtype).newbyteorder("<")
        return np.frombuffer(self.data, dtype, count, self._take(count * dtype.itemsize)).copy()

    def string(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated: an image name at byte {self.pos} has no terminating NUL")
        text = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return text

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise DatasetError(f"{self.path}: {len(self.data) - self.pos} unexpected bytes after the last record")


def read_cameras_binary(path) -> dict[int, ColmapCamera]:
    """Cameras of a COLMAP ``cameras.bin`` by camera id."""
    f = _BinaryFile(path)
    cameras = {}
    for _ in range(f.read("Q")[0]):
        cam_id, model_id, width, height = f.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DatasetError(f"{f.path}: camera {cam_id} has unknown model id {model_id}")
        name, n_params = CAMERA_MODELS[model_id]
        cameras[cam_id] = ColmapCamera(cam_id, name, width, height, f.array(np.float64, n_params))
    f.finish()
    return cameras


def read_images_binary(path) -> dict[int, ColmapImage]:
    """Registered images of a COLMAP ``images.bin`` by image id."""
    f = _BinaryFile(path)
    images = {}
    for _ in range(f.read("Q")[0]):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = f.read("idddddddi")
        name = f.string()
        n_points = f.read("Q")[0]
        obs = f.array([("xy", "<f8", 2), ("id", "<i8")], n_points)
        images[image_id] = ColmapImage(
            image_id, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), camera_id, name,
            obs["xy"].copy(), obs["id"].copy(),
        )
    f.finish()
    return images


def read_points3d_binary(path) -> ColmapPoints:
    """Points of a COLMAP ``points3D.bin`` with their reprojection errors and tracks."""
    f = _BinaryFile(path)
    n = f.read("Q")[0]
    if n * 51 > len(f.data):  # 51 bytes: the smallest record (an empty track)
        raise DatasetError(f"{f.path}: truncated: {n} points cannot fit in {len(f.data)} bytes")
    ids, xyz, rgb, error, lengths, tracks = (np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3), np.uint8),
                                             np.empty(n), np.empty(n, np.int64), [])
    for k in range(n):
        point_id, x, y, z, r, g, b, err, length = f.read("QdddBBBdQ")
        ids[k], xyz[k], rgb[k], error[k], lengths[k] = point_id, (x, y, z), (r, g, b), err, length
        tracks.append(f.array("<i4", 2 * length))
    f.finish()
    track = np.concatenate(tracks).reshape(-1, 2) if tracks else np.empty((0, 2), np.int32)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    return ColmapPoints(ids, xyz, rgb, error, offsets, track[:, 0].copy(), track[:, 1].copy())
