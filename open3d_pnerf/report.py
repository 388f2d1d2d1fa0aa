"""Markdown reports of a reconstruction run (the command line's report.md and its tables)."""

from __future__ import annotations

from .comparison import FIGURE_ROWS, scores_table


def report_markdown(report: dict, recon) -> str:
    """report.md of a reconstruct/demo run: tracking, training, timings, geometry and the held-out table."""
    lines = [f"# open3d_pnerf reconstruction: {report['sequence']}", ""]
    if report.get("ate_rmse_m") is not None:
        lines.append(f"- Tracking ATE RMSE vs ground truth: {1000 * report['ate_rmse_m']:.1f} mm")
    tr = report["training"]
    lines += [
        f"- Training: {tr['steps']} steps in {tr['seconds']} s, {tr['samples_per_s'] / 1000:.0f} k samples/s, "
        f"loss {recon.config.loss}, field {recon.config.field}",
        f"- Timings (s): {report['timings']}",
        f"- Mesh: {len(recon.mesh.triangles)} triangles (`mesh.ply`); point cloud: {len(recon.point_cloud.points)} "
        "points with per-point `depth_sigma` (`point_cloud.ply`)",
        "",
    ]
    scores = report["scores"]
    if scores:
        lines += ["## Held-out frames", ""]
        if "tsdf" in scores:
            lines += ["Each method on the held-out frames: on the pixels every method but the last covers, on its "
                      "own hits, and where only the model (or its mesh) covers; the sensor alone is the export "
                      "without the model; the TSDFs are Open3D's of the same training frames and poses (the first "
                      "at the exported mesh's threshold).", ""]
        shown = ", ".join(["input", "model"] + [label for name, label in FIGURE_ROWS.items() if name in scores])
        lines += [*scores_table(scores), "", *(f"![held-out frame: {shown}]({name})" for name in report["figures"])]
    return "\n".join(lines) + "\n"
