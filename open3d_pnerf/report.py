"""Markdown reports of a reconstruction run (the command line's report.md and its tables)."""

from __future__ import annotations


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
    if report["scores"]:
        lines += ["## Held-out frames", "", *scores_table(report["scores"]), ""]
        shown = "input, model, TSDF" if "tsdf" in report["scores"] else "input, model"
        lines += [f"![held-out frame: {shown}]({name})" for name in report["figures"]]
    return "\n".join(lines) + "\n"


def scores_table(scores: dict) -> list[str]:
    """Markdown lines: a table of heldout_scores() output and the model's depth calibration
    (image metrics only for sequences without depth)."""
    lines = ["| method | PSNR (dB) | PSNR on TSDF hits | SSIM | depth L1 (mm) |", "| --- | --- | --- | --- | --- |"]
    for name, s in scores.items():
        hits = f"{s['psnr_hits']:.2f}" if "psnr_hits" in s else "-"
        depth = f"{1000 * s['depth_l1']:.1f}" if "depth_l1" in s else "-"
        lines.append(f"| {name} | {s['psnr']:.2f} | {hits} | {s['ssim']:.3f} | {depth} |")
    model = scores["model"]
    if "within_1" not in model:
        return lines + ["", "No depth images: depth and calibration are not scored."]
    return lines + ["", f"Depth calibration (model): {model['within_1']:.2f} / {model['within_2']:.2f} / "
                    f"{model['within_3']:.2f} of held-out errors within the 68.3 / 95.4 / 99.7% intervals of "
                    "the calibrated error law (1/2/3 sigma for a Gaussian): 0.68 / 0.95 / 1.00 if honest."]
