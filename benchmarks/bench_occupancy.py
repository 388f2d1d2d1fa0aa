"""Is the occupancy grid right, and does it beat OctoMap built from the same frames?

Per scene and seed: the `fast` preset with ground-truth poses and every 4th frame held out (320x240);
the grid at 5 cm over the scene box (recon.occupancy_grid); OctoMap (octomap-python, its own sensor
model: insertPointCloud from each camera's centre) from the same training frames' depth, poses and
voxels. Both are scored on the voxels the held-out frames' rays reach (every 4th pixel): occupied
where a ray ends, free where it passes before its depth; on the synthetic room the rays are the exact
renders' and the labels the exact mesh's (a voxel is occupied where the mesh meets it). Scores: the
Brier score (and per class), the expected calibration error (10 bins), the share of the reference's
occupied voxels called free (P < 0.2), the share of its voxels decided (P < 0.2 or > 0.8), seconds.

Settings are chosen on one scene and reported on the others: `--tune` fits the grid's SensorModel
(weights, grazing discount and clamp), the sensor ablation's and OctoMap's (hit, miss, clamping) on
7-Scenes redkitchen seed 0, each the lowest Brier score over a small grid of values (OctoMap's
defaults among them) among those that call at most 1% of the occupied voxels free, and writes
results/occupancy_tuning.json, which the report runs read for OctoMap (the grid's chosen values are
open3d_pnerf.occupancy.SensorModel's defaults).

    python benchmarks/bench_occupancy.py --tune
    python benchmarks/bench_occupancy.py [--datasets synthetic,tum,7scenes] [--seeds 0,1,2] [--name occupancy]

Writes benchmarks/results/<name>.json and <name>.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time

import numpy as np
from common import CACHE, OUT, commit, exact_surface, load, machine, poses_for, require_shared, synthetic_room, write_result

VOXEL = 0.05
TUNE_ON = "7scenes"
OCTOMAP_DEFAULT = {"hit": 0.7, "miss": 0.4, "low": 0.1192, "high": 0.971}
TUNING = OUT / "occupancy_tuning.json"


def train(dataset: str, seed: int):
    import open3d_pnerf as pn

    seq, _ = load(dataset)
    seq, poses, covs = poses_for(dataset, seq)
    cfg = pn.ReconstructionConfig.preset("fast", holdout_every=4, seed=seed, progress=False)
    return seq, pn.reconstruct(seq, cfg, poses=poses, covariances=covs)


def reference(dataset: str, seq, recon) -> tuple[np.ndarray, np.ndarray]:
    """(voxel centres (M, 3) m, occupied (M,) bool) of the voxels the held-out frames' rays reach
    (open3d_pnerf.occupancy.heldout_voxels, every 4th pixel); on the synthetic room the rays are the exact
    renders' and a voxel is occupied where the exact mesh meets it."""
    from open3d_pnerf.occupancy import heldout_voxels, voxel_codes

    mesh = exact_surface(dataset)
    if mesh is None:
        return heldout_voxels(recon, seq, VOXEL)
    from open3d_pnerf.synthetic import room_scene

    scene = room_scene(seed=0)
    exact = [scene.render(seq.gt_poses[i], seq.intrinsic)["depth"] for i in recon.holdout_indices]
    centers, _ = heldout_voxels(recon, seq, VOXEL, depths=exact)
    samples = np.asarray(mesh.sample_points_uniformly(int(mesh.get_surface_area() / (VOXEL / 6) ** 2)).points)
    return centers, np.isin(voxel_codes(centers, VOXEL), voxel_codes(samples, VOXEL))


# -- the maps -----------------------------------------------------------------------------------------
def training_frames(seq, recon, stride: int = 1):
    """(depths (F, h, w) m, K (3, 3), poses (F, 4, 4)) of the training frames at the training resolution
    over `stride`."""
    frames = seq.select(recon.train_indices).scaled_by(recon.config.image_scale / stride)
    return np.stack([f.depth for f in frames]), frames.K, recon.poses[recon.train_indices]


def sensor_views(seq, recon, stride: int = 4):
    """The ablation without the model: the same evidence (open3d_pnerf.occupancy.ViewEvidence) from the
    training frames' sensor depth at every `stride`-th pixel (the grid's fused views have every training
    pixel; both walk rays in the same directions near the surface, the ablation's at its coarser
    pixel's depth), its sigma the sensor noise model's (a Gaussian); a pixel without depth says
    nothing, as in the grid."""
    from open3d_pnerf.error_law import DepthErrorLaw
    from open3d_pnerf.occupancy import ViewEvidence
    from open3d_pnerf.targets import SensorNoise

    depths, K, poses = training_frames(seq, recon, stride)
    valid = depths > 0
    sigma = np.where(valid, SensorNoise().sigma(np.where(valid, depths, 1.0)), 1.0)
    return ViewEvidence(poses, K, np.where(valid, depths, 0.0), sigma, valid.astype(float), DepthErrorLaw(), stride)


def octomap_probabilities(seq, recon, params: dict, centers: np.ndarray) -> tuple[np.ndarray, float]:
    """(probability (M,) of the voxels at `centers` (0.5 where OctoMap has no node), seconds to build) of
    OctoMap from the training frames' depth: each frame's points inserted from its camera's centre
    with OctoMap's sensor model `params` (hit, miss probabilities; clamping low, high)."""
    import octomap

    from open3d_pnerf.camera import unproject

    t0 = time.perf_counter()
    tree = octomap.OcTree(VOXEL)
    tree.setProbHit(params["hit"])
    tree.setProbMiss(params["miss"])
    tree.setClampingThresMin(params["low"])
    tree.setClampingThresMax(params["high"])
    depths, K, poses = training_frames(seq, recon)
    v, u = np.mgrid[0:depths.shape[1], 0:depths.shape[2]]
    for depth, pose in zip(depths, poses):
        ok = depth > 0
        points = unproject(K, u[ok], v[ok], depth[ok]) @ pose[:3, :3].T + pose[:3, 3]
        tree.insertPointCloud(points, pose[:3, 3].copy(), maxrange=seq.depth_trunc or -1.0)
    seconds = time.perf_counter() - t0
    p = np.full(len(centers), 0.5)
    for k, center in enumerate(centers):
        node = tree.search(center)
        try:
            p[k] = node.getOccupancy()
        except octomap.NullPointerException:
            pass
    return p, seconds


def scores(p: np.ndarray, occupied: np.ndarray) -> dict:
    """open3d_pnerf.occupancy.calibration without its reliability diagram."""
    from open3d_pnerf.occupancy import calibration

    return {k: v for k, v in calibration(p, occupied).items() if k != "reliability"}


# -- tuning on one scene ------------------------------------------------------------------------------
def chosen(trials: list[tuple[dict, dict]]) -> dict:
    """The settings of the lowest Brier score among those that call at most 1% of the occupied voxels
    free (all of them when none does)."""
    safe = [t for t in trials if t[1]["occupied_called_free"] <= 0.01] or trials
    return min(safe, key=lambda t: t[1]["brier"])[0]


def tune(keep_octomap: bool = False) -> dict:
    """The grid's, the sensor ablation's and OctoMap's settings on TUNE_ON seed 0 (chosen());
    keep_octomap: OctoMap's from the last run."""
    from open3d_pnerf.occupancy import SensorModel, view_evidence

    import open3d_pnerf as pn

    saved = CACHE / f"occupancy_tuning_{TUNE_ON}"  # the trained model, kept for trying settings again
    if (saved / "reconstruction.json").is_file():
        seq, recon = load(TUNE_ON)[0], pn.Reconstruction.load(saved)
    else:
        seq, recon = train(TUNE_ON, 0)
        recon.save(saved)
    centers, occupied = reference(TUNE_ON, seq, recon)
    out = {"scene": TUNE_ON, "seed": 0, "voxels": int(len(occupied)), "commit": commit(), "machine": machine()}
    values = itertools.product((0.1, 0.2, 0.4, 0.8, 1.6), (-0.4, -0.8, -1.6, -3.2), (0.0, 1.0, 3.0, 10.0, 30.0),
                               ((-4.0, 4.0), (-6.0, 6.0), (-8.0, 8.0)))
    models = [SensorModel(hit, miss, grazing, low, high) for hit, miss, grazing, (low, high) in values]
    for name, views in (("grid", view_evidence(recon)), ("sensor", sensor_views(seq, recon))):
        hits, passes = views.at(centers, VOXEL)
        trials = [(dataclasses.asdict(m), scores(m.probability(hits, passes), occupied))
                  for m in models]
        out[name] = {"chosen": chosen(trials), "trials": trials}
    if keep_octomap and TUNING.is_file():  # OctoMap's search, as the last --tune ran it on the same frames
        out["octomap"] = json.loads(TUNING.read_text())["octomap"]
        TUNING.write_text(json.dumps(out, indent=1) + "\n")
        return out
    trials = []
    for hit, miss, (low, high) in itertools.product((0.7, 0.8, 0.9, 0.97), (0.1, 0.2, 0.3, 0.4),
                                                    ((0.1192, 0.971), (0.01, 0.999), (0.001, 0.9999))):
        params = {"hit": hit, "miss": miss, "low": low, "high": high}
        trials.append((params, scores(octomap_probabilities(seq, recon, params, centers)[0], occupied)))
        print(f"octomap {params}: Brier {trials[-1][1]['brier']:.4f}", flush=True)
    out["octomap"] = {"chosen": chosen(trials), "trials": trials}
    TUNING.write_text(json.dumps(out, indent=1) + "\n")
    return out


# -- the report ---------------------------------------------------------------------------------------
def run_one(dataset: str, seed: int, tuning: dict) -> dict:
    from open3d_pnerf.occupancy import SensorModel

    seq, recon = train(dataset, seed)
    t0 = time.perf_counter()
    grid = recon.occupancy_grid(VOXEL)
    grid_s = time.perf_counter() - t0
    centers, occupied = reference(dataset, seq, recon)
    hits, passes = sensor_views(seq, recon).at(centers, VOXEL)
    sensor = SensorModel(**tuning["sensor"]["chosen"]).probability(hits, passes)
    octo, octomap_s = octomap_probabilities(seq, recon, tuning["octomap"]["chosen"], centers)
    octo_default, _ = octomap_probabilities(seq, recon, OCTOMAP_DEFAULT, centers)
    return {"dataset": dataset, "seed": seed, "train_s": recon.stats["training"]["seconds"],
            "grid_s": round(grid_s, 2), "octomap_s": round(octomap_s, 2), "grid_voxels": int(grid.log_odds.size),
            "training_views": len(recon.train_indices),
            "scores": {"grid": scores(grid.probability(centers), occupied), "sensor": scores(sensor, occupied),
                       "octomap": scores(octo, occupied), "octomap_default": scores(octo_default, occupied)}}


METHODS = {"grid": "the grid (model)", "sensor": "the same evidence from the sensor alone",
           "octomap": "OctoMap (tuned)", "octomap_default": "OctoMap (its defaults)"}
COLUMNS = [("Brier", "brier", ".4f"), ("Brier occupied", "brier_occupied", ".3f"), ("Brier free", "brier_free", ".4f"),
           ("ECE", "ece", ".3f"), ("occupied called free", "occupied_called_free", ".4f"),
           ("free called occupied", "free_called_occupied", ".4f"), ("decided", "decided", ".3f")]


def markdown(report: dict) -> str:
    lines = [f"# Occupancy at {VOXEL * 100:g} cm against OctoMap from the same frames", "",
             f"commit {report['commit']}; {report['machine']}", "",
             f"Settings chosen on {TUNE_ON} seed 0 (`--tune`, results/occupancy_tuning.json); the means of seeds "
             f"{report['seeds']} below. The reference: the held-out frames' rays (the synthetic room: exact "
             "renders and the exact mesh's voxels).", ""]
    for dataset in report["datasets"]:
        runs = [r for r in report["runs"] if r["dataset"] == dataset]
        tuned = " (the tuning scene)" if dataset == TUNE_ON else ""
        lines += [f"## {dataset}{tuned}", "",
                  f"{runs[0]['scores']['grid']['voxels']} reference voxels, "
                  f"{100 * runs[0]['scores']['grid']['occupied_share']:.1f}% occupied; "
                  f"{runs[0]['training_views']} training views; grid {np.mean([r['grid_s'] for r in runs]):.1f} s "
                  f"against {np.mean([r['train_s'] for r in runs]):.0f} s of training, OctoMap "
                  f"{np.mean([r['octomap_s'] for r in runs]):.1f} s", "",
                  "| method | " + " | ".join(c[0] for c in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
        for method, label in METHODS.items():
            cells = [format(np.mean([r["scores"][method][key] for r in runs]), fmt) for _, key, fmt in COLUMNS]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tune", action="store_true")
    parser.add_argument("--keep-octomap", action="store_true", help="with --tune: OctoMap's settings as last tuned")
    parser.add_argument("--datasets", default="synthetic,tum,7scenes")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--name", default="occupancy")
    args = parser.parse_args()
    require_shared("tum", "7scenes")
    if args.tune:
        print(json.dumps({k: v["chosen"] for k, v in tune(args.keep_octomap).items() if isinstance(v, dict)}, indent=1))
        return
    tuning = json.loads(TUNING.read_text())
    datasets = [synthetic_room() if d == "synthetic" else d for d in args.datasets.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    runs = []
    for dataset, seed in itertools.product(datasets, seeds):
        runs.append(run_one(dataset, seed, tuning))
        print(dataset, seed, {m: round(s["brier"], 4) for m, s in runs[-1]["scores"].items()}, flush=True)
    report = {"commit": commit(), "machine": machine(), "voxel": VOXEL, "datasets": datasets, "seeds": seeds,
              "tuning": {k: v["chosen"] for k, v in tuning.items() if isinstance(v, dict)}, "runs": runs}
    write_result(args.name, report, markdown(report))


if __name__ == "__main__":
    main()
