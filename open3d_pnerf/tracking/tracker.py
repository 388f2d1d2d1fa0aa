"""track(): RGB-D odometry + loop closures + pose-graph optimisation + pose covariances."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import open3d as o3d
from tqdm.auto import tqdm

from ..camera import adjoint, matrix_twist, motion
from ..data.sequence import RGBDSequence, check_sequence, evenly_spaced
from ..errors import InputError, TrackingError
from ..settings import FLAG, Settings, setting
from .color import ColorOffsets, measurement_noise
from .covariance import pose_graph_covariances
from .odometry import FrameRegistration, OdometryOptions, PairResult
from .posegraph import add_edge, loop_closure_candidates, optimize
from .trajectory import Edge, Trajectory
from .uncertainty import misregistration_covariance

PINNED_VARIANCE = 1e-10
"""Variance (rad^2, m^2) of the edges that pin known poses to frame 0 when tracking onto a map
(:func:`track_onto`): the optimisation leaves them where they are."""

LOOP_INFLATION = 16.0
"""A loop closure's covariance is this many times its registration's: its two images already
entered the odometry chain, so it is not an independent measurement (the error common to all
registrations is OdometryOptions.misregistration_systematic, which no edge carries). Chosen on the
tuning halves, with 4 rejected by the synthetic Monte-Carlo draws (benchmarks/README.md)."""


@dataclasses.dataclass
class TrackingConfig(Settings):
    """How a reconstruction estimates poses when none are given (see :func:`track`)."""

    loop_closure: bool = setting(True, FLAG)
    """Register keyframes that see the same place and optimise the pose graph."""
    color_poses: bool = setting(True, FLAG)
    """Place each frame's colour camera beside its depth camera (see tracking.color) and train on
    the colour images' poses, each depth image moved into its colour camera."""

    def track(self, sequence: RGBDSequence, progress: bool = True) -> Trajectory:
        """:func:`track` with these settings."""
        return track(sequence, loop_closure=self.loop_closure, progress=progress, color_poses=self.color_poses)

    def track_onto(self, sequence: RGBDSequence, known_poses: np.ndarray, known_covariances: np.ndarray,
                   progress: bool = True) -> Trajectory:
        """:func:`track_onto` with these settings."""
        return track_onto(sequence, known_poses, known_covariances, loop_closure=self.loop_closure, progress=progress)


def track(
    sequence: RGBDSequence,
    *,
    keyframe_every: int = 5,
    max_keyframes: int | None = 200,
    loop_closure: bool = True,
    max_depth: float = 3.0,
    device=None,
    progress: bool = True,
    odometry: OdometryOptions = OdometryOptions(),
    loop_odometry: OdometryOptions | None = None,
    loop_max_distance_m: float = 1.0,
    loop_max_angle_deg: float = 45.0,
    loops_per_keyframe: int = 10,
    color_poses: bool = True,
) -> Trajectory:
    """Estimate camera poses and their 6x6 covariances for an RGB-D sequence.

    1. Frame i is registered to frame i-1 by Open3D's tensor RGB-D odometry (``odometry``:
       hybrid loss by default; at half resolution from 320 pixels wide, the refinement below
       working on the full depth images), from the constant-velocity guess (the last motion, repeated).
       Each result is checked (:class:`OdometryOptions`: overlap, plausible motion) and its
       point-to-plane residual and overlap compared with the medians of the sequence's
       registrations so far. A failed or doubtful one (residual above ``odometry.residual_ratio``
       times the median, or overlap under ``odometry.overlap_ratio`` times it) is re-done from
       other guesses: no motion, the colour images' ORB keypoints matched and solved by
       PnP-RANSAC on the depth (:func:`~open3d_pnerf.tracking.odometry.feature_registration`),
       the global registration of the two frames' point clouds (FPFH + RANSAC,
       :func:`~open3d_pnerf.tracking.odometry.global_registration`), and the last frame
       registered before i-1; the pose most passing candidates agree on is kept (between poses
       with as many votes, the one with the lowest residual per overlap), from the candidate
       with the lowest residual among those that reach it. When the predicted motion is fast
       (``odometry.search_all_above_m`` / ``search_all_above_deg``) every guess is tried, as a
       wrong minimum need not stand out.
       A frame that still fits badly, or whose starts reached different poses (its covariance
       then grows by their disagreement), is kept and flagged; one that no candidate places
       keeps the constant-velocity guess with a covariance spanning the plausible-motion
       limits, and a warning names both.
    2. Loop closures (``loop_closure=True``): every ``keyframe_every``-th frame is a
       keyframe (sparser on long sequences so that there are at most ``max_keyframes``
       keyframes, None = no limit); keyframe pairs within ``loop_max_distance_m`` /
       ``loop_max_angle_deg`` of each other (at most ``loops_per_keyframe`` per keyframe) are
       registered from their current relative pose with ``loop_odometry`` (None: ``odometry``,
       made point-to-plane when the colour is not registered to the depth), held to the same
       checks and the residual test, and added as uncertain edges; Open3D's
       ``global_optimization`` (Levenberg-Marquardt, frame 0 fixed) then refines all poses and
       prunes inconsistent loops.
    3. Covariances: the marginals of the pose-graph Hessian (:func:`pose_graph_covariances`)
       built from each registration's own covariance: every registration is finished by a
       sub-pixel point-to-plane refinement both ways, and its covariance estimated from its
       residuals (:mod:`~open3d_pnerf.tracking.uncertainty`: cluster-robust over image tiles, so
       it neither depends on the processing resolution nor counts correlated pixels as
       independent), plus a misregistration floor for what a real sensor's calibration leaves
       (``odometry.misregistration_rad``) and what grows with the camera's motion while it takes
       the two frames, motion blur, rolling shutter and wrong minima
       (``odometry.misregistration_per_squared_motion``, per squared radian of each frame's step
       from its neighbour); a loop closure's is LOOP_INFLATION times larger (its images are already in the
       chain). Then each pose's systematic misregistration (``odometry.misregistration_systematic``
       per radian of its turn from frame 0), common to all registrations, so neither the chain's
       length nor loop closures change it.
    4. Colour cameras (``color_poses``, when the colour is registered to the depth): Open3D's
       hybrid answer for each frame from the frame before it (its intensity term dominates, so it
       fits the colour images) is kept beside the refined one, and every frame's colour-camera
       offset solved from them (:mod:`~open3d_pnerf.tracking.color`; Trajectory.color_offsets).

    sequence: an :class:`~open3d_pnerf.RGBDSequence` of at least 2 frames. max_depth: depth
    beyond this (m) is ignored. device: Open3D device for odometry (None = "CPU:0"). progress:
    show tqdm progress bars. Returns a :class:`Trajectory`; raises TrackingError when no
    registration succeeds at all.
    """
    n = len(check_sequence(sequence, 2, "track(): sequence", needs_depth=True))
    if not isinstance(keyframe_every, (int, np.integer)) or keyframe_every < 1:
        raise InputError(f"keyframe_every must be an integer >= 1, got {keyframe_every!r}")
    if max_keyframes is not None and (not isinstance(max_keyframes, (int, np.integer)) or max_keyframes < 2):
        raise InputError(f"max_keyframes must be None or an integer >= 2, got {max_keyframes!r}")
    run = _Run(FrameRegistration(sequence, max_depth, device), odometry,
               colors=ColorOffsets() if color_poses and sequence.color_registered else None)
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
        _close_loops(run, sequence, keyframes=list(range(0, n, keyframe_spacing(n, keyframe_every, max_keyframes))),
                     odometry=odometry, loop_odometry=loop_odometry, max_distance_m=loop_max_distance_m,
                     max_angle_deg=loop_max_angle_deg, per_keyframe=loops_per_keyframe, progress=progress)
    _warn_failures(run, sequence.name)
    return _trajectory(run, sequence)


def track_onto(
    sequence: RGBDSequence,
    known_poses: np.ndarray,
    known_covariances: np.ndarray,
    *,
    anchors: int = 8,
    keyframe_every: int = 5,
    max_keyframes: int | None = 200,
    loop_closure: bool = True,
    max_depth: float = 3.0,
    device=None,
    progress: bool = True,
    odometry: OdometryOptions = OdometryOptions(),
    loop_odometry: OdometryOptions | None = None,
    loop_max_distance_m: float = 1.0,
    loop_max_angle_deg: float = 45.0,
    loops_per_keyframe: int = 10,
) -> Trajectory:
    """Track the frames of `sequence` after its first K onto a map: the first K frames' poses
    (K, 4, 4) and covariances (K, 6, 6) are known and stay as they are.

    Frame K is placed on the map by the first of these that passes :func:`track`'s checks: the
    chain's own guesses from frame K-1 (constant velocity, zero motion, keypoints, global
    registration: a capture that continues), then zero motion, the keypoints and the global
    registration against `anchors`
    map frames evenly spaced over the others, best residual first; when none passes, the frames
    cannot join the map and TrackingError says so (they are never chained from a guess). The
    frames after K are tracked as :func:`track` tracks them; with ``loop_closure``, keyframes of
    the new frames are registered to every keyframe (old or new) near them, and the pose graph,
    with the known frames pinned, is optimised. The new frames' covariances are the graph's
    marginals relative to the map plus the map frame they were placed from (its covariance
    carried to them). Returns the Trajectory of all N frames (the known ones as given).
    """
    n = len(check_sequence(sequence, 2, "track_onto(): sequence", needs_depth=True))
    known = len(known_poses)
    if not 1 <= known < n:
        raise InputError(f"track_onto(): {known} known poses for a sequence of {n} frames; the known frames "
                         "come first and at least one frame must be new")
    known_poses = np.asarray(known_poses, np.float64)
    known_covariances = np.asarray(known_covariances, np.float64)
    if known_poses.shape != (known, 4, 4) or known_covariances.shape != (known, 6, 6):
        raise InputError(f"track_onto(): known poses {known_poses.shape} and covariances {known_covariances.shape}, "
                         f"expected ({known}, 4, 4) and ({known}, 6, 6)")
    run = _Run(FrameRegistration(sequence, max_depth, device), odometry, known_poses)
    anchor = run.place_on_map(known, [int(j) for j in evenly_spaced(known - 1, anchors)], sequence.name)
    for i in tqdm(range(known + 1, n), desc="odometry", disable=not progress, leave=False):
        run.track_frame(i)
    if loop_closure:
        keyframes = list(range(0, n, keyframe_spacing(n, keyframe_every, max_keyframes)))
        _close_loops(run, sequence, keyframes, odometry, loop_odometry, loop_max_distance_m, loop_max_angle_deg,
                     loops_per_keyframe, progress, new_from=known)
    _warn_failures(run, sequence.name)
    trajectory = _trajectory(run, sequence, origin=anchor)
    covariances = trajectory.covariances
    covariances[:known] = known_covariances
    for i in range(known, n):  # the map frame's own uncertainty, carried along the relative pose
        ad = adjoint(np.linalg.inv(known_poses[anchor]) @ trajectory.poses[i])
        ad_inv = np.linalg.inv(ad)
        covariances[i] += ad_inv @ known_covariances[anchor] @ ad_inv.T
    return trajectory


def _close_loops(run: "_Run", sequence: RGBDSequence, keyframes: list[int], odometry: OdometryOptions,
                 loop_odometry: OdometryOptions | None, max_distance_m: float, max_angle_deg: float,
                 per_keyframe: int, progress: bool, new_from: int = 0) -> None:
    """Register the keyframe pairs near each other that have a frame from `new_from` on, add the
    passing ones as uncertain edges, and optimise the graph when any was added."""
    linked = {(e.source_node_id, e.target_node_id) for e in run.graph.edges}
    pairs = [(s, t) for s, t in loop_closure_candidates(np.stack(run.poses), keyframes, linked, max_distance_m,
                                                         max_angle_deg, per_keyframe) if t >= new_from]
    loop_odometry = loop_odometry or _default_loop_odometry(sequence, odometry)
    run.registrar.reserve(sorted({frame for pair in pairs for frame in pair}))
    for k, (s, t) in enumerate(tqdm(pairs, desc="loop closures", disable=not progress, leave=False)):
        for frame in pairs[k + 1] if k + 1 < len(pairs) else ():
            run.registrar.prefetch(frame)
        run.close_loop(s, t, loop_odometry)
    if any(e.kind == "loop" and e.success for e in run.edges):
        optimize(run.graph)
        run.mark_pruned_loops()


def _trajectory(run: "_Run", sequence: RGBDSequence, origin: int = 0) -> Trajectory:
    """The Trajectory of a finished run: the graph's poses, their covariances (:meth:`_Run.covariances`,
    the systematic misregistration measured from frame `origin`), the registration log, and the colour
    cameras' offsets when the run measured them."""
    poses = np.stack([np.asarray(node.pose, dtype=np.float64) for node in run.graph.nodes])
    covariances = run.covariances(origin=origin)
    return Trajectory(
        poses=poses,
        covariances=covariances,
        pose_graph=run.graph,
        edges=run.edges,
        failed_frames=run.failed_frames,
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64).copy(),
        flagged_frames=run.flagged_frames,
        recovered_frames=run.recovered_frames,
        color_offsets=None if run.colors is None else run.colors.solve(poses),
    )


def keyframe_spacing(n_frames: int, keyframe_every: int, max_keyframes: int | None) -> int:
    """Frames between keyframes: `keyframe_every`, widened so that at most `max_keyframes`
    of `n_frames` are keyframes (None: no limit)."""
    if max_keyframes is None:
        return keyframe_every
    return max(keyframe_every, -(-n_frames // max_keyframes))


def constant_velocity_pose(poses, i: int) -> np.ndarray:
    """Frame i's camera-to-world pose (4, 4) if the camera kept its motion from frame i-2 to i-1
    (poses: a sequence of (4, 4) camera-to-world poses of frames 0..i-1); frame i-1's pose for i < 2."""
    if i < 2:
        return poses[i - 1]
    return poses[i - 1] @ np.linalg.inv(poses[i - 2]) @ poses[i - 1]


def _default_loop_odometry(sequence: RGBDSequence, odometry: OdometryOptions) -> OdometryOptions:
    """`odometry`, made purely geometric when the colour is not registered to the depth:
    wide-baseline loop closures magnify any colour-to-depth misregistration in the photometric
    term."""
    return odometry if sequence.color_registered else dataclasses.replace(odometry, method="point_to_plane")


class _Run:
    """Mutable state of one tracking run: chain poses, pose graph, registration log and statistics."""

    def __init__(self, registrar: FrameRegistration, options: OdometryOptions, known_poses: np.ndarray | None = None,
                 colors: ColorOffsets | None = None):
        self.registrar = registrar
        self.options = options
        self.colors = colors  # gathers the colour relative poses of consecutive frames, when given
        self.poses = [np.eye(4)] if known_poses is None else list(known_poses)
        self.graph = o3d.pipelines.registration.PoseGraph()
        for pose in self.poses:
            self.graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
        self.edges: list[Edge] = []
        self.failed_frames: list[int] = []
        self.flagged_frames: list[int] = []
        self.recovered_frames: list[int] = []
        self.registered = list(range(len(self.poses)))  # frames with a verified incoming registration (or known)
        self.steps: dict[int, np.ndarray] = {}  # frame i -> its accepted registration from frame i-1 (its own motion)
        self.residuals: list[float] = []  # point-to-plane residual RMS of the accepted odometry registrations
        self.overlaps: list[float] = []  # and their overlap
        self.depths: list[float] = []  # and their median inlier depth (m)
        for j in range(1, len(self.poses)):  # known poses: pinned to frame 0 (the optimisation's fixed node)
            self.add_edge(j, 0, np.linalg.inv(self.poses[0]) @ self.poses[j], PINNED_VARIANCE * np.eye(6))
        limits = np.array([np.radians(options.max_rotation_deg)] * 3 + [options.max_translation_m] * 3)
        self.guess_covariance = np.diag(limits**2)  # a guessed pose: anywhere within the plausible motion

    def register(self, source: int, target: int, kind: str, options: OdometryOptions, init: np.ndarray,
                 init_name: str, prior: np.ndarray | None = None,
                 frame_steps: list[np.ndarray] | None = None) -> PairResult:
        """Register two frames from `init` (source -> target), motion limits around `prior`, the
        misregistration floor from `frame_steps` (FrameRegistration.register); log it."""
        result = self.registrar.register(source, target, init, options, init_name, prior, frame_steps)
        self.edges.append(
            Edge(source, target, kind, result.success, result.fitness, result.inlier_rmse,
                 result.overlap, result.inliers, result.message, result.residual_rms,
                 init_name)
        )
        return result

    def suspicious(self, result: PairResult) -> bool:
        """Whether a registration's residual is high against the sequence's accepted ones so far."""
        if len(self.residuals) < 3:
            return False
        return result.residual_rms > self.options.residual_ratio * float(np.median(self.residuals[-30:]))

    def doubtful(self, result: PairResult) -> bool:
        """Whether a registration is suspicious or overlaps little against the sequence's accepted
        ones so far (then the other starts are tried too)."""
        if self.suspicious(result):
            return True
        if len(self.overlaps) < 3:
            return False
        return result.overlap < self.options.overlap_ratio * float(np.median(self.overlaps[-30:]))

    def relative(self, source: int, target: int) -> np.ndarray:
        """The current estimate of the transformation source camera -> target camera."""
        return np.linalg.inv(self.poses[target]) @ self.poses[source]

    def predicted_pose(self, i: int) -> np.ndarray:
        """Frame i's pose if the camera kept the motion of the last two frames (constant velocity)."""
        return constant_velocity_pose(self.poses, i)

    def candidates(self, i: int):
        """(name, source frame, initial guess source -> i, expected source -> i) to try for frame
        i, in order; the keypoint and global registrations are computed only if reached. Every result is held
        to the plausible-motion limits around the constant-velocity prediction."""
        guess = self.predicted_pose(i)
        expected = np.linalg.inv(guess) @ self.poses[i - 1]
        yield "constant velocity", i - 1, expected, expected
        yield "zero motion", i - 1, np.eye(4), expected
        for name, start in (("features", self.registrar.feature_guess), ("global", self.registrar.global_guess)):
            found = start(i - 1, i)
            if found is not None:
                yield name, i - 1, found, expected
        earlier = [j for j in self.registered if j < i - 1]
        if earlier:
            from_earlier = np.linalg.inv(guess) @ self.poses[earlier[-1]]
            yield f"from frame {earlier[-1]}", earlier[-1], from_earlier, from_earlier

    def fast(self, relative: np.ndarray) -> bool:
        """Whether a (4, 4) relative pose exceeds the options' search_all_above limits."""
        moved_m, turned_deg = motion(relative)
        return moved_m > self.options.search_all_above_m or turned_deg > self.options.search_all_above_deg

    def fast_motion(self, i: int) -> bool:
        """Whether the motion predicted from frame i-1 to i exceeds the options' search_all_above limits."""
        return i >= 2 and self.fast(self.relative(i - 1, i - 2))

    def track_frame(self, i: int) -> None:
        """Add frame i: the consensus of the candidates that pass (try_candidates), else a guess."""
        self.registrar.prefetch(i + 1)
        passed = self.try_candidates(i)
        if not self.add_registered(i, passed):  # nothing placed it: continue the motion, with a covariance to match
            self.failed_frames.append(i)
            pose, source = self.predicted_pose(i), i - 1
            self.add_node(i, pose, source, np.linalg.inv(pose) @ self.poses[source], self.guess_covariance,
                          uncertain=True)

    def place_on_map(self, i: int, anchors: list[int], name: str) -> int:
        """Add frame i, the first after the known ones, from the chain's candidates or else from
        zero motion, the keypoints or a global registration to each map frame in `anchors`;
        returns the frame it was registered from. TrackingError when none passes (nothing is
        guessed)."""
        passed = self.try_candidates(i)
        for j in anchors if not passed else ():
            for start, init in (("zero motion", lambda: np.eye(4)),
                                ("features", lambda: self.registrar.feature_guess(j, i)),
                                ("global", lambda: self.registrar.global_guess(j, i))):
                guess = init()
                result = None if guess is None else self.register(j, i, "odometry", self.options, guess,
                                                                  f"map frame {j}: {start}")
                if result is not None and result.success:
                    passed.append((result, j))
                    break
        if not self.add_registered(i, passed):
            tried = sorted({e.source for e in self.edges if e.target == i})
            raise TrackingError(f"{name}: frame {i}, the first new frame, registers to none of the map's frames "
                                f"tried ({tried}): the new frames do not overlap the map, or their depth is not usable "
                                "(a guess would put them anywhere, so they are not added)")
        return self.graph.edges[-1].source_node_id

    def try_candidates(self, i: int) -> list[tuple[PairResult, int]]:
        """The (registration, source) of frame i's candidates that pass: up to the first that
        passes and is not doubtful, or all of them when the camera moves fast or one of them
        lands beyond the search_all_above limits from the prediction. (7-Scenes every 10th frame,
        frame 87: when the constant-velocity start passes, odometry settles 37-52 mm off, 66-73 mm
        from the prediction, at a residual and overlap that need not stand out; where exactly depends
        on the last bits of Open3D's multi-threaded sums, so the run decided whether it was tried
        again: benchmarks/bench_tracking_starts.py.)"""
        passed = []
        search_all = self.fast_motion(i)
        for name, source, init, expected in self.candidates(i):
            result = self.register(source, i, "odometry", self.options, init, name, expected)
            if result.success:
                passed.append((result, source))
                search_all = search_all or self.fast(np.linalg.inv(expected) @ result.transformation)
                if not self.doubtful(result) and not search_all:
                    break
        return passed

    def add_registered(self, i: int, passed: list[tuple[PairResult, int]]) -> bool:
        """Add frame i from the consensus of its passing registrations; False when there is none."""
        best, recovered = self.consensus(passed)
        if best is None:
            return False
        result, source = best
        if recovered:
            self.recovered_frames.append(i)
        if self.suspicious(result):
            self.flagged_frames.append(i)
        else:
            self.residuals.append(result.residual_rms)
            self.overlaps.append(result.overlap)
            self.depths.append(result.depth)
        self.registered.append(i)
        pose = self.poses[source] @ np.linalg.inv(result.transformation)
        spread = self.disagreement(pose, source, result.transformation, passed)
        if spread.any() and i not in self.flagged_frames:
            self.flagged_frames.append(i)
        self.add_node(i, pose, source, result.transformation, result.covariance + spread)
        if source == i - 1:
            self.steps[i] = result.transformation
            if self.colors is not None and result.odometry_transformation is not None:
                back = np.linalg.inv(result.transformation)  # frame i -> i-1, its covariance carried over
                ad = adjoint(back)
                noise = measurement_noise(result.residual_covariance, result.depth)
                self.colors.add(i, np.linalg.inv(result.odometry_transformation), back, ad @ noise @ ad.T)
        return True

    def add_node(self, i: int, pose: np.ndarray, source: int, transformation: np.ndarray, covariance: np.ndarray,
                 uncertain: bool = False) -> None:
        """Append frame i's pose, its graph node and its edge from `source` with the edge's covariance."""
        self.poses.append(pose)
        self.graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
        self.add_edge(source, i, transformation, covariance, uncertain)

    def disagreement(self, pose: np.ndarray, source: int, transformation: np.ndarray,
                     passed: list[tuple[PairResult, int]]) -> np.ndarray:
        """(6, 6) sum of xi xi^T over the passing candidates that reached another pose than the
        kept one: xi, the left perturbation [rotation, translation] of the kept edge
        (source -> i) that gives the other candidate's pose. Added to the edge's covariance, so
        that when starts disagree the pose is uncertain by as much as they disagree (a choice
        between minima that the residuals cannot make reliably; zeros when all agree)."""
        extra = np.zeros((6, 6))
        for result, other_source in passed:
            other = self.poses[other_source] @ np.linalg.inv(result.transformation)
            moved_m, turned_deg = motion(np.linalg.inv(pose) @ other)
            if moved_m < self.options.inlier_distance_m and turned_deg < 1.0:
                continue
            xi = matrix_twist(np.linalg.inv(other) @ self.poses[source] @ np.linalg.inv(transformation))  # exp(xi)
            extra += np.outer(xi, xi)
        return extra

    def consensus(self, passed: list[tuple[PairResult, int]]) -> tuple[tuple[PairResult, int] | None, bool]:
        """The (registration, source) to keep among those that passed, and whether it is a
        recovery (the constant-velocity start did not pass or reached another pose). Kept: of
        the pose that most of them agree on (within inlier_distance_m and 1 degree; between poses
        with as many votes, the one reached with the lowest residual per overlap, residual RMS /
        overlap), the one with the lowest residual. Agreement first: guesses that
        converge to one pose from different starts outvote a lone wrong minimum, whose residual
        can be a few percent lower (the synthetic room at 40 frames per circuit, seed 3, frame 33:
        6.01 mm 28 cm off against 6.42 mm). The residual alone would favour a pose that fits a
        few percent better by overlapping a third less (7-Scenes every 10th frame, frame 35: 7.0
        mm at overlap 0.55, 69 mm off, against 7.5 mm at 0.81, 12 mm off); the overlap alone, a
        pose that overlaps a little more with a quarter more residual (synthetic room, seed 0,
        frame 4: 4.5 mm at 0.55, 23 cm off, against 3.6 mm at 0.54, right)."""
        if not passed:
            return None, False
        poses = [self.poses[source] @ np.linalg.inv(result.transformation) for result, source in passed]

        def agree(a: np.ndarray, b: np.ndarray) -> bool:
            moved_m, turned_deg = motion(np.linalg.inv(a) @ b)
            return moved_m < self.options.inlier_distance_m and turned_deg < 1.0

        groups = [[q for q, other in enumerate(poses) if agree(pose, other)] for pose in poses]
        fit = [min(passed[q][0].residual_rms / passed[q][0].overlap for q in group) for group in groups]
        k = min(range(len(passed)), key=lambda j: (-len(groups[j]), fit[j], passed[j][0].residual_rms))
        recovered = not any(result.init == "constant velocity" and agree(poses[k], pose)
                            for (result, _), pose in zip(passed, poses))
        return passed[k], recovered

    def frame_steps(self, *frames: int) -> list[np.ndarray] | None:
        """The frames' own steps (their accepted registrations from the frame before; frame 0:
        frame 1's), what a registration of non-consecutive frames grows its misregistration floor
        with; None when this run registered none of them (then the floor grows with the
        registration's own motion: a bound, FrameRegistration.register)."""
        steps = [self.steps[k] for k in (k or 1 for k in frames) if k in self.steps]
        return steps or None

    def close_loop(self, s: int, t: int, options: OdometryOptions) -> None:
        """Register keyframe s to keyframe t; add an uncertain edge when it passes every check."""
        result = self.register(s, t, "loop", options, self.relative(s, t), "loop", frame_steps=self.frame_steps(s, t))
        if result.success and self.suspicious(result):
            self.edges[-1] = dataclasses.replace(self.edges[-1], success=False,
                                                 message="residual far above the sequence's registrations")
        elif result.success:
            self.add_edge(s, t, result.transformation, LOOP_INFLATION * result.covariance, uncertain=True)

    def mark_pruned_loops(self) -> None:
        """Flag the loop closures that global optimisation pruned as unsuccessful."""
        kept = {(e.source_node_id, e.target_node_id) for e in self.graph.edges}
        for k, e in enumerate(self.edges):
            if e.kind == "loop" and e.success and (e.source, e.target) not in kept:
                self.edges[k] = dataclasses.replace(e, success=False, message="pruned by global optimisation")

    def covariances(self, nodes=None, origin: int = 0) -> np.ndarray:
        """(N, 6, 6) covariances of the graph's poses (nodes: only these, the others zero): the pose
        graph's marginals (:func:`pose_graph_covariances`, frame 0 fixed) plus the systematic
        misregistration (OdometryOptions.misregistration_systematic) of each frame's turn from frame
        `origin` (rotation angle; translation: that std times the accepted registrations' median
        depth), an error common to the registrations that the graph, which takes them as
        independent, cannot see."""
        covariances = pose_graph_covariances(self.graph, nodes=nodes)
        per_rad = self.options.misregistration_systematic
        if per_rad == 0 or not self.depths:
            return covariances
        depth = float(np.median(self.depths))
        from_origin = np.linalg.inv(np.asarray(self.graph.nodes[origin].pose))
        for i in range(len(self.graph.nodes)) if nodes is None else nodes:
            _, turned_deg = motion(from_origin @ np.asarray(self.graph.nodes[i].pose))
            covariances[i] += misregistration_covariance(per_rad * np.radians(turned_deg), depth)
        return covariances

    def add_edge(self, source: int, target: int, transformation: np.ndarray, covariance: np.ndarray,
                 uncertain: bool = False) -> None:
        """Add the graph edge source -> target with its (6, 6) covariance; the edge's information,
        what the optimisation weighs it by and the covariances are marginals of, is its inverse."""
        add_edge(self.graph, source, target, transformation, np.linalg.pinv(covariance, hermitian=True), uncertain)


def _warn_failures(run: _Run, name: str) -> None:
    """One warning naming the frames no registration placed and those placed by a poor fit."""
    if not (run.failed_frames or run.flagged_frames):
        return
    parts = []
    if run.failed_frames:
        parts.append(f"no registration placed frames {run.failed_frames[:20]}"
                     f"{' ...' if len(run.failed_frames) > 20 else ''}: their poses continue the motion before them, "
                     "with covariances as wide as the plausible motion (and so have the frames chained through them)")
    if run.flagged_frames:
        parts.append(f"frames {run.flagged_frames[:20]}{' ...' if len(run.flagged_frames) > 20 else ''} fit their "
                     "neighbours poorly (residual far above the sequence's others) or were placed differently from "
                     "different starts: kept, with covariances as large as their residuals and the starts' "
                     "disagreement give")
    warnings.warn(f"track({name!r}): " + "; ".join(parts), stacklevel=3)
