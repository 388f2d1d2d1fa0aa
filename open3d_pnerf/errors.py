"""One exception hierarchy for everything a user can get wrong.

Every error is raised at the API boundary and names the file or argument and what was
expected, so that a bad input never surfaces as a deep NumPy/Open3D/torch traceback.
"""


class PNeRFError(Exception):
    """Base class of every error raised on purpose by open3d_pnerf."""


class InputError(PNeRFError, ValueError):
    """An argument or input file is missing, malformed or inconsistent."""


class DatasetError(InputError):
    """A dataset folder or one of its files cannot be read as an RGB-D sequence."""


class PoseError(InputError):
    """Poses are not finite rigid camera-to-world transforms of the expected shape."""


class ConfigError(InputError):
    """An unknown configuration field or an out-of-range value."""


class CheckpointError(InputError):
    """A checkpoint or saved reconstruction is missing, corrupt or from another version."""


class TrackingError(PNeRFError, RuntimeError):
    """Tracking could not produce a trajectory (e.g. every odometry edge failed)."""


class TrainingError(PNeRFError, RuntimeError):
    """Training diverged (NaN/inf loss) or cannot continue."""


class DistributedError(PNeRFError, RuntimeError):
    """Data-parallel training could not join its process group, or a collective failed or
    timed out because another rank died or hung."""


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped training after `step` steps; `checkpoint` (a checkpoint.pt) holds the work.

    A KeyboardInterrupt, so that an interrupted notebook cell or script stops; the message says
    how to continue from the checkpoint or to export what it has.
    """

    def __init__(self, step: int, checkpoint):
        self.step, self.checkpoint = step, checkpoint
        folder = str(checkpoint.parent) if checkpoint is not None else None
        super().__init__(
            f"training interrupted after step {step}; the checkpoint is {checkpoint}. Continue with "
            f"reconstruct(sequence, config, checkpoint_dir={folder!r}, resume=True) (the same sequence and "
            "config); to stop training and export what it has, resume with config.replace(max_steps=1)"
        )
