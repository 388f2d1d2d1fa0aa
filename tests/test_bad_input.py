"""Bad input gets a clear error at the API boundary: one table of cases (issue 6).

Each case builds a bad input in tmp_path (small real image files in TUM, 7-Scenes and
Redwood layouts, in-memory arrays, a saved reconstruction, a checkpoint), makes one public
call and expects an error type from open3d_pnerf.errors whose message names the culprit
(the file or the argument) and what was expected. test_the_good_inputs_are_accepted checks
that every builder's unmodified input loads, so each case fails for its own defect only.

Depth dtypes (files and memory alike): uint16 is raw sensor units divided by depth_scale,
float32/float64 is metres; anything else (8-bit, 3-channel, other integers) is rejected.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch
from conftest import tiny_reconstruction
from scipy.spatial.transform import Rotation

from open3d_pnerf import (
    Reconstruction,
    ReconstructionConfig,
    RGBDSequence,
    depth_targets,
    load_sequence,
    reconstruct,
    track,
    tsdf_fusion,
)
from open3d_pnerf.training import OptimizerConfig
from open3d_pnerf.data import read_log_trajectory, write_log_trajectory
from open3d_pnerf.errors import CheckpointError, ConfigError, DatasetError, InputError, PoseError

W, H = 32, 24


def pinhole(w=W, h=H, fx=30.0, fy=30.0, cx=15.5, cy=11.5):
    return o3d.camera.PinholeCameraIntrinsic(w, h, fx, fy, cx, cy)


K = pinhole()
CONFIG = ReconstructionConfig.preset("test", field="grid", progress=False, **{"grid.resolutions": (8, 16)})


# -- builders of good inputs -------------------------------------------------------------------
def write_image(path: Path, image: np.ndarray) -> Path:
    """Write with OpenCV (colour given as RGB); returns the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image[..., ::-1].copy() if image.ndim == 3 else image)
    return path


def colour(k: int = 0) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 256, (H, W, 3), dtype=np.uint8)


def rigid(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = t
    return pose


POSES = np.stack([rigid(t=(0.02 * k, 0, 0)) for k in range(3)])
TUM_RGB, TUM_DEPTH = (1.0, 1.5, 2.0), (1.004, 1.504, 2.004)


def tum(tmp: Path, raw: int = 7500) -> Path:
    """TUM folder: 3 associated frames at raw depth `raw` (/5000 = m) and a ground truth."""
    root = tmp / "rgbd_dataset_freiburg1_tiny"
    for k, (tc, td) in enumerate(zip(TUM_RGB, TUM_DEPTH)):
        write_image(root / "rgb" / f"{tc:.6f}.png", colour(k))
        write_image(root / "depth" / f"{td:.6f}.png", np.full((H, W), raw, np.uint16))
    (root / "rgb.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in TUM_RGB))
    (root / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in TUM_DEPTH))
    (root / "groundtruth.txt").write_text("0.5 0 0 0 0 0 0 1\n2.5 0.1 0 0 0 0 0 1\n")
    return root


def redwood(tmp: Path, raw: int = 1500) -> Path:
    """Open3D/Redwood folder: color/, depth/ (/1000 = m), camera.json, traj.log."""
    root = tmp / "rw"
    for k in range(3):
        write_image(root / "color" / f"{k:05d}.png", colour(k))
        write_image(root / "depth" / f"{k:05d}.png", np.full((H, W), raw, np.uint16))
    Kc = np.asarray(K.intrinsic_matrix)
    (root / "camera.json").write_text(json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": Kc.T.ravel().tolist(), "depth_scale": 1000.0}))
    write_log_trajectory(root / "traj.log", POSES)
    return root


def seven_scenes(tmp: Path, jpg: bool = False) -> Path:
    """7-Scenes folder: frame-XXXXXX.{color.png|color.jpg, depth.png, pose.txt}, camera-intrinsics.txt."""
    root = tmp / "kitchen"
    for k in range(2):
        write_image(root / f"frame-{k:06d}.color.{'jpg' if jpg else 'png'}", colour(k))
        write_image(root / f"frame-{k:06d}.depth.png", np.full((H, W), 1500, np.uint16))
        np.savetxt(root / f"frame-{k:06d}.pose.txt", POSES[k])
    np.savetxt(root / "camera-intrinsics.txt", np.asarray(K.intrinsic_matrix))
    return root


def frames(n: int = 3, depth=1.5) -> list:
    """In-memory (colour, depth) pairs; depth float32 metres unless an array is given."""
    d = np.full((H, W), depth, np.float32) if np.isscalar(depth) else depth
    return [(colour(k), d.copy()) for k in range(n)]


def memory(n: int = 3) -> RGBDSequence:
    return RGBDSequence.from_rgbd_images(frames(n), K, gt_poses=POSES[:n])


def saved(tmp: Path) -> Path:
    """A saved (untrained) reconstruction folder with every file."""
    return tiny_reconstruction().save(tmp / "recon")


def checkpoint_dir(tmp: Path) -> Path:
    """A folder holding a real (small) checkpoint.pt-like file: a dict of tensors."""
    d = tmp / "ckpt"
    d.mkdir()
    torch.save({"version": 1, "field": {"w": torch.arange(5000.0)}}, d / "checkpoint.pt")
    return d


# -- small edits ---------------------------------------------------------------------------------
def edit(build, change):
    """A builder: build(tmp), then change(root) to break it; returns root."""

    def make(tmp):
        root = build(tmp)
        change(root)
        return root

    return make


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def write_text(name: str, text: str):
    return lambda root: (root / name).write_text(text)


def edit_meta(**changes):
    def change(root):
        meta = json.loads((root / "reconstruction.json").read_text())
        for k, v in changes.items():
            if v is None:
                del meta[k]
            elif isinstance(v, dict) and isinstance(meta.get(k), dict):
                meta[k].update(v)
            else:
                meta[k] = v
        (root / "reconstruction.json").write_text(json.dumps(meta))

    return change


def broken(poses, index=1, nan=False):
    """A copy of poses whose pose `index` has a NaN translation (nan=True) or a scaled rotation."""
    poses = poses.copy()
    if nan:
        poses[index, 0, 3] = np.nan
    else:
        poses[index, :3, :3] *= 1.1
    return poses


def nan_depth() -> np.ndarray:
    depth = frames()[0][1]
    depth[5, 5] = np.nan
    return depth


# -- the table -----------------------------------------------------------------------------------
@dataclasses.dataclass
class Case:
    id: str
    build: Callable[[Path], object]
    """Makes the bad input in tmp_path."""
    call: Callable[[object], object]
    """The public call that must reject it."""
    error: type
    names: tuple
    """Substrings the message must contain: the culprit and what was expected."""


def load(root):
    return load_sequence(root, intrinsic=K)


def load_frame_2(root):
    return load(root)[2]


def in_memory(pairs):
    return RGBDSequence.from_rgbd_images(pairs, K)


def nothing(tmp):
    return None


CASES = [
    # folders and the files they list
    Case("missing-folder", lambda t: t / "no_such_scan", load, DatasetError, ("no_such_scan", "not found")),
    Case("path-is-a-file-of-no-known-kind", lambda t: (t / "scan.txt", (t / "scan.txt").write_text("x"))[0], load,
         DatasetError, ("scan.txt", "not a known layout", ".bag file")),
    Case("path-of-wrong-type", lambda t: 42, load, InputError, ("path", "int")),
    Case("unknown-layout", lambda t: (t / "mystery" / "images").mkdir(parents=True) or t / "mystery", load,
         DatasetError, ("mystery", "not a known layout", "rgb.txt")),
    Case("tum-listed-colour-missing", edit(tum, lambda r: (r / "rgb" / "1.500000.png").unlink()), load,
         DatasetError, ("1.500000.png", "rgb.txt", "do not exist")),
    Case("tum-listed-depth-missing", edit(tum, lambda r: (r / "depth" / "2.004000.png").unlink()), load,
         DatasetError, ("2.004000.png", "depth.txt")),
    Case("tum-empty-list", edit(tum, write_text("rgb.txt", "# only comments\n")), load, DatasetError,
         ("rgb.txt", "lists no entries")),
    Case("tum-line-without-filename", edit(tum, write_text("rgb.txt", "1.000000\n")), load, DatasetError,
         ("rgb.txt", "timestamp filename")),
    Case("tum-unassociable-timestamps",
         edit(tum, write_text("depth.txt", "".join(f"{t + 10:.6f} depth/{t:.6f}.png\n" for t in TUM_DEPTH))),
         load, DatasetError, ("depth.txt", "associate")),
    Case("tum-groundtruth-not-numbers", edit(tum, write_text("groundtruth.txt", "0.5 0 0 0 0 0 0 1\nabc 0 0 0 0 0 0 1\n")),
         load, DatasetError, ("groundtruth.txt", "timestamp tx ty tz qx qy qz qw")),
    Case("tum-groundtruth-7-columns", edit(tum, write_text("groundtruth.txt", "0.5 0 0 0 0 0 0 1\n2.5 0 0 0 0 0 1\n")),
         load, DatasetError, ("groundtruth.txt", "timestamp tx ty tz qx qy qz qw")),
    Case("tum-groundtruth-nan", edit(tum, write_text("groundtruth.txt", "0.5 0 0 0 0 0 0 1\n2.5 nan 0 0 0 0 0 1\n")),
         load, DatasetError, ("groundtruth.txt", "NaN")),
    Case("tum-groundtruth-zero-quaternion", edit(tum, write_text("groundtruth.txt", "0.5 0 0 0 0 0 0 1\n2.5 0 0 0 0 0 0 0\n")),
         load, DatasetError, ("groundtruth.txt", "quaternion")),
    Case("7scenes-missing-colour", edit(seven_scenes, lambda r: (r / "frame-000001.color.png").unlink()), load,
         DatasetError, ("frame-000001.color.png", "missing")),
    Case("7scenes-pose-not-4x4", edit(seven_scenes, write_text("frame-000001.pose.txt", "1 0 0\n0 1 0\n0 0 1\n")),
         load, DatasetError, ("frame-000001.pose.txt", "4x4")),
    Case("7scenes-pose-not-rigid", edit(seven_scenes, lambda r: np.savetxt(r / "frame-000001.pose.txt", 2 * np.eye(4))),
         load, PoseError, ("frame-000001.pose.txt", "not rigid")),
    Case("7scenes-intrinsics-negative-focal",
         edit(seven_scenes, lambda r: np.savetxt(r / "camera-intrinsics.txt", np.diag([-30.0, 30.0, 1.0]))),
         load_sequence, InputError, ("camera-intrinsics.txt", "positive", "focal")),
    Case("redwood-colour-and-depth-counts-differ", edit(redwood, lambda r: (r / "depth" / "00002.png").unlink()),
         load, DatasetError, ("3 colour images in color/", "2 in depth/")),
    Case("redwood-intrinsic-json-malformed", edit(redwood, write_text("camera.json", json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": [1, 2, 3, 4]}))), load_sequence, DatasetError,
         ("camera.json", "9-value intrinsic_matrix")),
    Case("redwood-intrinsic-json-depth-scale", edit(redwood, write_text("camera.json", json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": np.asarray(K.intrinsic_matrix).T.ravel().tolist(),
         "depth_scale": -1}))), load_sequence, DatasetError, ("camera.json", "depth_scale > 0")),
    Case("redwood-trajectory-nan", edit(redwood, lambda r: write_log_trajectory(r / "traj.log", broken(POSES, nan=True))),
         load, PoseError, ("traj.log", "NaN", "[1]")),
    Case("log-not-5-lines-per-pose", lambda t: (t / "bad.log", (t / "bad.log").write_text("0 0 1\n1 0 0 0\n"))[0],
         read_log_trajectory, DatasetError, ("bad.log", "5 lines per pose")),
    Case("log-not-numbers", lambda t: (t / "bad.log", (t / "bad.log").write_text("0 0 1\n1 0 0 0\n0 1 x 0\n" * 5))[0],
         read_log_trajectory, DatasetError, ("bad.log", "malformed")),
    # load_sequence's own arguments
    *[Case(f"load-argument-{k}={v}", redwood, lambda r, k=k, v=v: load_sequence(r, **{k: v}), InputError, (k,))
      for k, v in [("stride", 0), ("stride", 1.5), ("max_frames", 0), ("depth_scale", -5.0), ("depth_trunc", -1.0),
                   ("image_scale", 0.0), ("image_scale", 2.0)]],
    # unreadable, truncated or inconsistent images
    Case("garbage-bytes-as-png", edit(redwood, lambda r: (r / "color" / "00000.png").write_bytes(b"not a png" * 20)),
         load, DatasetError, ("color/00000.png", "cannot decode")),
    Case("garbage-png-found-when-the-frame-is-read", edit(redwood, lambda r: (r / "color" / "00002.png").write_bytes(b"x")),
         load_frame_2, DatasetError, ("color/00002.png", "cannot decode")),
    Case("garbage-png-found-by-the-tracker-reading-ahead",
         edit(redwood, lambda r: (r / "color" / "00002.png").write_bytes(b"x")),
         lambda root: track(load(root), progress=False), DatasetError, ("color/00002.png", "cannot decode")),
    Case("empty-depth-png", edit(redwood, lambda r: (r / "depth" / "00000.png").write_bytes(b"")), load,
         DatasetError, ("depth/00000.png", "cannot decode")),
    Case("truncated-depth-png", edit(redwood, lambda r: truncate(r / "depth" / "00000.png")), load, DatasetError,
         ("depth/00000.png", "truncated")),
    Case("truncated-colour-jpg", edit(lambda t: seven_scenes(t, jpg=True), lambda r: truncate(r / "frame-000000.color.jpg")),
         load, DatasetError, ("frame-000000.color.jpg", "truncated")),
    Case("colour-and-depth-sizes-differ", edit(redwood, lambda r: write_image(r / "color" / "00000.png", colour()[::2, ::2])),
         load, DatasetError, ("color/00000.png", "colour is 16x12", "32x24")),
    Case("colour-and-depth-sizes-differ-in-memory", lambda t: [(colour()[::2, ::2], frames()[0][1])], in_memory,
         DatasetError, ("images[0]", "colour is 16x12", "32x24")),
    Case("depth-size-differs-from-intrinsic", redwood, lambda r: load_sequence(r, intrinsic=pinhole(64, 48, cx=31.5, cy=23.5)),
         DatasetError, ("depth/00000.png", "depth is 32x24 but the intrinsic is 64x48")),
    Case("depth-all-zero", lambda t: redwood(t, raw=0), load, DatasetError, ("depth/00000.png", "no valid depth")),
    Case("depth-all-zero-in-memory", lambda t: frames(depth=0.0), in_memory, DatasetError, ("images[0]", "no valid depth")),
    Case("depth-negative", lambda t: frames(2) + [(colour(), np.full((H, W), -1.5, np.float32))], in_memory,
         DatasetError, ("images[2]", "negative", ">= 0 metres")),
    Case("depth-nan", lambda t: [(colour(), nan_depth())], in_memory, DatasetError, ("images[0]", "NaN")),
    Case("depth-nan-in-an-rgbdimage", lambda t: [o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(colour()), o3d.geometry.Image(nan_depth()), depth_scale=1.0, convert_rgb_to_intensity=False)],
         in_memory, DatasetError, ("images[0]", "NaN")),
    Case("depth-8-bit-png", edit(redwood, lambda r: write_image(r / "depth" / "00000.png", np.full((H, W), 200, np.uint8))),
         load, DatasetError, ("depth/00000.png", "uint16", "uint8")),
    Case("depth-png-with-3-channels", edit(redwood, lambda r: write_image(r / "depth" / "00000.png", colour())),
         load, DatasetError, ("depth/00000.png", "single-channel")),
    Case("depth-uint8-in-memory", lambda t: frames(depth=np.full((H, W), 2, np.uint8)), in_memory, DatasetError,
         ("images[0]", "uint16", "uint8")),
    Case("depth-int64-in-memory", lambda t: frames(depth=np.full((H, W), 1500, np.int64)), in_memory, DatasetError,
         ("images[0]", "uint16", "int64")),
    Case("depth-scale-wrong-30-m-median", lambda t: tum(t, raw=3000), lambda r: load_sequence(r, intrinsic=K, depth_scale=100),
         DatasetError, ("depth/1.004000.png", "median depth is 30 m", "depth_scale=")),
    Case("depth-scale-wrong-7-mm-median", tum, lambda r: load_sequence(r, intrinsic=K, depth_scale=1e6), DatasetError,
         ("median depth is 0.0075 m", "depth_scale=")),
    Case("depth-scale-missing-for-uint16-in-memory", lambda t: frames(depth=np.full((H, W), 1500, np.uint16)), in_memory,
         DatasetError, ("images[0]", "median depth is 1.5e+03 m", "depth_scale=")),
    Case("depth-scale-negative-in-memory", lambda t: frames(),
         lambda p: RGBDSequence.from_rgbd_images(p, K, depth_scale=-1.0), InputError, ("depth_scale", "> 0")),
    # intrinsics
    Case("intrinsic-not-a-pinhole", lambda t: frames(), lambda p: RGBDSequence.from_rgbd_images(p, np.eye(3)),
         InputError, ("intrinsic", "PinholeCameraIntrinsic", "ndarray")),
    Case("intrinsic-negative-focal", lambda t: frames(), lambda p: RGBDSequence.from_rgbd_images(p, pinhole(fx=-30.0)),
         InputError, ("intrinsic", "positive", "fx=-30")),
    Case("intrinsic-of-another-image-size", redwood, lambda r: load_sequence(r, intrinsic=pinhole(cx=319.5, cy=239.5)),
         InputError, ("intrinsic", "principal point (319.5, 239.5)", "32x24")),
    Case("color-intrinsic-negative-focal", redwood, lambda r: load_sequence(r, color_intrinsic=pinhole(fy=-1.0)),
         InputError, ("color_intrinsic", "positive")),
    Case("color-extrinsic-not-rigid", redwood, lambda r: load_sequence(r, color_extrinsic=2 * np.eye(4)),
         PoseError, ("color_extrinsic",)),
    # sequences: empty, too short, not a sequence
    Case("no-frames", lambda t: [], in_memory, InputError, ("no frames",)),
    Case("rgbdimage-with-grey-colour", lambda t: [o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(colour()), o3d.geometry.Image(frames()[0][1]))], in_memory, InputError,
         ("images[0]", "convert_rgb_to_intensity=False")),
    Case("frame-is-not-a-pair", lambda t: [np.zeros((H, W))], in_memory, InputError, ("images[0]", "(color, depth) pair")),
    Case("timestamps-count", lambda t: frames(), lambda p: RGBDSequence.from_rgbd_images(p, K, timestamps=[0.0]),
         InputError, ("timestamps", "1 timestamps for 3 frames")),
    Case("track-a-single-frame", lambda t: memory(1), lambda s: track(s, progress=False), InputError,
         ("sequence", "at least 2 frames")),
    Case("track-keyframe-every-0", lambda t: memory(), lambda s: track(s, keyframe_every=0, progress=False), InputError,
         ("keyframe_every", ">= 1")),
    Case("track-a-list", lambda t: frames(), lambda p: track(p, progress=False), InputError, ("sequence", "RGBDSequence")),
    Case("reconstruct-a-single-frame", lambda t: memory(1), lambda s: reconstruct(s, CONFIG, poses=POSES[:1]),
         InputError, ("rgbd_sequence", "at least 2 frames")),
    Case("depth-targets-of-a-list", lambda t: frames(), lambda p: depth_targets(p, poses=POSES, progress=False),
         InputError, ("sequence", "RGBDSequence")),
    Case("tsdf-fusion-of-a-folder-name", redwood, lambda r: tsdf_fusion(str(r), POSES, progress=False), InputError,
         ("sequence", "RGBDSequence", "str")),
    # poses and covariances
    Case("gt-poses-count", lambda t: frames(), lambda p: RGBDSequence.from_rgbd_images(p, K, gt_poses=POSES[:2]),
         PoseError, ("gt_poses", "2 poses for 3 frames")),
    Case("poses-nan", lambda t: memory(), lambda s: tsdf_fusion(s, broken(POSES, 2, nan=True), progress=False),
         PoseError, ("poses", "NaN", "[2]")),
    Case("poses-wrong-shape", lambda t: memory(), lambda s: depth_targets(s, poses=POSES[:, :3], progress=False),
         PoseError, ("poses", "(N, 4, 4)", "(3, 3, 4)")),
    Case("poses-not-rigid", lambda t: memory(), lambda s: reconstruct(s, CONFIG, poses=broken(POSES)),
         PoseError, ("poses", "not rigid", "[1]")),
    Case("poses-reflection", lambda t: memory(), lambda s: depth_targets(s, poses=POSES @ np.diag([1, 1, -1, 1]), progress=False),
         PoseError, ("poses", "det != 1")),
    Case("poses-missing", lambda t: memory(), lambda s: depth_targets(s, progress=False), InputError,
         ("trajectory or poses",)),
    Case("covariances-count", lambda t: memory(), lambda s: reconstruct(s, CONFIG, poses=POSES, covariances=np.zeros((2, 6, 6))),
         InputError, ("covariances", "(3, 6, 6)", "(2, 6, 6)")),
    Case("covariances-nan", lambda t: memory(),
         lambda s: depth_targets(s, poses=POSES, covariances=np.full((3, 6, 6), np.nan), progress=False),
         InputError, ("covariances", "finite")),
    # configuration
    Case("config-unknown-field", nothing, lambda _: ReconstructionConfig.preset("test", bogus=1), ConfigError,
         ("bogus", "valid fields")),
    Case("config-wrong-type", nothing, lambda _: ReconstructionConfig.from_dict({"max_steps": "ten"}), ConfigError,
         ("max_steps", "an int >= 1")),
    Case("config-unknown-value", nothing, lambda _: ReconstructionConfig.preset("test", loss="l2"), ConfigError,
         ("loss", "'l2'", "pnerf")),
    Case("config-negative-systematic-sigma", nothing,
         lambda _: ReconstructionConfig.preset("test", **{"targets.depth_sigma_relative": -0.02}), ConfigError,
         ("depth_sigma_relative", "[0, 1)")),
    Case("config-adam-beta2-one", nothing,
         lambda _: ReconstructionConfig.preset("test", **{"optimizer.adam_beta2": 1.0}), ConfigError,
         ("adam_beta2", "[0, 1)")),
    Case("config-sub-config-not-a-dict", nothing, lambda _: ReconstructionConfig.preset("test", sampling=16),
         ConfigError, ("sampling=16", "dict")),
    Case("config-unknown-preset", nothing, lambda _: ReconstructionConfig.preset("tiny"), ConfigError, ("tiny", "fast")),
    Case("config-invalid-reaches-reconstruct", lambda t: memory(),
         lambda s: reconstruct(s, dataclasses.replace(CONFIG, optimizer=OptimizerConfig(rays_per_batch=0)),
                               poses=POSES), ConfigError,
         ("rays_per_batch=0", "an int >= 1")),
    Case("config-not-a-config", lambda t: memory(), lambda s: reconstruct(s, {"max_steps": 5}, poses=POSES), InputError,
         ("config", "ReconstructionConfig", "dict")),
    Case("holdout-leaves-no-training-frames", lambda t: memory(),
         lambda s: reconstruct(s, CONFIG.replace(holdout_every=1), poses=POSES), InputError, ("holdout_every=1",)),
    # saved reconstructions
    Case("saved-folder-without-json", lambda t: t, Reconstruction.load, CheckpointError, ("reconstruction.json missing",)),
    Case("saved-json-corrupt", edit(saved, write_text("reconstruction.json", "{not json")), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "corrupt JSON")),
    Case("saved-json-truncated", edit(saved, lambda r: truncate(r / "reconstruction.json")), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "corrupt JSON")),
    Case("saved-json-not-an-object", edit(saved, write_text("reconstruction.json", "[1, 2]")), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "JSON object")),
    Case("saved-json-incomplete", edit(saved, edit_meta(intrinsic=None)), Reconstruction.load, CheckpointError,
         ("reconstruction.json", "missing ['intrinsic']")),
    Case("saved-json-malformed-box", edit(saved, edit_meta(aabb=[1, 2])), Reconstruction.load, CheckpointError,
         ("reconstruction.json", "malformed")),
    Case("saved-json-bad-depth-dof", edit(saved, edit_meta(depth_error={"scale": 1.0, "floor": 0.0, "dof": -1.0})),
         Reconstruction.load, CheckpointError, ("reconstruction.json", "dof > 0 or null", "-1.0")),
    Case("saved-json-depth-error-not-a-law", edit(saved, edit_meta(depth_error=2.0)), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "depth_error 2.0",
                           "{scale, floor, dof[, unseen, unseen_ramp, edge, through]}")),
    Case("saved-json-bad-edge-term", edit(saved, edit_meta(depth_error={"scale": 1.0, "floor": 0.0, "dof": None,
                                                                        "edge": float("nan")})),
         Reconstruction.load, CheckpointError, ("reconstruction.json", "edge >= 0", "nan")),
    Case("saved-json-bad-through-term", edit(saved, edit_meta(depth_error={"scale": 1.0, "floor": 0.0, "dof": None,
                                                                           "through": -1.0})),
         Reconstruction.load, CheckpointError, ("reconstruction.json", "through >= 0", "-1.0")),
    Case("saved-json-bad-unseen-term", edit(saved, edit_meta(depth_error={"scale": 1.0, "floor": 0.0, "dof": None,
                                                                          "unseen": -0.5, "unseen_ramp": 0.01})),
         Reconstruction.load, CheckpointError, ("reconstruction.json", "unseen >= 0", "-0.5")),
    Case("saved-observed-not-points", edit(saved, lambda r: np.save(r / "observed.npy", np.ones((4, 2)))),
         Reconstruction.load, CheckpointError, ("observed.npy", "(None, 3)")),
    Case("saved-observed-depths-wrong-size",
         edit(saved, lambda r: np.save(r / "observed_depths.npy", np.ones((1, 4, 4)))),
         Reconstruction.load, CheckpointError, ("observed_depths.npy", "shape")),
    Case("saved-json-bad-depth-range", edit(saved, edit_meta(depth_range=[2.0, 1.0])), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "depth_range [2.0, 1.0]", "0 < near < far")),
    Case("saved-json-indices-out-of-range", edit(saved, edit_meta(train_indices=[1, 7])), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "frame indices outside [0, 3)")),
    Case("saved-json-future-format", edit(saved, edit_meta(format_version=99)), Reconstruction.load, CheckpointError,
         ("reconstruction.json", "format version 99")),
    Case("saved-json-unknown-config-field", edit(saved, edit_meta(config={"bogus": 1})), Reconstruction.load,
         CheckpointError, ("reconstruction.json", "bogus")),
    Case("saved-model-truncated", edit(saved, lambda r: truncate(r / "model.pt")), Reconstruction.load, CheckpointError,
         ("model.pt", "not a valid")),
    Case("saved-model-of-another-config", edit(saved, edit_meta(config={"field": "grid", "grid": {"resolutions": [8]}})),
         Reconstruction.load, CheckpointError, ("model.pt", "do not match")),
    Case("saved-poses-missing", edit(saved, lambda r: (r / "poses.npy").unlink()), Reconstruction.load, CheckpointError,
         ("poses.npy", "missing")),
    Case("saved-poses-wrong-shape", edit(saved, lambda r: np.save(r / "poses.npy", POSES[:2])), Reconstruction.load,
         CheckpointError, ("poses.npy", "(3, 4, 4)")),
    Case("saved-color-gains-wrong-shape", edit(saved, lambda r: np.save(r / "color_gains.npy", np.ones((2, 3)))),
         Reconstruction.load, CheckpointError, ("color_gains.npy", "(3, 3)")),
    Case("saved-color-gains-negative", edit(saved, lambda r: np.save(r / "color_gains.npy", -np.ones((3, 3)))),
         Reconstruction.load, CheckpointError, ("color_gains.npy", "> 0")),
    Case("saved-mesh-corrupt", edit(saved, lambda r: (r / "mesh.ply").write_bytes(b"ply\ngarbage")), Reconstruction.load,
         CheckpointError, ("mesh.ply", "unreadable")),
    # training checkpoints: rejected before any tracking or training
    Case("resume-checkpoint-truncated", edit(checkpoint_dir, lambda d: truncate(d / "checkpoint.pt")),
         lambda d: reconstruct(memory(), CONFIG, poses=POSES, checkpoint_dir=d, resume=True), CheckpointError,
         ("checkpoint.pt", "not a valid")),
    Case("resume-checkpoint-missing", lambda t: t, lambda d: reconstruct(memory(), CONFIG, poses=POSES, checkpoint_dir=d,
                                                                          resume=True), CheckpointError,
         ("checkpoint.pt", "not found")),
    Case("resume-checkpoint-of-another-version", edit(checkpoint_dir, lambda d: torch.save({"version": 99}, d / "checkpoint.pt")),
         lambda d: reconstruct(memory(), CONFIG, poses=POSES, checkpoint_dir=d, resume=True), CheckpointError,
         ("checkpoint.pt", "version 99")),
    Case("resume-without-checkpoint-dir", lambda t: memory(), lambda s: reconstruct(s, CONFIG, poses=POSES, resume=True),
         InputError, ("resume=True", "checkpoint_dir")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_raises_a_named_error(case, tmp_path):
    bad = case.build(tmp_path)
    with pytest.raises(case.error) as info:
        case.call(bad)
    message = str(info.value)
    assert isinstance(info.value, InputError), type(info.value)
    for name in case.names:
        assert name in message, f"{name!r} not in {message!r}"


def test_case_ids_are_unique():
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids))


def test_the_good_inputs_are_accepted(tmp_path):
    """The builders' unmodified inputs load: each case above fails for its own defect."""
    for k, build in enumerate((tum, redwood, seven_scenes, lambda t: seven_scenes(t, jpg=True))):
        root = build(tmp_path / str(k))
        seq = load(root)
        assert len(seq) in (2, 3) and seq.gt_poses is not None
        assert all(f.depth.shape == (H, W) and (f.depth == 1.5).all() for f in seq)
    assert len(memory()) == 3
    loaded = Reconstruction.load(saved(tmp_path))
    assert len(loaded.poses) == 3 and loaded.mesh is not None and loaded.point_cloud is not None
    stats = reconstruct(memory(), CONFIG.replace(max_steps=1), poses=POSES).stats["training"]
    assert stats["steps"] == 1


def test_depth_dtypes_uint16_and_float_are_accepted_consistently():
    """uint16 is divided by depth_scale; float32 and float64 are metres, in memory as in RGBDImage."""
    raw = np.full((H, W), 3000, np.uint16)
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(colour()), o3d.geometry.Image(raw), depth_scale=2000.0, convert_rgb_to_intensity=False)
    for images in ([(colour(), raw)], [(colour(), raw / 2000.0)], [(colour(), (raw / 2000.0).astype(np.float32))], [rgbd]):
        seq = RGBDSequence.from_rgbd_images(images, K, depth_scale=2000.0)
        depth = seq[0].depth
        assert depth.dtype == np.float32 and (depth == 1.5).all()
