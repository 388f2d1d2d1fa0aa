"""Where 7-Scenes' colour camera sits against its depth camera: the 7-Scenes reader's default
registration (open3d_pnerf.data.seven_scenes) beside rigs with a baseline, fitted on one subset
and checked on the other.

A registration maps a depth pixel (u, v) with depth z to the colour pixel
u_c = s * f * (X - b) / z + cx + dx, v_c = s * f * Y / z + cy + dy (X, Y: the pixel's point in
the depth camera, m; f, cx, cy: the depth intrinsic): a colour focal length ratio s, a
principal-point shift (dx, dy) px at 640x480 and a baseline b (m) along x. The ratio stays the
reader's default 0.905 (colour edges matched to depth edges; shared data's SOURCE.md): the
fit subset hardly tells 0.9 from 0.905 (exploratory) while the shift at the image border moves
by 1.6 px between them. Its score is how
strongly the colour image changes where the depth has an edge: the mean colour gradient magnitude
(relative to the image's mean) at the colour pixels that the depth-edge pixels (their nearer side)
project to. A misregistered colour edge lies beside the depth edge, where the gradient is weaker.

The grid is fitted on redkitchen every10th_0-990 (every 5th of its 100 frames) and the scores are
reported on frames_150-199 (every 4th frame), which the fit never saw, for the reader's default
(s = 0.905, dx = -7 px, no baseline), the best without a baseline and the best with one.
A second table asks whether the colour images carry lens distortion that the pinhole maps
ignore: at the best rig's baseline, a radial term k1 on the colour camera's normalised
coordinates (x, y) -> (x, y) (1 + k1 (x^2 + y^2)), each k1 with its best focal ratio and shift.
About a minute; needs the shared data.

    python benchmarks/bench_color_registration.py

Writes benchmarks/results/color_registration.json and .md.
"""

from __future__ import annotations

import itertools
import json
import time

import cv2
import numpy as np
from bench_suite import OUT, SHARED, machine

FIT = SHARED / "7scenes_redkitchen" / "every10th_0-990"
REPORT = SHARED / "7scenes_redkitchen" / "frames_150-199"
BASELINES = (0.0, 0.01, 0.02, 0.025, 0.03, 0.035, 0.04, 0.05)
DX_AROUND = np.arange(-4.0, 4.01, 0.5)  # px around the shift that keeps the default's at 1.4 m
DY = np.arange(-2.0, 1.01, 0.25)
K1 = (-0.2, -0.1, -0.05, 0.0, 0.05, 0.1, 0.2)  # the colour camera's radial distortion
RATIOS = (0.885, 0.895, 0.905, 0.915, 0.925)  # a distortion changes the focal length that fits best
EDGE_STEP = 0.5  # a depth edge: |grad z| / z over this (per pixel)


def edges(path, every: int) -> list[tuple]:
    """Per frame: the colour's relative gradient magnitude (H, W), the depth-edge pixels' u, v and
    their nearer depth (m), and the depth intrinsic's f, cx, cy."""
    import open3d_pnerf as pn

    seq = pn.load_sequence(path)
    (f, _), (cx, cy) = seq.intrinsic.get_focal_length(), seq.intrinsic.get_principal_point()
    out = []
    for i in range(0, len(seq), every):
        frame = seq[i]
        gray = frame.color.astype(np.float32).mean(2)
        grad = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
        d, valid = frame.depth, frame.depth > 0
        step = np.hypot(cv2.Sobel(d, cv2.CV_32F, 1, 0), cv2.Sobel(d, cv2.CV_32F, 0, 1)) / np.maximum(d, 1e-3)
        inner = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        nearer = -cv2.dilate(-np.where(valid, d, np.inf).astype(np.float32), np.ones((5, 5), np.uint8))
        v, u = np.nonzero((step > EDGE_STEP) & inner)
        out.append((grad / grad.mean(), u.astype(np.float64), v.astype(np.float64), nearer[v, u], (f, cx, cy)))
    return out


def score(frames: list[tuple], ratio: float, dx: float, dy: float, baseline: float, k1: float = 0.0) -> float:
    """The mean relative colour gradient at the projected depth-edge pixels (see the module), the
    colour camera with radial distortion k1."""
    values = []
    for grad, u, v, z, (f, cx, cy) in frames:
        x, y = ((u - cx) - f * baseline / z) / f, (v - cy) / f
        radial = 1 + k1 * (x * x + y * y)
        uc = ratio * f * x * radial + cx + dx
        vc = ratio * f * y * radial + cy + dy
        values.append(cv2.remap(grad, uc[None].astype(np.float32), vc[None].astype(np.float32), cv2.INTER_LINEAR,
                                borderValue=0.0).mean())
    return float(np.mean(values))


def default_registration() -> dict:
    """The 7-Scenes reader's default: its focal ratio and shift, no baseline."""
    from open3d_pnerf.data import seven_scenes as reader

    dx, dy = reader.COLOR_CENTRE_SHIFT
    return {"ratio": reader.COLOR_FOCAL_RATIO, "dx": dx, "dy": dy, "baseline": 0.0}


def fit(frames: list[tuple], default: dict) -> list[dict]:
    """Every grid point's score, best first (the focal ratio kept at the default's)."""
    rows, ratio, f = [], default["ratio"], frames[0][4][0]
    for baseline in BASELINES:
        centre = default["dx"] + ratio * f * baseline / 1.4
        for dx, dy in itertools.product(DX_AROUND + round(centre * 2) / 2, DY):
            rows.append({"ratio": ratio, "dx": float(dx), "dy": float(dy), "baseline": baseline,
                         "score": score(frames, ratio, dx, dy, baseline)})
    return sorted(rows, key=lambda r: -r["score"])


def fit_distortion(fit_frames: list[tuple], report_frames: list[tuple], rig: dict) -> list[dict]:
    """Per k1 in K1: the best focal ratio and shift (within 2 / 1 px of `rig`'s) at `rig`'s baseline
    on the fit subset, with its scores on both subsets."""
    rows = []
    for k1 in K1:
        grid = itertools.product(RATIOS, rig["dx"] + np.arange(-2.0, 2.01, 0.5), rig["dy"] + np.arange(-1.0, 1.01, 0.5))
        best = max(({"k1": k1, "ratio": r, "dx": float(dx), "dy": float(dy), "baseline": rig["baseline"],
                     "fit score": score(fit_frames, r, dx, dy, rig["baseline"], k1)} for r, dx, dy in grid),
                   key=lambda row: row["fit score"])
        best["report score"] = score(report_frames, *(best[k] for k in ("ratio", "dx", "dy", "baseline", "k1")))
        rows.append(best)
    return rows


def main():
    t0 = time.perf_counter()
    fit_frames, report_frames = edges(FIT, 5), edges(REPORT, 4)
    default = default_registration()
    grid = fit(fit_frames, default)
    chosen = {"the reader's default (no baseline)": default,
              "best without a baseline": next(r for r in grid if r["baseline"] == 0.0),
              "best with a baseline (opt-in)": grid[0]}
    keys = ("ratio", "dx", "dy", "baseline")
    rows = [{"registration": name, **{k: p[k] for k in keys},
             "fit score": score(fit_frames, *(p[k] for k in keys)),
             "report score": score(report_frames, *(p[k] for k in keys))} for name, p in chosen.items()]
    per_baseline = [next(r for r in grid if r["baseline"] == b) for b in BASELINES]
    distortion = fit_distortion(fit_frames, report_frames, grid[0])
    meta = {"fit": str(FIT.name), "report": str(REPORT.name), "machine": machine(),
            "minutes": round((time.perf_counter() - t0) / 60, 2)}
    (OUT / "color_registration.json").write_text(json.dumps(
        {"meta": meta, "rows": rows, "best_per_baseline": per_baseline, "distortion": distortion}, indent=1))
    lines = [f"7-Scenes redkitchen colour against depth: fitted on {meta['fit']} (every 5th frame), reported on "
             f"{meta['report']} (every 4th); {meta['minutes']} min, {meta['machine']}.", "",
             "Score: mean colour gradient (relative to the image's mean) at the colour pixels the depth-edge "
             "pixels project to; higher is better aligned.", "",
             "| registration | focal ratio | dx (px) | dy (px) | baseline (m) | score, fit subset "
             "| score, report subset |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['registration']} | {r['ratio']} | {r['dx']:+.2f} | {r['dy']:+.2f} | {r['baseline']:.3f} | "
              f"{r['fit score']:.3f} | {r['report score']:.3f} |" for r in rows]
    lines += ["", "Best of the fit grid at each baseline (fit subset):", "",
              "| baseline (m) | focal ratio | dx (px) | dy (px) | score |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| {r['baseline']:.3f} | {r['ratio']} | {r['dx']:+.2f} | {r['dy']:+.2f} | {r['score']:.3f} |"
              for r in per_baseline]
    lines += ["", f"The colour camera's radial distortion k1, at the best rig's baseline ({grid[0]['baseline']:.3f} m), "
              "each with its best focal ratio and shift on the fit subset:", "",
              "| k1 | focal ratio | dx (px) | dy (px) | score, fit subset | score, report subset |",
              "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['k1']:+.2f} | {r['ratio']} | {r['dx']:+.2f} | {r['dy']:+.2f} | {r['fit score']:.3f} | "
              f"{r['report score']:.3f} |" for r in distortion]
    (OUT / "color_registration.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
