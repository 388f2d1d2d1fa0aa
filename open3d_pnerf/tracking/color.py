"""Where each frame's colour image was taken: its camera beside the depth camera the tracker places.

A TUM-style RGB-D camera does not take its colour and depth images at the same instant (fr1: up
to 20 ms apart) and its factory registration of the two is not exact, so the pose that fits a
frame's depth (what the point-to-plane refinement gives) leaves its colour image off the colour
images of the frames around it. Each frame's colour camera is estimated as a small offset delta_i
of its depth camera (colour pose = pose_i @ delta_i) from the relative poses that fit the colour
images of consecutive frames: Open3D's hybrid odometry answers, whose intensity term dominates
(with depth in metres and intensity in [0, 1] on equal weights), before the tracker refines them
on the depth. The colour relative pose is X^c_i = delta_{i-1}^-1 X_i delta_i (X_i the depth cameras'
relative pose, frame i -> i-1), which with delta_i = exp(a_i) reads, to first order,

    log(X^c_i X_i^-1) = Ad(X_i) a_i - a_{i-1} + noise   (noise: the depth registration's residual
                                                        covariance plus MEASUREMENT_FLOOR_RAD),

and with a prior a_i ~ N(0, OFFSET_PRIOR) (which also settles what consecutive frames cannot
see: an offset common to every frame) all offsets are solved at once by least squares.

Measured: `make demo` (the bundled sample) reaches 24.69 dB held-out PSNR on the colour cameras
(benchmarks/results/demo.md, 3 runs; 21.48 dB with the depth cameras' poses, the same file at
commit 8696d16), and on TUM fr1/xyz the colour cameras beat the ground-truth poses in every seed and the
depth cameras by 2.7 dB (results/color_poses.md). Refining one pose on colour and depth at once was
tried first and cost held-out depth (exploratory): one pose cannot fit both images when they were
taken apart.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import spsolve

from ..camera import adjoint, matrix_twist, motion, twist_matrix
from .covariance import block_matrix
from .uncertainty import misregistration_covariance

OFFSET_PRIOR = np.diag([5e-3**2] * 3 + [1e-2**2] * 3)
"""Prior covariance of a colour camera's offset from its depth camera ([rotation rad, translation
m]): 20 ms of a hand-held camera's motion (0.25 rad/s, 0.5 m/s) and the registration's error."""
MEASUREMENT_FLOOR_RAD = 3e-3
"""A colour relative pose's noise is its depth registration's residual covariance plus a constant
misregistration of this (rad; translation: times the median depth): the photometric answer's own
error does not grow with the motion as the depth registration's does, and weighing the fast
frames (where a colour camera's offset shows most) less cost the bundled sample's held-out TSDF
colour 0.2 dB and the demo 0.5 dB (benchmarks/README.md). The tracker's former constant floor."""
MAX_DISAGREEMENT = (0.03, 2.0)
"""A colour relative pose further than this (m, degrees) from the depth one is not used (a
wrong minimum of the photometric alignment, not a colour camera's offset)."""


def measurement_noise(residual_covariance: np.ndarray, depth: float) -> np.ndarray:
    """(6, 6) noise of a colour relative pose measured beside a depth registration: that
    registration's residual covariance (6, 6) plus MEASUREMENT_FLOOR_RAD at its median depth (m)."""
    return residual_covariance + misregistration_covariance(MEASUREMENT_FLOOR_RAD, depth)


class ColorOffsets:
    """The colour relative poses of consecutive frames, gathered while a sequence is tracked, and
    every frame's colour-camera offset solved from them at the end."""

    def __init__(self):
        self.measured: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # i -> (X^c_i, covariance)

    def add(self, i: int, color: np.ndarray, depth: np.ndarray, covariance: np.ndarray) -> None:
        """Frame i's colour relative pose `color` (4, 4, frame i -> i-1) beside its depth one
        `depth`, with that registration's covariance (6, 6, left perturbation in frame i-1's
        camera); ignored when implausible."""
        if not np.isfinite(color).all():
            return
        moved_m, turned_deg = motion(color @ np.linalg.inv(depth))
        if moved_m < MAX_DISAGREEMENT[0] and turned_deg < MAX_DISAGREEMENT[1]:
            self.measured[i] = (np.asarray(color, np.float64), covariance)

    def solve(self, poses: np.ndarray) -> np.ndarray:
        """(N, 4, 4) offsets delta_i of the colour cameras from the depth cameras at `poses` (N, 4, 4)."""
        n = len(poses)
        prior = np.linalg.inv(OFFSET_PRIOR)
        rows, cols, blocks = list(range(n)), list(range(n)), [prior] * n
        rhs = np.zeros((n, 6))
        for i, (color, covariance) in self.measured.items():
            relative = np.linalg.inv(poses[i - 1]) @ poses[i]
            m = matrix_twist(color @ np.linalg.inv(relative))
            weight = np.linalg.pinv(covariance, hermitian=True)
            terms = {i: adjoint(relative), i - 1: -np.eye(6)}  # m = sum_j D_j a_j + noise
            for a, d_a in terms.items():
                rhs[a] += d_a.T @ weight @ m
                for b, d_b in terms.items():
                    rows.append(a)
                    cols.append(b)
                    blocks.append(d_a.T @ weight @ d_b)
        twists = spsolve(block_matrix(rows, cols, blocks, n), rhs.ravel()).reshape(n, 6)
        return np.stack([twist_matrix(a) for a in twists])
