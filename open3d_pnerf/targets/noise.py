"""Depth noise of an RGB-D sensor: the one model that targets assume and the synthetic sensor draws."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Depth noise of a sensor, in metres for z-depth z in metres.

    Random axial noise sigma_z(z) = a + b (z - c)^2 (Nguyen et al. 2012, Kinect): independent
    between frames, so fusing views averages it down. Systematic error sigma_sys(z) = relative * z
    (calibration, depth distortion, depth-to-colour registration): the same in every frame of
    the sensor, so fusion cannot average it away; it is added to each fused target.
    """

    a: float = 0.0012
    b: float = 0.0019
    c: float = 0.4
    relative: float = 0.02

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Random sigma_z (m) for z-depth `z` (m), any shape."""
        return self.a + self.b * (z - self.c) ** 2

    def systematic_var(self, z: np.ndarray) -> np.ndarray:
        """Variance (m^2) of the systematic error at z-depth `z` (m), any shape."""
        return (self.relative * z) ** 2

