"""A reconstruction scored: its renders at the held-out frames beside every other method's
(:func:`heldout_views`) pooled into held-out scores (:func:`score_views`, the metrics of
:mod:`open3d_pnerf.metrics`), the training frames it fits (the depth law is fitted on them), and its
exported sigmas against a synthetic scene's exact surface."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from .camera import pixel_coordinates
from .data.derived import evenly_spaced
from .data.sequence import RGBDSequence
from .error_law import depth_jump
from .errors import InputError
from .metrics import (MIN_AUSE_PIXELS, auce, ause, depth_calibration, depth_errors, distances_to, mse_to_psnr, psnr,
                      sigma_coverage, ssim)
from .raycast import MeshRaycaster


def exact_sigma_coverage(recon, sequence: RGBDSequence, reference: o3d.geometry.TriangleMesh) -> dict:
    """How a reconstruction's exported sigmas hold its exact errors (a synthetic scene, whose exact
    surface `reference` is known): {"fused_depth": ..., "mesh": ...}, each :func:`sigma_coverage`.
    fused_depth: the export views' depth (:func:`~open3d_pnerf.export.export_views`, the sensor's
    fused with the model's) against the reference's depth at the same pixels, where both exist;
    mesh: the distance of each of recon.mesh's vertices to the reference against its sigma
    (recon.mesh_sigma)."""
    from .export import export_views

    if not isinstance(reference, o3d.geometry.TriangleMesh) or not reference.has_triangles():
        raise InputError(f"exact_sigma_coverage(): reference must be the exact surface as an "
                         f"open3d.geometry.TriangleMesh with triangles, got {type(reference).__name__}")
    views = export_views(recon, sequence, progress=False)
    exact, err, sigma = MeshRaycaster(reference), [], []
    for pose, r in zip(views.poses, views.renders):
        h, w = r["depth"].shape
        z = exact.render(pose, views.K, w, h)["depth"]
        scored = (r["depth"] > 0) & np.isfinite(r["depth_std"]) & (z > 0)
        err.append(r["depth"][scored] - z[scored])
        sigma.append(r["depth_std"][scored])
    out = {"fused_depth": sigma_coverage(np.concatenate(err), np.concatenate(sigma))}
    if recon.mesh is not None and recon.mesh_sigma is not None and recon.mesh.has_vertices():
        distance = distances_to(o3d.geometry.PointCloud(recon.mesh.vertices), reference, None)
        out["mesh"] = sigma_coverage(distance, recon.mesh_sigma)
    return out


def heldout_views(recon, sequence: RGBDSequence, surfaces: dict | None = None, scale: float | None = None):
    """Yield, per held-out frame of a Reconstruction, the inputs and every method's render.

    Renders at the training resolution (or `scale` of the sequence). Each item is a dict:
    index (frame), color (H, W, 3) in [0, 1] on the depth grid, depth (H, W) sensor z-depth m
    (0: none), model (Reconstruction.render output at the frame's own exposure), surfaces
    {name: color, depth, hit} of each mesh in `surfaces` ({name: o3d.geometry.TriangleMesh})
    ray-cast at the frame's pose.
    """
    scale = scale or recon.config.image_scale
    seq = sequence.select(recon.holdout_indices).scaled_by(scale)
    K, (h, w) = seq.K, seq.image_size
    casters = {name: MeshRaycaster(mesh) for name, mesh in (surfaces or {}).items()}
    for k, i in enumerate(recon.holdout_indices):
        frame = seq[k]
        yield {"index": int(i), "color": seq.color_on_depth_grid(frame.color, frame.depth) / 255.0,
               "depth": frame.depth,
               "model": recon.render(recon.poses[i], seq.intrinsic, frame=int(i)),
               "surfaces": {name: caster.render(recon.poses[i], K, w, h) for name, caster in casters.items()}}


def score_views(views, min_opacity: float, dof: float = np.inf, common_of=None, sensor_based=()) -> dict:
    """Held-out scores of the model and each surface, pooled over the frames (items of
    :func:`heldout_views`): {"model": {...}, name: {...} for each surface}.

    The model covers a pixel where its opacity reaches `min_opacity`, a surface where its ray
    cast hits. Pixel sets: each method's own hits, the "common" pixels that every method named in
    `common_of` covers (default: all; scored for those methods only), and for those of them not in
    `sensor_based`, the pixels each covers that no method in `sensor_based` covers ("only": what
    the model alone fills). Keys (depth in m; shares of the pixels with sensor depth): psnr and ssim
    (the whole frame, a surface's misses black; means over frames, the NeRF convention), psnr_hits
    and psnr_common (of the squared errors pooled over the frames' pixels),
    coverage, depth_l1 / depth_rmse / depth_rel / depth_pixels (the model: every pixel with
    sensor depth; a surface: its hits), depth_l1_hits, depth_l1_common and common_share,
    depth_l1_only and only_share, holes_at_edges (of the pixels with sensor depth a method does not
    cover, the share beside a depth edge of the held-out depth: :func:`held_out_edges`) and
    edge_share (that share of all pixels with sensor depth: holes_at_edges if holes fell anywhere),
    depth_l1_common_edges and depth_l1_common_flat (depth L1 on the common pixels beside a depth
    edge and away from every one), psnr_edges and psnr_flat (the same split of the whole frame's
    colour, pooled over the frames' pixels, a pixel without sensor depth counting as an edge);
    the model's depth calibration under its error law (`dof` degrees of freedom): within_1..3 and
    nll over every pixel with sensor depth, within_3_only over its "only" pixels. Without sensor
    depth (image-only sequences): colour only."""
    views = list(views)
    names = ["model", *views[0]["surfaces"]] if views else ["model"]
    common_of = names if common_of is None else list(common_of)
    with_depth = any(v["depth"].any() for v in views)
    pools = {name: _Pool() for name in names}
    for v in views:
        gt, color, sensor = v["depth"], v["color"], v["depth"] > 0
        out = {"model": v["model"], **v["surfaces"]}
        covers = {"model": v["model"]["opacity"] >= min_opacity, **{n: s["hit"] for n, s in v["surfaces"].items()}}
        every = np.ones_like(sensor)
        edges = held_out_edges(gt) if with_depth else None
        common = np.logical_and.reduce([covers[n] for n in common_of])
        by_sensor = np.logical_or.reduce([covers[n] for n in sensor_based]) if sensor_based else ~every
        for name in names:
            o, pool, main = out[name], pools[name], name in common_of
            pool.color(o["color"], color, {"_hits": covers[name], **({"_common": common} if main else {})}, edges)
            if not with_depth:
                continue
            sets = {"": every if name == "model" else covers[name], "_hits": covers[name]}
            if main:
                sets["_common"] = common
            if main and name not in sensor_based:
                sets["_only"] = covers[name] & ~by_sensor
            pool.depth(o["depth"], gt, sensor, sets, edges)
            if name == "model":
                pool.calibration(o["depth"], o["depth_std"], gt, sensor, sets.get("_only", ~every))
    return {name: pool.scores(dof) for name, pool in pools.items()}


EDGE_STEP = 0.1
"""A depth edge of :func:`held_out_edges`: a step of at least this (m) between nearby pixels."""


def held_out_edges(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of a sensor z-depth image (H, W) m (0: none) within the error law's edge
    radius (:func:`~open3d_pnerf.error_law.depth_jump`) of a depth step of at least EDGE_STEP, or of
    a pixel without depth (a silhouette against what the sensor did not return)."""
    return depth_jump(np.where(depth > 0, depth, 1e3)) >= EDGE_STEP  # no depth: as if far away


class _Pool:
    """Squared colour errors and absolute depth errors of several pixel sets, and the model's
    depth with its sigma, gathered over frames (sums for means, arrays for errors and laws)."""

    def __init__(self):
        self.sums: dict[str, list] = {}
        self.frames: dict[str, list[float]] = {"psnr": [], "ssim": []}  # whole-frame scores
        self.depths: list[np.ndarray] = []  # (pred, gt) of the whole set: a surface's hits, the model's every pixel
        self.law: dict[str, list[np.ndarray]] = {"": [], "_only": []}

    def add(self, key: str, values: np.ndarray) -> None:
        total = self.sums.setdefault(key, [0.0, 0])
        total[0] += float(values.sum())
        total[1] += int(values.size)

    def color(self, pred, gt, sets: dict, edges=None) -> None:
        err = ((np.asarray(pred, np.float64) - gt) ** 2).mean(-1)
        self.frames["psnr"].append(mse_to_psnr(err.mean()))
        self.frames["ssim"].append(ssim(pred, gt))
        for suffix, mask in sets.items():
            self.add(f"psnr{suffix}", err[mask])
        if edges is not None:  # where in the frame colour is lost
            for part, where in (("edges", edges), ("flat", ~edges)):
                self.add(f"psnr_{part}", err[where])

    def depth(self, pred, gt, sensor, sets: dict, edges) -> None:
        self.add("holes_at_edges", edges[sensor & ~sets["_hits"]])
        self.add("edge_share", edges[sensor])
        err = np.abs(pred - gt)
        for suffix, mask in sets.items():
            self.add(f"depth_l1{suffix}", err[mask & sensor])
            self.add(f"share{suffix}", (mask & sensor)[sensor])
        if "_common" in sets:  # where on the common pixels the error lies: beside depth edges or away
            for part, where in (("edges", edges), ("flat", ~edges)):
                self.add(f"depth_l1_common_{part}", err[sets["_common"] & sensor & where])
        whole = sets[""] & sensor
        self.depths.append(np.stack([pred[whole], gt[whole]]))

    def calibration(self, pred, std, gt, sensor, only) -> None:
        for suffix, mask in (("", sensor), ("_only", only & sensor)):
            self.law[suffix].append(np.stack([pred[mask], std[mask], gt[mask]]))

    def scores(self, dof: float) -> dict:
        mean = {k: total / count for k, (total, count) in self.sums.items() if count}
        out = {k: mse_to_psnr(v) for k, v in mean.items() if k.startswith("psnr")}
        out.update({k: float(np.mean(v)) for k, v in self.frames.items() if v})
        if self.depths:
            pred, gt = np.concatenate(self.depths, 1)
            out.update({f"depth_{m}": v for m, v in depth_errors(pred, gt, np.ones_like(gt, bool)).items()})
            out.update({k: v for k, v in mean.items()
                        if k.startswith("depth_l1_") or k in ("holes_at_edges", "edge_share")})
            out["coverage"] = mean.get("share_hits", 0.0)
            out.update({f"{name}_share": mean[f"share_{name}"] for name in ("common", "only") if f"share_{name}" in mean})
        for suffix, rows in self.law.items():
            pred, std, gt = np.concatenate(rows, 1) if rows else np.zeros((3, 0))
            if pred.size:
                law = depth_calibration(pred, std, gt, dof=dof)
                out.update(law if not suffix else {f"within_3{suffix}": law["within_3"]})
        frames = [ause(pred - gt, std) for pred, std, gt in self.law[""] if pred.size >= MIN_AUSE_PIXELS]
        if frames:  # the Bayes' Rays protocol: per image, then averaged; AUCE over every pixel
            out.update({k: float(np.mean([f[k] for f in frames])) for k in frames[0]})
            pred, std, gt = np.concatenate(self.law[""], 1)
            out["auce"] = auce(pred - gt, std, dof)
        return {k: round(float(v), 5) for k, v in out.items()}


def _training_frames(recon, sequence: RGBDSequence, frames: int) -> tuple[np.ndarray, RGBDSequence]:
    """(indices, sequence) of up to `frames` of a Reconstruction's training frames, evenly spaced:
    their indices in `sequence` and those frames alone at the training resolution."""
    train = recon.train_indices[evenly_spaced(len(recon.train_indices), frames)]
    return train, sequence.select(train).scaled_by(recon.config.image_scale)


def training_pixels(recon, sequence: RGBDSequence, frames: int = 8, pixels: int = 1024):
    """Yield, for up to `frames` training frames of a Reconstruction (evenly spaced) at the training
    resolution, (i, intrinsic, u, v, z): the frame's index, its o3d PinholeCameraIntrinsic, `pixels`
    random pixels with sensor depth (u, v (P,) float32 tensors on recon.device, drawn from config.seed
    + 2) and their sensor z-depth (P,) m. Held-out frames are never read."""
    train, seq = _training_frames(recon, sequence, frames)
    rng = np.random.default_rng(recon.config.seed + 2)
    for k, i in enumerate(train):
        depth = seq[k].depth.reshape(-1)
        pix = rng.choice(np.flatnonzero(depth > 0), min(pixels, int((depth > 0).sum())), replace=False)
        u, v = (torch.as_tensor(c, dtype=torch.float32, device=recon.device)
                for c in pixel_coordinates(pix, seq.image_size[1]))
        yield int(i), seq.intrinsic, u, v, depth[pix]


def training_psnr(recon, sequence: RGBDSequence, frames: int = 8) -> float:
    """Mean PSNR (dB) of a Reconstruction's renders of up to `frames` of its training frames (evenly
    spaced, at the training resolution and each frame's own exposure) against their colour images:
    how well it fits what it trained on, beside the held-out PSNR (fitting against generalising).
    Held-out frames are never read."""
    train, seq = _training_frames(recon, sequence, frames)
    scores = []
    for k, i in enumerate(train):
        frame = seq[k]
        scores.append(psnr(recon.render(recon.poses[i], seq.intrinsic, frame=int(i))["color"],
                           seq.color_on_depth_grid(frame.color, frame.depth) / 255.0))
    return float(np.mean(scores))


def training_depth_errors(recon, sequence: RGBDSequence, frames: int = 8,
                          pixels: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(err, spread, z, unseen), each (M,) metres: a Reconstruction's depth errors against the
    sensor on its training frames, the raw spread of its depth distribution there (at least 1 um),
    the sensor's z-depth and the rendered point's distance to the observed surfaces
    (recon.observed; 0 without them), at the pixels of :func:`training_pixels`, kept where the
    model's opacity exceeds 0.5."""
    rows = []
    for i, intrinsic, u, v, z in training_pixels(recon, sequence, frames, pixels):
        out = recon.render_pixels(recon.poses[i], intrinsic, u, v)
        ok = out["opacity"] > 0.5
        unseen = recon.unseen_distance(recon.poses[i], np.asarray(intrinsic.intrinsic_matrix), u.cpu().numpy()[ok],
                                       v.cpu().numpy()[ok], out["depth"][ok])
        unseen = np.zeros(ok.sum()) if unseen is None else unseen
        rows.append((np.abs(out["depth"] - z)[ok], np.maximum(out["depth_std"][ok], 1e-6), z[ok], unseen))
    return tuple(np.concatenate(a) for a in zip(*rows)) if rows else (np.zeros(0),) * 4


def heldout_scores(recon, sequence: RGBDSequence, scale: float | None = None) -> dict:
    """The model's held-out scores ({"model": {...}}, see :func:`score_views`)."""
    return score_views(heldout_views(recon, sequence, scale=scale), recon.config.export.min_opacity,
                       recon.depth_error.dof)
