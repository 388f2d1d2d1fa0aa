"""Tests of open3d_pnerf.rendering: rays, samplers and volume rendering on analytic scenes."""

from __future__ import annotations

import math

import pytest
import torch

from open3d_pnerf.rendering import (
    Rays,
    SamplingConfig,
    bin_edges,
    composite,
    depth_guided,
    importance,
    intersect_aabb,
    make_rays,
    merge,
    pixel_rays,
    render_rays,
    render_weights,
    stratified,
    weight_quantile,
)

FX, FY, CX, CY = 200.0, 180.0, 79.5, 59.5
K = torch.tensor([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])


def rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def pose_of(R: torch.Tensor, t) -> torch.Tensor:
    T = torch.eye(4)
    T[:3, :3] = R
    T[:3, 3] = torch.as_tensor(t, dtype=torch.float32)
    return T


def rays_along_z(r: int, near: float = 1.0, far: float = 3.0) -> Rays:
    return Rays(torch.zeros(r, 3), torch.tensor([[0.0, 0.0, 1.0]]).expand(r, 3).clone(),
                torch.full((r,), near), torch.full((r,), far), torch.ones(r))


# -- rays --------------------------------------------------------------------------------
def test_pixel_rays_opencv_axes_and_unit_directions():
    u = torch.tensor([CX, CX + FX, CX, CX - 2 * FX, 0.0])
    v = torch.tensor([CY, CY, CY + FY, CY - FY, 0.0])
    origins, dirs, norms = pixel_rays(torch.eye(4), K, u, v)
    k = torch.tensor(
        [[0.0, 0, 1], [1, 0, 1], [0, 1, 1], [-2, -1, 1], [-CX / FX, -CY / FY, 1]]
    )  # K^-1 [u, v, 1]
    torch.testing.assert_close(norms, k.norm(dim=-1))
    torch.testing.assert_close(dirs, k / k.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(origins, torch.zeros(5, 3))
    # the pixel centre is at integer coordinates: pixel (cx, cy) has no half-pixel offset
    assert dirs[0, 0].item() == 0.0 and dirs[0, 1].item() == 0.0


def test_pixel_rays_follow_a_camera_to_world_pose():
    R = rot_z(0.3) @ rot_x(-0.7)
    t = torch.tensor([0.5, -1.0, 2.0])
    pose = pose_of(R, t)
    u = torch.tensor([CX, CX + FX, 12.0])
    v = torch.tensor([CY, CY, 100.0])
    _, d_cam, _ = pixel_rays(torch.eye(4), K, u, v)
    origins, dirs, norms = pixel_rays(pose, K, u, v)
    torch.testing.assert_close(dirs, d_cam @ R.T)
    torch.testing.assert_close(origins, t.expand(3, 3))
    # the camera's +z axis (optical axis) is the third column of R
    torch.testing.assert_close(dirs[0], R[:, 2])
    # a point at z-depth 2.5 lies at distance 2.5 * ||K^-1 [u, v, 1]|| along the unit ray
    p = origins + 2.5 * norms[:, None] * dirs
    z_cam = ((p - t) @ R)[:, 2]
    torch.testing.assert_close(z_cam, torch.full((3,), 2.5))
    # per-ray poses and intrinsics (batched) agree with the shared ones
    o_b, d_b, _ = pixel_rays(pose.expand(3, 4, 4), K.expand(3, 3, 3), u, v)
    torch.testing.assert_close(d_b, dirs)
    torch.testing.assert_close(o_b, origins)


def test_pixel_rays_origins_are_not_views_of_the_pose():
    pose = pose_of(torch.eye(3), [1.0, 2.0, 3.0])
    origins, _, _ = pixel_rays(pose, K, torch.tensor([1.0]), torch.tensor([2.0]))
    origins += 1
    assert pose[0, 3].item() == 1.0


def test_intersect_aabb_analytic_entry_and_exit():
    box = torch.tensor([[0.0, 0, 0], [1, 1, 1]])
    origins = torch.tensor([[0.5, 0.5, -1.0], [-1.0, 0.5, -1.0], [0.5, 0.5, 3.0], [0.2, 0.3, 0.4]])
    dirs = torch.tensor([[0.0, 0, 1], [1.0, 0, 1], [0.0, 0, -2], [1.0, 0, 0]])
    near, far = intersect_aabb(origins, dirs, box)
    torch.testing.assert_close(near, torch.tensor([1.0, 1.0, 1.0, 0.05]))  # inside: min_near
    torch.testing.assert_close(far, torch.tensor([2.0, 2.0, 1.5, 0.8]))


def test_intersect_aabb_misses_have_far_not_after_near():
    box = torch.tensor([[0.0, 0, 0], [1, 1, 1]])
    origins = torch.tensor([[2.0, 2.0, -1.0], [0.5, 0.5, -1.0], [-1.0, 0.5, 0.5]])
    dirs = torch.tensor([[0.0, 0, 1], [0.0, 0, -1], [0.0, 1, 0]])  # beside, away, parallel outside
    near, far = intersect_aabb(origins, dirs, box)
    assert (far <= near).all()


def test_make_rays_clamps_near_and_gives_misses_a_tiny_interval():
    box = torch.tensor([[-1.0, -1, 1], [1, 1, 3]])
    u = torch.tensor([CX, 10 * FX + CX])  # on axis: hits; far off axis: misses the box
    v = torch.tensor([CY, CY])
    rays = make_rays(torch.eye(4), K, u, v, box, min_near=0.2)
    assert isinstance(rays, Rays) and len(rays) == 2
    assert rays.near[0].item() == pytest.approx(1.0) and rays.far[0].item() == pytest.approx(3.0)
    assert rays.far[1].item() == pytest.approx(rays.near[1].item() + 1e-3)
    assert (rays.near >= 0.2).all()
    # camera inside the box: near is clamped to min_near
    inside = make_rays(pose_of(torch.eye(3), [0, 0, 2.0]), K, u[:1], v[:1], box, min_near=0.2)
    assert inside.near.item() == pytest.approx(0.2) and inside.far.item() == pytest.approx(1.0)
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(2))
    torch.testing.assert_close(rays.norms, torch.tensor([1.0, (1 + 10.0**2) ** 0.5]))
    sub = rays[1:]
    assert len(sub) == 1 and sub.far.item() == rays.far[1].item()


# -- samplers ------------------------------------------------------------------------------
def test_bin_edges_contain_samples_sorted_and_clipped():
    g = torch.Generator().manual_seed(0)
    rays = rays_along_z(8, 0.5, 2.5)
    t = stratified(rays, 16, g)
    e = bin_edges(t, rays.near, rays.far)
    assert e.shape == (8, 17)
    assert (e[:, 1:] >= e[:, :-1]).all()
    assert (e[:, :-1] <= t).all() and (t <= e[:, 1:]).all()
    assert (e[:, 0] >= 0.5).all() and (e[:, -1] <= 2.5).all()
    torch.testing.assert_close(e[:, 1:-1], 0.5 * (t[:, 1:] + t[:, :-1]))
    # uniform mid-slice samples: edges are exactly the slice boundaries
    t0 = stratified(rays, 4, jitter=False)
    torch.testing.assert_close(bin_edges(t0, rays.near, rays.far), torch.linspace(0.5, 2.5, 5).expand(8, 5))
    # a single sample owns [near, far]
    one = bin_edges(torch.full((8, 1), 1.0), rays.near, rays.far)
    torch.testing.assert_close(one, torch.tensor([0.5, 2.5]).expand(8, 2))


def test_stratified_one_sorted_sample_per_slice():
    g = torch.Generator().manual_seed(1)
    rays = Rays(torch.zeros(5, 3), torch.ones(5, 3), torch.tensor([0.1, 0.5, 1.0, 2.0, 0.3]),
                torch.tensor([1.0, 0.9, 4.0, 2.5, 0.4]), torch.ones(5))
    n = 12
    t = stratified(rays, n, g)
    assert t.shape == (5, n)
    assert (t >= rays.near[:, None]).all() and (t <= rays.far[:, None]).all()
    assert (t[:, 1:] >= t[:, :-1]).all()
    slot = ((t - rays.near[:, None]) / (rays.far - rays.near)[:, None] * n).floor().clamp(max=n - 1)
    assert (slot == torch.arange(n)).all()


def test_importance_concentrates_samples_in_the_heavy_bin():
    g = torch.Generator().manual_seed(2)
    edges = torch.linspace(1.0, 3.0, 33).expand(4, 33).contiguous()
    w = torch.zeros(4, 32)
    w[torch.arange(4), torch.tensor([3, 10, 20, 31])] = torch.tensor([1.0, 0.5, 0.05, 0.9])
    s = importance(edges, w, 64, g)
    assert s.shape == (4, 64) and torch.isfinite(s).all()
    assert (s[:, 1:] >= s[:, :-1]).all()
    for r, j in enumerate([3, 10, 20, 31]):
        inside = ((s[r] >= edges[r, j]) & (s[r] <= edges[r, j + 1])).float().mean()
        assert inside > 0.8


def test_importance_with_zero_weights_samples_uniformly():
    edges = torch.linspace(1.0, 3.0, 17).expand(3, 17).contiguous()
    w = torch.zeros(3, 16, requires_grad=True)
    s = importance(edges, w, 64, jitter=False)
    assert torch.isfinite(s).all()
    assert (s >= 1.0).all() and (s <= 3.0).all()
    counts = torch.stack([torch.histc(s[r], bins=16, min=1.0, max=3.0) for r in range(3)])
    assert (counts == 4).all()
    torch.testing.assert_close(s[0], 1.0 + (torch.arange(64) + 0.5) / 64 * 2.0)


def test_depth_guided_samples_lie_within_three_sigma_and_average_to_mu():
    g = torch.Generator().manual_seed(4)
    r = 200
    rays = rays_along_z(r, 0.5, 4.0)
    mu = torch.linspace(1.0, 3.0, r)
    sigma = torch.full((r,), 0.05)
    s = depth_guided(rays, mu, sigma, 32, g)
    assert s.shape == (r, 32)
    assert ((s - mu[:, None]).abs() <= 3 * sigma[:, None] + 1e-5).all()
    assert (s.mean(1) - mu).abs().max() < 0.1 * 0.05
    assert (s[:, 1:] >= s[:, :-1]).all()
    # most samples near the mean (equal-probability slices of the Gaussian)
    assert ((s - mu[:, None]).abs() <= sigma[:, None]).float().mean() > 0.6


def test_depth_guided_clips_to_near_far():
    g = torch.Generator().manual_seed(5)
    rays = rays_along_z(2, 1.0, 2.0)
    s = depth_guided(rays, torch.tensor([1.0, 2.0]), torch.tensor([0.3, 0.3]), 16, g)
    assert (s >= 1.0).all() and (s <= 2.0).all()
    assert (s[0] == 1.0).sum() >= 5 and (s[1] == 2.0).sum() >= 5


def test_merge_sorts_and_returns_the_permutation():
    g = torch.Generator().manual_seed(6)
    a = torch.rand(4, 5, generator=g).sort(1).values
    b = torch.rand(4, 7, generator=g)
    t, order = merge(a, b)
    assert t.shape == (4, 12)
    assert (t[:, 1:] >= t[:, :-1]).all()
    torch.testing.assert_close(t, torch.cat([a, b], 1).gather(1, order))
    assert ((order < 5).sum(1) == 5).all()


# -- volume rendering ------------------------------------------------------------------------
def test_render_weights_constant_density_matches_the_closed_form():
    near, far, n, sig = 0.5, 2.5, 20, 1.3
    edges = torch.linspace(near, far, n + 1, dtype=torch.float64)[None]
    w = render_weights(torch.full((1, n), sig, dtype=torch.float64), edges)
    delta = (far - near) / n
    start = edges[0, :-1]
    expected = torch.exp(-sig * (start - near)) * (1 - math.exp(-sig * delta))
    torch.testing.assert_close(w[0], expected)
    assert w.sum().item() == pytest.approx(1 - math.exp(-sig * (far - near)))


def test_render_weights_nonuniform_bins_total_opacity():
    edges = torch.tensor([[1.0, 1.1, 1.5, 1.6, 3.0]], dtype=torch.float64)
    sigma = torch.tensor([[2.0, 0.5, 4.0, 1.0]], dtype=torch.float64)
    w = render_weights(sigma, edges)
    tau = (sigma * (edges[:, 1:] - edges[:, :-1])).sum()
    assert w.sum().item() == pytest.approx(1 - math.exp(-tau.item()))
    assert w[0, 0].item() == pytest.approx(1 - math.exp(-0.2))
    assert w[0, 1].item() == pytest.approx(math.exp(-0.2) * (1 - math.exp(-0.2)))


def test_composite_single_opaque_bin():
    n, j = 16, 9
    edges = torch.linspace(1.0, 3.0, n + 1)[None]
    t = 0.5 * (edges[:, 1:] + edges[:, :-1])
    sigma = torch.zeros(1, n)
    sigma[0, j] = 1e5
    rgb = torch.rand(1, n, 3, generator=torch.Generator().manual_seed(0))
    out = composite(t, edges, sigma, rgb)
    expected = torch.zeros(1, n)
    expected[0, j] = 1
    torch.testing.assert_close(out.weights, expected)
    assert out.depth.item() == pytest.approx(t[0, j].item(), abs=1e-6)
    assert out.depth_var.item() == pytest.approx(0.0, abs=1e-8)
    assert out.opacity.item() == pytest.approx(1.0)
    torch.testing.assert_close(out.color[0], rgb[0, j])


def test_composite_two_equal_spikes_have_the_known_variance():
    n = 20
    edges = torch.linspace(1.0, 3.0, n + 1, dtype=torch.float64)[None]
    t = 0.5 * (edges[:, 1:] + edges[:, :-1])
    a, b = 4, 15
    sigma = torch.zeros(1, n, dtype=torch.float64)
    sigma[0, a] = math.log(2) / 0.1  # alpha = 1/2 over a 0.1 m bin
    sigma[0, b] = 1e6  # opaque: takes the remaining 1/2
    out = composite(t, edges, sigma, torch.zeros(1, n, 3, dtype=torch.float64))
    assert out.weights[0, a].item() == pytest.approx(0.5)
    assert out.weights[0, b].item() == pytest.approx(0.5)
    ta, tb = t[0, a].item(), t[0, b].item()
    assert out.depth.item() == pytest.approx((ta + tb) / 2)
    assert out.depth_var.item() == pytest.approx(((tb - ta) / 2) ** 2)
    assert out.opacity.item() == pytest.approx(1.0)
    # the expected depth lies in the empty space between the spikes; the median at their boundary
    assert out.median.item() == pytest.approx(edges[0, a + 1].item(), abs=1e-6)


def test_median_lies_on_the_heavier_of_two_surfaces():
    edges = torch.linspace(1.0, 3.0, 21)[None]
    weights = torch.zeros(1, 20)
    weights[0, 2], weights[0, 15] = 0.3, 0.6  # a faint floater at 1.2-1.3 m, the wall at 2.5-2.6 m
    median = weight_quantile(edges, weights, 0.5)
    # half of the 0.9 total is 0.45: 0.15 into the wall's 0.6, a quarter of its 0.1 m bin
    assert median.item() == pytest.approx(2.525, abs=1e-5)
    expected = (weights * 0.5 * (edges[:, 1:] + edges[:, :-1])).sum() / weights.sum()
    assert abs(expected.item() - median.item()) > 0.4  # the mean is in the empty space between


def test_weight_quantile_inverts_a_piecewise_constant_cdf():
    edges = torch.tensor([[0.0, 1.0, 3.0], [0.0, 1.0, 3.0]])
    weights = torch.tensor([[1.0, 1.0], [0.0, 0.0]])  # half the mass in [0, 1], half in [1, 3]; none
    torch.testing.assert_close(weight_quantile(edges, weights, 0.25), torch.tensor([0.5, 0.5]))
    torch.testing.assert_close(weight_quantile(edges, weights, 0.75), torch.tensor([2.0, 2.0]))
    torch.testing.assert_close(weight_quantile(edges, weights, 0.5), torch.tensor([1.0, 1.0]))


def test_composite_colour_is_the_weighted_sum():
    g = torch.Generator().manual_seed(7)
    edges = torch.linspace(1.0, 2.0, 9).expand(3, 9).contiguous()
    t = 0.5 * (edges[:, 1:] + edges[:, :-1])
    sigma = torch.rand(3, 8, generator=g) * 5
    rgb = torch.rand(3, 8, 3, generator=g)
    out = composite(t, edges, sigma, rgb)
    w = render_weights(sigma, edges)
    torch.testing.assert_close(out.color, (w[..., None] * rgb).sum(1))
    torch.testing.assert_close(out.opacity, w.sum(-1))
    p = w / w.sum(-1, keepdim=True)
    torch.testing.assert_close(out.depth, (p * t).sum(-1))


# -- render_rays on an analytic field ------------------------------------------------------------
class SlabField:
    """Density `value` for world z in [z0, z0 + thickness], zero elsewhere; constant colour.
    Records the number of points of every encoding, and of them the encodings it was given.
    Trained as grid fields are: every sample of a step encoded in one call."""

    encodes_in_one_pass = True

    def __init__(self, z0=1.5, thickness=0.01, value=1e4, color=(0.2, 0.5, 0.8)):
        self.z0, self.thickness, self.value = z0, thickness, value
        self.rgb = torch.tensor(color)
        self.calls = []

    def density(self, x):
        z = x[:, 2]
        return torch.where((z >= self.z0) & (z <= self.z0 + self.thickness), self.value, 0.0)

    def encode(self, x, known=None):
        self.calls.append((x.shape[0], 0 if known is None else known.shape[0]))
        return x

    def geometry(self, x, encoded=None):
        return self.density(x), torch.zeros(x.shape[0], 1)

    def color(self, features, d):
        assert d.shape == (features.shape[0], 3)
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(d.shape[0]))  # unit view directions
        return self.rgb.expand(d.shape[0], 3)


class SmoothField:
    """A smooth positive density and position-dependent colour (to check sample bookkeeping)."""

    def density(self, x):
        return 2.0 + torch.sin(3 * x[:, 2]) + x[:, 0] ** 2

    def encode(self, x, known=None):
        return x

    def geometry(self, x, encoded=None):
        return self.density(x), x  # the point itself as the feature colour() sees

    def color(self, features, d):
        return torch.sigmoid(features)


def camera_rays(n_side: int = 6, aabb=((-1.0, -1.0, 0.5), (1.0, 1.0, 1.5001))):
    """Rays of a small identity camera, clipped to a box ending just behind the slab."""
    u, v = torch.meshgrid(torch.linspace(CX - 40, CX + 40, n_side), torch.linspace(CY - 40, CY + 40, n_side),
                          indexing="xy")
    box = torch.tensor(aabb)
    return make_rays(torch.eye(4), K, u.reshape(-1), v.reshape(-1), box)


def z_of(rays: Rays, t: torch.Tensor) -> torch.Tensor:
    """World z of the points at parameter t (R,) along the rays (any direction scaling)."""
    return rays.origins[:, 2] + t * rays.directions[:, 2]


@pytest.mark.parametrize("with_targets", [False, True])
def test_render_rays_finds_an_opaque_slab(with_targets):
    field = SlabField(z0=1.2)
    u, v = torch.meshgrid(torch.linspace(0, 159, 6), torch.linspace(0, 119, 5), indexing="xy")
    rays = make_rays(torch.eye(4), K, u.reshape(-1), v.reshape(-1), torch.tensor([[-2.0, -2, 0.7], [2, 2, 1.7]]))
    sampling = SamplingConfig(n_coarse=128, n_fine=32, n_guided=16)
    g = torch.Generator().manual_seed(0)
    mean = sigma = None
    if with_targets:
        # target in the slab, in the rays' own parameter (t such that o + t d has z = 1.205)
        mean = (1.205 - rays.origins[:, 2]) / rays.directions[:, 2]
        mean[::4] = float("nan")  # a few rays without target
        sigma = 0.005 / rays.directions[:, 2]
    fine, coarse = render_rays(field, rays, sampling, mean, sigma, g, with_coarse=True)
    assert (z_of(rays, fine.depth) - 1.2).abs().max() < 0.01
    torch.testing.assert_close(fine.opacity, torch.ones(len(rays)), atol=1e-4, rtol=0)
    torch.testing.assert_close(fine.color, field.rgb.expand(len(rays), 3), atol=1e-4, rtol=0)
    assert (fine.depth_var.sqrt() * rays.directions[:, 2] < 0.01).all()  # z spread under 1 cm
    n_total = sampling.n_coarse + sampling.n_fine + sampling.n_guided
    assert fine.t.shape == (len(rays), n_total) and fine.edges.shape == (len(rays), n_total + 1)
    assert coarse.t.shape == (len(rays), sampling.n_coarse)
    assert coarse.weights.shape == (len(rays), sampling.n_coarse)
    assert (z_of(rays, coarse.depth) - 1.2).abs().max() < 0.02
    # the coarse samples are encoded (to place the others), then every sample in one call that is
    # given the coarse encodings to reuse; a render (no gradient) never encodes the coarse ones again
    n_coarse = len(rays) * sampling.n_coarse
    assert field.calls == [(n_coarse, 0), (len(rays) * n_total, n_coarse)]
    with torch.no_grad():
        render_rays(field, rays, sampling, mean, sigma, g, with_coarse=True)
    assert field.calls[2:] == [(n_coarse, 0)]
    if with_targets:
        has = torch.isfinite(mean)
        inside = (fine.t - mean[:, None]).abs() <= 3 * sigma[:, None] + 1e-6
        # rays with a target got the n_guided depth-guided samples in mean +- 3 sigma
        assert (inside[has].sum(1) >= sampling.n_guided).all()


def test_render_rays_misses_the_slab_outside_the_box():
    field = SlabField(z0=2.5)  # behind the box: the rays end before it
    rays = camera_rays()
    fine, _ = render_rays(field, rays, SamplingConfig(64, 16, 0), generator=torch.Generator().manual_seed(1))
    assert fine.opacity.max() < 1e-6
    assert fine.color.abs().max() < 1e-6


def test_render_rays_coarse_render_reuses_the_field_values_at_coarse_samples():
    field = SmoothField()
    rays = camera_rays()
    sampling = SamplingConfig(n_coarse=16, n_fine=8, n_guided=4)
    mean = 1.0 * rays.norms
    sigma = 0.05 * rays.norms
    fine, coarse = render_rays(field, rays, sampling, mean, sigma, torch.Generator().manual_seed(2),
                               with_coarse=True)
    # every coarse sample is one of the fine samples
    assert torch.isin(coarse.t, fine.t).all()
    assert (coarse.t[:, 1:] >= coarse.t[:, :-1]).all()
    # and the coarse render equals compositing the field at those samples
    pts = (rays.origins[:, None] + rays.directions[:, None] * coarse.t[..., None]).reshape(-1, 3)
    ref = composite(coarse.t, coarse.edges, field.density(pts).view_as(coarse.t),
                    torch.sigmoid(pts).view(*coarse.t.shape, 3))
    torch.testing.assert_close(coarse.weights, ref.weights)
    torch.testing.assert_close(coarse.color, ref.color)
    torch.testing.assert_close(coarse.edges, bin_edges(coarse.t, rays.near, rays.far))


def test_render_rays_is_deterministic_without_jitter_and_differentiable():
    torch.manual_seed(0)
    lin = torch.nn.Linear(3, 4)

    class Tiny:
        def encode(self, x, known=None):
            return x

        def geometry(self, x, encoded=None):
            h = lin(x)
            return torch.nn.functional.softplus(h[:, 0]), h[:, 1:]

        def color(self, features, d):
            return torch.sigmoid(features)

    rays = camera_rays(4)
    s = SamplingConfig(8, 8, 0)
    a, _ = render_rays(Tiny(), rays, s, jitter=False)
    b, _ = render_rays(Tiny(), rays, s, jitter=False)
    torch.testing.assert_close(a.t, b.t)
    torch.testing.assert_close(a.color, b.color)
    (a.color.sum() + a.depth.sum()).backward()
    assert lin.weight.grad is not None and torch.isfinite(lin.weight.grad).all()
    assert lin.weight.grad.abs().sum() > 0


class TwoSlabField:
    """Two half-transparent slabs along z (0.1 thick each, at z0 and z1) of density `value`."""

    def __init__(self, z0: float, z1: float, value: float = 4.0):
        self.z0, self.z1, self.value = z0, z1, value

    def encode(self, x, known=None):
        return x

    def geometry(self, x, encoded=None):
        z = x[:, 2]
        inside = ((z >= self.z0) & (z <= self.z0 + 0.1)) | ((z >= self.z1) & (z <= self.z1 + 0.1))
        return torch.where(inside, self.value, 0.0), torch.zeros(x.shape[0], 1)

    def color(self, features, d):
        return torch.full((features.shape[0], 3), 0.5)


def test_render_rays_fine_samples_of_target_rays_cover_the_whole_coarse_pdf():
    """Rays with a depth target draw their n_fine importance samples over the whole coarse PDF
    (here two equal-ish modes, the second behind the target), as rays without one do; not the
    front part of a longer draw (which never reached the second mode)."""
    field = TwoSlabField(1.2, 2.4, value=3.0)  # each slab stops ~26% of the light
    rays = rays_along_z(64, near=1.0, far=3.0)
    sampling = SamplingConfig(n_coarse=32, n_fine=24, n_guided=16)
    mean, sigma = torch.full((64,), 1.25), torch.full((64,), 0.01)
    fine, _ = render_rays(field, rays, sampling, mean, sigma, torch.Generator().manual_seed(3))
    coarse_t = stratified(rays, sampling.n_coarse, torch.Generator().manual_seed(3))
    extra = fine.t[~torch.isin(fine.t, coarse_t)].view(64, -1)  # importance + guided samples
    assert extra.shape[1] == sampling.n_fine + sampling.n_guided
    behind = ((extra >= 2.35) & (extra <= 2.55)).sum(1).float()
    # the second mode holds ~40% of the coarse weight: ~10 of the 24 importance samples land there
    assert behind.mean() > 6, behind.mean()
    # rays without a target keep n_fine + n_guided importance samples
    fine_nt, _ = render_rays(field, rays, sampling, torch.full((64,), float("nan")), sigma,
                             torch.Generator().manual_seed(3))
    extra_nt = fine_nt.t[~torch.isin(fine_nt.t, coarse_t)].view(64, -1)
    assert ((extra_nt >= 2.35) & (extra_nt <= 2.55)).sum(1).float().mean() > 10
