"""What does the mesh's TSDF truncation (export.mesh_trunc_voxels) trade: holes against accuracy?

Per dataset and seed, one model (the `fast` preset, ground-truth poses, every 4th frame held out,
320x240) is exported once per truncation, and each export is compared fairly
(open3d_pnerf.comparison.compare) with the sensor alone and Open3D's TSDF of the same truncation, on
the same held-out pixels: the share of the sensor's pixels the mesh misses (holes), its depth L1 on its
own hits and on the pixels every method covers, its colour there, and against the synthetic room's
exact surface, accuracy and completeness. Datasets as bench_map.py's, and 7scenes_every10 (redkitchen,
every 10th frame of 0-990: the same kitchen, other views), where the default is chosen.

    python benchmarks/bench_export.py --datasets 7scenes_every10,tum,7scenes,synthetic --seeds 0,1 --name export_trunc

Writes benchmarks/results/<name>.json and <name>.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import time

import numpy as np
from common import (TRAIN_VIEWS, commit, load, machine, poses_for, require_shared, run_in_processes, synthetic_room,
                    write_result)

ROWS = ("mesh", "sensor", "tsdf")
COLUMNS = [  # label, key, factor, format
    ("holes", "holes", 100, ".2f"), ("depth L1 own hits (mm)", "depth_l1_hits", 1000, ".1f"),
    ("depth L1 common (mm)", "depth_l1_common", 1000, ".1f"), ("colour PSNR common (dB)", "psnr_common", 1, ".2f"),
    ("acc. (mm)", "accuracy", 1000, ".1f"), ("compl. (mm)", "completeness", 1000, ".1f")]


def run_one(spec: dict) -> dict:
    """Train one (dataset, seed), then export and compare it at each truncation."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf.comparison import compare
    from open3d_pnerf.export import export_geometry

    seq, reference = load(spec["source"])
    seq, poses, covs = poses_for(spec["source"], seq)
    views = TRAIN_VIEWS.get(spec["dataset"], 0)  # 7scenes_every10: every frame not held out
    cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, train_views=views, seed=spec["seed"], progress=False)
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    tables, seconds = {}, {}
    for trunc in spec["truncs"]:
        t0 = time.perf_counter()
        variant = dataclasses.replace(recon, config=recon.config.replace(**{"export.mesh_trunc_voxels": trunc}))
        variant.geometry = export_geometry(variant, seq, progress=False)
        seconds[trunc] = round(time.perf_counter() - t0, 1)
        table = compare(variant, seq, reference=reference, figure_frames=0, progress=False).table
        for row in ROWS:
            table[row]["holes"] = 1 - table[row]["coverage"]
        tables[trunc] = {row: table[row] for row in ROWS}
    return {"dataset": spec["dataset"], "seed": spec["seed"], "views": len(recon.train_indices), "tables": tables,
            "export_s": seconds, "train_s": recon.stats["training"]["seconds"]}


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"`fast` preset, ground-truth poses, every 4th frame held out, 320x240, seeds {meta['seeds']}, "
             f"truncations {meta['truncs']} voxels of 1 cm; at commit {meta['commit']}; {meta['wall_minutes']} min "
             f"in all; {meta['machine']}.", "",
             "Each cell: the mean over the seeds (min..max). Holes: % of the held-out sensor pixels a method "
             "misses.", ""]
    for d in dict.fromkeys(r["dataset"] for r in results):
        runs = [r for r in results if r["dataset"] == d]
        lines += [f"### {d}, {runs[0]['views']} training views", "",
                  "| method | truncation (voxels) | " + " | ".join(c[0] for c in COLUMNS) + " |",
                  "|" + " --- |" * (len(COLUMNS) + 2)]
        for row in ROWS:
            for trunc in meta["truncs"]:
                cells = []
                for _, key, factor, fmt in COLUMNS:
                    values = [factor * r["tables"][trunc][row][key] for r in runs if key in r["tables"][trunc][row]]
                    cells.append(f"{np.mean(values):{fmt}} ({min(values):{fmt}}..{max(values):{fmt}})"
                                 if values else "-")
                lines.append(f"| {row} | {trunc} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="tum,7scenes,synthetic")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--truncs", default="4,8", help="comma-separated truncations (voxels)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--name", default="export_trunc")
    args = ap.parse_args()
    datasets, seeds = args.datasets.split(","), [int(s) for s in args.seeds.split(",")]
    truncs = [float(t) for t in args.truncs.split(",")]
    require_shared(*datasets)
    t0 = time.perf_counter()
    sources = {d: synthetic_room() if d == "synthetic" else d for d in datasets}
    specs = [dict(dataset=d, source=sources[d], seed=s, truncs=truncs, threads=args.threads)
             for d in datasets for s in seeds]

    def progress(r):
        return f"{r['dataset']} seed {r['seed']}: holes " + ", ".join(
            f"{t:g} voxels {100 * r['tables'][t]['mesh']['holes']:.2f}%" for t in truncs)

    results = run_in_processes(run_one, specs, args.jobs, progress)
    for r in results:  # JSON keys are strings
        r["tables"] = {f"{t:g}": v for t, v in r["tables"].items()}
    meta = {"machine": machine(), "commit": commit(), "seeds": seeds, "truncs": [f"{t:g}" for t in truncs],
            "threads": args.threads, "jobs": args.jobs, "wall_minutes": round((time.perf_counter() - t0) / 60, 1)}
    write_result(args.name, {"meta": meta, "runs": results}, markdown(results, meta))


if __name__ == "__main__":
    main()
