"""Training: rays drawn from images on the fly, Adam with an exponential schedule, held-out
evaluation, atomic checkpoints, clean stop on Ctrl-C and on a NaN loss; data-parallel over
the ranks of a torchrun launch (see :mod:`open3d_pnerf.distributed`)."""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ._files import atomic_write
from .config import ReconstructionConfig
from .data.sequence import RGBDSequence
from .distributed import DistributedContext
from .errors import CheckpointError, ConfigError, TrainingError
from .losses import LossGains, total_loss
from .pose_refinement import PoseCorrections
from .rendering import BatchShare, Rays, SamplingConfig, make_rays, render_rays
from .rendering.exposure import ExposureGains
from .targets import DepthTargets, ray_norms

CHECKPOINT_VERSION = 1


@dataclasses.dataclass
class RayBatch:
    """R training rays with what they saw: rgb (R, 3) in [0, 1], depth target mean and sigma
    (R,) ray-distance metres (NaN = none), and frames (R,) the index of each ray's frame."""

    rays: Rays
    rgb: torch.Tensor
    mean: torch.Tensor
    sigma: torch.Tensor
    frames: torch.Tensor

    def __len__(self) -> int:
        return len(self.rays)

    def __getitem__(self, index) -> "RayBatch":
        return RayBatch(self.rays[index], self.rgb[index], self.mean[index], self.sigma[index], self.frames[index])


class RayBatcher:
    """Draws random training rays from a bounded cache of decoded frames.

    sequence: the training frames at training resolution; poses (N, 4, 4) camera-to-world;
    targets: their DepthTargets (same resolution) or None. At most `cache_frames` frames
    are decoded at a time; with more frames the cache rotates one frame every
    `refresh_every` steps, in a seeded order, so memory stays bounded on long sequences.
    pose_corrections: a PoseCorrections of the N frames when poses are refined (the Trainer
    optimises it); rays then start from the corrected poses.
    """

    def __init__(self, sequence: RGBDSequence, poses, targets: DepthTargets | None, aabb, device, seed: int,
                 cache_frames: int = 64, refresh_every: int = 4, pose_corrections: PoseCorrections | None = None):
        self.sequence, self.targets, self.device = sequence, targets, device
        self.poses = torch.as_tensor(np.asarray(poses), dtype=torch.float32, device=device)
        self.K = torch.as_tensor(np.array(sequence.K), dtype=torch.float32, device=device)
        self.aabb = aabb
        self.height, self.width = sequence.image_size
        self.norms = torch.as_tensor(ray_norms(sequence.K, self.height, self.width), device=device)
        self.capacity = min(cache_frames, len(sequence))
        self.refresh_every = refresh_every
        self.order_rng = np.random.default_rng(seed)
        self.queue: list[int] = []
        self.cache: OrderedDict[int, tuple] = OrderedDict()
        self.draws = 0
        self.pose_corrections = pose_corrections
        while len(self.cache) < self.capacity:
            self._load(self._next_frame())

    def _next_frame(self) -> int:
        if not self.queue:
            self.queue = [int(i) for i in self.order_rng.permutation(len(self.sequence)) if i not in self.cache]
        return int(self.queue.pop())

    def _load(self, i: int) -> None:
        frame = self.sequence[i]
        color = torch.as_tensor(self.sequence.color_on_depth_grid(frame.color), device=self.device).float().div_(255).view(-1, 3)
        if self.targets is not None:
            valid = torch.as_tensor(np.asarray(self.targets.valid[i]), device=self.device).view(-1)
            norms = self.norms.view(-1)
            mean = torch.as_tensor(np.asarray(self.targets.mean[i]), device=self.device).view(-1) * norms
            sigma = torch.as_tensor(np.asarray(self.targets.sigma[i]), device=self.device).view(-1) * norms
            mean = torch.where(valid, mean, torch.full_like(mean, float("nan")))
        else:
            mean = sigma = None
        self.cache[i] = (color, mean, sigma)

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random rays of the cached frames, with their colours, depth targets and frames."""
        self.draws += 1
        if len(self.cache) < len(self.sequence) and self.draws % self.refresh_every == 0:
            self.cache.popitem(last=False)
            self._load(self._next_frame())
        ids = list(self.cache)
        which = torch.randint(len(ids), (n,), generator=generator).to(self.device)  # drawn on the CPU generator
        pix = torch.randint(self.height * self.width, (n,), generator=generator).to(self.device)
        frame_ids = torch.tensor(ids, device=self.device)[which]
        rgb = torch.empty(n, 3, device=self.device)
        mean = torch.full((n,), float("nan"), device=self.device)
        sigma = torch.full((n,), float("nan"), device=self.device)
        for slot, i in enumerate(ids):
            sel = which == slot
            if not sel.any():
                continue
            color, m, s = self.cache[i]
            rgb[sel] = color[pix[sel]]
            if m is not None:
                mean[sel], sigma[sel] = m[pix[sel]], s[pix[sel]]
        u = (pix % self.width).float().to(self.device)
        v = (pix // self.width).float().to(self.device)
        poses = self.poses[frame_ids]
        if self.pose_corrections is not None:
            poses = self.pose_corrections(poses, frame_ids)
        rays = make_rays(poses, self.K, u, v, self.aabb)
        return RayBatch(rays, rgb, mean, sigma, frame_ids)

    def state(self) -> dict:
        """Plain ints/dicts only, so checkpoints load with torch.load(weights_only=True)."""
        return {"cache": [int(i) for i in self.cache], "queue": list(self.queue), "draws": self.draws,
                "order_rng": self.order_rng.bit_generator.state}

    def restore(self, state: dict) -> None:
        self.cache.clear()
        for i in state["cache"]:
            self._load(int(i))
        self.queue = [int(i) for i in state["queue"]]
        self.draws = int(state["draws"])
        self.order_rng.bit_generator.state = state["order_rng"]


def sampling_of(config: ReconstructionConfig) -> SamplingConfig:
    """Samples per ray; every loss gets the same count (guided ones become importance ones without targets)."""
    return SamplingConfig(config.n_coarse, config.n_fine, config.n_guided)


class Trainer:
    """Optimises a field on rays from a :class:`RayBatcher`.

    eval_rays: optional (Rays, rgb) of held-out pixels scored every `config.eval_every`
    steps. checkpoint_dir: where ``checkpoint.pt`` is written atomically (by rank 0 only).
    dist: this process's place in a data-parallel run (default: a single process). With
    several ranks each step renders this rank's share of the same `rays_per_batch` rays,
    sums gradients and statistics over the ranks, and follows rank 0's clock for the time
    budget and the schedule; a Ctrl-C on any rank stops every rank after the same step.
    """

    def __init__(self, field, batcher: RayBatcher, config: ReconstructionConfig, eval_rays=None,
                 checkpoint_dir: str | Path | None = None, dist: DistributedContext | None = None):
        self.field, self.batcher, self.config = field, batcher, config
        self.pose_corrections = batcher.pose_corrections
        self.dist = dist or DistributedContext()
        if config.rays_per_batch < self.dist.world_size:
            raise ConfigError(f"config field rays_per_batch={config.rays_per_batch} is invalid: "
                              f"{self.dist.world_size} ranks need at least one ray each")
        self.eval_rays = eval_rays
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir else None
        self.exposure = (ExposureGains(len(batcher.sequence), batcher.device)
                         if config.exposure_compensation else None)
        fused = dict(fused=True) if _fused_adam_ok(field) else {}
        groups = [{"params": list(field.parameters()), "lr": config.lr}]
        if self.pose_corrections is not None:
            groups.append({"params": list(self.pose_corrections.parameters()), "lr": config.pose_lr})
        if self.exposure is not None:
            groups.append({"params": list(self.exposure.parameters()), "lr": config.lr})
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, config.adam_beta2), eps=1e-15, **fused)
        self._initial_lrs = [g["lr"] for g in groups]
        self.generator = torch.Generator().manual_seed(config.seed)
        self.sampling = sampling_of(config)
        self.step = 0
        self.elapsed = 0.0
        self.history: list[dict] = []
        self.samples_seen = 0
        self._stop_requested = False  # set by Ctrl-C in a data-parallel run

    # -- schedule ------------------------------------------------------------------------
    def _progress_fraction(self) -> float:
        frac = self.step / self.config.max_steps
        if self.config.time_budget_s:
            frac = max(frac, self.elapsed / self.config.time_budget_s)
        return min(frac, 1.0)

    def _set_lr(self) -> None:
        decay = self.config.lr_final_factor ** self._progress_fraction()
        for group, lr in zip(self.optimizer.param_groups, self._initial_lrs):
            group["lr"] = lr * decay

    def _gains(self) -> LossGains:
        """config.gains with Kd and Kz decayed by depth_gain_final_factor ** progress."""
        g, f = self.config.gains, self.config.depth_gain_final_factor ** self._progress_fraction()
        return dataclasses.replace(g, density=g.density * f, depth=g.depth * f)

    def _done(self) -> bool:
        if self.step >= self.config.max_steps:
            return True
        return bool(self.config.time_budget_s) and self.elapsed >= self.config.time_budget_s

    # -- one step ------------------------------------------------------------------------
    def train_step(self) -> dict:
        """One optimiser step on `rays_per_batch` rays: {"loss": ..., "psnr": ...} of the whole batch."""
        batch = self.batcher.sample(self.config.rays_per_batch, self.generator)
        noise, whole = self.generator, {}
        if self.dist.enabled:  # every rank drew the same batch; render this rank's rows with the batch's noise
            rows = self.dist.share(len(batch))
            whole = {"n_rays": len(batch), "n_target": int(torch.isfinite(batch.mean).sum())}
            noise = BatchShare(self.generator, len(batch), rows.start, rows.stop)
            batch = batch[rows]
        rgb, mean, sigma = batch.rgb, batch.mean, batch.sigma
        guide = self.config.loss != "photometric" and self.config.depth_guided_sampling
        fine, coarse = render_rays(
            self.field, batch.rays, self.sampling, mean if guide else None, sigma if guide else None,
            noise, with_coarse=self.config.coarse_loss,
        )
        renders = [fine] + ([coarse] if coarse is not None else [])
        if self.exposure is not None:  # the colours as each ray's frame recorded them
            renders = [dataclasses.replace(r, color=self.exposure(r.color, batch.frames)) for r in renders]
            fine = renders[0]
        terms = total_loss(self.config.loss, renders, rgb, mean, sigma, self._gains(), **whole)
        loss = terms["loss"]
        if self.pose_corrections is not None:  # each rank adds its share of the prior
            loss = loss + self.config.pose_prior_weight * self.pose_corrections.prior() / self.dist.world_size
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        loss, samples = loss.detach(), fine.t.numel()
        mse = ((fine.color.detach() - rgb) ** 2).mean()
        if self.dist.enabled:
            loss, mse, samples = self._sum_over_ranks(loss, mse * (len(rgb) / whole["n_rays"]), samples)
        if not torch.isfinite(loss):
            raise TrainingError(
                f"loss became {loss.item()} at step {self.step}; stopped. "
                + (f"The last good checkpoint is {self.checkpoint_path}." if self.checkpoint_path
                   and self.checkpoint_path.exists() else "No checkpoint was written.")
                + " Try a lower lr."
            )
        self.optimizer.step()
        self.samples_seen += samples
        return {"loss": float(loss), "psnr": float(-10 * torch.log10(mse.clamp(min=1e-10)))}

    def _sum_over_ranks(self, loss: torch.Tensor, mse: torch.Tensor, samples: int):
        """Sum the gradients and this step's (loss, mse, samples) shares over the ranks (in place).

        Each rank's loss is its share of the whole batch's loss, so the sums are the whole
        batch's gradient, loss and mean squared colour error. A parameter without a gradient
        counts as zero (every rank must send the same tensors)."""
        grads = []
        for p in self._trained_parameters():
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            grads.append(p.grad)
        stats = torch.stack([loss.double(), mse.double(), torch.tensor(float(samples), dtype=torch.float64,
                                                                        device=loss.device)])
        self.dist.sum_([*grads, stats], f"the gradient sum of step {self.step + 1}")
        return stats[0], stats[1], int(stats[2])

    def _trained_parameters(self) -> list[torch.Tensor]:
        """The field's parameters, then the pose corrections' and exposure gains' (when used)."""
        extra = [p for m in (self.pose_corrections, self.exposure) if m is not None for p in m.parameters()]
        return list(self.field.parameters()) + extra

    def _agree(self, elapsed: float) -> tuple[float, bool]:
        """(rank 0's elapsed seconds, whether Ctrl-C hit any rank): every rank then sets the
        same learning rate and stops after the same step."""
        device = next(self.field.parameters()).device
        t = torch.tensor([elapsed if self.dist.is_main else 0.0, float(self._stop_requested)],
                         dtype=torch.float64, device=device)
        self.dist.sum_([t], f"the clock agreement after step {self.step}")
        return float(t[0]), bool(t[1] > 0)

    def evaluate(self) -> dict:
        """PSNR (dB) of the held-out pixel set as {"eval_psnr": ...}; {} without one."""
        if self.eval_rays is None:
            return {}
        rays, rgb = self.eval_rays
        out = render_field(self.field, rays, self.sampling)
        mse = ((out["color"] - rgb) ** 2).mean()
        return {"eval_psnr": float(-10 * torch.log10(mse.clamp(min=1e-10)))}

    # -- loop --------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path | None:
        return self.checkpoint_dir / "checkpoint.pt" if self.checkpoint_dir else None

    def train(self) -> dict:
        """Run until max_steps or the time budget. Ctrl-C finishes the step, checkpoints, stops.

        Returns a summary: steps, seconds, samples_per_s, interrupted, last metrics.
        """
        cfg = self.config
        main = self.dist.is_main
        bar = tqdm(total=cfg.max_steps, initial=self.step, desc="training", disable=not (cfg.progress and main),
                   leave=False, dynamic_ncols=True)
        interrupted = False
        stats: dict = {}
        start_samples = self.samples_seen
        start_time = time.perf_counter() - self.elapsed
        run_start = time.perf_counter()
        restore_ctrl_c = self._catch_ctrl_c()
        try:
            if self.dist.enabled:  # as DistributedDataParallel does: every rank starts from rank 0's weights
                self.dist.broadcast_([p.data for p in self._trained_parameters()], "the initial parameters' broadcast")
            while not self._done():
                self._set_lr()
                try:
                    stats = self.train_step()
                except KeyboardInterrupt:  # the interrupted step is discarded
                    interrupted = True
                    break
                self.step += 1
                self.elapsed = time.perf_counter() - start_time
                if self.dist.enabled:
                    self.elapsed, interrupted = self._agree(self.elapsed)
                bar.update(1)
                if self.step % cfg.eval_every == 0 or self._done():
                    stats.update(self.evaluate())
                    self.history.append({"step": self.step, "seconds": round(self.elapsed, 2), **stats})
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}")
                if self.checkpoint_dir and main and self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
                if interrupted:  # a Ctrl-C on some rank, agreed by all after this step
                    break
        except KeyboardInterrupt:
            interrupted = True
        finally:
            bar.close()
            restore_ctrl_c()
        if self.checkpoint_dir and main:
            self.save_checkpoint()
        seconds = time.perf_counter() - run_start
        return {
            "steps": self.step,
            "seconds": round(self.elapsed, 2),
            "samples_per_s": round((self.samples_seen - start_samples) / max(seconds, 1e-9), 1),
            "interrupted": interrupted,
            **{k: round(v, 4) for k, v in stats.items()},
        }

    def _catch_ctrl_c(self):
        """With several ranks, make Ctrl-C only ask to stop (agreed at the end of the step, so
        no rank is left waiting in a collective). Returns a function that puts the previous
        SIGINT handler back (nothing changes in a single process or outside the main thread)."""
        if not self.dist.enabled or threading.current_thread() is not threading.main_thread():
            return lambda: None
        self._stop_requested = False

        def request_stop(signum, frame):
            self._stop_requested = True

        previous = signal.signal(signal.SIGINT, request_stop)
        return lambda: signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)

    # -- checkpoints ---------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "step": self.step,
            "elapsed": self.elapsed,
            "samples_seen": self.samples_seen,
            "field": self.field.state_dict(),
            **({"poses": self.pose_corrections.state_dict()} if self.pose_corrections is not None else {}),
            **({"exposure": self.exposure.state_dict()} if self.exposure is not None else {}),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "batcher": self.batcher.state(),
            "history": self.history,
        }

    def save_checkpoint(self) -> Path:
        """Write checkpoint.pt atomically (temporary file, fsync, rename)."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(self.checkpoint_path, lambda p: torch.save(self.state_dict(), p))
        return self.checkpoint_path

    def load_checkpoint(self, path: str | Path, state: dict | None = None) -> None:
        """Resume from a checkpoint written by :meth:`save_checkpoint` (weights_only load).

        state: the checkpoint's content when already read with :func:`read_checkpoint`.
        """
        state = read_checkpoint(path) if state is None else state
        try:
            self.field.load_state_dict(state["field"])
            if self.pose_corrections is not None:
                self.pose_corrections.load_state_dict(state["poses"])
            if self.exposure is not None:
                self.exposure.load_state_dict(state["exposure"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.generator.set_state(state["generator"])
            self.batcher.restore(state["batcher"])
            self.step, self.elapsed = int(state["step"]), float(state["elapsed"])
            self.samples_seen = int(state["samples_seen"])
            self.history = list(state["history"])
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise CheckpointError(f"{path}: does not match this model/config ({type(exc).__name__}: {exc})") from None


def _fused_adam_ok(field) -> bool:
    p = next(field.parameters())
    return p.device.type in ("cpu", "cuda") and p.dtype == torch.float32


def read_checkpoint(path) -> dict:
    """A training checkpoint's content, loaded safely (see :func:`safe_torch_load`) and version-checked."""
    state = safe_torch_load(path)
    version = state.get("version") if isinstance(state, dict) else None
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {version!r}, this library reads {CHECKPOINT_VERSION}")
    return state


def safe_torch_load(path) -> dict:
    """torch.load(weights_only=True): tensors and plain containers only, never code."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling errors, truncated files, foreign objects
        raise CheckpointError(f"{path}: not a valid open3d_pnerf checkpoint ({type(exc).__name__}: {exc})") from None


@torch.no_grad()
def render_field(field, rays, sampling: SamplingConfig, chunk: int = 2048,
                 keys: tuple = ("color", "depth", "depth_var", "opacity")) -> dict:
    """Render rays in chunks without gradient (deterministic mid-bin samples).

    Returns the :class:`~open3d_pnerf.rendering.RayRender` fields named by `keys`: by default
    color (R, 3), depth (R,) expected ray distance, depth_var (R,), opacity (R,); also
    t (R, S), edges (R, S + 1), weights (R, S) with S = n_coarse + n_fine + n_guided.
    """
    outs = {k: [] for k in keys}
    inference = SamplingConfig(sampling.n_coarse, sampling.n_fine + sampling.n_guided, 0)
    for start in range(0, len(rays), chunk):
        fine, _ = render_rays(field, rays[start : start + chunk], inference, jitter=False)
        for k in outs:
            outs[k].append(getattr(fine, k))
    return {k: torch.cat(v) for k, v in outs.items()}

