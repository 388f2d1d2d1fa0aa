"""open3d_pnerf: probabilistic neural scene representations (PNeRF) from RGB-D, for Open3D.

Public API::

    seq = open3d_pnerf.load_sequence("path/to/tum_or_7scenes_or_redwood_folder")
    traj = open3d_pnerf.track(seq)                      # poses + 6x6 covariances
    targets = open3d_pnerf.depth_targets(seq, traj)     # per-pixel depth mean and sigma
    mesh = open3d_pnerf.tsdf_fusion(seq, traj.poses)    # the Open3D TSDF baseline
    recon = open3d_pnerf.reconstruct(seq)               # all of it + the probabilistic NeRF
    bigger = recon.extend(more_frames)                  # the map grows: new frames tracked onto it
    mapper = open3d_pnerf.Mapper(seq.intrinsic)         # or map a live stream: mapper.add(rgbd_image)
    cmp = open3d_pnerf.compare_with_tsdf(seq, reconstruction=recon)
"""

from ._deps import require

require("open3d")
require("torch")

from . import errors  # noqa: E402
from .comparison import Comparison  # noqa: E402
from .config import ReconstructionConfig  # noqa: E402
from .data import RGBDSequence, SfMData, load_sample, load_sequence  # noqa: E402
from .losses import LossWeights  # noqa: E402
from .mapper import Mapper  # noqa: E402
from .model import PNeRFModel  # noqa: E402
from .pipeline import compare_with_tsdf, reconstruct  # noqa: E402
from .reconstruction import Reconstruction  # noqa: E402
from .synthetic import synthetic_sequence  # noqa: E402
from .targets import DepthTargets, SensorNoise, depth_targets, sparse_depth_targets  # noqa: E402
from .tracking import Trajectory, absolute_trajectory_error, track  # noqa: E402
from .tsdf import TSDFVolume, tsdf_fusion  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Comparison",
    "DepthTargets",
    "LossWeights",
    "Mapper",
    "PNeRFModel",
    "RGBDSequence",
    "Reconstruction",
    "ReconstructionConfig",
    "SensorNoise",
    "SfMData",
    "TSDFVolume",
    "Trajectory",
    "absolute_trajectory_error",
    "compare_with_tsdf",
    "depth_targets",
    "errors",
    "load_sample",
    "load_sequence",
    "reconstruct",
    "sparse_depth_targets",
    "synthetic_sequence",
    "track",
    "tsdf_fusion",
]

