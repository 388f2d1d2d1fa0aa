"""Run folders, what the command line writes: a reconstruction's (its config, checkpoints with the
tracked poses, the saved reconstruction, its comparison with TSDF fusion and report.md), an
extension's, a streamed map's, a trajectory's, a TSDF's, an occupancy grid's, renders and evaluations. The command line
(:mod:`open3d_pnerf.cli`) parses its options and calls these.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from ._files import atomic_write, atomic_write_all, read_json_object
from .comparison import FIGURE_ROWS, compare, scores_table
from .config import ReconstructionConfig
from .data import write_log_trajectory, write_open3d_trajectory, write_tum_trajectory
from .data.sequence import RGBDSequence, check_sequence
from .distributed import distributed_session
from .errors import CheckpointError, InputError
from .evaluation import heldout_scores
from .export import write_mesh_ply, write_point_cloud_ply
from .extension import extension_config
from .mapper import Mapper
from .occupancy import FREE_BELOW, OCCUPIED_ABOVE
from .pipeline import run
from .reconstruction import Reconstruction
from .stages import checked_config, resolve_poses
from .tracking import absolute_trajectory_error
from .tsdf import tsdf_fusion

RUN_CONFIG = "run_config.json"


# -- a reconstruction's folder --------------------------------------------------------------------
def reconstruct_folder(sequence: RGBDSequence, config: ReconstructionConfig, out, poses=None, covariances=None,
                       resume: bool = False, inputs: dict | None = None) -> dict | None:
    """:func:`reconstruct` into the folder `out`: run_config.json (the config and `inputs`, what
    names the data, for resuming and evaluating), checkpoints/ (with the tracked poses), the saved
    reconstruction, its comparison with TSDF fusion on the held-out frames (figures,
    tsdf_mesh.ply) and report.json / report.md. resume=True continues the run in `out` from its
    checkpoint. Returns the report; under torchrun every rank trains, rank 0 writes every file
    and the other ranks return None."""
    check_sequence(sequence, 2, "reconstruct(): rgbd_sequence")
    config, out = checked_config(config), Path(out)
    with distributed_session(config.device, config.runtime.dist_backend, config.runtime.dist_timeout_s) as dist:
        if dist.is_main and not resume:
            write_run_config(out, config, inputs or {})
        recon = run(sequence, config, poses, covariances, out / "checkpoints", resume, dist)
    if not dist.is_main:
        return None
    return write_outputs(recon, sequence if recon.frames is None else recon.frames, out, config.progress)


def extend_folder(base_dir, sequence: RGBDSequence, out, overrides: dict | None = None, poses=None,
                  inputs: dict | None = None) -> dict:
    """:meth:`Reconstruction.extend` of the saved reconstruction in `base_dir` (unchanged) into the
    folder `out`, with run_config.json, the saved reconstruction, its comparison with TSDF fusion
    on the held-out frames of all segments and report.json / report.md. overrides: config fields
    changed from the extension's default config (:func:`extension_config`). Returns the report."""
    base = Reconstruction.load(base_dir, (overrides or {}).get("device"))
    config = extension_config(base, None).replace(**overrides) if overrides else None
    recon = base.extend(sequence, config, poses)
    # the frames of all segments are saved with it: evaluate reads those (no "data" recorded)
    write_run_config(Path(out), recon.config, {"extends": str(Path(base_dir).resolve()), "added": inputs or {}})
    return write_outputs(recon, recon.frames, Path(out), recon.config.progress)


def write_outputs(recon: Reconstruction, sequence: RGBDSequence, out: Path, progress: bool) -> dict:
    """Save `recon` (built from `sequence`) into `out` with its comparison with TSDF fusion on the
    held-out frames (figures, tsdf_mesh.ply) and report.json / report.md; returns the report."""
    recon.save(out)
    scores, figures = {}, []
    if len(recon.holdout_indices):  # TSDF of the same training frames and poses; writes tsdf_mesh.ply, figures
        comparison = compare(recon, sequence, progress=progress)
        comparison.save(out)
        scores, figures = comparison.table, [f"compare_frame_{i:04d}.png" for i in comparison.frames]
    report = {"sequence": repr(sequence), "frames": len(sequence), "ate_rmse_m": recon.stats["tracking"].get("ate_rmse_m"),
              "scores": scores, "figures": figures, **recon.stats}
    atomic_write_all({out / "report.json": lambda p: Path(p).write_text(json.dumps(report, indent=1, default=float)),
                      out / "report.md": lambda p: Path(p).write_text(report_markdown(report, recon))})
    return report


def write_run_config(out: Path, config: ReconstructionConfig, inputs: dict) -> None:
    """run_config.json in the run folder `out`: the config and the inputs (what names the data)."""
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"config": config.to_dict(), **inputs}, indent=1, default=float)
    atomic_write(out / RUN_CONFIG, lambda p: Path(p).write_text(text))


def read_run_config(out: Path, what: str) -> dict:
    """The run_config.json of a run folder (CheckpointError naming `what` if it is not one)."""
    path = Path(out) / RUN_CONFIG
    if not path.is_file():
        raise CheckpointError(f"{what} {out}: no {RUN_CONFIG} there (not a reconstruct output folder)")
    return read_json_object(path, CheckpointError)


def report_markdown(report: dict, recon) -> str:
    """report.md of a reconstruct/demo run: tracking, training, timings, geometry and the held-out table."""
    lines = [f"# open3d_pnerf reconstruction: {report['sequence']}", ""]
    if report.get("ate_rmse_m") is not None:
        lines.append(f"- Tracking ATE RMSE vs ground truth: {1000 * report['ate_rmse_m']:.1f} mm")
    tr = report["training"]
    lines += [
        f"- Training: {tr['steps']} steps in {tr['seconds']} s, {tr['samples_per_s'] / 1000:.0f} k samples/s, "
        f"loss {recon.config.loss}, field {recon.config.field}",
        f"- Timings (s): {report['timings']}",
        f"- Mesh: {len(recon.mesh.triangles)} triangles (`mesh.ply`); point cloud: {len(recon.point_cloud.points)} "
        "points with per-point `depth_sigma` (`point_cloud.ply`)",
        "",
    ]
    scores = report["scores"]
    if scores:
        lines += ["## Held-out frames", ""]
        if "tsdf" in scores:
            lines += ["Each method on the held-out frames: on the pixels every method but the last covers, on its "
                      "own hits, and where only the model (or its mesh) covers; the sensor alone is the export "
                      "without the model; the TSDFs are Open3D's of the same training frames and poses (the first "
                      "at the exported mesh's threshold).", ""]
        shown = ", ".join(["input", "model"] + [label for name, label in FIGURE_ROWS.items() if name in scores])
        lines += [*scores_table(scores), "", *(f"![held-out frame: {shown}]({name})" for name in report["figures"])]
    return "\n".join(lines) + "\n"


# -- the other commands' outputs ------------------------------------------------------------------
def map_stream(frames, intrinsic, config: ReconstructionConfig, out, finish: float | None = None,
               total: int | None = None, score_every: int = 5, progress: bool = True) -> dict:
    """Feed `frames` (an iterable of (colour, depth m) pairs or of (o3d.geometry.RGBDImage, timestamp)
    pairs, e.g. a live camera's) in order through a :class:`~open3d_pnerf.Mapper` with `intrinsic` and
    `config`, showing frames, keyframes and the map's held-out PSNR (every `score_every` keyframes) on a
    progress bar of `total` frames; Ctrl-C ends the stream (a live camera's end). Then `finish`
    seconds of training on every keyframe (default config.mapping.finish_s), the map saved into
    `out` (a folder Mapper.resume and extend go on from) with map_report.json; returns that report."""
    import open3d as o3d

    mapper = Mapper(intrinsic, config)
    bar = tqdm(total=total, desc="map", unit="frame", disable=not progress, dynamic_ncols=True)
    scored, score, streaming = 0, None, 0.0
    try:
        for frame in frames:
            image, stamp = frame if isinstance(frame[0], o3d.geometry.RGBDImage) else (frame, None)
            t0 = time.perf_counter()
            mapper.add(image, stamp)
            streaming += time.perf_counter() - t0
            if progress and len(mapper.keyframes) >= scored + score_every and mapper.holdout:
                scored, score = len(mapper.keyframes), mapper.heldout_psnr()
            bar.update(1)
            held_out = f", held-out PSNR {score:.2f} dB" if score else ""
            bar.set_postfix_str(f"keyframes {len(mapper.keyframes)}{held_out}")
    except KeyboardInterrupt:  # a live camera: Ctrl-C ends the capture, the map is finished and saved
        pass
    bar.close()
    if not len(mapper):
        raise InputError("map: no frame was added")
    recon = mapper.finish(finish)
    out = Path(out)
    mapper.save(out, recon)
    summary = {**mapper.summary(), "frames_per_s": round(len(mapper) / max(streaming, 1e-9), 2),
               "finish_s": config.mapping.finish_s if finish is None else finish}
    if len(recon.holdout_indices):
        summary["heldout"] = heldout_scores(recon, recon.frames)["model"]
    atomic_write(out / "map_report.json", lambda p: Path(p).write_text(json.dumps(summary, indent=1, default=float)))
    return summary


def track_folder(sequence: RGBDSequence, out, progress: bool = True) -> str:
    """Track `sequence` and write its trajectory into `out` (trajectory_tum.txt, trajectory.log,
    Open3D's trajectory.json, poses.npy, covariances.npy); returns a one-line summary."""
    traj = ReconstructionConfig().tracking.track(sequence, progress=progress)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_tum_trajectory(out / "trajectory_tum.txt", traj.poses, sequence.timestamps)
    write_log_trajectory(out / "trajectory.log", traj.poses)
    write_open3d_trajectory(out / "trajectory.json", traj.poses, sequence.intrinsic)
    atomic_write_all({out / "poses.npy": lambda p: np.save(p, traj.poses),
                      out / "covariances.npy": lambda p: np.save(p, traj.covariances)})
    msg = f"tracked {len(sequence)} frames; failed frames: {traj.failed_frames or 'none'}"
    if sequence.gt_poses is not None:
        msg += f"; ATE RMSE {1000 * absolute_trajectory_error(traj.poses, sequence.gt_poses)['rmse']:.1f} mm"
    return msg


def tsdf_folder(sequence: RGBDSequence, out, poses=None, voxel_size: float = 0.01, progress: bool = True) -> None:
    """Open3D TSDF fusion of `sequence` at `poses` (None: as reconstruct() would take them, tracked when
    the sequence has none) into `out`: mesh.ply and point_cloud.ply."""
    out = Path(out)
    sequence, poses, _, _ = resolve_poses(sequence, ReconstructionConfig(progress=progress), poses)
    volume = tsdf_fusion(sequence, poses, voxel_size=voxel_size, sdf_trunc=4 * voxel_size, return_volume=True,
                         progress=progress)
    write_mesh_ply(out / "mesh.ply", volume.mesh())
    write_point_cloud_ply(out / "point_cloud.ply", volume.point_cloud())


def render_files(recon: Reconstruction, pose: np.ndarray, out, frame: int | None = None) -> list[Path]:
    """Render `recon` at a camera-to-world `pose` (with frame `frame`'s exposure when given) into the
    PNG `out` (8-bit colour) and <out>_depth.png, <out>_depth_std.png (16-bit, millimetres); returns
    the three paths."""
    view = recon.render(pose, frame=frame)
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    stem = target.with_suffix("")
    images = {target: cv2.cvtColor((view["color"] * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR),
              Path(f"{stem}_depth.png"): (view["depth"] * 1000).round().clip(0, 65535).astype(np.uint16),
              Path(f"{stem}_depth_std.png"): (view["depth_std"] * 1000).round().clip(0, 65535).astype(np.uint16)}
    atomic_write_all({path: (lambda p, a=image: cv2.imwrite(p, a)) for path, image in images.items()})
    return list(images)


def evaluate_folder(folder, recon: Reconstruction, sequence: RGBDSequence, out=None, tsdf: bool = True,
                    progress: bool = True) -> dict:
    """Score the reconstruction `recon` (saved in `folder`) on its held-out frames of `sequence` (and,
    with `tsdf`, the TSDF of its training frames beside it); writes the result as JSON to `out`
    (default folder/evaluation.json) and returns it."""
    folder = Path(folder)
    if len(sequence) != len(recon.poses):
        raise InputError(f"{sequence.name}: {len(sequence)} frames, but {folder} reconstructed {len(recon.poses)}")
    scores = compare(recon, sequence, progress=progress).table if tsdf else heldout_scores(recon, sequence)
    result = {"reconstruction": str(folder.resolve()), "sequence": repr(sequence),
              "holdout_frames": recon.holdout_indices.tolist(), "scores": scores}
    out = Path(out) if out else folder / "evaluation.json"
    atomic_write(out, lambda p: Path(p).write_text(json.dumps(result, indent=1, default=float)))
    return result


def occupancy_folder(recon: Reconstruction, out, voxel_size: float = 0.05, bounds=None) -> dict:
    """Write the reconstruction's occupancy grid of `voxel_size` (m) over `bounds` (None: its scene
    box) into `out`: occupancy.npz (OccupancyGrid.load), occupancy.ot and occupancy.bt (OctoMap) and
    esdf.npz (the distance field), all or none; returns its voxel counts and seconds."""
    t0 = time.perf_counter()
    grid = recon.occupancy_grid(voxel_size, bounds)
    seconds = time.perf_counter() - t0
    esdf = grid.esdf()
    out = Path(out)
    atomic_write_all({out / "occupancy.npz": grid.save, out / "occupancy.ot": grid.write_octomap,
                      out / "occupancy.bt": grid.write_octomap, out / "esdf.npz": esdf.save})
    p = grid.probabilities()
    return {"voxel_size": voxel_size, "shape": list(grid.shape), "occupied": int((p > OCCUPIED_ABOVE).sum()),
            "free": int((p < FREE_BELOW).sum()), "unknown": int(grid.unknown().sum()), "seconds": round(seconds, 2)}
