"""Tracking results: the estimated trajectory with covariances and the registration log."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d


@dataclasses.dataclass(frozen=True)
class Edge:
    """One attempted registration of frame `source` to frame `target`.

    kind: "odometry" (consecutive frames, or a fallback from an earlier frame after a
    failure) or "loop" (a loop closure between keyframes). success: the result passed the
    checks (and, for loops, survived global optimisation). fitness / inlier_rmse: Open3D's
    odometry result. overlap: fraction of the source's valid depth pixels with a
    correspondence after alignment. correspondences: how many of the refinement's sampled
    source pixels have one.
    residual_rms: point-to-plane residual after alignment (m); init: the initial guess it
    started from ("constant velocity", "zero motion", "features", "global", "from frame j", "loop").
    """

    source: int
    target: int
    kind: str
    success: bool
    fitness: float
    inlier_rmse: float
    overlap: float
    correspondences: int
    message: str = ""
    residual_rms: float = float("nan")
    init: str = ""


@dataclasses.dataclass
class Trajectory:
    """Camera trajectory estimated by :func:`~open3d_pnerf.tracking.track`.

    poses: (N, 4, 4) float64 camera-to-world in metres, frame 0 = identity.
    covariances: (N, 6, 6) float64, [rotation (rad^2), translation (m^2)] of the right
    perturbation ``pose @ exp(xi)`` (xi in the camera frame); zero for frame 0.
    pose_graph: the optimised ``o3d.pipelines.registration.PoseGraph`` (node i = frame i).
    edges: every attempted registration (see :class:`Edge`), including failed ones.
    failed_frames: frames that no registration placed: their pose is a guess (the motion so far,
    continued) with a covariance as wide as the plausible motion, and so are the covariances of
    the frames chained through them. flagged_frames: frames placed by a registration whose
    residual stayed high against the sequence's others, or whose initial guesses reached different
    poses (kept, with the covariance their residuals and that disagreement give).
    recovered_frames: frames whose registration from the constant-velocity guess failed, looked
    suspicious, overlapped little or was outvoted, and that another initial guess placed.
    timestamps: (N,) float64 seconds, from the sequence.
    color_offsets: (N, 4, 4) each frame's colour camera in its depth camera's frame (the colour
    image's pose is ``poses[i] @ color_offsets[i]``, see :mod:`~open3d_pnerf.tracking.color`), or
    None when not estimated (colour not registered to the depth, or not asked for).
    """

    poses: np.ndarray
    covariances: np.ndarray
    pose_graph: o3d.pipelines.registration.PoseGraph
    edges: list[Edge]
    failed_frames: list[int]
    timestamps: np.ndarray
    flagged_frames: list[int] = dataclasses.field(default_factory=list)
    recovered_frames: list[int] = dataclasses.field(default_factory=list)
    color_offsets: np.ndarray | None = None

    @property
    def color_poses(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses of the colour images (the depth ones when no offsets)."""
        return self.poses if self.color_offsets is None else self.poses @ self.color_offsets

    def __len__(self) -> int:
        return len(self.poses)

    def __repr__(self) -> str:
        loops = sum(e.kind == "loop" and e.success for e in self.edges)
        return (
            f"Trajectory({len(self)} poses, {loops} loop closures, "
            f"failed frames {self.failed_frames}, flagged frames {self.flagged_frames}, "
            f"recovered frames {self.recovered_frames})"
        )
