"""A map that grows, against training from scratch on everything seen so far (the upper bound).

Per scene and seed, the recording is cut into consecutive segments (each a multiple of 4 frames,
so that every 4th frame of each segment is held out both ways). Incremental: `reconstruct` the
first segment (the `fast` preset, ground-truth poses), then `Reconstruction.extend` it with each
next segment (its default: extension.EXTENSION_BUDGET of the map's steps at its learning rate;
--extension-budget and --extension-lr try others). After each extension, a
reconstruction trained from scratch on all the segments so far with the same total number of
steps as the incremental map has had. Both scored on the held-out frames of all segments so
far (the model's held-out PSNR and depth L1 on its hits); forgetting = the first segment's
held-out PSNR right after it was mapped minus after the last extension; wall time of each update
(extend) against the retrain (each a whole call: tracking/poses, targets, training, calibration,
export; each run alone on the machine, as wall times are compared); peak memory of each process.
Tracking: the ATE of each new segment tracked onto the map (`track_onto`, on the frames as given:
640x480) against the same frames' ATE when the whole recording is tracked at once.

The streaming Mapper (--kinds stream): the whole recording at 320x240 fed frame by frame (`fast`
preset at image_scale 1, so it trains at 320x240 too), every frame tracked and keyframes trained
between frames; frames per second over the add() calls; its map after `finish()` (a further minute
of training) against an offline reconstruction of the same kept frames with the same poses and split
(the `fast` preset's budget), both scored on the held-out frames it kept; the ATE of every streamed
frame.

    python benchmarks/bench_mapping.py [--scenes tum,7scenes] [--seeds 0,1,2] [--segments 3] [--name mapping]
    python benchmarks/bench_mapping.py --kinds stream --name mapping_stream
    python benchmarks/bench_mapping.py --name mapping --markdown-only

Writes benchmarks/results/<name>.json and <name>.md.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import time

import numpy as np
from common import OUT, PATHS, commit, machine, require_shared, run_in_processes, write_result

from open3d_pnerf.extension import EXTENSION_BUDGET

SEGMENT_MULTIPLE = 4  # = holdout_every: the held-out frames are the same in a segment and in the concatenation


def segments(n: int, count: int) -> list[slice]:
    """`count` consecutive segments of equal length, a multiple of SEGMENT_MULTIPLE, from frame 0."""
    length = n // count // SEGMENT_MULTIPLE * SEGMENT_MULTIPLE
    return [slice(k * length, (k + 1) * length) for k in range(count)]


def _scores(recon, sequence, holdout=None) -> dict:
    """The model's held-out PSNR and depth L1 on its hits (mm), over `holdout` (default: all held-out frames)."""
    import dataclasses

    from open3d_pnerf.evaluation import heldout_scores

    if holdout is not None:
        recon = dataclasses.replace(recon, holdout_indices=np.asarray(holdout))
    row = heldout_scores(recon, sequence)["model"]
    return {"psnr": round(row["psnr"], 3), "depth_l1_mm": round(1000 * row["depth_l1_hits"], 2),
            "coverage": round(row["coverage"], 4)}


def run_one(spec: dict) -> dict:
    """One process: the incremental map ("incremental"), a retrain ("retrain", on spec["upto"]
    segments) or the tracking comparison ("tracking")."""
    import warnings

    import torch

    torch.set_num_threads(spec["threads"])
    warnings.simplefilter("ignore")
    import open3d_pnerf as pn
    from open3d_pnerf.data import concatenate
    from open3d_pnerf.tracking import track_onto

    seq = pn.load_sequence(PATHS[spec["scene"]])
    parts = [seq.select(np.arange(len(seq))[s]) for s in segments(len(seq), spec["segments"])]
    cfg = pn.ReconstructionConfig.preset(spec["preset"], holdout_every=SEGMENT_MULTIPLE, seed=spec["seed"],
                                         progress=False)
    out = {k: spec[k] for k in ("scene", "seed", "kind", "upto")}
    if spec["kind"] == "stream":
        return {**out, **_stream(pn, spec)}
    if spec["kind"] == "tracking":
        whole = pn.track(concatenate(parts), progress=False).poses
        known = pn.track(parts[0], progress=False)
        rows = []
        for k in range(1, len(parts)):
            joined = concatenate(parts[: k + 1])
            t0 = time.perf_counter()
            known = track_onto(joined, known.poses, known.covariances, progress=False)
            frames = np.arange(sum(len(p) for p in parts[:k]), len(joined))
            gt = joined.gt_poses[frames]
            rows.append({"segment": k + 1, "onto_s": round(time.perf_counter() - t0, 2),
                         "ate_onto_mm": round(1000 * pn.absolute_trajectory_error(known.poses[frames], gt)["rmse"], 2),
                         "ate_whole_mm": round(1000 * pn.absolute_trajectory_error(whole[frames], gt)["rmse"], 2)})
        return {**out, "segments": rows}
    if spec["kind"] == "retrain":
        joined = concatenate(parts[: spec["upto"]])
        steps = cfg.max_steps + round(spec["extension_budget"] * cfg.max_steps) * (spec["upto"] - 1)
        t0 = time.perf_counter()
        recon = pn.reconstruct(joined, cfg.replace(max_steps=steps, time_budget_s=None), poses=joined.gt_poses)
        first_hold = np.arange(0, len(parts[0]), SEGMENT_MULTIPLE)
        return {**out, "wall_s": round(time.perf_counter() - t0, 1), "steps": recon.stats["training"]["steps"],
                "timings": recon.stats["timings"],
                "scores": _scores(recon, joined), "first": _scores(recon, joined, first_hold),
                "peak_rss_mb": _peak_rss_mb()}
    t0 = time.perf_counter()  # incremental
    extension = cfg.replace(max_steps=round(spec["extension_budget"] * cfg.max_steps), time_budget_s=None,
                            **{"optimizer.lr": spec["extension_lr"] * cfg.optimizer.lr})
    recon = pn.reconstruct(parts[0], cfg.replace(time_budget_s=None), poses=parts[0].gt_poses)
    first_hold = recon.holdout_indices.copy()
    steps = [{"segments": 1, "wall_s": round(time.perf_counter() - t0, 1), "steps": recon.stats["training"]["steps"],
              "scores": _scores(recon, recon.frames), "first": _scores(recon, recon.frames, first_hold)}]
    for k in range(1, len(parts)):
        t0 = time.perf_counter()
        recon = recon.extend(parts[k], extension, poses=parts[k].gt_poses)
        steps.append({"segments": k + 1, "wall_s": round(time.perf_counter() - t0, 1),
                      "steps": recon.stats["training"]["steps"], "box_grown": recon.stats["extended"][-1]["box_grown"],
                      "timings": recon.stats["timings"],
                      "scores": _scores(recon, recon.frames), "first": _scores(recon, recon.frames, first_hold)})
    return {**out, "steps": steps, "peak_rss_mb": _peak_rss_mb()}


def _stream(pn, spec: dict) -> dict:
    """The streaming Mapper over the whole recording at 320x240, against the offline reconstruction."""
    from tqdm.auto import tqdm

    from open3d_pnerf.stages import finish, fit

    seq = pn.load_sequence(PATHS[spec["scene"]], image_scale=0.5)
    cfg = pn.ReconstructionConfig.preset(spec["preset"], holdout_every=SEGMENT_MULTIPLE, seed=spec["seed"],
                                         image_scale=1.0, progress=False)
    mapper = pn.Mapper(seq.intrinsic, cfg)
    t0 = time.perf_counter()
    for i in range(len(seq)):
        mapper.add(seq.to_open3d(i), seq.timestamps[i])
    streaming = time.perf_counter() - t0
    t0 = time.perf_counter()
    recon = mapper.finish()
    finish_s = time.perf_counter() - t0
    timings, stages = {}, tqdm(disable=True)
    offline = pn.Reconstruction(**fit(recon.frames, cfg, recon.poses, recon.covariances, recon.train_indices,
                                      recon.holdout_indices, {"tracked": True}, timings, stages))
    finish(offline, recon.frames, timings, stages, time.perf_counter())
    return {"frames": len(seq), "frames_per_s": round(len(seq) / streaming, 2), "summary": mapper.summary(),
            "finish_s": round(finish_s, 1), "ate_mm": round(1000 * pn.absolute_trajectory_error(
                mapper.poses, seq.gt_poses)["rmse"], 2),
            "mapper": _scores(recon, recon.frames), "offline": _scores(offline, recon.frames),
            "offline_steps": offline.stats["training"]["steps"], "peak_rss_mb": _peak_rss_mb()}


def _peak_rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)  # Linux: KiB


def _ms_per_step(run: dict) -> float | None:
    """A call's time less tracking, targets and export (calibration included), per training step (ms):
    training and building the model; None where the run recorded no timings."""
    t = run.get("timings")
    if not t or "export_s" not in t:
        return None
    return 1000 * (t["total_s"] - t["tracking_s"] - t["targets_s"] - t["export_s"]) / run["steps"]


def table(results: list[dict]) -> dict:
    """{scene: {segments k: {...means over seeds...}}} pairing each incremental step with its retrain."""
    out = {}
    for inc in (r for r in results if r["kind"] == "incremental"):
        for step in inc["steps"][1:]:
            k = step["segments"]
            retrain = next(r for r in results if r["kind"] == "retrain" and r["scene"] == inc["scene"]
                           and r["seed"] == inc["seed"] and r["upto"] == k)
            row = {"psnr_extend": step["scores"]["psnr"], "psnr_retrain": retrain["scores"]["psnr"],
                   "depth_extend": step["scores"]["depth_l1_mm"], "depth_retrain": retrain["scores"]["depth_l1_mm"],
                   "wall_extend": step["wall_s"], "wall_retrain": retrain["wall_s"],
                   "step_ms_extend": _ms_per_step(step), "step_ms_retrain": _ms_per_step(retrain),
                   "forgetting_db": inc["steps"][0]["first"]["psnr"] - step["first"]["psnr"],
                   "forgetting_retrain_db": inc["steps"][0]["first"]["psnr"] - retrain["first"]["psnr"],
                   "rss_incremental": inc["peak_rss_mb"], "rss_retrain": retrain["peak_rss_mb"]}
            out.setdefault(inc["scene"], {}).setdefault(k, []).append(row)
    return out


def markdown(results: list[dict], meta: dict) -> str:
    lines = [f"`{meta['preset']}` preset, seeds {meta['seeds']}; {meta['threads']} thread(s) per run, {meta['jobs']} "
             f"at once; {meta['wall_minutes']} min in all; {meta['machine']}.", ""]
    extended = table(results)
    schedule = (f"{meta['extension_budget']:g} of the map's steps at {meta['extension_lr']:g} of its learning rate"
                if "extension_budget" in meta else "its default budget and learning rate at the time")  # older files
    lines += [] if not extended else [
             f"A map that grows: {meta['segments']} consecutive segments, GT poses, every 4th frame of each segment "
             "held out, 320x240. Each cell: mean over the seeds (min..max). *extend*: the map of the segments before, extended with "
             f"segment k by `Reconstruction.extend` ({schedule}); *retrain*: trained from "
             "scratch on segments 1..k with as many steps as the incremental map has had in all. Scores on the "
             "held-out frames of segments 1..k; forgetting: the first segment's held-out PSNR when it was mapped "
             "minus after this extension (beside it, the same drop for the retrain: what sharing the field with "
             "more frames costs the first segment without any forgetting); wall: the whole call (targets, training, "
             "calibration, export); per step: the call less tracking, targets and export, over its training steps.",
             "",
             "| scene | k | PSNR extend / retrain (dB) | depth L1 extend / retrain (mm) | wall extend / retrain (s) "
             "| wall ratio | per step extend / retrain (ms) | forgetting extend / retrain (dB) "
             "| peak RSS incremental / retrain (MB) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]

    def cell(rows, key, fmt):
        v = [r[key] for r in rows]
        if any(x is None for x in v):  # files written before the runs recorded it
            return "-"
        return format(np.mean(v), fmt) + (f" ({min(v):{fmt}}..{max(v):{fmt}})" if len(v) > 1 else "")

    for scene, by_k in extended.items():
        for k, rows in sorted(by_k.items()):
            ratio = [r["wall_extend"] / r["wall_retrain"] for r in rows]
            lines.append(f"| {scene} | {k} | {cell(rows, 'psnr_extend', '.2f')} / {cell(rows, 'psnr_retrain', '.2f')} "
                         f"| {cell(rows, 'depth_extend', '.1f')} / {cell(rows, 'depth_retrain', '.1f')} "
                         f"| {cell(rows, 'wall_extend', '.0f')} / {cell(rows, 'wall_retrain', '.0f')} "
                         f"| {np.mean(ratio):.2f} | {cell(rows, 'step_ms_extend', '.0f')} / "
                         f"{cell(rows, 'step_ms_retrain', '.0f')} | {cell(rows, 'forgetting_db', '.2f')} / "
                         f"{cell(rows, 'forgetting_retrain_db', '.2f')} "
                         f"| {cell(rows, 'rss_incremental', '.0f')} / {cell(rows, 'rss_retrain', '.0f')} |")
    stream = [r for r in results if r["kind"] == "stream"]
    if stream:
        lines += ["", "Streaming Mapper (320x240, every frame tracked, keyframes trained between frames; alone on the "
                  "machine): frames per second over the add() calls; the map after finish() (a further minute of "
                  "training) against the offline reconstruction of the same kept frames, poses and split.", "",
                  "| scene | seed | frames/s | frames / keyframes / held out | ATE (mm) | held-out PSNR mapper / "
                  "offline (dB) | depth L1 mapper / offline (mm) | peak RSS (MB) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in stream:
            m, o, n = r["mapper"], r["offline"], r["summary"]
            lines.append(f"| {r['scene']} | {r['seed']} | {r['frames_per_s']:.2f} | {n['frames']} / {n['keyframes']} / "
                         f"{n['holdout']} | {r['ate_mm']:.1f} | {m['psnr']:.2f} / {o['psnr']:.2f} | "
                         f"{m['depth_l1_mm']:.1f} / {o['depth_l1_mm']:.1f} | {r['peak_rss_mb']:.0f} |")
    tracking = [r for r in results if r["kind"] == "tracking"]
    if tracking:
        lines += ["", "Tracking (no GT poses): ATE of each new segment tracked onto the map of the segments before "
                  "(`track_onto`) against the same frames' ATE when the whole recording is tracked at once "
                  "(each aligned to the ground truth over the segment's frames).", "",
                  "| scene | segment | ATE onto the map (mm) | ATE whole recording (mm) | tracking onto (s) |",
                  "| --- | --- | --- | --- | --- |"]
        for r in tracking:
            for s in r["segments"]:
                lines.append(f"| {r['scene']} | {s['segment']} | {s['ate_onto_mm']:.1f} | {s['ate_whole_mm']:.1f} "
                             f"| {s['onto_s']:.1f} |")
    lines += ["", "### Targets", "", "| scene | target | met in seeds |", "| --- | --- | --- |"]
    for scene in dict.fromkeys(r["scene"] for r in stream):
        rows = [r for r in stream if r["scene"] == scene]
        for text, test in (("streaming at 5 frames/s or more", lambda r: r["frames_per_s"] >= 5),
                           ("mapper within 1 dB of the offline reconstruction",
                            lambda r: r["mapper"]["psnr"] >= r["offline"]["psnr"] - 1)):
            lines.append(f"| {scene} | {text} | {sum(map(test, rows))}/{len(rows)} |")
    for scene, by_k in extended.items():  # after the last segment
        rows = by_k[max(by_k)]
        for text, test in (
                ("extend within 0.5 dB of the retrain", lambda r: r["psnr_extend"] >= r["psnr_retrain"] - 0.5),
                ("extend depth L1 within 10% of the retrain", lambda r: r["depth_extend"] <= 1.1 * r["depth_retrain"]),
                ("extend in at most 40% of the retrain's wall time", lambda r: r["wall_extend"] <= 0.4 * r["wall_retrain"]),
                ("forgetting at most 0.3 dB", lambda r: r["forgetting_db"] <= 0.3),
                ("forgetting at most the retrain's + 0.3 dB",
                 lambda r: r["forgetting_db"] <= r["forgetting_retrain_db"] + 0.3)):
            lines.append(f"| {scene} | {text} | {sum(map(test, rows))}/{len(rows)} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="tum,7scenes")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--segments", type=int, default=3)
    ap.add_argument("--kinds", default="incremental,retrain,tracking", help="also: stream")
    ap.add_argument("--threads", type=int, default=min(2, multiprocessing.cpu_count()), help="torch threads per run")
    ap.add_argument("--jobs", type=int, default=1,
                    help="runs at once (default 1: wall times are compared, so each run has the machine to itself; "
                         "with 2, a run's time depends on what runs beside it)")
    ap.add_argument("--preset", default="fast", help="'test': a smoke test of the script")
    ap.add_argument("--extension-budget", type=float, default=EXTENSION_BUDGET,
                    help="each extension's share of the map's steps (default: extend's own)")
    ap.add_argument("--extension-lr", type=float, default=1.0,
                    help="each extension's share of the map's learning rate (default 1, extend's own: the map's rate)")
    ap.add_argument("--name", default="mapping")
    ap.add_argument("--markdown-only", action="store_true", help="write results/<name>.md again from its .json")
    args = ap.parse_args()
    if args.markdown_only:
        saved = json.loads((OUT / f"{args.name}.json").read_text())
        (OUT / f"{args.name}.md").write_text(markdown(saved["runs"], saved["meta"]))
        return
    scenes, seeds = args.scenes.split(","), [int(s) for s in args.seeds.split(",")]
    require_shared(*scenes)
    common = dict(segments=args.segments, threads=args.threads, preset=args.preset,
                  extension_budget=args.extension_budget, extension_lr=args.extension_lr)
    kinds = args.kinds.split(",")
    specs = [dict(scene=s, seed=seed, kind=kind, upto=None, **common) for kind in ("incremental", "stream")
             if kind in kinds for s in scenes for seed in seeds]
    if "retrain" in kinds:
        specs += [dict(scene=s, seed=seed, kind="retrain", upto=k, **common)
                  for s in scenes for seed in seeds for k in range(2, args.segments + 1)]
    if "tracking" in kinds:
        specs += [dict(scene=s, seed=0, kind="tracking", upto=None, **common) for s in scenes]
    t0 = time.perf_counter()
    results = run_in_processes(run_one, specs, args.jobs, lambda r: f"{r['scene']} seed {r['seed']} {r['kind']} done")
    meta = {"machine": machine(), "commit": commit(), "seeds": seeds, "segments": args.segments, "kinds": kinds, "threads": args.threads,
            "jobs": args.jobs, "preset": args.preset, "extension_budget": args.extension_budget,
            "extension_lr": args.extension_lr, "wall_minutes": round((time.perf_counter() - t0) / 60, 1)}
    write_result(args.name, {"meta": meta, "runs": results}, markdown(results, meta))


if __name__ == "__main__":
    main()
