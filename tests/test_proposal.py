"""The proposal network (issue 30): its weights bound the field's on an exact ray, its loss trains
it alone, and a field with one places its samples where the proposal says and saves with it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import open3d_pnerf as pn
from open3d_pnerf.fields import HashGridField, ProposalField
from open3d_pnerf.losses import proposal_bounds, proposal_loss
from open3d_pnerf.rendering import SamplingConfig, make_rays, render_rays
from open3d_pnerf.synthetic import synthetic_sequence


def exact_weights(edges: torch.Tensor, slab: tuple[float, float], sigma: float) -> torch.Tensor:
    """(R, S) exact weights of bins `edges` (R, S + 1) on a ray through an absorbing slab
    [a, b] of density sigma (1/m): T(e_k) - T(e_{k+1}), T(t) = exp(-sigma |[0, t] & [a, b]|)."""
    a, b = slab
    transmittance = torch.exp(-sigma * (edges.clamp(a, b) - a))
    return transmittance[:, :-1] - transmittance[:, 1:]


def random_edges(n_rays: int, n_bins: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    inner = torch.rand(n_rays, n_bins - 1, generator=g, dtype=torch.float64).sort(1).values
    return torch.cat([torch.zeros(n_rays, 1, dtype=torch.float64), inner, torch.ones(n_rays, 1, dtype=torch.float64)], 1)


def test_the_weights_of_the_same_ray_on_coarser_bins_bound_the_fine_ones():
    """A proposal that has the scene's density, on its own coarse bins, holds at least the fine
    weight in every fine bin (what the interlevel loss asks), so its loss is zero; a proposal
    that put the surface elsewhere is penalised, by the field's weight it misses."""
    fine_edges = random_edges(4, 48, seed=0)
    coarse_edges = random_edges(4, 7, seed=1)
    slab, sigma = (0.42, 0.47), 60.0
    fine = exact_weights(fine_edges, slab, sigma)
    coarse = exact_weights(coarse_edges, slab, sigma)
    assert (proposal_bounds(fine_edges, coarse_edges, coarse) >= fine - 1e-12).all()
    assert proposal_loss(fine, fine_edges, coarse, coarse_edges).abs().max() < 1e-12
    wrong = exact_weights(coarse_edges, (0.8, 0.85), sigma)
    loss = proposal_loss(fine, fine_edges, wrong, coarse_edges)
    assert (loss > 0.5).all()  # ~95% of the fine weight lies where the wrong proposal has (almost) none
    # bins the same as the proposal's: the bound is the weight itself
    np.testing.assert_allclose(proposal_bounds(coarse_edges, coarse_edges, coarse).numpy(), coarse.numpy())


def test_the_proposal_loss_trains_the_proposal_and_not_the_field():
    weights = torch.tensor([[0.1, 0.6, 0.2]], requires_grad=True)
    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
    proposal = torch.tensor([[0.1, 0.2]], requires_grad=True)  # bounds 0.1, 0.3, 0.2: short in the middle bin
    proposal_loss(weights, edges, proposal, torch.tensor([[0.0, 1.5, 3.0]])).sum().backward()
    assert weights.grad is None and (proposal.grad < 0).all()  # more proposal weight lowers the loss


class SlabProposal(torch.nn.Module):
    """A proposal whose density is high only in a slab z in [2.0, 2.2] m of the box below."""

    def forward(self, u):
        z = u[:, 2] * 4.0  # the box's z runs over [0, 4] m
        return 1e3 * ((z >= 2.0) & (z <= 2.2)).float()


def test_the_coarse_samples_go_where_the_proposal_puts_the_weight():
    field = HashGridField(torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 4.0]]), levels=4, log2_table_size=12,
                          max_resolution=64)
    field.proposal = SlabProposal()
    sampling = SamplingConfig(n_coarse=12, n_fine=4, n_guided=0, n_proposal=64)
    rays = make_rays(torch.eye(4), torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]),
                     torch.arange(4.0, 13.0), torch.full((9,), 8.0), field.aabb)
    fine, coarse = render_rays(field, rays, sampling, jitter=False, with_coarse=True)
    z = coarse.t * (rays.directions[:, 2:])  # the coarse samples' z (m)
    assert ((z > 2.0 - 0.04) & (z < 2.2 + 0.04)).all()  # within a proposal bin of the slab
    assert fine.proposal_weights.shape == (9, 64) and fine.proposal_edges.shape == (9, 65)
    assert fine.proposal_weights.sum(1).min() > 0.99
    del field.proposal  # without one: stratified over the whole ray
    _, plain = render_rays(field, rays, dataclasses.replace(sampling, n_proposal=0), jitter=False, with_coarse=True)
    assert plain.t.min() < 1.0 and plain.t.max() > 3.0 and plain.proposal_weights is None


def test_reconstruct_trains_the_proposal_and_saves_it(tmp_path):
    seq = synthetic_sequence(n_frames=4, width=32, height=24, seed=0).sequence
    cfg = pn.ReconstructionConfig.preset("test", max_steps=20, progress=False, **{"sampling.n_proposal": 32})
    initial = cfg.build_field(np.array([[-1.0, -1, -1], [1, 1, 1]])).proposal.mlp[0].weight.detach().clone()
    recon = pn.reconstruct(seq, cfg, poses=seq.gt_poses)
    field = recon.model.field
    assert isinstance(field.proposal, ProposalField)
    assert not torch.allclose(field.proposal.mlp[0].weight, initial)  # trained (by its loss only)
    recon.save(tmp_path / "saved")
    loaded = pn.Reconstruction.load(tmp_path / "saved").model.field
    torch.testing.assert_close(loaded.proposal.mlp[0].weight, field.proposal.mlp[0].weight)
    with pytest.raises(ValueError, match="proposal network"):
        cfg.grow_field(field, field.aabb * 2)
