"""Training rays as pixels: random pixels of the training frames with their colours and depth
targets, drawn from a bounded cache of decoded frames; and the fixed held-out pixels that
training scores itself on."""

from __future__ import annotations

import dataclasses
from collections import OrderedDict

import numpy as np
import torch

from .camera import camera_rays, pixel_coordinates, pixel_grid, ray_norms
from .data.sequence import RGBDSequence
from .rendering import Rays
from .targets import DepthTargets


@dataclasses.dataclass
class RayBatch:
    """R training rays with what they saw: u, v (R,) image coordinates (float, pixel centres at
    integers; off-centre for sparse targets seen between centres), frames (R,) the index of
    each ray's training frame, rgb (R, 3) in [0, 1] (bilinear between pixels off the centres),
    depth target mean and sigma (R,) in ray-distance metres (NaN = none), and weight (R,) of
    each target's loss terms (1 where the targets have no weights)."""

    u: torch.Tensor
    v: torch.Tensor
    frames: torch.Tensor
    rgb: torch.Tensor
    mean: torch.Tensor
    sigma: torch.Tensor
    weight: torch.Tensor

    def __len__(self) -> int:
        return len(self.u)

    def __getitem__(self, index) -> "RayBatch":
        return RayBatch(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))


class RayBatcher:
    """Draws random training rays from a bounded cache of decoded frames.

    sequence: the training frames at training resolution; targets: their DepthTargets (same
    resolution) or None. At most `cache_frames` frames are decoded at a time, into slots of
    preallocated tensors; with more frames the cache rotates one frame every `refresh_every`
    steps, in a seeded order, so memory stays bounded on long sequences.
    target_share: the share of each batch drawn among the cached frames' target pixels (the
    rest uniformly among all pixels) when targets are sparser than that; with denser targets
    (e.g. RGB-D) the uniform draw already holds that share and every ray is drawn uniformly.
    Sparse targets (SfM points) cover ~1% of the pixels: a uniform batch of 512 rays holds
    ~5 of them.
    """

    def __init__(self, sequence: RGBDSequence, targets: DepthTargets | None, device, seed: int,
                 cache_frames: int = 64, refresh_every: int = 4, target_share: float = 0.0):
        if not 0 <= target_share < 1:
            raise ValueError(f"target_share must be in [0, 1), got {target_share!r}")
        self.sequence, self.targets, self.device = sequence, targets, device
        self.height, self.width = sequence.image_size
        self.norms = torch.as_tensor(ray_norms(sequence.K, self.height, self.width), device=device).view(-1)
        self.capacity = min(cache_frames, len(sequence))
        self.refresh_every = refresh_every
        self.target_share = target_share
        self.order_rng = np.random.default_rng(seed)
        self.queue: list[int] = []
        self.cache: OrderedDict[int, int] = OrderedDict()  # frame -> slot, oldest first
        pixels = self.height * self.width
        self.colors = torch.empty(self.capacity, pixels, 3, device=device)
        has = targets is not None
        self.means = torch.empty(self.capacity, pixels, device=device) if has else None
        self.sigmas = torch.empty(self.capacity, pixels, device=device) if has else None
        self.weights = torch.empty(self.capacity, pixels, device=device) if has and targets.weight is not None else None
        self.offsets = (torch.empty(self.capacity, pixels, 2, device=device)
                        if has and targets.offset is not None else None)
        self.target_pixels: list[torch.Tensor] = [torch.empty(0, dtype=torch.long)] * self.capacity
        self._target_index: torch.Tensor | None = None  # slot * pixels + pixel of every cached target
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
        color = self.sequence.color_on_depth_grid(frame.color, frame.depth)
        self.colors[slot] = torch.as_tensor(color, device=self.device).float().div_(255).view(-1, 3)
        if self.targets is not None:
            t = self.targets
            valid = torch.as_tensor(np.asarray(t.valid[i]), device=self.device).view(-1)
            norms = self.norms
            if self.offsets is not None:  # metres along the ray per metre of depth, at the exact spots
                offset = np.asarray(t.offset[i])
                u, v = pixel_grid(self.height, self.width)
                norms = np.linalg.norm(camera_rays(self.sequence.K, u + offset[..., 0], v + offset[..., 1]), axis=-1)
                norms = torch.as_tensor(norms, dtype=torch.float32, device=self.device).view(-1)
                self.offsets[slot] = torch.as_tensor(offset, device=self.device).view(-1, 2)
            mean = torch.as_tensor(np.asarray(t.mean[i]), device=self.device).view(-1) * norms
            self.means[slot] = torch.where(valid, mean, torch.full_like(mean, float("nan")))
            self.sigmas[slot] = torch.as_tensor(np.asarray(t.sigma[i]), device=self.device).view(-1) * norms
            if self.weights is not None:
                self.weights[slot] = torch.as_tensor(np.asarray(t.weight[i]), device=self.device).view(-1)
            self.target_pixels[slot] = valid.nonzero()[:, 0].cpu()
            self._target_index = None
        self.cache[i] = slot

    def _draw_target_pixels(self) -> bool:
        """Whether batches draw target_share of their rays among the target pixels: targets
        cover less than that share of the cached pixels."""
        if self.targets is None or self.target_share == 0:
            return False
        covered = sum(len(p) for p in self.target_pixels[: len(self.cache)])
        return 0 < covered < self.target_share * len(self.cache) * self.height * self.width

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random rays of the cached frames, with their colours, depth targets and frames."""
        self.draws += 1
        if len(self.cache) < len(self.sequence) and self.draws % self.refresh_every == 0:
            _, slot = self.cache.popitem(last=False)
            self._load(self._next_frame(), slot)
        pixels = self.height * self.width
        n_target = round(self.target_share * n) if self._draw_target_pixels() else 0
        ids = list(self.cache)
        which = torch.randint(len(ids), (n - n_target,), generator=generator)  # drawn on the CPU generator
        pix = torch.randint(pixels, (n - n_target,), generator=generator)
        slot_of = torch.tensor(list(self.cache.values()))
        slots = slot_of[which]
        if n_target:
            if self._target_index is None:
                self._target_index = torch.cat([s * pixels + self.target_pixels[s] for s in slot_of.tolist()])
            picked = self._target_index[torch.randint(len(self._target_index), (n_target,), generator=generator)]
            slot_frame = torch.empty(self.capacity, dtype=torch.long)
            slot_frame[slot_of] = torch.tensor(ids)
            slots, pix = torch.cat([slots, picked // pixels]), torch.cat([pix, picked % pixels])
            frames = slot_frame[slots]
        else:
            frames = torch.tensor(ids)[which]
        slots, pix, frames = slots.to(self.device), pix.to(self.device), frames.to(self.device)
        u, v = (c.float() for c in pixel_coordinates(pix, self.width))
        if self.offsets is not None:
            off = self.offsets[slots, pix]
            u, v = u + off[:, 0], v + off[:, 1]
            rgb = self._bilinear(slots, u, v)
        else:
            rgb = self.colors[slots, pix]
        if self.means is None:
            mean = torch.full((n,), float("nan"), device=self.device)
            sigma = mean.clone()
        else:
            mean, sigma = self.means[slots, pix], self.sigmas[slots, pix]
        weight = self.weights[slots, pix] if self.weights is not None else torch.ones(n, device=self.device)
        return RayBatch(u, v, frames, rgb, mean, sigma, weight)

    def _bilinear(self, slots: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """(R, 3) colours of the cached frames in `slots` at image coordinates u, v (R,), bilinear
        between the pixel centres (clamped at the image border)."""
        u = u.clamp(0, self.width - 1)
        v = v.clamp(0, self.height - 1)
        u0 = u.floor().clamp(max=self.width - 2).long()
        v0 = v.floor().clamp(max=self.height - 2).long()
        fu, fv = (u - u0)[:, None], (v - v0)[:, None]
        at = lambda du, dv: self.colors[slots, (v0 + dv) * self.width + u0 + du]  # noqa: E731
        return (at(0, 0) * (1 - fu) + at(1, 0) * fu) * (1 - fv) + (at(0, 1) * (1 - fu) + at(1, 1) * fu) * fv

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


def heldout_rays(model, sequence: RGBDSequence, poses: np.ndarray, seed: int, n_rays: int = 2048):
    """A fixed random subset of held-out pixels for periodic evaluation: (Rays, rgb (R, 3) in [0, 1])
    of about n_rays pixels spread over the frames of `sequence` (the held-out frames at the
    training resolution) with camera-to-world poses (N, 4, 4), drawn from seed + 1; model: the
    PNeRFModel whose rays they are."""
    h, w = sequence.image_size
    rng = np.random.default_rng(seed + 1)
    per = max(1, n_rays // len(sequence))
    rays, rgbs = [], []
    for k, pose in enumerate(poses):
        pix = rng.choice(h * w, min(per, h * w), replace=False)
        frame = sequence[k]
        color = sequence.color_on_depth_grid(frame.color, frame.depth).reshape(-1, 3)[pix] / 255.0
        u, v = (torch.as_tensor(c, dtype=torch.float32) for c in pixel_coordinates(pix, w))
        rays.append(model.camera_rays(pose, sequence.K, u.to(model.device), v.to(model.device)))
        rgbs.append(torch.as_tensor(color, dtype=torch.float32, device=model.device))
    return Rays.cat(rays), torch.cat(rgbs)
