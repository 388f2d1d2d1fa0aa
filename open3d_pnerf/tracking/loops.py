"""Loop closures: keyframe pairs that see the same place are registered, added to the pose graph as
uncertain edges, and the graph optimised by Open3D's ``global_optimization`` (Levenberg-Marquardt,
frame 0 fixed), whose line process prunes the loops that do not fit (as Open3D's reconstruction
system does between fragments).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
from scipy.stats import chi2
from tqdm.auto import tqdm

from ..camera import motion
from ..data.sequence import RGBDSequence
from .chain import Chain
from .odometry import OdometryOptions

registration = o3d.pipelines.registration

LOOP_PRUNE_CHI2 = float(chi2.ppf(0.999, 6) / (1 / np.sqrt(0.9) - 1))
"""A loop closure whose residual in the optimised graph exceeds this Mahalanobis square (415) is
pruned as inconsistent. Open3D's line process also weighs every loop by (mu / (mu + c))^2 for a
residual c, so mu is set where a consistent loop at the 99.9% point of 6 degrees of freedom (22.5)
keeps 90% of its weight. With mu = 22.5 itself such loops kept a third of it: the synthetic room's
200-frame circuits (seeds 0 and 2) drifted to 36 and 11 frames 1 cm off and outside their
covariances, and none with 415 (benchmarks/README.md)."""

LOOP_INFLATION = 16.0
"""A loop closure's covariance is this many times its registration's: its two images already
entered the odometry chain, so it is not an independent measurement (the error common to all
registrations is OdometryOptions.misregistration_systematic, which no edge carries). Chosen on the
tuning halves, with 4 rejected by the synthetic Monte-Carlo draws (benchmarks/README.md)."""


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


def close_loops(chain: Chain, sequence: RGBDSequence, keyframes: list[int], odometry: OdometryOptions,
                loop_odometry: OdometryOptions | None, max_distance_m: float, max_angle_deg: float,
                per_keyframe: int, progress: bool, new_from: int = 0) -> None:
    """Register the keyframe pairs near each other that have a frame from `new_from` on, add the
    passing ones as uncertain edges, and optimise the graph when any was added."""
    linked = {(e.source_node_id, e.target_node_id) for e in chain.graph.edges}
    pairs = [(s, t) for s, t in loop_closure_candidates(np.stack(chain.poses), keyframes, linked, max_distance_m,
                                                         max_angle_deg, per_keyframe) if t >= new_from]
    loop_odometry = loop_odometry or default_loop_odometry(sequence, odometry)
    chain.registrar.reserve(sorted({frame for pair in pairs for frame in pair}))
    for k, (s, t) in enumerate(tqdm(pairs, desc="loop closures", disable=not progress, leave=False)):
        for frame in pairs[k + 1] if k + 1 < len(pairs) else ():
            chain.registrar.prefetch(frame)
        close_loop(chain, s, t, loop_odometry)
    if any(e.kind == "loop" and e.success for e in chain.edges):
        optimize(chain.graph)
        mark_pruned_loops(chain)


def close_loop(chain: Chain, s: int, t: int, options: OdometryOptions) -> None:
    """Register keyframe s to keyframe t; add an uncertain edge when it passes every check."""
    result = chain.register(s, t, "loop", options, chain.relative(s, t), "loop", frame_steps=chain.frame_steps(s, t))
    if result.success and chain.suspicious(result):
        chain.edges[-1] = dataclasses.replace(chain.edges[-1], success=False,
                                              message="residual far above the sequence's registrations")
    elif result.success:
        chain.add_edge(s, t, result.transformation, LOOP_INFLATION * result.covariance, uncertain=True)


def mark_pruned_loops(chain: Chain) -> None:
    """Flag the loop closures that global optimisation pruned as unsuccessful."""
    kept = {(e.source_node_id, e.target_node_id) for e in chain.graph.edges}
    for k, e in enumerate(chain.edges):
        if e.kind == "loop" and e.success and (e.source, e.target) not in kept:
            chain.edges[k] = dataclasses.replace(e, success=False, message="pruned by global optimisation")


def default_loop_odometry(sequence: RGBDSequence, odometry: OdometryOptions) -> OdometryOptions:
    """`odometry`, made purely geometric when the colour is not registered to the depth:
    wide-baseline loop closures magnify any colour-to-depth misregistration in the photometric
    term."""
    return odometry if sequence.color_registered else dataclasses.replace(odometry, method="point_to_plane")
