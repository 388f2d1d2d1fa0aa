"""`load_sequence`: detect a dataset folder's format and read it with that format's reader.

Formats are tried in registration order; a reader module registers itself with
:func:`register_format` (the library's own ones below). Each reader returns the folder's
whole sequence; striding, capping and the first-frame check happen here, once.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable

import numpy as np
import open3d as o3d

from ..camera import check_intrinsic
from ..errors import DatasetError, InputError
from .sequence import RGBDSequence, check_first_frame

RGBD_OPTIONS = frozenset({"intrinsic", "depth_scale", "depth_trunc", "color_intrinsic", "color_extrinsic"})
CAMERA_OPTIONS = frozenset({"intrinsic", "depth_scale", "depth_trunc"})  # formats with one registered camera


@dataclasses.dataclass(frozen=True)
class Format:
    """A dataset layout: `detect(path)` says whether a folder (or a recording file) has it; `read(path,
    image_scale=, **options)` returns its sequence, taking the `options` of load_sequence it understands."""

    name: str
    layout: str
    detect: Callable[[Path], bool]
    read: Callable[..., RGBDSequence]
    options: frozenset = RGBD_OPTIONS


FORMATS: list[Format] = []


def register_format(fmt: Format) -> None:
    """Add a dataset layout to those load_sequence() detects (tried after the earlier ones)."""
    FORMATS.append(fmt)


def detect_format(path: Path) -> Format:
    """The first registered format whose detector accepts the folder (DatasetError if none)."""
    for fmt in FORMATS:
        if fmt.detect(path):
            return fmt
    expected = "; ".join(f"{f.name} ({f.layout})" for f in FORMATS)
    raise DatasetError(f"{path}: not a known layout. Expected one of: {expected} (open3d-pnerf formats lists them)")


def load_sequence(
    path,
    intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None,
    depth_scale: float | None = None,
    depth_trunc: float = 0.0,
    stride: int = 1,
    max_frames: int | None = None,
    image_scale: float = 1.0,
    color_intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None,
    color_extrinsic: np.ndarray | None = None,
    gt_time_offset: float = 0.0,
    pose_convention: str | None = None,
) -> RGBDSequence:
    """Read a dataset folder or a recording file, detecting its layout (``FORMATS``, in order; the
    command ``open3d-pnerf formats`` lists them).

    intrinsic / color_intrinsic / depth_scale override what the folder says (RGB-D formats);
    color_extrinsic (4, 4) places the colour camera (depth-camera to colour-camera coordinates,
    m) where it is not at the depth camera's centre (a 7-Scenes folder has its Kinect's colour
    camera unless color_intrinsic or color_extrinsic is given; the one not given is then the
    depth camera's).
    depth_trunc (m, 0 = none) drops farther depth. stride keeps every stride-th frame,
    max_frames caps the count after striding. image_scale in (0, 1] resizes frames on load.
    gt_time_offset (s, TUM folders) is added to the frames' timestamps where the ground truth is
    read, for a motion capture whose clock disagrees with the camera's (TUM's ``--offset``).
    pose_convention (posed folders): how their poses are written, one of
    :data:`~open3d_pnerf.data.posed_folder.POSE_CONVENTIONS` ("opencv" camera-to-world by default).
    A benchmark's reference trajectory comes as ``sequence.gt_poses``; poses a capture brings (a
    device's own tracking, SfM) as ``sequence.sfm.poses``, which reconstruct() uses instead of tracking.
    An image-only folder (e.g. LLFF) gives a sequence without depth that carries its structure
    from motion (``sequence.sfm``).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path must be a folder path (str or pathlib.Path), got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"dataset folder or recording not found: {path}")
    if not isinstance(stride, int) or stride < 1:
        raise InputError(f"stride must be an integer >= 1, got {stride!r}")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"max_frames must be >= 1 or None, got {max_frames!r}")
    if depth_scale is not None and not depth_scale > 0:
        raise InputError(f"depth_scale must be > 0 (raw units per metre), got {depth_scale!r}")
    if intrinsic is not None:
        check_intrinsic(intrinsic)
    if isinstance(gt_time_offset, bool) or not isinstance(gt_time_offset, (int, float)) \
            or not abs(gt_time_offset) < 1.0:
        raise InputError(f"gt_time_offset must be a number of seconds under 1 in size, got {gt_time_offset!r}")
    fmt = detect_format(path)
    given = {"intrinsic": intrinsic, "depth_scale": depth_scale, "color_intrinsic": color_intrinsic,
             "color_extrinsic": color_extrinsic, "depth_trunc": depth_trunc or None,
             "gt_time_offset": gt_time_offset or None, "pose_convention": pose_convention}
    given = {k: v for k, v in given.items() if v is not None}
    unused = [k for k in given if k not in fmt.options]
    if unused:
        raise InputError(f"{path} is {fmt.name} ({fmt.layout}): {', '.join(unused)} do not apply")
    seq = fmt.read(path, image_scale=image_scale, **given)
    keep = np.arange(0, len(seq), stride)[:max_frames]
    if len(keep) < len(seq):
        seq = seq.select(keep)
    if seq.has_depth:
        check_first_frame(seq)
    return seq


def _register_builtin_formats() -> None:
    from .icl_nuim import is_icl_nuim, read_icl_nuim
    from .llff import POSES_FILE, is_llff, read_llff
    from .nerfstudio import TRANSFORMS, is_nerfstudio, read_nerfstudio
    from .open3d_folder import is_open3d_folder, read_open3d_folder
    from .posed_folder import is_posed_folder, read_posed_folder
    from .record3d import is_record3d, read_record3d
    from .recordings import is_azure_kinect_mkv, is_realsense_bag, read_azure_kinect_mkv, read_realsense_bag
    from .replica import is_replica, read_replica
    from .scannet import is_scannet, read_scannet
    from .seven_scenes import is_seven_scenes, read_seven_scenes
    from .tum import is_tum, read_tum

    def llff(path, image_scale=1.0):
        return read_llff(path, image_scale=image_scale)

    recording = frozenset({"intrinsic", "depth_trunc"})
    for fmt in (
        Format("an LLFF image folder", f"{POSES_FILE} + images_N/, no depth, camera from {POSES_FILE}", is_llff,
               llff, frozenset()),
        Format("nerfstudio", f"{TRANSFORMS} + images, optional depth; the capture's poses as sequence.sfm", is_nerfstudio,
               read_nerfstudio, CAMERA_OPTIONS),
        Format("TUM RGB-D", "rgb.txt + depth.txt; groundtruth.txt as gt_poses", is_tum, read_tum, RGBD_OPTIONS | {"gt_time_offset"}),
        Format("ICL-NUIM (TUM-compatible)", "rgb/ + depth/ + associations.txt (fy < 0: frames flipped); *.gt.freiburg as gt_poses",
               is_icl_nuim, read_icl_nuim, CAMERA_OPTIONS),
        Format("Replica (NICE-SLAM)", "results/frame*.jpg + depth*.png, cam_params.json; traj.txt as gt_poses",
               is_replica, read_replica, CAMERA_OPTIONS),
        Format("ScanNet (exported frames)", "color/ + depth/ + intrinsic/ (colour resampled to the depth camera); pose/ as gt_poses", is_scannet,
               read_scannet, CAMERA_OPTIONS | {"color_intrinsic"}),
        Format("Record3D (EXR + JPG export)", "rgb/ + depth/*.exr + metadata.json; the phone's poses as sequence.sfm",
               is_record3d, read_record3d, CAMERA_OPTIONS),
        Format("7-Scenes", "frame-XXXXXX.color.png + .depth.png; .pose.txt as gt_poses", is_seven_scenes, read_seven_scenes),
        Format("posed RGB-D folder", "images|color|rgb/ + depth/ + K.txt|intrinsics.txt|.json; poses.txt|pose/ as "
               "sequence.sfm (pose_convention=)", is_posed_folder, read_posed_folder, CAMERA_OPTIONS | {"pose_convention"}),
        Format("Open3D/Redwood", "color|rgb|image/ + depth/, intrinsic JSON; a .log trajectory as gt_poses", is_open3d_folder,
               read_open3d_folder),
        Format("RealSense recording", "a .bag file: cameras, rig, depth units and frame times as recorded; no poses",
               is_realsense_bag, read_realsense_bag, recording),
        Format("Azure Kinect recording", "an .mkv file, through Open3D with Microsoft's Azure Kinect SDK; no poses",
               is_azure_kinect_mkv, read_azure_kinect_mkv, recording),
    ):
        register_format(fmt)


_register_builtin_formats()
