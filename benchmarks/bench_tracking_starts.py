"""Where the tracker's first start lands against its constant-velocity prediction: the figures
behind OdometryOptions.search_all_above_m / _deg applied to registrations (tracker._Run.try_candidates).

1. Sequences (TUM fr1/xyz and 7-Scenes 150-199 at 640x480, 7-Scenes every 10th frame's first 100
   frames), tracked without loop closures (the poses are then the tracker's chain): every frame
   i >= 2 re-registered from the chain's constant-velocity prediction, as the tracker's first
   start is. Per sequence: the odometry registrations the tracker made per frame, the largest
   landing (distance from the prediction) of the replayed registrations within 25 mm of the
   ground truth's step, and the landings of those further off.
2. Frame 87 (and frame 35) of 7-Scenes every 10th frame, frames 83-89 (31-37) tracked `--runs`
   times without loop closures, idle and with a thread beside it that keeps a core busy with
   matrix products: the frame's step error against the ground truth per run (the 25 mm bound of
   tests/test_tracking.py), and the landing and error of the constant-velocity start replayed on
   each run's chain (where it settles depends on the last bits of Open3D's multi-threaded sums,
   so the runs differ).

About 5 minutes; needs the shared data.

    python benchmarks/bench_tracking_starts.py [--runs 5]
"""

from __future__ import annotations

import argparse
import threading
import time
import warnings

import numpy as np
from bench_suite import PATHS, SHARED, machine, write_result

from open3d_pnerf.camera import motion
from open3d_pnerf.data import load_sequence
from open3d_pnerf.tracking import track
from open3d_pnerf.tracking.odometry import FrameRegistration, OdometryOptions
from open3d_pnerf.tracking.tracker import constant_velocity_pose

EVERY10 = SHARED / "7scenes_redkitchen" / "every10th_0-990"
SEQUENCES = {"tum_fr1_xyz": PATHS["tum"], "7scenes_150-199": PATHS["7scenes"], "7scenes_every10th": EVERY10}
WINDOWS = {87: 83, 35: 31}  # frame -> first frame of its 7-frame window (as in tests/test_tracking.py)
RIGHT_M = 0.025  # a step within this of the ground truth's is right


def step_error(poses: np.ndarray, gt: np.ndarray, i: int, step: np.ndarray | None = None) -> float:
    """Translation error (m) of frame i's step from frame i-1 (`step`, (4, 4) i-1 -> i camera, or
    the poses') against the ground truth's."""
    step = np.linalg.inv(poses[i]) @ poses[i - 1] if step is None else step
    return motion(np.linalg.inv(np.linalg.inv(gt[i]) @ gt[i - 1]) @ step)[0]


def replay(seq, poses: np.ndarray, frames) -> list[dict]:
    """The constant-velocity start of each frame i in `frames` on the chain `poses`: its landing
    (m, deg from the prediction), its step error (m) and whether it passed the checks."""
    registrar, options, rows = FrameRegistration(seq), OdometryOptions(), []
    for i in frames:
        expected = np.linalg.inv(constant_velocity_pose(poses, i)) @ poses[i - 1]
        result = registrar.register(i - 1, i, expected, options, "constant velocity", expected)
        landed_m, landed_deg = motion(np.linalg.inv(expected) @ result.transformation)
        rows.append({"frame": int(i), "passed": bool(result.success), "landed_mm": round(1e3 * landed_m, 1),
                     "landed_deg": round(landed_deg, 2),
                     "error_mm": round(1e3 * step_error(poses, seq.gt_poses, i, result.transformation), 1)})
    return rows


def sequences() -> dict:
    out = {}
    for name, path in SEQUENCES.items():
        seq = load_sequence(path)
        if name == "7scenes_every10th":
            seq = seq.select(range(100))
        traj = track(seq, loop_closure=False, progress=False)
        rows = [r for r in replay(seq, traj.poses, range(2, len(seq))) if r["passed"]]
        right = [r for r in rows if r["error_mm"] <= 1e3 * RIGHT_M]
        odometry = sum(e.kind == "odometry" for e in traj.edges)
        out[name] = {"frames": len(seq), "odometry registrations per frame": round(odometry / (len(seq) - 1), 3),
                     "largest landing of the right ones (mm, deg)": [max(r["landed_mm"] for r in right),
                                                                     max(r["landed_deg"] for r in right)],
                     "wrong ones": [r for r in rows if r["error_mm"] > 1e3 * RIGHT_M]}
        print(name, out[name], flush=True)
    return out


def busy(stop: threading.Event) -> None:
    """Matrix products until `stop` is set (a core kept busy beside the tracker)."""
    a = np.random.default_rng(0).random((400, 400))
    while not stop.is_set():
        a @ a


def windows(runs: int) -> dict:
    out = {}
    for load in ("idle", "busy"):
        stop = threading.Event()
        if load == "busy":
            threading.Thread(target=busy, args=(stop,), daemon=True).start()
        for frame, first in WINDOWS.items():
            seq = load_sequence(EVERY10).select(range(first, first + 7))
            k, rows = frame - first, []
            for _ in range(runs):
                traj = track(seq, loop_closure=False, progress=False)
                rows.append({"kept_error_mm": round(1e3 * step_error(traj.poses, seq.gt_poses, k), 1),
                             "constant velocity start": replay(seq, traj.poses, [k])[0]})
            out[f"frame {frame}, {load}"] = rows
            print(frame, load, rows, flush=True)
        stop.set()
    return out


def markdown(report: dict) -> str:
    lines = [f"# Where the first start lands against its prediction ({report['minutes']} min, "
             "`python benchmarks/bench_tracking_starts.py`)", "", f"{report['machine']}; loop closures off.", "",
             "| sequence | frames | odometry registrations per frame | largest landing of the right ones (mm / deg) "
             "| wrong ones: frame, landing mm, error mm |", "| --- | --- | --- | --- | --- |"]
    for name, s in report["sequences"].items():
        wrong = "; ".join(f"{r['frame']}: {r['landed_mm']}, {r['error_mm']}" for r in s["wrong ones"]) or "-"
        mm, deg = s["largest landing of the right ones (mm, deg)"]
        lines.append(f"| {name} | {s['frames']} | {s['odometry registrations per frame']} | {mm} / {deg} | {wrong} |")
    lines += ["", "7-Scenes every 10th frame, per run: the kept step's error (mm), and the constant-velocity "
              "start replayed on that run's chain (landing mm, error mm, passed the checks):", "",
              "| frame, load | kept error (mm) | constant-velocity start |", "| --- | --- | --- |"]
    for name, rows in report["windows"].items():
        kept = ", ".join(str(r["kept_error_mm"]) for r in rows)
        starts = "; ".join(f"{s['landed_mm']}, {s['error_mm']}, {'passed' if s['passed'] else 'failed'}"
                           for s in (r["constant velocity start"] for r in rows))
        lines.append(f"| {name} | {kept} | {starts} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    warnings.simplefilter("ignore")  # the tracker's flagged-frame warnings: the tables say more
    start = time.perf_counter()
    report = {"machine": machine(), "sequences": sequences(), "windows": windows(args.runs)}
    report["minutes"] = round((time.perf_counter() - start) / 60, 1)
    write_result("tracking_starts", report, markdown(report))


if __name__ == "__main__":
    main()
