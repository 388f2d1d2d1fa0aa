"""Training rays as pixels: random pixels of the training frames with their colours and depth
targets, drawn from a bounded cache of decoded frames."""

from __future__ import annotations

import dataclasses
from collections import OrderedDict

import numpy as np
import torch

from .camera import ray_norms
from .data.sequence import RGBDSequence
from .targets import DepthTargets


@dataclasses.dataclass
class RayBatch:
    """R training pixels with what they saw: u, v (R,) pixel coordinates (float, centres at
    integers), frames (R,) the index of each pixel's training frame, rgb (R, 3) in [0, 1],
    depth target mean and sigma (R,) in ray-distance metres (NaN = none)."""

    u: torch.Tensor
    v: torch.Tensor
    frames: torch.Tensor
    rgb: torch.Tensor
    mean: torch.Tensor
    sigma: torch.Tensor

    def __len__(self) -> int:
        return len(self.u)

    def __getitem__(self, index) -> "RayBatch":
        return RayBatch(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))


class RayBatcher:
    """Draws random training pixels from a bounded cache of decoded frames.

    sequence: the training frames at training resolution; targets: their DepthTargets (same
    resolution) or None. At most `cache_frames` frames are decoded at a time, into slots of
    preallocated tensors; with more frames the cache rotates one frame every `refresh_every`
    steps, in a seeded order, so memory stays bounded on long sequences.
    """

    def __init__(self, sequence: RGBDSequence, targets: DepthTargets | None, device, seed: int,
                 cache_frames: int = 64, refresh_every: int = 4):
        self.sequence, self.targets, self.device = sequence, targets, device
        self.height, self.width = sequence.image_size
        self.norms = torch.as_tensor(ray_norms(sequence.K, self.height, self.width), device=device).view(-1)
        self.capacity = min(cache_frames, len(sequence))
        self.refresh_every = refresh_every
        self.order_rng = np.random.default_rng(seed)
        self.queue: list[int] = []
        self.cache: OrderedDict[int, int] = OrderedDict()  # frame -> slot, oldest first
        pixels = self.height * self.width
        self.colors = torch.empty(self.capacity, pixels, 3, device=device)
        self.means = torch.empty(self.capacity, pixels, device=device) if targets is not None else None
        self.sigmas = torch.empty(self.capacity, pixels, device=device) if targets is not None else None
        self.draws = 0
        while len(self.cache) < self.capacity:
            self._load(self._next_frame(), len(self.cache))

    def _next_frame(self) -> int:
        if not self.queue:
            self.queue = [int(i) for i in self.order_rng.permutation(len(self.sequence)) if i not in self.cache]
        return int(self.queue.pop())

    def _load(self, i: int, slot: int) -> None:
        """Decode frame i (colour in [0, 1]; targets in ray-distance metres, NaN = none) into a slot."""
        frame = self.sequence[i]
        self.colors[slot] = torch.as_tensor(self.sequence.color_on_depth_grid(frame.color), device=self.device
                                            ).float().div_(255).view(-1, 3)
        if self.targets is not None:
            valid = torch.as_tensor(np.asarray(self.targets.valid[i]), device=self.device).view(-1)
            mean = torch.as_tensor(np.asarray(self.targets.mean[i]), device=self.device).view(-1) * self.norms
            self.means[slot] = torch.where(valid, mean, torch.full_like(mean, float("nan")))
            self.sigmas[slot] = torch.as_tensor(np.asarray(self.targets.sigma[i]), device=self.device).view(-1) * self.norms
        self.cache[i] = slot

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random pixels of the cached frames, with their colours, depth targets and frames."""
        self.draws += 1
        if len(self.cache) < len(self.sequence) and self.draws % self.refresh_every == 0:
            _, slot = self.cache.popitem(last=False)
            self._load(self._next_frame(), slot)
        ids = list(self.cache)
        which = torch.randint(len(ids), (n,), generator=generator).to(self.device)  # drawn on the CPU generator
        pix = torch.randint(self.height * self.width, (n,), generator=generator).to(self.device)
        frames = torch.tensor(ids, device=self.device)[which]
        slots = torch.tensor(list(self.cache.values()), device=self.device)[which]
        rgb = self.colors[slots, pix]
        if self.means is None:
            mean = torch.full((n,), float("nan"), device=self.device)
            sigma = mean.clone()
        else:
            mean, sigma = self.means[slots, pix], self.sigmas[slots, pix]
        u = (pix % self.width).float().to(self.device)
        v = (pix // self.width).float().to(self.device)
        return RayBatch(u, v, frames, rgb, mean, sigma)

    def state(self) -> dict:
        """Plain ints/dicts only, so checkpoints load with torch.load(weights_only=True)."""
        return {"cache": [int(i) for i in self.cache], "queue": list(self.queue), "draws": self.draws,
                "order_rng": self.order_rng.bit_generator.state}

    def restore(self, state: dict) -> None:
        self.cache.clear()
        for slot, i in enumerate(state["cache"]):
            self._load(int(i), slot)
        self.queue = [int(i) for i in state["queue"]]
        self.draws = int(state["draws"])
        self.order_rng.bit_generator.state = state["order_rng"]
