"""Pose-graph assembly, loop-closure candidates and global optimisation.

Follows Open3D's reconstruction system: node i holds frame i's camera-to-world pose; an
edge (source, target, X) holds the transformation mapping source-camera points into the
target camera, so a consistent graph has ``X = inv(pose_target) @ pose_source``, and its
information is the inverse of the registration's covariance. Odometry edges are certain; loop
closures are uncertain (Open3D's line process may prune them).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.stats import chi2

from ..camera import motion


registration = o3d.pipelines.registration

LOOP_PRUNE_CHI2 = float(chi2.ppf(0.999, 6) / (1 / np.sqrt(0.9) - 1))
"""A loop closure whose residual in the optimised graph exceeds this Mahalanobis square (415) is
pruned as inconsistent. Open3D's line process also weighs every loop by (mu / (mu + c))^2 for a
residual c, so mu is set where a consistent loop at the 99.9% point of 6 degrees of freedom (22.5)
keeps 90% of its weight. With mu = 22.5 itself such loops kept a third of it: the synthetic room's
200-frame circuits (seeds 0 and 2) drifted to 36 and 11 frames 1 cm off and outside their
covariances, and none with 415 (benchmarks/README.md)."""


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


def optimize(graph: registration.PoseGraph, prune_chi2: float = LOOP_PRUNE_CHI2,
             edge_prune_threshold: float = 0.25) -> None:
    """Levenberg-Marquardt global optimisation of `graph` in place, node 0 held fixed.

    The edges' information matrices are inverse covariances, so the line process is set on the
    chi-square scale: Open3D weighs an uncertain edge whose residual e gives e^T Lambda e = c by
    (mu / (mu + c))^2 and removes it below `edge_prune_threshold` (0.25: c > mu), where
    mu = preference_loop_closure * max_correspondence_distance^2 * (mean of the edges'
    information[5, 5]); the preference is chosen so that mu = `prune_chi2`.
    """
    mean_information = float(np.mean([edge.information[5, 5] for edge in graph.edges]))
    option = registration.GlobalOptimizationOption(
        max_correspondence_distance=1.0,
        edge_prune_threshold=edge_prune_threshold,
        preference_loop_closure=prune_chi2 / max(mean_information, 1e-300),
        reference_node=0,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        registration.global_optimization(
            graph,
            registration.GlobalOptimizationLevenbergMarquardt(),
            registration.GlobalOptimizationConvergenceCriteria(),
            option,
        )
