"""Normalized device coordinates for forward-facing captures (issue 30): the warp against NeRF's
closed-form NDC rays, samples even in NDC depth, a depth target's mass kept across the warp,
when a sequence gets NDC, and a saved NDC field rendering as it did."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from scipy.stats import norm
from test_llff import VISIBLE, make_llff

import open3d_pnerf as pn
from open3d_pnerf import pipeline
from open3d_pnerf.data import load_sequence
from open3d_pnerf.errors import InputError
from open3d_pnerf.fields import NDCWarp
from open3d_pnerf.losses import gaussian_bin_masses
from open3d_pnerf.rendering import Rays, stratified
from open3d_pnerf.scene import ndc_warp
from open3d_pnerf.synthetic import synthetic_sequence

W, H, FX, FY, NEAR = 64, 48, 50.0, 45.0, 0.7
K = np.array([[FX, 0, (W - 1) / 2], [0, FY, (H - 1) / 2], [0, 0, 1]])  # centred: NeRF's NDC has no offset


def nerf_ndc_ray(o, d):
    """NeRF's ndc_rays (Mildenhall et al. 2020, appendix C) for a camera looking down -z (OpenGL
    axes), the ray's origin first moved to the near plane: (o', d') with o + t d -> o' + t' d'."""
    o = o + (-(NEAR + o[2]) / d[2]) * d
    o_ndc = np.array([-FX / (W / 2) * o[0] / o[2], -FY / (H / 2) * o[1] / o[2], 1 + 2 * NEAR / o[2]])
    d_ndc = np.array([-FX / (W / 2) * (d[0] / d[2] - o[0] / o[2]), -FY / (H / 2) * (d[1] / d[2] - o[1] / o[2]),
                      -2 * NEAR / o[2]])
    return o, o_ndc, d_ndc


def test_a_ray_maps_to_nerfs_ndc_ray():
    """OpenCV axes are OpenGL's with y and z flipped, so the warp's NDC is NeRF's with y mirrored
    (image rows down); every point of a world ray lands on NeRF's NDC ray at its t'."""
    reference = np.eye(4)
    reference[:3, 3] = [0.3, -0.2, 0.1]  # the reference camera away from the origin
    warp = NDCWarp(reference, K, (H, W), NEAR, [[-1, -1, -1], [1, 1, 1]])
    flip = np.diag([1.0, -1.0, -1.0])  # OpenCV <-> OpenGL camera axes
    for o_cv, d_cv in [([0.05, 0.02, 0.0], [0.1, -0.05, 1.0]), ([-0.1, 0.08, 0.2], [-0.3, 0.2, 1.0])]:
        o_cv, d_cv = np.array(o_cv), np.array(d_cv) / np.linalg.norm(d_cv)
        o_near, o_ndc, d_ndc = nerf_ndc_ray(flip @ o_cv, flip @ d_cv)
        t = np.array([0.0, 0.3, 1.0, 4.0, 50.0])
        points = o_near + t[:, None] * (flip @ d_cv)  # camera frame, OpenGL axes
        t_ndc = 1 - o_near[2] / (o_near[2] + t * (flip @ d_cv)[2])
        expected = o_ndc + t_ndc[:, None] * d_ndc
        world = (flip @ points.T).T + reference[:3, 3]
        got = warp.ndc(torch.as_tensor(world, dtype=torch.float32)).double().numpy()
        np.testing.assert_allclose(got * [1, -1, 1], expected, atol=2e-5)
        assert got[0, 2] == pytest.approx(-1, abs=1e-5) and got[-1, 2] < 1  # the near plane, and short of infinity
    # a principal point off the centre shifts x and y by its offset in NDC units
    shifted = K.copy()
    shifted[:2, 2] += [3.0, -2.0]
    warp_shifted = NDCWarp(reference, shifted, (H, W), NEAR, [[-1, -1, -1], [1, 1, 1]])
    x = torch.tensor([[0.4, 0.1, 2.5]])
    np.testing.assert_allclose((warp_shifted.ndc(x) - warp.ndc(x)).numpy(), [[6 / W, -4 / H, 0]], atol=1e-6)


def test_disparity_samples_are_even_in_ndc_depth():
    warp = NDCWarp(np.eye(4), K, (H, W), NEAR, [[-1, -1, -1], [1, 1, 1]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.2, -0.1, 1.0]])
    d = d / d.norm(dim=1, keepdim=True)
    norms = 1 / d[:, 2]  # metres along the ray per metre of z-depth
    rays = Rays(torch.zeros(2, 3), d, NEAR * norms, 8.0 * norms, norms)
    t = stratified(rays, 12, jitter=False, disparity=True)
    z_ndc = warp.ndc((rays.origins[:, None] + t[..., None] * d[:, None]).reshape(-1, 3))[:, 2].reshape(2, 12)
    steps = z_ndc.diff(dim=1)
    np.testing.assert_allclose(steps.numpy(), (1 - 2 * NEAR / 8.0 + 1) / 12, rtol=1e-4)
    assert (t >= rays.near[:, None]).all() and (t <= rays.far[:, None]).all()
    uniform = stratified(rays, 12, jitter=False)
    np.testing.assert_allclose(uniform.diff(dim=1).numpy(), ((rays.far - rays.near) / 12)[:, None].expand(2, 11),
                               rtol=1e-5)


def test_a_gaussian_depth_targets_mass_is_kept_across_the_warp():
    """Bins placed evenly in NDC z hold the metric Gaussian's mass: per bin, the Gaussian target's
    mass the loss uses equals the integral over the bin's NDC interval of the target's density
    carried into NDC (p(t(z)) |dt/dz|, not a Gaussian in z), and the masses sum to one."""
    near, far, mu, sigma = NEAR, 8.0, 2.0, 0.4
    rays = Rays(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([near]), torch.tensor([far]),
                torch.ones(1))
    t = stratified(rays, 24, jitter=False, disparity=True).double()
    edges = torch.cat([torch.tensor([[near]], dtype=torch.float64), 0.5 * (t[:, 1:] + t[:, :-1]),
                       torch.tensor([[far]], dtype=torch.float64)], 1)
    mass = gaussian_bin_masses(edges, torch.tensor([mu], dtype=torch.float64), torch.tensor([sigma],
                                                                                            dtype=torch.float64))[0]

    def density_in_ndc(z):  # t = 2 near / (1 - z), dt/dz = 2 near / (1 - z)^2
        return norm.pdf(2 * near / (1 - z), mu, sigma) * 2 * near / (1 - z) ** 2

    warp = NDCWarp(np.eye(4), K, (H, W), near, [[-1, -1, -1], [1, 1, 1]]).double()  # the ray: its optical axis
    on_axis = torch.zeros(edges.shape[1], 3, dtype=torch.float64)
    on_axis[:, 2] = edges[0]
    z_edges = warp.ndc(on_axis)[:, 2].numpy()
    inside = norm.cdf(far, mu, sigma) - norm.cdf(near, mu, sigma)
    expected = [quad(density_in_ndc, a, b)[0] / inside for a, b in zip(z_edges[:-1], z_edges[1:])]
    np.testing.assert_allclose(mass.numpy(), expected, atol=1e-9)
    assert float(mass.sum()) == pytest.approx(1.0, abs=1e-12)


def test_which_sequences_get_ndc(tmp_path, monkeypatch):
    llff = load_sequence(make_llff(tmp_path / "scene", points=VISIBLE))
    warp = ndc_warp(llff, llff.sfm.poses)
    assert isinstance(warp, NDCWarp) and ndc_warp(llff, llff.sfm.poses, "off") is None
    near = 0.9 * llff.sfm.bounds[:, 0].min()
    assert warp.near == pytest.approx(near)
    # every training frame's view (its image's corners and centre) between the near plane and its
    # far bound lies inside the NDC box
    h, w = llff.image_size
    pixels = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1],
                       [w / 2, h / 2, 1]])
    rays = pixels @ np.linalg.inv(llff.K).T  # camera frame, unit z
    for pose, bound in zip(llff.sfm.poses, llff.sfm.bounds):
        for depth in (near, bound[1]):
            points = rays * depth @ pose[:3, :3].T + pose[:3, 3]
            u = warp.normalize(torch.tensor(points, dtype=torch.float32))
            assert ((u > 0) & (u < 1)).all()
    rgbd = synthetic_sequence(n_frames=3, width=32, height=24, seed=0).sequence
    assert ndc_warp(rgbd, rgbd.gt_poses) is None
    with pytest.raises(InputError, match="ndc='on' needs an image-only sequence with SfM depth bounds"):
        ndc_warp(rgbd, rgbd.gt_poses, "on")
    monkeypatch.setattr(pipeline, "resolve_poses", lambda *a, **k: pytest.fail("tracked before the check"))
    with pytest.raises(InputError, match="ndc='on' needs an image-only sequence"):
        pn.reconstruct(rgbd, pn.ReconstructionConfig.preset("test", ndc="on", progress=False))
    turned = llff.sfm.poses.copy()
    turned[1, :3, :3] = np.diag([-1.0, 1.0, -1.0])  # a camera looking back at the others
    assert ndc_warp(llff, turned) is None  # auto: the scene box
    with pytest.raises(InputError, match="not a forward-facing capture; set ndc='off'"):
        ndc_warp(llff, turned, "on")


def test_a_saved_ndc_field_renders_as_it_did(tmp_path):
    seq = load_sequence(make_llff(tmp_path / "scene", points=VISIBLE))
    cfg = pn.ReconstructionConfig.preset("test", max_steps=6, image_scale=1.0, progress=False)
    recon = pn.reconstruct(seq, cfg)
    assert recon.model.field.warp is not None
    box = pn.reconstruct(seq, cfg.replace(ndc="off"))
    assert box.model.field.warp is None
    recon.save(tmp_path / "saved")
    loaded = pn.Reconstruction.load(tmp_path / "saved")
    np.testing.assert_array_equal(loaded.model.field.warp.box.numpy(), recon.model.field.warp.box.numpy())
    a = recon.render(seq.sfm.poses[1])
    b = loaded.render(seq.sfm.poses[1])
    np.testing.assert_allclose(b["depth"], a["depth"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b["color"], a["color"], atol=1e-6)
