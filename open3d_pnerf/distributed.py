"""Data-parallel training with torch.distributed: process-group setup and teardown, rank
helpers, gradient sums.

Launched by torchrun (``torchrun --nproc-per-node N -m open3d_pnerf.cli reconstruct ...``),
every process (rank) finds RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT in its
environment and joins one process group: gloo on CPU, NCCL on CUDA (``cuda:LOCAL_RANK``).
Every rank holds the whole field and its Adam state. Each step every rank draws the same
full batch of rays and random numbers from the same seeded generator and renders only its
share (rows ``[B * rank // W, B * (rank + 1) // W)``); the losses are normalised by the whole
batch's counts, so the gradients summed over ranks are those of one process with the whole
batch, and every rank takes the same optimiser step. Without those variables, or with
WORLD_SIZE=1, nothing here runs and training is the single-process one, bit for bit.

Every collective waits at most ``timeout_s``; a rank that died or hung makes the others
raise :class:`~open3d_pnerf.errors.DistributedError` naming the rank, the operation and the
timeout, instead of hanging.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import os
from typing import Iterable, Iterator

import numpy as np
import torch
import torch.distributed as dist

from .errors import ConfigError, DistributedError

BACKENDS = ("auto", "gloo", "nccl")
ENV_KEYS = ("RANK", "WORLD_SIZE", "LOCAL_RANK")


@dataclasses.dataclass(frozen=True)
class DistributedContext:
    """Where this process stands in a data-parallel run (the default: a single process).

    rank in [0, world_size); local_rank: the rank on this machine (its GPU index);
    timeout_s: the collectives' timeout (None: unknown, a group created elsewhere);
    owns_group: this context created the process group and destroys it on shutdown.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    timeout_s: float | None = None
    owns_group: bool = False

    @property
    def enabled(self) -> bool:
        """More than one rank: training splits each batch and sums gradients."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that writes checkpoints, progress bars, logs and exports."""
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This rank's rows of a batch of n: [n * rank // W, n * (rank + 1) // W)."""
        return slice(n * self.rank // self.world_size, n * (self.rank + 1) // self.world_size)

    def device(self, device: str) -> str:
        """The torch device of this rank: a CUDA device becomes ``cuda:LOCAL_RANK``."""
        return f"cuda:{self.local_rank}" if self.enabled and device.split(":")[0] == "cuda" else device

    def sum_(self, tensors: Iterable[torch.Tensor], what: str) -> None:
        """Sum each tensor over all ranks, in place (DistributedError if a rank is gone)."""
        with self._collective(what):
            for t in tensors:
                dist.all_reduce(t, op=dist.ReduceOp.SUM)

    def broadcast_(self, tensors: Iterable[torch.Tensor], what: str) -> None:
        """Overwrite each tensor with rank 0's, in place."""
        with self._collective(what):
            for t in tensors:
                dist.broadcast(t, src=0)

    def broadcast_array(self, array: np.ndarray, what: str, device: str = "cpu") -> np.ndarray:
        """Rank 0's copy of a numpy array of the same shape and dtype on every rank.

        device: where the collective runs (NCCL needs the rank's CUDA device)."""
        if not self.enabled:
            return array
        t = torch.as_tensor(np.ascontiguousarray(array)).to(device)
        self.broadcast_([t], what)
        return t.cpu().numpy()

    @contextlib.contextmanager
    def _collective(self, what: str) -> Iterator[None]:
        try:
            yield
        except RuntimeError as exc:  # gloo/NCCL errors, timeouts (DistBackendError is one)
            timeout = f"{self.timeout_s:g} s (dist_timeout_s)" if self.timeout_s else "the process group's timeout"
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise DistributedError(
                f"rank {self.rank} of {self.world_size}: {what} failed or did not complete within {timeout}; "
                f"another rank has probably died or hung (its log has the cause). ({type(exc).__name__}: {detail})"
            ) from None


def launch_environment() -> tuple[int, int, int] | None:
    """(rank, world_size, local_rank) set by torchrun, or None when not launched by it.

    Raises DistributedError when the variables are present but inconsistent."""
    present = [k for k in ENV_KEYS if k in os.environ]
    if not present:
        return None
    if "RANK" not in os.environ or "WORLD_SIZE" not in os.environ:
        raise DistributedError(f"environment has {present} but not both RANK and WORLD_SIZE; launch with torchrun")
    try:
        rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
        local = int(os.environ.get("LOCAL_RANK", rank))
    except ValueError:
        values = {k: os.environ.get(k) for k in ENV_KEYS}
        raise DistributedError(f"environment {values}: RANK, WORLD_SIZE and LOCAL_RANK must be integers") from None
    if world < 1 or not 0 <= rank < world or local < 0:
        raise DistributedError(f"environment RANK={rank}, WORLD_SIZE={world}, LOCAL_RANK={local}: "
                               "need WORLD_SIZE >= 1, 0 <= RANK < WORLD_SIZE and LOCAL_RANK >= 0")
    return rank, world, local


def _backend_for(backend: str, device: str) -> str:
    """"gloo" or "nccl" for a device: "auto" picks NCCL on CUDA, gloo otherwise."""
    cuda = device.split(":")[0] == "cuda"
    if backend == "auto":
        return "nccl" if cuda else "gloo"
    if backend == "nccl" and not cuda:
        raise ConfigError(f"distributed backend 'nccl' needs a CUDA device, got device={device!r}; use 'gloo' on CPU")
    return backend


def init_distributed(device: str = "cpu", backend: str = "auto", timeout_s: float = 600.0) -> DistributedContext:
    """Join the process group of a torchrun launch, or describe a single process.

    device: the configured torch device ("cpu", "cuda", ...); backend: "auto", "gloo" or
    "nccl"; timeout_s > 0: how long any collective (and joining) may wait for the other
    ranks. An already initialised process group (a caller's own) is used as it is and left
    to its creator to destroy; its timeout is then the creator's.
    """
    if backend not in BACKENDS:
        raise ConfigError(f"distributed backend {backend!r} is unknown; expected one of {BACKENDS}")
    if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not timeout_s > 0:
        raise ConfigError(f"distributed timeout {timeout_s!r} is invalid: expected a number of seconds > 0")
    if dist.is_available() and dist.is_initialized():
        local = int(os.environ.get("LOCAL_RANK", 0))
        return DistributedContext(dist.get_rank(), dist.get_world_size(), local, None, owns_group=False)
    env = launch_environment()
    if env is None or env[1] == 1:
        return DistributedContext()
    rank, world, local = env
    if not dist.is_available():
        raise DistributedError("this torch build has no torch.distributed; it cannot train on several ranks")
    name = _backend_for(backend, device)
    if device.split(":")[0] == "cuda":
        if not torch.cuda.is_available() or local >= torch.cuda.device_count():
            count = torch.cuda.device_count() if torch.cuda.is_available() else 0
            raise ConfigError(f"rank {rank}: LOCAL_RANK={local} needs cuda:{local}, but this machine has {count} "
                              "CUDA device(s); start at most that many processes per node (--nproc-per-node)")
        torch.cuda.set_device(local)
    where = f"{os.environ.get('MASTER_ADDR', '?')}:{os.environ.get('MASTER_PORT', '?')}"
    try:
        dist.init_process_group(name, init_method="env://", rank=rank, world_size=world,
                                timeout=datetime.timedelta(seconds=float(timeout_s)))
    except (RuntimeError, ValueError) as exc:  # rendezvous timeouts, refused connections, missing MASTER_*
        raise DistributedError(f"rank {rank} of {world} could not join the {name} process group at {where} within "
                               f"{timeout_s:g} s ({type(exc).__name__}: {str(exc).strip().splitlines()[0]})") from None
    return DistributedContext(rank, world, local, float(timeout_s), owns_group=True)


def shutdown(context: DistributedContext) -> None:
    """Destroy the process group if `context` created it (a process exiting without this can abort)."""
    if context.owns_group and dist.is_initialized():
        dist.destroy_process_group()


@contextlib.contextmanager
def distributed_session(device: str = "cpu", backend: str = "auto", timeout_s: float = 600.0
                        ) -> Iterator[DistributedContext]:
    """:func:`init_distributed` for the duration of a with-block, then :func:`shutdown`."""
    context = init_distributed(device, backend, timeout_s)
    try:
        yield context
    finally:
        shutdown(context)
