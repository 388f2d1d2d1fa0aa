"""Tracking against ground truth: accuracy, failures and recoveries, and whether the pose
covariances hold as error bars. Errors are right-perturbation twists of each pose against the
ground truth re-anchored at frame 0 (track()'s fixed reference), as in its covariances.

Sections, in one run:

1. real: TUM fr1/xyz (mocap GT, read GT_TIME_OFFSET early) and 7-Scenes redkitchen frames 150-199
   (KinectFusion GT), at full (640x480) and half resolution, loop closures on and off: ATE,
   ms/frame, failed / recovered / flagged frames, NEES per dof with its chi-square 95% band,
   per-axis z-score std, shares of per-axis errors within 1 and 2 sigma; the same for the previous
   release (`--previous`, its fixed ``point_noise_m = 2``) on the same frames, run in a subprocess
   from a git worktree; and, this tracker's only, the optimised graph's chi-square per dof of its
   loop and odometry edges (whether they agree with each other as their covariances say);
   The same with each sequence cut in two halves (TUM fr1/xyz frames 0-15 / 16-31, 7-Scenes
   150-174 / 175-199): the first halves are the tuning split of the misregistration floor, the
   second halves report on frames no setting looked at;
2. large motion: the synthetic room (seeds 0-3; 40, 100 and 200 frames around the room, 320x240)
   and 7-Scenes every 10th frame (100 frames, 68 mm / 3.7 deg apart): frames more than 1 cm
   (3 cm on 7-Scenes) from the truth, and those of them that are silently wrong (not covered by
   their covariance: per-frame NEES above the chi-square 99% point of 6 dof);
3. Monte Carlo: the synthetic room's known trajectory (frames 0-11 of a 300-frame circle,
   2.8 cm / 1.2 deg apart) with `--draws` independent draws of the simulated sensor's noise,
   320x240 and half of it, loops on and off: pooled NEES per dof against the chi-square band of
   that many draws, z-score std;
4. downstream: depth targets built with each release's poses and covariances on synthetic
   sequences, against the exact depth along each target's ray: median sigma and the shares of
   targets within 1, 2 and 3 sigma.

    python benchmarks/bench_tracking.py [--draws 40] [--quick]

Writes benchmarks/results/tracking.json and tracking.md.
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings

import numpy as np
import open3d as o3d
from scipy.stats import chi2

from open3d_pnerf.camera import matrix_twist
from open3d_pnerf.data import load_sequence
from open3d_pnerf.synthetic import room_scene, synthetic_sequence
from open3d_pnerf.targets import depth_targets
from open3d_pnerf.tracking import OdometryOptions, absolute_trajectory_error, consistency_of_errors, pose_errors, track

from common import PATHS, Revision, commit, require_shared, write_result

REAL = {"tum_fr1_xyz": PATHS["tum"], "7scenes_150-199": PATHS["7scenes"]}
HALVES = {"tum_fr1_xyz": ((0, 16), (16, 32)), "7scenes_150-199": ((0, 25), (25, 50))}
"""Per sequence, (tuning half, report half) as frame ranges of its sequence."""
GT_TIME_OFFSET = {"tum_fr1_xyz": -0.025}
"""Seconds added to a real sequence's frame times where its ground truth is read (load_sequence's
gt_time_offset): fr1/xyz's motion capture agrees best with the tracked steps' rotations that much
early. Chosen on frames 0-15 (docs/benchmarks.md: where the constants come from)."""
EVERY10 = PATHS["7scenes_every10"]
PREVIOUS = "4dc4fa7"  # the tracker of the release e7fdb54 (4dc4fa7 only restructured it): point_noise_m = 2
WRONG_NEES = float(chi2.ppf(0.99, 6))  # a frame's 6-dof NEES above this: its covariance does not cover its error

PREVIOUS_SCRIPT = """
import json, sys, time, warnings
import numpy as np
import open3d_pnerf as pn
from open3d_pnerf.tracking import track
args = json.loads(sys.argv[1])
if args["data"].startswith("synthetic:"):
    _, n, seed = args["data"].split(":")
    from open3d_pnerf.synthetic import synthetic_sequence
    seq = synthetic_sequence(int(n), 320, 240, seed=int(seed)).sequence
else:
    seq = pn.load_sequence(args["data"])
if args["scale"] != 1:
    seq = seq.at_scale(args["scale"])
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    traj = track(seq, loop_closure=args["loops"], progress=False)
    seconds = time.perf_counter() - t0
np.savez(args["out"], poses=traj.poses, covariances=traj.covariances)
print("RESULT " + json.dumps({"seconds": seconds, "failed_frames": traj.failed_frames,
                             "loops_kept": sum(e.kind == "loop" and e.success for e in traj.edges)}))
"""


def tracked(seq, loops: bool, simulated: bool = False):
    """(trajectory, seconds, warning messages) of track() on `seq` (a simulated sensor: no
    misregistration floor)."""
    options = OdometryOptions().without_misregistration() if simulated else OdometryOptions()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.perf_counter()
        traj = track(seq, loop_closure=loops, progress=False, odometry=options)
        seconds = time.perf_counter() - start
    return traj, seconds, [str(w.message) for w in caught if issubclass(w.category, UserWarning)]


def scores(poses, covariances, gt, wrong_m: float) -> dict:
    """ATE, consistency and the frames off by more than `wrong_m` (and those not covered)."""
    errors = pose_errors(poses, gt)
    off = np.linalg.norm(errors[:, 3:], axis=1)
    nees = np.array([e @ np.linalg.solve(c, e) if i else 0.0 for i, (e, c) in enumerate(zip(errors, covariances))])
    wrong = np.flatnonzero(off > wrong_m)
    return {"ate_mm": round(1000 * absolute_trajectory_error(poses, gt)["rmse"], 2),
            "max_frame_error_mm": round(1000 * float(np.nanmax(off)), 1),
            "median_sigma_mm": round(1000 * float(np.median(np.sqrt(np.trace(covariances[1:, 3:, 3:], axis1=1,
                                                                                  axis2=2)))), 2),
            **{k: (round(v, 3) if isinstance(v, float) else v)
               for k, v in consistency_of_errors(errors[1:], covariances[1:]).items()},
            f"frames_off_by_{wrong_m * 1000:g}mm": wrong.tolist(),
            "silently_wrong": [int(i) for i in wrong if nees[i] > WRONG_NEES]}


def edge_agreement(graph) -> dict:
    """How well the optimised pose graph's edges agree with its poses, against their own
    covariances: the mean of e^T Lambda e / 6 over the kept loop closures (uncertain edges) and over
    the odometry edges, e = log(T_t^-1 T_s X^-1) (tracking.covariance's residual), Lambda the
    edge's information. Edges whose errors are independent and as large as their covariances say
    give about the graph's share of redundant edges (loops / all edges) on average; far less when
    the loop closures and the chain share their errors (None: no such edge)."""
    poses = [np.asarray(node.pose) for node in graph.nodes]
    chi = {True: [], False: []}
    for edge in graph.edges:
        e = matrix_twist(np.linalg.inv(poses[edge.target_node_id]) @ poses[edge.source_node_id]
                         @ np.linalg.inv(np.asarray(edge.transformation)))
        chi[edge.uncertain].append(float(e @ np.asarray(edge.information) @ e) / 6)
    return {f"{name}_chi2_per_dof": round(float(np.mean(chi[kind])), 4) if chi[kind] else None
            for name, kind in (("loop", True), ("odometry", False))}


def row(seq, traj, seconds, messages, wrong_m: float) -> dict:
    return {"ms_per_frame": round(1000 * seconds / len(seq), 1),
            "failed": traj.failed_frames, "recovered": traj.recovered_frames, "flagged": traj.flagged_frames,
            "loops_kept": sum(e.kind == "loop" and e.success for e in traj.edges),
            **edge_agreement(traj.pose_graph),
            **scores(traj.poses, traj.covariances, seq.gt_poses, wrong_m), "warnings": messages}


def real_sequence(name: str):
    """The real sequence `name` of REAL, its ground truth read at its GT_TIME_OFFSET."""
    return load_sequence(REAL[name], gt_time_offset=GT_TIME_OFFSET.get(name, 0.0))


def real_section(previous: Revision, scales) -> dict:
    out = {}
    for name, path in REAL.items():
        full = real_sequence(name)
        for scale in scales:
            seq = full if scale == 1 else full.at_scale(scale)
            for loops in (True, False):
                key = f"{name} {seq.image_size[1]}x{seq.image_size[0]} {'loops' if loops else 'odometry only'}"
                out[key] = {"new": row(seq, *tracked(seq, loops), wrong_m=0.03)}
                before = previous.run(PREVIOUS_SCRIPT, {"data": str(path), "scale": scale, "loops": loops,
                                                        "out": str(previous.tmp / "traj.npz")})
                saved = np.load(previous.tmp / "traj.npz")
                out[key]["previous"] = {"ms_per_frame": round(1000 * before["seconds"] / len(seq), 1),
                                        "failed": before["failed_frames"], "loops_kept": before["loops_kept"],
                                        **scores(saved["poses"], saved["covariances"], seq.gt_poses, 0.03)}
                print(key, {w: {k: out[key][w][k] for k in ("ate_mm", "nees_per_dof", "z_std", "ms_per_frame")}
                            for w in ("new", "previous")}, flush=True)
    return out


def halves_section(scales) -> dict:
    """Each real sequence's tuning and report halves, this tracker only."""
    out = {}
    for name in REAL:
        full = real_sequence(name)
        for use, (a, b) in zip(("tuning", "report"), HALVES[name]):
            for scale in scales:
                seq = full.select(range(a, b))
                seq = seq if scale == 1 else seq.at_scale(scale)
                for loops in (True, False):
                    key = (f"{name} frames {a}-{b - 1} ({use}) {seq.image_size[1]}x{seq.image_size[0]} "
                           f"{'loops' if loops else 'odometry only'}")
                    out[key] = row(seq, *tracked(seq, loops), wrong_m=0.03)
                    print(key, {k: out[key][k] for k in ("ate_mm", "nees_per_dof", "z_std")}, flush=True)
    return out


def large_motion_section(seeds, lengths, every10_frames: int) -> dict:
    out = {}
    for n in lengths:
        for seed in seeds:
            seq = synthetic_sequence(n, 320, 240, seed=seed).sequence
            out[f"synthetic {n} frames seed {seed}"] = r = row(seq, *tracked(seq, True, simulated=True), wrong_m=0.01)
            print(f"synthetic {n}/{seed}", {k: r[k] for k in ("ate_mm", "failed", "recovered", "flagged",
                                                              "frames_off_by_10mm", "silently_wrong")}, flush=True)
    seq = load_sequence(EVERY10).select(range(every10_frames))
    out["7scenes every10th"] = r = row(seq, *tracked(seq, True), wrong_m=0.03)
    print("7scenes every10th", {k: r[k] for k in ("ate_mm", "failed", "recovered", "flagged", "silently_wrong")},
          flush=True)
    return out


def monte_carlo(draws: int, frames: int = 12, path_frames: int = 300) -> dict:
    """Pooled consistency over `draws` independent sensor-noise draws of one known trajectory."""
    scene = room_scene(0)
    runs = {}
    for draw in range(draws):
        base = synthetic_sequence(path_frames, 320, 240, seed=draw, scene=scene).sequence.select(range(frames))
        for scale in (1.0, 0.5):
            seq = base if scale == 1 else base.at_scale(scale)
            for loops in (True, False):
                traj, _, _ = tracked(seq, loops, simulated=True)
                key = f"{seq.image_size[1]}x{seq.image_size[0]} {'loops' if loops else 'odometry only'}"
                errors = pose_errors(traj.poses, seq.gt_poses)
                runs.setdefault(key, []).append((errors[1:], traj.covariances[1:]))
    out = {}
    for key, pairs in runs.items():
        errors = np.concatenate([e for e, _ in pairs])
        covs = np.concatenate([c for _, c in pairs])
        res = consistency_of_errors(errors, covs, independent=draws)
        end = consistency_of_errors(np.stack([e[-1] for e, _ in pairs]), np.stack([c[-1] for _, c in pairs]))
        out[key] = {**{k: (round(v, 3) if isinstance(v, float) else v) for k, v in res.items()},
                    "end_frame_nees_per_dof": round(end["nees_per_dof"], 3),
                    "median_sigma_mm": round(1000 * float(np.median(np.sqrt(np.trace(covs[:, 3:, 3:], axis1=1,
                                                                                     axis2=2)))), 2)}
        print("monte carlo", key, out[key], flush=True)
    return {"draws": draws, "frames": frames, "path_frames": path_frames, "settings": out}


def target_coverage(data, poses, covariances) -> dict:
    """Depth targets from these poses and covariances against the exact depth along their rays."""
    seq = data.sequence
    targets = depth_targets(seq, poses=poses, covariances=covariances, progress=False)
    anchor = seq.gt_poses[0]  # the estimate's world is the ground truth's frame 0
    ratios, sigmas = [], []
    for i in range(len(seq)):
        exact = data.scene.render(anchor @ poses[i], seq.intrinsic)["depth"]
        ok = targets.valid[i] & (exact > 0)
        ratios.append(np.abs(targets.mean[i][ok] - exact[ok]) / targets.sigma[i][ok])
        sigmas.append(targets.sigma[i][ok])
    ratios, sigmas = np.concatenate(ratios), np.concatenate(sigmas)
    return {"median_sigma_mm": round(1000 * float(np.median(sigmas)), 2),
            **{f"within_{k}_sigma": round(float((ratios <= k).mean()), 3) for k in (1, 2, 3)}}


def downstream_section(previous: Revision, cases) -> dict:
    out = {}
    for n, seed in cases:
        data = synthetic_sequence(n, 320, 240, seed=seed)
        traj, _, _ = tracked(data.sequence, True, simulated=True)
        previous.run(PREVIOUS_SCRIPT, {"data": f"synthetic:{n}:{seed}", "scale": 1, "loops": True,
                                       "out": str(previous.tmp / "traj.npz")})
        saved = np.load(previous.tmp / "traj.npz")
        out[f"synthetic {n} frames seed {seed}"] = r = {
            "new": target_coverage(data, traj.poses, traj.covariances),
            "previous": target_coverage(data, saved["poses"], saved["covariances"]),
            "exact poses": target_coverage(data, np.linalg.inv(data.sequence.gt_poses[0]) @ data.sequence.gt_poses,
                                           np.zeros((n, 6, 6)))}
        print("downstream", n, seed, r, flush=True)
    return out


def agreement(r: dict) -> str:
    """A row's edge_agreement cell ("-" where the run has none)."""
    keys = ("loop_chi2_per_dof", "odometry_chi2_per_dof")
    return " / ".join("-" if r.get(k) is None else f"{r[k]:.3f}" for k in keys)


def markdown(report: dict) -> str:
    lines = [f"# Tracking ({report['total_minutes']} min, `python benchmarks/bench_tracking.py`)", "",
             f"## Real sequences: this tracker / the previous release ({report['previous']}, e7fdb54's tracker; "
             "`point_noise_m = 2`), run one after the other", "",
             "| sequence, setting | ATE mm | ms/frame (ratio) | loops kept | NEES/dof (band) | z std | within 1σ / 2σ | "
             "recovered / flagged / failed | edges' χ²/dof, loops / odometry |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for key, r in report["real"].items():
        n, p = r["new"], r["previous"]
        lines.append(f"| {key} | {n['ate_mm']} / {p['ate_mm']} | {n['ms_per_frame']:.0f} / {p['ms_per_frame']:.0f} "
                     f"({n['ms_per_frame'] / p['ms_per_frame']:.2f}) | {n['loops_kept']} / {p.get('loops_kept', '-')} | "
                     f"{n['nees_per_dof']} / {p['nees_per_dof']} ({n['nees_band'][0]:.2f}-{n['nees_band'][1]:.2f}) | "
                     f"{n['z_std']} / {p['z_std']} | {n['within_1']:.2f}, {n['within_2']:.2f} / "
                     f"{p['within_1']:.2f}, {p['within_2']:.2f} | "
                     f"{len(n['recovered'])} / {len(n['flagged'])} / {len(n['failed'])} | {agreement(n)} |")
    lines += ["", "## Halves: the misregistration floor was chosen on the tuning halves; the report halves are "
              "frames no setting looked at", "",
              "| sequence, half, setting | ATE mm | ms/frame | loops kept | NEES/dof (band) | z std | within 1σ / 2σ | "
              "edges' χ²/dof, loops / odometry |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for key, n in report["halves"].items():
        lines.append(f"| {key} | {n['ate_mm']} | {n['ms_per_frame']:.0f} | {n['loops_kept']} | {n['nees_per_dof']} "
                     f"({n['nees_band'][0]:.2f}-{n['nees_band'][1]:.2f}) | {n['z_std']} | "
                     f"{n['within_1']:.2f} / {n['within_2']:.2f} | {agreement(n)} |")
    lines += ["", "## Large motion", "",
              "| sequence | ATE mm | max frame error mm | frames off (>1 cm synthetic, >3 cm 7-Scenes) | "
              "silently wrong | recovered | flagged | failed | NEES/dof | z std |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for key, r in report["large_motion"].items():
        off = next(v for k, v in r.items() if k.startswith("frames_off_by"))
        lines.append(f"| {key} | {r['ate_mm']} | {r['max_frame_error_mm']} | {len(off)} | {len(r['silently_wrong'])} | "
                     f"{len(r['recovered'])} | {len(r['flagged'])} | {len(r['failed'])} | {r['nees_per_dof']} | "
                     f"{r['z_std']} |")
    mc = report["monte_carlo"]
    lines += ["", f"## Monte Carlo: {mc['draws']} noise draws, frames 0-{mc['frames'] - 1} of the synthetic room", "",
              "| setting | NEES/dof (band) | end frame NEES/dof | z std | within 1σ / 2σ | median σ mm |",
              "| --- | --- | --- | --- | --- | --- |"]
    for key, r in mc["settings"].items():
        lines.append(f"| {key} | {r['nees_per_dof']} ({r['nees_band'][0]:.2f}-{r['nees_band'][1]:.2f}) | "
                     f"{r['end_frame_nees_per_dof']} | {r['z_std']} | {r['within_1']:.2f} / {r['within_2']:.2f} | "
                     f"{r['median_sigma_mm']} |")
    lines += ["", "## Downstream: depth targets against the exact depth along their rays", "",
              "| sequence | poses | median σ mm | within 1σ / 2σ / 3σ |", "| --- | --- | --- | --- |"]
    for key, r in report["downstream"].items():
        for which, c in r.items():
            lines.append(f"| {key} | {which} | {c['median_sigma_mm']} | "
                         f"{c['within_1_sigma']} / {c['within_2_sigma']} / {c['within_3_sigma']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=40, help="Monte Carlo noise draws")
    ap.add_argument("--previous", default=PREVIOUS, help="git revision of the tracker to compare with")
    ap.add_argument("--quick", action="store_true", help="a smoke test of the script: tiny everything")
    args = ap.parse_args()
    require_shared("tum", "7scenes", "7scenes_every10")
    start = time.perf_counter()
    report = {"machine": {"platform": platform.platform(), "open3d": o3d.__version__}, "commit": commit(),
              "previous": args.previous}
    with Revision(args.previous) as previous:
        if args.quick:
            report["real"] = real_section(previous, (0.5,))
            report["halves"] = halves_section((0.5,))
            report["large_motion"] = large_motion_section((0,), (40,), 10)
            report["monte_carlo"] = monte_carlo(2)
            report["downstream"] = downstream_section(previous, [(40, 0)])
        else:
            report["real"] = real_section(previous, (1.0, 0.5))
            report["halves"] = halves_section((1.0, 0.5))
            report["large_motion"] = large_motion_section(range(4), (40, 100, 200), 100)
            report["monte_carlo"] = monte_carlo(args.draws)
            report["downstream"] = downstream_section(previous, [(40, 0), (100, 3)])
    report["total_minutes"] = round((time.perf_counter() - start) / 60, 1)
    name = "tracking_quick" if args.quick else "tracking"
    write_result(name, report, markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
