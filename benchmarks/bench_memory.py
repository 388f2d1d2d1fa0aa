"""Issue-6 benchmark: a long sequence in bounded memory.

Renders a synthetic 640x480 sequence of the room (open3d_pnerf.synthetic) to a temporary
Open3D/Redwood folder, loads it lazily with load_sequence and runs the whole
reconstruct() pipeline on it (tracking, depth targets, a short training, export), sampling
the process's resident memory (RSS) every 0.2 s. Reports peak RSS and time per frame of
each stage.

    python benchmarks/bench_memory.py [--frames 2000] [--steps 300] [--threads 1]

Writes benchmarks/results/memory.json (memory_<frames>.json for other sizes). Needs no
shared data. About 36 minutes at 2,000 frames on this 2-core machine (10 writing the frames,
5.5 tracking, 8 building depth targets, 1.5 training and export: results/memory.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import threading
import time
from pathlib import Path

from common import OUT



class RSSSampler(threading.Thread):
    """Samples this process's RSS (MB) from /proc every `period` seconds."""

    def __init__(self, period: float = 0.2):
        super().__init__(daemon=True)
        self.period, self.samples, self.running = period, [], True

    def run(self):
        while self.running:
            self.samples.append((time.perf_counter(), rss_mb()))
            time.sleep(self.period)

    def peak(self, start: float = 0.0, stop: float = float("inf")) -> float:
        return max((m for t, m in self.samples if start <= t <= stop), default=0.0)


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--steps", type=int, default=300, help="training steps")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    import open3d_pnerf as pn
    from open3d_pnerf.data import write_sequence
    from open3d_pnerf.synthetic import synthetic_sequence

    sampler = RSSSampler()
    sampler.start()
    marks = {"start": time.perf_counter()}
    with tempfile.TemporaryDirectory(prefix="pnerf-memory-") as tmp:
        data = synthetic_sequence(args.frames, 640, 480, seed=0)
        write_sequence(data.sequence, tmp, progress=True)
        marks["written"] = time.perf_counter()
        seq = pn.load_sequence(tmp)
        config = pn.ReconstructionConfig.preset("fast", max_steps=args.steps, time_budget_s=None, holdout_every=10,
                                                progress=True)
        recon = pn.reconstruct(seq, config)
        marks["done"] = time.perf_counter()
    sampler.running = False
    t = recon.stats["timings"]
    bounds = {"tracking": (0, t["tracking_s"]), "targets": (t["tracking_s"], t["tracking_s"] + t["targets_s"]),
              "training": (t["tracking_s"] + t["targets_s"], t["total_s"] - t["export_s"]),
              "export": (t["total_s"] - t["export_s"], t["total_s"])}
    t0 = marks["written"]
    n, n_train = len(seq), len(recon.train_indices)
    stages = {name: {"seconds": round(b - a, 1), "peak_rss_mb": round(sampler.peak(t0 + a, t0 + b))}
              for name, (a, b) in bounds.items()}
    stages["tracking"]["ms_per_frame"] = round(1000 * t["tracking_s"] / n)
    stages["targets"]["ms_per_frame"] = round(1000 * t["targets_s"] / n_train)
    report = {
        "machine": f"{platform.machine()} {platform.system()}, torch {torch.__version__}, {args.threads} thread(s)",
        "frames": n, "train_frames": n_train, "size": "640x480 (training at 320x240)", "steps": args.steps,
        "write_s_per_frame": round((marks["written"] - marks["start"]) / n, 3),
        "stages": stages, "peak_rss_mb": round(sampler.peak()), "total_s": round(marks["done"] - marks["start"]),
        "samples_per_s": round(recon.stats["training"]["samples_per_s"]),
    }
    OUT.mkdir(exist_ok=True)
    name = "memory.json" if args.frames == 2000 else f"memory_{args.frames}.json"
    (OUT / name).write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
