"""Tests of open3d_pnerf.rendering.exposure: per-frame colour gains and their interpolation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from open3d_pnerf.rendering.exposure import ExposureGains, interpolate_gains


def test_gains_start_at_one_and_keep_a_geometric_mean_of_one():
    exposure = ExposureGains(4)
    torch.testing.assert_close(exposure.gains(), torch.ones(4, 3))
    with torch.no_grad():
        exposure.log_gains.copy_(torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]))
    g = exposure.gains()
    # only ratios between frames are learned: the common factor stays in the field
    torch.testing.assert_close(g[:, 0], torch.exp(torch.tensor([-1.5, -0.5, 0.5, 1.5])))
    torch.testing.assert_close(g.log().mean(0), torch.zeros(3), atol=1e-6, rtol=0)


def test_forward_scales_each_ray_by_its_frames_gains_and_clips_at_one():
    exposure = ExposureGains(2)
    with torch.no_grad():
        exposure.log_gains.copy_(torch.log(torch.tensor([[0.5, 1.0, 2.0], [2.0, 1.0, 0.5]])))
    color = torch.tensor([[0.4, 0.4, 0.4], [0.4, 0.4, 0.4], [0.8, 0.2, 0.8]])
    out = exposure(color, torch.tensor([0, 1, 0]))
    # geometric mean per channel is sqrt(0.5 * 2) = 1, so the gains are as set
    torch.testing.assert_close(out, torch.tensor([[0.2, 0.4, 0.8], [0.8, 0.4, 0.2], [0.4, 0.2, 1.0]]))


def test_gains_learn_a_frames_exposure_from_its_colours():
    exposure = ExposureGains(2)
    opt = torch.optim.Adam(exposure.parameters(), lr=0.05)
    scene = torch.rand(200, 3) * 0.5 + 0.2
    frames = torch.arange(200) % 2
    seen = scene * torch.where(frames[:, None] == 0, 0.8, 1.25)  # frame 1 is 1.5625x brighter than frame 0
    for _ in range(300):
        loss = ((exposure(scene, frames) - seen) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    g = exposure.gains().detach()
    torch.testing.assert_close(g[1] / g[0], torch.full((3,), 1.5625), atol=0.02, rtol=0)


def test_interpolate_gains_is_log_linear_in_time_and_constant_beyond_the_ends():
    times = np.array([3.0, 1.0])  # any order
    gains = np.array([[4.0, 1.0, 2.0], [1.0, 1.0, 8.0]])
    out = interpolate_gains(times, gains, np.array([0.0, 1.0, 2.0, 2.5, 5.0]))
    np.testing.assert_allclose(out[:, 0], [1, 1, 2, 2 ** 1.5, 4])  # geometric between 1 and 4
    np.testing.assert_allclose(out[:, 1], 1)
    np.testing.assert_allclose(out[:, 2], [8, 8, 4, 2 ** 1.5, 2])


@pytest.mark.parametrize("n", [1, 3])
def test_interpolate_gains_from_few_frames(n):
    out = interpolate_gains(np.arange(n, dtype=float), np.full((n, 3), 0.9), np.array([-1.0, 0.5, 10.0]))
    np.testing.assert_allclose(out, 0.9)
