"""Tests of open3d_pnerf.evaluation (image, depth, calibration and geometry metrics, held-out
scoring), open3d_pnerf.comparison (the model against TSDF fusion) and the sparse-view frame
split (split_frames with train_views).

Metrics are checked on tiny analytic cases with known values; the end-to-end comparison
trains a short model on the synthetic room (marked slow).
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import open3d as o3d
import pytest

from open3d_pnerf import ReconstructionConfig, RGBDSequence
from open3d_pnerf.comparison import METHODS, Comparison, comparison_figure
from open3d_pnerf.error_law import GAUSSIAN_SHARES, depth_nll, sigma_multiple
from open3d_pnerf.errors import ConfigError, InputError
from open3d_pnerf.evaluation import exact_sigma_coverage, held_out_edges, heldout_views, score_views, training_psnr
from open3d_pnerf.metrics import (auce, ause, depth_calibration, depth_errors, geometry_metrics, psnr, sigma_coverage,
                                  sparsification, ssim)
from open3d_pnerf.pipeline import compare_with_tsdf
from open3d_pnerf.stages import split_frames
from open3d_pnerf.reconstruction import Reconstruction
from open3d_pnerf.synthetic import synthetic_sequence

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


# -- image metrics -----------------------------------------------------------------------------------
def test_psnr_of_a_constant_offset():
    target = np.full((6, 8, 3), 0.5)
    assert psnr(target + 0.1, target) == pytest.approx(20.0)  # mse 0.01
    assert psnr(target - 0.01, target) == pytest.approx(40.0)
    assert psnr(target, target) == float("inf")
    pred = target.copy()
    pred[:, :4] += 0.3  # error only in the left half
    mask = np.zeros((6, 8), bool)
    mask[:, 4:] = True
    assert psnr(pred, target, mask) == float("inf")
    assert psnr(pred, target, ~mask) == pytest.approx(-10 * math.log10(0.09))
    assert psnr(pred, target) == pytest.approx(-10 * math.log10(0.045))


def test_ssim_of_identical_constant_and_noisy_images():
    rng = np.random.default_rng(0)
    image = rng.random((32, 40, 3))
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-6)
    # constant images: SSIM = (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1), C1 = 0.01^2
    a, b = np.full((20, 24, 3), 0.5), np.full((20, 24, 3), 0.6)
    assert ssim(a, b) == pytest.approx((2 * 0.3 + 1e-4) / (0.61 + 1e-4), abs=2e-4)
    noisy = [ssim(np.clip(image + rng.normal(0, s, image.shape), 0, 1), image) for s in (0.02, 0.1, 0.3)]
    assert 1 > noisy[0] > noisy[1] > noisy[2]
    # images smaller than the 11-pixel window (tiny test scenes) use a window that fits
    assert ssim(image[:4, :3], image[:4, :3]) == pytest.approx(1.0, abs=1e-6)
    assert ssim(a[:3, :5], b[:3, :5]) == pytest.approx((2 * 0.3 + 1e-4) / (0.61 + 1e-4), abs=2e-4)


# -- depth metrics -----------------------------------------------------------------------------------
def test_depth_errors_on_known_offsets():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # 0 = no sensor depth: ignored
    pred = np.array([[1.1, 1.8], [4.4, 3.0]])
    out = depth_errors(pred, gt)
    assert out["pixels"] == 3
    assert out["l1"] == pytest.approx((0.1 + 0.2 + 0.4) / 3)
    assert out["rmse"] == pytest.approx(math.sqrt((0.01 + 0.04 + 0.16) / 3))
    assert out["rel"] == pytest.approx((0.1 + 0.1 + 0.1) / 3)
    # non-finite predictions are skipped without a mask; a mask selects pixels
    pred_nan = pred.copy()
    pred_nan[0, 1] = np.nan
    assert depth_errors(pred_nan, gt)["pixels"] == 2 and depth_errors(pred_nan, gt)["l1"] == pytest.approx(0.25)
    valid = np.array([[False, True], [True, True]])
    out = depth_errors(pred, gt, valid)
    assert out["pixels"] == 2 and out["l1"] == pytest.approx(0.3)
    empty = depth_errors(pred, np.zeros_like(gt))
    assert empty["pixels"] == 0 and all(math.isnan(empty[k]) for k in ("l1", "rmse", "rel"))


def test_depth_calibration_counts_errors_within_k_sigma_and_the_nll():
    gt = np.full(5, 2.0)
    pred = gt + np.array([0.5, -1.5, 2.5, -3.5, 0.0])
    std = np.ones(5)
    out = depth_calibration(pred, std, gt)
    assert (out["within_1"], out["within_2"], out["within_3"]) == (0.4, 0.6, 0.8)
    errs = np.array([0.5, 1.5, 2.5, 3.5, 0.0])
    assert out["nll"] == pytest.approx(np.mean(0.5 * errs**2) + HALF_LOG_2PI)
    # sigma 0.1 with errors 0.05: nll = 0.125 + log(0.1) + log(2 pi) / 2; gt = 0 pixels ignored
    out = depth_calibration(np.array([2.05, 1.95, 7.0]), np.full(3, 0.1), np.array([2.0, 2.0, 0.0]))
    assert out["within_1"] == 1.0 and out["nll"] == pytest.approx(0.125 + math.log(0.1) + HALF_LOG_2PI)
    # a calibrated Gaussian gives the textbook fractions
    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.01, 0.1, 200_000)
    gt = rng.uniform(1, 3, sigma.shape)
    out = depth_calibration(gt + rng.standard_normal(sigma.shape) * sigma, sigma, gt)
    for k, expected in ((1, 0.6827), (2, 0.9545), (3, 0.9973)):
        assert out[f"within_{k}"] == pytest.approx(expected, abs=0.004)
    assert out["nll"] == pytest.approx(np.mean(np.log(sigma)) + 0.5 + HALF_LOG_2PI, abs=0.01)
    nan = depth_calibration(gt, sigma, np.zeros_like(gt))
    assert all(math.isnan(v) for v in nan.values())


def test_sigma_multiple_is_1_2_3_for_a_gaussian_and_the_cauchy_quantiles_for_one_dof():
    assert [sigma_multiple(p) for p in (0.6827, 0.9545, 0.9973)] == pytest.approx([1, 2, 3], abs=2e-3)
    # Student-t with 1 dof is Cauchy: the central p interval is +-tan(pi p / 2) scales
    one = math.tan(math.pi * 0.6826894921370859 / 2)
    assert sigma_multiple(0.95, dof=1.0) == pytest.approx(math.tan(math.pi * 0.95 / 2) / one, rel=1e-6)
    assert sigma_multiple(0.6826894921370859, dof=3.0) == pytest.approx(1.0)
    with pytest.raises(InputError, match="probability"):
        sigma_multiple(1.0)


def test_depth_calibration_under_a_student_t_law_counts_its_own_intervals_and_nll():
    """Errors drawn from a Student-t (3 dof) whose central 68.27% is +-sigma: within_1/2/3 are the
    textbook Gaussian shares when scored with dof 3, and too few beyond 1 sigma with a Gaussian."""
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.01, 0.1, 200_000)
    one = 1.19688  # Student-t (3 dof) 84.13% quantile: the half-width of its central 68.27%
    gt = rng.uniform(1, 3, sigma.shape)
    pred = gt + rng.standard_t(3, sigma.shape) * sigma / one
    out = depth_calibration(pred, sigma, gt, dof=3.0)
    for k, expected in ((1, 0.6827), (2, 0.9545), (3, 0.9973)):
        assert out[f"within_{k}"] == pytest.approx(expected, abs=0.004)
    gaussian = depth_calibration(pred, sigma, gt)
    assert gaussian["within_1"] == pytest.approx(0.6827, abs=0.004) and gaussian["within_3"] < 0.98
    assert out["nll"] < gaussian["nll"]  # the law the errors came from explains them better
    # one error at 0 with sigma 1 under 1 dof (Cauchy, scale 1 / tan(0.3413 pi)): nll = log(pi scale)
    scale = 1 / math.tan(math.pi * 0.6826894921370859 / 2)
    assert depth_nll(np.zeros(1), np.ones(1), dof=1.0)[0] == pytest.approx(math.log(math.pi * scale))


# -- geometry metrics --------------------------------------------------------------------------------
def unit_box(dz: float = 0.0) -> o3d.geometry.TriangleMesh:
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    return box.translate((0.0, 0.0, dz))


def open_box() -> o3d.geometry.TriangleMesh:
    """The unit box without its top face z = 1 (5 of 6 faces)."""
    box = unit_box()
    z = np.asarray(box.vertices)[np.asarray(box.triangles)][..., 2]
    box.remove_triangles_by_mask((z == 1.0).all(axis=1))
    box.remove_unreferenced_vertices()
    return box


# Box vs the box shifted by 1 cm along z, per face of the shifted box (area 1 each):
# top: 1 cm from the reference top; bottom (inside the reference): min(1 cm, distance to its
# edges), mean 1 cm - 1.987e-4 m; sides: 0 except a 1 cm strip above z = 1 (mean 5 mm), which
# adds 4 * 0.01 * 0.005 = 2e-4. Mean over 6 faces: 0.0200001 / 6 = 1/3 cm. Within 5 mm: the
# sides below z = 1.005 (3.98) and the bottom's 5 mm border (0.0199): 3.9999 / 6 = 2/3.
SHIFTED_MEAN = 0.01 / 3


def test_geometry_metrics_of_a_box_shifted_by_one_centimetre():
    out = geometry_metrics(unit_box(0.01), unit_box(), thresholds=(0.005, 0.02))
    assert out["accuracy"] == pytest.approx(SHIFTED_MEAN, abs=2e-4)
    assert out["completeness"] == pytest.approx(SHIFTED_MEAN, abs=2e-4)  # symmetric situation
    assert out["chamfer"] == pytest.approx((out["accuracy"] + out["completeness"]) / 2)
    for kind in ("precision", "recall", "fscore"):
        assert out[f"{kind}_5mm"] == pytest.approx(2 / 3, abs=0.01)
        assert out[f"{kind}_20mm"] == 1.0
    assert set(out) == {"accuracy", "completeness", "chamfer"} | {
        f"{k}_{t}" for k in ("precision", "recall", "fscore") for t in ("5mm", "20mm")}
    same = geometry_metrics(unit_box(), unit_box())
    assert same["accuracy"] < 1e-6 and same["completeness"] < 1e-6
    assert same["fscore_20mm"] == same["fscore_50mm"] == 1.0


def test_geometry_metrics_with_point_clouds():
    o3d.utility.random.seed(1)
    ref_points = unit_box().sample_points_uniformly(100_000)
    # a point-cloud reference: completeness (reference -> mesh) is exact
    out = geometry_metrics(unit_box(0.01), ref_points)
    assert out["completeness"] == pytest.approx(SHIFTED_MEAN, abs=2e-4)
    # accuracy is a nearest-point distance: at least the surface distance, plus the spacing
    # of the samples (mean nearest-neighbour distance ~ 0.5 / sqrt(density) = 4 mm)
    assert SHIFTED_MEAN - 2e-4 < out["accuracy"] < SHIFTED_MEAN + 0.006
    # a point-cloud prediction against a mesh: accuracy (points -> mesh) is exact
    pred_points = unit_box(0.01).sample_points_uniformly(100_000)
    out = geometry_metrics(pred_points, unit_box())
    assert out["accuracy"] == pytest.approx(SHIFTED_MEAN, abs=2e-4)


def test_geometry_metrics_of_a_partial_reconstruction():
    # Every point of the open box lies on the full box: accuracy 0, precision 1. A top-face
    # point (x, y, 1) is min(x, 1-x, y, 1-y) from the open box: mean 1/6 over the face, so
    # completeness = (1/6) / 6 = 1/36; within t: the face's border 1 - (1 - 2t)^2.
    out = geometry_metrics(open_box(), unit_box())
    assert out["accuracy"] < 1e-6
    assert out["precision_20mm"] == out["precision_50mm"] == 1.0
    assert out["completeness"] == pytest.approx(1 / 36, abs=5e-4)
    for t in (0.02, 0.05):
        recall = (5 + 1 - (1 - 2 * t) ** 2) / 6
        key = f"{t * 1000:g}mm"
        assert out[f"recall_{key}"] == pytest.approx(recall, abs=0.005)
        assert out[f"fscore_{key}"] == pytest.approx(2 * recall / (1 + recall), abs=0.005)
    # swapped roles: the full box is less accurate than the open box is complete
    swapped = geometry_metrics(unit_box(), open_box())
    assert swapped["accuracy"] == pytest.approx(out["completeness"], abs=5e-4) and swapped["completeness"] < 1e-6


def test_geometry_metrics_rejects_empty_and_foreign_geometry():
    with pytest.raises(InputError, match="pred: the mesh has no triangles"):
        geometry_metrics(o3d.geometry.TriangleMesh(), unit_box())
    with pytest.raises(InputError, match="reference: the point cloud is empty"):
        geometry_metrics(unit_box(), o3d.geometry.PointCloud())
    with pytest.raises(InputError, match="reference must be an open3d.geometry.TriangleMesh or PointCloud"):
        geometry_metrics(unit_box(), np.zeros((10, 3)))
    with pytest.raises(InputError, match="pred must be"):
        geometry_metrics(o3d.t.geometry.TriangleMesh.from_legacy(unit_box()), unit_box())


# -- scoring held-out views -------------------------------------------------------------------------
def view_item(index, model_color_err, model_depth_err, tsdf=True, h=6, w=8):
    """A heldout_views item with known errors: gt colour 0.5, depth 2 m (a missing row); the model
    covers every pixel, the TSDF (if any) the left half."""
    color = np.full((h, w, 3), 0.5)
    depth = np.full((h, w), 2.0, np.float32)
    depth[0] = 0  # no sensor depth: not scored
    model = {"color": color + model_color_err, "depth": depth + model_depth_err,
             "depth_std": np.full((h, w), 0.02, np.float32), "opacity": np.ones((h, w), np.float32)}
    item = {"index": index, "color": color, "depth": depth, "model": model, "surfaces": {}}
    if tsdf:
        item["surfaces"]["tsdf"] = surface(color, depth, columns=range(w // 2), color_err=0.1, depth_err=-0.03)
        item["surfaces"]["tsdf"]["color"][:, w // 2:] += 0.2  # misses: a colour error 0.3
    return item


def surface(color, depth, columns, color_err=0.0, depth_err=0.0):
    """A surface render that hits the pixels of `columns` with known colour and depth errors."""
    hit = np.zeros(depth.shape, bool)
    hit[:, list(columns)] = True
    return {"color": color + color_err, "depth": np.where(hit, depth + depth_err, 0).astype(np.float32), "hit": hit}


def test_score_views_pools_known_errors_over_frames():
    items = [view_item(0, 0.1, 0.01), view_item(4, 0.2, 0.03)]
    scores = score_views(items, min_opacity=0.9, sensor_based=["tsdf"])
    assert set(scores) == {"model", "tsdf"}
    model, tsdf = scores["model"], scores["tsdf"]
    # whole frame: the mean of the frames' PSNRs; on pixel sets: of the errors pooled over frames
    assert model["psnr"] == pytest.approx((20 - 10 * math.log10(0.04)) / 2, abs=1e-4)
    assert model["psnr_common"] == model["psnr_hits"] == pytest.approx(-10 * math.log10((0.01 + 0.04) / 2), abs=1e-4)
    assert model["depth_l1"] == pytest.approx(0.02, abs=1e-5)
    assert model["depth_rmse"] == pytest.approx(math.sqrt((0.01**2 + 0.03**2) / 2), abs=1e-5)
    assert model["depth_rel"] == pytest.approx(0.01, abs=1e-5)
    assert model["depth_pixels"] == 80  # 5 rows x 8, two frames
    assert model["coverage"] == 1.0 and model["common_share"] == 0.5 and model["only_share"] == 0.5
    # errors 0.01 and 0.03 against sigma 0.02: within 1 sigma in the first frame only
    assert (model["within_1"], model["within_2"], model["within_3"]) == (0.5, 1.0, 1.0)
    assert model["within_3_only"] == 1.0
    nll = lambda e: 0.5 * (e / 0.02) ** 2 + math.log(0.02) + HALF_LOG_2PI  # noqa: E731
    assert model["nll"] == pytest.approx((nll(0.01) + nll(0.03)) / 2, abs=1e-4)
    assert model["ssim"] == pytest.approx(np.mean([ssim(i["model"]["color"], i["color"]) for i in items]), abs=1e-5)
    # TSDF: colour error 0.1 on its hits (left half), 0.3 elsewhere; depth 3 cm short on hits
    assert tsdf["psnr_hits"] == tsdf["psnr_common"] == pytest.approx(20.0, abs=1e-4)
    assert tsdf["psnr"] == pytest.approx(-10 * math.log10((0.01 + 0.09) / 2), abs=1e-4)
    assert tsdf["coverage"] == tsdf["common_share"] == 0.5
    assert tsdf["depth_l1"] == tsdf["depth_l1_hits"] == tsdf["depth_l1_common"] == pytest.approx(0.03, abs=1e-5)
    assert tsdf["depth_pixels"] == 40 and "depth_l1_only" not in tsdf and "within_1" not in tsdf
    # the TSDF's holes (columns 4-7 of rows 1-5): row 1 lies beside row 0, which has no depth
    assert tsdf["holes_at_edges"] == pytest.approx(0.2) and "holes_at_edges" not in model
    assert tsdf["edge_share"] == model["edge_share"] == pytest.approx(0.2)  # row 1 of rows 1-5
    # without surfaces only the model is scored
    assert set(score_views([view_item(0, 0.1, 0.01, tsdf=False)], 0.9)) == {"model"}


def test_score_views_splits_errors_at_depth_edges():
    """Row 1 lies beside row 0, which has no depth: the common depth pixels (the TSDF's left half)
    there are beside an edge, rows 2-5 away from every one. Colour is split over the whole frame,
    where row 0 itself (no depth) counts as beside an edge."""
    item = view_item(0, 0.1, 0.01)
    item["model"]["depth"][1] = item["depth"][1] + 0.2  # the model is 0.2 m off beside the edge only
    item["model"]["color"][1] += 0.2  # and its colour 0.3 off there
    model, tsdf = (score_views([item], min_opacity=0.9)[n] for n in ("model", "tsdf"))
    assert model["depth_l1_common_edges"] == pytest.approx(0.2, abs=1e-6)
    assert model["depth_l1_common_flat"] == pytest.approx(0.01, abs=1e-6)
    assert model["depth_l1_common"] == pytest.approx((4 * 0.2 + 16 * 0.01) / 20, abs=1e-6)
    assert tsdf["depth_l1_common_edges"] == tsdf["depth_l1_common_flat"] == pytest.approx(0.03, abs=1e-6)
    # colour over the whole frame: rows 0-1 beside an edge, rows 2-5 away; the TSDF's misses (right
    # half) are 0.3 off
    assert model["psnr_edges"] == pytest.approx(-10 * math.log10((8 * 0.1**2 + 8 * 0.3**2) / 16), abs=1e-4)
    assert model["psnr_flat"] == pytest.approx(20.0, abs=1e-4)
    assert tsdf["psnr_edges"] == tsdf["psnr_flat"] == pytest.approx(-10 * math.log10((0.1**2 + 0.3**2) / 2), abs=1e-4)


def test_score_views_scores_common_own_and_model_only_pixels():
    item = view_item(3, 0.1, 0.01, tsdf=False)
    color, gt, model = item["color"], item["depth"], item["model"]
    model["depth"][:, 4:] = gt[:, 4:] + 0.5  # the model is 0.5 m off right of the sensor-based surfaces
    model["depth_std"][:, 6:] = 0.2  # ... and says so in column 6 only
    model["opacity"][:, 7] = 0.5  # it does not cover column 7
    item["surfaces"] = {"mesh": surface(color, gt, range(6), depth_err=0.02),
                        "sensor": surface(color, gt, range(3)),
                        "tsdf": surface(color, gt, range(4), depth_err=-0.03),
                        "tsdf_default": surface(color, gt, range(2), depth_err=-0.03)}
    scores = score_views([item], min_opacity=0.9, common_of=["model", "mesh", "sensor", "tsdf"],
                         sensor_based=["sensor", "tsdf"])
    model, mesh, sensor, tsdf = (scores[n] for n in ("model", "mesh", "sensor", "tsdf"))
    # common: columns 0-2 (the sensor alone's), 15 of the 40 pixels with sensor depth
    for row in (model, mesh, sensor, tsdf):
        assert row["common_share"] == 0.375
    assert (model["depth_l1_common"], mesh["depth_l1_common"], sensor["depth_l1_common"],
            tsdf["depth_l1_common"]) == pytest.approx((0.01, 0.02, 0.0, 0.03), abs=1e-6)
    # own hits: the model columns 0-6, the mesh 0-5; the model's whole-frame depth counts column 7
    assert model["coverage"] == 0.875 and mesh["coverage"] == 0.75 and tsdf["coverage"] == 0.5
    assert model["depth_l1_hits"] == pytest.approx((20 * 0.01 + 15 * 0.5) / 35, abs=1e-6)
    assert model["depth_l1"] == pytest.approx((20 * 0.01 + 20 * 0.5) / 40, abs=1e-6)
    # only the model: columns 4-6 (the mesh: 4-5), where neither the sensor nor the TSDF covers
    assert model["only_share"] == 0.375 and model["depth_l1_only"] == pytest.approx(0.5, abs=1e-6)
    assert mesh["only_share"] == 0.25 and mesh["depth_l1_only"] == pytest.approx(0.02, abs=1e-6)
    assert model["within_3_only"] == pytest.approx(1 / 3, abs=1e-5)  # column 6's sigma covers 0.5 m
    assert "depth_l1_only" not in sensor and "depth_l1_only" not in tsdf
    # a reference surface outside common_of: its own hits only, and the common pixels do not shrink
    assert "depth_l1_common" not in scores["tsdf_default"] and scores["tsdf_default"]["coverage"] == 0.25
    assert scores["model"]["psnr_common"] == pytest.approx(20.0, abs=1e-4)


def test_held_out_edges_mark_steps_and_missing_depth_within_the_edge_radius():
    depth = np.full((6, 320), 2.0)
    depth[:, :20] = 2.05  # a 5 cm step at column 20: not an edge
    depth[:, 160:] = 2.2  # a 20 cm step: the two pixels each side of it (radius 2 at 320 pixels wide)
    depth[3, 300] = 0  # no depth: the pixels within 2 of it (itself too) are beside an edge
    edges = held_out_edges(depth)
    assert np.flatnonzero(edges[0]).tolist() == [158, 159, 160, 161]
    assert np.argwhere(edges[:, 200:]).tolist() == [[r, c - 200] for r in range(1, 6) for c in range(298, 303)]


# -- comparison table and figure ---------------------------------------------------------------------
def test_comparison_markdown_lists_each_metric_once_in_display_units():
    table = {
        "model": {"psnr": 25.123, "depth_l1_common": 0.0123, "within_1": 0.7, "within_2": 0.9, "within_3": 0.99,
                  "fscore_20mm": 0.5, "fscore_5mm": 0.25},
        "tsdf": {"psnr": 20.0, "psnr_hits": 28.0, "depth_l1_common": 0.02, "fscore_20mm": 0.4},
    }
    text = Comparison(table, None, {}, [], []).markdown()
    assert text == (
        "| metric | model (the field's renders) | Open3D TSDF, same threshold |\n"
        "| --- | --- | --- |\n"
        "| PSNR, whole frame (dB) | 25.12 | 20.00 |\n"
        "| PSNR on its own hits (dB) | - | 28.00 |\n"
        "| depth L1 on common pixels (mm) | 12.3 | 20.0 |\n"
        "| errors within 68.3 / 95.4 / 99.7% intervals | 0.700 / 0.900 / 0.990 | - |\n"
        "| F-score @ 20mm | 0.500 | 0.400 |\n"
        "| F-score @ 5mm | 0.250 | - |\n"
    )


def panels(fig) -> dict:
    """{(row, col): Axes} of a comparison figure's image grid (colour bars excluded)."""
    out = {}
    for ax in fig.axes:
        spec = ax.get_subplotspec()
        if spec is not None:
            out[spec.rowspan.start, spec.colspan.start] = ax
    return out


def test_comparison_figure_shows_inputs_renders_and_errors():
    item = view_item(7, 0.1, 0.01)
    item["model"]["depth"][1, 1] = 2.5
    fig = comparison_figure(item)
    grid = panels(fig)
    assert sorted(grid) == [(r, c) for r in range(3) for c in range(4)]
    assert [grid[r, 0].get_ylabel() for r in range(3)] == ["input", "model", "TSDF"]
    assert [grid[0, c].get_title() for c in range(4)] == ["colour", "depth (m)", "|depth error| (m)", "depth sigma (m)"]
    assert fig.get_suptitle() == "held-out frame 7"
    # input and TSDF have no depth sigma, the input no error map
    assert not grid[0, 2].images and not grid[0, 3].images and not grid[2, 3].images
    assert all(len(grid[r, c].images) == 1 for r, c in grid if (r, c) not in {(0, 2), (0, 3), (2, 3)})
    gt = item["depth"]
    model_err = np.asarray(grid[1, 2].images[0].get_array().filled(np.nan))
    expected = np.where(gt > 0, np.abs(item["model"]["depth"] - gt), np.nan)
    np.testing.assert_allclose(model_err, expected, atol=1e-6)
    assert model_err[1, 1] == pytest.approx(0.5)
    tsdf_err = np.asarray(grid[2, 2].images[0].get_array().filled(np.nan))
    hit = item["surfaces"]["tsdf"]["hit"] & (gt > 0)
    assert np.isnan(tsdf_err[~hit]).all()
    np.testing.assert_allclose(tsdf_err[hit], 0.03, atol=1e-6)
    np.testing.assert_allclose(np.asarray(grid[1, 3].images[0].get_array()), 0.02)
    # with the exported mesh: a row between the model and the TSDF; without surfaces: two rows
    item["surfaces"]["mesh"] = surface(item["color"], gt, range(6), depth_err=0.02)
    grid = panels(comparison_figure(item))
    assert [grid[r, 0].get_ylabel() for r in range(4)] == ["input", "model", "exported mesh", "TSDF"]
    item["surfaces"] = {}
    assert sorted(panels(comparison_figure(item))) == [(r, c) for r in range(2) for c in range(4)]


# -- sparse-view split -------------------------------------------------------------------------------
def test_split_frames_keeps_train_views_evenly_spaced_frames():
    train_all, hold = split_frames(13, 4)
    np.testing.assert_array_equal(hold, [0, 4, 8, 12])
    np.testing.assert_array_equal(train_all, [1, 2, 3, 5, 6, 7, 9, 10, 11])
    train, hold5 = split_frames(13, 4, train_views=5)
    np.testing.assert_array_equal(hold5, hold)  # held-out set unchanged
    np.testing.assert_array_equal(train, [1, 3, 6, 9, 11])  # positions 0, 2, 4, 6, 8 of the 9 others
    # 5 of 15 others: first and last kept, steps of 3.5 positions rounded to 3 or 4
    train, hold = split_frames(20, 4, train_views=5)
    others = split_frames(20, 4)[0]
    positions = np.searchsorted(others, train)
    assert len(train) == 5 and np.isin(train, others).all() and not np.isin(train, hold).any()
    assert train[0] == others[0] == 1 and train[-1] == others[-1] == 19
    assert set(np.diff(positions)) <= {3, 4}
    np.testing.assert_array_equal(split_frames(13, 4, train_views=9)[0], train_all)  # all of them
    np.testing.assert_array_equal(split_frames(10, 0, train_views=4)[0], [0, 3, 6, 9])  # no hold-out
    np.testing.assert_array_equal(split_frames(10, 0, train_views=2)[0], [0, 9])
    with pytest.raises(InputError, match="train_views=10 but only 9"):
        split_frames(13, 4, train_views=10)


@pytest.mark.parametrize("value", [1, -1, 2.5, True])
def test_config_rejects_bad_train_views(value):
    with pytest.raises(ConfigError, match="train_views"):
        ReconstructionConfig.preset("test", train_views=value)


def test_config_accepts_train_views():
    assert ReconstructionConfig.preset("test", train_views=2).train_views == 2
    assert ReconstructionConfig().train_views == 0


# -- compare_with_tsdf -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_room():
    return synthetic_sequence(12, 160, 120)


def stub_reconstruction(n: int, holdout=()) -> Reconstruction:
    """A Reconstruction of an untrained field, for argument checks that fail before any render."""
    intrinsic = o3d.camera.PinholeCameraIntrinsic(80, 60, 65.6, 65.6, 39.5, 29.5)
    train = [i for i in range(n) if i not in holdout]
    config = ReconstructionConfig.preset("test", progress=False)
    return Reconstruction(config.build_field(np.array([[-3, -3, -1], [3, 3, 3]])), config, np.tile(np.eye(4), (n, 1, 1)),
                          np.zeros((n, 6, 6)), intrinsic, train, list(holdout))


def test_compare_with_tsdf_rejects_bad_inputs(small_room):
    seq = small_room.sequence
    with pytest.raises(InputError, match="sequence must be an RGBDSequence"):
        compare_with_tsdf([np.zeros((4, 4))], reconstruction=stub_reconstruction(12))
    with pytest.raises(InputError, match="no held-out frames"):
        compare_with_tsdf(seq, reconstruction=stub_reconstruction(12), progress=False)
    with pytest.raises(InputError, match="has 10 frames but the sequence has 12"):
        compare_with_tsdf(seq, reconstruction=stub_reconstruction(10, holdout=(0, 4, 8)), progress=False)
    with pytest.raises(InputError, match="reconstruction must be a Reconstruction"):
        compare_with_tsdf(seq, reconstruction="model.pt", progress=False)


@pytest.fixture(scope="module")
def comparison(small_room):
    # 60 steps leave depth spreads ~1 m: lower the export thresholds so that the model has a
    # mesh to score. The TSDF is extracted at the exported mesh's threshold (seen once).
    config = ReconstructionConfig.preset("test", holdout_every=4, progress=False, max_steps=60,
                                         export={"min_opacity": 0.5, "max_point_std": 1.0})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = compare_with_tsdf(small_room.sequence, config, poses=small_room.sequence.gt_poses,
                                   reference=small_room.reference_points(), progress=False)
    assert not [w for w in caught if "no mesh" in str(w.message)]  # every method has geometry to score
    return result


METRICS = ("psnr", "psnr_hits", "depth_l1", "depth_l1_hits", "coverage")
GEOMETRY = ("accuracy", "completeness", "fscore_20mm")  # of each mesh: every method but the field's renders
COMMON = ("psnr_common", "depth_l1_common", "common_share")


@pytest.mark.slow
def test_compare_with_tsdf_on_the_synthetic_room(comparison, small_room):
    c = comparison
    recon = c.reconstruction
    np.testing.assert_array_equal(recon.holdout_indices, [0, 4, 8])
    np.testing.assert_array_equal(recon.train_indices, [1, 2, 3, 5, 6, 7, 9, 10, 11])
    np.testing.assert_array_equal(recon.poses, small_room.sequence.gt_poses)
    assert list(c.table) == ["model", "mesh", "sensor", "tsdf", "tsdf_default"]
    for name, row in c.table.items():
        assert set(METRICS) <= set(row) and (set(GEOMETRY) <= set(row)) == (name != "model"), name
        assert all(math.isfinite(v) for v in row.values()), (name, row)
        assert (set(COMMON) <= set(row)) == (name != "tsdf_default"), name
    # the same common pixels for every method; the model-only pixels for the model and its mesh
    assert len({c.table[n]["common_share"] for n in ("model", "mesh", "sensor", "tsdf")}) == 1
    assert {n for n, row in c.table.items() if "depth_l1_only" in row} == {"model", "mesh"}
    model, tsdf, default = c.table["model"], c.table["tsdf"], c.table["tsdf_default"]
    assert model["within_1"] <= model["within_2"] <= model["within_3"]
    # the same threshold as the exported mesh (seen once) keeps more of the TSDF than Open3D's
    # default (seen more than 3 times) with 9 views around the room
    assert 0.5 < tsdf["coverage"] <= 1 and default["coverage"] < tsdf["coverage"]
    assert len(c.surfaces["tsdf"].triangles) > len(c.surfaces["tsdf_default"].triangles)
    # exact poses and Kinect-like noise: the TSDF's depth where it hits is ~2 cm off the
    # (noisy) held-out depth, most of it the held-out frame's own noise; so is the sensor alone's
    assert tsdf["depth_l1_hits"] < 0.03 and c.table["sensor"]["depth_l1_hits"] < 0.03
    assert tsdf["psnr_hits"] > tsdf["psnr"]  # misses render black
    # figures: evenly spread held-out frames (first and last): input, model, exported mesh, TSDF
    assert c.frames == [0, 8] and len(c.figures) == 2
    for fig in c.figures:
        assert sorted(panels(fig)) == [(r, col) for r in range(4) for col in range(4)]
    # the table's held-out scores are those of heldout_views + score_views
    items = list(heldout_views(recon, small_room.sequence, c.surfaces))
    assert [i["index"] for i in items] == [0, 4, 8]
    assert items[0]["color"].shape == (60, 80, 3) and items[0]["depth"].shape == (60, 80)
    assert set(items[0]["model"]) >= {"color", "depth", "depth_std", "opacity"}
    assert items[0]["surfaces"]["tsdf"]["hit"].shape == (60, 80)
    rescored = score_views(items, recon.config.export.min_opacity, recon.depth_error.dof,
                           common_of=["model", "mesh", "sensor", "tsdf"], sensor_based=["sensor", "tsdf"])
    for name in c.table:
        for key, value in rescored[name].items():
            assert c.table[name][key] == pytest.approx(value, abs=1e-5), (name, key)
    assert all(i["surfaces"] == {} for i in heldout_views(recon, small_room.sequence))


def test_sigma_coverage_of_gaussian_errors_gives_the_gaussian_shares():
    rng = np.random.default_rng(3)
    sigma = rng.uniform(0.005, 0.05, 200_000)
    shares = sigma_coverage(rng.normal(0, sigma), sigma)
    assert shares["count"] == 200_000
    for k in (1, 2, 3):
        assert shares[f"within_{k}"] == pytest.approx(GAUSSIAN_SHARES[k], abs=0.004)
    assert sigma_coverage(0.5 * rng.normal(0, sigma), sigma)["within_1"] > 0.95  # too wide: over-covers
    assert math.isnan(sigma_coverage(np.zeros(0), np.zeros(0))["within_2"])


@pytest.mark.slow
def test_exact_sigma_coverage_scores_the_export_against_the_exact_surface(comparison, small_room):
    coverage = exact_sigma_coverage(comparison.reconstruction, small_room.sequence, small_room.mesh)
    for part in ("fused_depth", "mesh"):
        shares = coverage[part]
        assert shares["count"] > 1000, part
        assert 0 < shares["within_1"] <= shares["within_2"] <= shares["within_3"] <= 1, part
    recon = comparison.reconstruction
    assert coverage["mesh"]["count"] == len(recon.mesh.vertices)
    # the sensor's noise model is the synthetic sensor's: its fused depth errors are mostly inside 3 sigma
    assert coverage["fused_depth"]["within_3"] > 0.9
    with pytest.raises(InputError, match="reference must be the exact surface"):
        exact_sigma_coverage(recon, small_room.sequence, small_room.reference_points())


@pytest.mark.slow
def test_training_psnr_scores_the_training_frames_alone(comparison, small_room):
    recon, seq = comparison.reconstruction, small_room.sequence

    def with_black(frames):  # the room with the colour of `frames` black
        images = [(np.zeros_like(seq[i].color) if i in frames else seq[i].color, seq[i].depth) for i in range(len(seq))]
        return RGBDSequence.from_rgbd_images(images, seq.intrinsic, gt_poses=seq.gt_poses)

    score = training_psnr(recon, seq)
    assert 10 < score < 60
    assert training_psnr(recon, with_black(set(recon.holdout_indices))) == pytest.approx(score, abs=1e-6)
    assert training_psnr(recon, with_black(set(recon.train_indices))) < score - 3


@pytest.mark.slow
def test_comparison_save_and_markdown(comparison, tmp_path):
    c = comparison
    text = c.markdown()
    lines = text.splitlines()
    assert lines[0] == "| metric | " + " | ".join(METHODS.values()) + " |"
    labels = [line.split(" | ")[0][2:] for line in lines[2:]]
    for label in ("PSNR, whole frame (dB)", "depth L1 on common pixels (mm)", "pixels only the model covers (share)",
                  "accuracy (mm)", "completeness (mm)", "F-score @ 20mm", "F-score @ 50mm"):
        assert labels.count(label) == 1, label
    assert all(line.count("|") == 7 for line in lines)
    row = lines[2 + labels.index("depth L1 on common pixels (mm)")]
    cells = [f"{c.table[n]['depth_l1_common'] * 1000:.1f}" for n in ("model", "mesh", "sensor", "tsdf")]
    assert row == "| depth L1 on common pixels (mm) | " + " | ".join(cells) + " | - |"
    out = c.save(tmp_path / "cmp")
    assert json.loads((out / "comparison.json").read_text()) == c.table
    assert (out / "comparison.md").read_text() == text
    for frame in c.frames:
        assert (out / f"compare_frame_{frame:04d}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for name in ("tsdf_mesh.ply", "sensor_mesh.ply"):
        mesh = o3d.io.read_triangle_mesh(str(out / name))
        assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors(), name
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["comparison.json", "comparison.md", "tsdf_mesh.ply", "sensor_mesh.ply"]
        + [f"compare_frame_{f:04d}.png" for f in c.frames])


# -- AUSE and AUCE: the uncertainty-NeRF literature's yardsticks ----------------------------------
def test_ause_is_zero_when_sigma_ranks_the_errors_as_they_are():
    err = np.random.default_rng(0).normal(0, 0.02, 5000)
    scores = ause(err, 3 * np.abs(err) + 0.001)  # any increasing function of the error: the oracle order
    assert scores == {"ause_rmse": 0.0, "ause_mae": 0.0}


def test_ause_of_a_sigma_unrelated_to_the_error_is_the_random_order_value():
    rng = np.random.default_rng(1)
    err = rng.normal(0, 0.02, 200_000)
    oracle = sparsification(err, np.abs(err))
    share = np.arange(100) / 100
    for metric in ("rmse", "mae"):  # a random order keeps the whole set's error at every share
        whole = oracle[metric][0]
        gap = (whole - oracle[metric]) / whole
        expected = float(np.sum((gap[1:] + gap[:-1]) / 2 * np.diff(share)))
        assert ause(err, rng.random(err.size))[f"ause_{metric}"] == pytest.approx(expected, abs=0.01)
        assert expected > 0.3


def test_auce_is_near_zero_for_the_right_law_and_large_for_a_wrong_one():
    rng = np.random.default_rng(2)
    sigma = rng.uniform(0.005, 0.05, 200_000)
    gaussian = rng.normal(0, sigma)
    assert auce(gaussian, sigma) < 0.005
    assert auce(gaussian, sigma / 2) > 0.2  # over-confident: every interval holds less than it claims
    heavy = rng.standard_t(2.5, sigma.size) * sigma
    from scipy import stats

    scale = stats.t(2.5).ppf((1 + GAUSSIAN_SHARES[1]) / 2)  # the Student-t's 1-sigma equivalent in its units
    assert auce(heavy, sigma * scale, dof=2.5) < 0.005
    assert auce(heavy, sigma * scale) > auce(heavy, sigma * scale, dof=2.5) + 0.02
    assert np.isnan(auce(np.zeros(0), np.zeros(0)))
