"""The probabilistic model and Open3D TSDF fusion on the same training frames and poses, scored on
the held-out frames (and against a reference surface when one exists), with side-by-side figures
(:func:`compare`; :func:`open3d_pnerf.compare_with_tsdf` trains the model first when asked)."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np

from ._files import atomic_write
from .data.sequence import RGBDSequence, evenly_spaced
from .errors import InputError
from .evaluation import geometry_metrics, heldout_renders, score_renders
from .export import write_mesh_ply
from .reconstruction import Reconstruction
from .tsdf import TSDFVolume, tsdf_fusion


@dataclasses.dataclass
class Comparison:
    """Result of :func:`compare_with_tsdf`.

    table: {"model": {metric: value}, "tsdf": {metric: value}} (held-out image/depth/
    calibration means; accuracy/completeness/chamfer/F-score when a reference was given;
    lengths in metres). figures: one matplotlib Figure per shown held-out frame (rows:
    input, model, TSDF; columns: colour, depth, |depth error|, depth sigma); frames: their
    frame indices. An image-only sequence has no TSDF: tsdf is None, table has "model" only.
    """

    table: dict
    reconstruction: Reconstruction
    tsdf: TSDFVolume | None
    figures: list
    frames: list

    def markdown(self) -> str:
        """The table as Markdown (lengths in mm)."""
        rows = [("PSNR (dB)", "psnr", 1, ".2f"), ("PSNR on TSDF hits (dB)", "psnr_hits", 1, ".2f"),
                ("SSIM", "ssim", 1, ".3f"), ("depth L1 (mm)", "depth_l1", 1000, ".1f"),
                ("depth RMSE (mm)", "depth_rmse", 1000, ".1f"), ("errors within 1 sigma", "within_1", 1, ".2f"),
                ("accuracy (mm)", "accuracy", 1000, ".1f"), ("completeness (mm)", "completeness", 1000, ".1f"),
                ("Chamfer (mm)", "chamfer", 1000, ".1f")]
        keys = {k for m in self.table.values() for k in m}
        rows += [(f"F-score @ {k[7:]}", k, 1, ".3f") for k in sorted(keys) if k.startswith("fscore_")]
        names = list(self.table)
        lines = ["| metric | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
        for label, key, factor, fmt in rows:
            if key in keys:
                cells = [format(m[key] * factor, fmt) if key in m else "-" for m in self.table.values()]
                lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"

    def _repr_markdown_(self) -> str:
        """The table, for Jupyter."""
        return self.markdown()

    def save(self, directory) -> Path:
        """Write comparison.json, comparison.md, compare_frame_<i>.png and tsdf_mesh.ply."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        atomic_write(d / "comparison.json", lambda p: Path(p).write_text(json.dumps(self.table, indent=1)))
        atomic_write(d / "comparison.md", lambda p: Path(p).write_text(self.markdown()))
        for frame, fig in zip(self.frames, self.figures):
            atomic_write(d / f"compare_frame_{frame:04d}.png", lambda p, f=fig: f.savefig(p, dpi=80, format="png"))
        mesh = self.tsdf.mesh() if self.tsdf is not None else None
        if mesh is not None and not mesh.is_empty():
            write_mesh_ply(d / "tsdf_mesh.ply", mesh)
        return d


def compare(recon: Reconstruction, sequence: RGBDSequence, reference=None, figure_frames: int = 2,
            voxel_size: float = 0.01, weight_threshold: float | None = None, progress: bool = True) -> Comparison:
    """A trained Reconstruction and the Open3D TSDF fused from its training frames and poses,
    scored on its held-out frames (and against `reference`); see
    :func:`open3d_pnerf.compare_with_tsdf`, which trains one first when asked."""
    if len(recon.poses) != len(sequence):
        raise InputError(f"reconstruction has {len(recon.poses)} frames but the sequence has {len(sequence)}")
    if len(recon.holdout_indices) == 0 and reference is None:
        raise InputError("nothing to compare on: the reconstruction has no held-out frames "
                         "(set config.holdout_every > 0) and no reference surface was given")
    tsdf = None
    if sequence.has_depth:
        train = sequence.select(recon.train_indices).scaled_by(recon.config.image_scale)
        if weight_threshold is None:
            weight_threshold = min(3.0, len(recon.train_indices) / 5)
        depth_max = float(np.linalg.norm(recon.aabb[1] - recon.aabb[0]))  # nothing in the box is farther
        tsdf = tsdf_fusion(train, recon.poses[recon.train_indices], voxel_size=voxel_size, sdf_trunc=4 * voxel_size,
                           depth_max=depth_max, return_volume=True, progress=progress,
                           weight_threshold=weight_threshold)
    renders = list(heldout_renders(recon, sequence, tsdf)) if len(recon.holdout_indices) else []
    table = score_renders(renders) if renders else {"model": {}, "tsdf": {}}
    if reference is not None:
        meshes = [("model", recon.mesh)] + ([("tsdf", tsdf.mesh())] if tsdf is not None else [])
        for name, mesh in meshes:
            if mesh is None or mesh.is_empty():
                warnings.warn(f"{name} has no mesh: geometry metrics skipped")
                continue
            table[name].update({k: round(v, 5) for k, v in geometry_metrics(mesh, reference).items()})
    shown = [renders[i] for i in evenly_spaced(len(renders), figure_frames)]
    return Comparison(table, recon, tsdf, [comparison_figure(r) for r in shown], [r["index"] for r in shown])


def comparison_figure(item: dict):
    """A matplotlib Figure for one held-out frame (an item of evaluation.heldout_renders):
    rows input / model / TSDF, columns colour, depth, |depth error|, depth sigma (shared
    colour scales per column; errors and sigmas on the same scale). Without sensor depth
    (image-only sequences) the depth and error panels of the input are left empty and the
    scales follow the model's depth and sigma."""
    from matplotlib.figure import Figure

    gt = item["depth"]
    valid = gt > 0
    model, tsdf = item["model"], item["tsdf"]
    dmax = float(np.percentile(gt[valid] if valid.any() else model["depth"], 99))
    err = lambda d, ok: np.where(ok & valid, np.abs(d - gt), np.nan) if valid.any() else None  # noqa: E731
    model_err = err(model["depth"], np.ones_like(valid))
    spread = model_err if model_err is not None else model["depth_std"]
    emax = float(np.nanpercentile(spread, 95)) if np.isfinite(spread).any() else 0.1
    rows = [
        ("input", item["color"], np.where(valid, gt, np.nan) if valid.any() else None, None, None),
        ("model", model["color"], model["depth"], model_err, model["depth_std"]),
    ]
    if tsdf is not None:
        rows.append(("TSDF", tsdf["color"], np.where(tsdf["hit"], tsdf["depth"], np.nan),
                     err(tsdf["depth"], tsdf["hit"]), None))
    fig = Figure(figsize=(12, 2.6 * len(rows)), layout="constrained")
    axes = fig.subplots(len(rows), 4, squeeze=False)
    titles = ("colour", "depth (m)", "|depth error| (m)", "depth sigma (m)")
    for r, (name, color, depth, error, sigma) in enumerate(rows):
        images = (color, depth, error, sigma)
        for c, (ax, image) in enumerate(zip(axes[r], images)):
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c])
            if c == 0:
                ax.set_ylabel(name)
            if image is None:
                ax.set_frame_on(False)
                continue
            kw = {} if c == 0 else dict(cmap="viridis" if c == 1 else "magma", vmin=0, vmax=dmax if c == 1 else emax)
            im = ax.imshow(image, **kw)
            if c:
                fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"held-out frame {item['index']}")
    return fig
