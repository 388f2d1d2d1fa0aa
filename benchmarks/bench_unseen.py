"""Where the depth-error law's unseen and edge terms come from (open3d_pnerf.error_law.UNSEEN,
UNSEEN_RAMP, EDGE, EDGE_RADIUS).

Trains one reconstruction (the `fast` preset, GT poses, every 4th frame held out, seed 0) on the
tuning scene, TUM fr1/xyz, and on the held-out frames collects the field's depth error against
the sensor, its sigma without the unseen term, the z-depth and the rendered point's distance to
the training frames' observed surfaces, on two pixel sets: the pixels only the model covers (the
sensor-alone mesh misses them) and the pixels both cover. Then tabulates, for a grid of (unseen,
unseen_ramp), the share of errors inside the law's 99.7% interval and the mean negative
log-likelihood on both sets: the chosen values should hold 99% where only the model covers and
leave the common pixels' calibration as it was. Then the same for a grid of (edge, radius) with
the unseen term at its default: the range of the rendered depths within `radius` (pixels of a
320-pixel-wide image) of each pixel, times `edge`, added to sigma, with the through term at its
default (the least widening that holds 99% where only the model covers is the choice). Then the
through term with the other two at their defaults: how far beyond the rendered point a training
view's depth saw, by more than `margin` (ObservedSurface.seen_through), over the 99.73% interval's
multiple, times `through`, added to sigma. `--dataset 7scenes` checks the choices elsewhere.

    python benchmarks/bench_unseen.py [--dataset tum] [--name unseen] [--markdown-only]

Writes benchmarks/results/<name>.json and .md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from bench_suite import OUT, load, machine, poses_for

from open3d_pnerf.error_law import EDGE_RADIUS, GAUSSIAN_SHARES
from open3d_pnerf.observed import SEEN_THROUGH_MARGIN

UNSEEN = (0.0, 0.2, 0.3, 0.5)
RAMPS = (0.01, 0.02, 0.05)
EDGES = (0.0, 0.1, 0.2, 0.3, 0.5)
RADII = (1, 2, 4)  # pixels of a 320-pixel-wide image
THROUGHS = (0.0, 0.5, 1.0, 2.0)
MARGINS = (0.03, 0.1)  # m


def collect(dataset: str) -> tuple[dict, object]:
    """{set: {err, sigma (law without the unseen, edge and through terms), z, distance, jump_<r> for r
    in RADII, gap_<m> (seen through by more than m metres) for m in MARGINS}} over the held-out frames."""
    import open3d_pnerf as pn
    from open3d_pnerf.camera import backproject
    from open3d_pnerf.error_law import depth_jump
    from open3d_pnerf.evaluation import heldout_views
    from open3d_pnerf.export import sensor_geometry

    cache = OUT / "cache"
    seq, _ = load(dataset, cache)
    poses, covs = poses_for(dataset, seq, "gt", cache)
    cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, seed=0, progress=False)
    recon = pn.reconstruct(seq, cfg, poses=poses, covariances=covs)
    law, observed = recon.depth_error, recon.observed
    recon.observed = None  # renders with the law's sigma alone; distances and jumps computed here
    recon.depth_error = dataclasses.replace(law, edge=0.0)
    K = seq.scaled_by(cfg.image_scale).K
    rows = {"only": [], "common": []}
    for v in heldout_views(recon, seq, {"sensor": sensor_geometry(recon, seq).mesh}):
        model, gt = v["model"], v["depth"]
        covers = (model["opacity"] >= cfg.export.min_opacity) & (gt > 0)
        hit = v["surfaces"]["sensor"]["hit"]
        jumps = [depth_jump(model["depth"], r / 320) for r in RADII]
        pose = recon.poses[v["index"]]
        camera = pose[:3, 3]
        for name, mask in (("only", covers & ~hit), ("common", covers & hit)):
            points = backproject(model["depth"], K, pose, mask)[0]
            rows[name].append(np.stack([np.abs(model["depth"] - gt)[mask], model["depth_std"][mask],
                                        model["depth"][mask], observed.distance(points)] + [j[mask] for j in jumps]
                                       + [observed.seen_through(points, camera, m) for m in MARGINS]))
    keys = ("err", "sigma", "z", "distance", *(f"jump_{r}" for r in RADII), *(f"gap_{m}" for m in MARGINS))
    data = {name: dict(zip(keys, np.concatenate(r, 1))) for name, r in rows.items()}
    return data, law


def score(data: dict, law, unseen: float, ramp: float, edge: float = 0.0, radius: int = RADII[0],
          through: float = 0.0, margin: float = MARGINS[0]) -> dict:
    """Shares within the 68.3% and 99.7% intervals and mean NLL of each pixel set under the law
    with this unseen term, edge term and through term."""
    law = dataclasses.replace(law, unseen=unseen, unseen_ramp=ramp, edge=edge, through=through)
    spread_free = dataclasses.replace(law, scale=1.0, floor=0.0)  # sigma already holds scale and floor
    out = {}
    for name, d in data.items():
        sigma = np.sqrt(d["sigma"] ** 2 + spread_free.sigma(0 * d["z"], d["z"], d["distance"], d[f"jump_{radius}"],
                                                            d[f"gap_{margin}"]) ** 2)
        out[name] = {"within_1": float(np.mean(d["err"] <= law.interval(GAUSSIAN_SHARES[1]) * sigma)),
                     "within_3": float(np.mean(d["err"] <= law.interval(GAUSSIAN_SHARES[3]) * sigma)),
                     "nll": float(np.mean(law.nll(d["err"], sigma))), "median_sigma_mm": 1000 * float(np.median(sigma))}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="tum")
    ap.add_argument("--name", default="unseen")
    ap.add_argument("--markdown-only", action="store_true",
                    help="no run: write results/<name>.md again from results/<name>.json")
    args = ap.parse_args()
    if args.markdown_only:
        write_markdown(json.loads((OUT / f"{args.name}.json").read_text()), args.name)
        return
    data, law = collect(args.dataset)
    grid = [{"unseen": u, "unseen_ramp": r, **score(data, law, u, r)}
            for u in UNSEEN for r in (RAMPS if u else RAMPS[:1])]
    edge_grid = [{"edge": e, "radius_px": r, **score(data, law, law.unseen, law.unseen_ramp, e, r, law.through,
                                                     SEEN_THROUGH_MARGIN)}
                 for e in EDGES for r in (RADII if e else RADII[:1])]
    radius = round(EDGE_RADIUS * 320)
    through_grid = [{"through": t, "margin": m, **score(data, law, law.unseen, law.unseen_ramp, law.edge, radius, t, m),
                     "flagged": {name: float(np.mean(d[f"gap_{m}"] > 0)) for name, d in data.items()}}
                    for m in MARGINS for t in THROUGHS]
    sizes = {name: len(d["err"]) for name, d in data.items()}
    quantiles = {name: {"distance_mm": [1000 * float(q) for q in np.quantile(d["distance"], [0.5, 0.9])],
                        "error_mm": [1000 * float(q) for q in np.quantile(d["err"], [0.5, 0.9])]}
                 for name, d in data.items()}
    terms = {k: getattr(law, k) for k in ("unseen", "unseen_ramp", "edge", "through")}
    result = {"meta": {"dataset": args.dataset, "machine": machine(), "law": {"scale": law.scale, "floor": law.floor,
                                                                             "dof": law.dof, **terms}},
              "pixels": sizes, "quantiles": quantiles, "grid": grid, "edge_grid": edge_grid,
              "through_grid": through_grid}
    (OUT / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    write_markdown(result, args.name)


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown table lines."""
    return ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)] + [
        "| " + " | ".join(r) + " |" for r in rows]


def write_markdown(result: dict, name: str) -> None:
    """results/<name>.md from a result dict (as saved in results/<name>.json)."""
    from open3d_pnerf.error_law import EDGE, THROUGH, UNSEEN, UNSEEN_RAMP

    meta, sizes, q = result["meta"], result["pixels"], result["quantiles"]
    terms = {"unseen": UNSEEN, "unseen_ramp": UNSEEN_RAMP, "edge": EDGE, "through": THROUGH,
             **meta["law"]}  # files written before the terms were saved: the defaults they were run with
    radius = round(EDGE_RADIUS * 320)
    lines = [f"{meta['dataset']}, `fast` preset, GT poses, seed 0, held-out frames; {meta['machine']}. Pixels only the "
             f"model covers: {sizes['only']} (distance to the observed surfaces median / 90%: "
             f"{q['only']['distance_mm'][0]:.0f} / {q['only']['distance_mm'][1]:.0f} mm; error "
             f"{q['only']['error_mm'][0]:.0f} / {q['only']['error_mm'][1]:.0f} mm); both cover: "
             f"{sizes['common']} (distance {q['common']['distance_mm'][0]:.0f} / "
             f"{q['common']['distance_mm'][1]:.0f} mm).", ""]
    lines += table(["unseen", "ramp (mm)", "only: within 99.7%", "only: NLL", "only: median sigma (mm)",
                    "common: within 99.7%", "common: NLL", "common: median sigma (mm)"],
                   [[f"{g['unseen']:g}", f"{1000 * g['unseen_ramp']:g}", f"{o['within_3']:.4f}", f"{o['nll']:.2f}",
                     f"{o['median_sigma_mm']:.0f}", f"{c['within_3']:.4f}", f"{c['nll']:.3f}",
                     f"{c['median_sigma_mm']:.1f}"] for g in result["grid"] for o, c in [(g["only"], g["common"])]])
    lines += ["", f"The edge term, with the unseen term at its default ({terms['unseen']:g}, "
              f"{1000 * terms['unseen_ramp']:g} mm) and the through term at its ({terms['through']:g}, "
              f"{SEEN_THROUGH_MARGIN:g} m); radius in pixels of a 320-pixel-wide image:", ""]
    lines += table(["edge", "radius (px)", "only: within 68.3%", "only: within 99.7%", "only: NLL",
                    "common: within 68.3%", "common: within 99.7%", "common: NLL", "common: median sigma (mm)"],
                   [[f"{g['edge']:g}", f"{g['radius_px']}", f"{o['within_1']:.3f}", f"{o['within_3']:.4f}",
                     f"{o['nll']:.2f}", f"{c['within_1']:.3f}", f"{c['within_3']:.4f}", f"{c['nll']:.3f}",
                     f"{c['median_sigma_mm']:.1f}"]
                    for g in result["edge_grid"] for o, c in [(g["only"], g["common"])]])
    lines += ["", f"The through term, with the unseen and edge terms at their defaults ({terms['unseen']:g}, "
              f"{1000 * terms['unseen_ramp']:g} mm; {terms['edge']:g}, {radius} px); flagged: the share of pixels a "
              "training view saw through by more than the margin:", ""]
    lines += table(["margin (m)", "through", "only: flagged", "only: within 68.3%", "only: within 99.7%", "only: NLL",
                    "common: flagged", "common: within 68.3%", "common: within 99.7%", "common: NLL"],
                   [[f"{g['margin']:g}", f"{g['through']:g}", f"{g['flagged']['only']:.3f}", f"{o['within_1']:.3f}",
                     f"{o['within_3']:.4f}", f"{o['nll']:.3f}", f"{g['flagged']['common']:.3f}", f"{c['within_1']:.3f}",
                     f"{c['within_3']:.4f}", f"{c['nll']:.3f}"]
                    for g in result["through_grid"] for o, c in [(g["only"], g["common"])]])
    (OUT / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    Path(OUT).mkdir(exist_ok=True)
    main()
