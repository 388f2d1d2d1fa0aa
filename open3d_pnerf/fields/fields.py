"""Scene fields: world position (+ view direction) -> volume density and colour.

Both fields map points inside an axis-aligned box ``aabb`` ((2, 3) metres, min and max
corner) and return density sigma >= 0 (1/m) and colour in [0, 1].
"""

from __future__ import annotations

import torch
from torch import nn

from .encodings import DenseGridEncoding, FrequencyEncoding, HashGridEncoding


def _mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    dims = [in_dim] + [hidden] * layers
    mods: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        mods += [nn.Linear(a, b), nn.ReLU(inplace=True)]
    mods.append(nn.Linear(dims[-1], out_dim))
    return nn.Sequential(*mods)


def density_activation(raw: torch.Tensor) -> torch.Tensor:
    """exp with a clamped input: the 'truncated exponential' of Instant-NGP (1/m)."""
    return torch.exp(raw.clamp(max=15.0))


class Field(nn.Module):
    """Common interface: ``density(x)`` and ``forward(x, d) -> (sigma, rgb)``."""

    def __init__(self, aabb: torch.Tensor):
        super().__init__()
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3))

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """World points (B, 3) -> box coordinates in [0, 1]^3."""
        return (x - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) density of world points x (B, 3); zero outside the box."""
        return self.forward(x, None)[0]


class EncodedField(Field):
    """A grid encoding + small MLPs (Instant-NGP/nerfacto-sized heads).

    density = exp(MLP_sigma(enc(x))[0]); colour = sigmoid(MLP_rgb(geo_features, PE(d))).
    """

    def __init__(self, aabb, encoding: nn.Module, hidden: int = 64, geo_features: int = 15):
        super().__init__(aabb)
        self.encoding = encoding
        self.sigma_net = _mlp(encoding.out_dim, hidden, 1, 1 + geo_features)
        self.dir_encoding = FrequencyEncoding(3, 4)
        self.color_net = _mlp(geo_features + self.dir_encoding.out_dim, hidden, 2, 3)

    def forward(self, x: torch.Tensor, d: torch.Tensor | None):
        u = self.normalize(x)
        inside = ((u >= 0) & (u <= 1)).all(-1)
        h = self.sigma_net(self.encoding(u))
        sigma = density_activation(h[:, 0]) * inside
        if d is None:
            return sigma, None
        rgb = torch.sigmoid(self.color_net(torch.cat([h[:, 1:], self.dir_encoding(d)], -1)))
        return sigma, rgb


class GridField(EncodedField):
    """Multi-resolution dense grids: resolutions per level, features each."""

    def __init__(self, aabb, resolutions=(16, 32, 64, 128, 256), features: int = 2, **heads):
        super().__init__(aabb, DenseGridEncoding(resolutions, features), **heads)


class HashGridField(EncodedField):
    """Instant-NGP multi-resolution hash grid (levels x features, 2^log2_table_size per level)."""

    def __init__(self, aabb, levels=8, features=2, log2_table_size=19, max_resolution=2048, **heads):
        super().__init__(aabb, HashGridEncoding(levels, features, log2_table_size, 16, max_resolution), **heads)


class VanillaNeRFField(Field):
    """The original NeRF MLP (8 x 256, skip at layer 4, PE 10/4 frequencies), as in nerf_pl."""

    def __init__(self, aabb, width: int = 256, depth: int = 8, skip: int = 4):
        super().__init__(aabb)
        self.pos_encoding = FrequencyEncoding(3, 10)
        self.dir_encoding = FrequencyEncoding(3, 4)
        self.skip = skip
        in_dim = self.pos_encoding.out_dim
        self.layers = nn.ModuleList(
            nn.Linear(in_dim if i == 0 else width + (in_dim if i == skip else 0), width) for i in range(depth)
        )
        self.sigma_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.color_head = nn.Sequential(
            nn.Linear(width + self.dir_encoding.out_dim, width // 2), nn.ReLU(inplace=True), nn.Linear(width // 2, 3)
        )

    def forward(self, x: torch.Tensor, d: torch.Tensor | None):
        u = self.normalize(x)
        inside = ((u >= 0) & (u <= 1)).all(-1)
        e = self.pos_encoding(u * 2 - 1)
        h = e
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, e], -1)
            h = torch.relu(layer(h))
        sigma = torch.relu(self.sigma_head(h)[:, 0]) * inside
        if d is None:
            return sigma, None
        rgb = torch.sigmoid(self.color_head(torch.cat([self.feature(h), self.dir_encoding(d)], -1)))
        return sigma, rgb
