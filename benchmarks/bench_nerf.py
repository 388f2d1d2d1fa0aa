"""Issue-3 benchmark: the probabilistic NeRF on the shared TUM fr1/xyz frames.

Every 4th frame held out (frames 0, 4, 8, ...), poses from our tracking, `fast` preset
(time budget per run), images at half resolution (320x240). Compares, at equal time:
pnerf vs photometric (each with --seeds seeds: a 150 s run moves by ~0.5 dB between
seeds) vs dsnerf losses, depth-guided vs plain stratified+importance sampling, depth targets
with and without the sensor's systematic error (depth_sigma_relative), photometric with
PyTorch's default Adam beta2 of 0.999 (the default is 0.99, chosen for the pnerf loss), and the
Open3D TSDF baseline fused from the same training frames and poses. Also measures
training throughput of the hashgrid, grid and vanilla fields.

    python benchmarks/bench_nerf.py [--budget 150] [--seeds 3] [--quick]
    python benchmarks/bench_nerf.py --steps 1000 --losses-only --seeds 2 --name nerf_1000_steps

Writes benchmarks/results/<name>.json and <name>.md (name: nerf). --steps trains every run
for a fixed number of steps instead of a time budget: equal work rather than equal time,
which takes this machine's speed variations out of the comparison.
"""

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

import open3d_pnerf as pn
from open3d_pnerf.evaluation import heldout_scores, heldout_views, score_views
from open3d_pnerf.pipeline import run

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TUM = SHARED / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz"
OUT = Path(__file__).resolve().parent / "results"


def throughput(field: str, seq, poses, seconds: float = 20.0) -> float:
    """Training samples/s of a field on the sequence (short run, same sampling, no export)."""
    cfg = pn.ReconstructionConfig.preset("fast", field=field, time_budget_s=seconds, max_steps=10**6,
                                         holdout_every=4, progress=False)
    return run(seq, cfg, poses, export=False).stats["training"]["samples_per_s"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=float, default=150.0, help="training seconds per run")
    ap.add_argument("--seeds", type=int, default=3, help="seeds 0..n-1 of the pnerf and photometric runs")
    ap.add_argument("--quick", action="store_true", help="30 s runs (a smoke test of the script)")
    ap.add_argument("--steps", type=int, help="train each run for this many steps, without a time budget")
    ap.add_argument("--losses-only", action="store_true",
                    help="only the pnerf and photometric runs and the TSDF (no variants, no throughput)")
    ap.add_argument("--name", default="nerf", help="stem of the result files in benchmarks/results/")
    args = ap.parse_args()
    if not TUM.is_dir():
        sys.exit(f"shared data not found: {TUM}")
    budget = 30.0 if args.quick else args.budget
    limits = dict(time_budget_s=budget, max_steps=10**6)  # equal time
    if args.steps:  # equal work
        limits = dict(time_budget_s=None, max_steps=args.steps)
    seq = pn.load_sequence(TUM)
    t0 = time.perf_counter()
    traj = pn.track(seq, progress=False)
    tracking_s = time.perf_counter() - t0
    ate = pn.absolute_trajectory_error(traj.poses, seq.gt_poses)["rmse"]
    print(f"tracking: {len(seq)} frames in {tracking_s:.1f} s, ATE {1000 * ate:.1f} mm", flush=True)

    runs = {f"{loss}_seed{seed}": dict(loss=loss, seed=seed)
            for seed in range(args.seeds) for loss in ("pnerf", "photometric")}
    if not args.losses_only:
        runs["dsnerf_seed0"] = dict(loss="dsnerf")
        runs["pnerf_no_guided_sampling_seed0"] = {"loss": "pnerf", "sampling.depth_guided": False}
        runs["pnerf_without_systematic_sigma_seed0"] = {"loss": "pnerf", "targets.depth_sigma_relative": 0.0}
        runs["photometric_adam_beta2_0.999_seed0"] = {"loss": "photometric", "optimizer.adam_beta2": 0.999}
    results = {}
    tsdf_scores = None
    for name, overrides in runs.items():
        cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, progress=False, **limits, **overrides)
        t = time.perf_counter()
        recon = pn.reconstruct(seq, cfg, poses=traj.poses, covariances=traj.covariances)
        wall = time.perf_counter() - t
        if tsdf_scores is None:
            train = seq.select(recon.train_indices).scaled_by(cfg.image_scale)
            tsdf = pn.tsdf_fusion(train, traj.poses[recon.train_indices], progress=False)
            tsdf_scores = score_views(heldout_views(recon, seq, {"tsdf": tsdf}), cfg.export.min_opacity)["tsdf"]
        scores = heldout_scores(recon, seq)["model"]
        results[name] = {"scores": scores, "training": recon.stats["training"], "wall_s": round(wall, 1),
                         "mesh_triangles": len(recon.mesh.triangles), "points": len(recon.point_cloud.points)}
        print(f"{name}: PSNR {scores['psnr']:.2f} dB, depth L1 {1000 * scores['depth_l1']:.1f} mm, "
              f"{recon.stats['training']['steps']} steps, wall {wall:.0f} s", flush=True)
    print(f"tsdf: PSNR {tsdf_scores['psnr']:.2f} (hits {tsdf_scores['psnr_hits']:.2f}), "
          f"depth L1 {1000 * tsdf_scores['depth_l1']:.1f} mm", flush=True)

    means = {loss: {k: float(np.mean([r["scores"][k] for n, r in results.items() if n.startswith(loss + "_seed")]))
                    for k in ("psnr", "ssim", "depth_l1")} for loss in ("pnerf", "photometric")}
    speeds = {} if args.losses_only else {
        f: throughput(f, seq, traj.poses, 15.0 if args.quick else 30.0) for f in ("hashgrid", "grid", "vanilla")}
    print("samples/s:", speeds, flush=True)
    report = {
        "machine": {"platform": platform.platform(), "cpus": torch.get_num_threads(), "torch": torch.__version__},
        "dataset": "TUM fr1/xyz, 32 associated frames, every 4th held out (8), 320x240",
        "budget_s": None if args.steps else budget, "steps_per_run": args.steps,
        "tracking": {"ate_rmse_mm": round(1000 * ate, 2), "seconds": round(tracking_s, 1)},
        "runs": results, "tsdf": tsdf_scores, "samples_per_s": speeds, "mean_over_seeds": means,
        "total_minutes": round((time.perf_counter() - t0) / 60, 1),
    }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    rows = ["| run | held-out PSNR (dB) | SSIM | depth L1 (mm) | within 1 sigma | steps |", "| --- | --- | --- | --- | --- | --- |"]
    for name, r in results.items():
        s = r["scores"]
        rows.append(f"| {name} | {s['psnr']:.2f} | {s['ssim']:.3f} | {1000 * s['depth_l1']:.1f} | "
                    f"{s['within_1']:.2f} | {r['training']['steps']} |")
    rows.append(f"| TSDF (all pixels / on its hits) | {tsdf_scores['psnr']:.2f} / {tsdf_scores['psnr_hits']:.2f} | "
                f"{tsdf_scores['ssim']:.3f} | {1000 * tsdf_scores['depth_l1']:.1f} (hits) | - | - |")
    for loss, m in means.items():
        rows.append(f"| {loss}, mean of {args.seeds} seeds | {m['psnr']:.2f} | {m['ssim']:.3f} | "
                    f"{1000 * m['depth_l1']:.1f} | - | - |")
    speed = " / ".join(f"{k} {v / 1000:.0f}k" for k, v in speeds.items()) or "not measured"
    limit = f"{args.steps} steps" if args.steps else f"{budget:.0f} s"
    md = OUT / f"{args.name}.md"
    md.write_text("\n".join(rows) + f"\n\nTraining samples/s: {speed}. Budget {limit} a run, "
                  f"{report['total_minutes']} min in all; {report['machine']}\n")
    print(md.read_text())


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
