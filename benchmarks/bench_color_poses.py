"""Poses for the colour images: held-out colour and depth of reconstructions trained on the
ground-truth poses, on tracked poses of the colour cameras (the default: each frame's depth moved
into its colour camera, see open3d_pnerf.tracking.color) and on tracked poses of the depth cameras
(``tracking.color_poses=False``), paired over seeds.

Datasets: TUM fr1/xyz (its 32 shared frames; colour registered to the depth but taken up to 20 ms
apart) and 7-Scenes redkitchen frames 150-199 (colour not registered to the depth: no colour
cameras are placed, so only the default tracked variant runs). Every 4th frame held out,
training at 320x240, the `fast` preset for --steps steps (equal work). Held-out PSNR is scored on
the same colour images for every variant; depth on each variant's own frames (the colour-camera
variant's depth is the sensor's moved into the colour camera), on the pixels every method covers.
The colour-camera settings (tracking.color's prior and limits) were chosen on the bundled sample,
TUM fr1/xyz's first 32 frames: the TUM rows here are that sequence, the 7-Scenes rows are not.

    python benchmarks/bench_color_poses.py [--seeds 0,1,2] [--steps 1500] [--jobs 2]

Writes benchmarks/results/color_poses.json and .md.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from bench_suite import PATHS, machine, run_in_processes, write_result

DATASETS = ("tum", "7scenes")
VARIANTS = {"ground truth": None, "tracked: colour cameras": True, "tracked: depth cameras": False}
METRICS = {"psnr": ("model", "psnr"), "model depth mm": ("model", "depth_l1_common"),
           "mesh depth mm": ("mesh", "depth_l1_common"), "TSDF PSNR on its hits": ("tsdf", "psnr_hits")}


def variants(dataset: str) -> list[str]:
    """The variants that differ on a dataset: without registered colour there are no colour cameras."""
    return list(VARIANTS) if dataset == "tum" else ["ground truth", "tracked: colour cameras"]


def run_one(spec: dict) -> dict:
    """One reconstruction and its comparison with TSDF fusion; runs in a fresh process."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn

    seq = pn.load_sequence(PATHS[spec["dataset"]])
    color_poses = VARIANTS[spec["variant"]]
    overrides = {} if color_poses is None else {"tracking.color_poses": color_poses}
    cfg = pn.ReconstructionConfig.preset("fast", max_steps=spec["steps"], time_budget_s=10**6, holdout_every=4,
                                         image_scale=0.5, seed=spec["seed"], progress=False, **overrides)
    t0 = time.perf_counter()
    recon = pn.reconstruct(seq, cfg, poses=seq.gt_poses if color_poses is None else None)
    comparison = pn.compare_with_tsdf(seq, reconstruction=recon, progress=False)
    row = {name: comparison.table[method][key] for name, (method, key) in METRICS.items()}
    for name in ("model depth mm", "mesh depth mm"):
        row[name] = round(1000 * row[name], 2)
    return {**{k: spec[k] for k in ("dataset", "variant", "seed")}, **row,
            "ate_mm": round(1000 * recon.stats["tracking"].get("ate_rmse_m", np.nan), 2),
            "wall_s": round(time.perf_counter() - t0, 1)}


def summary(results: list[dict]) -> dict:
    """Per dataset and variant: the seed mean of each metric, and per tracked variant the paired
    PSNR differences against the ground truth's (seed by seed)."""
    out = {}
    for d in DATASETS:
        rows = {v: sorted((r for r in results if r["dataset"] == d and r["variant"] == v), key=lambda r: r["seed"])
                for v in variants(d)}
        out[d] = {v: {k: round(float(np.mean([r[k] for r in rs])), 2) for k in (*METRICS, "ate_mm")}
                  for v, rs in rows.items()}
        for v, rs in rows.items():
            out[d][v]["psnr_minus_gt"] = [round(a["psnr"] - b["psnr"], 2) for a, b in zip(rs, rows["ground truth"])]
    return out


def markdown(report: dict) -> str:
    lines = [f"# Poses for the colour images ({report['total_minutes']} min, `python benchmarks/bench_color_poses.py`)",
             "", f"{report['machine']}; seeds {report['seeds']}, {report['steps']} steps each, `fast` preset, "
             "every 4th frame held out, 320x240.", "",
             "| dataset | poses | held-out PSNR dB | PSNR - ground truth's, per seed | model depth mm | mesh depth mm "
             "| TSDF PSNR on its hits | ATE mm (depth cameras) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for d, rows in report["summary"].items():
        for v, r in rows.items():
            lines.append(f"| {d} | {v} | {r['psnr']} | {r['psnr_minus_gt']} | {r['model depth mm']} | "
                         f"{r['mesh depth mm']} | {r['TSDF PSNR on its hits']} | {r['ate_mm']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    start = time.perf_counter()
    specs = [{"dataset": d, "variant": v, "seed": s, "steps": args.steps, "threads": max(1, 2 // args.jobs)}
             for d in DATASETS for v in variants(d) for s in seeds]
    results = run_in_processes(run_one, specs, args.jobs, lambda r: json.dumps(r))
    report = {"machine": machine(), "seeds": seeds, "steps": args.steps, "runs": results,
              "summary": summary(results), "total_minutes": round((time.perf_counter() - start) / 60, 1)}
    write_result("color_poses", report, markdown(report))


if __name__ == "__main__":
    main()
