"""Tests of open3d_pnerf.losses: analytic values of the PNeRF, depth and DS-NeRF losses."""

from __future__ import annotations

import math

import pytest
import torch

from open3d_pnerf.losses import (
    LossWeights,
    color_l1,
    depth_pdf_l1,
    depth_l1,
    distortion,
    dsnerf_loss,
    gaussian_bin_masses,
    total_loss,
)
from open3d_pnerf.rendering import RayRender, render_weights


def uniform_edges(r: int, s: int, near: float = 1.0, far: float = 3.0) -> torch.Tensor:
    return torch.linspace(near, far, s + 1).expand(r, s + 1).contiguous()


def nonuniform_edges(r: int, s: int, near: float = 1.0, far: float = 3.0, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    inner = torch.rand(r, s - 1, generator=g).sort(1).values * (far - near) + near
    return torch.cat([torch.full((r, 1), near), inner, torch.full((r, 1), far)], 1)


def centres(edges: torch.Tensor) -> torch.Tensor:
    return 0.5 * (edges[:, 1:] + edges[:, :-1])


def phi(x: float) -> float:
    return 0.5 * (1 + math.erf(x / math.sqrt(2)))


def make_render(weights: torch.Tensor, edges: torch.Tensor, color: torch.Tensor) -> RayRender:
    t = centres(edges)
    opacity = weights.sum(-1)
    p = weights / (opacity[:, None] + 1e-10)
    depth = (p * t).sum(-1)
    return RayRender(t, edges, weights, color, opacity, depth, (p * (t - depth[:, None]) ** 2).sum(-1))


# -- gaussian_bin_masses -------------------------------------------------------------------
@pytest.mark.parametrize("make_edges", [uniform_edges, nonuniform_edges])
def test_bin_masses_sum_to_one_and_match_the_normal_cdf(make_edges):
    edges = make_edges(4, 24)
    mu = torch.tensor([1.5, 2.0, 2.3, 2.9])
    sigma = torch.tensor([0.2, 0.1, 0.3, 0.25])
    q = gaussian_bin_masses(edges, mu, sigma)
    assert q.shape == (4, 24)
    assert (q >= 0).all()
    torch.testing.assert_close(q.sum(-1), torch.ones(4), atol=1e-5, rtol=0)
    # reference: renormalised Phi differences (sigma is far above half a bin here, no floor)
    for r in range(4):
        widths = edges[r, 1:] - edges[r, :-1]
        k = int(torch.searchsorted(edges[r], mu[r])) - 1
        s = max(float(sigma[r]), 0.5 * float(widths[k]))
        cdf = [phi((float(e) - float(mu[r])) / s) for e in edges[r]]
        ref = torch.tensor([(b - a) / (cdf[-1] - cdf[0]) for a, b in zip(cdf[:-1], cdf[1:])])
        torch.testing.assert_close(q[r], ref, atol=1e-5, rtol=0)


def test_bin_masses_floor_sigma_at_half_the_bin_holding_mu():
    edges = uniform_edges(1, 20)  # bins of 0.1 m on [1, 3]
    mu = torch.tensor([2.05])  # centre of bin 10
    for tiny in (0.0, 1e-9, 1e-4):
        q = gaussian_bin_masses(edges, mu, torch.tensor([tiny]))
        assert torch.isfinite(q).all()
        # sigma floored to 0.05 = half a bin: the bin holds P(|Z| < 1), each neighbour P(1 < Z < 3)
        assert q[0, 10].item() == pytest.approx(phi(1) - phi(-1), abs=1e-4)
        assert q[0, 9].item() == pytest.approx(phi(3) - phi(1), abs=1e-4)
        assert q[0, 11].item() == pytest.approx(phi(3) - phi(1), abs=1e-4)
        assert q[0, 9:12].sum().item() > 0.997
        torch.testing.assert_close(q.sum(), torch.tensor(1.0), atol=1e-5, rtol=0)


def test_bin_masses_floor_uses_the_width_of_the_bin_holding_mu_on_nonuniform_bins():
    edges = torch.tensor([[1.0, 1.1, 1.2, 1.3, 3.1, 3.2]])  # mu in the wide bin [1.3, 3.1]
    mu, sigma = torch.tensor([2.2]), torch.tensor([0.001])
    q = gaussian_bin_masses(edges, mu, sigma)
    s = 0.9  # half of 1.8
    cdf = [phi((e - 2.2) / s) for e in edges[0].tolist()]
    ref = torch.tensor([(b - a) / (cdf[-1] - cdf[0]) for a, b in zip(cdf[:-1], cdf[1:])])
    torch.testing.assert_close(q[0], ref, atol=1e-5, rtol=0)


def test_bin_masses_tiny_sigma_with_mu_on_a_bin_edge_is_finite_and_local():
    edges = uniform_edges(1, 16)
    mu = edges[:, 8].clone()  # exactly on an edge
    q = gaussian_bin_masses(edges, mu, torch.zeros(1))
    assert torch.isfinite(q).all()
    assert q[0, 6:10].sum() > 0.99
    torch.testing.assert_close(q.sum(), torch.tensor(1.0), atol=1e-5, rtol=0)


# -- depth_pdf_l1 ----------------------------------------------------------------------------
@pytest.mark.parametrize("make_edges", [uniform_edges, nonuniform_edges])
def test_depth_pdf_l1_is_zero_for_the_target_itself(make_edges):
    edges = make_edges(3, 32)
    mu = torch.tensor([1.6, 2.0, 2.7])
    sigma = torch.tensor([0.05, 0.2, 0.1])
    q = gaussian_bin_masses(edges, mu, sigma)
    assert depth_pdf_l1(q, edges, mu, sigma).abs().max() < 1e-5
    # only the shape matters: an opacity of 0.6 with the same PDF costs nothing either
    assert depth_pdf_l1(0.6 * q, edges, mu, sigma).abs().max() < 1e-5


def test_depth_pdf_l1_of_disjoint_pdfs_is_two():
    edges = uniform_edges(1, 40)
    mu, sigma = torch.tensor([1.5]), torch.tensor([0.02])
    w = torch.zeros(1, 40)
    w[0, 35] = 1.0  # all mass far from the target
    assert depth_pdf_l1(w, edges, mu, sigma).item() == pytest.approx(2.0, abs=1e-4)


def test_depth_pdf_l1_gradient_step_moves_the_pdf_toward_the_target():
    edges = uniform_edges(1, 32)
    t = centres(edges)
    mu, sigma = torch.tensor([2.0]), torch.tensor([0.15])
    logits = (-((t - 2.4) ** 2) / (2 * 0.15**2)).clone().requires_grad_(True)  # peaked at 2.4

    def state(lg):
        w = 0.9 * torch.softmax(lg, -1)
        return depth_pdf_l1(w, edges, mu, sigma).sum(), (torch.softmax(lg, -1) * t).sum()

    loss0, depth0 = state(logits)
    loss0.backward()
    assert torch.isfinite(logits.grad).all() and logits.grad.abs().sum() > 0
    with torch.no_grad():
        stepped = logits - 2.0 * logits.grad
    loss1, depth1 = state(stepped)
    assert loss1 < loss0 - 1e-3
    assert abs(depth1.item() - 2.0) < abs(depth0.item() - 2.0) - 1e-3


def test_depth_pdf_l1_gradient_through_raw_densities_reduces_the_loss():
    edges = uniform_edges(1, 32)
    mu, sigma = torch.tensor([2.0]), torch.tensor([0.1])
    raw = torch.zeros(1, 32, requires_grad=True)  # sigma = exp(0) = 1/m: mass piles up near 1 m

    def state(r):
        w = render_weights(torch.exp(r), edges)
        p = w / w.sum(-1, keepdim=True)
        return depth_pdf_l1(w, edges, mu, sigma).sum(), (p * centres(edges)).sum()

    loss0, depth0 = state(raw)
    loss0.backward()
    with torch.no_grad():
        stepped = raw - 1.0 * raw.grad
    loss1, depth1 = state(stepped)
    assert loss1 < loss0 - 1e-3
    assert abs(depth1.item() - 2.0) < abs(depth0.item() - 2.0)


def test_depth_pdf_l1_with_all_zero_weights_has_finite_loss_and_gradients():
    edges = uniform_edges(2, 16)
    mu, sigma = torch.tensor([1.5, 2.5]), torch.tensor([0.1, 0.0])
    w = torch.zeros(2, 16, requires_grad=True)
    loss = depth_pdf_l1(w, edges, mu, sigma)
    torch.testing.assert_close(loss, torch.ones(2), atol=1e-5, rtol=0)  # sum of q, p = 0
    loss.sum().backward()
    assert torch.isfinite(w.grad).all()
    # the same through rendering from zero densities
    raw = torch.full((2, 16), -30.0, requires_grad=True)
    sig = torch.relu(raw)  # exactly zero densities
    wr = render_weights(sig, edges)
    assert (wr == 0).all()
    loss = depth_pdf_l1(wr, edges, mu, sigma).sum() + depth_l1(wr, centres(edges), mu).sum()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(raw.grad).all()


# -- depth_l1, colour ------------------------------------------------------------------------
def test_depth_l1_is_the_unnormalised_expected_depth_error():
    w = torch.tensor([[0.2, 0.3, 0.5], [0.1, 0.1, 0.0]])
    t = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    mu = torch.tensor([2.0, 1.0])
    # 0.2 + 0.6 + 1.5 = 2.3 -> 0.3;  0.1 + 0.2 = 0.3 (no renormalisation) -> 0.7
    torch.testing.assert_close(depth_l1(w, t, mu), torch.tensor([0.3, 0.7]))


def test_color_l1_is_mean_absolute_error():
    pred = torch.tensor([[0.0, 0.5, 1.0], [0.2, 0.2, 0.2]])
    target = torch.tensor([[0.1, 0.5, 0.7], [0.2, 0.0, 0.2]])
    assert color_l1(pred, target).item() == pytest.approx((0.1 + 0.3 + 0.2) / 6)


# -- DS-NeRF ---------------------------------------------------------------------------------
def test_dsnerf_loss_is_finite_at_zero_weights_and_prefers_a_peak_at_mu():
    edges = uniform_edges(1, 32)
    t = centres(edges)
    mu, sigma = torch.tensor([2.0]), torch.tensor([0.05])
    zero = torch.zeros(1, 32, requires_grad=True)
    loss0 = dsnerf_loss(zero, t, edges, mu, sigma)
    assert torch.isfinite(loss0).all() and loss0.item() > 0
    loss0.sum().backward()
    assert torch.isfinite(zero.grad).all()
    # analytic value at w = 0: -log(eps) * sum_k exp(-(t_k - mu)^2 / 2 s^2) delta_k
    delta = edges[:, 1:] - edges[:, :-1]
    ref = (-math.log(1e-5) * torch.exp(-((t - 2.0) ** 2) / (2 * 0.05**2)) * delta).sum()
    assert loss0.item() == pytest.approx(ref.item(), rel=1e-5)

    def peaked_at(x):
        return 0.95 * torch.softmax(-((t - x) ** 2) / (2 * 0.05**2), -1)

    at_mu = dsnerf_loss(peaked_at(2.0), t, edges, mu, sigma).item()
    elsewhere = dsnerf_loss(peaked_at(2.6), t, edges, mu, sigma).item()
    assert at_mu < elsewhere - 1.0


def test_distortion_is_mipnerf360s_sum_and_smallest_for_one_compact_peak():
    # two bins [0, 1], [1, 3] with weights 0.3, 0.5: 2 * 0.3 * 0.5 * |0.5 - 2| + (0.09 * 1 + 0.25 * 2) / 3
    value = distortion(torch.tensor([[0.3, 0.5]]), torch.tensor([[0.0, 1.0, 3.0]]))
    assert value.item() == pytest.approx(0.45 + 0.59 / 3)
    g = torch.Generator().manual_seed(0)  # the O(S) form equals the pairwise double sum
    w = torch.rand(4, 9, generator=g)
    edges = torch.sort(torch.rand(4, 10, generator=g), -1).values
    mid, delta = (edges[:, 1:] + edges[:, :-1]) / 2, edges[:, 1:] - edges[:, :-1]
    pairs = (w[:, :, None] * w[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()).sum((1, 2))
    torch.testing.assert_close(distortion(w, edges), pairs + (w**2 * delta).sum(-1) / 3)
    # the same mass in one bin scores lower than split between two far apart
    edges = uniform_edges(1, 32)
    one, two = torch.zeros(1, 32), torch.zeros(1, 32)
    one[0, 10], two[0, [5, 25]] = 0.8, 0.4
    assert distortion(one, edges).item() < distortion(two, edges).item()


def test_total_loss_adds_the_distortion_of_every_ray_only_when_weighted(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    render = make_render(w, edges, color)
    mu, sigma = torch.tensor([1.5, float("nan"), 2.5]), torch.full((3,), 0.1)
    off = total_loss("pnerf", [render], target, mu, sigma)
    on = total_loss("pnerf", [render], target, mu, sigma, LossWeights(distortion=0.2))
    torch.testing.assert_close(on["distortion"], distortion(w, edges).mean())  # every ray, with a target or not
    torch.testing.assert_close(on["loss"], off["loss"] + 0.2 * on["distortion"])
    assert off["distortion"].item() == 0.0


# -- total_loss ------------------------------------------------------------------------------
@pytest.fixture
def two_ray_batch():
    edges = uniform_edges(3, 32)
    t = centres(edges)
    g = torch.Generator().manual_seed(3)
    w = 0.8 * torch.softmax(torch.randn(3, 32, generator=g), -1)
    color = torch.rand(3, 3, generator=g)
    target = torch.rand(3, 3, generator=g)
    return edges, t, w, color, target


def test_total_loss_photometric_ignores_depth_targets(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    render = make_render(w, edges, color)
    sigma = torch.full((3,), 0.1)
    losses = [
        total_loss("photometric", [render], target, torch.tensor(m), sigma)["loss"].item()
        for m in ([1.2, 1.5, 2.0], [2.8, 2.9, 1.1], [float("nan")] * 3)
    ]
    assert losses[0] == losses[1] == losses[2]
    assert losses[0] == pytest.approx(color_l1(color, target).item())


def test_total_loss_combines_terms_with_the_gains(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    render = make_render(w, edges, color)
    mu, sigma = torch.tensor([1.5, 2.0, 2.5]), torch.tensor([0.1, 0.2, 0.05])
    gains = LossWeights(color=2.0, depth_pdf=0.5, depth=3.0)
    out = total_loss("pnerf", [render], target, mu, sigma, gains)
    c = color_l1(color, target)
    d = depth_pdf_l1(w, edges, mu, sigma).mean()
    z = depth_l1(w, t, mu).mean()
    torch.testing.assert_close(out["color"], c)
    torch.testing.assert_close(out["depth_pdf"], d)
    torch.testing.assert_close(out["depth"], z)
    torch.testing.assert_close(out["loss"], 2.0 * c + 0.5 * d + 3.0 * z)
    # coarse + fine: every term is summed over the renders
    both = total_loss("pnerf", [render, render], target, mu, sigma, gains)
    torch.testing.assert_close(both["loss"], 2 * out["loss"])


def test_total_loss_scores_only_the_colour_of_renders_past_depth_renders(two_ray_batch):
    """objective.coarse_color: the coarse render adds its colour term, the depth terms and the
    distortion score the fine render alone."""
    edges, t, w, color, target = two_ray_batch
    fine = make_render(w, edges, color)
    coarse = make_render(0.5 * torch.flip(w, [1]), edges, torch.rand(3, 3, generator=torch.Generator().manual_seed(9)))
    mu, sigma = torch.tensor([1.5, 2.0, 2.5]), torch.tensor([0.1, 0.2, 0.05])
    gains = LossWeights(color=2.0, depth_pdf=0.5, depth=3.0, distortion=0.2)
    alone = total_loss("pnerf", [fine], target, mu, sigma, gains)
    out = total_loss("pnerf", [fine, coarse], target, mu, sigma, gains, depth_renders=1)
    for name in ("depth_pdf", "depth", "distortion"):
        torch.testing.assert_close(out[name], alone[name])
    torch.testing.assert_close(out["color"], color_l1(color, target) + color_l1(coarse.color, target))
    torch.testing.assert_close(out["loss"], alone["loss"] + 2.0 * color_l1(coarse.color, target))
    assert total_loss("pnerf", [fine, coarse], target, mu, sigma, gains)["depth"].item() > alone["depth"].item()


def test_total_loss_rays_without_target_contribute_only_colour(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    mu = torch.tensor([1.5, float("nan"), 2.5])
    sigma = torch.tensor([0.1, float("nan"), 0.05])
    out = total_loss("pnerf", [make_render(w, edges, color)], target, mu, sigma)
    assert torch.isfinite(out["loss"])
    has = torch.tensor([True, False, True])
    # depth terms averaged over the 2 rays that have a target, not over all 3
    torch.testing.assert_close(out["depth_pdf"], depth_pdf_l1(w[has], edges[has], mu[has], sigma[has]).mean())
    torch.testing.assert_close(out["depth"], depth_l1(w[has], t[has], mu[has]).mean())
    # changing the weights of the target-less ray (same colour) changes nothing
    w2 = w.clone()
    w2[1] = torch.flip(w2[1], [0]) * 0.3
    out2 = total_loss("pnerf", [make_render(w2, edges, color)], target, mu, sigma)
    torch.testing.assert_close(out2["loss"], out["loss"])
    # and dsnerf as well
    ds1 = total_loss("dsnerf", [make_render(w, edges, color)], target, mu, sigma)
    ds2 = total_loss("dsnerf", [make_render(w2, edges, color)], target, mu, sigma)
    torch.testing.assert_close(ds1["loss"], ds2["loss"])
    assert ds1["dsnerf"] > 0 and ds1["depth_pdf"] == 0


def test_total_loss_target_weights_scale_each_targets_depth_terms(two_ray_batch):
    """A target's weight (DS-NeRF's reprojection weight) multiplies its depth terms, for every
    method; the mean stays over the rays with a target, and colour is untouched."""
    edges, t, w, color, target = two_ray_batch
    render = make_render(w, edges, color)
    mu, sigma = torch.tensor([1.5, 2.0, float("nan")]), torch.tensor([0.1, 0.2, float("nan")])
    weight = torch.tensor([0.25, 1.0, 7.0])  # the target-less ray's weight plays no part
    out = total_loss("pnerf", [render], target, mu, sigma, target_weight=weight)
    has = torch.tensor([True, True, False])
    torch.testing.assert_close(out["depth_pdf"], (depth_pdf_l1(w[has], edges[has], mu[has], sigma[has])
                                                * weight[has]).sum() / 2)
    torch.testing.assert_close(out["depth"], (depth_l1(w[has], t[has], mu[has]) * weight[has]).sum() / 2)
    torch.testing.assert_close(out["color"], color_l1(color, target))
    ds = total_loss("dsnerf", [render], target, mu, sigma, target_weight=weight)
    torch.testing.assert_close(ds["dsnerf"], (dsnerf_loss(w[has], t[has], edges[has], mu[has], sigma[has])
                                              * weight[has]).sum() / 2)
    ones = total_loss("pnerf", [render], target, mu, sigma, target_weight=torch.ones(3))
    torch.testing.assert_close(ones["loss"], total_loss("pnerf", [render], target, mu, sigma)["loss"])


def test_total_loss_all_targets_missing_gives_colour_only_and_finite_gradients(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    color = color.clone().requires_grad_(True)
    nan = torch.full((3,), float("nan"))
    out = total_loss("pnerf", [make_render(w, edges, color)], target, nan, nan)
    torch.testing.assert_close(out["loss"], color_l1(color, target))
    out["loss"].backward()
    assert torch.isfinite(color.grad).all()


def test_total_loss_unknown_kind_raises(two_ray_batch):
    edges, t, w, color, target = two_ray_batch
    with pytest.raises(ValueError, match="unknown loss 'nerf'"):
        total_loss("nerf", [make_render(w, edges, color)], target, torch.ones(3), torch.ones(3))


class DensityOfZ:
    """A stub field for render_rays: density(x) (P,) 1/m of points x (P, 3), grey everywhere."""

    def __init__(self, density):
        self.density = density

    def encode(self, x, known=None):
        return x

    def geometry(self, x, encoded=None):
        return self.density(x), torch.zeros(x.shape[0], 1)

    def color(self, features, d):
        return torch.full((features.shape[0], 3), 0.5)


def rays_along_z(r: int):
    """R rays from the origin along +z, near 0.5 m, far 6 m."""
    from open3d_pnerf.rendering import Rays

    return Rays(torch.zeros(r, 3), torch.tensor([[0.0, 0.0, 1.0]]).expand(r, 3).clone(), torch.full((r,), 0.5),
                torch.full((r,), 6.0), torch.ones(r))


@pytest.mark.parametrize("sigma_z", [0.002, 0.01, 0.05])
def test_the_sigma_floor_never_binds_on_the_fine_render_of_a_target_ray(sigma_z):
    """gaussian_bin_masses floors sigma at half the width of the bin holding mu. On the fine
    render the n_guided depth-guided samples sit on equal-probability slices of the target, so
    that bin is ~sigma sqrt(2 pi) / n_guided wide and the floor stays below sigma: the fine
    density term asks for exactly the target. (It binds on the 16 wide coarse bins, by design.)"""
    from open3d_pnerf.rendering import SamplingConfig, render_rays

    r = 256
    fog = DensityOfZ(lambda x: torch.full((x.shape[0],), 0.3))
    mu = torch.linspace(1.0, 5.0, r)
    sigma = torch.full((r,), sigma_z)
    fine, coarse = render_rays(fog, rays_along_z(r), SamplingConfig(16, 8, 16), mu, sigma,
                               torch.Generator().manual_seed(0), with_coarse=True)

    def half_width_at_mu(edges):
        idx = torch.searchsorted(edges.contiguous(), mu[:, None].contiguous()).clamp(1, edges.shape[1] - 1)
        return 0.5 * (edges.gather(1, idx) - edges.gather(1, idx - 1))[:, 0]

    assert (half_width_at_mu(fine.edges) < sigma).all()
    assert (half_width_at_mu(coarse.edges) > sigma).all()  # coarse bins are ~0.34 wide


def test_on_a_shared_field_the_coarse_terms_reward_density_in_front_of_the_surface():
    """Why `objective.coarse_terms` is off by default: the coarse render composites the 16
    stratified samples alone, each standing for a bin ~0.34 m wide, so where a ray's coarse
    sample falls in front of the surface inside the bin that holds the target, only density at
    that sample (fog in front of the surface) puts the coarse weight in the right bin. The fine
    render, whose guided samples resolve the target, asks for the opposite: a surface at the
    target and nothing in front."""
    from open3d_pnerf.rendering import SamplingConfig, render_rays

    r = 256
    mu, sigma = torch.linspace(1.0, 5.0, r), torch.full((r,), 0.01)

    def surface(fog=0.0, front=0.0):
        """The density whose weights are N(mu, sigma^2) along z (its hazard rate), plus `fog` (1/m)
        from `front` m before mu to 3 sigma before it."""

        def density(x):
            per_ray = x.shape[0] // r
            m, s = mu.repeat_interleave(per_ray), sigma.repeat_interleave(per_ray)
            u = (x[:, 2] - m) / s
            hazard = torch.exp(-0.5 * u**2 - 0.5 * math.log(2 * math.pi) - torch.special.log_ndtr(-u)) / s
            return hazard.clamp(max=1e4) + fog * ((x[:, 2] >= m - front) & (x[:, 2] < m - 3 * s))

        return DensityOfZ(density)

    terms = {}
    for name, field in (("surface", surface()), ("fog in front", surface(20.0, 0.17))):
        fine, coarse = render_rays(field, rays_along_z(r), SamplingConfig(16, 8, 16), mu, sigma,
                                   torch.Generator().manual_seed(0), jitter=False, with_coarse=True)
        terms[name] = [depth_pdf_l1(x.weights, x.edges, mu, sigma).mean().item() for x in (fine, coarse)]
    # measured: fine 0.32 against 1.69, coarse 1.00 against 0.78
    assert terms["surface"][0] < 0.5 * terms["fog in front"][0]  # fine: the surface
    # coarse: the fog (sigma is floored at half a coarse bin, so neither matches the target there)
    assert terms["fog in front"][1] < 0.9 * terms["surface"][1]
