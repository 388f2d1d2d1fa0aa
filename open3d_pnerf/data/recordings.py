"""Device recordings: a RealSense ``.bag`` (a ROS1 bag in librealsense's layout, read with rosbags)
and an Azure Kinect ``.mkv`` (``o3d.io.AzureKinectMKVReader``, where Open3D finds Microsoft's Azure
Kinect SDK).

Both are streams: a frame can only be read after the ones before it. The first load therefore
decodes the recording once, frame by frame, into a folder of lossless PNGs (colour, and depth in the
recording's own units) under the library's cache (``$XDG_CACHE_HOME/open3d_pnerf/recordings``, one
folder per recording file, its path, size and time), written to a temporary folder that is renamed
into place only when complete; later loads read the frames from there, lazily, as any folder's.
A RealSense frame keeps its depth camera and its time as recorded, the colour registered to it
through the recorded colour camera and depth-to-colour extrinsics (as 7-Scenes' Kinect); an Azure
Kinect frame's depth comes transformed into the colour camera by Open3D. The depth scale is the
recording's.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import struct
import tempfile
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag1 import ReaderError
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from .._files import cache_dir
from ..camera import check_intrinsic, pinhole
from ..errors import DatasetError
from .images import file_reader
from .sequence import RGBDSequence

EXTRACTED = "recording.json"  # written last: marks a complete extraction
AZURE_KINECT_DEPTH_SCALE = 1000.0  # millimetres
TYPES = get_typestore(Stores.ROS1_NOETIC)  # the ROS1 messages a RealSense bag holds besides its images


def is_realsense_bag(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".bag"


def is_azure_kinect_mkv(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".mkv"


def read_realsense_bag(path: Path, intrinsic=None, depth_trunc: float = 0.0, image_scale: float = 1.0) -> RGBDSequence:
    """A RealSense recording (see the module docstring); intrinsic overrides the recorded camera."""
    return _read_extracted(_extracted(path, _decode_bag), path, intrinsic, depth_trunc, image_scale)


def read_azure_kinect_mkv(path: Path, intrinsic=None, depth_trunc: float = 0.0,
                          image_scale: float = 1.0) -> RGBDSequence:
    """An Azure Kinect recording (see the module docstring); a DatasetError names what is missing
    where this Open3D cannot read one (it loads Microsoft's Azure Kinect SDK, libk4a and
    libk4arecord, at run time). Not tested here: no such SDK in this project's environment."""
    return _read_extracted(_extracted(path, _decode_mkv), path, intrinsic, depth_trunc, image_scale)


def _extracted(path: Path, decode) -> Path:
    """The folder of `path`'s decoded frames in the cache, decoding them first when it has none."""
    stat = path.stat()
    key = hashlib.sha256(f"{path.resolve()}\0{stat.st_size}\0{stat.st_mtime_ns}".encode()).hexdigest()[:20]
    folder = cache_dir() / "recordings" / f"{path.stem}-{key}"
    if (folder / EXTRACTED).is_file():
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    try:
        meta = decode(path, tmp)
        (tmp / EXTRACTED).write_text(json.dumps({**meta, "source": str(path.resolve())}, indent=1))
        if not (folder / EXTRACTED).is_file():  # another process (a rank of the same launch) may have finished first
            shutil.rmtree(folder, ignore_errors=True)  # a partial folder of an interrupted run
            os.replace(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _write_png(file: Path, image: np.ndarray) -> None:
    """A lossless PNG of a frame: colour (H, W, 3) uint8 RGB, or depth (H, W) uint16 in the recording's units."""
    if not cv2.imwrite(str(file), cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image):
        raise DatasetError(f"cannot write a frame extracted from a recording: {file}")


STREAM_IMAGES = re.compile(r"^/device_0/sensor_\d+/(Depth|Color)_\d+/image/data$")
COLOR_ENCODINGS = {"rgb8": None, "bgr8": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB, "bgra8": cv2.COLOR_BGRA2RGB,
                   "yuyv": cv2.COLOR_YUV2RGB_YUYV}


def _decode_bag(path: Path, folder: Path) -> dict:
    """Every colour frame of a RealSense bag that has a depth frame, into `folder`; the depth and colour
    cameras, the rig between them, the depth scale, the frame times (s) and the device.

    A bag is a ROS1 bag in librealsense's layout; rosbags reads its messages in order, every one (a
    real-time playback, as librealsense's and Open3D's readers do, drops frames and pairs a colour
    frame with an older depth frame when the machine is busy). Each colour frame takes the depth frame
    nearest in time, if one lies within half a frame period; the others are left out with a warning."""
    times, camera, rig, units, device = {"Depth": [], "Color": []}, {}, {}, None, {}
    for sub in ("all_color", "all_depth", "color", "depth"):
        (folder / sub).mkdir()
    try:
        with Reader1(path) as bag:
            for connection, _, raw in bag.messages():
                topic = connection.topic
                if match := STREAM_IMAGES.match(topic):
                    stream, (t, encoding, image) = match[1], _ros_image(raw, path)
                    _check_encoding(path, stream, encoding)
                    if COLOR_ENCODINGS.get(encoding) is not None:
                        image = cv2.cvtColor(image, COLOR_ENCODINGS[encoding])
                    _write_png(folder / f"all_{stream.lower()}" / f"{len(times[stream]):06d}.png", image)
                    times[stream].append(t)
                elif topic.endswith("/info/camera_info"):
                    info = TYPES.deserialize_ros1(raw, connection.msgtype)
                    camera[_stream(topic)] = (info.width, info.height, *info.K[[0, 4, 2, 5]].tolist())
                elif re.search(r"_\d+/tf/\d+$", topic):
                    move = TYPES.deserialize_ros1(raw, connection.msgtype)
                    rig[_stream(topic)] = _transform(move.rotation, move.translation)
                elif re.search(r"/option/Depth[ _]Units/value$", topic):
                    units = float(TYPES.deserialize_ros1(raw, connection.msgtype).data)
                elif topic == "/device_0/info":
                    pair = TYPES.deserialize_ros1(raw, connection.msgtype)
                    device[pair.key] = pair.value
    except (ReaderError, OSError, ValueError, struct.error) as exc:
        raise DatasetError(f"{path}: cannot read it as a RealSense recording (a ROS bag; a truncated one "
                           f"loses its index, kept at its end): {exc}") from None
    if not times["Depth"] or not times["Color"] or {"Depth", "Color"} - camera.keys():
        raise DatasetError(f"{path}: a RealSense recording with a depth and a colour stream and their cameras "
                           f"was expected; it has {len(times['Depth'])} depth and {len(times['Color'])} colour "
                           f"frames, and cameras for {sorted(camera) or 'neither'}")
    stamps = _pair_frames(folder, np.array(times["Color"]), np.array(times["Depth"]))
    if len(stamps) < len(times["Color"]):
        warnings.warn(f"{path}: {len(times['Color']) - len(stamps)} of {len(times['Color'])} colour frames have "
                      "no depth frame within half a frame period and are left out")
    if not stamps:
        raise DatasetError(f"{path}: no colour frame has a depth frame within half a frame period")
    if units is None:
        units = 0.001
        warnings.warn(f"{path}: the recording gives no depth units; the RealSense default, 1 mm, is assumed")
    to_color = rig.get("Color", np.eye(4)) @ np.linalg.inv(rig.get("Depth", np.eye(4)))
    return {"depth_camera": camera["Depth"], "color_camera": camera["Color"], "color_extrinsic": to_color.tolist(),
            "depth_scale": 1.0 / units, "timestamps": stamps, "device": device.get("Name", ""),
            "serial": device.get("Serial Number", "")}


def _pair_frames(folder: Path, color_times: np.ndarray, depth_times: np.ndarray) -> list[float]:
    """Moves each colour frame of folder/all_color that has a depth frame in folder/all_depth within half
    a frame period (the nearest) to folder/color, and that depth frame to folder/depth, numbered
    alike; returns the kept frames' times."""
    period = np.median(np.diff(color_times)) if len(color_times) > 1 else np.inf
    stamps = []
    for i, t in enumerate(color_times):
        j = int(np.argmin(np.abs(depth_times - t)))
        if abs(depth_times[j] - t) <= period / 2:
            name = f"{len(stamps):06d}.png"
            os.replace(folder / "all_color" / f"{i:06d}.png", folder / "color" / name)
            shutil.copyfile(folder / "all_depth" / f"{j:06d}.png", folder / "depth" / name)
            stamps.append(float(t))
    shutil.rmtree(folder / "all_color")
    shutil.rmtree(folder / "all_depth")
    return stamps


def _check_encoding(path: Path, stream: str, encoding: str) -> None:
    if (stream == "Depth" and encoding != "mono16") or (stream == "Color" and encoding not in COLOR_ENCODINGS):
        raise DatasetError(f"{path}: its {stream.lower()} stream is {encoding!r}; mono16 (Z16) depth and colour "
                           f"in {', '.join(COLOR_ENCODINGS)} are supported")


def _ros_image(raw: bytes, path: Path) -> tuple[float, str, np.ndarray]:
    """(time (s), encoding, pixels (H, W) or (H, W, C)) of a serialised sensor_msgs/Image. Read by
    hand, field by field: librealsense writes a few bytes after the pixels, which rosbags' strict
    deserialiser refuses."""
    _, sec, nsec, n = struct.unpack_from("<4I", raw)
    height, width, n = struct.unpack_from("<3I", raw, 16 + n)
    at = 28 + struct.unpack_from("<I", raw, 12)[0]
    encoding = raw[at:at + n].decode().lower()
    big_endian, (step, size) = raw[at + n], struct.unpack_from("<2I", raw, at + n + 1)
    pixels = np.frombuffer(raw, np.uint8, size, at + n + 9).reshape(height, step)
    if encoding in ("mono16", "16uc1"):
        image = pixels.view(">u2" if big_endian else "<u2")[:, :width].astype(np.uint16)
    else:
        image = pixels[:, :width * (step // width)].reshape(height, width, -1)
    if image.size == 0:
        raise DatasetError(f"{path}: an empty {encoding} image")
    return sec + nsec * 1e-9, encoding, np.ascontiguousarray(image)


def _stream(topic: str) -> str:
    """'Depth' or 'Color': the stream a librealsense topic (/device_0/sensor_0/Depth_0/...) is of."""
    return topic.split("/")[3].split("_")[0]


def _transform(rotation, translation) -> np.ndarray:
    """(4, 4) of a geometry_msgs Transform: a librealsense stream's extrinsics from its group's
    reference stream."""
    move = np.eye(4)
    move[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    move[:3, 3] = translation.x, translation.y, translation.z
    return move


def _decode_mkv(path: Path, folder: Path) -> dict:
    """Every frame of an Azure Kinect recording into `folder` (depth transformed into the colour camera
    by Open3D); its camera, depth scale and frame times (their order: the reader gives no time)."""
    if not hasattr(o3d.io, "AzureKinectMKVReader"):
        raise DatasetError(f"{path}: this Open3D build has no Azure Kinect support (o3d.io.AzureKinectMKVReader)")
    reader = o3d.io.AzureKinectMKVReader()
    try:
        opened = reader.open(str(path))
    except RuntimeError as exc:
        raise DatasetError(f"{path}: Open3D reads Azure Kinect recordings through Microsoft's Azure Kinect SDK "
                           f"(libk4a and libk4arecord, the k4a-tools packages), which it cannot load here: "
                           f"{str(exc).strip().splitlines()[-1]}") from None
    if not opened:
        raise DatasetError(f"{path}: Open3D's Azure Kinect reader cannot open it (not an Azure Kinect recording?)")
    try:
        meta, k = reader.get_metadata(), 0
        for sub in ("color", "depth"):
            (folder / sub).mkdir()
        while not reader.is_eof():
            frame = reader.next_frame()
            if frame is None:
                continue
            _write_png(folder / "color" / f"{k:06d}.png", np.asarray(frame.color)[..., :3])
            _write_png(folder / "depth" / f"{k:06d}.png", np.asarray(frame.depth).astype(np.uint16))
            k += 1
    finally:
        reader.close()
    if not k:
        raise DatasetError(f"{path}: the recording holds no colour and depth frame")
    camera = (meta.width, meta.height, *meta.intrinsics.get_focal_length(), *meta.intrinsics.get_principal_point())
    return {"depth_camera": camera, "color_camera": None, "color_extrinsic": None,
            "depth_scale": AZURE_KINECT_DEPTH_SCALE, "timestamps": list(range(k)), "device": "Azure Kinect",
            "serial": ""}


def _read_extracted(folder: Path, source: Path, intrinsic, depth_trunc: float, image_scale: float) -> RGBDSequence:
    """The sequence of a recording's extracted frames (read lazily from `folder`)."""
    meta = json.loads((folder / EXTRACTED).read_text())
    n = len(meta["timestamps"])
    if intrinsic is None:
        intrinsic = check_intrinsic(pinhole(*meta["depth_camera"]), f"{source}: the recorded depth camera")
    color_intrinsic = meta["color_camera"] and check_intrinsic(pinhole(*meta["color_camera"]),
                                                               f"{source}: the recorded colour camera")
    readers = [file_reader(folder / "color" / f"{k:06d}.png", folder / "depth" / f"{k:06d}.png", meta["depth_scale"])
               for k in range(n)]
    for read in readers:  # errors name the recording the frame came from
        read.source = f"{source} (extracted to {read.source})"
    return RGBDSequence(readers, intrinsic, meta["timestamps"], None, depth_trunc, color_intrinsic, source.stem,
                        image_scale, color_extrinsic=meta["color_extrinsic"])
