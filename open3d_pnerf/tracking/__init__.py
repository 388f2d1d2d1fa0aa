"""Camera tracking: Open3D RGB-D odometry, loop closures, pose graph, pose covariances.

    traj = track(sequence)            # Trajectory: poses (N,4,4), covariances (N,6,6), ...
    absolute_trajectory_error(traj.poses, sequence.gt_poses)["rmse"]
"""

from .covariance import edge_jacobians, pose_graph_covariances, pose_graph_hessian
from .metrics import absolute_trajectory_error, consistency_of_errors, covariance_consistency, pose_errors, rigid_alignment
from .odometry import FrameRegistration, OdometryOptions, PairResult
from .tracker import TrackingConfig, track, track_onto
from .trajectory import Edge, Trajectory

__all__ = [
    "Edge",
    "FrameRegistration",
    "OdometryOptions",
    "PairResult",
    "TrackingConfig",
    "Trajectory",
    "absolute_trajectory_error",
    "consistency_of_errors",
    "covariance_consistency",
    "edge_jacobians",
    "pose_graph_covariances",
    "pose_graph_hessian",
    "pose_errors",
    "rigid_alignment",
    "track",
    "track_onto",
]
