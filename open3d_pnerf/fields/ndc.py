"""Normalized device coordinates (NDC) of a forward-facing capture, as the field's input.

A forward-facing capture (LLFF) sees its scene from cameras that all look the same way. NeRF
trains such scenes in NDC, the projective frame of a reference camera: x and y are image
coordinates in [-1, 1] and z = 1 - 2 near / depth, so the field's resolution follows the
image's at every depth and equal steps of z are equal steps of disparity. Here only the field's
input is warped (:meth:`NDCWarp.normalize`): rays, sample distances, densities (1/m) and the
depth targets stay metric, so a depth target's mass in a sample's bin is its metric CDF over
the bin's metric edges whatever coordinates the field sees (no Gaussian has to be carried into
NDC, where it would not be one). The coarse samples are spaced evenly in NDC z, i.e. in
disparity (rendering.samplers.stratified), as NeRF's NDC samples are.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..camera import project

BOX_PAD = 0.02  # the NDC box's margin on every side, as a share of its size


class NDCWarp(nn.Module):
    """World points -> NDC of a reference camera -> [0, 1]^3 over the box the training frusta fill.

    camera_to_world: (4, 4) the reference camera (OpenCV axes: x right, y down, z forward);
    K: (3, 3) its intrinsics for an image of image_size (H, W) pixels; near: the z-depth (m) that
    NDC z = -1 stands for; box: (2, 3) [min, max] corner in NDC that normalize() maps to [0, 1]^3.
    """

    def __init__(self, camera_to_world, K, image_size: tuple[int, int], near: float, box):
        super().__init__()
        c2w = np.asarray(camera_to_world, np.float64).reshape(4, 4)
        self.register_buffer("rotation", torch.as_tensor(c2w[:3, :3].T, dtype=torch.float32), persistent=False)
        self.register_buffer("centre", torch.as_tensor(c2w[:3, 3], dtype=torch.float32), persistent=False)
        K = np.asarray(K, np.float64).reshape(3, 3)
        self.register_buffer("intrinsic", torch.as_tensor(K, dtype=torch.float32), persistent=False)
        self.register_buffer("box", torch.as_tensor(np.asarray(box), dtype=torch.float32).reshape(2, 3),
                             persistent=False)
        h, w = image_size
        self.camera_to_world, self.K, self.image_size, self.near = c2w, K, (int(h), int(w)), float(near)

    def ndc(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3) NDC of world points x (B, 3). Points at or behind the reference camera's plane
        (z <= 0) map far outside [-1, 1]^3 (finite)."""
        p = (x - self.centre) @ self.rotation.T
        z = p[:, 2].clamp(min=1e-6 * self.near)
        u, v = project(self.intrinsic, torch.cat([p[:, :2], z[:, None]], 1))
        h, w = self.image_size
        return torch.stack([2 * (u + 0.5) / w - 1, 2 * (v + 0.5) / h - 1, 1 - 2 * self.near / z], -1)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3) coordinates of world points x (B, 3) in the NDC box, [0, 1]^3 inside it."""
        return (self.ndc(x) - self.box[0]) / (self.box[1] - self.box[0])

    def to_dict(self) -> dict:
        """The warp as JSON-ready values (:meth:`from_dict` rebuilds it)."""
        return {"camera_to_world": self.camera_to_world.tolist(), "K": self.K.tolist(),
                "image_size": list(self.image_size), "near": self.near, "box": self.box.cpu().tolist()}

    @classmethod
    def from_dict(cls, values: dict) -> "NDCWarp":
        return cls(values["camera_to_world"], values["K"], tuple(values["image_size"]), values["near"], values["box"])

    @classmethod
    def around(cls, camera_to_world, K, image_size: tuple[int, int], near: float, points: np.ndarray) -> "NDCWarp":
        """The warp of a reference camera whose NDC box holds world points (M, 3) (e.g. the
        training frusta's corners), plus BOX_PAD of its size on every side."""
        warp = cls(camera_to_world, K, image_size, near, np.zeros((2, 3)))
        ndc = warp.ndc(torch.as_tensor(np.asarray(points), dtype=torch.float32)).double().numpy()
        lo, hi = ndc.min(0), ndc.max(0)
        pad = BOX_PAD * (hi - lo)
        warp.box.copy_(torch.as_tensor(np.stack([lo - pad, hi + pad]), dtype=torch.float32))
        return warp
