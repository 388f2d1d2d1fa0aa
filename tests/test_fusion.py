"""Per-pixel fusion of the sensor's and the model's depth Gaussians (open3d_pnerf.fusion)."""

from __future__ import annotations

import numpy as np
import pytest

from open3d_pnerf.errors import InputError
from open3d_pnerf.camera import pinhole, scale_intrinsic
from open3d_pnerf.fusion import fuse_gaussians, fuse_render_with_sensor, nearest_upsample


def test_two_gaussians_give_the_product_mean_and_sigma():
    # N(1.00, 0.03^2) x N(1.04, 0.04^2): weights 1/9e-4 and 1/16e-4 -> mean 1.0144, sigma 0.024
    mean, sigma = fuse_gaussians(1.00, 0.03, 1.04, 0.04)
    assert mean == pytest.approx((1.00 / 0.03**2 + 1.04 / 0.04**2) / (1 / 0.03**2 + 1 / 0.04**2))
    assert mean == pytest.approx(1.0144)
    assert sigma == pytest.approx(0.024)
    # equal sigmas: the midpoint, sigma / sqrt(2); the order of the two does not matter
    m, s = fuse_gaussians([2.0, 3.0], [0.1, 0.1], [2.2, 3.0], [0.1, 0.1])
    np.testing.assert_allclose(m, [2.1, 3.0])
    np.testing.assert_allclose(s, [0.1 / np.sqrt(2)] * 2)
    np.testing.assert_allclose(fuse_gaussians(1.04, 0.04, 1.00, 0.03), fuse_gaussians(1.00, 0.03, 1.04, 0.04))


def test_a_pixel_with_one_source_keeps_it_and_none_gives_nan():
    nan = np.nan
    mean, sigma = fuse_gaussians([1.5, nan, 1.5, nan, 2.0], [0.02, nan, 0.02, 0.01, 0.0],
                                 [nan, 2.5, 0.0 + nan, nan, 2.1], [0.05, 0.05, 0.05, nan, 0.3])
    np.testing.assert_allclose(mean[:3], [1.5, 2.5, 1.5])
    np.testing.assert_allclose(sigma[:3], [0.02, 0.05, 0.02])
    assert np.isnan(mean[3]) and np.isnan(sigma[3])  # neither
    assert mean[4] == 2.1 and sigma[4] == 0.3  # sigma 0 is no estimate


def test_disagreeing_sources_keep_the_more_certain_one():
    # 0.5 m apart with sigmas 0.01 and 0.1: 5 combined sigmas -> not averaged
    mean, sigma = fuse_gaussians([1.0, 1.0], [0.01, 0.1], [1.5, 1.5], [0.1, 0.01])
    np.testing.assert_allclose(mean, [1.0, 1.5])
    np.testing.assert_allclose(sigma, [0.01, 0.01])
    # just inside the gate they are fused
    d = 2.9 * np.hypot(0.01, 0.1)
    mean, _ = fuse_gaussians(1.0, 0.01, 1.0 + d, 0.1)
    assert 1.0 < mean < 1.0 + 0.02 * d


def test_maps_broadcast_and_a_bad_gate_is_refused():
    mean, sigma = fuse_gaussians(np.ones((4, 5)), 0.1, np.full((4, 5), 1.1), np.full((4, 5), 0.1))
    assert mean.shape == sigma.shape == (4, 5)
    np.testing.assert_allclose(mean, 1.05)
    with pytest.raises(InputError, match="gate must be > 0"):
        fuse_gaussians(1.0, 0.1, 1.0, 0.1, gate=0)


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
