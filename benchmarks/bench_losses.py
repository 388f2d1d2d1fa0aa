"""The paper's loss comparison, paired over seeds: pnerf vs DS-NeRF's loss vs colour only.

Every loss trains the same configuration (the `fast` preset, the library's defaults; Fern the
`forward_facing` preset) for the same number of steps from the same seeds; a run's held-out PSNR/SSIM (and depth L1 and sigma
coverage where the dataset has depth) is scored on full held-out images at the end. Equal
time: each run also scores a fixed set of 2,048 held-out pixels every 250 steps; the table's
"equal-time" column is that PSNR at the largest time every run of the dataset and seed
reached (linear between evaluations).

Datasets (common.py): fern (LLFF, 10 training views, every 8th image held out, COLMAP
poses and points, 504x378), synthetic (the room, 10 views at ground-truth poses, every 4th
frame held out, 320x240), tum (TUM fr1/xyz, 10 views at ground-truth poses, every 4th held
out, 320x240), 7scenes (redkitchen 150-199, the same); `--poses tracked` trains the RGB-D ones
at the tracker's poses and covariances instead, as reconstruct() trains on them (its colour
cameras where it places them; what refine_poses needs). Each run is a fresh process, `--jobs` at
once with `--threads` torch threads each.

    python benchmarks/bench_losses.py --datasets fern --steps 14000 --name losses_fern
    python benchmarks/bench_losses.py --datasets fern,tum --seconds 300 --jobs 1 --threads 2 --name losses_300s
    python benchmarks/bench_losses.py --datasets tum,7scenes --variants pnerf,photometric --seconds 300 \
        --name losses_rgbd_300s
    python benchmarks/bench_losses.py --datasets 7scenes --seeds 0 --seconds 300 \
        --variants pnerf_sensor_targets,pnerf_fast_decay,pnerf_light_depth,pnerf --name losses_7scenes_levers
        # the file ran at d516ff0, when every variant but the 4% one had 2% targets
    python benchmarks/bench_losses.py --datasets 7scenes --poses tracked --seconds 300 \
        --variants pnerf,photometric,pnerf_refine,photometric_refine --name losses_7scenes_refine
    python benchmarks/bench_losses.py --datasets tum --poses tracked --seconds 300 --seeds 0 \
        --variants pnerf,pnerf_light_depth --name losses_tum_tracked_levers  # ran at d78a31a: light depth at 2%
    python benchmarks/bench_losses.py --datasets tum --poses tracked --seconds 300 --seeds 0,1 --split tuning \
        --variants pnerf_sensor_targets,pnerf,pnerf_wider_targets --name tuning_sigma_relative_tum
    python benchmarks/bench_losses.py --datasets tum,7scenes --poses tracked --seconds 300 \
        --variants pnerf_sensor_targets,pnerf --name losses_wide_targets_tracked
    python benchmarks/bench_losses.py --datasets tum,7scenes --variants pnerf --seconds 300 \
        --name losses_rgbd_300s_pnerf
    python benchmarks/bench_losses.py --datasets tum --variants pnerf,photometric --seconds 300 \
        --name losses_tum_300s_paired
    python benchmarks/bench_losses.py --datasets synthetic,tum --steps 3000 --name losses_rgbd
    python benchmarks/bench_losses.py --datasets synthetic --variants pnerf,pnerf_fine_terms --seeds 0,1 \
        --steps 1500 --name tuning_coarse_terms      # a settings choice, on the tuning scene
    python benchmarks/bench_losses.py --datasets fern --variants pnerf,pnerf_coarse16,pnerf_coarse64,pnerf_box,\
pnerf_proposal,pnerf_c2f --seeds 0 --steps 3000 --split tuning --name tuning_fern  # Fern's settings, chosen
        # on the pool frames the 10 views leave out (the held-out frames stay unseen)
    python benchmarks/bench_losses.py --datasets fern --variants pnerf,pnerf_proposal128 --seeds 0 --steps 3000 \
        --split tuning --name tuning_fern_proposal128
    python benchmarks/bench_losses.py --datasets fern --variants pnerf,pnerf_grid --seeds 0 --steps 3000 \
        --split tuning --name tuning_fern_grid    # the field type for sparse forward-facing views

Result files written before the targets' default became 4% name its runs pnerf_wide_targets and
the 2% ones (today's pnerf_sensor_targets) pnerf. Writes benchmarks/results/<name>.json and <name>.md.
"""

from __future__ import annotations

import argparse
import multiprocessing
import time

import numpy as np
from common import (HOLDOUT_EVERY, IMAGE_SCALE, commit, load, machine, poses_for, require_shared, run_in_processes,
                    synthetic_room, write_result)

VARIANTS = {  # name -> config overrides
    "pnerf": dict(loss="pnerf"),
    "dsnerf": dict(loss="dsnerf"),
    "photometric": dict(loss="photometric"),
    "pnerf_fine_terms": {"loss": "pnerf", "objective.coarse_terms": False},  # the default, except on Fern
    "pnerf_uniform_batches": {"loss": "pnerf", "optimizer.target_ray_share": 0.0},
    # on Fern, settings measured against its preset (forward_facing: NDC, 32 coarse samples)
    "pnerf_box": {"loss": "pnerf", "ndc": "off"},
    "photometric_box": {"loss": "photometric", "ndc": "off"},
    "pnerf_coarse16": {"loss": "pnerf", "sampling.n_coarse": 16},
    "pnerf_coarse64": {"loss": "pnerf", "sampling.n_coarse": 64},
    "pnerf_c2f": {"loss": "pnerf", "optimizer.coarse_to_fine": 0.5},
    "pnerf_proposal": {"loss": "pnerf", "sampling.n_proposal": 64, "sampling.n_coarse": 16},
    "pnerf_proposal128": {"loss": "pnerf", "sampling.n_proposal": 128, "sampling.n_coarse": 16},
    "pnerf_grid": {"loss": "pnerf", "field": "grid"},  # the dense-grid field in place of the hash grid
    # at a user's budget on sparse views: depth terms that leave colour more of the gradient
    "pnerf_light_depth": {"loss": "pnerf", "objective.weights.depth_pdf": 0.1, "objective.weights.depth": 0.1},
    "pnerf_fast_decay": {"loss": "pnerf", "objective.depth_weight_final_factor": 0.001},
    # the targets' systematic term: the sensor's own (2%, the default before the tuning below; the
    # default's is 4%) and twice the default's
    "pnerf_sensor_targets": {"loss": "pnerf", "targets.depth_sigma_relative": 0.02},
    "pnerf_wider_targets": {"loss": "pnerf", "targets.depth_sigma_relative": 0.08},
    # poses refined with the field, held by the tracker's covariances (with --poses tracked)
    "pnerf_refine": {"loss": "pnerf", "refine_poses": True},
    "photometric_refine": {"loss": "photometric", "refine_poses": True},
}
PRESET = {"fern": "forward_facing"}  # each dataset's preset (the others: "fast")
PAPER = {"fern": {"pnerf": (25.53, 0.80), "dsnerf": (24.27, 0.74)}}  # the PNeRF paper's Table (PSNR dB, SSIM)


def run_one(spec: dict) -> dict:
    """Train one (dataset, variant, seed) in a fresh process and score its held-out frames."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf.evaluation import heldout_scores

    seq, _ = load(spec["source"])
    seq, poses, covs = poses_for(spec["source"], seq, spec["poses"])
    d = spec["dataset"]
    budget = dict(max_steps=10**9, time_budget_s=spec["seconds"]) if spec["seconds"] else \
        dict(max_steps=spec["steps"], time_budget_s=None)
    cfg = pn.ReconstructionConfig.preset(
        PRESET.get(d, "fast"), **budget, holdout_every=HOLDOUT_EVERY.get(d, 4),
        image_scale=IMAGE_SCALE.get(d, 0.5), train_views=spec["views"], seed=spec["seed"], progress=False,
        **VARIANTS[spec["variant"]])
    t0 = time.perf_counter()
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    wall = time.perf_counter() - t0
    if spec["split"] == "tuning":  # score the pool's frames the sparse views left out, never the held-out ones
        recon.holdout_indices = np.setdiff1d(np.arange(len(seq)), np.union1d(recon.train_indices,
                                                                               recon.holdout_indices))
    scores = heldout_scores(recon, seq)["model"]
    tr = recon.stats["training"]
    history = [(h["seconds"], h["eval_psnr"]) for h in recon.stats["history"] if "eval_psnr" in h]
    return {**{k: spec[k] for k in ("dataset", "variant", "seed", "views")}, "model": scores,
            "steps": tr["steps"], "train_s": tr["seconds"], "wall_s": round(wall, 1),
            "timings": recon.stats["timings"], "eval_history": history}


def at_time(history: list, seconds: float) -> float:
    """The periodic held-out PSNR at `seconds`, linear between evaluations."""
    t, p = np.array(history).T
    return float(np.interp(seconds, t, p))


def add_equal_time(results: list[dict]) -> None:
    """Each run's periodic held-out PSNR at the largest time all runs of its dataset and seed reached."""
    for r in results:
        group = [q for q in results if q["dataset"] == r["dataset"] and q["seed"] == r["seed"]]
        common = min(q["eval_history"][-1][0] for q in group)
        r["equal_time"] = {"seconds": common, "psnr_subset": round(at_time(r["eval_history"], common), 3)}


def summary(results: list[dict], variants: list[str]) -> dict:
    """Per dataset: each variant's mean over seeds, and each variant's paired difference to the first."""
    out = {}
    for d in dict.fromkeys(r["dataset"] for r in results):
        rows = {v: sorted((r for r in results if r["dataset"] == d and r["variant"] == v), key=lambda r: r["seed"])
                for v in variants}
        first = rows[variants[0]]
        out[d] = {}
        for v, rs in rows.items():
            if not rs:
                continue
            keys = [k for k in ("psnr", "ssim", "depth_l1", "within_1") if k in rs[0]["model"]]
            entry = {k: round(float(np.mean([r["model"][k] for r in rs])), 4) for k in keys}
            entry["equal_time_psnr_subset"] = round(float(np.mean([r["equal_time"]["psnr_subset"] for r in rs])), 3)
            entry["train_s"] = round(float(np.mean([r["train_s"] for r in rs])), 1)
            if v != variants[0]:
                diff = [a["model"]["psnr"] - b["model"]["psnr"] for a, b in zip(first, rs)]
                entry[f"psnr_{variants[0]}_minus_this"] = [round(x, 3) for x in diff]
            out[d][v] = entry
    return out


def markdown(results: list[dict], meta: dict, variants: list[str]) -> str:
    split = ("Scored on the held-out frames." if meta.get("split", "report") == "report" else
             "Tuning split: scored on the training pool's frames the sparse views left out, not the held-out ones.")
    budget = (f"{meta['seconds']:g} s of training per run (equal time)" if meta.get("seconds") else
              f"{meta['steps']} steps per run (equal steps)")
    poses = "the tracker's poses and covariances" if meta.get("poses") == "tracked" else "ground-truth poses"
    lines = [f"{budget}, {poses}, seeds {meta['seeds']}, {meta['threads']} thread(s), "
             f"{meta['jobs']} run(s) at once; {meta['wall_minutes']} min in all; {meta['machine']}. {split}",
             "PSNR/SSIM/depth: full held-out images at the end. Equal time: PSNR of 2,048 fixed held-out pixels "
             "at the time every run of the same dataset and seed had reached.", ""]
    head = ("| dataset | loss | seed | PSNR (dB) | SSIM | depth L1 (mm) | within 1σ | equal-time PSNR (s) | train s "
            "| steps |")
    lines += [head, "|" + " --- |" * (head.count("|") - 1)]
    for r in sorted(results, key=lambda r: (r["dataset"], variants.index(r["variant"]), r["seed"])):
        m = r["model"]
        depth = f"{1000 * m['depth_l1']:.1f}" if "depth_l1" in m else "-"
        within = f"{m['within_1']:.2f}" if "within_1" in m else "-"
        lines.append(f"| {r['dataset']} | {r['variant']} | {r['seed']} | {m['psnr']:.2f} | {m['ssim']:.3f} | {depth} | "
                     f"{within} | {r['equal_time']['psnr_subset']:.2f} ({r['equal_time']['seconds']:.0f}) | "
                     f"{r['train_s']:.0f} | {r['steps']} |")
    lines += ["", "Means over seeds, and the paired PSNR difference of the first loss minus each other, seed by seed:",
              "", "| dataset | loss | PSNR (dB) | SSIM | depth L1 (mm) | equal-time PSNR | "
              f"{variants[0]} minus this, per seed (dB) | paper PSNR / SSIM |", "|" + " --- |" * 8]
    for d, per in meta["summary"].items():
        for v, e in per.items():
            paper = PAPER.get(d, {}).get(v)
            depth = f"{1000 * e['depth_l1']:.1f}" if "depth_l1" in e else "-"
            pairs = ", ".join(f"{x:+.2f}" for x in e.get(f"psnr_{variants[0]}_minus_this", [])) or "-"
            lines.append(f"| {d} | {v} | {e['psnr']:.2f} | {e['ssim']:.3f} | {depth} | "
                         f"{e['equal_time_psnr_subset']:.2f} | {pairs} | "
                         f"{f'{paper[0]:.2f} / {paper[1]:.2f}' if paper else '-'} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="fern", help="comma-separated: fern, synthetic, tum")
    ap.add_argument("--variants", default="pnerf,dsnerf,photometric", help=f"comma-separated, of {list(VARIANTS)}")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--steps", type=int, default=14000, help="training steps of every run")
    ap.add_argument("--seconds", type=float, help="instead of --steps: every run trains this long (equal time; "
                    "use --jobs 1 --threads 2, as a user runs it)")
    ap.add_argument("--views", type=int, default=10, help="training views (0 = every non-held-out frame)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--split", choices=("report", "tuning"), default="report",
                    help="score the held-out frames (report), or the training pool's frames the --views left out "
                         "(tuning: where settings are chosen, so the held-out frames stay unseen)")
    ap.add_argument("--poses", choices=("gt", "tracked"), default="gt",
                    help="train at the ground-truth poses (zero covariance) or at the tracker's as reconstruct() "
                         "trains on them (its colour cameras where it places them), aligned to the ground truth's "
                         "frame, with its covariances (what refine_poses needs)")
    ap.add_argument("--name", default="losses", help="stem of the result files in benchmarks/results/")
    args = ap.parse_args()
    datasets, variants = args.datasets.split(","), args.variants.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; expected some of {list(VARIANTS)}")
    refining = [v for v in variants if VARIANTS[v].get("refine_poses")]
    if refining and args.poses == "gt":  # zero covariances hold every pose still: the runs would be plain ones
        raise SystemExit(f"--variants {refining} refine the poses within their covariances: give --poses tracked")
    require_shared(*datasets)
    t0 = time.perf_counter()
    sources = {d: synthetic_room() if d == "synthetic" else d for d in datasets}
    if args.split == "tuning" and args.views == 0:
        raise SystemExit("--split tuning scores the frames --views leaves out: give --views")
    if args.poses == "tracked":  # track each sequence once, before the runs share the cached trajectory
        for d in datasets:
            poses_for(sources[d], load(sources[d])[0], "tracked")
    specs = [dict(dataset=d, source=sources[d], variant=v, seed=s, views=args.views, steps=args.steps,
                  seconds=args.seconds, threads=args.threads, split=args.split, poses=args.poses)
             for d in datasets for s in seeds for v in variants]
    results = run_in_processes(run_one, specs, args.jobs, lambda r: (
        f"{r['dataset']:10s} {r['variant']:22s} seed {r['seed']} PSNR {r['model']['psnr']:.2f} "
        f"SSIM {r['model']['ssim']:.3f} {r['train_s']:.0f} s"))
    add_equal_time(results)
    meta = {"machine": machine(), "commit": commit(),
            "steps": None if args.seconds else args.steps, "seconds": args.seconds, "seeds": seeds,
            "views": args.views, "split": args.split, "poses": args.poses, "threads": args.threads, "jobs": args.jobs,
            "wall_minutes": round((time.perf_counter() - t0) / 60, 1),
            "holdout_every": {d: HOLDOUT_EVERY.get(d, 4) for d in datasets},
            "preset": {d: PRESET.get(d, "fast") for d in datasets},
            "image_only": [d for d in datasets if d == "fern"]}
    meta["summary"] = summary(results, variants)
    write_result(args.name, {"meta": meta, "runs": results}, markdown(results, meta, variants))


if __name__ == "__main__":
    main()
