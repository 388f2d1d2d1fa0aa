"""Where pnerf's colour trails colour-only training's on dense 7-Scenes, pixel by pixel.

Trains pnerf and colour only on redkitchen frames_150-199 (ground-truth poses, `fast`, 1500 steps,
every 4th frame held out, 320x240; one seed, the same for both), renders every held-out frame and
every 8th training frame at that frame's exposure, and writes

- results/color_gap.png: rows of frames (held-out ones first, then training ones), each the
  colour image, pnerf's render, colour only's render, and where pnerf's squared colour error
  exceeds colour only's (red) or falls below it (blue), blurred by 3 px, full scale at 0.01;
- results/color_gap.{json,md}: both methods' PSNR on the held-out and the training frames, and
  per pixel class (no sensor depth; the evaluation's depth edges, `evaluation.held_out_edges`:
  near a depth step or a pixel without depth; the rest) its share of the pixels, its share of
  the squared-error gap and both PSNRs there.

About 5 minutes on 2 cores (one run of each loss at a time on each core); needs the shared data.

    python benchmarks/bench_color_gap.py [--seed 0] [--jobs 2]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from bench_suite import OUT, PATHS, machine, run_in_processes, write_result

LOSSES = ("pnerf", "photometric")
CLASSES = ("no sensor depth", "near a depth step or no depth", "the rest")
PICTURE_FRAMES = {"held out": 3, "training": 2}  # rows of the picture


def run_one(spec: dict) -> dict:
    """Train one loss on ground-truth poses and render the scored frames; runs in a fresh process."""
    import torch

    torch.set_num_threads(spec["threads"])
    import open3d_pnerf as pn
    from open3d_pnerf.pipeline import run

    seq = pn.load_sequence(PATHS["7scenes"])
    cfg = pn.ReconstructionConfig.preset("fast", loss=spec["loss"], max_steps=1500, time_budget_s=None,
                                         holdout_every=4, image_scale=0.5, seed=spec["seed"], progress=False)
    t0 = time.perf_counter()
    recon = run(seq, cfg, poses=seq.gt_poses, export=False)
    train_s = time.perf_counter() - t0
    renders = {}
    for kind, frames in (("held out", recon.holdout_indices), ("training", recon.train_indices[::8])):
        for i in map(int, frames):
            renders[(kind, i)] = recon.render(recon.poses[i], recon.intrinsic, frame=i)["color"]
    return {**spec, "renders": renders, "train_s": round(train_s, 1)}


def pixel_classes(depth: np.ndarray) -> np.ndarray:
    """(H, W) index into CLASSES of each pixel of a sensor depth image (m)."""
    from open3d_pnerf.evaluation import held_out_edges

    return np.select([depth <= 0, held_out_edges(depth)], [0, 1], default=2)


def psnr(squared_error_sum: float, count: float) -> float:
    from open3d_pnerf.evaluation import mse_to_psnr

    return round(mse_to_psnr(squared_error_sum / count), 2)


def analyse(results: list[dict]) -> tuple[dict, np.ndarray]:
    """(the summary, the picture (H, W, 3) uint8 BGR)."""
    import open3d_pnerf as pn

    seq = pn.load_sequence(PATHS["7scenes"]).at_scale(0.5)
    by_loss = {r["loss"]: r["renders"] for r in results}
    sums = {kind: {loss: 0.0 for loss in LOSSES} | {"pixels": 0} for kind in PICTURE_FRAMES}
    per_class = np.zeros((len(CLASSES), 3))  # pixels, pnerf's and colour only's squared-error sums (held out)
    rows, shown = [], {kind: 0 for kind in PICTURE_FRAMES}
    for kind, i in by_loss["pnerf"]:
        frame = seq[i]
        image = seq.color_on_depth_grid(frame.color, frame.depth).astype(np.float32) / 255
        errors = {loss: ((by_loss[loss][(kind, i)] - image) ** 2).mean(2) for loss in LOSSES}
        for loss in LOSSES:
            sums[kind][loss] += float(errors[loss].sum())
        sums[kind]["pixels"] += image.shape[0] * image.shape[1]
        if kind == "held out":
            classes = pixel_classes(frame.depth)
            for c in range(len(CLASSES)):
                mask = classes == c
                per_class[c] += (mask.sum(), errors["pnerf"][mask].sum(), errors["photometric"][mask].sum())
        if shown[kind] < PICTURE_FRAMES[kind]:
            shown[kind] += 1
            gap = np.clip(cv2.GaussianBlur(errors["pnerf"] - errors["photometric"], (0, 0), 3) / 0.01, -1, 1)
            gap_bgr = np.stack([np.clip(-gap, 0, 1), np.zeros_like(gap), np.clip(gap, 0, 1)], -1)
            panels = [image[..., ::-1], by_loss["pnerf"][(kind, i)][..., ::-1],
                      by_loss["photometric"][(kind, i)][..., ::-1], gap_bgr]
            rows.append(np.concatenate(panels, 1))
    gap_total = per_class[:, 1].sum() - per_class[:, 2].sum()
    summary = {
        "psnr": {kind: {loss: psnr(s[loss], s["pixels"]) for loss in LOSSES} for kind, s in sums.items()},
        "held-out classes": {name: {"share of pixels": round(float(n / per_class[:, 0].sum()), 3),
                                    "share of the gap": round(float((a - b) / gap_total), 3),
                                    "pnerf": psnr(a, n), "photometric": psnr(b, n)}
                             for name, (n, a, b) in zip(CLASSES, per_class)},
    }
    return summary, (np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8)


def markdown(report: dict) -> str:
    s = report["summary"]
    lines = [f"# Where pnerf's colour trails colour only's, dense 7-Scenes ({report['total_minutes']} min, "
             "`python benchmarks/bench_color_gap.py`)", "",
             f"{report['machine']}; seed {report['seed']}, ground-truth poses, `fast`, 1500 steps, every 4th frame "
             f"held out, 320x240; training {report['train_s']['pnerf']} s (pnerf), "
             f"{report['train_s']['photometric']} s (colour only), {report['threads']} thread(s) each. "
             "Picture: `color_gap.png` (per row: the colour image, pnerf's render, colour only's render, red where "
             "pnerf's squared error is the larger).", "",
             "| frames | pnerf PSNR (dB) | colour only PSNR (dB) |", "| --- | --- | --- |"]
    lines += [f"| {kind} | {p['pnerf']} | {p['photometric']} |" for kind, p in s["psnr"].items()]
    lines += ["", "Held-out pixels by class:", "",
              "| class | share of pixels | share of the squared-error gap | pnerf PSNR (dB) | colour only PSNR (dB) |",
              "| --- | --- | --- | --- | --- |"]
    lines += [f"| {name} | {c['share of pixels']} | {c['share of the gap']} | {c['pnerf']} | {c['photometric']} |"
              for name, c in s["held-out classes"].items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    start = time.perf_counter()
    specs = [{"loss": loss, "seed": args.seed, "threads": max(1, 2 // args.jobs)} for loss in LOSSES]
    results = run_in_processes(run_one, specs, args.jobs, lambda r: f"{r['loss']}: trained in {r['train_s']} s")
    summary, picture = analyse(results)
    report = {"machine": machine(), "seed": args.seed, "threads": specs[0]["threads"],
              "train_s": {r["loss"]: r["train_s"] for r in results}, "summary": summary,
              "total_minutes": round((time.perf_counter() - start) / 60, 1)}
    OUT.mkdir(exist_ok=True)
    cv2.imwrite(str(OUT / "color_gap.png"), picture)
    write_result("color_gap", report, markdown(report))


if __name__ == "__main__":
    main()
