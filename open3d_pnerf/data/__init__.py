"""Sequences: the RGB-D sequence model, dataset readers, the bundled sample, LLFF image scenes."""

from pathlib import Path

from .llff import ImageSequence, SparsePoints, read_llff, sfm_pose_covariances
from .loaders import load_sequence, read_log_trajectory, write_log_trajectory, write_tum_trajectory
from .sequence import Frame, RGBDSequence, check_poses

SAMPLE_DIR = Path(__file__).parent / "sample" / "tum_fr1_xyz"


def load_sample(**kwargs) -> RGBDSequence:
    """The bundled sample: 11 frames of TUM RGB-D fr1/xyz at 320x240 with GT poses (CC BY 4.0)."""
    return load_sequence(SAMPLE_DIR, **kwargs)


__all__ = [
    "Frame",
    "ImageSequence",
    "RGBDSequence",
    "SAMPLE_DIR",
    "SparsePoints",
    "check_poses",
    "load_sample",
    "load_sequence",
    "read_llff",
    "read_log_trajectory",
    "sfm_pose_covariances",
    "write_log_trajectory",
    "write_tum_trajectory",
]
