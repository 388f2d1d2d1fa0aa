"""The probabilistic model against Open3D TSDF fusion on the same training frames and poses, fairly:
the same extraction threshold, the same pixels, and the sensor alone beside them; scored on the
held-out frames (and against a reference surface when one exists), with side-by-side figures
(:func:`compare`; :func:`open3d_pnerf.compare_with_tsdf` trains the model first when asked).

The methods (:data:`METHODS`): the model (the field's own renders), the exported mesh (the
sensor's depth fused with the model's), the sensor alone (the same export without the model),
Open3D's TSDF of the training frames extracted at the exported mesh's weight threshold, and the
same TSDF at Open3D's default threshold (a reference row). Depth and colour are scored on the
pixels every method but the reference covers ("common"), on each method's own hits, and on the
pixels that the model or the mesh covers and the sensor-based methods do not ("only": what the
model alone fills), each with its share of the pixels with sensor depth.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np

from ._files import atomic_write
from .data.derived import evenly_spaced
from .data.sequence import RGBDSequence
from .errors import InputError
from .evaluation import heldout_views, score_views
from .metrics import geometry_metrics
from .export import sensor_geometry, write_mesh_ply
from .reconstruction import Reconstruction
from .tsdf import OPEN3D_WEIGHT_THRESHOLD, tsdf_fusion

METHODS = {"model": "model (the field's renders)", "mesh": "exported mesh (sensor + model)",
           "sensor": "sensor alone (the export without the model)", "tsdf": "Open3D TSDF, same threshold",
           "tsdf_default": f"Open3D TSDF, its default threshold (> {OPEN3D_WEIGHT_THRESHOLD:g} views)"}
"""The compared methods by their keys in Comparison.table, with their labels."""
FIGURE_ROWS = {"mesh": "exported mesh", "tsdf": "TSDF"}
"""The surfaces a held-out frame's figure shows below the input and the model, with their row labels."""
SENSOR_BASED = ("sensor", "tsdf")  # "only" pixels: covered by the model (or its mesh) and by neither of these
REFERENCE_ROWS = ("tsdf_default",)  # shown, but not part of the common pixels
ROWS = [  # label, key, factor, format
    ("PSNR, whole frame (dB)", "psnr", 1, ".2f"), ("PSNR on common pixels (dB)", "psnr_common", 1, ".2f"),
    ("PSNR on its own hits (dB)", "psnr_hits", 1, ".2f"),
    ("PSNR beside depth edges, whole frame (dB)", "psnr_edges", 1, ".2f"),
    ("PSNR away from depth edges, whole frame (dB)", "psnr_flat", 1, ".2f"), ("SSIM, whole frame", "ssim", 1, ".3f"),
    ("depth L1 on common pixels (mm)", "depth_l1_common", 1000, ".1f"),
    ("depth L1 on common pixels beside a depth edge (mm)", "depth_l1_common_edges", 1000, ".1f"),
    ("depth L1 on common pixels away from depth edges (mm)", "depth_l1_common_flat", 1000, ".1f"),
    ("common pixels (share of sensor pixels)", "common_share", 1, ".3f"),
    ("depth L1 on its own hits (mm)", "depth_l1_hits", 1000, ".1f"),
    ("its hits (share of sensor pixels)", "coverage", 1, ".3f"),
    ("of the sensor pixels it misses, the share beside a depth edge", "holes_at_edges", 1, ".3f"),
    ("depth L1 where only the model covers (mm)", "depth_l1_only", 1000, ".1f"),
    ("pixels only the model covers (share)", "only_share", 1, ".3f"),
    ("errors within the 99.7% interval there", "within_3_only", 1, ".3f"),
    ("depth L1, every sensor pixel it renders (mm)", "depth_l1", 1000, ".1f"),
    ("errors within 68.3 / 95.4 / 99.7% intervals", "within_1", 1, ".2f"),
    ("AUCE: calibration error over the 5-95% intervals (0: calibrated)", "auce", 1, ".3f"),
    ("AUSE (RMSE / MAE): sigma's ranking of the errors (0: as the errors rank)", "ause_rmse", 1, ".3f"),
    ("accuracy (mm)", "accuracy", 1000, ".1f"), ("completeness (mm)", "completeness", 1000, ".1f"),
    ("Chamfer (mm)", "chamfer", 1000, ".1f")]


@dataclasses.dataclass
class Comparison:
    """Result of :func:`compare_with_tsdf`.

    table: {method: {metric: value}} for the methods of :data:`METHODS` (held-out image, depth
    and calibration scores of :func:`~open3d_pnerf.evaluation.score_views`; accuracy /
    completeness / chamfer / F-scores of each mesh when a reference was given; lengths in
    metres). surfaces: {method: o3d.geometry.TriangleMesh} of the mesh methods. figures: one
    matplotlib Figure per shown held-out frame (rows: input, model, exported mesh, TSDF;
    columns: colour, depth, |depth error|, depth sigma); frames: their frame indices. A method
    with nothing to score (an empty mesh; the model without held-out frames) has no row; an
    image-only sequence has no sensor depth to fuse: "model" and "mesh" at most.
    """

    table: dict
    reconstruction: Reconstruction
    surfaces: dict
    figures: list
    frames: list

    @property
    def tsdf(self):
        """Open3D's TSDF mesh at the exported mesh's threshold (None without sensor depth)."""
        return self.surfaces.get("tsdf")

    def markdown(self) -> str:
        """The table as Markdown (lengths in mm; "-" where a metric does not apply)."""
        return "\n".join(scores_table(self.table)) + "\n"

    def _repr_markdown_(self) -> str:
        """The table, for Jupyter."""
        return self.markdown()

    def save(self, directory) -> Path:
        """Write comparison.json, comparison.md, compare_frame_<i>.png, tsdf_mesh.ply and
        sensor_mesh.ply (the export without the model)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        atomic_write(d / "comparison.json", lambda p: Path(p).write_text(json.dumps(self.table, indent=1)))
        atomic_write(d / "comparison.md", lambda p: Path(p).write_text(self.markdown()))
        for frame, fig in zip(self.frames, self.figures):
            atomic_write(d / f"compare_frame_{frame:04d}.png", lambda p, f=fig: f.savefig(p, dpi=80, format="png"))
        for name, filename in (("tsdf", "tsdf_mesh.ply"), ("sensor", "sensor_mesh.ply")):
            mesh = self.surfaces.get(name)
            if mesh is not None and not mesh.is_empty():
                write_mesh_ply(d / filename, mesh)
        return d


def scores_table(table: dict) -> list[str]:
    """Markdown lines of a comparison's table ({method: {metric: value}}, the methods as columns,
    lengths in mm; "-" where a metric does not apply), with a note when nothing had depth."""
    keys = {k for m in table.values() for k in m}
    rows = ROWS + [(f"F-score @ {k[7:]}", k, 1, ".3f") for k in sorted(keys) if k.startswith("fscore_")]
    lines = ["| metric | " + " | ".join(METHODS.get(n, n) for n in table) + " |", "| --- |" + " --- |" * len(table)]
    for label, key, factor, fmt in rows:
        if key not in keys:
            continue
        cells = []
        for m in table.values():
            if key == "within_1" and key in m:
                cells.append(" / ".join(f"{m[f'within_{k}']:.3f}" for k in (1, 2, 3)))
            elif key == "ause_rmse" and key in m:
                cells.append(f"{m['ause_rmse']:.3f} / {m['ause_mae']:.3f}")
            else:
                cells.append(format(m[key] * factor, fmt) if key in m else "-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if not any(key.startswith("depth_") for key in keys):
        lines += ["", "No depth images: depth and calibration are not scored."]
    return lines


def compare(recon: Reconstruction, sequence: RGBDSequence, reference=None, figure_frames: int = 2,
            voxel_size: float = 0.01, weight_threshold: float | None = None, progress: bool = True) -> Comparison:
    """A trained Reconstruction against the sensor alone and Open3D's TSDF of its training frames
    and poses (see the module's docstring), scored on its held-out frames and against
    `reference`; :func:`open3d_pnerf.compare_with_tsdf` trains one first when asked.
    weight_threshold: the TSDF's (default: the exported mesh's, export.mesh_min_views - 0.5)."""
    if len(recon.poses) != len(sequence):
        raise InputError(f"reconstruction has {len(recon.poses)} frames but the sequence has {len(sequence)}")
    if len(recon.holdout_indices) == 0 and reference is None:
        raise InputError("nothing to compare on: the reconstruction has no held-out frames "
                         "(set config.holdout_every > 0) and no reference surface was given")
    export = recon.config.export
    surfaces = {"mesh": recon.mesh}
    if sequence.has_depth:
        threshold = export.mesh_min_views - 0.5 if weight_threshold is None else weight_threshold
        train = sequence.select(recon.train_indices).scaled_by(recon.config.image_scale)
        depth_max = float(np.linalg.norm(recon.aabb[1] - recon.aabb[0]))  # nothing in the box is farther
        volume = tsdf_fusion(train, recon.poses[recon.train_indices], voxel_size=voxel_size,
                             sdf_trunc=export.mesh_trunc_voxels * voxel_size,
                             depth_max=depth_max, return_volume=True, progress=progress, weight_threshold=threshold)
        surfaces.update({"sensor": sensor_geometry(recon, sequence).mesh, "tsdf": volume.mesh(),
                         "tsdf_default": volume.mesh(OPEN3D_WEIGHT_THRESHOLD)})
    shown = {n: m for n, m in surfaces.items() if m is not None and not m.is_empty()}
    views = list(heldout_views(recon, sequence, shown)) if len(recon.holdout_indices) else []
    table = {}
    if views:
        common = [n for n in ("model", *shown) if n not in REFERENCE_ROWS]
        table = score_views(views, export.min_opacity, recon.depth_error.dof, common_of=common,
                            sensor_based=[n for n in SENSOR_BASED if n in shown])
    table = {name: table.get(name, {}) for name in ("model", *surfaces)}
    if reference is not None:
        for name, mesh in surfaces.items():
            if mesh is None or mesh.is_empty():
                warnings.warn(f"{METHODS[name]} has no mesh: geometry metrics skipped")
                continue
            table[name].update({k: round(v, 5) for k, v in geometry_metrics(mesh, reference).items()})
    table = {name: row for name, row in table.items() if row}
    picked = [views[i] for i in evenly_spaced(len(views), figure_frames)]
    return Comparison(table, recon, surfaces, [comparison_figure(v) for v in picked], [v["index"] for v in picked])


def comparison_figure(item: dict):
    """A matplotlib Figure for one held-out frame (an item of evaluation.heldout_views): rows
    input / model / exported mesh / TSDF (the surfaces the item has), columns colour, depth,
    |depth error|, depth sigma (shared colour scales per column; errors and sigmas on the same
    scale). Without sensor depth (image-only sequences) the depth and error panels of the input
    are left empty and the scales follow the model's depth and sigma."""
    from matplotlib.figure import Figure

    gt = item["depth"]
    valid = gt > 0
    model = item["model"]
    dmax = float(np.percentile(gt[valid] if valid.any() else model["depth"], 99))
    err = lambda d, ok: np.where(ok & valid, np.abs(d - gt), np.nan) if valid.any() else None  # noqa: E731
    model_err = err(model["depth"], np.ones_like(valid))
    spread = model_err if model_err is not None else model["depth_std"]
    emax = float(np.nanpercentile(spread, 95)) if np.isfinite(spread).any() else 0.1
    rows = [
        ("input", item["color"], np.where(valid, gt, np.nan) if valid.any() else None, None, None),
        ("model", model["color"], model["depth"], model_err, model["depth_std"]),
    ]
    for name, label in FIGURE_ROWS.items():
        surface = item["surfaces"].get(name)
        if surface is not None:
            rows.append((label, surface["color"], np.where(surface["hit"], surface["depth"], np.nan),
                         err(surface["depth"], surface["hit"]), None))
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
