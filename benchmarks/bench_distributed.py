"""Issue-8 benchmark: training samples/s of reconstruct() on 1 rank and on 2 ranks (torchrun, gloo).

The bundled sample (11 frames), the "fast" preset (default hashgrid field, 5.9 M parameters, 512 rays a
step) with a fixed training time; every rank tracks and builds depth targets itself. Each
rank runs one thread (OMP_NUM_THREADS=1). Measures training samples/s (the whole batch's
samples over rank 0's training time), seconds per step, the time rank 0 spends in the
per-step gradient sum, and the tracking and depth-target stages on every rank.

    python benchmarks/bench_distributed.py [--seconds 40]

Writes benchmarks/results/distributed.json.
"""

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

import torch
from common import OUT



def worker(out: Path, seconds: float) -> None:
    """One rank: reconstruct the sample, time the gradient sums, write rank{RANK}.json."""
    import open3d_pnerf as pn
    from open3d_pnerf import distributed

    spent = {"seconds": 0.0, "calls": 0}
    real_sum = distributed.DistributedContext.sum_

    def timed_sum(self, tensors, what):
        start = time.perf_counter()
        real_sum(self, tensors, what)
        if what.startswith("the gradient sum"):
            spent["seconds"] += time.perf_counter() - start
            spent["calls"] += 1

    distributed.DistributedContext.sum_ = timed_sum
    config = pn.ReconstructionConfig.preset("fast", time_budget_s=seconds, max_steps=10**6, progress=False)
    recon = pn.reconstruct(pn.load_sample(), config)
    rank = int(os.environ.get("RANK", 0))
    training = recon.stats["training"]
    (out / f"rank{rank}.json").write_text(json.dumps({
        "training": training, "timings": recon.stats.get("timings", {}),
        "seconds_per_step": training["seconds"] / training["steps"],
        "gradient_sum_s_per_step": spent["seconds"] / max(spent["calls"], 1),
        "parameters": sum(p.numel() for p in recon.field.parameters()),
    }))


def launch(ranks: int, out: Path, seconds: float) -> dict:
    """Run `ranks` ranks (plain python for 1, torchrun on loopback for more); rank 0's result."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}
    script = [str(Path(__file__).resolve()), "--worker", str(out), "--seconds", str(seconds)]
    if ranks == 1:
        cmd = [sys.executable, *script]
    else:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(ranks),
               "--master-addr", "127.0.0.1", "--master-port", str(port), *script]
    start = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    results = [json.loads((out / f"rank{r}.json").read_text()) for r in range(ranks)]
    r0 = results[0]
    return {
        "ranks": ranks,
        "samples_per_s": r0["training"]["samples_per_s"],
        "steps": r0["training"]["steps"],
        "seconds_per_step": round(r0["seconds_per_step"], 4),
        "gradient_sum_s_per_step": round(r0["gradient_sum_s_per_step"], 4) if ranks > 1 else 0.0,
        "tracking_s_per_rank": [r["timings"].get("tracking_s") for r in results],
        "targets_s_per_rank": [r["timings"].get("targets_s") for r in results],
        "wall_s": round(wall, 1),
        "parameters": r0["parameters"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="training seconds per run")
    ap.add_argument("--note", default="machine otherwise idle", help="what else ran on the machine, for the record")
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(args.worker, args.seconds)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bench-distributed-") as tmp:
        runs = [launch(n, Path(tmp) / f"ranks{n}", args.seconds) for n in (1, 2)]
    one, two = runs
    report = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "threads_per_rank": 1, "note": args.note},
        "setup": "bundled sample (11 frames, 160x120 training images), fast preset (default hashgrid field, 512 rays a "
                 f"step, 40 samples a ray), {args.seconds:g} s of training per run, gloo over loopback",
        "runs": {str(r["ranks"]): r for r in runs},
        "speedup_2_over_1": round(two["samples_per_s"] / one["samples_per_s"], 3),
        "step_overhead_s": round(two["seconds_per_step"] - one["seconds_per_step"] / 2, 4),
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "distributed.json").write_text(json.dumps(report, indent=1))
    print("| ranks | samples/s | s/step | gradient sum s/step | tracking s (per rank) | targets s (per rank) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in runs:
        print(f"| {r['ranks']} | {r['samples_per_s']:.0f} | {r['seconds_per_step']:.3f} | "
              f"{r['gradient_sum_s_per_step']:.3f} | {r['tracking_s_per_rank']} | {r['targets_s_per_rank']} |")
    print(f"speed-up {report['speedup_2_over_1']}x; overhead per step vs an ideal halving: "
          f"{report['step_overhead_s']:.3f} s; wrote {OUT / 'distributed.json'}")


if __name__ == "__main__":
    main()
