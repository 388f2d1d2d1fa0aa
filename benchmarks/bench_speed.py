"""How fast does it train and render on this CPU? Where a training step and a render spend their time,
and the fused hash-grid kernel against the pure-PyTorch path, side by side in one run.

TUM fr1/xyz from ../shared/data (the bundled sample without it), every 4th frame held out, poses
from our tracking, the default config (`fast` preset, hash grid 8 levels 16..2048, 512 rays x 40
samples a step) unless stated. Sections, all in this one run, on `--threads` torch threads:

1. throughput: training samples/s of each path (`pytorch`: the pure-PyTorch hash grid, all
   float32, what the library was; `kernel`: the fused CPU kernel; `kernel+bf16`: and bfloat16 MLP
   products), the paths taking turns in `--rounds` blocks; a 640x480 render's seconds; as ratios;
2. profile: one training step and one 320x240 render per stage (torch.profiler, the library's
   `pnerf.*` regions and the costliest operators), per path;
3. agreement: `pytorch` and `kernel` trained `--agree-steps` steps from the same initial weights
   and seed: the largest parameter and loss differences (floating-point summation order differs);
4. bf16 check: `kernel` and `kernel+bf16` trained `--equal-steps` steps, `--seeds` seeds: held-out
   PSNR, SSIM and depth error, to show whether bfloat16 costs quality;
5. export: training and export seconds of a `fast` reconstruct() with the default config.

    python benchmarks/bench_speed.py [--threads 2] [--seeds 2] [--quick]
    python benchmarks/bench_speed.py --against REV --name speed_against_REV

Writes benchmarks/results/<name>.json and <name>.md (name: speed). --against REV measures only
this tree's training throughput and render time against the library at git revision REV (fresh
processes taking turns), e.g. before and after a change of the kernel.
"""

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import OUT, PATHS, Revision, commit

import open3d_pnerf as pn
from open3d_pnerf.batches import RayBatcher
from open3d_pnerf.config import overrides as config_overrides
from open3d_pnerf.evaluation import heldout_scores
from open3d_pnerf.fields import native
from open3d_pnerf.model import build_model
from open3d_pnerf.reconstruction import Reconstruction
from open3d_pnerf.scene import training_box
from open3d_pnerf.stages import split_frames
from open3d_pnerf.training import Trainer

TUM = PATHS["tum"]
SPEED_PATHS = {  # name -> config overrides
    "pytorch": {"hashgrid.backend": "torch", "runtime.bf16_mlp": False},  # the pure-PyTorch path, all float32
    "kernel": {"hashgrid.backend": "kernel", "runtime.bf16_mlp": False},  # the fused hash-grid kernel
    "kernel+bf16": {"hashgrid.backend": "kernel", "runtime.bf16_mlp": True},  # and bfloat16 MLP products
}


def config(path: str, **overrides) -> pn.ReconstructionConfig:
    return pn.ReconstructionConfig.preset("fast", holdout_every=4, progress=False, **{**SPEED_PATHS[path], **overrides})


def trainer_for(seq, poses, cfg) -> Trainer:
    """A Trainer on the training frames, built by the pipeline's own stages."""
    train, _ = split_frames(len(seq), cfg.holdout_every, cfg.train_views)
    train_seq = seq.select(train).scaled_by(cfg.image_scale)
    targets = cfg.targets.build(train_seq, poses[train], np.zeros((len(train), 6, 6)), progress=False)
    model = build_model(cfg, training_box(train_seq, targets, poses[train]), poses[train], train_seq.K,
                        np.zeros((len(train), 6, 6)))
    return Trainer(model, RayBatcher(train_seq, targets, model.device, cfg.seed), cfg)


def reconstruction_of(trainer: Trainer, seq, poses) -> Reconstruction:
    cfg = trainer.config
    train, hold = split_frames(len(seq), cfg.holdout_every)
    return Reconstruction(trainer.model, cfg, poses, np.zeros((len(seq), 6, 6)), trainer.batcher.sequence.intrinsic,
                          train, hold)


AGAINST_SCRIPT = """
import json, sys, time
import numpy as np, torch
import open3d_pnerf as pn
from open3d_pnerf.camera import scale_intrinsic
from open3d_pnerf.pipeline import run

args = json.loads(sys.argv[1])
torch.set_num_threads(args["threads"])
seq = pn.load_sequence(args["data"]) if args["data"] != "sample" else pn.load_sample()
poses, covs = np.load(args["poses"]), np.load(args["covariances"])
cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, progress=False, time_budget_s=None, max_steps=args["steps"],
                                     **args["overrides"])
recon = run(seq, cfg, poses, covs, export=False)
t0 = time.perf_counter()
recon.render(poses[1], scale_intrinsic(seq.intrinsic, 640 / seq.intrinsic.width))
print("RESULT " + json.dumps({"samples_per_s": recon.stats["training"]["samples_per_s"],
                              "render_640x480_s": round(time.perf_counter() - t0, 3)}))
"""


def against(revision: str, args: dict, rounds: int) -> dict:
    """Training samples/s (a `fast` run of args["steps"] steps with the default config, no export)
    and a 640x480 render's seconds of this tree and of the library at `revision`, each in a fresh
    subprocess, taking turns for `rounds` rounds (the machine's speed swings hit both alike);
    medians, and the median over rounds of the paired ratios (this tree's speed / revision's)."""
    runs: dict[str, list] = {"this tree": [], revision: []}
    with Revision(revision) as previous:
        args = {**args, "poses": previous.save("poses", args.pop("poses")),
                "covariances": previous.save("covariances", args.pop("covariances"))}
        for _ in range(rounds):
            runs[revision].append(previous.run(AGAINST_SCRIPT, args))
            done = subprocess.run([sys.executable, "-c", AGAINST_SCRIPT, json.dumps(args)], capture_output=True,
                                  text=True, cwd=Path(__file__).resolve().parents[1])
            line = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
            if done.returncode != 0 or not line:
                raise RuntimeError(f"this tree failed: {done.stderr[-2000:]}")
            runs["this tree"].append(json.loads(line[0][len("RESULT "):]))
            print({name: r[-1] for name, r in runs.items()}, flush=True)
    median = {name: {k: float(np.median([r[k] for r in rs])) for k in ("samples_per_s", "render_640x480_s")}
              for name, rs in runs.items()}
    pairs = list(zip(runs["this tree"], runs[revision]))
    return {"revision": revision, "steps": args["steps"], "overrides": args["overrides"], "rounds": runs, "median": median,
            "training_ratio": round(float(np.median([a["samples_per_s"] / b["samples_per_s"] for a, b in pairs])), 3),
            "render_ratio": round(float(np.median([b["render_640x480_s"] / a["render_640x480_s"] for a, b in pairs])), 3)}


def profile(trainer: Trainer, recon: Reconstruction, pose, steps: int) -> dict:
    """ms per step (and per 320x240 render) in each pnerf.* region, and the costliest operators."""
    from torch.profiler import ProfilerActivity, profile as torch_profile

    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            trainer.train_step()
    step = _regions(prof, steps)
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        recon.render(pose)
    return {"train_step_ms": step, "render_320x240_ms": _regions(prof, 1)}


def _regions(prof, n: int) -> dict:
    events = prof.key_averages()
    regions = {e.key: round(e.cpu_time_total / 1000 / n, 2) for e in events if e.key.startswith("pnerf.")}
    ops = sorted((e for e in events if not e.key.startswith("pnerf.") and not e.key.startswith("ProfilerStep")),
                 key=lambda e: -e.self_cpu_time_total)[:10]
    return {"regions": dict(sorted(regions.items(), key=lambda kv: -kv[1])),
            "top_ops_self_ms": {e.key: round(e.self_cpu_time_total / 1000 / n, 2) for e in ops}}


def throughput(trainers: dict, rounds: int, steps: int) -> dict:
    """Training ms per step and samples/s of each trainer: `rounds` blocks of `steps` steps each,
    the paths taking turns (so that the machine's speed swings hit all alike); medians."""
    times = {name: [] for name in trainers}
    for trainer in trainers.values():
        for _ in range(3):  # warm-up
            trainer.train_step()
    for _ in range(rounds):
        for name, trainer in trainers.items():
            seen, t0 = trainer.samples_seen, time.perf_counter()
            for _ in range(steps):
                trainer.train_step()
            times[name].append(((time.perf_counter() - t0) / steps, (trainer.samples_seen - seen) / steps))
    out = {}
    for name, runs in times.items():
        seconds = float(np.median([t for t, _ in runs]))
        out[name] = {"ms_per_step": round(1000 * seconds, 1), "samples_per_s": round(runs[0][1] / seconds),
                     "ms_per_step_each_round": [round(1000 * t, 1) for t, _ in runs]}
    return out


def render_seconds(recons: dict, pose, intrinsic, rounds: int = 3) -> dict:
    """Seconds of one render per path, the paths taking turns; medians."""
    times = {name: [] for name in recons}
    for _ in range(rounds):
        for name, recon in recons.items():
            t0 = time.perf_counter()
            recon.render(pose, intrinsic)
            times[name].append(time.perf_counter() - t0)
    return {name: round(float(np.median(t)), 3) for name, t in times.items()}


def agreement(seq, poses, steps: int) -> dict:
    """Train the pure-PyTorch path and the kernel (both float32) from the same weights and seed:
    their losses step by step, and their renders of a held-out view after the last step. (Single
    parameters are no measure: Adam turns rounding on near-zero gradients into whole steps.)"""
    runs = {}
    for path in ("pytorch", "kernel"):
        trainer = trainer_for(seq, poses, config(path, max_steps=steps, time_budget_s=None))
        losses = [trainer.train_step()["loss"] for _ in range(steps)]
        runs[path] = (np.array(losses), reconstruction_of(trainer, seq, poses).render(poses[0]))
    (loss_t, view_t), (loss_k, view_k) = runs["pytorch"], runs["kernel"]
    return {"steps": steps, "max_rel_loss_diff": float(np.max(np.abs(loss_t - loss_k) / np.abs(loss_t))),
            "max_abs_color_diff": float(np.abs(view_t["color"] - view_k["color"]).max()),
            "max_abs_depth_diff_m": float(np.abs(view_t["depth"] - view_k["depth"]).max())}


def reconstruct_timed(seq, poses, covs, cfg) -> dict:
    t0 = time.perf_counter()
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    wall = time.perf_counter() - t0
    scores = heldout_scores(recon, seq)["model"]
    t = recon.stats["timings"]
    train_s = t["total_s"] - t["export_s"] - t["tracking_s"] - t["targets_s"]
    return {"psnr": round(scores["psnr"], 3), "ssim": round(scores["ssim"], 4),
            "depth_l1_mm": round(1000 * scores.get("depth_l1", float("nan")), 1),
            "steps": recon.stats["training"]["steps"], "training_s": round(train_s, 1),
            "export_s": t["export_s"], "export_share_of_training": round(t["export_s"] / train_s, 3),
            "wall_s": round(wall, 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="torch threads (run alone on the machine)")
    ap.add_argument("--rounds", type=int, default=6, help="timed blocks per path (the paths take turns)")
    ap.add_argument("--steps", type=int, default=8, help="training steps per timed block")
    ap.add_argument("--agree-steps", type=int, default=20, help="steps of the agreement check")
    ap.add_argument("--equal-steps", type=int, default=800, help="steps of the bf16 check (0: skip it)")
    ap.add_argument("--seeds", type=int, default=2, help="seeds of the bf16 check")
    ap.add_argument("--against", metavar="REV",
                    help="only this: training and render speed of this tree against the library at git revision REV "
                    "(fresh processes taking turns, --rounds rounds of --against-steps steps); writes <name>.json/md")
    ap.add_argument("--against-steps", type=int, default=500, help="training steps of each --against run")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="with --against: a config override of both sides' runs, e.g. field=grid (repeatable)")
    ap.add_argument("--name", default="speed", help="stem of the result files in benchmarks/results/")
    ap.add_argument("--quick", action="store_true", help="a smoke test of the script: tiny everything")
    args = ap.parse_args()
    export_budget = 150.0
    if args.quick:
        args.rounds, args.steps, args.agree_steps, args.equal_steps, args.seeds = 1, 2, 2, 5, 1
        export_budget = 10.0
    torch.set_num_threads(args.threads)
    if not native.available():
        sys.exit("the fused kernel cannot be built here (no C++ compiler?): nothing to compare")
    t_start = time.perf_counter()
    seq = pn.load_sequence(TUM) if TUM.is_dir() else pn.load_sample()
    trajectory = pn.ReconstructionConfig().tracking.track(seq, progress=False)
    poses, covs = trajectory.poses, trajectory.covariances
    report = {"machine": {"platform": platform.platform(), "processor": platform.processor(), "threads": args.threads,
                          "torch": torch.__version__}, "commit": commit(),
              "data": f"{seq.name}, {len(seq)} frames, every 4th held out, 320x240 training images",
              "paths": SPEED_PATHS, "default_path": {
                  k: pn.ReconstructionConfig().to_dict()[k.split(".")[0]][k.split(".")[1]] for k in SPEED_PATHS["pytorch"]}}
    if args.against:
        report["against"] = against(args.against, {"data": str(TUM) if TUM.is_dir() else "sample",
                                                   "threads": args.threads, "steps": args.against_steps,
                                                   "overrides": config_overrides(args.set), "poses": poses,
                                                   "covariances": covs}, args.rounds)
        report["total_minutes"] = round((time.perf_counter() - t_start) / 60, 1)
        OUT.mkdir(exist_ok=True)
        (OUT / f"{args.name}.json").write_text(json.dumps(report, indent=1))
        (OUT / f"{args.name}.md").write_text(against_markdown(report))
        print(against_markdown(report))
        return
    trainers = {path: trainer_for(seq, poses, config(path)) for path in SPEED_PATHS}
    report["throughput"] = throughput(trainers, args.rounds, args.steps)
    recons = {path: reconstruction_of(t, seq, poses) for path, t in trainers.items()}
    full = pn.camera.scale_intrinsic(seq.intrinsic, 640 / seq.intrinsic.width)
    report["render_640x480_s"] = render_seconds(recons, poses[1], full)
    print("throughput:", report["throughput"], flush=True)
    report["profile"] = {path: profile(trainers[path], recons[path], poses[1], 5) for path in SPEED_PATHS}
    report["ratios"] = {path: {"training_to_pytorch_path": round(report["throughput"][path]["samples_per_s"]
                                                                 / report["throughput"]["pytorch"]["samples_per_s"], 2),
                               "render_to_pytorch_path": round(report["render_640x480_s"]["pytorch"]
                                                               / report["render_640x480_s"][path], 2)}
                        for path in SPEED_PATHS}
    del trainers, recons
    report["agreement"] = agreement(seq, poses, args.agree_steps)
    print("agreement:", report["agreement"], flush=True)
    if args.equal_steps:
        report["bf16_equal_steps"] = {
            f"{path}_seed{seed}": reconstruct_timed(seq, poses, covs, config(path, max_steps=args.equal_steps,
                                                                             time_budget_s=None, seed=seed))
            for seed in range(args.seeds) for path in ("kernel", "kernel+bf16")}
        print("bf16 check:", report["bf16_equal_steps"], flush=True)
    report["export"] = reconstruct_timed(seq, poses, covs, pn.ReconstructionConfig.preset(
        "fast", holdout_every=4, progress=False, time_budget_s=export_budget))
    report["total_minutes"] = round((time.perf_counter() - t_start) / 60, 1)
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    (OUT / f"{args.name}.md").write_text(markdown(report))
    print(markdown(report))


def against_markdown(r: dict) -> str:
    a, name = r["against"], r["against"]["revision"]
    m = a["median"]
    lines = [f"# Speed against {name} (`python benchmarks/bench_speed.py --against {name} --name ...`)", "",
             f"Data: {r['data']}; {r['machine']['threads']} threads; {r['total_minutes']} min in all. Each run: a fresh "
             f"process, the default config (`fast`){''.join(f', {k}={v}' for k, v in a['overrides'].items())}, "
             f"{a['steps']} training steps without export, then a 640x480 render; "
             f"this tree and {name} take turns, {len(a['rounds'][name])} rounds; medians.", "",
             "| library | training samples/s | 640x480 render (s) | samples/s of each round |", "| --- | --- | --- | --- |"]
    for who in ("this tree", name):
        lines.append(f"| {who} | {m[who]['samples_per_s']:,.0f} | {m[who]['render_640x480_s']:.3f} | "
                     + ", ".join(f"{x['samples_per_s']:,.0f}" for x in a["rounds"][who]) + " |")
    lines += ["", f"Median over the rounds of this tree's speed over {name}'s in the same round: training "
              f"{a['training_ratio']} x, 640x480 render {a['render_ratio']} x."]
    return "\n".join(lines) + "\n"


def markdown(r: dict) -> str:
    t, ratio, render = r["throughput"], r["ratios"], r["render_640x480_s"]
    lines = ["# Speed (`python benchmarks/bench_speed.py`)", "", f"Data: {r['data']}; {r['machine']['threads']} "
             f"threads; {r['total_minutes']} min in all; commit {r.get('commit')}. Paths: "
             + "; ".join(f"`{name}` = {overrides}" for name, overrides in r["paths"].items())
             + f"; the default config is {r['default_path']}.", "",
             "| path | training samples/s | x `pytorch` path | 640x480 render (s) | x `pytorch` path |",
             "| --- | --- | --- | --- | --- |"]
    lines += [f"| {p} | {t[p]['samples_per_s']:,} | {ratio[p]['training_to_pytorch_path']} | {render[p]} | "
              f"{ratio[p]['render_to_pytorch_path']} |" for p in r["paths"]]
    lines += ["", "| region (ms per training step, profiled) | " + " | ".join(r["paths"]) + " |",
              "| --- |" + " --- |" * len(r["paths"])]
    regions = dict.fromkeys(k for p in r["paths"] for k in r["profile"][p]["train_step_ms"]["regions"])
    for k in regions:
        lines.append(f"| {k} | " + " | ".join(str(r["profile"][p]["train_step_ms"]["regions"].get(k, "-"))
                                                for p in r["paths"]) + " |")
    a = r["agreement"]
    lines += ["", f"Agreement of the kernel with the pure-PyTorch path, {a['steps']} float32 steps from the same "
              f"weights and seed: losses within {a['max_rel_loss_diff']:.1e} (relative) at every step; renders of a "
              f"held-out view after them within {a['max_abs_color_diff']:.1e} in colour and "
              f"{1000 * a['max_abs_depth_diff_m']:.2g} mm in depth.", ""]
    for key, title in (("bf16_equal_steps", "bfloat16 MLP products at equal steps"),):
        if key in r:
            lines += [f"{title}:", "", "| run | held-out PSNR (dB) | SSIM | depth L1 (mm) | steps | training s |",
                      "| --- | --- | --- | --- | --- | --- |"]
            lines += [f"| {k} | {q['psnr']} | {q['ssim']} | {q['depth_l1_mm']} | {q['steps']} | {q['training_s']} |"
                      for k, q in r[key].items()]
            lines.append("")
    e = r["export"]
    lines.append(f"`fast` reconstruct with the default config: {e['steps']} steps, training {e['training_s']} s, export "
                 f"{e['export_s']} s ({100 * e['export_share_of_training']:.0f}% of training); held-out PSNR "
                 f"{e['psnr']} dB.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
