"""How does the map compare with the sensor alone and Open3D TSDF fusion, per scene? Fairly: the same
frames, poses, resolution, extraction threshold and pixels (open3d_pnerf.compare_with_tsdf).

Per dataset, loss and seed (the `fast` preset, ground-truth poses, every 4th frame held out,
320x240), one run scored by compare_with_tsdf: the field's own renders, the exported mesh (the
sensor's depth fused with the model's), the sensor alone (the same export without the model),
Open3D's TSDF at the exported mesh's threshold and at its default one; on the held-out frames,
depth and colour on the pixels every method covers, on each method's own hits and where only the
model covers (with the share of the errors inside its 99.7% interval there), and the field's PSNR on
8 of its training frames (how well it fits what it trained on); accuracy,
completeness and F-scores against the exact surface (synthetic room only). Beside them the
model-only mesh (the export without the sensor: the neural surface's own geometry).
With --ensemble K, beside each pnerf run the ensemble baseline of predictive uncertainty (K seeds, the
spread of their depths calibrated as the model's sigma is: ensemble_rows), at equal steps per member and
at equal total steps; the model's depth sigma is scored on every held-out pixel with sensor depth (shares
inside its 68.3/95.4/99.7% intervals, NLL, AUCE, AUSE). Where the synthetic room's exact mesh is known,
the exported sigmas (fused depth, mesh vertices) are scored against exact errors.
Datasets: synthetic (the synthetic room, 48 frames at 640x480: 10 training views), synthetic_all (all 36 views,
pnerf only), tum (TUM fr1/xyz, 24 training frames), 7scenes (redkitchen 150-199, 38 training
frames), tum_10 and 7scenes_10 (the same with 10 training views, evenly spaced). The targets of the
fair comparison are checked per seed at the end.

    python benchmarks/bench_map.py [--datasets synthetic,synthetic_all,tum,7scenes] [--losses pnerf,photometric]
                                   [--seeds 0,1,2] [--set geometry=sdf ...] (config overrides of every run) [--name map]
                                   [--ensemble 3]
    python benchmarks/bench_map.py --name map --markdown-only     (the .md again from the .json)

Writes benchmarks/results/<name>.json and <name>.md, and <name>_<dataset>.png: the first held-out
frame of each dataset's first pnerf run (input, model, exported mesh, TSDF).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time

import numpy as np
from common import (OUT, PATHS, TRAIN_VIEWS, commit, exact_surface, load, machine, poses_for, require_shared,
                    run_in_processes, synthetic_room, write_result)

from open3d_pnerf.config import overrides as config_overrides

SOURCES = {"tum_10": "tum", "7scenes_10": "7scenes"}  # the sparse variants' recordings
MESH_ONLY = {"synthetic_all"}  # datasets run with pnerf only (the all-views mesh against the TSDF's)
COLUMNS = [  # label, key, factor, format
    ("acc. (mm)", "accuracy", 1000, ".1f"), ("compl. (mm)", "completeness", 1000, ".1f"),
    ("F@20mm", "fscore_20mm", 1, ".3f"), ("F@50mm", "fscore_50mm", 1, ".3f"),
    ("depth L1 common (mm)", "depth_l1_common", 1000, ".1f"), ("common share", "common_share", 1, ".3f"),
    ("depth L1 common, beside depth edges (mm)", "depth_l1_common_edges", 1000, ".1f"),
    ("depth L1 common, away from edges (mm)", "depth_l1_common_flat", 1000, ".1f"),
    ("depth L1 own hits (mm)", "depth_l1_hits", 1000, ".1f"), ("coverage", "coverage", 1, ".3f"),
    ("holes at depth edges", "holes_at_edges", 1, ".3f"), ("sensor pixels at depth edges", "edge_share", 1, ".3f"),
    ("depth L1 model only (mm)", "depth_l1_only", 1000, ".1f"), ("model-only share", "only_share", 1, ".3f"),
    ("99.7% interval holds (model only)", "within_3_only", 1, ".3f"),
    ("PSNR (dB)", "psnr", 1, ".2f"), ("PSNR training frames (dB)", "psnr_train", 1, ".2f"),
    ("PSNR common (dB)", "psnr_common", 1, ".2f"),
    ("PSNR beside depth edges (dB)", "psnr_edges", 1, ".2f"), ("PSNR away from edges (dB)", "psnr_flat", 1, ".2f"),
    ("depth L1 (mm)", "depth_l1", 1000, ".1f"), ("in 68.3%", "within_1", 1, ".3f"), ("in 95.4%", "within_2", 1, ".3f"),
    ("in 99.7%", "within_3", 1, ".3f"), ("NLL", "nll", 1, ".2f"),
    ("AUCE", "auce", 1, ".3f"), ("AUSE RMSE", "ause_rmse", 1, ".3f"), ("AUSE MAE", "ause_mae", 1, ".3f"),
    ("exact in 1 sigma (0.683)", "exact_within_1", 1, ".3f"), ("exact in 2 sigma (0.954)", "exact_within_2", 1, ".3f"),
    ("exact in 3 sigma (0.997)", "exact_within_3", 1, ".3f")]


def run_one(spec: dict) -> dict:
    """Train one (dataset, loss, seed) and compare it fairly with the sensor alone and the TSDF."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf import compare_with_tsdf
    from open3d_pnerf.evaluation import exact_sigma_coverage, heldout_views, score_views, training_psnr
    from open3d_pnerf.export import export_geometry
    from open3d_pnerf.metrics import geometry_metrics

    seq, reference = load(spec["source"])
    seq, poses, covs = poses_for(spec["source"], seq)
    cfg = pn.ReconstructionConfig.preset(spec["preset"], holdout_every=4, train_views=TRAIN_VIEWS[spec["dataset"]],
                                         loss=spec["loss"], seed=spec["seed"], progress=False, **spec["overrides"])
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    t0 = time.perf_counter()
    comparison = compare_with_tsdf(seq, reconstruction=recon, reference=reference, progress=False)
    compare_s = time.perf_counter() - t0
    if spec.get("figure") and comparison.figures:
        comparison.figures[0].savefig(spec["figure"], dpi=70)
    table = comparison.table
    table["model"]["psnr_train"] = round(training_psnr(recon, seq), 5)  # beside held-out PSNR: fit or generalise
    if reference is not None:  # the exported sigmas against the exact errors: the mesh's vertices, the fused depth
        coverage = exact_sigma_coverage(recon, seq, exact_surface(spec["source"]))
        for row, key in (("mesh", "mesh"), ("fused_depth", "fused_depth")):
            table.setdefault(row, {}).update({f"exact_{k}": v for k, v in coverage.get(key, {}).items()})
    model_only = export_geometry(recon, progress=False).mesh  # the export without the sensor
    if model_only.has_triangles():
        views = heldout_views(recon, seq, {"model_only": model_only})
        row = score_views(views, cfg.export.min_opacity, common_of=["model"])["model_only"]  # its own hits
        if reference is not None:
            row.update(geometry_metrics(model_only, reference))
        table["model_only"] = {k: round(v, 5) for k, v in row.items()}
    ensemble_s = {}
    if spec.get("ensemble", 1) > 1 and spec["loss"] == "pnerf":
        rows, ensemble_s = ensemble_rows(recon, seq, poses, covs, cfg, spec["ensemble"])
        table.update(rows)
    return {**{k: spec[k] for k in ("dataset", "loss", "seed")}, "views": len(recon.train_indices), "table": table,
            "ensemble_train_s": ensemble_s,
            "mesh_triangles": len(recon.mesh.triangles),
            "sdf_beta": recon.field.beta.item() if getattr(recon.field, "sdf", None) is not None else None,
            "train_s": recon.stats["training"]["seconds"],
            "steps": recon.stats["training"]["steps"], "export_s": recon.stats["timings"]["export_s"],
            "compare_s": round(compare_s, 1)}


def ensemble_rows(recon, seq, poses, covs, cfg, members: int) -> dict:
    """The ensemble baseline of predictive uncertainty (--ensemble K): K pnerf models of other seeds,
    their mean depth with the spread (std) of their depths as the raw sigma, calibrated as the single
    model's is (DepthErrorLaw.fit by maximum likelihood on training frames: the same frames, pixels and
    law), scored on the same held-out pixels by score_views: "ensemble" at equal steps per member (the
    run's own model and K - 1 more, K times the compute), "ensemble_split" at equal total steps (K
    models of 1/K of the steps and time budget each). The models of a run differ only in their seed."""
    import open3d_pnerf as pn
    from open3d_pnerf.error_law import DepthErrorLaw
    from open3d_pnerf.evaluation import heldout_views, score_views

    def train(seed, share=1):
        budget = None if cfg.time_budget_s is None else cfg.time_budget_s / share
        return pn.reconstruct(seq, cfg.replace(seed=seed, max_steps=cfg.max_steps // share, time_budget_s=budget),
                              poses=poses, covariances=covs)

    rows, seconds, intrinsic = {}, {}, seq.scaled_by(cfg.image_scale).intrinsic
    for name, models in (("ensemble", lambda: [recon] + [train(cfg.seed + 1000 * j) for j in range(1, members)]),
                         ("ensemble_split", lambda: [train(cfg.seed + 1000 * j, members) for j in range(members)])):
        models = models()
        law = DepthErrorLaw.fit(*_ensemble_training_errors(models, seq))
        views = []
        for item in heldout_views(recon, seq):  # the run's own model has rendered each held-out frame there
            i = item["index"]
            renders = [item["model"] if m is recon else m.render(recon.poses[i], intrinsic, frame=i) for m in models]
            depth = np.stack([r["depth"] for r in renders])
            spread = np.maximum(depth.std(0), 1e-6)
            views.append({**item, "model": {"color": np.mean([r["color"] for r in renders], 0), "depth": depth.mean(0),
                                            "opacity": np.mean([r["opacity"] for r in renders], 0),
                                            "depth_std": law.sigma(spread, depth.mean(0))}})
        row = score_views(views, cfg.export.min_opacity, law.dof)["model"]
        rows[name] = {k: row[k] for k in ("psnr", "depth_l1", "within_1", "within_2", "within_3", "nll", "auce",
                                          "ause_rmse", "ause_mae") if k in row}
        seconds[name] = round(sum(m.stats["training"]["seconds"] for m in models), 1)
    return rows, seconds


def _ensemble_training_errors(models, seq) -> tuple:
    """(err, spread, z) (M,) m of an ensemble on its training frames, at the pixels where one model's
    law is fitted (evaluation.training_pixels): the members' mean depth against the sensor's and the
    spread of the members' depths, where every member's opacity exceeds 0.5."""
    from open3d_pnerf.evaluation import training_pixels

    err, spread, depth = [], [], []
    for i, intrinsic, u, v, z in training_pixels(models[0], seq):
        outs = [m.render_pixels(m.poses[i], intrinsic, u, v) for m in models]
        d = np.stack([o["depth"] for o in outs])
        ok = np.all([o["opacity"] > 0.5 for o in outs], 0)
        err.append(np.abs(d.mean(0) - z)[ok])
        spread.append(np.maximum(d.std(0), 1e-6)[ok])
        depth.append(z[ok])
    return np.concatenate(err), np.concatenate(spread), np.concatenate(depth)


def mean_table(runs: list[dict]) -> dict:
    """{method: {metric: (mean, min, max)}} over the runs (seeds) of one dataset and loss."""
    methods = {m: None for r in runs for m in r["table"]}
    out = {}
    for m in methods:
        keys = {k for r in runs for k in r["table"].get(m, {})}
        out[m] = {k: (float(np.mean(v)), float(np.min(v)), float(np.max(v)))
                  for k in keys if (v := [r["table"][m][k] for r in runs if k in r["table"].get(m, {})])}
    return out


def checks(runs: list[dict]) -> list[tuple[str, str, list[bool]]]:
    """The fair comparison's targets: (dataset, target, passed per seed) for the runs present."""
    by = {}
    for r in runs:
        by.setdefault((r["dataset"], r["loss"]), {})[r["seed"]] = r["table"]
    out = []

    def check(dataset, text, test, loss="pnerf"):
        seeds = by.get((dataset, loss), {})
        if seeds:
            out.append((dataset, text, [bool(test(t, s)) for s, t in sorted(seeds.items())]))

    check("synthetic", "mesh accuracy no worse than the sensor alone's",
          lambda t, s: t["mesh"]["accuracy"] <= t["sensor"]["accuracy"])
    check("synthetic", "mesh completeness at most half the sensor alone's",
          lambda t, s: t["mesh"]["completeness"] <= 0.5 * t["sensor"]["completeness"])
    check("synthetic", "mesh F@20mm at least the sensor alone's + 0.05",
          lambda t, s: t["mesh"]["fscore_20mm"] >= t["sensor"]["fscore_20mm"] + 0.05)
    for key in ("accuracy", "completeness"):
        check("synthetic_all", f"mesh {key} better than the TSDF's (same threshold)",
              lambda t, s, k=key: t["mesh"][k] < t["tsdf"][k])
    check("synthetic_all", "mesh F@20mm better than the TSDF's", lambda t, s: t["mesh"]["fscore_20mm"] > t["tsdf"]["fscore_20mm"])
    for d in ("tum", "7scenes", "tum_10", "7scenes_10"):
        check(d, "model depth on common pixels no worse than the TSDF's",
              lambda t, s: t["model"]["depth_l1_common"] <= t["tsdf"]["depth_l1_common"])
        check(d, "mesh depth on common pixels at most 0.8x the TSDF's",
              lambda t, s: t["mesh"]["depth_l1_common"] <= 0.8 * t["tsdf"]["depth_l1_common"])
        check(d, "mesh depth on its hits no worse than the TSDF's on its hits",
              lambda t, s: t["mesh"]["depth_l1_hits"] <= t["tsdf"]["depth_l1_hits"])
        check(d, "mesh holes at most 1% of the sensor's pixels", lambda t, s: t["mesh"]["coverage"] >= 0.99)
        check(d, "model's depth sigma: AUCE at most 0.03", lambda t, s: t["model"]["auce"] <= 0.03)
        for k, claim, tol in ((1, 0.683, 0.03), (2, 0.954, 0.02), (3, 0.997, 0.005)):
            check(d, f"model's depth sigma: share inside the {claim:.1%} interval within {tol} of it",
                  lambda t, s, k=k, claim=claim, tol=tol: abs(t["model"][f"within_{k}"] - claim) <= tol)
        for name in ("ensemble", "ensemble_split"):
            if any(name in r["table"] for r in runs if r["dataset"] == d):
                check(d, f"AUSE-RMSE of pnerf's sigma below the {name.replace('_', ' ')}'s",
                      lambda t, s, name=name: t["model"]["ause_rmse"] < t[name]["ause_rmse"])
        check(d, "model-only pixels: at least 99% of errors inside the 99.7% interval",
              lambda t, s: t["model"].get("within_3_only", 1.0) >= 0.99)
        colour_only = by.get((d, "photometric"), {})
        if colour_only:  # runs without colour-only training have nothing to compare with
            check(d, "held-out PSNR at least colour-only training's (same seed)",
                  lambda t, s: s in colour_only and t["model"]["psnr"] >= colour_only[s]["model"]["psnr"])
    return out


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"`{meta['preset']}` preset, GT poses, every 4th frame held out, 320x240, seeds {meta['seeds']}; "
             f"{meta['threads']} thread(s) per run, {meta['jobs']} at once; {meta['wall_minutes']} min in all; "
             f"{meta['machine']}." + "".join(f" {k}={v}" for k, v in meta.get("overrides", {}).items()), "",
             "Each cell: the mean over the seeds (min..max). Held-out frames: depth L1 on the pixels every method "
             "but the default-threshold TSDF covers (common), on each method's own hits, and where only the model "
             "(or its mesh) covers, each with its share of the pixels with sensor depth; acc./compl./F against the "
             "exact surface (synthetic only), and there the shares of the exact errors inside 1, 2, 3 of the exported "
             "sigmas (the mesh's vertices: distance to the exact surface; the fused depth of the export views: "
             "depth error at each pixel). The TSDF rows are Open3D's of the same training frames and poses.", ""]
    labels = {"model": "model (renders)", "mesh": "exported mesh", "sensor": "sensor alone",
              "tsdf": "TSDF, same threshold", "tsdf_default": "TSDF, Open3D default threshold",
              "model_only": "model-only mesh", "fused_depth": "fused depth (export views)",
              "ensemble": f"ensemble of {meta.get('ensemble')} (equal steps per member)",
              "ensemble_split": f"ensemble of {meta.get('ensemble')} (equal total steps)"}
    groups = {}
    for r in results:
        groups.setdefault((r["dataset"], r["loss"]), []).append(r)
    for (dataset, loss), runs in groups.items():
        table = mean_table(runs)
        cols = [c for c in COLUMNS if any(c[1] in row for row in table.values())]
        train = np.mean([r["train_s"] for r in runs])
        lines += [f"### {dataset}, {runs[0]['views']} views, {loss} ({len(runs)} seeds, {train:.0f} s training, "
                  f"{np.mean([r['steps'] for r in runs]):.0f} steps)", "",
                  "| method | " + " | ".join(c[0] for c in cols) + " |", "|" + " --- |" * (len(cols) + 1)]
        for method, row in table.items():
            if loss != "pnerf" and method in ("sensor", "tsdf", "tsdf_default"):
                continue  # the same in every loss's run
            cells = []
            for _, key, factor, fmt in cols:
                if key not in row:
                    cells.append("-")
                    continue
                mean, lo, hi = (factor * v for v in row[key])
                cells.append(format(mean, fmt) + (f" ({lo:{fmt}}..{hi:{fmt}})" if len(runs) > 1 else ""))
            lines.append(f"| {labels.get(method, method)} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["### Targets", "", "| dataset | target | met in seeds |", "| --- | --- | --- |"]
    for dataset, text, passed in checks(results):
        lines.append(f"| {dataset} | {text} | {sum(passed)}/{len(passed)} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="synthetic,synthetic_all,tum,7scenes")
    ap.add_argument("--losses", default="pnerf,photometric")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--preset", default="fast", help="'test': a smoke test of the script")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override of every run, e.g. objective.weights.distortion=0.1 (repeatable)")
    ap.add_argument("--ensemble", type=int, default=1, metavar="K",
                    help="K > 1: beside each pnerf run, the ensemble baseline of K seeds (ensemble_rows)")
    ap.add_argument("--name", default="map")
    ap.add_argument("--markdown-only", action="store_true",
                    help="no runs: write results/<name>.md again from results/<name>.json (after a change of the tables)")
    args = ap.parse_args()
    if args.markdown_only:
        saved = json.loads((OUT / f"{args.name}.json").read_text())
        (OUT / f"{args.name}.md").write_text(markdown(saved["runs"], saved["meta"]))
        return
    datasets, losses = args.datasets.split(","), args.losses.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    overrides = config_overrides(args.set)
    require_shared(*(SOURCES.get(d, d) for d in datasets if d in PATHS or d in SOURCES))
    t0 = time.perf_counter()
    synthetic = synthetic_room() if any(d.startswith("synthetic") for d in datasets) else None
    specs = [dict(dataset=d, source=synthetic if d.startswith("synthetic") else SOURCES.get(d, d), loss=loss, seed=seed,
                  threads=args.threads, preset=args.preset, overrides=overrides, ensemble=args.ensemble,
                  figure=str(OUT / f"{args.name}_{d}.png") if seed == seeds[0] and loss == losses[0] else None)
             for seed in seeds for d in datasets for loss in losses if d not in MESH_ONLY or loss == "pnerf"]
    results = run_in_processes(run_one, specs, args.jobs, lambda r: (
        f"{r['dataset']:14s} {r['loss']:12s} seed {r['seed']} mesh {r['table']['mesh']} "
        f"sensor {r['table'].get('sensor')} tsdf {r['table'].get('tsdf')}"))
    meta = {"machine": machine(), "commit": commit(), "seeds": seeds, "threads": args.threads, "jobs": args.jobs, "preset": args.preset,
            "overrides": overrides, "wall_minutes": round((time.perf_counter() - t0) / 60, 1), "views": TRAIN_VIEWS,
            "ensemble": args.ensemble}
    write_result(args.name, {"meta": meta, "runs": results}, markdown(results, meta))


if __name__ == "__main__":
    main()
