"""The signed-distance geometry (geometry="sdf"): its density law, eikonal term, level-set mesh
and settings, on analytic cases."""

import numpy as np
import pytest
import torch

import open3d_pnerf as pn
from open3d_pnerf.errors import ConfigError
from open3d_pnerf.fields.sdf import eikonal_loss, finite_difference_gradient, laplace_cdf, sdf_density
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
    ({"geometry": "surface"}, "geometry"),
])
def test_bad_sdf_settings_name_the_field(overrides, named):
    with pytest.raises(ConfigError, match=named):
        pn.ReconstructionConfig.preset("fast", **overrides)


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
