"""Camera tracking: Open3D RGB-D odometry, loop closures, pose graph, pose covariances.

    traj = track(sequence)            # Trajectory: poses (N,4,4), covariances (N,6,6), ...
    absolute_trajectory_error(traj.poses, sequence.gt_poses)["rmse"]

One module per job: ``odometry`` (a verified registration of two frames) with ``uncertainty`` (its
sub-pixel refinement and covariance) and ``starts`` (initial guesses without a motion model);
``chain`` (a run's poses, pose graph and log), ``recovery`` (how each frame is placed, and what
happens when a registration fails), ``loops`` (loop closures and the graph's optimisation),
``covariance`` (the graph's marginals), ``color`` (the colour cameras beside the depth ones);
``tracker`` puts them together; ``metrics`` scores a trajectory against ground truth.
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
