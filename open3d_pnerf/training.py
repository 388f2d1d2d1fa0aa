"""Training: Adam with an exponential schedule over a PNeRFModel, held-out evaluation, atomic
checkpoints, clean stop on Ctrl-C and on a NaN loss; data-parallel over the ranks of a
torchrun launch (see :mod:`open3d_pnerf.distributed`). What is rendered and how it is scored
is the model's business (:mod:`open3d_pnerf.model`); this module only optimises."""

from __future__ import annotations

import dataclasses
import signal
import tempfile
import threading
import time
from pathlib import Path

import torch
from torch.profiler import record_function
from tqdm.auto import tqdm

from ._files import atomic_write
from .batches import RayBatcher
from .distributed import BACKENDS, DistributedContext
from .errors import CheckpointError, ConfigError, TrainingError
from .metrics import mse_to_psnr
from .losses import LossWeights
from .model import PNeRFModel
from .rendering import BatchShare
from .settings import FLAG, Settings, count, number, one_of, optional, setting

CHECKPOINT_VERSION = 1


@dataclasses.dataclass
class OptimizerConfig(Settings):
    """Adam and its schedule."""

    rays_per_batch: int = setting(512, count(1))
    """Rays per optimiser step; with several ranks, the whole batch, split between them."""
    lr: float = setting(1e-2, number(0, low_open=True))
    """Initial Adam learning rate."""
    lr_final_factor: float = setting(0.05, number(0, 1, low_open=True))
    """The learning rate decays exponentially to lr * lr_final_factor at the end."""
    adam_beta2: float = setting(0.99, number(0, 1, high_open=True))
    """Adam's second-moment decay (Instant-NGP's 0.99; PyTorch's 0.999 remembers the large early
    depth-loss gradients for ~1000 steps, after the depth weights have decayed)."""
    pose_lr: float = setting(1e-3, number(0, low_open=True))
    """Initial learning rate of the pose corrections (rad or m per step; same decay as lr)."""
    coarse_to_fine: float = setting(0.0, number(0, 1))
    """Share of training over which a grid field's encoding levels join, coarsest first
    (fields.EncodedField.enable_levels; BARF / Neuralangelo's coarse-to-fine): sparse views fit
    coarse geometry before fine levels can overfit them. 0: every level from the start."""
    target_ray_share: float = setting(0.5, number(0, 1, high_open=True))
    """Share of each batch's rays drawn among pixels with a depth target when targets are
    sparser than that (SfM points: ~1% of the pixels); 0 = every ray uniform over the pixels.
    DS-NeRF's setting (half its rays are depth rays); dense RGB-D targets already exceed it."""


@dataclasses.dataclass
class RuntimeConfig(Settings):
    """Evaluation, checkpoints, memory and data-parallel settings."""

    eval_every: int = setting(250, count(1))
    """Steps between held-out evaluations (a fixed subset of held-out pixels)."""
    checkpoint_every: int = setting(500, count(1))
    """Steps between checkpoints (when a checkpoint directory is given)."""
    cache_frames: int = setting(64, count(1))
    """Training frames kept decoded in memory at once (long sequences rotate through)."""
    dist_backend: str = setting("auto", one_of(BACKENDS))
    """torch.distributed backend when launched by torchrun with several ranks: "auto" (NCCL
    on CUDA, gloo on CPU), "gloo" or "nccl". Unused in a single process."""
    dist_timeout_s: float = setting(600.0, number(0, low_open=True, unit="seconds"))
    """Seconds any rank waits in a collective before raising DistributedError: a dead or hung
    rank gives an error, not a hang. Must exceed the longest gap between ranks."""
    bf16_mlp: bool | None = setting(None, optional(FLAG))
    """Run the fields' MLP matrix products in bfloat16 (autocast; parameters, encodings, colours
    and densities stay float32): about twice as fast MLPs where the device multiplies bfloat16
    natively, several times slower where it emulates it (fields.native_bf16). None: bfloat16
    where it is native, float32 elsewhere; True: always; False: all float32."""


class Trainer:
    """Optimises a :class:`~open3d_pnerf.model.PNeRFModel` on pixels from a :class:`RayBatcher`,
    as a ReconstructionConfig says (its optimizer, runtime and objective settings, max_steps,
    time_budget_s, seed and progress).

    eval_rays: optional (Rays, rgb) of held-out pixels scored every `runtime.eval_every`
    steps. checkpoint_dir: where ``checkpoint.pt`` is written atomically (by rank 0 only).
    dist: this process's place in a data-parallel run (default: a single process). With
    several ranks each step renders this rank's share of the same `rays_per_batch` rays,
    sums gradients and statistics over the ranks, and follows rank 0's clock for the time
    budget and the schedule; a Ctrl-C on any rank stops every rank after the same step.
    """

    def __init__(self, model: PNeRFModel, batcher: RayBatcher, config, eval_rays=None,
                 checkpoint_dir: str | Path | None = None, dist: DistributedContext | None = None):
        self.model, self.batcher, self.config = model, batcher, config
        self.dist = dist or DistributedContext()
        opt = config.optimizer
        if opt.rays_per_batch < self.dist.world_size:
            raise ConfigError(f"config field optimizer.rays_per_batch={opt.rays_per_batch} is invalid: "
                              f"{self.dist.world_size} ranks need at least one ray each")
        self.eval_rays = eval_rays
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir else None
        fused = dict(fused=True) if _fused_adam_ok(model.field) else {}
        groups = [{"params": list(model.field.parameters()), "lr": opt.lr}]
        if model.pose_corrections is not None:
            groups.append({"params": list(model.pose_corrections.parameters()), "lr": opt.pose_lr})
        if model.exposure is not None:
            groups.append({"params": list(model.exposure.parameters()), "lr": opt.lr})
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, opt.adam_beta2), eps=1e-15, **fused)
        self._initial_lrs = [g["lr"] for g in groups]
        self.generator = torch.Generator().manual_seed(config.seed)
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
        decay = self.config.optimizer.lr_final_factor ** self._progress_fraction()
        for group, lr in zip(self.optimizer.param_groups, self._initial_lrs):
            group["lr"] = lr * decay

    def _enable_levels(self, done: bool = False) -> None:
        """The field's encoding levels for this point of the schedule (optimizer.coarse_to_fine);
        done: all of them (training stopped, or a field without levels)."""
        share = self.config.optimizer.coarse_to_fine
        field = self.model.field
        if share > 0 and hasattr(field, "enable_levels"):
            field.enable_levels(None if done else self._progress_fraction() / share)

    def loss_weights(self) -> LossWeights:
        """objective.weights with every depth term's weight (Kd, Kz and the DS-NeRF one: the same
        schedule for every loss compared) decayed by depth_weight_final_factor ** progress."""
        objective = self.config.objective
        w, f = objective.weights, objective.depth_weight_final_factor ** self._progress_fraction()
        return dataclasses.replace(w, depth_pdf=w.depth_pdf * f, depth=w.depth * f, dsnerf=w.dsnerf * f)

    def _done(self) -> bool:
        if self.step >= self.config.max_steps:
            return True
        return bool(self.config.time_budget_s) and self.elapsed >= self.config.time_budget_s

    # -- one step ------------------------------------------------------------------------
    def train_step(self) -> dict:
        """One optimiser step on `rays_per_batch` rays: {"loss": ..., "psnr": ...} of the whole batch."""
        with record_function("pnerf.batch"):
            batch = self.batcher.sample(self.config.optimizer.rays_per_batch, self.generator)
        noise, whole = self.generator, {}
        if self.dist.enabled:  # every rank drew the same batch; render this rank's rows with the batch's noise
            rows = self.dist.share(len(batch))
            whole = {"n_rays": len(batch), "n_target": int(torch.isfinite(batch.mean).sum())}
            noise = BatchShare(self.generator, len(batch), rows.start, rows.stop)
            batch = batch[rows]
        renders = self.model(batch, noise)
        with record_function("pnerf.loss"):
            loss = self.model.loss(renders, batch, self.loss_weights(), **whole)["loss"]
        self.optimizer.zero_grad(set_to_none=True)
        with record_function("pnerf.backward"):
            loss.backward()
        fine = renders[0]
        loss, samples = loss.detach(), fine.t.numel()
        mse = ((fine.color.detach() - batch.rgb) ** 2).mean()
        if self.dist.enabled:
            loss, mse, samples = self._sum_over_ranks(loss, mse * (len(batch) / whole["n_rays"]), samples)
        if not torch.isfinite(loss):
            raise TrainingError(
                f"loss became {loss.item()} at step {self.step}; stopped. "
                + (f"The last good checkpoint is {self.checkpoint_path}." if self.checkpoint_path
                   and self.checkpoint_path.exists() else "No checkpoint was written.")
                + " Try a lower lr."
            )
        with record_function("pnerf.optimizer"):
            self.optimizer.step()
        self.samples_seen += samples
        return {"loss": float(loss), "psnr": float(mse_to_psnr(mse))}

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
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    def _agree(self, elapsed: float) -> tuple[float, bool]:
        """(rank 0's elapsed seconds, whether Ctrl-C hit any rank): every rank then sets the
        same learning rate and stops after the same step."""
        device = self.model.device
        t = torch.tensor([elapsed if self.dist.is_main else 0.0, float(self._stop_requested)],
                         dtype=torch.float64, device=device)
        self.dist.sum_([t], f"the clock agreement after step {self.step}")
        return float(t[0]), bool(t[1] > 0)

    def evaluate(self) -> dict:
        """PSNR (dB) of the held-out pixel set as {"eval_psnr": ...}; {} without one."""
        if self.eval_rays is None:
            return {}
        rays, rgb = self.eval_rays
        out = self.model.render(rays, keys=("color",))
        return {"eval_psnr": float(mse_to_psnr(((out["color"] - rgb) ** 2).mean()))}

    # -- loop --------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path | None:
        return self.checkpoint_dir / "checkpoint.pt" if self.checkpoint_dir else None

    def interrupted_checkpoint(self) -> Path | None:
        """The checkpoint of an interrupted run: the one in checkpoint_dir or, on rank 0 without a
        checkpoint_dir, one written now to a new temporary folder."""
        if self.checkpoint_dir is None and self.dist.is_main:
            self.checkpoint_dir = Path(tempfile.mkdtemp(prefix="pnerf-interrupted-"))
            self.save_checkpoint()
        return self.checkpoint_path

    def train(self, seconds: float | None = None) -> dict:
        """Run until max_steps or the time budget (or, given `seconds`, for at most that long in
        this call: training resumes where it stopped at the next call). Ctrl-C finishes the
        step, checkpoints, stops.

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
            while not self._done() and not (seconds is not None and time.perf_counter() - run_start >= seconds):
                self._set_lr()
                self._enable_levels()
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
                if self.step % cfg.runtime.eval_every == 0 or self._done():
                    stats.update(self.evaluate())
                    self.history.append({"step": self.step, "seconds": round(self.elapsed, 2), **stats})
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}")
                if self.checkpoint_dir and main and self.step % cfg.runtime.checkpoint_every == 0:
                    self.save_checkpoint()
                if interrupted:  # a Ctrl-C on some rank, agreed by all after this step
                    break
        except KeyboardInterrupt:
            interrupted = True
        finally:
            bar.close()
            restore_ctrl_c()
            self._enable_levels(done=True)  # what is saved and rendered uses every level
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
        model = self.model
        return {
            "version": CHECKPOINT_VERSION,
            "step": self.step,
            "elapsed": self.elapsed,
            "samples_seen": self.samples_seen,
            "field": model.field.state_dict(),
            **({"poses": model.pose_corrections.state_dict()} if model.pose_corrections is not None else {}),
            **({"exposure": model.exposure.state_dict()} if model.exposure is not None else {}),
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
            model = self.model
            model.field.load_state_dict(state["field"])
            if model.pose_corrections is not None:
                model.pose_corrections.load_state_dict(state["poses"])
            if model.exposure is not None:
                model.exposure.load_state_dict(state["exposure"])
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
