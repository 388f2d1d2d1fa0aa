"""Pose-graph assembly, loop-closure candidates and global optimisation.

Follows Open3D's reconstruction system: node i holds frame i's camera-to-world pose; an
edge (source, target, X) holds the transformation mapping source-camera points into the
target camera, so a consistent graph has ``X = inv(pose_target) @ pose_source``. Odometry
edges are certain; loop closures are uncertain (Open3D's line process may prune them).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .odometry import motion

registration = o3d.pipelines.registration


def add_edge(
    graph: registration.PoseGraph,
    source: int,
    target: int,
    transformation: np.ndarray,
    information: np.ndarray,
    uncertain: bool,
) -> None:
    """Append an edge; `transformation` (4x4) maps source-camera points into the target's."""
    graph.edges.append(
        registration.PoseGraphEdge(source, target, transformation, information, uncertain=uncertain)
    )


def loop_closure_candidates(
    poses: np.ndarray,
    keyframes: list[int],
    linked: set[tuple[int, int]],
    max_distance_m: float,
    max_angle_deg: float,
    max_per_keyframe: int,
) -> list[tuple[int, int]]:
    """Keyframe pairs (s, t), s < t, worth a loop-closure registration.

    poses: (N, 4, 4) camera-to-world estimates. A pair qualifies when the cameras are
    within `max_distance_m` and `max_angle_deg` of each other and not already `linked` by
    an edge; each keyframe t keeps the `max_per_keyframe` nearest earlier keyframes
    (distance in m plus angle in rad x 1 m, i.e. 1 degree ~ 17 mm).
    """
    pairs = []
    for k, t in enumerate(keyframes):
        scored = []
        for s in keyframes[:k]:
            if (s, t) in linked:
                continue
            dist, angle = motion(np.linalg.inv(poses[t]) @ poses[s])
            if dist <= max_distance_m and angle <= max_angle_deg:
                scored.append((dist + np.radians(angle), s))
        pairs += [(s, t) for _, s in sorted(scored)[:max_per_keyframe]]
    return sorted(pairs)


def optimize(
    graph: registration.PoseGraph,
    max_correspondence_distance: float = 0.07,
    preference_loop_closure: float = 0.1,
    edge_prune_threshold: float = 0.25,
) -> None:
    """Levenberg-Marquardt global optimisation of `graph` in place, node 0 held fixed.

    Defaults are those of Open3D's reconstruction system for frame-level graphs
    (max_correspondence_distance = its depth_diff_max, 7 cm). Uncertain edges whose
    line-process confidence drops below `edge_prune_threshold` are removed from the graph.
    """
    option = registration.GlobalOptimizationOption(
        max_correspondence_distance=max_correspondence_distance,
        edge_prune_threshold=edge_prune_threshold,
        preference_loop_closure=preference_loop_closure,
        reference_node=0,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        registration.global_optimization(
            graph,
            registration.GlobalOptimizationLevenbergMarquardt(),
            registration.GlobalOptimizationConvergenceCriteria(),
            option,
        )
