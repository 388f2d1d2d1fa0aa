"""track() and track_onto(): a sequence's camera poses and their covariances, from the parts of this
package (odometry, recovery, loops, covariance), and the settings a reconstruction tracks with."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from tqdm.auto import tqdm

from ..camera import adjoint
from ..data.derived import evenly_spaced
from ..data.sequence import RGBDSequence, check_sequence
from ..errors import InputError, TrackingError
from ..settings import FLAG, Settings, setting
from .chain import Chain
from .color import ColorOffsets
from .loops import close_loops
from .odometry import FrameRegistration, OdometryOptions
from .recovery import place_on_map, track_frame
from .trajectory import Trajectory


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
    chain = Chain(FrameRegistration(sequence, max_depth, device), odometry,
                  colors=ColorOffsets() if color_poses and sequence.color_registered else None)
    for i in tqdm(range(1, n), desc="odometry", disable=not progress, leave=False):
        track_frame(chain, i)
    if not any(e.success for e in chain.edges):
        reasons = "; ".join(f"{e.source}->{e.target}: {e.message}" for e in chain.edges[:5])
        raise TrackingError(
            f"tracking failed: odometry failed for every frame pair of {sequence.name!r} "
            f"({reasons}). Check the depth scale, max_depth={max_depth} and the frame rate "
            "(consecutive frames must overlap)"
        )
    if loop_closure:
        close_loops(chain, sequence, keyframes=list(range(0, n, keyframe_spacing(n, keyframe_every, max_keyframes))),
                    odometry=odometry, loop_odometry=loop_odometry, max_distance_m=loop_max_distance_m,
                    max_angle_deg=loop_max_angle_deg, per_keyframe=loops_per_keyframe, progress=progress)
    _warn_failures(chain, sequence.name)
    return _trajectory(chain, sequence)


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
    chain = Chain(FrameRegistration(sequence, max_depth, device), odometry, known_poses)
    anchor = place_on_map(chain, known, [int(j) for j in evenly_spaced(known - 1, anchors)], sequence.name)
    for i in tqdm(range(known + 1, n), desc="odometry", disable=not progress, leave=False):
        track_frame(chain, i)
    if loop_closure:
        keyframes = list(range(0, n, keyframe_spacing(n, keyframe_every, max_keyframes)))
        close_loops(chain, sequence, keyframes, odometry, loop_odometry, loop_max_distance_m, loop_max_angle_deg,
                    loops_per_keyframe, progress, new_from=known)
    _warn_failures(chain, sequence.name)
    trajectory = _trajectory(chain, sequence, origin=anchor)
    covariances = trajectory.covariances
    covariances[:known] = known_covariances
    for i in range(known, n):  # the map frame's own uncertainty, carried along the relative pose
        ad = adjoint(np.linalg.inv(known_poses[anchor]) @ trajectory.poses[i])
        ad_inv = np.linalg.inv(ad)
        covariances[i] += ad_inv @ known_covariances[anchor] @ ad_inv.T
    return trajectory


def _trajectory(chain: Chain, sequence: RGBDSequence, origin: int = 0) -> Trajectory:
    """The Trajectory of a finished run: the graph's poses, their covariances (:meth:`Chain.covariances`,
    the systematic misregistration measured from frame `origin`), the registration log, and the colour
    cameras' offsets when the run measured them."""
    poses = np.stack([np.asarray(node.pose, dtype=np.float64) for node in chain.graph.nodes])
    covariances = chain.covariances(origin=origin)
    return Trajectory(
        poses=poses,
        covariances=covariances,
        pose_graph=chain.graph,
        edges=chain.edges,
        failed_frames=chain.failed_frames,
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64).copy(),
        flagged_frames=chain.flagged_frames,
        recovered_frames=chain.recovered_frames,
        color_offsets=None if chain.colors is None else chain.colors.solve(poses),
    )


def keyframe_spacing(n_frames: int, keyframe_every: int, max_keyframes: int | None) -> int:
    """Frames between keyframes: `keyframe_every`, widened so that at most `max_keyframes`
    of `n_frames` are keyframes (None: no limit)."""
    if max_keyframes is None:
        return keyframe_every
    return max(keyframe_every, -(-n_frames // max_keyframes))


def _warn_failures(chain: Chain, name: str) -> None:
    """One warning naming the frames no registration placed and those placed by a poor fit."""
    if not (chain.failed_frames or chain.flagged_frames):
        return
    parts = []
    if chain.failed_frames:
        parts.append(f"no registration placed frames {chain.failed_frames[:20]}"
                     f"{' ...' if len(chain.failed_frames) > 20 else ''}: their poses continue the motion before them, "
                     "with covariances as wide as the plausible motion (and so have the frames chained through them)")
    if chain.flagged_frames:
        parts.append(f"frames {chain.flagged_frames[:20]}{' ...' if len(chain.flagged_frames) > 20 else ''} fit their "
                     "neighbours poorly (residual far above the sequence's others) or were placed differently from "
                     "different starts: kept, with covariances as large as their residuals and the starts' "
                     "disagreement give")
    warnings.warn(f"track({name!r}): " + "; ".join(parts), stacklevel=3)
