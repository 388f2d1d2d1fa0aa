"""The reconstruction pipeline, the one orchestrator of ``reconstruct()``, ``compare_with_tsdf``, the
command line and the benchmarks: it runs the stages (:mod:`open3d_pnerf.stages`: poses, depth
targets and the scene box, the model and its training, calibration and export) on one rank of a
data-parallel launch or alone, and returns the :class:`~open3d_pnerf.Reconstruction`.
"""

from __future__ import annotations

import time
from pathlib import Path

from tqdm.auto import tqdm

from .comparison import Comparison, compare
from .config import ReconstructionConfig
from .data.sequence import RGBDSequence, check_sequence
from .distributed import DistributedContext, distributed_session
from .errors import InputError
from .reconstruction import Reconstruction
from .scene import ndc_depth_range
from .stages import checked_config, finish, fit, resolve_poses, split_frames
from .training import read_checkpoint


def run(sequence: RGBDSequence, config: ReconstructionConfig, poses=None, covariances=None, checkpoint_dir=None,
        resume: bool = False, dist: DistributedContext | None = None, export: bool = True) -> Reconstruction:
    """All stages on one rank of `dist` (a single process by default); see :func:`reconstruct`.
    export=False stops after training (no calibration, mesh or point cloud)."""
    dist = dist or DistributedContext()
    if not dist.is_main:
        config = config.replace(progress=False)
    if dist.enabled:
        config = config.replace(device=dist.device(config.device))
    train_idx, hold_idx = split_frames(len(sequence), config.holdout_every, config.train_views)
    ndc_depth_range(sequence, config.ndc)  # ndc="on" on a sequence that cannot have it fails before any work
    checkpoint = None
    if resume:  # read it now, not after minutes of tracking
        if not checkpoint_dir:
            raise InputError("resume=True needs checkpoint_dir")
        checkpoint = read_checkpoint(Path(checkpoint_dir) / "checkpoint.pt")
    stages = tqdm(total=4, desc="reconstruct", disable=not config.progress, dynamic_ncols=True)
    timings = {}
    t0 = time.perf_counter()

    stages.set_postfix_str("tracking")  # given poses are checked first, before any work
    sequence, poses, covariances, tracking = resolve_poses(sequence, config, poses, covariances, checkpoint_dir,
                                                           resume, write=dist.is_main)
    if dist.enabled:  # every rank trains on rank 0's trajectory, bit for bit
        poses = dist.broadcast_array(poses, "the poses' broadcast", config.device)
        covariances = dist.broadcast_array(covariances, "the covariances' broadcast", config.device)
    timings["tracking_s"] = round(time.perf_counter() - t0, 2)
    stages.update(1)

    recon = Reconstruction(**fit(sequence, config, poses, covariances, train_idx, hold_idx, tracking, timings, stages,
                                 checkpoint_dir=checkpoint_dir, checkpoint=checkpoint, dist=dist))
    finish(recon, sequence, timings, stages, t0, export, dist)
    return recon


def reconstruct(rgbd_sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                covariances=None, checkpoint_dir=None, resume: bool = False) -> Reconstruction:
    """Reconstruct a probabilistic scene model from an RGB-D sequence.

    Stages: poses (tracking, skipped when `poses` are given: (N, 4, 4) camera-to-world, an Open3D
    ``PinholeCameraTrajectory`` or a Trajectory), per-pixel depth targets, training the model,
    exporting mesh and point cloud. An image-only sequence (an LLFF folder: ``has_depth`` False)
    brings its SfM poses and covariances and trains on its sparse points' targets; its depth
    spread is not calibrated (no sensor depth).
    config: a ReconstructionConfig (default: ReconstructionConfig(), the "fast" preset).
    checkpoint_dir: where training checkpoints (and tracked poses) go; resume=True continues from
    its checkpoint.pt with the poses tracked before.

    Launched by torchrun with several ranks, training is data-parallel (see
    :mod:`open3d_pnerf.distributed`): every rank tracks and builds depth targets itself and
    takes rank 0's poses, covariances and scene box; rank 0 shows progress, writes the
    checkpoints, calibrates and exports. The other ranks return the same trained field
    without calibration or export (no mesh or point cloud). Resuming reads checkpoint_dir
    on every rank: it must be the same checkpoint on every machine.

    Ctrl-C (or interrupting a notebook cell) stops training after the current step, writes the
    checkpoint (to checkpoint_dir, or a new temporary folder) and raises
    :class:`~open3d_pnerf.errors.TrainingInterrupted`, a KeyboardInterrupt naming it. Resume
    with the same sequence and config; to export what the checkpoint has without training
    further, resume with ``config.replace(max_steps=1)``.
    """
    check_sequence(rgbd_sequence, 2, "reconstruct(): rgbd_sequence")
    config = checked_config(config)
    with distributed_session(config.device, config.runtime.dist_backend, config.runtime.dist_timeout_s) as dist:
        return run(rgbd_sequence, config, poses, covariances, checkpoint_dir, resume, dist)


def compare_with_tsdf(sequence: RGBDSequence, config: ReconstructionConfig | None = None, poses=None,
                      covariances=None, reconstruction: Reconstruction | None = None, reference=None,
                      figure_frames: int = 2, voxel_size: float = 0.01, weight_threshold: float | None = None,
                      progress: bool = True) -> Comparison:
    """Train (or take) a model and fuse the TSDF baseline on the same frames; compare them.

    sequence: the RGB-D sequence the model was (or is to be) trained on. config: for
    training (default: the "fast" preset holding out every 4th frame); ignored when a
    trained `reconstruction` of this sequence is given. poses/covariances: as for
    reconstruct(). reference: a ground-truth ``o3d.geometry.TriangleMesh`` or
    ``PointCloud`` (world frame of the poses) for geometry metrics. voxel_size: TSDF voxel
    (m), truncated as the exported mesh is (export.mesh_trunc_voxels). weight_threshold: the
    TSDF keeps voxels seen by more training frames than this; None = the exported mesh's own
    threshold (export.mesh_min_views - 0.5), so both keep the same surfaces; Open3D's default
    (3) is a second, labelled row. Every method is rendered at the held-out poses at the
    training resolution, against the frames the model was built from
    (``reconstruction.frames``: tracked frames have their depth moved into their colour
    cameras, see :func:`resolve_poses`). An image-only sequence (no depth images, e.g.
    an LLFF folder) has no TSDF to fuse: the model is scored alone (colour metrics). See
    :func:`open3d_pnerf.comparison.compare`.
    """
    if not isinstance(sequence, RGBDSequence):
        raise InputError(f"sequence must be an RGBDSequence, got {type(sequence).__name__}")
    if reconstruction is None:
        config = config or ReconstructionConfig.preset("fast", holdout_every=4, progress=progress)
        reconstruction = reconstruct(sequence, config, poses=poses, covariances=covariances)
    elif not isinstance(reconstruction, Reconstruction):
        raise InputError(f"reconstruction must be a Reconstruction, got {type(reconstruction).__name__}")
    frames = sequence if reconstruction.frames is None else reconstruction.frames
    return compare(reconstruction, frames, reference, figure_frames, voxel_size, weight_threshold, progress)
