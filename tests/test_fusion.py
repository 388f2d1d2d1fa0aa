"""Per-pixel fusion of the sensor's and the model's depth estimates (open3d_pnerf.fusion)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from open3d_pnerf.errors import InputError
from open3d_pnerf.camera import pinhole, scale_intrinsic
from open3d_pnerf.error_law import GAUSSIAN_SHARES, standard_deviation, standardized_multiple
from open3d_pnerf.fusion import GATE_REJECT, consistent, fuse_depths, fuse_render_with_sensor, nearest_upsample

ONE_SIGMA = GAUSSIAN_SHARES[1]


def test_two_gaussians_give_the_product_mean_and_sigma():
    # N(1.00, 0.03^2) x N(1.04, 0.04^2): weights 1/9e-4 and 1/16e-4 -> mean 1.0144, sigma 0.024
    mean, sigma = fuse_depths(1.00, 0.03, 1.04, 0.04)
    assert mean == pytest.approx((1.00 / 0.03**2 + 1.04 / 0.04**2) / (1 / 0.03**2 + 1 / 0.04**2))
    assert mean == pytest.approx(1.0144)
    assert sigma == pytest.approx(0.024)
    # equal sigmas: the midpoint, sigma / sqrt(2); the order of the two does not matter
    m, s = fuse_depths([2.0, 3.0], [0.1, 0.1], [2.2, 3.0], [0.1, 0.1])
    np.testing.assert_allclose(m, [2.1, 3.0])
    np.testing.assert_allclose(s, [0.1 / np.sqrt(2)] * 2)
    np.testing.assert_allclose(fuse_depths(1.04, 0.04, 1.00, 0.03), fuse_depths(1.00, 0.03, 1.04, 0.04))


def test_a_pixel_with_one_source_keeps_it_and_none_gives_nan():
    nan = np.nan
    mean, sigma = fuse_depths([1.5, nan, 1.5, nan, 2.0], [0.02, nan, 0.02, 0.01, 0.0],
                                 [nan, 2.5, 0.0 + nan, nan, 2.1], [0.05, 0.05, 0.05, nan, 0.3])
    np.testing.assert_allclose(mean[:3], [1.5, 2.5, 1.5])
    np.testing.assert_allclose(sigma[:3], [0.02, 0.05, 0.02])
    assert np.isnan(mean[3]) and np.isnan(sigma[3])  # neither
    assert mean[4] == 2.1 and sigma[4] == 0.3  # sigma 0 is no estimate


def test_disagreeing_sources_keep_the_more_certain_one():
    # 0.5 m apart with sigmas 0.01 and 0.1: 5 combined sigmas -> not averaged
    mean, sigma = fuse_depths([1.0, 1.0], [0.01, 0.1], [1.5, 1.5], [0.1, 0.01])
    np.testing.assert_allclose(mean, [1.0, 1.5])
    np.testing.assert_allclose(sigma, [0.01, 0.01])
    # just inside the gate they are fused
    d = 2.9 * np.hypot(0.01, 0.1)
    mean, _ = fuse_depths(1.0, 0.01, 1.0 + d, 0.1)
    assert 1.0 < mean < 1.0 + 0.02 * d


def test_maps_broadcast_and_a_bad_gate_is_refused():
    mean, sigma = fuse_depths(np.ones((4, 5)), 0.1, np.full((4, 5), 1.1), np.full((4, 5), 0.1))
    assert mean.shape == sigma.shape == (4, 5)
    np.testing.assert_allclose(mean, 1.05)
    with pytest.raises(InputError, match="reject must be in"):
        fuse_depths(1.0, 0.1, 1.0, 0.1, reject=0)


def test_a_student_t_estimate_is_weighted_by_its_variance_not_its_1_sigma_equivalent():
    # a Student-t with 5 dof and 1-sigma equivalent s: its standard deviation (from draws) is wider than s
    draws = np.random.default_rng(0).standard_t(5, 2_000_000)
    one = np.quantile(np.abs(draws), ONE_SIGMA)  # the draws' own 1-sigma equivalent
    assert standard_deviation(1.0, 5) == pytest.approx(np.std(draws) / one, rel=0.01)
    assert standard_deviation(0.02, np.inf) == 0.02 and np.isinf(standard_deviation(0.02, 1.8))
    assert standardized_multiple(GAUSSIAN_SHARES[3]) == pytest.approx(3.0)
    with pytest.raises(InputError, match="no standard deviation"):
        standardized_multiple(0.99, 2.0)
    # model 1.00 (t, 5 dof, s = 0.03) and sensor 1.04 (Gaussian 0.03): weights 1 / sd^2, the sensor counts more
    sd = standard_deviation(0.03, 5)
    mean, sigma = fuse_depths(1.00, 0.03, 1.04, 0.03, dof_a=5)
    assert mean == pytest.approx((1.00 / sd**2 + 1.04 / 0.03**2) / (1 / sd**2 + 1 / 0.03**2))
    assert mean > 1.02 and sigma == pytest.approx((1 / sd**2 + 1 / 0.03**2) ** -0.5)


def test_an_estimate_without_a_variance_adds_nothing_where_the_other_exists():
    # dof 1.8: the variance does not exist, so the sensor is kept (however far the model is) and the model fills holes
    mean, sigma = fuse_depths([1.0, 1.0, 1.0], [0.01, 0.01, 0.01], [1.02, 3.0, np.nan], [0.02, 0.02, 0.02], dof_a=1.8)
    np.testing.assert_allclose(mean, [1.02, 3.0, 1.0])
    np.testing.assert_allclose(sigma, [0.02, 0.02, 0.01])


@pytest.mark.parametrize("dof", [2.5, 3.0, 5.0, 10.0, np.inf])
def test_the_gate_rejects_few_consistent_pairs_whatever_the_tails(dof):
    """Pairs drawn from their own laws (a Student-t model, a Gaussian sensor, sd ratios 0.1 to 10):
    the gate takes at most 0.5% of them for disagreeing. Three 1-sigma equivalents summed as if
    Gaussian (the fusion's former rule) reject 1.6 to 4% of them at 2.5 to 5 dof."""
    rng, n = np.random.default_rng(1), 400_000
    for ratio in (0.1, 0.3, 1.0, 3.0, 10.0):
        s_model, s_sensor = 0.01, 0.01 * ratio
        t = rng.standard_t(dof, n) / stats.t(dof).ppf((1 + ONE_SIGMA) / 2) if np.isfinite(dof) else rng.normal(size=n)
        model = 2.0 + t * s_model  # 1-sigma equivalent s_model
        sensor = 2.0 + rng.normal(0, s_sensor, n)
        sd_model = standard_deviation(s_model, dof)
        rejected = ~consistent(model, sd_model, sensor, s_sensor, dof)
        assert rejected.mean() <= 0.005, (dof, ratio, rejected.mean())
        assert rejected.mean() <= GATE_REJECT + 0.0005, (dof, ratio)  # the README's 0.27%, 6 draw std over
        if np.isfinite(dof) and dof <= 5 and ratio <= 0.3:
            assert (np.abs(model - sensor) > 3 * np.hypot(s_model, s_sensor)).mean() > 0.01  # the former rule
    assert GATE_REJECT < 0.005



def test_nearest_upsample_takes_the_pixel_whose_centre_is_nearest():
    small = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(nearest_upsample(small, (4, 6)), np.repeat(np.repeat(small, 2, 0), 2, 1))
    # the same rule as scale_intrinsic: a 3x upsampled pixel u sees small pixel (u + 0.5) / 3 - 0.5, rounded
    K = scale_intrinsic(pinhole(30, 30, 10.0, 10.0, 14.5, 14.5), 1 / 3)
    assert (K.width, K.height) == (10, 10) and K.get_principal_point() == pytest.approx((4.5, 4.5))
    row = nearest_upsample(np.arange(10.0)[None], (1, 30))[0]
    np.testing.assert_array_equal(row, np.repeat(np.arange(10.0), 3))


def test_a_half_size_render_fills_the_sensor_holes_at_the_sensor_resolution():
    render = {"depth": np.array([[1.0, 2.0]]), "depth_std": np.full((1, 2), 0.01), "opacity": np.ones((1, 2)),
              "color": np.zeros((1, 2, 3))}
    sensor = np.array([[1.1, 0.0, 0.0, 2.0], [0.0, 1.0, 2.0, 0.0]])  # (2, 4): twice the render's size
    out = fuse_render_with_sensor(render, sensor, np.full(sensor.shape, 0.01), min_opacity=0.5, max_std=1.0)
    assert out["depth"].shape == out["opacity"].shape == (2, 4) and out["color"].shape == (2, 4, 3)
    # 1.1 vs 1.0 disagree beyond 3 sigma (equal sigmas: the first one, the model's, is kept); holes take the model
    np.testing.assert_allclose(out["depth"], [[1.0, 1.0, 2.0, 2.0], [1.0, 1.0, 2.0, 2.0]], atol=1e-6)
    np.testing.assert_allclose(out["depth_std"][1, 1], 0.01 / np.sqrt(2), rtol=1e-5)  # both agree: fused
    with pytest.raises(InputError, match="must not be larger"):
        fuse_render_with_sensor(render, sensor[:, :1], np.full((2, 1), 0.01), 0.5, 1.0)


def test_the_fused_export_colours_its_mesh_from_the_training_images_at_the_average_exposure(plane_scene):
    """An untrained model renders no colour worth keeping; the mesh fused with the sensor takes the
    training images' colour, divided by each frame's gains (the model renders the average exposure)."""
    from conftest import tiny_reconstruction

    from open3d_pnerf.export import export_geometry

    seq, _ = plane_scene(color=(200, 100, 50))
    recon = tiny_reconstruction()  # frames 1 and 2 trained
    recon.color_gains = np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [2.0, 2.0, 2.0]])  # they saw it twice as bright
    colors = np.asarray(export_geometry(recon, seq, progress=False).mesh.vertex_colors)
    assert len(colors) > 100
    np.testing.assert_allclose(np.median(colors, 0), np.array([200, 100, 50]) / 255 / 2, atol=2 / 255)
