"""track(): RGB-D odometry + loop closures + pose-graph optimisation + pose covariances."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import open3d as o3d
from tqdm.auto import tqdm

from ..data.sequence import RGBDSequence, check_sequence
from ..errors import InputError, TrackingError
from .covariance import pose_graph_covariances
from .odometry import FrameRegistration, OdometryOptions, PairResult
from .posegraph import add_edge, loop_closure_candidates, optimize, prior_information
from .trajectory import Edge, Trajectory

DEFAULT_POINT_NOISE_M = 2.0
"""Noise of one Open3D correspondence (m) that scales the pose-graph information.

An effective value, not a physical per-pixel noise: the ~2x10^5 correspondences of a
640x480 pair are far from independent (s = 2 m gives an odometry edge a translation std of
about s / sqrt(N) ~ 4 mm). Calibrated in benchmarks/bench_tracking.py so that the frames'
errors against ground truth match their covariances (chi-square per degree of freedom 1):
fits 2.0 (TUM fr1/xyz) and 2.9 (7-Scenes) with loop closures, 0.6 and 1.6 with odometry
only. Covariances scale as 1/(number of correspondences), so at lower resolution they grow.
"""


def track(
    sequence: RGBDSequence,
    *,
    keyframe_every: int = 5,
    max_keyframes: int | None = 200,
    loop_closure: bool = True,
    point_noise_m: float = DEFAULT_POINT_NOISE_M,
    max_depth: float = 3.0,
    device=None,
    progress: bool = True,
    odometry: OdometryOptions = OdometryOptions(),
    loop_odometry: OdometryOptions | None = None,
    loop_max_distance_m: float = 1.0,
    loop_max_angle_deg: float = 45.0,
    loops_per_keyframe: int = 10,
) -> Trajectory:
    """Estimate camera poses and their 6x6 covariances for an RGB-D sequence.

    1. Open3D tensor RGB-D odometry between consecutive frames (``odometry``: hybrid loss by
       default), each result checked (:class:`OdometryOptions`). When frame i's odometry
       fails, frame i is registered from the last successfully registered earlier frame;
       if that fails too it keeps frame i-1's pose through an uncertain edge whose
       covariance spans the plausible-motion limits (huge), and a warning names it.
    2. Loop closures (``loop_closure=True``): every ``keyframe_every``-th frame is a
       keyframe (sparser on long sequences so that there are at most ``max_keyframes``
       keyframes, None = no limit: loop-closure work grows with the number of keyframes,
       not with the length of the sequence); keyframe pairs within ``loop_max_distance_m`` / ``loop_max_angle_deg`` of
       each other (at most ``loops_per_keyframe`` per keyframe) are registered from their
       current relative pose with ``loop_odometry`` (None: ``odometry``, made
       point-to-plane when the colour is not registered to the depth), verified by the same
       checks and added as uncertain edges; Open3D's ``global_optimization``
       (Levenberg-Marquardt, frame 0 fixed) then refines all poses and prunes bad loops.
    3. Covariances from the pose-graph Hessian (:func:`pose_graph_covariances`).

    sequence: an :class:`~open3d_pnerf.RGBDSequence` of at least 2 frames. point_noise_m:
    per-correspondence noise (m) scaling the covariances (see ``DEFAULT_POINT_NOISE_M``).
    max_depth: depth beyond this (m) is ignored. device: Open3D device for odometry
    (None = "CPU:0"). progress: show tqdm progress bars. Returns a :class:`Trajectory`;
    raises TrackingError when no registration succeeds at all.
    """
    n = len(check_sequence(sequence, 2, "track(): sequence", needs_depth=True))
    if not isinstance(keyframe_every, (int, np.integer)) or keyframe_every < 1:
        raise InputError(f"keyframe_every must be an integer >= 1, got {keyframe_every!r}")
    if max_keyframes is not None and (not isinstance(max_keyframes, (int, np.integer)) or max_keyframes < 2):
        raise InputError(f"max_keyframes must be None or an integer >= 2, got {max_keyframes!r}")
    if not point_noise_m > 0:
        raise InputError(f"point_noise_m must be > 0 metres, got {point_noise_m!r}")
    run = _Run(FrameRegistration(sequence, max_depth, device), odometry, point_noise_m)

    for i in tqdm(range(1, n), desc="odometry", disable=not progress, leave=False):
        run.track_frame(i)
    if not any(e.success for e in run.edges):
        reasons = "; ".join(f"{e.source}->{e.target}: {e.message}" for e in run.edges[:5])
        raise TrackingError(
            f"tracking failed: odometry failed for every frame pair of {sequence.name!r} "
            f"({reasons}). Check the depth scale, max_depth={max_depth} and the frame rate "
            "(consecutive frames must overlap)"
        )
    if loop_closure:
        keyframes = list(range(0, n, keyframe_spacing(n, keyframe_every, max_keyframes)))
        linked = {(e.source_node_id, e.target_node_id) for e in run.graph.edges}
        pairs = loop_closure_candidates(
            np.stack(run.poses), keyframes, linked,
            loop_max_distance_m, loop_max_angle_deg, loops_per_keyframe,
        )
        loop_odometry = loop_odometry or _default_loop_odometry(sequence, odometry)
        for s, t in tqdm(pairs, desc="loop closures", disable=not progress, leave=False):
            run.close_loop(s, t, loop_odometry)
        if any(e.kind == "loop" and e.success for e in run.edges):
            optimize(run.graph, max_correspondence_distance=odometry.inlier_distance_m)
            run.mark_pruned_loops()

    _warn_failures(run.edges, run.failed_frames, sequence.name)
    poses = np.stack([np.asarray(node.pose, dtype=np.float64) for node in run.graph.nodes])
    return Trajectory(
        poses=poses,
        covariances=pose_graph_covariances(run.graph, point_noise_m),
        pose_graph=run.graph,
        edges=run.edges,
        failed_frames=run.failed_frames,
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64).copy(),
    )


def keyframe_spacing(n_frames: int, keyframe_every: int, max_keyframes: int | None) -> int:
    """Frames between keyframes: `keyframe_every`, widened so that at most `max_keyframes`
    of `n_frames` are keyframes (None: no limit)."""
    if max_keyframes is None:
        return keyframe_every
    return max(keyframe_every, -(-n_frames // max_keyframes))


def _default_loop_odometry(sequence: RGBDSequence, odometry: OdometryOptions) -> OdometryOptions:
    """`odometry`, made purely geometric when the colour is not registered to the depth.

    Wide-baseline loop closures magnify any colour-to-depth misregistration in the
    photometric term. Measured: on 7-Scenes (colour resampled onto the depth grid with an
    approximate intrinsic) point-to-plane loops gave 6.4 mm ATE against 23 mm with hybrid
    ones; on TUM (registered colour) hybrid loops were better (5.3 mm against 6.4 mm).
    """
    registered = np.allclose(sequence.color_intrinsic.intrinsic_matrix, sequence.intrinsic.intrinsic_matrix)
    return odometry if registered else dataclasses.replace(odometry, method="point_to_plane")


class _Run:
    """Mutable state of one tracking run: chain poses, pose graph and registration log."""

    def __init__(self, registrar: FrameRegistration, options: OdometryOptions, point_noise_m: float):
        self.registrar = registrar
        self.options = options
        self.poses = [np.eye(4)]
        self.graph = o3d.pipelines.registration.PoseGraph()
        self.graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(np.eye(4)))
        self.edges: list[Edge] = []
        self.failed_frames: list[int] = []
        self.registered = [0]  # frames with a verified incoming registration (and frame 0)
        self.guess_information = prior_information(
            point_noise_m, np.radians(options.max_rotation_deg), options.max_translation_m
        )

    def register(self, source: int, target: int, kind: str, options: OdometryOptions) -> PairResult:
        """Register two frames, initialised from the current pose estimates, and log it."""
        # a frame not tracked yet starts at the latest pose (zero-motion guess)
        guess = self.poses[target] if target < len(self.poses) else self.poses[-1]
        init = np.linalg.inv(guess) @ self.poses[source]
        result = self.registrar.register(source, target, init, options)
        self.edges.append(
            Edge(source, target, kind, result.success, result.fitness, result.inlier_rmse,
                 result.overlap, int(round(result.information[5, 5])), result.message)
        )
        return result

    def track_frame(self, i: int) -> None:
        """Add frame i: odometry from i-1, else from the last registered frame, else a guess."""
        result = self.register(i - 1, i, "odometry", self.options)
        source = i - 1
        if not result.success:
            self.failed_frames.append(i)
            earlier = [j for j in self.registered if j < i - 1]
            if earlier:
                source = earlier[-1]
                result = self.register(source, i, "odometry", self.options)
        if result.success:
            self.registered.append(i)
            information, uncertain = result.information, False
        else:  # keep the previous pose; the prior edge gives it a huge covariance
            source, information, uncertain = i - 1, self.guess_information, True
        transformation = result.transformation if result.success else np.eye(4)
        pose = self.poses[source] @ np.linalg.inv(transformation)
        self.poses.append(pose)
        self.graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
        add_edge(self.graph, source, i, transformation, information, uncertain)

    def close_loop(self, s: int, t: int, options: OdometryOptions) -> None:
        """Register keyframe s to keyframe t; add an uncertain edge when it is verified."""
        result = self.register(s, t, "loop", options)
        if result.success:
            add_edge(self.graph, s, t, result.transformation, result.information, uncertain=True)

    def mark_pruned_loops(self) -> None:
        """Flag the loop closures that global optimisation pruned as unsuccessful."""
        kept = {(e.source_node_id, e.target_node_id) for e in self.graph.edges}
        for k, e in enumerate(self.edges):
            if e.kind == "loop" and e.success and (e.source, e.target) not in kept:
                self.edges[k] = dataclasses.replace(e, success=False, message="pruned by global optimisation")


def _warn_failures(edges: list[Edge], failed_frames: list[int], name: str) -> None:
    """One warning naming the frames whose odometry failed and what became of them."""
    if not failed_frames:
        return
    recovered = {e.target for e in edges if e.kind == "odometry" and e.success and e.target in failed_frames}
    details = []
    for i in failed_frames[:10]:
        reason = next(e.message for e in edges if (e.source, e.target) == (i - 1, i))
        fate = "re-registered from an earlier frame" if i in recovered else "pose guessed, huge covariance"
        details.append(f"frame {i}: {reason}; {fate}")
    more = f"; ... ({len(failed_frames) - 10} more)" if len(failed_frames) > 10 else ""
    warnings.warn(
        f"track({name!r}): odometry failed into frames {failed_frames}: " + "; ".join(details) + more,
        stacklevel=3,
    )
