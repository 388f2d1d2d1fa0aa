"""Uncertain depth targets: the sensor noise model, dense multi-view fusion of RGB-D frames,
sparse targets from SfM points, and their storage."""

from .dense import TargetsConfig, depth_targets, reproject
from .noise import SensorNoise
from .sparse import gaussian_along_ray, sparse_depth_targets
from .storage import DepthTargets

__all__ = ["DepthTargets", "SensorNoise", "TargetsConfig", "depth_targets", "gaussian_along_ray", "reproject", "sparse_depth_targets"]
