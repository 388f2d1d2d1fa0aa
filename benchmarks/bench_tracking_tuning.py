"""Where the tracker's covariance constants come from, on the tuning halves only: TUM fr1/xyz
frames 0-15 and 7-Scenes 150-174, at 640x480 and 320x240, loop closures on and off (the second
halves, which bench_tracking.py reports, are not looked at here).

0. the ground truth's time offset on TUM fr1/xyz 0-15 (bench_tracking.GT_TIME_OFFSET): the RMS
   rotation error of the odometry steps (640x480, loop closures off) against the ground truth
   read at each offset of a grid; the choice is the smallest, and 1, 1b and 2 score against it;
1. the misregistration floor (OdometryOptions.misregistration_rad, misregistration_systematic):
   NEES per dof and per-axis z-score std of the poses against the ground truth in the 8 settings
   for a grid of (rad, systematic), without the motion term; the choice is the pair whose worst
   setting lies nearest 1 (the larger of |log NEES| and 2 |log z std|);
1b. its motion term (misregistration_per_squared_motion), which the slow tuning halves hardly
   see: at the pair chosen in 1, for each value of a grid, 7-Scenes every 10th frame (the first
   100, loop closures on, 68 mm / 3.7 degrees apart; in the tuning split already): its frames
   wrong beyond their covariance (bench_tracking's silently wrong) and ATE, beside the tuning
   halves' worst; the choice is the smallest value that leaves no frame silently wrong;
2. LOOP_INFLATION (tracking/tracker.py), loop closures on, the floor chosen in 1: NEES per dof
   and ATE for each value of a grid;
3. STOP_FRACTION (tracking/uncertainty.py), a speed setting: the time per frame on 7-Scenes
   150-199 at 320x240 without loop closures (the setting where it costs most), best of two runs,
   and the ATE, for each value; run it alone on the machine.

The constants are set on the modules for each run (LOOP_INFLATION, STOP_FRACTION are module
constants); every other setting is the default.

    python benchmarks/bench_tracking_tuning.py [--name tracking_tuning]

Writes benchmarks/results/<name>.json and .md, with the run's duration (about 11 minutes alone on 2 cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import numpy as np
from bench_suite import machine, write_result
from bench_tracking import EVERY10, OFFSET_GRID, REAL, scores
from bench_tracking_axes import odometry_steps, rotation_rms_by_offset

from open3d_pnerf.data import load_sequence
from open3d_pnerf.tracking import (OdometryOptions, absolute_trajectory_error, consistency_of_errors, pose_errors,
                                   track, tracker, uncertainty)

HALVES = {"TUM fr1/xyz 0-15": ("tum_fr1_xyz", range(0, 16)), "7-Scenes 150-174": ("7scenes_150-199", range(0, 25))}
FLOOR_GRID = [(rad, systematic) for rad in (0.5e-3, 1e-3, 1.5e-3) for systematic in (0.02, 0.03, 0.04, 0.05)]
MOTION_GRID = (0.0, 0.25, 0.5, 1.0)
LOOP_GRID = (4.0, 9.0, 16.0, 25.0, 36.0)
STOP_GRID = (0.1, 0.15)


def scored(seq, loops: bool, options: OdometryOptions) -> dict:
    """NEES per dof, z std and ATE (mm) of track() on `seq`, and its seconds."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        traj = track(seq, loop_closure=loops, progress=False, odometry=options)
        seconds = time.perf_counter() - t0
    c = consistency_of_errors(pose_errors(traj.poses, seq.gt_poses)[1:], traj.covariances[1:])
    return {"nees_per_dof": round(c["nees_per_dof"], 3), "z_std": round(c["z_std"], 3), "seconds": seconds,
            "ate_mm": round(1000 * absolute_trajectory_error(traj.poses, seq.gt_poses)["rmse"], 2)}


def time_offset() -> tuple[float, dict]:
    """The ground-truth time offset (s) of TUM fr1/xyz 0-15 whose steps agree best with the tracked
    ones' rotations, and the RMS rotation step error (mrad) at each offset of OFFSET_GRID."""
    name, frames = HALVES["TUM fr1/xyz 0-15"]
    seq = load_sequence(REAL[name]).select(frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        traj = track(seq, loop_closure=False, progress=False)
    rms = rotation_rms_by_offset(odometry_steps(traj), frames)
    return float(min(OFFSET_GRID, key=lambda o: rms[f"{o + 0:g}"])), rms


def settings(offsets: dict):
    """(label, sequence, loops) of the tuning halves' settings, the ground truth read at `offsets` (s, by name)."""
    for label, (name, frames) in HALVES.items():
        half = load_sequence(REAL[name], gt_time_offset=offsets.get(name, 0.0)).select(frames)
        for scale in (1.0, 0.5):
            seq = half if scale == 1 else half.at_scale(scale)
            for loops in (True, False):
                yield f"{label} {seq.image_size[1]}x{seq.image_size[0]} {'loops' if loops else 'odometry'}", seq, loops


def worst(rows: dict) -> float:
    return max(max(abs(np.log(r["nees_per_dof"])), 2 * abs(np.log(r["z_std"]))) for r in rows.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--name", default="tracking_tuning")
    args = ap.parse_args()
    start = time.perf_counter()
    report = {"machine": machine(), "floor": {}, "motion": {}, "loop_inflation": {}, "stop_fraction": {}}
    offset, report["time_offset"] = time_offset()
    report["chosen_time_offset"] = offset
    print(f"ground-truth time offset {offset:g} s: {report['time_offset']}", flush=True)
    cases = list(settings({"tum_fr1_xyz": offset}))
    chosen, best, best_rows = None, np.inf, None
    for rad, systematic in FLOOR_GRID:
        options = OdometryOptions(misregistration_rad=rad, misregistration_per_squared_motion=0.0,
                                  misregistration_systematic=systematic)
        rows = {label: scored(seq, loops, options) for label, seq, loops in cases}
        key = f"{rad * 1e3:g} mrad + {systematic:g} x turn from frame 0"
        score = worst(rows)
        report["floor"][key] = {"worst": round(score, 3), "rows": rows}
        print(f"floor {key}: worst {score:.3f}", flush=True)
        if score < best:
            chosen, best, best_rows = options, score, rows
    every10 = load_sequence(EVERY10).select(range(100))
    for k in MOTION_GRID:
        options = dataclasses.replace(chosen, misregistration_per_squared_motion=k)
        rows = best_rows if k == 0 else {label: scored(seq, loops, options) for label, seq, loops in cases}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            traj = track(every10, loop_closure=True, progress=False, odometry=options)
        large = scores(traj.poses, traj.covariances, every10.gt_poses, 0.03)
        report["motion"][f"{k:g}"] = {"worst": round(worst(rows), 3), "rows": rows, "every10_ate_mm": large["ate_mm"],
                                     "every10_silently_wrong": large["silently_wrong"]}
        print(f"motion {k:g}: {large['ate_mm']} mm, silently wrong {large['silently_wrong']}", flush=True)
    k = min((float(k) for k, r in report["motion"].items() if not r["every10_silently_wrong"]), default=MOTION_GRID[-1])
    chosen = dataclasses.replace(chosen, misregistration_per_squared_motion=k)
    report["chosen_floor"] = {name: getattr(chosen, name) for name in ("misregistration_rad",
                                                                        "misregistration_per_squared_motion",
                                                                        "misregistration_systematic")}
    default_inflation = tracker.LOOP_INFLATION
    try:
        for inflation in LOOP_GRID:
            tracker.LOOP_INFLATION = inflation
            report["loop_inflation"][f"{inflation:g}"] = {label: scored(seq, loops, chosen)
                                                         for label, seq, loops in cases if loops}
            print(f"loop inflation {inflation:g}", flush=True)
    finally:
        tracker.LOOP_INFLATION = default_inflation
    default_stop = uncertainty.STOP_FRACTION
    seq = load_sequence(REAL["7scenes_150-199"]).at_scale(0.5)
    try:
        for fraction in STOP_GRID:
            uncertainty.STOP_FRACTION = fraction
            runs = [scored(seq, False, OdometryOptions()) for _ in range(2)]
            report["stop_fraction"][f"{fraction:g}"] = {"ms_per_frame": round(1000 * min(r["seconds"] for r in runs)
                                                                              / len(seq), 1),
                                                         "ate_mm": runs[0]["ate_mm"]}
            print(f"stop fraction {fraction:g}: {report['stop_fraction'][f'{fraction:g}']}", flush=True)
    finally:
        uncertainty.STOP_FRACTION = default_stop
    report["minutes"] = round((time.perf_counter() - start) / 60, 1)
    write_result(args.name, report, markdown(report))


def markdown(report: dict) -> str:
    labels = list(next(iter(report["floor"].values()))["rows"])
    lines = [f"# Tracking constants on the tuning halves ({report['minutes']} min, "
             f"`python benchmarks/bench_tracking_tuning.py`; {report['machine']})", "",
             "## The ground truth's time offset: TUM fr1/xyz 0-15, 640x480, odometry only: RMS rotation error of the "
             "steps (mrad) with the ground truth read that many seconds off; "
             f"chosen: {report['chosen_time_offset']:g} s",
             "", "| offset s | " + " | ".join(report["time_offset"]) + " |",
             "|" + " --- |" * (len(report["time_offset"]) + 1),
             "| step rotation RMS mrad | " + " | ".join(str(v) for v in report["time_offset"].values()) + " |", "",
             "## Misregistration floor, without the motion term: NEES per dof / z std per setting (worst: max of "
             "|log NEES|, 2 |log z std|)", "",
             "| floor | worst | " + " | ".join(labels) + " |", "|" + " --- |" * (len(labels) + 2)]
    for key, r in sorted(report["floor"].items(), key=lambda kv: kv[1]["worst"]):
        cells = [f"{r['rows'][k]['nees_per_dof']} / {r['rows'][k]['z_std']}" for k in labels]
        lines.append(f"| {key} | {r['worst']} | " + " | ".join(cells) + " |")
    lines += ["", "## The motion term at the floor chosen above: 7-Scenes every 10th frame (the first 100, loops on), "
              "ATE and frames wrong beyond their covariance; the tuning halves' worst and NEES per dof / z std", "",
              "| per squared motion | every 10th ATE mm | silently wrong | worst | " + " | ".join(labels) + " |",
              "|" + " --- |" * (len(labels) + 4)]
    for key, r in report["motion"].items():
        cells = [f"{r['rows'][k]['nees_per_dof']} / {r['rows'][k]['z_std']}" for k in labels]
        lines.append(f"| {key} | {r['every10_ate_mm']} | {r['every10_silently_wrong']} | {r['worst']} | "
                     + " | ".join(cells) + " |")
    loop_labels = list(next(iter(report["loop_inflation"].values())))
    lines += ["", f"## LOOP_INFLATION (loop closures on, the floor chosen above: {report['chosen_floor']}): "
              "NEES per dof / ATE mm", "",
              "| inflation | " + " | ".join(loop_labels) + " |", "|" + " --- |" * (len(loop_labels) + 1)]
    for key, rows in report["loop_inflation"].items():
        lines.append(f"| {key} | " + " | ".join(f"{rows[k]['nees_per_dof']} / {rows[k]['ate_mm']}" for k in loop_labels)
                     + " |")
    lines += ["", "## STOP_FRACTION: 7-Scenes 150-199 at 320x240, odometry only, best of 2 runs", "",
              "| stop fraction | ms/frame | ATE mm |", "| --- | --- | --- |"]
    for key, r in report["stop_fraction"].items():
        lines.append(f"| {key} | {r['ms_per_frame']} | {r['ate_mm']} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
