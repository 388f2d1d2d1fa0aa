"""Mapping as you go: a live RGB-D stream tracked frame by frame, its keyframes kept and trained on
between frames, a renderable Reconstruction at any moment.

    mapper = Mapper(intrinsic)
    for rgbd in camera:                        # o3d.geometry.RGBDImage, depth in metres
        pose, covariance = mapper.add(rgbd)    # tracked now; training runs after it, within a budget
    recon = mapper.finish()                    # a further training budget on every keyframe, then export
    mapper.save("map/")                        # the map, and what it takes to go on: Mapper.resume("map/")
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from ._files import atomic_write, read_json_object
from .batches import RayBatcher
from .camera import adjoint, check_intrinsic, motion
from .config import ReconstructionConfig
from .data.derived import evenly_spaced
from .data.devices import StreamFrames
from .data.sequence import RGBDSequence
from .errors import CheckpointError, InputError
from .evaluation import heldout_scores
from .export import export_geometry
from .fields import EncodedField
from .model import build_model
from .observed import ObservedSurface
from .occupancy import OccupancyGrid
from .reconstruction import Reconstruction
from .scene import BOX_MARGIN, scene_box
from .stages import checked_config
from .targets import DepthTargets
from .tracking.chain import Chain
from .tracking.loops import close_loops
from .tracking.odometry import FrameRegistration, OdometryOptions
from .tracking.recovery import place_on_map, track_frame
from .training import Trainer

MAPPER_STATE = "mapper.json"
TARGET_WINDOW = 3  # a new keyframe's depth targets fuse it with the keyframes just before it (this many in all)


class Mapper:
    """Maps a live RGB-D stream (see the module docstring).

    intrinsic: the depth camera's ``o3d.camera.PinholeCameraIntrinsic`` (colour registered to
    depth, as Open3D's sensors deliver with alignment on). config: a ReconstructionConfig
    (default: the fast preset); its ``mapping`` settings pick keyframes and the per-frame
    training budget, its ``tracking.loop_closure`` closes loops at every keyframe.
    depth_scale: raw depth units per metre of a uint16 depth image (Open3D's sensors: 1000).
    """

    def __init__(self, intrinsic: o3d.camera.PinholeCameraIntrinsic, config: ReconstructionConfig | None = None,
                 depth_scale: float = 1000.0):
        self.intrinsic = check_intrinsic(intrinsic)
        self.config = checked_config(config)
        if not depth_scale > 0:
            raise InputError(f"depth_scale must be > 0 (raw units per metre), got {depth_scale!r}")
        self.depth_scale = float(depth_scale)
        self.frames = StreamFrames(self.intrinsic)
        self.chain: Chain | None = None
        self.keyframes: list[int] = []
        self.holdout: list[int] = []
        self.timestamps: list[float] = []
        self.covariances: list[np.ndarray] = []  # of each frame when it was tracked
        self.targets: dict[int, tuple[np.ndarray, ...]] = {}  # keyframe -> (mean, sigma, valid, support, filled)
        self.field: torch.nn.Module | None = None
        self.aabb: np.ndarray | None = None
        self.trainer: Trainer | None = None
        self.steps = 0
        self.seconds = {"tracking": 0.0, "targets": 0.0, "training": 0.0}
        self._overrun = 0.0  # training seconds past the per-frame budget, taken from the next frames'
        self._since_keyframe = 0
        self._resumed: tuple[int, np.ndarray] | None = None  # (kept frames, their covariances) of a resumed map
        self._anchor: int | None = None  # the resumed map's frame the stream was placed from
        self._occupancy: tuple[tuple, OccupancyGrid] | None = None  # (what it was built from, the grid)

    # -- the stream -------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses of every frame added (as the pose graph has them now)."""
        return np.stack(self.chain.poses) if self.chain else np.zeros((0, 4, 4))

    def add(self, rgbd_image, timestamp: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Track one frame and train the map for ``config.mapping.train_s_per_frame`` seconds.

        rgbd_image: an ``o3d.geometry.RGBDImage`` (colour uint8 RGB, depth float metres or uint16
        raw units per depth_scale) of the mapper's intrinsic size, or a (color, depth) pair of
        arrays. timestamp: seconds (default: the frame's number). Returns the frame's pose (4, 4)
        camera-to-world and its covariance (6, 6) [rotation, translation] in the pose graph now.
        """
        index = len(self.timestamps)
        color, depth = self._arrays(rgbd_image, index)
        stamp = float(index if timestamp is None else timestamp)
        if self.timestamps and not stamp > self.timestamps[-1]:
            raise InputError(f"add(): timestamp {stamp} does not follow the last frame's {self.timestamps[-1]}")
        self.frames.images[index] = (color, depth, stamp)
        t0 = time.perf_counter()
        try:
            if self.chain is None:
                self.chain = Chain(FrameRegistration(self.frames), OdometryOptions())
            elif self._resumed is not None and index == self._resumed[0]:  # placed on the map, never guessed
                self._anchor = place_on_map(self.chain, index, [int(j) for j in evenly_spaced(index - 1, 8)], "stream")
            else:
                track_frame(self.chain, index)
        except BaseException:  # the frame is not added: the mapper stays as it was
            del self.frames.images[index]
            if self.chain is not None:
                self.chain.registrar.forget(index)
                self.chain.edges = [e for e in self.chain.edges if e.target != index]
            raise
        self.timestamps.append(stamp)
        keyframe = self._is_keyframe(index)
        if keyframe:
            self.keyframes.append(index)
            loops = self.config.mapping.loops_per_keyframe
            if self.config.tracking.loop_closure and loops and len(self.keyframes) > 2:
                close_loops(self.chain, self.frames, self.keyframes, self.chain.options, None, 1.0, 45.0, loops, False,
                            new_from=index)
        elif (self.config.holdout_every and index not in self.chain.failed_frames
              and self._since_keyframe == self.config.mapping.keyframe_every // 2):
            self.holdout.append(index)
        self._forget_frames(index)
        covariance = self._covariances([index])[0]
        self.covariances.append(covariance)
        self.seconds["tracking"] += time.perf_counter() - t0
        if keyframe:
            self._add_keyframe(index)
        self._train_within_budget()
        return self.chain.poses[index].copy(), covariance

    def _train_within_budget(self) -> None:
        """Train for the per-frame budget less what earlier frames ran past theirs (a step is never
        cut short), so that the stream trains ``config.mapping.train_s_per_frame`` per frame on average."""
        allowance = self.config.mapping.train_s_per_frame - self._overrun
        if allowance <= 0:  # this frame repays an earlier step's overrun
            self._overrun = -allowance
        else:
            self._overrun = max(0.0, self.train(allowance) - allowance)

    def _arrays(self, rgbd_image, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(colour uint8 (H, W, 3), depth float32 metres (H, W)) of what add() was given, checked."""
        if isinstance(rgbd_image, o3d.geometry.RGBDImage):
            color, depth = np.asarray(rgbd_image.color), np.asarray(rgbd_image.depth)
        elif isinstance(rgbd_image, (tuple, list)) and len(rgbd_image) == 2:
            color, depth = (np.asarray(a) for a in rgbd_image)
        else:
            raise InputError(f"add(): frame {index} must be an o3d.geometry.RGBDImage or a (color, depth) pair, "
                             f"got {type(rgbd_image).__name__}")
        size = (self.intrinsic.height, self.intrinsic.width)
        if color.shape != (*size, 3) or color.dtype != np.uint8:
            raise InputError(f"add(): frame {index}'s colour is {color.dtype} {color.shape}, expected uint8 "
                             f"{(*size, 3)} (the intrinsic's size; an RGBDImage made with "
                             "convert_rgb_to_intensity=False)")
        if depth.shape != size:
            raise InputError(f"add(): frame {index}'s depth is {depth.shape}, expected {size} (the intrinsic's size)")
        if np.issubdtype(depth.dtype, np.integer):
            depth = depth.astype(np.float32) / self.depth_scale
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        return np.ascontiguousarray(color), depth

    def _is_keyframe(self, index: int) -> bool:
        """Whether frame `index` (just tracked) becomes a keyframe: the first, every keyframe_every-th
        since the last, or one the camera moved or turned far enough from the last; never a frame
        that no registration placed (its pose is a guess: it is not trained on)."""
        cfg = self.config.mapping
        if index in self.chain.failed_frames:
            return False
        self._since_keyframe += 1
        if self.keyframes:
            moved_m, turned_deg = motion(np.linalg.inv(self.chain.poses[self.keyframes[-1]]) @ self.chain.poses[index])
            if not (self._since_keyframe >= cfg.keyframe_every or moved_m > cfg.keyframe_distance_m
                    or turned_deg > cfg.keyframe_angle_deg):
                return False
        self._since_keyframe = 0
        return True

    def _forget_frames(self, index: int) -> None:
        """Drop the images the tracker no longer needs: all but keyframes, held-out frames and the last two."""
        keep = set(self.keyframes) | set(self.holdout) | {index, index - 1}
        for i in [i for i in self.frames.images if i not in keep]:
            del self.frames.images[i]

    def _covariances(self, nodes: list[int]) -> np.ndarray:
        """(len(nodes), 6, 6) covariances of frames `nodes` in the pose graph as it is now; after a
        resume, the kept frames' saved ones, and the others' relative to the map plus the map frame's
        they were placed from (carried along the relative pose, as track_onto does)."""
        graph = self.chain.covariances(nodes, origin=self._anchor or 0)
        out = graph[nodes]
        if self._resumed is not None:
            kept, saved = self._resumed
            for k, i in enumerate(nodes):
                if i < kept:
                    out[k] = saved[i]
                elif self._anchor is not None:
                    ad_inv = np.linalg.inv(adjoint(np.linalg.inv(self.chain.poses[self._anchor]) @ self.chain.poses[i]))
                    out[k] = out[k] + ad_inv @ saved[self._anchor] @ ad_inv.T
        return out

    # -- the map ---------------------------------------------------------------------------
    def _add_keyframe(self, index: int) -> None:
        """Depth targets of a new keyframe (fused with the keyframes just before it), the scene box
        (made, or grown when its surfaces leave it) and the model that trains on every keyframe."""
        t0 = time.perf_counter()
        seq = self._keyframe_targets(index)
        box = scene_box(_stack([self.targets[index]]), self.poses[index][None], seq.K)
        self.seconds["targets"] += time.perf_counter() - t0
        self._fit_box(box, seq)
        self._rebuild_trainer()

    def _keyframe_targets(self, index: int) -> RGBDSequence:
        """Keep the depth targets of keyframe `index`, fused with the TARGET_WINDOW - 1 keyframes
        before it (at their poses and covariances now); returns that window's frames at the training
        resolution."""
        window = [k for k in self.keyframes if k <= index][-TARGET_WINDOW:]
        seq = self.frames.sequence(window).scaled_by(self.config.image_scale)
        fused = self.config.targets.build(seq, self.poses[window], self._covariances(window), None, False)
        self.targets[index] = tuple(a[-1].copy() for a in (fused.mean, fused.sigma, fused.valid, fused.support,
                                                            fused.filled))
        return seq

    def _fit_box(self, box: np.ndarray, seq: RGBDSequence) -> None:
        """Make the field over the first keyframe's box padded by grow_pad, or grow it when `box` (a new
        keyframe's) pokes out by more than the box's margin."""
        pad = self.config.mapping.grow_pad
        if self.field is None:
            size = box[1] - box[0]
            self.aabb = np.stack([box[0] - pad * size, box[1] + pad * size]).astype(np.float32)
            self.field = self.config.build_field(self.aabb)
            return
        if (box[0] >= self.aabb[0] - BOX_MARGIN).all() and (box[1] <= self.aabb[1] + BOX_MARGIN).all():
            return
        if not isinstance(self.field, EncodedField):
            raise InputError(f"the stream left the map's box {self.aabb.tolist()} and a {self.config.field!r} "
                             "field cannot grow (a grid field can: 'hashgrid' or 'grid')")
        lo, hi = np.minimum(self.aabb[0], box[0]), np.maximum(self.aabb[1], box[1])
        union = np.stack([lo - pad * (hi - lo), hi + pad * (hi - lo)]).astype(np.float32)
        self.field = self.config.grow_field(self.field, union)
        self.aabb = union

    def _rebuild_trainer(self, config: ReconstructionConfig | None = None) -> None:
        """A Trainer over every keyframe at their current poses, continuing the field (and the Adam
        moments of its parameters). config: the training schedule (default: a constant learning
        rate and depth weights, as at the start of an offline reconstruction)."""
        cfg = config or self.config.replace(max_steps=10**9, time_budget_s=None, progress=False)
        seq = self.frames.sequence(self.keyframes).scaled_by(cfg.image_scale)
        poses = self.poses[self.keyframes]
        model = build_model(cfg, self.aabb, poses, seq.K, np.zeros((len(poses), 6, 6)), field=self.field)
        batcher = RayBatcher(seq, _stack([self.targets[k] for k in self.keyframes]), model.device,
                             cfg.seed + len(self.keyframes), cfg.runtime.cache_frames,
                             target_share=cfg.optimizer.target_ray_share)
        old = self.trainer
        if old is not None and model.exposure is not None and old.model.exposure is not None:
            with torch.no_grad():  # the keyframes trained before keep their exposure
                known = old.model.exposure.log_gains
                model.exposure.log_gains[: len(known)] = known
        trainer = Trainer(model, batcher, cfg)
        if old is not None:  # keep what Adam learned about the field's parameters
            for p in self.field.parameters():
                if p in old.optimizer.state:
                    trainer.optimizer.state[p] = old.optimizer.state[p]
            trainer.step = old.step
        self.trainer = trainer

    def train(self, seconds: float) -> float:
        """Train the map on every keyframe for `seconds` (nothing before the first keyframe; the
        last step ends after them); returns the seconds it took."""
        if self.trainer is None or seconds <= 0:
            return 0.0
        t0, before = time.perf_counter(), self.trainer.step
        self.trainer.train(seconds=seconds)
        self.steps += self.trainer.step - before
        used = time.perf_counter() - t0
        self.seconds["training"] += used
        return used

    def finish(self, seconds: float | None = None, export: bool = True) -> Reconstruction:
        """Train every keyframe for `seconds` more (default ``config.mapping.finish_s``) with the
        learning rate and depth weights decaying as in an offline reconstruction, then return
        :meth:`reconstruction`."""
        seconds = self.config.mapping.finish_s if seconds is None else seconds
        if self.trainer is None:
            raise InputError("finish(): no keyframe yet: add frames first")
        if seconds > 0:
            self._rebuild_trainer(self.config.replace(max_steps=10**9, time_budget_s=seconds, progress=False))
            self.trainer.step, self.trainer.elapsed = 0, 0.0
            self.train(seconds)
            self._rebuild_trainer()
        return self.reconstruction(export)

    def reconstruction(self, export: bool = True) -> Reconstruction:
        """The map now: a :class:`Reconstruction` of the kept frames (keyframes trained, held-out
        frames held out) with a copy of the field, every kept frame's pose and covariance from the
        pose graph, the depth sigma calibrated on the keyframes and, with `export`, its mesh and
        point cloud."""
        if self.trainer is None:
            raise InputError("reconstruction(): no keyframe yet: add frames first")
        kept = sorted(self.keyframes + self.holdout)
        position = {k: i for i, k in enumerate(kept)}
        sequence = self.frames.sequence(kept, "mapped stream")
        train = np.array([position[k] for k in self.keyframes])
        hold = np.array([position[k] for k in self.holdout], int)
        targets = _stack([self.targets[k] for k in self.keyframes])
        train_seq = sequence.select(train).scaled_by(self.config.image_scale)
        poses = self.poses[kept]
        observed = ObservedSurface.from_depths(targets.mean, targets.valid, train_seq.K, poses[train],
                                               self.config.export.mesh_voxel_size, self.aabb)
        gains = np.ones((len(kept), 3))
        if self.trainer.model.exposure is not None:
            _, gains = self.trainer.model.frames_after_training(poses, sequence.timestamps, train, hold)
        model = copy.deepcopy(self.trainer.model.field)
        stats = {"tracking": {"tracked": True}, "training": {"steps": self.steps,
                                                              "seconds": round(self.seconds["training"], 2)},
                 "mapping": self.summary()}
        recon = Reconstruction(model, self.config, poses, self._covariances(kept), train_seq.intrinsic, train, hold,
                               timestamps=sequence.timestamps, color_gains=gains, observed=observed, frames=sequence,
                               stats=stats)
        if export:
            recon.calibrate_depth_sigma(sequence)
            recon.geometry = export_geometry(recon, sequence, progress=False)
        return recon

    def occupancy_grid(self, voxel_size: float = 0.05, bounds=None) -> OccupancyGrid:
        """The map's occupancy grid now (:meth:`Reconstruction.occupancy_grid` of :meth:`reconstruction`,
        its depth sigma calibrated on the keyframes): built again only after frames or training."""
        key = (len(self), self.steps, voxel_size, None if bounds is None else np.asarray(bounds, float).tobytes())
        if self._occupancy is None or self._occupancy[0] != key:
            recon = self.reconstruction(export=False)
            recon.calibrate_depth_sigma(recon.frames)
            self._occupancy = (key, recon.occupancy_grid(voxel_size, bounds))
        return self._occupancy[1]

    def heldout_psnr(self) -> float | None:
        """The map's held-out PSNR now (dB, over the held-out frames kept so far; None without any)."""
        if not self.holdout or self.trainer is None:
            return None
        recon = self.reconstruction(export=False)
        return heldout_scores(recon, recon.frames)["model"]["psnr"]

    def summary(self) -> dict:
        """Frames, keyframes, held-out frames, training steps and seconds spent per stage."""
        return {"frames": len(self), "keyframes": len(self.keyframes), "holdout": len(self.holdout),
                "steps": self.steps, "seconds": {k: round(v, 2) for k, v in self.seconds.items()}}

    # -- on disk ---------------------------------------------------------------------------
    def save(self, directory, reconstruction: Reconstruction | None = None) -> Path:
        """Write the map (`reconstruction`, default :meth:`reconstruction` now; saved with its
        frames) and ``mapper.json`` (the depth scale and :meth:`summary`) into `directory`;
        :meth:`resume` goes on from it."""
        d = (reconstruction or self.reconstruction()).save(directory)
        state = {"depth_scale": self.depth_scale, **self.summary()}
        atomic_write(d / MAPPER_STATE, lambda p: Path(p).write_text(json.dumps(state, indent=1)))
        return d

    @classmethod
    def resume(cls, directory, config: ReconstructionConfig | None = None) -> "Mapper":
        """A mapper that goes on from a folder written by :meth:`save`: its kept frames, their poses
        (pinned) and the field; the next frame is placed on the map as
        :func:`~open3d_pnerf.tracking.track_onto` places a new segment (TrackingError when it cannot be)."""
        d = Path(directory)
        if not (d / MAPPER_STATE).is_file():
            raise CheckpointError(f"{d}: not a saved mapper ({MAPPER_STATE} missing)")
        state = read_json_object(d / MAPPER_STATE, CheckpointError)
        recon = Reconstruction.load(d)
        if recon.frames is None:
            raise CheckpointError(f"{d}: the saved map has no frames/ to go on from")
        config = recon.config if config is None else checked_config(config)
        frames = recon.frames
        mapper = cls(frames.intrinsic, config, state.get("depth_scale", 1000.0))
        for i in range(len(frames)):
            frame = frames[i]
            mapper.frames.images[i] = (frame.color, frame.depth, float(recon.timestamps[i]))
        mapper.timestamps = [float(t) for t in recon.timestamps]
        mapper.keyframes, mapper.holdout = recon.train_indices.tolist(), recon.holdout_indices.tolist()
        mapper.chain = Chain(FrameRegistration(mapper.frames), OdometryOptions(), recon.poses)
        mapper.covariances = list(recon.covariances)
        mapper._resumed = (len(frames), recon.covariances)
        mapper.field, mapper.aabb = recon.field, recon.aabb
        mapper.steps = int(state.get("steps", 0))
        for k in mapper.keyframes:  # targets again, each fused with the keyframes before it
            mapper._keyframe_targets(k)
        mapper._rebuild_trainer()
        return mapper


def _stack(targets: list[tuple[np.ndarray, ...]]) -> DepthTargets:
    """DepthTargets of per-frame (mean, sigma, valid, support, filled) tuples."""
    return DepthTargets(*(np.stack(a) for a in zip(*targets)))
