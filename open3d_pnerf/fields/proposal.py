"""The proposal network: a small density-only field that says where along a ray the scene field
should be sampled (Mip-NeRF 360's proposal MLP, as nerfacto builds it on a hash grid).

It is evaluated at many cheap samples per ray (SamplingConfig.n_proposal); the scene field is
then sampled where the proposal's weights lie (rendering.volume.render_rays). It does not render
colour or take part in the colour and depth terms: it is trained by the interlevel loss alone
(losses.proposal_loss), to hold at least the scene field's weight in every stretch of the ray.
"""

from __future__ import annotations

import torch
from torch import nn

from .encodings import HashGridEncoding
from .fields import density_activation

LEVELS, FEATURES, LOG2_TABLE_SIZE, MAX_RESOLUTION, HIDDEN = 5, 2, 17, 256, 16
"""The proposal's size: nerfacto's first proposal network (5 levels up to 128-256 cells per axis,
2^17-row tables, one 16-wide hidden layer)."""


class ProposalField(nn.Module):
    """Points in the scene field's [0, 1]^3 coordinates (B, 3) -> density (B,) 1/m."""

    def __init__(self, backend: str = "auto"):
        super().__init__()
        self.encoding = HashGridEncoding(LEVELS, FEATURES, LOG2_TABLE_SIZE, 16, MAX_RESOLUTION, backend)
        self.mlp = nn.Sequential(nn.Linear(self.encoding.out_dim, HIDDEN), nn.ReLU(inplace=True), nn.Linear(HIDDEN, 1))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return density_activation(self.mlp(self.encoding(u))[:, 0])
