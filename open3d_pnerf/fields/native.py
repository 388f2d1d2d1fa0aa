"""The hash-grid encoding's fused CPU kernel, a torch custom operator built on the machine at first use.

``hashgrid_kernel.cpp`` (package data) defines the operators ``open3d_pnerf::hashgrid_encode`` and
``open3d_pnerf::hashgrid_encode_backward``. :func:`available` builds it once per source, compiler
flags, CPU, torch and Python version with ``torch.utils.cpp_extension`` (ninja and the machine's
C++ compiler with OpenMP; ``-march=native``) in a build directory under
``$XDG_CACHE_HOME/open3d_pnerf`` (``~/.cache`` by default), guarded by cpp_extension's file lock so
that ranks starting together build it once, and afterwards loads the built library from there. This
module pairs the operators in an autograd formula and gives them fake (shape-only) versions.

Anything that stops the kernel (no compiler, a cache directory that cannot be written, a failed
compile, a library that does not load, e.g. without the OpenMP runtime) makes :func:`available`
False and :func:`unavailable_reason` say why; :class:`~open3d_pnerf.fields.HashGridEncoding` then
runs its pure-PyTorch path after one warning naming the cause. ``PNERF_NATIVE=0`` in the
environment turns the kernel off (no warning).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import shutil
import sys
import time
import warnings
from functools import lru_cache
from pathlib import Path

import torch

from .._files import cache_dir

NAME = "open3d_pnerf_hashgrid"
SOURCE = Path(__file__).with_name("hashgrid_kernel.cpp")
FLAGS = ("-O3", "-march=native", "-fopenmp")
MAX_LEVELS = 32  # kMaxLevels of the kernel
OFF = "PNERF_NATIVE=0 is set"
STALE_LOCK_S = 600  # a build's lock file older than this was left by a killed build (a build takes ~10-60 s)


def _cpu_id() -> str:
    """What -march=native depends on: the CPU's model and flags (a home shared by other CPUs rebuilds)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        return next((ln for ln in info.splitlines() if ln.startswith("flags")), "") + platform.processor()
    except OSError:
        return platform.machine() + platform.processor()


def build_directory() -> Path:
    """Where this source is built for this compiler, CPU, torch and Python."""
    key = " ".join((os.environ.get("CXX", "c++"), *FLAGS, _cpu_id(), torch.__version__, sys.version))
    return cache_dir() / f"hashgrid-{hashlib.sha256(SOURCE.read_bytes() + key.encode()).hexdigest()[:16]}"


@contextlib.contextmanager
def _ninja_on_path():
    """cpp_extension runs `ninja` from PATH: add the ninja package's when none is there (a virtual
    environment that is not activated)."""
    path = os.environ.get("PATH", "")
    if shutil.which("ninja") is None:
        import ninja

        os.environ["PATH"] = os.pathsep.join(p for p in (ninja.BIN_DIR, path) if p)
    try:
        yield
    finally:
        os.environ["PATH"] = path


def _build_and_load() -> None:
    """Build the kernel (if not built yet) and load it; raises with the cause when it cannot."""
    from torch.utils import cpp_extension

    if not SOURCE.is_file():
        raise RuntimeError(f"its source {SOURCE} is missing from the installed package")
    folder = build_directory()
    built, lock = folder / f"{NAME}.so", folder / "lock"
    if lock.exists() and time.time() - lock.stat().st_mtime > STALE_LOCK_S:
        lock.unlink()  # left by a build that was killed: cpp_extension would wait for it forever
    if built.is_file() and not lock.exists():  # built before (a read-only cache still loads)
        torch.ops.load_library(str(built))
        return
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        raise RuntimeError(f"no C++ compiler found ({compiler!r} is not on PATH; install g++, or set CXX)")
    folder.mkdir(parents=True, exist_ok=True)
    with _ninja_on_path():
        cpp_extension.load(NAME, [str(SOURCE)], extra_cflags=list(FLAGS), extra_ldflags=["-fopenmp"],
                           build_directory=str(folder), is_python_module=False, verbose=False)


@lru_cache(maxsize=None)
def unavailable_reason() -> str | None:
    """None if the kernel is loaded (building it first if needed), else why it cannot run here."""
    if os.environ.get("PNERF_NATIVE", "1") == "0":
        return OFF
    try:
        _build_and_load()
    except Exception as exc:  # compiler, ninja, file system and loader errors alike: the kernel is optional
        cause = f" ({exc.__cause__})" if exc.__cause__ is not None else ""  # what the loader said, under torch's words
        message = " ".join(f"{exc}{cause}".split())
        if len(message) > 600:  # a compiler's output: its command line first, the error last
            message = f"{message[:200]} ... {message[-400:]}"
        return f"{type(exc).__name__}: {message}"
    _register_autograd()
    return None


def available() -> bool:
    """Whether the fused kernel runs here (built and loaded on the first call)."""
    return unavailable_reason() is None


@lru_cache(maxsize=None)
def warn_fallback() -> None:
    """Say once per process that the hash grid runs its pure-PyTorch path, and why."""
    reason = unavailable_reason()
    if reason is not None and reason != OFF:
        warnings.warn(f"open3d_pnerf: the hash-grid kernel cannot run here ({reason}); the hash grid runs its "
                      "pure-PyTorch path instead (slower)", RuntimeWarning, stacklevel=4)


def hashgrid_encode(x: torch.Tensor, params: list[torch.Tensor], resolutions: list[int], dense: list[int],
                    table_size: int, features: int, known: torch.Tensor | None = None) -> torch.Tensor:
    """(n, L * F) encoding of points x (n, 3) in [0, 1] (see hashgrid_kernel.cpp), differentiable in
    x and params; known (m, L * F): the encoding of x's last m rows, computed before (its values are
    copied; it carries no gradient, the backward covers every row). Needs :func:`available`."""
    return torch.ops.open3d_pnerf.hashgrid_encode(x, params, resolutions, dense, table_size, features, known)


def _register_autograd() -> None:
    """The autograd formula of hashgrid_encode (its backward operator) and both operators' fake versions."""
    encode, backward = "open3d_pnerf::hashgrid_encode", "open3d_pnerf::hashgrid_encode_backward"

    def setup_context(ctx, inputs, output):
        x, params, *spec, _known = inputs
        ctx.save_for_backward(x, *params)
        ctx.spec = spec

    def gradient(ctx, grad_out):
        x, *params = ctx.saved_tensors
        x_needs_grad = ctx.needs_input_grad[0]
        grad_x, grad_params = torch.ops.open3d_pnerf.hashgrid_encode_backward(grad_out, x, params, *ctx.spec,
                                                                              x_needs_grad)
        # none for the other inputs (the dispatcher leaves out `known` when it is None)
        return (grad_x if x_needs_grad else None), grad_params, *[None] * (len(ctx.needs_input_grad) - 2)

    torch.library.register_autograd(encode, gradient, setup_context=setup_context)

    @torch.library.register_fake(encode)
    def _(x, params, resolutions, dense, table_size, features, known=None):
        return x.new_empty(x.shape[0], len(resolutions) * features)

    @torch.library.register_fake(backward)
    def _(grad_out, x, params, resolutions, dense, table_size, features, x_needs_grad):
        return x.new_empty(x.shape[0] if x_needs_grad else 0, 3), [torch.empty_like(p) for p in params]
