"""Issue-4 benchmark suite: the paper's experiments against Open3D TSDF fusion.

Datasets (RGB-D ones: every 4th frame held out: 0, 4, 8, ...; training at 320x240):
  synthetic   the room of open3d_pnerf.synthetic, 48 frames rendered at 640x480 with the
              Kinect-like noise model; exact GT mesh (geometry metrics against the surface
              seen by the sequence's cameras)
  tum         TUM fr1/xyz, the 32 shared frames (../shared/data)
  7scenes     7-Scenes redkitchen frames 150-199 (../shared/data)
  fern        LLFF fern (../shared/data), images only, the paper's protocol: every 8th image
              held out (0, 8, 16), 10 training views, 504x378, COLMAP poses and sparse points
              as depth targets; no TSDF (no depth images); not in the default set, run
              on its own with a longer budget (below)
Experiments per dataset (ground-truth poses unless said, SfM poses for fern; `--views`
training views when sparse, default 10, evenly spaced over the non-held-out frames):
  ablation    photometric / + depth PDF (Kd) / + depth PDF + depth (Kd, Kz) at sparse views
  losses      pnerf vs dsnerf vs photometric at sparse views (shares the ablation runs)
  views       pnerf and TSDF with 5, 10, 20 and all training frames (RGB-D datasets)
  poses       pnerf at sparse views with poses from our tracking instead of GT (RGB-D)
Every run reports held-out PSNR/SSIM, depth L1, depth calibration, mesh accuracy/
completeness/F-score (synthetic), wall time, peak RSS and training samples/s; the TSDF
baseline is fused from the same training frames and poses. Each run is a fresh process
(so peak RSS is per run); `--jobs` of them run at once (default: one per core, one torch
thread each). Before the runs, the synthetic sequence and its reference surface are rendered
once to benchmarks/results/cache/ (gitignored) and each dataset is tracked once there; the
suite's wall time includes that.

    python benchmarks/bench_suite.py [--budget 50] [--jobs 2] [--datasets synthetic,tum,7scenes] [--quick]
    python benchmarks/bench_suite.py --datasets fern --budget 600 --name fern [--seed 1]   # the Fern experiment

Writes benchmarks/results/<name>.json, <name>.md and <name>_*.png (name: suite; --quick:
tiny synthetic runs, results/suite_quick.*, a smoke test of the script in ~2 minutes).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import platform
import resource
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
PATHS = {"tum": SHARED / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz",
         "7scenes": SHARED / "7scenes_redkitchen" / "frames_150-199",
         "fern": SHARED / "llff_fern" / "nerf_llff_data" / "fern"}
IMAGE_ONLY = {"fern"}  # datasets without depth images: SfM poses, no TSDF, no tracking
OUT = Path(__file__).resolve().parent / "results"
HOLDOUT_EVERY = {"fern": 8}  # the LLFF protocol; 4 for the others
IMAGE_SCALE = {"fern": 1.0}  # 504x378 (images_8, nerf-pytorch's fern setting); 0.5 (320x240) for the others
VARIANTS = {  # name -> config overrides
    "photometric": dict(loss="photometric"),
    "+density": {"loss": "pnerf", "objective.weights.depth": 0.0},
    "pnerf": dict(loss="pnerf"),
    "dsnerf": dict(loss="dsnerf"),
}


def run_in_processes(run_one, specs: list[dict], jobs: int, summary) -> list[dict]:
    """run_one(spec) for every spec, each in a fresh process (so peak RSS is per run), `jobs` at
    once; prints summary(result) as each ends; returns the results in the order of `specs`."""
    with ProcessPoolExecutor(jobs, multiprocessing.get_context("spawn"), max_tasks_per_child=1) as pool:
        futures = [pool.submit(run_one, spec) for spec in specs]
        for future in as_completed(futures):
            print(summary(future.result()), flush=True)
    return [f.result() for f in futures]


def write_result(name: str, report: dict, text: str) -> None:
    """Write results/<name>.json (the report) and results/<name>.md (`text`), and print the text."""
    OUT.mkdir(exist_ok=True)
    (OUT / f"{name}.json").write_text(json.dumps(report, indent=1) + "\n")
    (OUT / f"{name}.md").write_text(text)
    print(text)


def machine() -> str:
    """This machine and torch, for a result file's meta."""
    import torch

    return (f"{platform.machine()} {platform.processor() or ''} {multiprocessing.cpu_count()} cores, "
            f"torch {torch.__version__}").replace("  ", " ")


def load(dataset: str, cache: Path):
    """(sequence, reference surface or None) for a dataset name; the synthetic one from its
    folder in the cache (see prepare_synthetic)."""
    import open3d as o3d

    import open3d_pnerf as pn

    if dataset.startswith("synthetic"):
        folder = cache / dataset
        return pn.load_sequence(folder), o3d.io.read_point_cloud(str(folder / "reference.ply"))
    return pn.load_sequence(PATHS[dataset]), None


def prepare_synthetic(cache: Path, quick: bool) -> str:
    """Render the synthetic sequence and its exact visible surface (reference.ply, points) once, to a Redwood folder
    in the cache (PNG colour, depth in mm), so that runs read frames instead of re-rendering
    them, with the room's whole exact mesh (surface.ply). The folder name carries a hash of synthetic.py:
    a changed generator renders anew.
    Returns the dataset name (the folder's name)."""
    import open3d as o3d

    from open3d_pnerf import synthetic
    from open3d_pnerf.data import write_sequence

    digest = hashlib.sha1(Path(synthetic.__file__).read_bytes()).hexdigest()[:8]
    name = f"synthetic_{'quick' if quick else 'full'}_{digest}"
    folder = cache / name
    if not (folder / "reference.ply").is_file():  # written last: marks a complete folder
        data = synthetic.synthetic_sequence(16 if quick else 48, 320 if quick else 640, 240 if quick else 480, seed=0)
        write_sequence(data.sequence, folder)
        o3d.io.write_point_cloud(str(folder / "reference.ply"), data.reference_points(stride=2))
    if not (folder / "surface.ply").is_file():  # the whole exact surface, for exact depth errors
        o3d.io.write_triangle_mesh(str(folder / "surface.ply"), synthetic.room_scene(seed=0).mesh)
    return name


def poses_for(dataset: str, seq, kind: str, cache: Path):
    """(poses, covariances): exact/GT ones, or tracked (cached per dataset) and expressed in
    the GT world frame by the ATE alignment (so geometry metrics use the GT mesh's frame);
    (None, None) for an image-only sequence (reconstruct() takes its SfM poses)."""
    if not seq.has_depth:
        return None, None
    if kind == "gt":
        return seq.gt_poses, np.zeros((len(seq), 6, 6))
    file = cache / f"tracked_{dataset}.npz"
    if not file.is_file():
        import open3d_pnerf as pn

        traj = pn.track(seq, progress=False)
        ate = pn.absolute_trajectory_error(traj.poses, seq.gt_poses)
        np.savez(file, poses=ate["alignment"] @ traj.poses, covariances=traj.covariances, ate=ate["rmse"])
    z = np.load(file)
    return z["poses"], z["covariances"]


def run_one(spec: dict) -> dict:
    """Train one configuration, compare with TSDF; runs in a fresh process."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf import compare_with_tsdf

    seq, reference = load(spec["source"], Path(spec["cache"]))
    poses, covs = poses_for(spec["source"], seq, spec["poses"], Path(spec["cache"]))
    d = spec["dataset"]
    cfg = pn.ReconstructionConfig.preset(
        "test" if spec["quick"] else "fast", time_budget_s=spec["budget"], max_steps=10**6,
        holdout_every=HOLDOUT_EVERY.get(d, 4), image_scale=IMAGE_SCALE.get(d, 0.5), train_views=spec["views"],
        seed=spec["seed"], progress=False, **VARIANTS[spec["variant"]])
    t0 = time.perf_counter()
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    wall = time.perf_counter() - t0
    comparison = compare_with_tsdf(seq, reconstruction=recon, reference=reference, progress=False)
    compare_s = time.perf_counter() - t0 - wall
    if spec.get("figure"):
        comparison.figures[0].savefig(spec["figure"], dpi=60)
    tr = recon.stats["training"]
    return {**{k: spec[k] for k in ("dataset", "variant", "views", "poses")},
            "train_frames": len(recon.train_indices), "model": comparison.table["model"],
            "mesh": comparison.table.get("mesh", {}),
            "tsdf": comparison.table.get("tsdf", {}), "wall_s": round(wall, 1), "compare_s": round(compare_s, 1),
            "timings": recon.stats["timings"], "targets": recon.stats["targets"], "steps": tr["steps"],
            "samples_per_s": round(tr["samples_per_s"]), "peak_rss_mb": round(_peak_rss_mb())}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def plan(datasets, views: int, quick: bool) -> list[dict]:
    """The runs: (dataset, variant, training views (0 = all), poses)."""
    sweep = (3, 0) if quick else (5, 10, 20, 0)
    runs = []
    for d in datasets:
        given = "sfm" if d in IMAGE_ONLY else "gt"
        runs += [dict(dataset=d, variant=v, views=views, poses=given) for v in VARIANTS]
        if d in IMAGE_ONLY:
            continue
        runs += [dict(dataset=d, variant="pnerf", views=n, poses="gt") for n in sweep if n != views]
        runs.append(dict(dataset=d, variant="pnerf", views=views, poses="tracked"))
    return runs


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"Budget {meta['budget_s']:.0f} s of training per run, {meta['threads']} thread(s), {meta['jobs']} run(s) "
             f"at once; the suite took {meta['wall_minutes']} min; {meta['machine']}.",
             "Held out: every 4th frame (fern: every 8th). Views: training frames (all = every non-held-out "
             "frame). '-': not measured (fern has no depth images, so no depth metrics and no TSDF).", ""]
    head = ("| dataset | run | views | poses | PSNR (dB) | SSIM | depth L1 (mm) | within 1σ | "
            "mesh acc. (mm) | mesh compl. (mm) | mesh F@20mm | mesh F@50mm | TSDF PSNR (all / hits) | TSDF depth L1 (mm) | "
            "TSDF compl. (mm) | TSDF F@20mm | steps | samples/s | peak RSS (MB) |")
    lines += [head, "|" + " --- |" * (head.count("|") - 1)]
    for r in results:
        m, t, e = r["model"], r["tsdf"], r["mesh"]
        g = lambda d, k, f=".3f": format(d[k], f) if k in d else "-"  # noqa: E731
        mm = lambda d, k: f"{1000 * d[k]:.1f}" if k in d else "-"  # noqa: E731
        tsdf_psnr = f"{t['psnr']:.2f} / {t['psnr_hits']:.2f}" if t else "-"
        lines.append(
            f"| {r['dataset']} | {r['variant']} | {r['views'] or 'all'} ({r['train_frames']}) | {r['poses']} | "
            f"{m['psnr']:.2f} | {m['ssim']:.3f} | {mm(m, 'depth_l1')} | {g(m, 'within_1', '.2f')} | "
            f"{mm(e, 'accuracy')} | {mm(e, 'completeness')} | {g(e, 'fscore_20mm')} | {g(e, 'fscore_50mm')} | "
            f"{tsdf_psnr} | {mm(t, 'depth_l1')} | {mm(t, 'completeness')} | "
            f"{g(t, 'fscore_20mm')} | {r['steps']} | {r['samples_per_s'] / 1000:.0f}k | {r['peak_rss_mb']} |")
    return "\n".join(lines) + "\n"


def sweep_figure(results: list[dict], path: Path) -> None:
    """Held-out PSNR (and F-score where known) against the number of training views."""
    from matplotlib.figure import Figure

    datasets = sorted({r["dataset"] for r in results if r["tsdf"]})  # the RGB-D ones have a view sweep
    if not datasets:
        return
    fig = Figure(figsize=(4 * len(datasets), 3.2), layout="constrained")
    axes = fig.subplots(1, len(datasets), squeeze=False)[0]
    for ax, d in zip(axes, datasets):
        rows = sorted((r for r in results if r["dataset"] == d and r["variant"] == "pnerf" and r["poses"] == "gt"),
                      key=lambda r: r["train_frames"])
        n = [r["train_frames"] for r in rows]
        ax.plot(n, [r["model"]["psnr"] for r in rows], "o-", label="pnerf PSNR")
        ax.plot(n, [r["tsdf"]["psnr"] for r in rows], "s--", label="TSDF PSNR")
        ax.set_xlabel("training views")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.set_title(d)
        if "fscore_20mm" in rows[0]["mesh"]:
            f = ax.twinx()
            f.plot(n, [r["mesh"]["fscore_20mm"] for r in rows], "o:", color="C2", label="pnerf mesh F@20mm")
            f.plot(n, [r["tsdf"]["fscore_20mm"] for r in rows], "s:", color="C3", label="TSDF F@20mm")
            f.set_ylabel("F-score @ 20 mm")
            f.legend(loc="lower right", fontsize=7)
        ax.legend(loc="upper left", fontsize=7)
    fig.savefig(path, dpi=70)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=float, default=50.0, help="training seconds per run")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--datasets", default="synthetic,tum,7scenes", help="comma-separated; also: fern")
    ap.add_argument("--name", default="suite", help="stem of the result files in benchmarks/results/")
    ap.add_argument("--seed", type=int, default=0, help="seed of every run (rays, samples, initialisation)")
    ap.add_argument("--views", type=int, default=10, help="training views of the sparse-view runs")
    ap.add_argument("--quick", action="store_true", help="tiny synthetic runs: a smoke test of the script")
    args = ap.parse_args()
    datasets = ["synthetic"] if args.quick else args.datasets.split(",")
    missing = [d for d in datasets if d != "synthetic" and not PATHS.get(d, SHARED / "?").is_dir()]
    if missing:
        raise SystemExit(f"shared data not found for {missing} (expected under {SHARED}); use --datasets synthetic")
    budget = 10.0 if args.quick else args.budget
    views = 5 if args.quick else args.views
    stem = "suite_quick" if args.quick else args.name
    cache = OUT / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sources = {d: prepare_synthetic(cache, args.quick) if d == "synthetic" else d for d in datasets}
    for d, source in sources.items():  # track each RGB-D dataset once, before the runs that share it
        if d not in IMAGE_ONLY:
            poses_for(source, load(source, cache)[0], "tracked", cache)
    specs = plan(datasets, views, args.quick)
    for spec in specs:
        spec.update(threads=args.threads, budget=budget, quick=args.quick, cache=str(cache), seed=args.seed,
                    source=sources[spec["dataset"]])
        if spec["variant"] == "pnerf" and spec["views"] == views and spec["poses"] in ("gt", "sfm"):
            spec["figure"] = str(OUT / f"{stem}_{spec['dataset']}_frame.png")
    results = run_in_processes(run_one, specs, args.jobs, summary_line)
    tracked = {d: float(np.load(cache / f"tracked_{s}.npz")["ate"]) for d, s in sources.items() if d not in IMAGE_ONLY}
    meta = {"machine": machine(),
            "budget_s": budget, "threads": args.threads, "jobs": args.jobs, "seed": args.seed,
            "wall_minutes": round((time.perf_counter() - t0) / 60, 1),
            "holdout_every": {d: HOLDOUT_EVERY.get(d, 4) for d in datasets}, "views": views,
            "tracked_ate_rmse_mm": {d: round(1000 * a, 2) for d, a in tracked.items()}}
    (OUT / f"{stem}.json").write_text(json.dumps({"meta": meta, "runs": results}, indent=1))
    (OUT / f"{stem}.md").write_text(markdown(results, meta))
    sweep_figure(results, OUT / f"{stem}_views.png")
    print((OUT / f"{stem}.md").read_text())


def summary_line(r: dict) -> str:
    m, t = r["model"], r["tsdf"]
    line = (f"{r['dataset']:9s} {r['variant']:11s} views {r['views'] or 'all':>3} {r['poses']:7s} "
            f"PSNR {m['psnr']:.2f} SSIM {m['ssim']:.3f}")
    if t:
        line += (f" (TSDF {t['psnr']:.2f}) depth L1 {1000 * m['depth_l1']:.1f} mm within1 {m['within_1']:.2f} "
                 f"F@20 {r['mesh'].get('fscore_20mm', float('nan')):.3f} (TSDF {t.get('fscore_20mm', float('nan')):.3f})")
    return line + f" {r['wall_s']:.0f} s {r['peak_rss_mb']} MB"


if __name__ == "__main__":
    main()
