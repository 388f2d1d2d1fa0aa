"""The signed-distance geometry (geometry="sdf"): its density law, eikonal term, level-set mesh
and settings, on analytic cases."""

import numpy as np
import pytest
import torch

import open3d_pnerf as pn
from open3d_pnerf.errors import ConfigError
from open3d_pnerf.fields.sdf import (depth_sdf_loss, depth_sdf_samples, eikonal_loss, finite_difference_gradient,
                                    laplace_cdf, sdf_density, surface_distance)
from open3d_pnerf.rendering.volume import render_weights
from open3d_pnerf.tsdf import level_set_mesh


def test_laplace_cdf_is_the_laplace_law():
    beta = 0.05
    s = torch.linspace(-0.5, 0.5, 2001, dtype=torch.float64)
    cdf = laplace_cdf(s, beta)
    assert cdf[1000].item() == pytest.approx(0.5)
    assert cdf[0].item() == pytest.approx(0.5 * np.exp(-10), rel=1e-9)
    density = torch.diff(cdf) / torch.diff(s)  # the law's density: exp(-|s| / beta) / (2 beta)
    mid = (s[1:] + s[:-1]) / 2
    assert torch.allclose(density, torch.exp(-mid.abs() / beta) / (2 * beta), rtol=1e-3)


@pytest.mark.parametrize("beta", [0.01, 0.05])
def test_sdf_density_stops_a_ray_at_a_plane_with_the_right_probability(beta):
    # a ray hitting a plane head-on at t0: sdf(t) = t0 - t. The optical depth up to the plane is
    # int Psi(t - t0) / beta dt = 1/2, so the ray terminates before it with probability 1 - e^-1/2,
    # and beyond the plane the density tends to 1 / beta: the ray stops within a few beta.
    t0 = 1.0
    edges = torch.linspace(0.0, 2.0, 40001, dtype=torch.float64)[None]
    mids = (edges[:, 1:] + edges[:, :-1]) / 2
    weights = render_weights(sdf_density(t0 - mids, beta), edges)
    before = weights[0, mids[0] < t0].sum().item()
    assert before == pytest.approx(1 - np.exp(-0.5), abs=1e-4)
    assert weights.sum().item() == pytest.approx(1.0, abs=1e-6)
    mean = (weights * mids).sum().item()
    assert abs(mean - t0) < 2 * beta


def test_eikonal_term_is_zero_for_an_exact_distance_field():
    centre, radius = torch.tensor([0.1, -0.2, 0.3]), 0.5
    sphere = lambda x: (x - centre).norm(dim=-1) - radius  # noqa: E731
    x = centre + torch.randn(500, 3) * 0.4
    x = x[(x - centre).norm(dim=-1) > 0.1]  # the distance has no gradient at the centre
    assert eikonal_loss(sphere, x, 0.005).item() < 1e-6
    g = finite_difference_gradient(sphere, x, 0.005)
    assert torch.allclose(g, (x - centre) / (x - centre).norm(dim=-1, keepdim=True), atol=1e-3)
    assert eikonal_loss(lambda p: 2 * sphere(p), x, 0.005).item() == pytest.approx(1.0, abs=1e-3)


def _rays_at_a_plane(n=64, z0=1.5):
    """Rays from the origin to the plane z = z0 (the camera looks along +z): origins, unit
    directions, near ends, and each ray's distance to the plane."""
    torch.manual_seed(0)
    d = torch.cat([1.6 * (torch.rand(n, 2) - 0.5), torch.ones(n, 1)], 1)
    d = d / d.norm(dim=-1, keepdim=True)
    return torch.zeros(n, 3), d, torch.full((n,), 0.1), z0 / d[:, 2]


def test_depth_sdf_samples_lie_in_the_band_and_in_front_of_three_sigmas():
    near, mu = torch.tensor([0.1, 0.5, 1.0, 0.1]), torch.tensor([2.0, 0.52, 1.0, 2.0])
    sigma = torch.tensor([0.01, 0.01, 0.01, 0.1])
    band, free, has_free = depth_sdf_samples(near, mu, sigma, 0.05, 200, 200)
    assert ((band - mu[:, None]).abs() <= 0.05).all() and band.shape == (4, 200)
    end = mu - torch.clamp(3 * sigma, min=0.05)  # the band's start, or three sigmas before mu
    assert (free <= end[:, None] + 1e-6).all() and (free[[0, 3]] >= 0.1).all()
    assert free[0].max() > 1.9 and free[0].min() < 0.2 and free[3].max() > 1.65 and free[3].max() <= 1.7
    assert has_free.tolist() == [True, False, False, True]  # no room in front of the second and third


def test_depth_sdf_terms_vanish_for_the_exact_distance_and_measure_a_shift():
    # a plane z = 1.5 seen head-on and obliquely: its exact signed distance 1.5 - z keeps every
    # free point within [0, mu - t] (the projective bound), and fits mu - t in the band up to the
    # obliqueness (mu - t = (1.5 - z) / cos); a plane moved 2 cm nearer costs 2 cm in the band
    o, d, near, mu = _rays_at_a_plane()
    cos = d[:, 2]
    sigma, weight = torch.full_like(mu, 0.01), torch.ones_like(mu)
    exact = lambda x: 1.5 - x[:, 2]  # noqa: E731
    terms = depth_sdf_loss(exact, o, d, near, mu, sigma, weight, 0.05, 16, 16)
    assert terms["sdf_free"].item() < 1e-7
    expected = (1 - cos).mean().item() * 0.05 / 2  # |mu - t| (1 - cos), |mu - t| 2.5 cm on average in the band
    assert expected > 2e-3 and terms["sdf_surface"].item() == pytest.approx(expected, rel=0.1)
    head_on = (torch.zeros(8, 3), torch.tensor([[0.0, 0.0, 1.0]]).repeat(8, 1), torch.full((8,), 0.1),
               torch.full((8,), 1.5), torch.full((8,), 0.01), torch.ones(8))
    assert depth_sdf_loss(exact, *head_on, 0.05, 16, 16)["sdf_surface"].item() < 1e-6
    nearer = depth_sdf_loss(lambda x: 1.48 - x[:, 2], *head_on, 0.05, 16, 16)
    assert nearer["sdf_surface"].item() == pytest.approx(0.02, rel=1e-4)
    # a wide target does not carve free space out of a surface within its three sigmas: the plane
    # 10 cm before a target of sigma 5 cm costs nothing in front of it, with sigma 1 cm it does
    before = lambda x: 1.4 - x[:, 2]  # noqa: E731
    wide = depth_sdf_loss(before, *head_on[:4], torch.full((8,), 0.05), torch.ones(8), 0.05, 0, 256)
    sharp = depth_sdf_loss(before, *head_on[:4], torch.full((8,), 0.01), torch.ones(8), 0.05, 0, 256)
    # the sharp target's free points in (1.40, 1.45) are inside: 3.7% of them, 2.5 cm deep on average
    assert wide["sdf_free"].item() == 0 and sharp["sdf_free"].item() == pytest.approx(0.05 / 1.35 * 0.025, rel=0.3)
    # points outside the field's box count zero
    outside = depth_sdf_loss(lambda x: 1.48 - x[:, 2], *head_on, 0.05, 16, 16, inside=lambda x: x[:, 2] > 10)
    assert outside["sdf_surface"].item() == 0 and outside["sdf_free"].item() == 0
    # negative in free space, or beyond the projective bound, is penalised by how far
    assert depth_sdf_loss(lambda x: 1.5 - x[:, 2] - 1.0, *head_on, 0.05, 0, 16)["sdf_free"].item() > 0.1
    assert depth_sdf_loss(lambda x: 2 * (1.5 - x[:, 2]), *head_on, 0.05, 0, 16)["sdf_free"].item() > 0.1


def test_depth_sdf_band_term_trusts_a_target_by_its_sigma():
    o, d, near = torch.zeros(4, 3), torch.tensor([[0.0, 0.0, 1.0]]).repeat(4, 1), torch.full((4,), 0.1)
    mu, weight = torch.full((4,), 1.5), torch.ones(4)
    shifted = lambda x: 1.48 - x[:, 2]  # noqa: E731
    sharp = depth_sdf_loss(shifted, o, d, near, mu, torch.full((4,), 0.01), weight, 0.05, 8, 0)["sdf_surface"]
    wide = depth_sdf_loss(shifted, o, d, near, mu, torch.full((4,), 0.2), weight, 0.05, 8, 0)["sdf_surface"]
    assert wide.item() == pytest.approx(sharp.item() * 0.05 / 0.2, rel=1e-4)
    none = depth_sdf_loss(shifted, o[:0], d[:0], near[:0], mu[:0], mu[:0], weight[:0], 0.05, 8, 8)
    assert none["sdf_surface"].item() == 0 and none["sdf_free"].item() == 0


def test_surface_distance_finds_the_first_zero_crossing_between_samples():
    # rays from the origin at a sphere of radius 0.3 centred 1.5 m ahead, and behind it a wall at
    # z = 3: the first crossing is the sphere's near side (closed form), between samples 16 cm
    # apart, not the sphere's far side or the wall; a ray that misses the sphere meets the wall;
    # one that meets nothing gets NaN
    centre, radius, beta = torch.tensor([0.0, 0.0, 1.5]), 0.3, 0.02
    scene = lambda x: torch.minimum((x - centre).norm(dim=-1) - radius, 3.0 - x[:, 2])  # noqa: E731
    d = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.05, 1.0], [0.5, 0.0, 1.0]])
    d = d / d.norm(dim=-1, keepdim=True)
    o = torch.zeros(3, 3)
    t = torch.linspace(0.05, 4.0, 25)[None].repeat(3, 1)  # the first two rays cross the sphere, then the wall
    density = sdf_density(scene((o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)).view(t.shape), beta)
    found = surface_distance(scene, o, d, t, density, beta)
    b = (d[:2] * centre).sum(-1)  # the sphere's near side: t = b - sqrt(b^2 - |c|^2 + r^2)
    exact = b - (b ** 2 - centre.norm() ** 2 + radius ** 2).sqrt()
    assert torch.allclose(found[:2], exact, atol=1e-4)
    assert found[2].item() == pytest.approx(3.0 / d[2, 2].item(), abs=1e-4)
    assert surface_distance(scene, o, d, t, torch.zeros_like(density), beta).isnan().all()


def test_level_set_mesh_of_a_sphere_lies_within_a_voxel_of_it():
    centre, radius, voxel = np.array([0.3, 0.1, -0.2]), 0.4, 0.02
    sphere = lambda p: np.linalg.norm(p - centre, axis=1) - radius  # noqa: E731
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(2000, 3))
    on_surface = centre + radius * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    mesh = level_set_mesh(sphere, on_surface, voxel)
    vertices = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 1000
    assert np.abs(np.linalg.norm(vertices - centre, axis=1) - radius).max() < voxel
    assert mesh.is_edge_manifold(allow_boundary_edges=False)  # closed: no hole at the blocks' seams
    # only near the given points: half a sphere's points give part of it, no empty mesh errors
    assert len(level_set_mesh(sphere, on_surface[on_surface[:, 2] > centre[2] + 0.3], voxel).triangles) < \
        len(mesh.triangles)
    assert level_set_mesh(sphere, np.zeros((0, 3)), voxel).is_empty()


def test_an_sdf_field_derives_its_density_from_its_signed_distance():
    config = pn.ReconstructionConfig.preset("test", geometry="sdf", **{"sdf.sharpness": 30.0})
    field = config.build_field(np.array([[-1, -1, -1], [1, 1, 1]], np.float32))
    x = torch.rand(64, 3) * 1.8 - 0.9
    sigma, _ = field.geometry(x)
    assert torch.allclose(field.beta, torch.tensor(1 / 30.0))
    assert torch.allclose(sigma, sdf_density(field.signed_distance(x), field.beta), rtol=1e-5)
    assert "log_sharpness" in field.state_dict()
    assert (field.signed_distance(x) > 0).float().mean() > 0.9  # starts as free space
    density = pn.ReconstructionConfig.preset("test").build_field(np.array([[-1, -1, -1], [1, 1, 1]], np.float32))
    with pytest.raises(TypeError, match="geometry='sdf'"):
        density.signed_distance(x)


@pytest.mark.parametrize("overrides, named", [
    ({"geometry": "sdf", "sdf.sharpness": 0.0}, "sdf.sharpness"),
    ({"geometry": "sdf", "sdf.sharpness": -5.0}, "sdf.sharpness"),
    ({"geometry": "sdf", "sdf.eikonal_step": 0.0}, "sdf.eikonal_step"),
    ({"geometry": "sdf", "field": "vanilla"}, "geometry"),
    ({"geometry": "sdf", "sdf.max_sharpness": 10.0}, "sdf.max_sharpness"),
    ({"geometry": "sdf", "sdf.truncation": 0.0}, "sdf.truncation"),
    ({"geometry": "sdf", "sdf.band_points": -1}, "sdf.band_points"),
    ({"geometry": "sdf", "objective.weights.sdf_surface": -1.0}, "sdf_surface"),
    ({"geometry": "surface"}, "geometry"),
])
def test_bad_sdf_settings_name_the_field(overrides, named):
    with pytest.raises(ConfigError, match=named):
        pn.ReconstructionConfig.preset("fast", **overrides)


@pytest.mark.slow
def test_an_sdf_reconstruction_trains_with_the_eikonal_term_and_exports_its_zero_level_set(sample):
    seq = sample.select(range(8))
    config = pn.ReconstructionConfig.preset("test", geometry="sdf", max_steps=160, holdout_every=4, progress=False)
    recon = pn.reconstruct(seq, config, poses=seq.gt_poses)
    history = recon.stats["history"]
    assert history and all(np.isfinite(h["loss"]) for h in history)
    assert recon.field.beta.item() < 1 / config.sdf.sharpness  # the sharpness was learned, and grew
    mesh, sigma = recon.mesh, recon.mesh_sigma
    assert mesh is not None and len(mesh.triangles) > 100 and mesh.has_vertex_colors()
    assert sigma.shape == (len(mesh.vertices),) and (sigma <= config.export.max_point_std).all()
    # the mesh is the level set: the signed distance at its vertices is ~0 (within the voxel it was cut at)
    with torch.no_grad():
        sdf = recon.field.signed_distance(torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32))
    assert sdf.abs().median().item() < config.export.mesh_voxel_size
    # its depth is its surface: the signed distance at the rendered depth of a held-out view is ~0
    i = recon.holdout_indices[0]
    view = recon.render(recon.poses[i])
    row = view["depth"].shape[0] // 2
    rays = recon._rays(recon.poses[i], recon.intrinsic, torch.arange(0, view["depth"].shape[1], 7.0),
                       torch.full((len(range(0, view["depth"].shape[1], 7)),), float(row)))
    z = torch.as_tensor(view["depth"][row, ::7])
    with torch.no_grad():
        at_depth = recon.field.signed_distance(rays.origins + (z * rays.norms)[:, None] * rays.directions)
    assert at_depth.abs().median().item() < 1e-3
    # and its raw spread is the weights' about that surface: at least their spread about their mean,
    # more where they put the ray elsewhere
    u = torch.arange(0, view["depth"].shape[1], 7.0)
    pixels = recon.render_pixels(recon.poses[i], recon.intrinsic, u, torch.full_like(u, float(row)))
    weights = recon.model.render(rays, keys=("depth", "depth_var"))
    about_mean = (weights["depth_var"].sqrt() / rays.norms).numpy()
    shift = weights["depth"].numpy() / rays.norms.numpy() - pixels["depth"]  # z-depth m
    assert np.abs(shift).max() > 0.01 and (pixels["depth_std"] >= about_mean - 1e-6).all()
    assert np.allclose(pixels["depth_std"] ** 2, about_mean ** 2 + shift ** 2, rtol=1e-3, atol=1e-8)
