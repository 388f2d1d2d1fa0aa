"""The chain of a tracking run: every frame's pose as it is placed, the pose graph it builds (node i
holds frame i's camera-to-world pose; an edge (source, target, X) the transformation mapping
source-camera points into the target camera, so a consistent graph has ``X = inv(pose_target) @
pose_source``, and its information is the inverse of the registration's covariance), the log of
every registration tried, and the statistics that the next registrations are judged by. How a frame
is placed is :mod:`~open3d_pnerf.tracking.recovery`'s, how loops join it
:mod:`~open3d_pnerf.tracking.loops`'.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..camera import motion
from .color import ColorOffsets
from .covariance import pose_graph_covariances
from .odometry import FrameRegistration, OdometryOptions, PairResult
from .trajectory import Edge
from .uncertainty import misregistration_covariance

PINNED_VARIANCE = 1e-10
"""Variance (rad^2, m^2) of the edges that pin known poses to frame 0 when tracking onto a map
(:func:`track_onto`): the optimisation leaves them where they are."""


class Chain:
    """Mutable state of one tracking run: chain poses, pose graph, registration log and statistics.

    registrar: the sequence's FrameRegistration; options: its odometry's settings; known_poses
    (K, 4, 4): frames already placed (a map the new frames are tracked onto), pinned where they are;
    colors: gathers the colour relative poses of consecutive frames (tracking.color), or None.
    """

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

    def fast(self, relative: np.ndarray) -> bool:
        """Whether a (4, 4) relative pose exceeds the options' search_all_above limits."""
        moved_m, turned_deg = motion(relative)
        return moved_m > self.options.search_all_above_m or turned_deg > self.options.search_all_above_deg

    def fast_motion(self, i: int) -> bool:
        """Whether the motion predicted from frame i-1 to i exceeds the options' search_all_above limits."""
        return i >= 2 and self.fast(self.relative(i - 1, i - 2))

    def add_node(self, i: int, pose: np.ndarray, source: int, transformation: np.ndarray, covariance: np.ndarray,
                 uncertain: bool = False) -> None:
        """Append frame i's pose, its graph node and its edge from `source` with the edge's covariance."""
        self.poses.append(pose)
        self.graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(pose))
        self.add_edge(source, i, transformation, covariance, uncertain)

    def frame_steps(self, *frames: int) -> list[np.ndarray] | None:
        """The frames' own steps (their accepted registrations from the frame before; frame 0:
        frame 1's), what a registration of non-consecutive frames grows its misregistration floor
        with; None when this run registered none of them (then the floor grows with the
        registration's own motion: a bound, FrameRegistration.register)."""
        steps = [self.steps[k] for k in (k or 1 for k in frames) if k in self.steps]
        return steps or None

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
        information = np.linalg.pinv(covariance, hermitian=True)
        self.graph.edges.append(o3d.pipelines.registration.PoseGraphEdge(source, target, transformation, information,
                                                                         uncertain=uncertain))


def constant_velocity_pose(poses, i: int) -> np.ndarray:
    """Frame i's camera-to-world pose (4, 4) if the camera kept its motion from frame i-2 to i-1
    (poses: a sequence of (4, 4) camera-to-world poses of frames 0..i-1); frame i-1's pose for i < 2."""
    if i < 2:
        return poses[i - 1]
    return poses[i - 1] @ np.linalg.inv(poses[i - 2]) @ poses[i - 1]
