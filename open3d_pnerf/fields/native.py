"""The fused CPU hash-grid kernel (hashgrid_kernel.cpp): compiled at first use, loaded with ctypes.

The kernel is plain C++ with OpenMP and a C ABI, so it needs a C++ compiler (g++ or clang, with
OpenMP) and nothing else: no build step at install time, no torch headers. It is compiled once
per source version and machine into ``$XDG_CACHE_HOME/open3d_pnerf`` (``~/.cache`` by default)
and reused from there. Without a compiler, or with ``PNERF_NATIVE=0`` in the environment, or on
a non-CPU device, :class:`~open3d_pnerf.fields.encodings.HashGridEncoding` uses its pure-PyTorch
path; a warning says so once.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("hashgrid_kernel.cpp")
MAX_LEVELS = 32  # kMaxLevels of the kernel
FLAGS = ("-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=c++17")


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), sysconfig.get_config_var("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name.split()[0]):
            return name.split()[0]
    return None


def _cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "open3d_pnerf"


def _cpu_id() -> str:
    """What -march=native depends on: the CPU's model and flags (so a shared home on other CPUs recompiles)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        return next((ln for ln in info.splitlines() if ln.startswith("flags")), "") + platform.processor()
    except OSError:
        return platform.machine() + platform.processor()


@lru_cache(maxsize=None)
def library() -> ctypes.CDLL | None:
    """The loaded kernel library, compiling it first if needed; None (with one warning) if it
    cannot be built here or PNERF_NATIVE=0."""
    if os.environ.get("PNERF_NATIVE", "1") == "0":
        return None
    compiler = _compiler()
    if compiler is None:
        warnings.warn("open3d_pnerf: no C++ compiler found, so the hash grid runs its pure-PyTorch path (slower); "
                      "install g++ for the fused kernel", RuntimeWarning, stacklevel=3)
        return None
    key = hashlib.sha256(SOURCE.read_bytes() + " ".join((compiler, *FLAGS, _cpu_id())).encode()).hexdigest()[:16]
    target = _cache_dir() / f"hashgrid_kernel-{key}.so"
    if not target.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:  # compile beside, rename: safe with several ranks
            built = Path(tmp) / target.name
            run = subprocess.run([compiler, *FLAGS, str(SOURCE), "-o", str(built)], capture_output=True, text=True)
            if run.returncode != 0:
                warnings.warn(f"open3d_pnerf: compiling the hash-grid kernel failed ({run.stderr.strip()[:300]}); "
                              "using the pure-PyTorch path (slower)", RuntimeWarning, stacklevel=3)
                return None
            os.replace(built, target)
    lib = ctypes.CDLL(str(target))
    pointer, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.hashgrid_forward.argtypes = [pointer, i64, i32, pointer, pointer, pointer, i64, i32, pointer, i32]
    lib.hashgrid_backward.argtypes = [pointer, i64, i32, pointer, pointer, pointer, i64, i32, pointer, pointer, pointer,
                                      i32]
    return lib


def available() -> bool:
    """Whether the fused kernel can run here."""
    return library() is not None


class HashGridKernel(torch.autograd.Function):
    """out (B, L * F) of points x (B, 3) in [0, 1] over the levels' parameters (CPU float32).

    spec: (resolutions (L,) int32 tensor, dense flags (L,) int32 tensor: the dense levels come
    first, table_size, features); params: the dense levels' (1, F, R, R, R) volumes, then (when
    there are hashed levels) the hashed table (L_h * table_size, F). Gradients: for the
    parameters, and for x when it requires one (pose refinement).
    """

    @staticmethod
    def forward(ctx, spec, x: torch.Tensor, *params: torch.Tensor) -> torch.Tensor:
        resolutions, dense, table_size, features = spec
        x = x.contiguous()
        out = torch.empty(len(x), len(resolutions) * features, dtype=torch.float32)
        library().hashgrid_forward(x.data_ptr(), len(x), len(resolutions), resolutions.data_ptr(), dense.data_ptr(),
                                   _level_pointers(params, spec), table_size, features, out.data_ptr(),
                                   torch.get_num_threads())
        ctx.spec, ctx.parameters = spec, params
        ctx.save_for_backward(x, *params)
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        resolutions, dense, table_size, features = ctx.spec
        x, *params = ctx.saved_tensors
        grads = [_accumulator(p, original) for p, original in zip(params, ctx.parameters)]
        grad_x = torch.empty_like(x) if ctx.needs_input_grad[1] else None
        library().hashgrid_backward(x.data_ptr(), len(x), len(resolutions), resolutions.data_ptr(), dense.data_ptr(),
                                    _level_pointers(params, ctx.spec), table_size, features,
                                    grad_out.contiguous().data_ptr(), _level_pointers(grads, ctx.spec),
                                    None if grad_x is None else grad_x.data_ptr(), torch.get_num_threads())
        # leaf parameters got their gradient accumulated in .grad directly (see _accumulator)
        return (None, grad_x, *(None if g is original.grad else g for g, original in zip(grads, ctx.parameters)))


def _accumulator(saved: torch.Tensor, parameter: torch.Tensor) -> torch.Tensor:
    """Where the kernel adds a parameter's gradient. Inside ``loss.backward()``, for a leaf
    parameter without gradient hooks, its .grad itself: the existing one (autograd's
    accumulation), or, when it has none, a buffer kept on the parameter from the last step,
    zeroed, which becomes its .grad. The 21 MB table gradient is then not allocated afresh every
    step (each fresh allocation page-faults: that cost more than the kernel). A buffer someone
    still holds (the refcount says so) is not reused. Otherwise (``torch.autograd.grad``, which
    leaves .grad alone, or a hooked parameter) a new zeroed tensor that autograd receives."""
    if not (parameter.is_leaf and parameter.requires_grad) or not _accumulates_here(parameter):
        return torch.zeros_like(saved)
    if parameter.grad is None:
        buffer = getattr(parameter, "_pnerf_grad_buffer", None)
        # references: the attribute, `buffer`, getrefcount's argument; more means it is held elsewhere
        if buffer is None or buffer.shape != parameter.shape or sys.getrefcount(buffer) > 3:
            buffer = parameter._pnerf_grad_buffer = torch.empty_like(parameter)
        parameter.grad = buffer.zero_()
    return parameter.grad


def _accumulates_here(parameter: torch.Tensor) -> bool:
    """Whether the running backward pass will accumulate into parameter.grad (its AccumulateGrad
    node runs: ``backward()``, not ``autograd.grad``) with no hook that would see the gradient."""
    if parameter._backward_hooks or getattr(parameter, "_post_accumulate_grad_hooks", None):
        return False
    try:
        return torch._C._will_engine_execute_node(torch.autograd.graph.get_gradient_edge(parameter).node)
    except RuntimeError:  # torch refuses the question for a leaf inside autograd.grad, which never accumulates
        return False


def _level_pointers(params, spec):
    """A C array of each level's data pointer: a dense level's volume, or a hashed level's rows of the table."""
    _, dense, table_size, features = spec
    n_dense = int(dense.sum())
    pointers = [p.data_ptr() for p in params[:n_dense]]
    if len(params) > n_dense:
        table = params[n_dense]
        step = table_size * features * table.element_size()
        pointers += [table.data_ptr() + j * step for j in range(len(dense) - n_dense)]
    return (ctypes.c_void_p * len(pointers))(*pointers)
