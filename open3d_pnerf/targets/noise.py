"""Depth noise of an RGB-D sensor: the one model that targets assume and the synthetic sensor draws,
and the targets' settings (TargetsConfig)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..settings import Settings, number, setting


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


@dataclasses.dataclass
class TargetsConfig(Settings):
    """How depth targets are built."""

    depth_sigma_relative: float = setting(SensorNoise.relative, number(0, 1, high_open=True))
    """Systematic depth error of the sensor as a fraction of depth (SensorNoise.relative):
    widens every depth target by relative * z in quadrature, after multi-view fusion
    (calibration and registration errors are shared by all views). 0 = random noise only."""

    def sensor_noise(self) -> SensorNoise:
        """The sensor noise model with this systematic term (targets and export use it)."""
        return SensorNoise(relative=self.depth_sigma_relative)
