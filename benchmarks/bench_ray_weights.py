"""Where the field puts each ray's weights against its depth target, with and without the coarse
render's loss terms (objective.coarse_terms): the evidence for their default.

Per seed and setting, one reconstruction of TUM fr1/xyz (the `fast` preset, ground-truth poses,
every 4th frame held out, 320x240). On every 4th training frame, 3,000 random pixels with a depth
target away from the sensor's depth edges (evaluation.held_out_edges): the 10 / 50 / 90% quantiles
and the mean of the ray's depth distribution (Reconstruction.depth_pdf, z-depth) minus the target's
mean, beside the target's own 10 / 90% quantiles (-+1.2816 sigma). On the held-out frames, away from
depth edges where the model covers: the rendered depth (the median) minus the sensor's depth.
Each cell: the median over the pixels, mm.

    python benchmarks/bench_ray_weights.py [--seeds 0,1,2] [--name ray_weights]

Writes benchmarks/results/<name>.json and <name>.md.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from pathlib import Path

import numpy as np
from bench_suite import OUT, load, machine, poses_for, run_in_processes

DATASET = "tum"
QUANTILES = (0.1, 0.5, 0.9)
PIXELS, FRAME_STEP = 3000, 4
KEYS = ["weights_q10", "weights_q50", "weights_q90", "weights_mean", "target_q10", "target_q90", "heldout_median"]


def run_one(spec: dict) -> dict:
    """Train one setting and seed; the medians (mm) of KEYS."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf.evaluation import held_out_edges
    from open3d_pnerf.rendering.volume import weight_quantile

    cache = Path(spec["cache"])
    seq, _ = load(DATASET, cache)
    poses, covs = poses_for(DATASET, seq, "gt", cache)
    cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, seed=spec["seed"], progress=False,
                                         **{"objective.coarse_terms": spec["coarse_terms"]})
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    scaled = seq.scaled_by(cfg.image_scale)
    train = recon.train_indices
    targets = cfg.targets.build(scaled.select(train), recon.poses[train], covs[train], progress=False)
    h, w = scaled.image_size
    rng = np.random.default_rng(spec["seed"])
    found = {k: [] for k in KEYS}
    for k in range(0, len(train), FRAME_STEP):
        i = int(train[k])
        ok = targets.valid[k] & ~held_out_edges(scaled[i].depth)
        rows = rng.choice(np.flatnonzero(ok), min(PIXELS, int(ok.sum())), replace=False)
        mu, sigma = targets.mean[k].reshape(-1)[rows], targets.sigma[k].reshape(-1)[rows]
        pdf = recon.depth_pdf(recon.poses[i], np.stack([rows % w, rows // w], 1))
        edges, mass = torch.as_tensor(pdf["edges"]), torch.as_tensor(pdf["mass"])
        for q in QUANTILES:
            found[f"weights_q{round(100 * q)}"].append(weight_quantile(edges, mass, q).numpy() - mu)
        found["weights_mean"].append((pdf["mass"] * pdf["z"]).sum(1) - mu)
        found["target_q10"].append(-1.2816 * sigma)
        found["target_q90"].append(1.2816 * sigma)
    for i in recon.holdout_indices:
        out, depth = recon.render(recon.poses[i], frame=int(i)), scaled[int(i)].depth
        ok = (depth > 0) & (out["opacity"] >= cfg.export.min_opacity) & ~held_out_edges(depth)
        found["heldout_median"].append((out["depth"] - depth)[ok])
    medians = {k: round(1000 * float(np.median(np.concatenate(v))), 2) for k, v in found.items()}
    return {"seed": spec["seed"], "coarse_terms": spec["coarse_terms"], "mm": medians,
            "train_s": recon.stats["training"]["seconds"]}


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"TUM fr1/xyz, `fast`, GT poses, seeds {meta['seeds']}; {meta['wall_minutes']} min in all; "
             f"{meta['machine']}.",
             "", "Medians over the pixels (mm): the training rays' depth distribution minus their target "
             "(away from depth edges), and the held-out rendered depth minus the sensor's.", "",
             "| coarse terms | seed | " + " | ".join(KEYS) + " |",
             "| --- | --- | " + " | ".join("---" for _ in KEYS) + " |"]
    for r in results:
        lines.append(f"| {'on' if r['coarse_terms'] else 'off'} | {r['seed']} | "
                     + " | ".join(f"{r['mm'][k]:.1f}" for k in KEYS) + " |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--name", default="ray_weights")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    cache = OUT / "cache"
    t0 = time.perf_counter()
    specs = [dict(seed=seed, coarse_terms=on, threads=1, cache=str(cache)) for seed in seeds for on in (True, False)]
    results = run_in_processes(run_one, specs, args.jobs,
                               lambda r: f"coarse terms {r['coarse_terms']} seed {r['seed']}: {r['mm']}")
    meta = {"machine": machine(), "seeds": seeds, "jobs": args.jobs,
            "wall_minutes": round((time.perf_counter() - t0) / 60, 1)}
    (OUT / f"{args.name}.json").write_text(json.dumps({"meta": meta, "runs": results}, indent=1))
    (OUT / f"{args.name}.md").write_text(markdown(results, meta))
    print((OUT / f"{args.name}.md").read_text())


if __name__ == "__main__":
    main()
