"""How the tracker places each frame, and what it does when a registration fails or looks wrong.

Frame i is registered to frame i-1 from the constant-velocity guess; a failed or doubtful result
(:meth:`Chain.doubtful`) is re-done from other starts (no motion, the colour images' keypoints,
the global registration of the point clouds, the last frame registered before i-1:
:func:`candidates`), all of them when the camera moves fast, and the pose most passing starts agree
on is kept (:func:`consensus`), widened by how far the others disagree (:func:`disagreement`). A
frame nothing places keeps the motion before it with a covariance as wide as the plausible
motion; a segment tracked onto a map must register to it (:func:`place_on_map`), never guessed.
"""

from __future__ import annotations

import numpy as np

from ..camera import adjoint, matrix_twist, motion
from ..errors import TrackingError
from .chain import Chain
from .color import measurement_noise
from .odometry import PairResult


def candidates(chain: Chain, i: int):
    """(name, source frame, initial guess source -> i, expected source -> i) to try for frame
    i, in order; the keypoint and global registrations are computed only if reached. Every result is held
    to the plausible-motion limits around the constant-velocity prediction."""
    guess = chain.predicted_pose(i)
    expected = np.linalg.inv(guess) @ chain.poses[i - 1]
    yield "constant velocity", i - 1, expected, expected
    yield "zero motion", i - 1, np.eye(4), expected
    for name, start in (("features", chain.registrar.feature_guess), ("global", chain.registrar.global_guess)):
        found = start(i - 1, i)
        if found is not None:
            yield name, i - 1, found, expected
    earlier = [j for j in chain.registered if j < i - 1]
    if earlier:
        from_earlier = np.linalg.inv(guess) @ chain.poses[earlier[-1]]
        yield f"from frame {earlier[-1]}", earlier[-1], from_earlier, from_earlier


def track_frame(chain: Chain, i: int) -> None:
    """Add frame i: the consensus of the candidates that pass (try_candidates), else a guess."""
    chain.registrar.prefetch(i + 1)
    passed = try_candidates(chain, i)
    if not add_registered(chain, i, passed):  # nothing placed it: continue the motion, with a covariance to match
        chain.failed_frames.append(i)
        pose, source = chain.predicted_pose(i), i - 1
        chain.add_node(i, pose, source, np.linalg.inv(pose) @ chain.poses[source], chain.guess_covariance,
                       uncertain=True)


def place_on_map(chain: Chain, i: int, anchors: list[int], name: str) -> int:
    """Add frame i, the first after the known ones, from the chain's candidates or else from
    zero motion, the keypoints or a global registration to each map frame in `anchors`;
    returns the frame it was registered from. TrackingError when none passes (nothing is
    guessed)."""
    passed = try_candidates(chain, i)
    for j in anchors if not passed else ():
        for start, init in (("zero motion", lambda: np.eye(4)),
                            ("features", lambda: chain.registrar.feature_guess(j, i)),
                            ("global", lambda: chain.registrar.global_guess(j, i))):
            guess = init()
            result = None if guess is None else chain.register(j, i, "odometry", chain.options, guess,
                                                               f"map frame {j}: {start}")
            if result is not None and result.success:
                passed.append((result, j))
                break
    if not add_registered(chain, i, passed):
        tried = sorted({e.source for e in chain.edges if e.target == i})
        raise TrackingError(f"{name}: frame {i}, the first new frame, registers to none of the map's frames "
                            f"tried ({tried}): the new frames do not overlap the map, or their depth is not usable "
                            "(a guess would put them anywhere, so they are not added)")
    return chain.graph.edges[-1].source_node_id


def try_candidates(chain: Chain, i: int) -> list[tuple[PairResult, int]]:
    """The (registration, source) of frame i's candidates that pass: up to the first that
    passes and is not doubtful, or all of them when the camera moves fast or one of them
    lands beyond the search_all_above limits from the prediction. (7-Scenes every 10th frame,
    frame 87: when the constant-velocity start passes, odometry settles 37-52 mm off, 66-73 mm
    from the prediction, at a residual and overlap that need not stand out; where exactly depends
    on the last bits of Open3D's multi-threaded sums, so the run decided whether it was tried
    again: benchmarks/bench_tracking_starts.py.)"""
    passed = []
    search_all = chain.fast_motion(i)
    for name, source, init, expected in candidates(chain, i):
        result = chain.register(source, i, "odometry", chain.options, init, name, expected)
        if result.success:
            passed.append((result, source))
            search_all = search_all or chain.fast(np.linalg.inv(expected) @ result.transformation)
            if not chain.doubtful(result) and not search_all:
                break
    return passed


def add_registered(chain: Chain, i: int, passed: list[tuple[PairResult, int]]) -> bool:
    """Add frame i from the consensus of its passing registrations; False when there is none."""
    best, recovered = consensus(chain, passed)
    if best is None:
        return False
    result, source = best
    if recovered:
        chain.recovered_frames.append(i)
    if chain.suspicious(result):
        chain.flagged_frames.append(i)
    else:
        chain.residuals.append(result.residual_rms)
        chain.overlaps.append(result.overlap)
        chain.depths.append(result.depth)
    chain.registered.append(i)
    pose = chain.poses[source] @ np.linalg.inv(result.transformation)
    spread = disagreement(chain, pose, source, result.transformation, passed)
    if spread.any() and i not in chain.flagged_frames:
        chain.flagged_frames.append(i)
    chain.add_node(i, pose, source, result.transformation, result.covariance + spread)
    if source == i - 1:
        chain.steps[i] = result.transformation
        if chain.colors is not None and result.odometry_transformation is not None:
            back = np.linalg.inv(result.transformation)  # frame i -> i-1, its covariance carried over
            ad = adjoint(back)
            noise = measurement_noise(result.residual_covariance, result.depth)
            chain.colors.add(i, np.linalg.inv(result.odometry_transformation), back, ad @ noise @ ad.T)
    return True


def disagreement(chain: Chain, pose: np.ndarray, source: int, transformation: np.ndarray,
                 passed: list[tuple[PairResult, int]]) -> np.ndarray:
    """(6, 6) sum of xi xi^T over the passing candidates that reached another pose than the
    kept one: xi, the left perturbation [rotation, translation] of the kept edge
    (source -> i) that gives the other candidate's pose. Added to the edge's covariance, so
    that when starts disagree the pose is uncertain by as much as they disagree (a choice
    between minima that the residuals cannot make reliably; zeros when all agree)."""
    extra = np.zeros((6, 6))
    for result, other_source in passed:
        other = chain.poses[other_source] @ np.linalg.inv(result.transformation)
        moved_m, turned_deg = motion(np.linalg.inv(pose) @ other)
        if moved_m < chain.options.inlier_distance_m and turned_deg < 1.0:
            continue
        xi = matrix_twist(np.linalg.inv(other) @ chain.poses[source] @ np.linalg.inv(transformation))  # exp(xi)
        extra += np.outer(xi, xi)
    return extra


def consensus(chain: Chain, passed: list[tuple[PairResult, int]]) -> tuple[tuple[PairResult, int] | None, bool]:
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
    poses = [chain.poses[source] @ np.linalg.inv(result.transformation) for result, source in passed]

    def agree(a: np.ndarray, b: np.ndarray) -> bool:
        moved_m, turned_deg = motion(np.linalg.inv(a) @ b)
        return moved_m < chain.options.inlier_distance_m and turned_deg < 1.0

    groups = [[q for q, other in enumerate(poses) if agree(pose, other)] for pose in poses]
    fit = [min(passed[q][0].residual_rms / passed[q][0].overlap for q in group) for group in groups]
    k = min(range(len(passed)), key=lambda j: (-len(groups[j]), fit[j], passed[j][0].residual_rms))
    recovered = not any(result.init == "constant velocity" and agree(poses[k], pose)
                        for (result, _), pose in zip(passed, poses))
    return passed[k], recovered
