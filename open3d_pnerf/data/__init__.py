"""Sequences: the sequence model, one reader module per dataset format behind a registry,
trajectory files, and the bundled sample."""

from pathlib import Path

from ..camera import check_poses
from .derived import concatenate, depth_in_color_cameras, evenly_spaced
from .images import FrameReader
from .llff import read_llff
from .nerfstudio import read_nerfstudio, write_nerfstudio
from .open3d_folder import write_sequence
from .registry import FORMATS, Format, load_sequence, register_format
from .sequence import Frame, RGBDSequence, check_sequence
from .sfm import SfMData, SparsePoints, sfm_pose_covariances
from .trajectories import read_log_trajectory, write_log_trajectory, write_open3d_trajectory, write_tum_trajectory

SAMPLE_DIR = Path(__file__).parent / "sample" / "tum_fr1_xyz"


def load_sample(**kwargs) -> RGBDSequence:
    """The bundled sample: 11 frames of TUM RGB-D fr1/xyz at 320x240 with GT poses (CC BY 4.0)."""
    return load_sequence(SAMPLE_DIR, **kwargs)


__all__ = [
    "FORMATS", "Format", "Frame", "FrameReader", "RGBDSequence", "SAMPLE_DIR", "SfMData", "SparsePoints",
    "check_poses", "check_sequence", "concatenate", "depth_in_color_cameras", "evenly_spaced", "load_sample",
    "load_sequence", "read_llff", "read_log_trajectory", "read_nerfstudio", "register_format", "sfm_pose_covariances",
    "write_log_trajectory", "write_nerfstudio", "write_open3d_trajectory", "write_sequence", "write_tum_trajectory",
]
