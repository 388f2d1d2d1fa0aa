"""Per-pixel fusion of the sensor's and the model's depth Gaussians (open3d_pnerf.fusion)."""

from __future__ import annotations

import numpy as np
import pytest

from open3d_pnerf.errors import InputError
from open3d_pnerf.fusion import fuse_gaussians


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
