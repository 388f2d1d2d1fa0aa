"""The map against Open3D TSDF fusion: mesh accuracy and completeness, held-out depth, and
whether the depth sigma holds as an error bar.

Per dataset and loss (pnerf, dsnerf, photometric: the same configuration, the `fast` preset,
ground-truth poses, every 4th frame held out, 320x240), one run:
  * the exported mesh, fused with the sensor depth (what reconstruct() writes; with pnerf also
    with the model's depth kept in the sensor's holes only where its sigma is at most
    --fill-std, and with export.mesh_min_views 2), and the model-only mesh (the same export
    without the sensor), against the TSDF mesh Open3D fuses from the same training frames and
    poses: accuracy, completeness, F@20/50 mm against the
    exact surface (synthetic room); on every held-out frame, each mesh ray-cast at the
    held-out pose: depth L1 on its hits and the share of the sensor's pixels it covers;
  * the field's own held-out renders: depth L1 over every pixel with sensor depth, and the
    shares of errors within the central 68.3/95.4/99.7% intervals of the calibrated error law
    with its negative log-likelihood, for the default Student-t law and a Gaussian one (both
    fitted on training frames only);
  * export time against training time.
Datasets: synthetic (the room of bench_suite.py: 10 training views, and all 36 with pnerf only), tum (TUM
fr1/xyz, all 24 training frames), 7scenes (redkitchen 150-199, all 38 training frames).

    python benchmarks/bench_map.py [--datasets synthetic,synthetic_all,tum,7scenes] [--losses pnerf,dsnerf,photometric]
                                   [--set objective.weights.distortion=0.1 ...] (config overrides of every run)

Writes benchmarks/results/<name>.json and <name>.md (name: map).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import time
from pathlib import Path

import numpy as np
from bench_suite import OUT, PATHS, SHARED, load, machine, poses_for, prepare_synthetic, run_in_processes

from open3d_pnerf.config import overrides as config_overrides

VIEWS = {"synthetic": 10, "synthetic_all": 0, "tum": 0, "7scenes": 0}  # training views (0 = all)
MESH_ONLY = {"synthetic_all"}  # datasets run with pnerf only (the all-views mesh against the TSDF's)


def mesh_on_heldout(mesh, recon, sequence) -> dict:
    """Ray-cast `mesh` at every held-out pose (training resolution): depth L1 (m) on the
    pixels it hits that have sensor depth, and the share of sensor pixels it hits."""
    from open3d_pnerf.raycast import MeshRaycaster

    caster = MeshRaycaster(mesh)
    seq = sequence.select(recon.holdout_indices).scaled_by(recon.config.image_scale)
    (h, w), errors, covered, sensor = seq.image_size, [], 0, 0
    for k, i in enumerate(recon.holdout_indices):
        depth = seq[k].depth
        out = caster.render(recon.poses[i], seq.K, w, h)
        both = out["hit"] & (depth > 0)
        errors.append(np.abs(out["depth"] - depth)[both])
        covered, sensor = covered + both.sum(), sensor + (depth > 0).sum()
    err = np.concatenate(errors)
    return {"depth_l1": float(err.mean()) if err.size else float("nan"), "coverage": float(covered / max(sensor, 1))}


def export_with(recon, sequence, **export):
    """The fused mesh of `recon` exported with these ExportConfig fields changed."""
    from open3d_pnerf.export import export_geometry

    return export_geometry(recon, sequence, dataclasses.replace(recon.config.export, **export), progress=False).mesh


def run_one(spec: dict) -> dict:
    """Train one (dataset, loss), export fused and model-only, compare with the TSDF."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf import compare_with_tsdf
    from open3d_pnerf.evaluation import geometry_metrics, heldout_scores
    from open3d_pnerf.export import export_geometry

    seq, reference = load(spec["source"], Path(spec["cache"]))
    poses, covs = poses_for(spec["source"], seq, "gt", Path(spec["cache"]))
    cfg = pn.ReconstructionConfig.preset(spec["preset"], holdout_every=4, train_views=VIEWS[spec["dataset"]], loss=spec["loss"],
                                         seed=spec["seed"], progress=False, **spec["overrides"])
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    comparison = compare_with_tsdf(seq, reconstruction=recon, reference=reference, progress=False)
    meshes = {"fused": recon.mesh, "tsdf": comparison.tsdf.mesh()}
    if spec["loss"] == "pnerf":  # variants of the fused export
        for std in spec["fill_std"]:  # the model's depth kept in the sensor's holes only where this confident
            meshes[f"fused, fill sigma <= {1000 * std:g} mm"] = export_with(recon, seq, max_point_std=std)
        meshes["fused, seen in >= 2 views"] = export_with(recon, seq, mesh_min_views=2)  # seen by two export views
    t0 = time.perf_counter()
    meshes["model_only"] = export_geometry(recon, progress=False).mesh  # the same export without the sensor
    model_only_export_s = time.perf_counter() - t0
    out = {k: spec[k] for k in ("dataset", "loss", "seed")}
    out["views"] = len(recon.train_indices)
    out["field"] = {k: comparison.table["model"][k] for k in ("psnr", "ssim", "depth_l1", "within_1", "within_2",
                                                               "within_3", "nll")}
    out["tsdf_field_like"] = {k: comparison.table["tsdf"][k] for k in ("depth_l1", "hit_fraction")}
    out["meshes"] = {}
    for name, mesh in meshes.items():
        if mesh is None or not mesh.has_triangles():  # no confident surface (e.g. colour only, model-only export)
            out["meshes"][name] = {"depth_l1": float("nan"), "coverage": 0.0}
            continue
        entry = mesh_on_heldout(mesh, recon, seq)
        if reference is not None:
            g = geometry_metrics(mesh, reference)
            entry.update({k: g[k] for k in ("accuracy", "completeness", "fscore_20mm", "fscore_50mm")})
        out["meshes"][name] = {k: round(v, 5) for k, v in entry.items()}
    out["calibration"] = {"scale": recon.depth_sigma_scale, "floor": recon.depth_sigma_floor,
                          "dof": None if np.isinf(recon.depth_sigma_dof) else recon.depth_sigma_dof}
    # the same model with a Gaussian error law (fitted the same way, on the same training pixels)
    recon.calibrate_depth_sigma(seq, method="gaussian")
    gaussian = heldout_scores(recon, seq)["model"]
    out["field_gaussian"] = {k: gaussian[k] for k in ("within_1", "within_2", "within_3", "nll")}
    out["calibration_gaussian"] = {"scale": recon.depth_sigma_scale, "floor": recon.depth_sigma_floor}
    out["train_s"] = recon.stats["training"]["seconds"]
    out["export_s"] = recon.stats["timings"]["export_s"]
    out["model_only_export_s"] = round(model_only_export_s, 2)
    return out


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"`{meta['preset']}` preset, GT poses, every 4th frame held out, 320x240, seed {meta['seed']}; {meta['threads']} "
             f"thread(s) per run, {meta['jobs']} at once; {meta['wall_minutes']} min in all; {meta['machine']}."
             + "".join(f" {k}={v}" for k, v in meta.get("overrides", {}).items()), "",
             "Meshes (held-out frames: each mesh ray-cast at the held-out poses; acc./compl./F against the exact "
             "surface, synthetic only):", "",
             "| dataset | views | loss | mesh | acc. (mm) | compl. (mm) | F@20mm | F@50mm | held-out depth L1 on hits (mm) "
             "| sensor pixels covered |", "|" + " --- |" * 10]
    mm = lambda d, k: f"{1000 * d[k]:.1f}" if k in d else "-"  # noqa: E731
    f3 = lambda d, k: f"{d[k]:.3f}" if k in d else "-"  # noqa: E731
    for r in results:
        for name, m in r["meshes"].items():
            if name == "tsdf" and r["loss"] != "pnerf":
                continue  # the same TSDF in every loss's run
            label = "Open3D TSDF" if name == "tsdf" else name.replace("_", "-")
            lines.append(f"| {r['dataset']} | {r['views']} | {r['loss'] if name != 'tsdf' else '-'} | {label} | "
                         f"{mm(m, 'accuracy')} | {mm(m, 'completeness')} | {f3(m, 'fscore_20mm')} | "
                         f"{f3(m, 'fscore_50mm')} | {mm(m, 'depth_l1')} | {m['coverage']:.3f} |")
    lines += ["", "The field's own held-out renders, and its depth sigma as an error bar: the share of held-out "
              "errors within the central 68.3 / 95.4 / 99.7% intervals of the calibrated law (what 1/2/3 sigma hold "
              "for a Gaussian; a calibrated law gives those shares) and its negative log-likelihood (nats), for the "
              "default Student-t law and a Gaussian one fitted the same way on the same training pixels; TSDF depth "
              "L1 on its hits:", "",
              "| dataset | views | loss | PSNR (dB) | depth L1 (mm) | TSDF depth L1 on hits (mm) | Student-t: 68.3% | "
              "95.4% | 99.7% | NLL | Gaussian: 68.3% | 95.4% | 99.7% | NLL | sigma = sqrt((s spread)^2 + (f z)^2), "
              "dof | train s | export s (fused) |", "|" + " --- |" * 18]
    for r in results:
        f, g, t, c = r["field"], r["field_gaussian"], r["tsdf_field_like"], r["calibration"]
        dof = "Gaussian" if c["dof"] is None else f"{c['dof']:.3g} dof"
        lines.append(f"| {r['dataset']} | {r['views']} | {r['loss']} | {f['psnr']:.2f} | {1000 * f['depth_l1']:.1f} | "
                     f"{1000 * t['depth_l1']:.1f} | {f['within_1']:.3f} | {f['within_2']:.3f} | {f['within_3']:.3f} | "
                     f"{f['nll']:.2f} | {g['within_1']:.3f} | {g['within_2']:.3f} | {g['within_3']:.3f} | "
                     f"{g['nll']:.2f} | s {c['scale']:.3g}, f {100 * c['floor']:.2g}%, {dof} | {r['train_s']:.0f} | "
                     f"{r['export_s']:.1f} ({100 * r['export_s'] / r['train_s']:.0f}%) |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="synthetic,synthetic_all,tum,7scenes")
    ap.add_argument("--losses", default="pnerf,dsnerf,photometric")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=min(2, multiprocessing.cpu_count()), help="runs at once")
    ap.add_argument("--preset", default="fast", help="'test': a smoke test of the script")
    ap.add_argument("--fill-std", default="0.02,0.05",
                    help="pnerf only: also export with the model's depth kept where its sigma is at most these (m)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override of every run, e.g. objective.weights.distortion=0.1 (repeatable)")
    ap.add_argument("--name", default="map")
    args = ap.parse_args()
    datasets, losses = args.datasets.split(","), args.losses.split(",")
    overrides = config_overrides(args.set)
    missing = [d for d in datasets if not d.startswith("synthetic") and not PATHS.get(d, SHARED / "?").is_dir()]
    if missing:
        raise SystemExit(f"shared data not found for {missing} (expected under {SHARED})")
    cache = OUT / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    synthetic = prepare_synthetic(cache, False) if any(d.startswith("synthetic") for d in datasets) else None
    specs = [dict(dataset=d, source=synthetic if d.startswith("synthetic") else d, loss=loss, seed=args.seed,
                  threads=args.threads, preset=args.preset, cache=str(cache),
                  fill_std=[float(v) for v in args.fill_std.split(",") if v], overrides=overrides)
             for d in datasets for loss in losses if d not in MESH_ONLY or loss == "pnerf"]
    results = run_in_processes(run_one, specs, args.jobs, lambda r: (
        f"{r['dataset']:14s} {r['loss']:12s} fused {r['meshes']['fused']} tsdf {r['meshes']['tsdf']} "
        f"field {r['field']}"))
    meta = {"machine": machine(),
            "seed": args.seed, "threads": args.threads, "jobs": args.jobs, "preset": args.preset, "fill_std": args.fill_std,
            "overrides": overrides,
            "wall_minutes": round((time.perf_counter() - t0) / 60, 1), "views": VIEWS}
    (OUT / f"{args.name}.json").write_text(json.dumps({"meta": meta, "runs": results}, indent=1))
    (OUT / f"{args.name}.md").write_text(markdown(results, meta))
    print((OUT / f"{args.name}.md").read_text())


if __name__ == "__main__":
    main()
