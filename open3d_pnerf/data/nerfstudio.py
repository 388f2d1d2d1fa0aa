"""nerfstudio's data format, in and out: a folder with ``transforms.json``.

It is what ``ns-process-data`` makes of phone captures (Record3D, Polycam, Scaniverse) and
videos, and how many RGB-D datasets are shared. ``transforms.json`` holds:

* the camera: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` at the top level or in every
  frame (all frames must then agree), optional ``camera_model`` ("OPENCV", "PINHOLE",
  "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") and distortion ``k1``, ``k2``, ``k3``,
  ``p1``, ``p2`` (frames are undistorted on load: colour bilinearly, depth to the nearest pixel);
* ``frames``: ``file_path`` (an image, relative to the folder), ``transform_matrix`` (4x4
  camera-to-world in OpenGL camera axes: x right, y up, z backward), optional
  ``depth_file_path`` (16-bit PNG or ``.npy``, any size with the image's aspect ratio);
* optional ``depth_unit_scale_factor`` (metres per depth unit; 0.001, nerfstudio's default,
  when absent), ``ply_file_path`` (sparse points, in the frame that ``applied_transform``, a
  3x4 matrix, maps to the poses' frame).

Conventions converted here, once: OpenGL to OpenCV camera axes (``pose @ diag(1, -1, -1, 1)``,
its own inverse) and nerfstudio's pixel centres at +0.5 (cx, cy minus 0.5). Frames are sorted
by file path, as nerfstudio does. The poses are the capture's own: ``reconstruct()`` uses them
(``sequence.sfm.poses``, zero covariance) instead of tracking.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from .._files import atomic_write, read_json_object
from ..camera import check_poses, intrinsic_matrix, pinhole
from ..errors import DatasetError, InputError, PoseError
from .images import read_color, read_depth, read_image, resized_depth
from .sequence import RGBDSequence, check_sequence
from .sfm import SfMData

TRANSFORMS = "transforms.json"
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes, either way
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
DEFAULT_DEPTH_UNIT = 1e-3  # metres per depth unit, nerfstudio's default (millimetre PNGs)


def is_nerfstudio(path: Path) -> bool:
    return (path / TRANSFORMS).is_file()


def read_nerfstudio(path: Path, intrinsic=None, depth_scale: float | None = None, depth_trunc: float = 0.0,
                    image_scale: float = 1.0) -> RGBDSequence:
    """A nerfstudio folder as a sequence: RGB-D when every frame has a ``depth_file_path``, else
    image-only; the capture's poses in ``sequence.sfm`` (see the module docstring). Depth
    images smaller than the colour images (phone depth sensors) are resized to them, nearest
    pixel, as nerfstudio does, so one camera serves both.

    intrinsic overrides the camera, depth_scale the depth units (raw units per metre, as for the
    other formats).
    """
    file = path / TRANSFORMS
    meta = read_json_object(file, DatasetError)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) for f in frames):
        raise DatasetError(f"{file}: 'frames' must be a non-empty list of objects")
    for k, frame in enumerate(frames):
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DatasetError(f"{file}: frames[{k}] has no {key!r}")
    frames = sorted(frames, key=lambda f: str(f["file_path"]))
    camera, distortion = _camera(meta, frames, file)
    width, height = int(camera["w"]), int(camera["h"])
    image_intrinsic = intrinsic or pinhole(width, height, camera["fl_x"], camera["fl_y"], camera["cx"] - 0.5,
                                                 camera["cy"] - 0.5)
    poses = _poses(frames, file) @ OPENGL_TO_OPENCV
    images = [_existing(path / f["file_path"], file, "file_path") for f in frames]
    first = read_image(images[0], cv2.IMREAD_COLOR)
    if first.shape[:2] != (image_intrinsic.height, image_intrinsic.width):
        raise DatasetError(f"{images[0]}: the image is {first.shape[1]}x{first.shape[0]} but {file} says "
                           f"{image_intrinsic.width}x{image_intrinsic.height}")
    with_depth = ["depth_file_path" in f for f in frames]
    if any(with_depth) and not all(with_depth):
        k = with_depth.index(False)
        raise DatasetError(f"{file}: frame {frames[k]['file_path']} has no depth_file_path but others have: "
                           "give every frame a depth image or none")
    undistort = _Undistortion(intrinsic_matrix(image_intrinsic), distortion, (image_intrinsic.width, image_intrinsic.height))
    if not all(with_depth):
        sfm = SfMData.from_poses(poses, _bounds(meta, path, file, poses, image_intrinsic))
        readers = [_Frame(p, None, undistort) for p in images]
        return RGBDSequence(readers, image_intrinsic, name=path.name, image_scale=image_scale, has_depth=False,
                            sfm=sfm)
    unit = 1.0 / depth_scale if depth_scale else float(meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT))
    if not unit > 0:
        raise DatasetError(f"{file}: depth_unit_scale_factor must be > 0 (metres per depth unit), got {unit!r}")
    depths = [_existing(path / f["depth_file_path"], file, "depth_file_path") for f in frames]
    size = (image_intrinsic.width, image_intrinsic.height)
    resized_depth(read_depth(depths[0], unit), size, depths[0])  # the first frame checked now
    readers = [_Frame(c, d, undistort, unit, size) for c, d in zip(images, depths)]
    sfm = SfMData.from_poses(poses)
    return RGBDSequence(readers, image_intrinsic, None, None, depth_trunc, None, path.name, image_scale, sfm=sfm)


def write_nerfstudio(sequence: RGBDSequence, path, poses: np.ndarray | None = None, train_indices=None,
                     holdout_indices=None, progress: bool = False) -> Path:
    """Write a sequence as a nerfstudio folder that nerfstudio (and :func:`load_sequence`) reads.

    poses: (N, 4, 4) camera-to-world (default: the sequence's own, ``sequence.sfm.poses``, else
    its complete ground truth). Writes ``images/frame_NNNNN.png`` (colour on the depth image's
    grid, so one camera serves both), ``depth/frame_NNNNN.png`` (16-bit millimetres) for RGB-D
    sequences, ``sparse_pc.ply`` with the SfM points of an image-only one, and
    ``transforms.json``. train_indices / holdout_indices: frames to list as nerfstudio's
    ``train_filenames`` and ``val_filenames`` / ``test_filenames`` (nerfstudio then uses that
    split). Frames are read one at a time.
    """
    from tqdm.auto import tqdm

    check_sequence(sequence, what="write_nerfstudio(): sequence")
    n = len(sequence)
    if poses is None:
        if sequence.sfm is not None:
            poses = sequence.sfm.poses
        elif sequence.gt_poses is not None and sequence.gt_valid.all():
            poses = sequence.gt_poses
        else:
            raise InputError(f"write_nerfstudio(): {sequence.name} has no poses of its own for every frame; pass "
                             "poses=(N, 4, 4) camera-to-world, e.g. open3d_pnerf.track(sequence).poses")
    poses = check_poses(poses, n, "poses")
    path = Path(path)
    intr = sequence.intrinsic
    fx, fy = intr.get_focal_length()
    cx, cy = intr.get_principal_point()
    meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx + 0.5, "cy": cy + 0.5, "w": intr.width,
            "h": intr.height, **dict.fromkeys(DISTORTION_KEYS, 0.0)}
    if sequence.has_depth:
        meta["depth_unit_scale_factor"] = DEFAULT_DEPTH_UNIT
    frames = []
    for i in tqdm(range(n), desc="write frames", disable=not progress, leave=False):
        frame = sequence[i]
        entry = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": (poses[i] @ OPENGL_TO_OPENCV).tolist()}
        color = cv2.cvtColor(sequence.color_on_depth_grid(frame.color, frame.depth), cv2.COLOR_RGB2BGR)
        atomic_write(path / entry["file_path"], lambda p: cv2.imwrite(p, color))
        if sequence.has_depth:
            depth = np.round(frame.depth / DEFAULT_DEPTH_UNIT)
            if depth.max(initial=0) > 65535:
                raise InputError(f"frame {i}: depth {frame.depth.max():.1f} m overflows 16-bit millimetres")
            entry["depth_file_path"] = f"depth/frame_{i:05d}.png"
            atomic_write(path / entry["depth_file_path"], lambda p: cv2.imwrite(p, depth.astype(np.uint16)))
        frames.append(entry)
    meta["frames"] = frames
    for key, indices in (("train_filenames", train_indices), ("val_filenames", holdout_indices),
                         ("test_filenames", holdout_indices)):
        if indices is not None:
            meta[key] = [frames[int(i)]["file_path"] for i in indices]
    if sequence.sfm is not None and len(sequence.sfm.points):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sequence.sfm.points.xyz))
        atomic_write(path / "sparse_pc.ply", lambda p: o3d.io.write_point_cloud(p, cloud))
        meta["ply_file_path"] = "sparse_pc.ply"
    atomic_write(path / TRANSFORMS, lambda p: Path(p).write_text(json.dumps(meta, indent=2)))
    return path


# -- reading helpers ----------------------------------------------------------------------------------
def _camera(meta: dict, frames: list[dict], file: Path) -> tuple[dict, np.ndarray]:
    """The one camera of all frames: {fl_x, fl_y, cx, cy, w, h} and distortion (5,) in OpenCV order."""
    model = meta.get("camera_model", "OPENCV")
    if model not in PINHOLE_MODELS:
        raise DatasetError(f"{file}: camera_model {model!r} is not supported; expected one of {PINHOLE_MODELS}")
    keys = CAMERA_KEYS + DISTORTION_KEYS
    values = []
    for k, frame in enumerate(frames):
        camera = {}
        for key in keys:
            value = frame.get(key, meta.get(key, 0.0 if key in DISTORTION_KEYS else None))
            if value is None:
                raise DatasetError(f"{file}: {key!r} missing (needed at the top level or in every frame; "
                                   f"frame {frame['file_path']} has none)")
            try:
                camera[key] = float(value)
            except (TypeError, ValueError):
                raise DatasetError(f"{file}: {key!r} of frame {frame['file_path']} is not a number: {value!r}") from None
        values.append([camera[key] for key in keys])
    values = np.array(values)
    differ = np.flatnonzero((np.abs(values - values[0]) > 1e-6).any(1))
    if differ.size:
        raise DatasetError(f"{file}: frames {[frames[k]['file_path'] for k in differ[:3]]} have other intrinsics than "
                           f"{frames[0]['file_path']}; one camera for all frames is supported")
    camera = dict(zip(keys, values[0]))
    if not (camera["fl_x"] > 0 and camera["fl_y"] > 0 and camera["w"] >= 1 and camera["h"] >= 1):
        raise DatasetError(f"{file}: need fl_x, fl_y > 0 and w, h >= 1, got {camera}")
    return camera, values[0, len(CAMERA_KEYS):]


def _poses(frames: list[dict], file: Path) -> np.ndarray:
    poses = []
    for frame in frames:
        try:
            pose = np.asarray(frame["transform_matrix"], np.float64)
        except (TypeError, ValueError):
            pose = None
        if pose is None or pose.shape not in ((4, 4), (3, 4)):
            raise DatasetError(f"{file}: transform_matrix of frame {frame['file_path']} is not a 4x4 (or 3x4) matrix")
        if pose.shape == (3, 4):
            pose = np.vstack([pose, [0, 0, 0, 1]])
        try:
            poses.append(check_poses(pose[None], 1, f"{file}: transform_matrix of frame {frame['file_path']}")[0])
        except PoseError as exc:
            raise PoseError(f"{exc} (it must be a camera-to-world rigid transform)") from None
    return np.stack(poses)


def _existing(file: Path, transforms: Path, key: str) -> Path:
    if not file.is_file():
        raise DatasetError(f"{transforms}: {key} {file} does not exist")
    return file


class _Undistortion:
    """Remaps of a distorted pinhole camera (K (3, 3) of images `size` (W, H), OpenCV distortion
    (5,)) to the same camera without distortion, for images of that size or resized."""

    def __init__(self, K: np.ndarray, distortion: np.ndarray, size: tuple[int, int]):
        self.K, self.distortion, self.size, self.maps = K, distortion, size, {}

    def __call__(self, image: np.ndarray, interpolation: int) -> np.ndarray:
        if not self.distortion.any():
            return image
        h, w = image.shape[:2]
        if (h, w) not in self.maps:
            sx, sy = w / self.size[0], h / self.size[1]  # pixel centres at integers: (c + 0.5) s - 0.5
            K = np.array([[self.K[0, 0] * sx, 0, (self.K[0, 2] + 0.5) * sx - 0.5],
                          [0, self.K[1, 1] * sy, (self.K[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
            self.maps[h, w] = cv2.initUndistortRectifyMap(K, self.distortion, None, K, (w, h), cv2.CV_32FC1)
        return cv2.remap(image, *self.maps[h, w], interpolation)


class _Frame:
    """Reader of one nerfstudio frame: (colour, depth in metres resized to the colour's `size`
    (W, H), or zeros), undistorted."""

    def __init__(self, color: Path, depth: Path | None, undistort: _Undistortion, unit: float = 1.0,
                 size: tuple[int, int] | None = None):
        self.color_path, self.depth_path, self.undistort, self.unit, self.size = color, depth, undistort, unit, size
        self.source = f"{color}, {depth}" if depth else str(color)

    def __call__(self) -> tuple[np.ndarray, np.ndarray]:
        color = self.undistort(read_color(self.color_path), cv2.INTER_LINEAR)
        if self.depth_path is None:
            return color, np.zeros(color.shape[:2], np.float32)
        depth = resized_depth(read_depth(self.depth_path, self.unit), self.size, self.depth_path)
        return color, self.undistort(depth, cv2.INTER_NEAREST)


def _bounds(meta: dict, path: Path, file: Path, poses: np.ndarray, intrinsic) -> np.ndarray:
    """(N, 2) near/far z-depth of each camera for an image-only capture: from the sparse points of
    ``ply_file_path`` the frame sees (0.5 / 99.5 percentiles), else a guess from the cameras' spread."""
    points = None
    if "ply_file_path" in meta:
        ply = _existing(path / meta["ply_file_path"], file, "ply_file_path")
        points = np.asarray(o3d.io.read_point_cloud(str(ply)).points)
        if "applied_transform" in meta:
            applied = np.asarray(meta["applied_transform"], np.float64)
            if applied.shape != (3, 4):
                raise DatasetError(f"{file}: applied_transform must be a 3x4 matrix, got shape {applied.shape}")
            points = points @ applied[:, :3].T + applied[:, 3]
    K, (h, w) = intrinsic_matrix(intrinsic), (intrinsic.height, intrinsic.width)
    bounds = np.full((len(poses), 2), np.nan)
    for i, pose in enumerate(poses):
        if points is None or not len(points):
            break
        q = (points - pose[:3, 3]) @ pose[:3, :3]
        u, v = q[:, 0] / q[:, 2] * K[0, 0] + K[0, 2], q[:, 1] / q[:, 2] * K[1, 1] + K[1, 2]
        seen = (q[:, 2] > 0) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        if seen.sum() >= 3:
            bounds[i] = np.percentile(q[seen, 2], [0.5, 99.5])
    missing = np.isnan(bounds).any(1)
    if missing.any():
        spread = float(np.linalg.norm(np.ptp(poses[:, :3, 3], axis=0)))
        guess = (0.05, max(2.0 * spread, 1.0))
        warnings.warn(f"{file}: no depth images and no sparse points in view of {int(missing.sum())} frame(s): "
                      f"assuming the scene lies {guess[0]:g} to {guess[1]:.3g} units in front of them (twice the "
                      "cameras' spread, at least 1); the scene box follows from it")
        bounds[missing] = guess
    return bounds
