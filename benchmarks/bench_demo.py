"""What does `make demo` give, and did a change move it? The demo run exactly as a user runs it, its
held-out scores kept as a regression test; with --against REV, the same runs of an earlier revision
beside today's, every number compared (a change meant to leave behaviour alone must leave them equal:
with --steps, training stops after a fixed number of steps, and the demo is bit-reproducible).

Runs the command line, ``open3d-pnerf demo --out <temporary folder>`` (the bundled TUM
sample: tracked poses, the `fast` preset, every 4th frame held out), `--runs` times in a row, and
reads its report.json: the model's held-out PSNR and SSIM, depth on the pixels every method
covers, the exported mesh's coverage and colour, the same for the sensor alone and the TSDF, tracking ATE and
training time; and, from the saved reconstruction, each held-out frame's PSNR, the share of its
pixels that lie inside some training view's image (at the sensor's depth, else the model's; the
rest no training frame saw; occlusion is not counted) and the PSNR on the rest, and the held-out
PSNR on the pixels some training view saw. Writes results/<name>.json and .md. Against the result
file it replaces (the committed one), a held-out PSNR lower by more than --tolerance dB, or a
coverage lower by more than 0.01, fails the run (exit status 1) and says which; the .md says
whether the held-out PSNR reaches --target dB.
Needs no shared data; about 2-3 minutes a run on 2 cores.

    python benchmarks/bench_demo.py [--runs 1] [--tolerance 1.0] [--target 25] [--name demo] [--set KEY=VALUE ...]
    python benchmarks/bench_demo.py --steps 300 --against c330ed1 --name demo_identity
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import OUT, REPO, Revision, commit, machine, write_result

KEYS = {  # report key: (method, metric)
    "psnr": ("model", "psnr"), "ssim": ("model", "ssim"), "psnr_common": ("model", "psnr_common"),
    "model_depth_l1_common_m": ("model", "depth_l1_common"), "mesh_depth_l1_common_m": ("mesh", "depth_l1_common"),
    "sensor_depth_l1_common_m": ("sensor", "depth_l1_common"), "tsdf_depth_l1_common_m": ("tsdf", "depth_l1_common"),
    "common_share": ("model", "common_share"), "mesh_coverage": ("mesh", "coverage"),
    "tsdf_coverage": ("tsdf", "coverage"), "mesh_depth_l1_hits_m": ("mesh", "depth_l1_hits"),
    "tsdf_depth_l1_hits_m": ("tsdf", "depth_l1_hits"), "tsdf_psnr_hits": ("tsdf", "psnr_hits"),
    "mesh_psnr_common": ("mesh", "psnr_common"), "tsdf_psnr_common": ("tsdf", "psnr_common"),
    "mesh_ssim": ("mesh", "ssim"), "tsdf_ssim": ("tsdf", "ssim"),
    "model_only_share": ("model", "only_share"), "within_3_only": ("model", "within_3_only"),
}


def run_demo(out: Path, settings=(), revision: Revision | None = None) -> dict:
    """One `open3d-pnerf demo` into `out` (settings: its options, e.g. --set KEY=VALUE), today's or
    the `revision`'s; its numbers (KEYS, ATE, training, wall time; today's also per held-out frame)."""
    args = ["-m", "open3d_pnerf.cli", "--quiet", "demo", "--out", str(out), *settings]
    t0 = time.perf_counter()
    if revision is None:
        subprocess.run([sys.executable, *args], check=True, stdout=subprocess.DEVNULL, cwd=REPO)
    else:
        revision.python(args, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    report = json.loads((out / "report.json").read_text())
    scores = report["scores"]
    row = {key: scores[m][k] for key, (m, k) in KEYS.items() if k in scores.get(m, {})}
    row.update({f"{m}.{k}": v for m, table in scores.items() for k, v in table.items()})  # every score, for --against
    return {**row, "ate_rmse_m": report["ate_rmse_m"], "train_s": report["training"]["seconds"],
            "steps": report["training"]["steps"], "wall_s": round(wall, 1),
            **(heldout_frames(out) if revision is None else {})}


def heldout_frames(folder: Path) -> dict:
    """For each held-out frame i of the demo saved in `folder`, at the training resolution:
    psnr_frame_<i> (dB), seen_frame_<i> (the share of its pixels whose surface point, at the
    sensor's depth or else the model's, projects inside some training frame's image; occlusion is
    not counted) and psnr_unseen_frame_<i> (dB, on the others; None when there are none); and
    psnr_seen (dB): the held-out PSNR on the seen pixels of every held-out frame."""
    from open3d_pnerf import Reconstruction
    from open3d_pnerf.camera import backproject, project
    from open3d_pnerf.data import load_sample
    from open3d_pnerf.evaluation import heldout_views, psnr

    recon = Reconstruction.load(folder)
    seq = load_sample()
    scaled = seq.scaled_by(recon.config.image_scale)
    K, (h, w) = scaled.K, scaled.image_size
    out, seen_colors = {}, []
    for view in heldout_views(recon, seq):
        i = view["index"]
        depth = np.where(view["depth"] > 0, view["depth"], view["model"]["depth"]).astype(np.float32)
        points, pixels = backproject(depth, K, recon.poses[i])
        inside = np.zeros(len(points), bool)
        for j in recon.train_indices:
            world_to_camera = np.linalg.inv(recon.poses[j])
            local = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
            u, v = project(K, local)
            inside |= (local[:, 2] > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        seen = np.zeros(h * w, bool)
        seen[pixels[inside]] = True
        seen = seen.reshape(h, w)
        rendered, color = view["model"]["color"], view["color"]
        out[f"psnr_frame_{i}"] = psnr(rendered, color)
        out[f"seen_frame_{i}"] = float(seen.mean())
        out[f"psnr_unseen_frame_{i}"] = psnr(rendered, color, ~seen) if (~seen).any() else None
        seen_colors.append((rendered[seen], color[seen]))
    out["psnr_seen"] = psnr(*(np.concatenate(c) for c in zip(*seen_colors)))
    return out


def mean(key: str, runs: list[dict]) -> float:
    return float(np.mean([r[key] for r in runs]))


def regressions(runs: list[dict], before: dict | None, tolerance: float) -> list[str]:
    """What got worse against the committed result `before` (None: nothing to compare)."""
    out = []
    if before:
        if mean("psnr", runs) < mean("psnr", before["runs"]) - tolerance:
            out.append(f"held-out PSNR {mean('psnr', runs):.2f} dB, was {mean('psnr', before['runs']):.2f} dB "
                       f"(commit {before['meta']['commit']})")
        if mean("mesh_coverage", runs) < mean("mesh_coverage", before["runs"]) - 0.01:
            out.append(f"mesh coverage {mean('mesh_coverage', runs):.3f}, was {mean('mesh_coverage', before['runs']):.3f}")
    return out


def markdown(result: dict) -> str:
    runs, meta = result["runs"], result["meta"]
    rows = [("held-out PSNR (dB)", "psnr", 1, ".2f"), ("held-out SSIM", "ssim", 1, ".3f"),
            ("PSNR on common pixels (dB)", "psnr_common", 1, ".2f"),
            ("depth L1 on common pixels: model (mm)", "model_depth_l1_common_m", 1000, ".1f"),
            ("  exported mesh (mm)", "mesh_depth_l1_common_m", 1000, ".1f"),
            ("  sensor alone (mm)", "sensor_depth_l1_common_m", 1000, ".1f"),
            ("  TSDF, same threshold (mm)", "tsdf_depth_l1_common_m", 1000, ".1f"),
            ("common pixels (share of sensor pixels)", "common_share", 1, ".3f"),
            ("depth L1 on its hits: mesh / TSDF (mm)", ("mesh_depth_l1_hits_m", "tsdf_depth_l1_hits_m"), 1000, ".1f"),
            ("coverage: mesh / TSDF", ("mesh_coverage", "tsdf_coverage"), 1, ".3f"),
            ("TSDF PSNR on its hits (dB)", "tsdf_psnr_hits", 1, ".2f"),
            ("colour PSNR on common pixels: mesh / TSDF (dB)", ("mesh_psnr_common", "tsdf_psnr_common"), 1, ".2f"),
            ("colour SSIM, whole frame: mesh / TSDF", ("mesh_ssim", "tsdf_ssim"), 1, ".3f"),
            ("pixels only the model covers (share)", "model_only_share", 1, ".3f"),
            ("errors within the 99.7% interval there", "within_3_only", 1, ".3f"),
            ("tracking ATE RMSE (mm)", "ate_rmse_m", 1000, ".1f"), ("training (s)", "train_s", 1, ".0f"),
            ("training steps", "steps", 1, ".0f"), ("demo wall time (s)", "wall_s", 1, ".0f")]
    settings = "".join(f" --set {kv}" for kv in meta.get("settings", []))
    if meta.get("steps"):
        settings += f" --max-steps {meta['steps']} --set time_budget_s=null"
    lines = [f"`open3d-pnerf demo{settings}` (bundled TUM sample, tracked poses, `fast` preset), {len(runs)} run(s) at "
             f"commit {meta['commit']}; {meta['machine']}.", "",
             "| | " + " | ".join(f"run {i + 1}" for i in range(len(runs))) + " |", "|" + " --- |" * (len(runs) + 1)]
    frames = sorted(int(k.rsplit("_", 1)[1]) for k in runs[0] if k.startswith("psnr_frame_"))
    rows[1:1] = [(f"  frame {i}: PSNR (dB) / share of its pixels inside a training view / PSNR on the others (dB)",
                  (f"psnr_frame_{i}", f"seen_frame_{i}", f"psnr_unseen_frame_{i}"), 1, ".2f") for i in frames]
    rows.insert(1 + len(frames), ("  on the pixels inside a training view (dB)", "psnr_seen", 1, ".2f"))
    for label, keys, factor, fmt in rows:
        keys = keys if isinstance(keys, tuple) else (keys,)
        cells = [" / ".join(format(factor * r[k], fmt) if r.get(k) is not None else "-" for k in keys) for r in runs]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", f"Target: held-out PSNR at least {meta['target']:g} dB: "
              + ("met." if mean("psnr", runs) >= meta["target"] else f"missed ({mean('psnr', runs):.2f} dB)."),
              "Regressions against the previous result file: " + ("; ".join(result["regressions"]) or "none.")]
    for k, c in enumerate(result.get("identity", [])):
        lines.append(f"Run {k + 1} against {meta['against']}: {c['compared']} numbers compared (every held-out score "
                     "of every method, tracking ATE, steps), " + ("all identical." if c["identical"] else
                     f"{len(c['differ'])} differ: {c['differ']}"))
    return "\n".join(lines) + "\n"


def compare_runs(runs: list[dict], old: list[dict]) -> list[dict]:
    """Per run, today's numbers against the earlier revision's: how many were compared, the keys that
    differ (with both values), and whether every one is equal (wall time and training seconds excepted)."""
    out = []
    for new, was in zip(runs, old):
        keys = [k for k in was if k in new and k not in ("wall_s", "train_s")]
        differ = {k: [was[k], new[k]] for k in keys if was[k] != new[k]}
        out.append({"compared": len(keys), "differ": differ, "identical": not differ})
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--tolerance", type=float, default=1.0, help="allowed held-out PSNR drop (dB)")
    ap.add_argument("--target", type=float, default=25.0, help="held-out PSNR the demo should reach (dB)")
    ap.add_argument("--name", default="demo")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config setting passed to the demo (repeatable), e.g. objective.coarse_color=true")
    ap.add_argument("--steps", type=int, help="train for this many steps, without a time budget (reproducible)")
    ap.add_argument("--against", metavar="REV", help="also run the demo at this earlier git revision; compare")
    args = ap.parse_args()
    path = OUT / f"{args.name}.json"
    before = json.loads(path.read_text()) if path.is_file() else None
    settings = [f"--set={kv}" for kv in args.set]
    if args.steps:
        settings += ["--max-steps", str(args.steps), "--set=time_budget_s=null"]
    runs, old = [], []
    with (Revision(args.against) if args.against else contextlib.nullcontext()) as revision:
        for i in range(args.runs):
            with tempfile.TemporaryDirectory() as tmp:
                runs.append(run_demo(Path(tmp) / "demo", settings))
                if revision is not None:
                    old.append(run_demo(Path(tmp) / "against", settings, revision))
            print(f"run {i + 1}: psnr {runs[-1]['psnr']:.4f}, steps {runs[-1]['steps']}"
                  + (f"; at {args.against}: psnr {old[-1]['psnr']:.4f}" if old else ""), flush=True)
    meta = {"commit": commit(), "machine": machine(), "target": args.target, "settings": args.set,
            "steps": args.steps, "against": args.against}
    result = {"meta": meta, "runs": runs, "regressions": regressions(runs, before, args.tolerance)}
    if old:
        result.update(against_runs=old, identity=compare_runs(runs, old))
    write_result(args.name, result, markdown(result))
    sys.exit(1 if result["regressions"] or not all(c["identical"] for c in result.get("identity", [])) else 0)


if __name__ == "__main__":
    main()
