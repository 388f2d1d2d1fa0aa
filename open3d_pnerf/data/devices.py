"""Frames that come from devices: a live stream's frames as the mapper keeps them
(:class:`StreamFrames`), and live RGB-D cameras driven by Open3D (:func:`camera_frames`)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..errors import InputError
from .sequence import Frame, RGBDSequence


class StreamFrames:
    """The frames of a stream that the tracker may still read, by index (what FrameRegistration needs):
    images {index: (colour uint8 (H, W, 3), depth (H, W) m, timestamp s)} of the camera `intrinsic`."""

    def __init__(self, intrinsic: o3d.camera.PinholeCameraIntrinsic):
        self.intrinsic = self.color_intrinsic = intrinsic
        self.K = np.asarray(intrinsic.intrinsic_matrix, np.float64)
        self.image_size = (intrinsic.height, intrinsic.width)
        self.name = "stream"
        self.images: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}

    def __len__(self) -> int:
        """Frames received so far (indices from 0; only the kept ones can still be read)."""
        return max(self.images, default=-1) + 1

    def __getitem__(self, index: int) -> Frame:
        if index not in self.images:
            raise InputError(f"stream frame {index} is no longer kept (neither a keyframe nor a held-out frame)")
        color, depth, timestamp = self.images[index]
        return Frame(color, depth, timestamp, index)

    color_registered = True

    def color_on_depth_grid(self, color: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        return color

    def sequence(self, indices: list[int], name: str = "stream") -> RGBDSequence:
        """The kept frames `indices` as an in-memory RGBDSequence."""
        frames = [self.images[i] for i in indices]
        return RGBDSequence.from_rgbd_images([(c, d) for c, d, _ in frames], self.intrinsic,
                                             timestamps=[t for _, _, t in frames], name=name)


def camera_frames(kind: str, intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None):
    """(intrinsic, generator of (colour, depth in metres) frames) of a live camera that Open3D
    drives: "realsense" (``o3d.t.io.RealSenseSensor``, depth aligned to colour; its intrinsic from
    the sensor unless `intrinsic` is given) or "azure-kinect" (``o3d.io.AzureKinectSensor``, which
    does not report its intrinsic: `intrinsic` is needed). Untested here (no camera): a thin path
    over Open3D's own sensor classes; everything after the frames is what recorded folders go
    through."""
    if kind == "realsense":
        if not hasattr(o3d.t.io, "RealSenseSensor"):
            raise InputError("--camera realsense: this Open3D build has no RealSense support")
        sensor = o3d.t.io.RealSenseSensor()
        sensor.init_sensor(o3d.t.io.RealSenseSensorConfig({"align_depth_to_color": "true"}), 0, "")
        sensor.start_capture()
        meta = sensor.get_metadata()
        intrinsic = intrinsic or meta.intrinsics
        scale = float(meta.depth_scale)

        def frames():
            try:
                while True:
                    rgbd = sensor.capture_frame(True, True).to_legacy()
                    yield (np.asarray(rgbd.color), np.asarray(rgbd.depth).astype(np.float32) / scale)
            finally:
                sensor.stop_capture()
        return intrinsic, frames()
    if kind == "azure-kinect":
        if intrinsic is None:
            raise InputError("--camera azure-kinect needs --intrinsic FILE (an Open3D PinholeCameraIntrinsic JSON of "
                             "the colour camera the depth is aligned to): Open3D's live sensor does not report it")
        if not hasattr(o3d.io, "AzureKinectSensor"):
            raise InputError("--camera azure-kinect: this Open3D build has no Azure Kinect support")
        sensor = o3d.io.AzureKinectSensor(o3d.io.AzureKinectSensorConfig())
        if not sensor.connect(0):
            raise InputError("--camera azure-kinect: no Azure Kinect found")

        def frames():
            while True:
                rgbd = sensor.capture_frame(True)
                if rgbd is not None:
                    yield (np.asarray(rgbd.color), np.asarray(rgbd.depth).astype(np.float32) / 1000.0)
        return intrinsic, frames()
    raise InputError(f"--camera {kind!r}: expected 'realsense' or 'azure-kinect'")
