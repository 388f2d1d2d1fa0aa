"""The `open3d-pnerf` command line: demo, reconstruct, extend, map, track, tsdf, render, evaluate, occupancy,
formats.

Errors a user can fix are printed as one line (`open3d-pnerf: error: ...`) with exit code 2;
Ctrl-C exits with 130 after training has written its checkpoint. `reconstruct` and `demo`
train data-parallel when launched by torchrun (`torchrun --nproc-per-node N -m
open3d_pnerf.cli reconstruct ...`): rank 0 prints and writes every output.

The commands parse their arguments, call what writes each command's folder (:mod:`open3d_pnerf.runs`,
over the pipeline, which runs every stage and handles the ranks) and print.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

from .comparison import scores_table
from .config import ReconstructionConfig
from .config import overrides as config_overrides
from .data import FORMATS, load_sample, load_sequence
from .data.devices import camera_frames
from .data.posed_folder import POSE_CONVENTIONS
from .distributed import BACKENDS
from .errors import DatasetError, InputError, PNeRFError, TrainingInterrupted
from .fields import FIELD_CONFIGS
from .losses import LOSSES
from .reconstruction import Reconstruction
from .runs import (RUN_CONFIG, evaluate_folder, extend_folder, map_stream, occupancy_folder, read_run_config,
                   reconstruct_folder, render_files, track_folder, tsdf_folder)

EXIT_OK, EXIT_ERROR, EXIT_INTERRUPTED = 0, 2, 130


def _frames(spec: str | None):
    """'a:b:s' (python slice) or 'i,j,k' -> slice or list; None -> None."""
    if not spec:
        return None
    try:
        if ":" in spec:
            return slice(*[int(p) if p else None for p in spec.split(":")])
        return [int(p) for p in spec.split(",")]
    except ValueError:
        raise InputError(f"--frames {spec!r}: expected 'start:stop:step' or 'i,j,k'") from None


def _load(args):
    given = {"depth_scale": getattr(args, "depth_scale", None), "pose_convention": getattr(args, "pose_convention", None)}
    options = {key: value for key, value in given.items() if value is not None}
    seq = load_sample() if args.data == "sample" else load_sequence(args.data, depth_trunc=args.depth_trunc, **options)
    frames = _frames(getattr(args, "frames", None))
    if frames is not None:
        seq = seq.select(np.arange(len(seq))[frames])
    return seq


def _config(args):
    return ReconstructionConfig.preset(args.preset, **_overrides(args))


def _overrides(args) -> dict:
    """The config fields the training options set (only those given), with progress."""
    overrides = {k: v for k, v in {
        "loss": args.loss, "field": args.field, "device": args.device, "max_steps": args.max_steps,
        "time_budget_s": args.time_budget, "holdout_every": args.holdout_every, "seed": args.seed,
        "image_scale": args.image_scale, "optimizer.rays_per_batch": args.rays_per_batch,
        "runtime.dist_backend": args.dist_backend, "runtime.dist_timeout_s": args.dist_timeout,
        "refine_poses": args.refine_poses or None,
    }.items() if v is not None}
    overrides.update(config_overrides(args.set or []))
    overrides["progress"] = not args.quiet
    return overrides


def _gt_poses(seq, args):
    """The sequence's ground-truth poses when --gt-poses asks for them (InputError if it lacks
    some), else None (the pipeline's: SfM poses of an image-only sequence, or tracking)."""
    if not (args.gt_poses and seq.has_depth):
        return None
    if seq.gt_poses is None or not seq.gt_valid.all():
        lacking = "has no ground-truth poses" if seq.gt_poses is None else (
            f"has no ground-truth pose for frames {np.flatnonzero(~seq.gt_valid)[:10].tolist()}; select the "
            "covered frames with --frames")
        raise InputError(f"--gt-poses: {args.data} {lacking}")
    return seq.gt_poses


RUN_OPTIONS = ("data", "frames", "gt_poses", "depth_trunc", "depth_scale", "pose_convention")  # run_config.json's input


def _inputs(args) -> dict:
    """The input options that run_config.json records (for --resume and evaluate)."""
    options = {key: getattr(args, key, None) for key in RUN_OPTIONS}
    return {**options, "data": args.data if args.data == "sample" else str(Path(args.data).resolve())}


# -- commands ---------------------------------------------------------------------------------
def cmd_demo(args) -> int:
    args.data, args.gt_poses = "sample", False
    report = reconstruct_folder(load_sample(), _config(args), args.out, inputs=_inputs(args))
    if report is not None:  # rank 0 (of a torchrun launch) reports
        print((Path(args.out) / "report.md").read_text())
        print(f"wrote {args.out}/mesh.ply, point_cloud.ply, tsdf_mesh.ply, report.md")
    return EXIT_OK


def cmd_reconstruct(args) -> int:
    out = Path(args.resume or args.out)
    if args.resume:
        saved = read_run_config(out, "--resume")
        config = ReconstructionConfig.from_dict(saved["config"])
        if args.finish:  # no step left to train: export what the checkpoint has
            config = config.replace(max_steps=1)
        for key in RUN_OPTIONS:
            setattr(args, key, saved.get(key))
    else:
        config = _config(args)
    seq = _load(args)
    report = reconstruct_folder(seq, config, out, _gt_poses(seq, args), resume=bool(args.resume),
                                inputs=_inputs(args))
    if report is not None and not args.quiet:
        print((out / "report.md").read_text())
    return EXIT_OK


def cmd_extend(args) -> int:
    seq = _load(args)
    extend_folder(args.dir, seq, args.out, _overrides(args), _gt_poses(seq, args), inputs=_inputs(args))
    if not args.quiet:
        print((Path(args.out) / "report.md").read_text())
    return EXIT_OK


def cmd_map(args) -> int:
    config = _config(args)
    if args.camera:
        given = None
        if args.intrinsic:
            if not Path(args.intrinsic).is_file():
                raise InputError(f"--intrinsic {args.intrinsic}: no such file")
            given = o3d.io.read_pinhole_camera_intrinsic(args.intrinsic)
        intrinsic, frames = camera_frames(args.camera, given)
        total = None
    else:
        if not args.data:
            raise InputError("map needs DATA (a recorded folder or 'sample') or --camera")
        seq = _load(args)
        intrinsic, total = seq.intrinsic, len(seq)
        frames = ((seq.to_open3d(i), seq.timestamps[i]) for i in range(len(seq)))
    summary = map_stream(frames, intrinsic, config, args.out, args.finish, total, args.score_every, not args.quiet)
    if not args.quiet:
        print(f"mapped {summary['frames']} frames ({summary['keyframes']} keyframes) at "
              f"{summary['frames_per_s']} frames/s; wrote {args.out} (resume with Mapper.resume)")
    return EXIT_OK


def cmd_track(args) -> int:
    print(track_folder(_load(args), args.out, progress=not args.quiet))
    return EXIT_OK


def cmd_tsdf(args) -> int:
    seq = _load(args)
    tsdf_folder(seq, args.out, _gt_poses(seq, args), args.voxel_size, progress=not args.quiet)
    print(f"wrote {args.out}/mesh.ply and point_cloud.ply")
    return EXIT_OK


def cmd_render(args) -> int:
    recon = Reconstruction.load(args.dir)
    index = None
    if args.pose.isdigit():
        index = int(args.pose)
        if not 0 <= index < len(recon.poses):
            raise InputError(f"--pose {index}: the reconstruction has frames 0..{len(recon.poses) - 1}")
        pose = recon.poses[index]
    else:
        path = Path(args.pose)
        if not path.is_file():
            raise InputError(f"--pose {args.pose}: neither a frame index nor a 4x4 matrix text file")
        pose = np.loadtxt(path)
    written = render_files(recon, pose, args.out, frame=index)  # a frame's pose: with that frame's exposure
    print(f"wrote {', '.join(map(str, written))} (depth and sigma 16-bit, millimetres)")
    return EXIT_OK


def cmd_evaluate(args) -> int:
    folder = Path(args.dir)
    recon = Reconstruction.load(folder)
    if not len(recon.holdout_indices):
        raise InputError(f"{folder}: the reconstruction has no held-out frames to score (reconstruct with --holdout-every)")
    config_path = folder / RUN_CONFIG
    saved = read_run_config(folder, "evaluate") if config_path.is_file() else {}
    recorded = args.data is None
    if recorded and recon.frames is not None:  # the frames it was built from, as it was built from them
        seq = recon.frames
    else:
        if recorded:
            if "data" not in saved:
                raise InputError(f"{folder}: neither a run_config.json naming its data nor its frames (saved from "
                                 "Python with frames=False?); pass --data DATA")
            args.data = saved["data"]
        args.frames, args.depth_trunc = saved.get("frames"), saved.get("depth_trunc") or 0.0
        args.depth_scale, args.pose_convention = saved.get("depth_scale"), saved.get("pose_convention")
        try:
            seq = _load(args)
        except DatasetError as exc:
            if not recorded:
                raise
            raise DatasetError(f"{exc} (recorded in {config_path}; pass --data DATA if it moved)") from None
    result = evaluate_folder(folder, recon, seq, args.out, args.tsdf, progress=not args.quiet)
    print(f"Held-out frames {result['holdout_frames']} of {result['sequence']}:\n")
    print("\n".join(scores_table(result["scores"])))
    print(f"\nwrote {args.out or folder / 'evaluation.json'}")
    return EXIT_OK


def cmd_occupancy(args) -> int:
    if not args.voxel > 0:
        raise InputError(f"--voxel {args.voxel}: a voxel size must be a positive number of metres")
    bounds = None if args.bounds is None else np.reshape(args.bounds, (2, 3))
    summary = occupancy_folder(Reconstruction.load(args.dir), args.out or args.dir, args.voxel, bounds)
    print(f"{summary['shape']} voxels of {args.voxel} m: {summary['occupied']} occupied, {summary['free']} free, "
          f"{summary['unknown']} unknown ({summary['seconds']} s); wrote occupancy.npz, .ot, .bt and esdf.npz "
          f"into {args.out or args.dir}")
    return EXIT_OK


def cmd_formats(args) -> int:
    print("DATA may be a folder (or a recording file) in any of these layouts, tried in this order:\n")
    for fmt in FORMATS:
        print(f"  {fmt.name}: {fmt.layout}")
    print("\nload_sequence(path) in Python reads the same; open3d_pnerf.data.register_format adds your own.")
    return EXIT_OK


def _add_training_options(p, preset: bool = True):
    defaults = ReconstructionConfig()
    if preset:
        p.add_argument("--preset", default="fast", choices=list(ReconstructionConfig.PRESETS),
                       help="configuration preset")
    p.add_argument("--loss", choices=LOSSES, help=f"training loss (default {defaults.loss})")
    p.add_argument("--field", choices=list(FIELD_CONFIGS), help=f"scene field (default {defaults.field})")
    p.add_argument("--device", help="torch device: cpu, cuda, cuda:1 (default cpu)")
    p.add_argument("--max-steps", type=int, help="optimiser steps")
    p.add_argument("--time-budget", type=float, help="training time budget in seconds")
    p.add_argument("--holdout-every", type=int, help="hold out every k-th frame for evaluation")
    p.add_argument("--image-scale", type=float, help="training image scale in (0, 1]")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--rays-per-batch", type=int,
                   help="rays per step (under torchrun: the whole batch, split between the ranks)")
    p.add_argument("--refine-poses", action="store_true",
                   help="optimise the training poses with the field, held by their covariances (best with --field grid)")
    p.add_argument("--dist-backend", choices=BACKENDS,
                   help="under torchrun: torch.distributed backend (default auto: nccl on CUDA, gloo on CPU)")
    p.add_argument("--dist-timeout", type=float, metavar="SECONDS",
                   help="under torchrun: how long a rank waits for the others before failing (default 600)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="any config field by its dotted name, e.g. --set sampling.n_coarse=32 --set "
                   "objective.weights.depth_pdf=0.2 (repeatable; VALUE read as JSON)")


def _add_data_options(p, data=True, gt_poses=True):
    if data:
        p.add_argument("data", help="a dataset folder or recording (open3d-pnerf formats lists them) or 'sample'")
    p.add_argument("--frames", help="frames to use: 'start:stop:step' or 'i,j,k'")
    p.add_argument("--depth-trunc", type=float, default=0.0, help="drop depth beyond this (m)")
    p.add_argument("--depth-scale", type=float, help="raw depth units per metre, where the data's own is wrong")
    p.add_argument("--pose-convention", choices=POSE_CONVENTIONS,
                   help="a posed folder's poses: OpenCV or OpenGL camera axes, camera-to-world (default) or inverse")
    if gt_poses:
        p.add_argument("--gt-poses", action="store_true", help="use the dataset's ground-truth poses, skip tracking")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="open3d-pnerf", description="Probabilistic NeRF mapping from RGB-D (Open3D).")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="reconstruct the bundled TUM sample and compare with TSDF (the README's main command)")
    p.add_argument("--out", default="out/demo", help="output folder")
    _add_training_options(p)
    p.set_defaults(func=cmd_demo, holdout_every=4)

    p = sub.add_parser("reconstruct", help="track, train the probabilistic NeRF, export mesh/point cloud/report")
    p.add_argument("data", nargs="?", help="a dataset folder or recording (open3d-pnerf formats lists them) or 'sample'")
    p.add_argument("--out", default="out/reconstruction", help="output folder")
    p.add_argument("--resume", metavar="DIR", help="continue an interrupted run in DIR from its last checkpoint")
    p.add_argument("--finish", action="store_true",
                   help="with --resume: stop training and export what the checkpoint has (no further steps)")
    _add_data_options(p, data=False)
    _add_training_options(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("extend", help="add frames to a saved reconstruction (tracked onto its map) and train further",
                       description="Track the frames of DATA onto the map saved in DIR (or take --gt-poses in the "
                       "map's world frame), build the depth targets of all frames, train the map's field further on "
                       "old and new frames (by default for 30%% of the map's own training budget), then export and "
                       "compare with TSDF fusion into --out. DIR is left unchanged; an extended folder extends again.")
    p.add_argument("dir", help="a saved reconstruction (reconstruct, demo or extend output folder)")
    _add_data_options(p)
    p.add_argument("--out", required=True, help="output folder of the extended reconstruction")
    _add_training_options(p, preset=False)
    p.set_defaults(func=cmd_extend)

    p = sub.add_parser("map", help="map a recorded folder frame by frame as if live (or a live camera)",
                       description="Feed the frames of DATA in order through the streaming Mapper: each frame "
                       "tracked as it comes, keyframes trained between frames (mapping.train_s_per_frame), then "
                       "--finish seconds of training on every keyframe; writes the map to --out (a saved "
                       "reconstruction that Mapper.resume and extend go on from) and map_report.json. With --camera, "
                       "frames come from a RealSense or Azure Kinect camera through Open3D until Ctrl-C.")
    p.add_argument("data", nargs="?", help="a dataset folder or recording, or 'sample' (or use --camera)")
    p.add_argument("--camera", choices=("realsense", "azure-kinect"), help="map a live camera instead of DATA")
    p.add_argument("--intrinsic", metavar="JSON", help="with --camera: the camera's Open3D PinholeCameraIntrinsic JSON "
                   "(needed for azure-kinect; a RealSense reports its own)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--finish", type=float, metavar="SECONDS",
                   help="training seconds on every keyframe at the end (default mapping.finish_s, 60)")
    p.add_argument("--score-every", type=int, default=5, metavar="KEYFRAMES",
                   help="show the map's held-out PSNR every this many keyframes (default 5)")
    _add_data_options(p, data=False, gt_poses=False)
    _add_training_options(p)
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("track", help="RGB-D odometry + pose graph: trajectory (TUM, .log, Open3D JSON) and covariances")
    _add_data_options(p)
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=cmd_track)

    p = sub.add_parser("tsdf", help="Open3D TSDF fusion baseline: mesh.ply and point_cloud.ply")
    _add_data_options(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--voxel-size", type=float, default=0.01, help="voxel size (m)")
    p.set_defaults(func=cmd_tsdf)

    p = sub.add_parser("render", help="render colour, depth and depth-sigma from a saved reconstruction")
    p.add_argument("dir", help="a reconstruct output folder")
    p.add_argument("--pose", required=True, help="frame index, or a text file with a 4x4 camera-to-world matrix")
    p.add_argument("--out", required=True, help="output PNG (depth and sigma written beside it)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("evaluate", help="score a saved reconstruction on its held-out frames (optionally against TSDF)",
                       description="Render a saved reconstruction at its held-out frames and compare with their colour "
                       "and sensor depth (PSNR, SSIM, depth L1, depth calibration); with --tsdf also an Open3D TSDF "
                       "fused from the same training frames and poses. Prints a table and writes JSON.")
    p.add_argument("dir", help="a reconstruct (or demo, or Reconstruction.save) output folder")
    p.add_argument("--data", help="dataset folder or 'sample' (default: the one recorded in DIR/run_config.json, "
                   "else the frames saved in DIR)")
    p.add_argument("--out", help="output JSON (default DIR/evaluation.json)")
    p.add_argument("--tsdf", action=argparse.BooleanOptionalAction, default=True,
                   help="also score the TSDF baseline (default: yes)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("occupancy", help="a saved reconstruction's occupancy grid: OctoMap .ot/.bt, .npz, distance",
                       description="The probability that each voxel is occupied, from the training views' rendered "
                       "depth and its calibrated law (Reconstruction.occupancy_grid): occupancy.ot (OctoMap, with the "
                       "probabilities), occupancy.bt (OctoMap, free or occupied), occupancy.npz (OccupancyGrid.load) "
                       "and esdf.npz (the signed distance to occupied space, with its bounds).")
    p.add_argument("dir", help="a saved reconstruction (reconstruct, demo or map output folder)")
    p.add_argument("--voxel", type=float, default=0.05, help="voxel size (m, default 0.05)")
    p.add_argument("--bounds", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="min and max corner (m; default the reconstruction's scene box)")
    p.add_argument("--out", help="output folder (default DIR)")
    p.set_defaults(func=cmd_occupancy)

    p = sub.add_parser("formats", help="the input layouts DATA may have (what load_sequence detects)")
    p.set_defaults(func=cmd_formats)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "reconstruct" and not (args.data or args.resume):
        parser.error("reconstruct needs DATA or --resume DIR")
    if args.command == "reconstruct" and args.finish and not args.resume:
        parser.error("--finish goes with --resume DIR")
    try:
        return args.func(args)
    except PNeRFError as exc:
        print(f"open3d-pnerf: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except TrainingInterrupted as exc:
        out = Path(args.resume or args.out) if args.command in ("reconstruct", "demo") else None
        print(f"open3d-pnerf: interrupted after training step {exc.step}; the checkpoint is {exc.checkpoint}. "
              f"Continue with `open3d-pnerf reconstruct --resume {out}`; add --finish to stop training and export "
              "what it has", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("open3d-pnerf: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
