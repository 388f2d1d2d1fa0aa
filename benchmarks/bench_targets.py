"""Cost and statistics of the uncertain depth targets on the shared TUM fr1/xyz frames.

Poses and covariances from our tracking; targets at full (640x480) and half resolution.

    python benchmarks/bench_targets.py      # writes benchmarks/results/targets.json
"""

import json
import platform
import sys
import time
from pathlib import Path

import open3d_pnerf as pn

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TUM = SHARED / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz"
OUT = Path(__file__).resolve().parent / "results"


def main():
    if not TUM.is_dir():
        sys.exit(f"shared data not found: {TUM}")
    seq = pn.load_sequence(TUM)
    traj = pn.track(seq, progress=False)
    rows = {}
    for scale in (1.0, 0.5):
        s = seq.at_scale(scale)
        t = time.perf_counter()
        targets = pn.depth_targets(s, traj, progress=False)
        seconds = time.perf_counter() - t
        h, w = s.image_size
        rows[f"{w}x{h}"] = {"ms_per_frame": round(1000 * seconds / len(s), 1), **targets.summary()}
        print(f"{w}x{h}: {rows[f'{w}x{h}']}", flush=True)
    OUT.mkdir(exist_ok=True)
    report = {"dataset": f"TUM fr1/xyz, {len(seq)} frames, tracked poses + covariances", "neighbors": 2,
              "machine": platform.platform(), "results": rows}
    (OUT / "targets.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
