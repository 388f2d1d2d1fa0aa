"""Tests of open3d_pnerf.fields: encodings (hash grid, dense grid, frequency) and fields."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from open3d_pnerf.fields import (
    FIELD_CONFIGS,
    DenseGridEncoding,
    FrequencyEncoding,
    GridField,
    HashGridEncoding,
    HashGridField,
    VanillaNeRFField,
    native,
)

FIELDS = {"grid": GridField, "hashgrid": HashGridField, "vanilla": VanillaNeRFField}


def make_field(name: str, aabb, **kwargs):
    return FIELDS[name](aabb, **kwargs)

AABB = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]])
SMALL = {
    "grid": dict(resolutions=(8, 16), features=2, hidden=16),
    "hashgrid": dict(levels=4, log2_table_size=12, max_resolution=64, hidden=16),
    "vanilla": dict(width=32, depth=3, skip=2),
}


def points_in_and_out(n: int = 64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g)
    inside = AABB[0] + u * (AABB[1] - AABB[0])
    outside = inside.clone()
    outside[: n // 2, 0] = 1.5  # beyond x max
    outside[n // 2 :, 2] = -0.3  # below z min
    return inside, outside


# -- fields ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(FIELDS))
def test_field_shapes_ranges_and_zero_density_outside_the_box(name):
    torch.manual_seed(0)
    field = make_field(name, AABB, **SMALL[name])
    assert isinstance(field, FIELDS[name])
    inside, outside = points_in_and_out()
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    with torch.no_grad():
        # vanilla's ReLU density can be exactly 0 at init: lift it to see the box mask act
        if name == "vanilla":
            field.sigma_head.bias.fill_(1.0)
        sigma, rgb = field(inside, d)
        sigma_out, rgb_out = field(outside, d)
        dens = field.density(inside)
        geometry, features = field.geometry(inside)
        rgb_split = field.color(features, d)
    assert sigma.shape == (64,) and rgb.shape == (64, 3)
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    assert (rgb >= 0).all() and (rgb <= 1).all()
    assert (sigma > 0).all()
    assert (sigma_out == 0).all()
    assert (rgb_out >= 0).all() and (rgb_out <= 1).all()
    torch.testing.assert_close(dens, sigma)
    torch.testing.assert_close(geometry, sigma)  # forward is geometry then colour
    torch.testing.assert_close(rgb_split, rgb)


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_field_gradients_reach_every_parameter(name):
    torch.manual_seed(0)
    field = make_field(name, AABB, **SMALL[name])
    if name == "vanilla":
        with torch.no_grad():
            field.sigma_head.bias.fill_(1.0)  # keep the ReLU density active
    inside, _ = points_in_and_out(256)
    d = torch.nn.functional.normalize(inside, dim=-1)
    sigma, rgb = field(inside, d)
    (sigma.mean() + rgb.mean()).backward()
    for pname, p in field.named_parameters():
        assert p.grad is not None, pname
        assert torch.isfinite(p.grad).all(), pname
        assert p.grad.abs().sum() > 0, pname


def test_each_field_config_builds_its_field_with_its_settings():
    assert set(FIELD_CONFIGS) == set(FIELDS)
    for name, cls in FIELD_CONFIGS.items():
        assert isinstance(cls().build(AABB), FIELDS[name])
    hashgrid = FIELD_CONFIGS["hashgrid"](levels=3, log2_table_size=10, max_resolution=64).build(AABB)
    assert len(hashgrid.encoding.resolutions) == 3 and hashgrid.encoding.table_size == 1024
    vanilla = FIELD_CONFIGS["vanilla"](width=32, depth=6).build(AABB)
    assert len(vanilla.layers) == 6 and vanilla.layers[0].out_features == 32


def test_field_normalize_maps_the_box_to_the_unit_cube():
    field = make_field("grid", AABB, **SMALL["grid"])
    torch.testing.assert_close(field.normalize(AABB), torch.tensor([[0.0, 0, 0], [1, 1, 1]]))
    torch.testing.assert_close(field.normalize(AABB.mean(0, keepdim=True)), torch.full((1, 3), 0.5))


def test_field_state_dict_round_trip_gives_identical_outputs():
    torch.manual_seed(0)
    a = make_field("hashgrid", AABB, **SMALL["hashgrid"])
    torch.manual_seed(1)
    b = make_field("hashgrid", AABB, **SMALL["hashgrid"])
    x, _ = points_in_and_out()
    d = torch.nn.functional.normalize(x, dim=-1)
    assert not torch.allclose(a(x, d)[1], b(x, d)[1])
    b.load_state_dict(a.state_dict())
    torch.testing.assert_close(a(x, d)[1], b(x, d)[1])
    torch.testing.assert_close(a(x, d)[0], b(x, d)[0])


# -- hash grid -------------------------------------------------------------------------------
PRIMES = (1, 2654435761, 805459861)


def reference_hash_encoding(x: torch.Tensor, resolutions, tables, table_size: int) -> torch.Tensor:
    """Instant-NGP's encoding written plainly, level by level (the reference for the fast path).

    tables[l]: (table_size, F) rows of level l. A level with (R + 1)^3 <= table_size reads
    vertex (i, j, k) from row i + j (R + 1) + k (R + 1)^2, a finer one from row
    (i * 1 ^ j * 2654435761 ^ k * 805459861) mod table_size; trilinear weights.
    """
    out = []
    for r, table in zip(resolutions, tables):
        pos = x.clamp(0, 1) * r
        base = pos.floor().clamp(max=r - 1)
        frac = pos - base
        feat = 0
        for corner in range(8):
            d = torch.tensor([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])
            v = base.long() + d
            if (r + 1) ** 3 <= table_size:
                row = v[:, 0] + v[:, 1] * (r + 1) + v[:, 2] * (r + 1) ** 2
            else:
                row = (v[:, 0] * PRIMES[0] ^ v[:, 1] * PRIMES[1] ^ v[:, 2] * PRIMES[2]) % table_size
            w = torch.where(d.bool(), frac, 1 - frac).prod(-1, keepdim=True)
            feat = feat + w * table[row]
        out.append(feat)
    return torch.cat(out, 1)


def load_level_tables(enc: HashGridEncoding, tables) -> None:
    """Give the encoding the per-level tables of :func:`reference_hash_encoding`."""
    res = enc.resolutions
    with torch.no_grad():
        for level in range(enc.n_dense):  # dense levels: row i + j(R+1) + k(R+1)^2 -> volume[k, j, i]
            n = res[level] + 1
            enc.dense.grids[level].copy_(tables[level][: n**3].T.reshape(1, -1, n, n, n))
        if enc.table is not None:
            enc.table.copy_(torch.cat(tables[enc.n_dense:]))


# the fused kernel needs a C++ compiler: without one these tests skip (as the library falls back)
needs_kernel = pytest.mark.skipif(not native.available(), reason="the hash-grid kernel cannot be built here")
PATHS = ["torch", pytest.param("kernel", marks=needs_kernel)]  # the pure-PyTorch path and the fused CPU kernel


@pytest.mark.parametrize("backend", PATHS)
def test_hashgrid_matches_the_plain_instant_ngp_encoding_with_dense_and_hashed_levels(backend):
    torch.manual_seed(0)
    enc = HashGridEncoding(levels=5, features=2, log2_table_size=10, base_resolution=4, max_resolution=64,
                           backend=backend)
    res = enc.resolutions
    assert enc.n_dense == 2 and enc.table.shape == (3 * 1024, 2)  # 4, 8 dense (<= 1024 vertices); 16.. hashed
    tables = [torch.randn(1024, 2) for _ in res]
    load_level_tables(enc, tables)
    x = torch.rand(500, 3)
    x[:5] = torch.tensor([[0.0, 0, 0], [1, 1, 1], [1, 0.5, 0.5], [0.25, 0.5, 0.75], [0.999, 0.001, 0.5]])
    with torch.no_grad():
        torch.testing.assert_close(enc(x), reference_hash_encoding(x, res, tables, 1024), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("backend", PATHS)
def test_hashgrid_table_and_position_gradients_match_the_plain_encoding(backend):
    """The gradients of every level's parameters, and of the positions (what pose refinement
    needs; the hashed levels gave none before)."""
    torch.manual_seed(1)
    enc = HashGridEncoding(levels=3, features=3, log2_table_size=8, base_resolution=4, max_resolution=32,
                           backend=backend)
    res = enc.resolutions
    tables = [torch.randn(256, 3) for _ in res]
    load_level_tables(enc, tables)
    x, g = torch.rand(200, 3).requires_grad_(True), torch.randn(200, 9)
    (enc(x) * g).sum().backward()
    ref = [t.clone().requires_grad_(True) for t in tables]
    x_ref = x.detach().clone().requires_grad_(True)
    (reference_hash_encoding(x_ref, res, ref, 256) * g).sum().backward()
    hashed = enc.n_dense
    torch.testing.assert_close(enc.table.grad, torch.cat([t.grad for t in ref[hashed:]]), atol=1e-5, rtol=1e-5)
    n = res[0] + 1  # the dense level's volume gradient, in the reference's row order
    torch.testing.assert_close(enc.dense.grids[0].grad[0].reshape(3, -1).T, ref[0].grad[: n**3], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(x.grad, x_ref.grad, atol=1e-4, rtol=1e-4)
    assert x.grad.abs().max() > 1.0  # the hashed levels (res 11, 32) dominate it


@needs_kernel
def test_the_kernel_agrees_with_the_pure_pytorch_path_on_the_default_grid_and_training_step_sizes():
    torch.manual_seed(2)
    paths = [HashGridEncoding(backend=b) for b in ("torch", "kernel")]  # 8 levels 16..2048, 2^19 rows
    with torch.no_grad():
        for p in paths[0].parameters():
            p.uniform_(-1, 1)
    paths[1].load_state_dict(paths[0].state_dict())
    x, g = torch.rand(20_000, 3), torch.randn(20_000, 16)
    xs = [x.clone().requires_grad_(True) for _ in paths]
    outs = [enc(xi) for enc, xi in zip(paths, xs)]
    torch.testing.assert_close(outs[1], outs[0], atol=1e-5, rtol=1e-5)
    for out in outs:
        (out * g).sum().backward()
    for (name, a), b in zip(paths[0].named_parameters(), paths[1].parameters()):
        torch.testing.assert_close(b.grad, a.grad, atol=1e-5, rtol=1e-5, msg=name)
    torch.testing.assert_close(xs[1].grad, xs[0].grad, atol=1e-2, rtol=1e-4)  # gradients of order 1e4


@needs_kernel
def test_the_kernel_accumulates_into_existing_gradients_and_keeps_gradients_someone_holds():
    enc = HashGridEncoding(levels=4, log2_table_size=10, base_resolution=4, max_resolution=64, backend="kernel")
    x, g = torch.rand(100, 3), torch.randn(100, 8)
    (enc(x) * g).sum().backward()
    first = enc.table.grad.clone()
    (enc(x) * g).sum().backward()  # no zero_grad: gradients add up, as autograd's do
    torch.testing.assert_close(enc.table.grad, 2 * first)
    held = enc.table.grad
    enc.zero_grad(set_to_none=True)
    (enc(x) * g).sum().backward()
    torch.testing.assert_close(held, 2 * first)  # a gradient someone still holds is not overwritten
    torch.testing.assert_close(enc.table.grad, first)


@needs_kernel
def test_the_kernel_gives_autograd_grad_its_gradients_and_leaves_dot_grad_alone():
    # autograd.grad (gradient checks, distributed shares) never accumulates into .grad, and
    # a parameter with a hook must see its gradient: the kernel then hands it to autograd
    enc = HashGridEncoding(levels=4, log2_table_size=10, base_resolution=4, max_resolution=64, backend="kernel")
    x, g = torch.rand(100, 3), torch.randn(100, 8)
    (enc(x) * g).sum().backward()
    expected = enc.table.grad.clone()
    enc.zero_grad(set_to_none=True)
    (grad,) = torch.autograd.grad((enc(x) * g).sum(), [enc.table])
    torch.testing.assert_close(grad, expected)
    assert enc.table.grad is None
    seen = []
    enc.table.register_hook(lambda gradient: seen.append(gradient.clone()))
    (enc(x) * g).sum().backward()
    torch.testing.assert_close(seen[0], expected)
    torch.testing.assert_close(enc.table.grad, expected)


def small_grid(backend: str, dtype=torch.float32) -> HashGridEncoding:
    """Two dense levels (4, 8) and two hashed ones (16, 32) with random parameters."""
    torch.manual_seed(3)
    enc = HashGridEncoding(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32,
                           backend=backend).to(dtype)
    with torch.no_grad():
        for p in enc.parameters():
            p.uniform_(-1, 1)
    return enc


def kernel_inputs(enc: HashGridEncoding) -> tuple:
    """The operator's arguments after x: the encoding's parameters and its level layout."""
    return ([*enc.dense.grids, enc.table], *enc._kernel_spec)


@needs_kernel
def test_the_kernel_operator_passes_gradcheck_in_its_positions_and_parameters():
    enc = small_grid("kernel", torch.float64)
    params, *spec = kernel_inputs(enc)
    g = torch.Generator().manual_seed(4)
    x = (0.02 + 0.96 * torch.rand(12, 3, dtype=torch.float64, generator=g)).requires_grad_(True)
    leaves = [p.detach().clone().requires_grad_(True) for p in params]

    def encode(x, *params):
        return native.hashgrid_encode(x, list(params), *spec)

    assert torch.autograd.gradcheck(encode, (x, *leaves))


@needs_kernel
def test_the_kernel_operator_passes_torch_library_opcheck():
    enc = small_grid("kernel")
    params, *spec = kernel_inputs(enc)
    x = torch.rand(50, 3)
    known = native.hashgrid_encode(x[30:], params, *spec)
    for args in ((x, params, *spec), (x.requires_grad_(True), params, *spec, known)):
        torch.library.opcheck(torch.ops.open3d_pnerf.hashgrid_encode.default, args)


@needs_kernel
def test_known_encodings_are_copied_and_their_rows_still_get_their_gradient():
    enc = small_grid("kernel")
    params, *spec = kernel_inputs(enc)
    x, g = torch.rand(40, 3), torch.randn(40, 8)
    whole = native.hashgrid_encode(x, params, *spec)
    (whole * g).sum().backward()
    expected = [p.grad.clone() for p in params]
    enc.zero_grad(set_to_none=True)
    marker = torch.full((15, 8), 7.0)  # not the encoding: shows that the values are copied, not computed
    out = native.hashgrid_encode(x, params, *spec, marker)
    torch.testing.assert_close(out[:25], whole[:25])
    assert (out[25:] == 7.0).all()
    (out * g).sum().backward()
    for p, e in zip(params, expected):
        torch.testing.assert_close(p.grad, e)


@pytest.mark.parametrize("backend", PATHS)
def test_nan_and_out_of_range_points_are_defined_and_the_same_on_both_paths(backend):
    """A point outside [0, 1] is clamped onto the box (no gradient along the clamped axis); a point
    with a NaN or infinite coordinate encodes to 0 and passes no gradient, on the kernel as on the
    PyTorch path (NaN used to be undefined behaviour in the kernel)."""
    reference, enc = small_grid("torch"), small_grid(backend)
    x = torch.rand(9, 3)
    x[0, 1] = float("nan")
    x[1] = float("inf")
    x[2, 0] = -float("inf")
    x[3] = torch.tensor([1.5, -0.2, 0.5])
    x[4] = torch.tensor([0.0, 0.3, 0.5])  # on a face: inside
    g = torch.randn(9, 8)
    grads = []
    for e in (reference, enc):
        xi = x.clone().requires_grad_(True)
        out = e(xi)
        (out * g).sum().backward()
        grads.append((out.detach(), xi.grad, [p.grad for p in e.parameters()]))
    (out_r, gx_r, gp_r), (out_k, gx_k, gp_k) = grads
    assert torch.isfinite(out_k).all() and (out_k[:3] == 0).all()
    torch.testing.assert_close(out_k, out_r)
    torch.testing.assert_close(gx_k, gx_r, atol=1e-4, rtol=1e-4)
    assert (gx_k[:3] == 0).all() and gx_k[3, 0] == 0 and gx_k[3, 1] == 0 and gx_k[3, 2] != 0
    for a, b in zip(gp_k, gp_r):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    clamped = x.clone()
    clamped[3] = torch.tensor([1.0, 0.0, 0.5])
    torch.testing.assert_close(out_k[3], enc(clamped)[3].detach())


def run_isolated(script: str, tmp_path, **env) -> subprocess.CompletedProcess:
    """Python `script` in a fresh process with a fresh kernel cache, the default compiler (no CXX),
    and `env` on top."""
    base = {k: v for k, v in os.environ.items() if k != "CXX"}
    env = {**base, "XDG_CACHE_HOME": str(tmp_path / "cache"), "PNERF_NATIVE": "1", **env}
    return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)


FALLBACK = (
    "import warnings, torch\n"
    "from open3d_pnerf.fields import HashGridEncoding, native\n"
    "with warnings.catch_warnings(record=True) as caught:\n"
    "    warnings.simplefilter('always')\n"
    "    enc = HashGridEncoding(levels=2, log2_table_size=8, base_resolution=4, max_resolution=16)\n"
    "    x = torch.rand(10, 3)\n"
    "    assert not enc.uses_kernel(x) and enc(x).shape == (10, 4)\n"
    "    enc(x).sum().backward()\n"
    "said = [str(w.message) for w in caught if 'hash-grid kernel cannot run here' in str(w.message)]\n"
    "print(len(said)); print(said[0] if said else '')\n"
)


def cached_library(tmp_path) -> Path:
    """Where this kernel's built library lies in the fresh cache of :func:`run_isolated`."""
    where = run_isolated("from open3d_pnerf.fields import native; print(native.build_directory())", tmp_path)
    folder = Path(where.stdout.strip())
    folder.mkdir(parents=True)
    return folder / f"{native.NAME}.so"


def put_a_corrupt_library_in_the_cache(tmp_path) -> None:
    """A build of this kernel cut short: a file the dynamic loader cannot open."""
    cached_library(tmp_path).write_bytes(b"\x7fELF truncated")


def put_a_library_whose_runtime_is_gone_in_the_cache(tmp_path) -> None:
    """A library built against a shared runtime (an OpenMP library, say) that this machine no longer
    has: the loader refuses it, naming the missing library."""
    runtime = tmp_path / "runtime"
    runtime.mkdir()
    source = runtime / "gone.c"
    source.write_text("int gone_runtime(void) { return 1; }\n")
    subprocess.run(["cc", "-shared", "-fPIC", str(source), "-o", str(runtime / "libgone_omp.so")], check=True)
    source.write_text("int gone_runtime(void);\nint uses_it(void) { return gone_runtime(); }\n")
    subprocess.run(["cc", "-shared", "-fPIC", str(source), f"-L{runtime}", "-lgone_omp", "-o",
                    str(cached_library(tmp_path))], check=True)
    shutil.rmtree(runtime)


@pytest.mark.parametrize("case, cause", [
    ("no compiler", "no C++ compiler found"),
    ("a cache that cannot be written", "Not a directory"),
    ("a compiler that fails", "error: no OpenMP"),
    ("a corrupt library", "OSError"),
    pytest.param("a missing runtime", "libgone_omp.so: cannot open shared object file",
                 marks=pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler to build the case")),
])
@pytest.mark.slow
def test_every_build_or_load_failure_falls_back_to_pytorch_with_one_warning_naming_the_cause(case, cause, tmp_path):
    env = {}
    if case == "no compiler":  # a machine without g++: nothing on PATH
        env = {"PATH": str(tmp_path)}
    elif case == "a cache that cannot be written":  # a file where the cache folder should be
        (tmp_path / "cache").write_text("not a folder")
    elif case == "a compiler that fails":  # it answers --version like g++, and fails to compile
        compiler = tmp_path / "c++"
        compiler.write_text('#!/bin/sh\n[ "$1" = --version ] && exec g++ --version\necho "error: no OpenMP" >&2; exit 1\n')
        compiler.chmod(0o755)
        env = {"CXX": str(compiler)}
    elif case == "a corrupt library":
        put_a_corrupt_library_in_the_cache(tmp_path)
    else:
        put_a_library_whose_runtime_is_gone_in_the_cache(tmp_path)
    run = run_isolated(FALLBACK, tmp_path, **env)
    assert run.returncode == 0, run.stderr
    count, message = run.stdout.strip().split("\n", 1)
    assert count == "1", run.stdout  # one warning, once
    assert cause in message, message


def test_the_kernel_builds_with_the_ninja_package_when_none_is_on_path(tmp_path, monkeypatch):
    """cpp_extension runs `ninja` from PATH; a virtual environment that is not activated has the
    ninja package's executable off PATH: the build puts it there, and only while it builds."""
    monkeypatch.setenv("PATH", str(tmp_path))
    with native._ninja_on_path():
        found = shutil.which("ninja")
        assert found is not None and subprocess.run([found, "--version"], capture_output=True).returncode == 0
    assert os.environ["PATH"] == str(tmp_path)


@pytest.mark.slow
def test_pnerf_native_0_turns_the_kernel_off_without_a_warning(tmp_path):
    run = run_isolated(FALLBACK, tmp_path, PNERF_NATIVE="0")
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().split("\n")[0] == "0"


@pytest.mark.slow
def test_a_kernel_built_once_loads_from_its_cache_without_building(tmp_path):
    script = ("import time; from open3d_pnerf.fields import native; t = time.perf_counter(); "
              "print(native.unavailable_reason(), round(time.perf_counter() - t, 1))")
    first = run_isolated(script, tmp_path)
    assert first.stdout.startswith("None"), first.stdout + first.stderr
    folders = list((tmp_path / "cache" / "open3d_pnerf").iterdir())  # one build, its library, no lock left
    assert len(folders) == 1 and (folders[0] / f"{native.NAME}.so").is_file() and not (folders[0] / "lock").exists()
    (folders[0] / "build.ninja").unlink()  # nothing left to build with: loading must not need it
    second = run_isolated(script, tmp_path, PATH=str(tmp_path))  # nor a compiler or ninja
    assert second.stdout.startswith("None"), second.stdout + second.stderr


def test_hashed_trilinear_gradcheck_of_the_table_and_the_weights():
    from open3d_pnerf.fields.encodings import _HashedTrilinear

    g = torch.Generator().manual_seed(0)
    table = torch.randn(40, 2, dtype=torch.float64, generator=g, requires_grad=True)
    rows = torch.randint(0, 40, (6, 2, 8), generator=g)  # repeated rows accumulate
    weights = torch.rand(6, 2, 8, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, w: _HashedTrilinear.apply(t, rows, w), (table, weights))


def test_hashgrid_dense_level_vertices_read_their_own_volume_entries():
    res = 16
    enc = HashGridEncoding(levels=1, features=2, log2_table_size=13, base_resolution=res, max_resolution=res)
    assert enc.n_dense == 1 and enc.table is None  # (16 + 1)^3 <= 2^13: stored densely
    with torch.no_grad():
        enc.dense.grids[0].normal_()
    ijk = torch.stack(torch.meshgrid(*[torch.arange(res + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    with torch.no_grad():
        out = enc(ijk.float() / res)  # exact vertices (res is a power of two)
    vol = enc.dense.grids[0][0]  # (F, z, y, x)
    torch.testing.assert_close(out, vol[:, ijk[:, 2], ijk[:, 1], ijk[:, 0]].T)


def test_hashgrid_interpolation_is_trilinear_and_continuous():
    torch.manual_seed(0)
    enc = HashGridEncoding(levels=3, features=2, log2_table_size=10, base_resolution=4, max_resolution=64)
    assert enc.table is not None and enc.n_dense == 1  # 4 is dense; 16 and 64 are hashed
    with torch.no_grad():
        for p in enc.parameters():
            p.normal_()
        # continuity across cell faces of every level (0.5 is a face of all three grids)
        x = torch.rand(50, 3)
        x[:, 0] = 0.5
        e = torch.tensor([1e-5, 0, 0])
        jump = (enc(x + e) - enc(x - e)).abs().max()
        assert jump < 1e-2
        # within a cell the encoding is linear along an axis: midpoint = mean of the ends
        res = enc.resolutions
        for level, r in enumerate(res):
            a = (torch.floor(torch.rand(20, 3) * r) + 0.1) / r  # well inside one cell
            b = a + torch.tensor([0.8 / r, 0, 0])
            sl = slice(2 * level, 2 * level + 2)
            mid = enc((a + b) / 2)[:, sl]
            torch.testing.assert_close(mid, (enc(a)[:, sl] + enc(b)[:, sl]) / 2, atol=1e-4, rtol=1e-4)


def test_hashgrid_output_dim_and_gradients():
    enc = HashGridEncoding(levels=4, features=3, log2_table_size=10, base_resolution=4, max_resolution=32)
    assert enc.out_dim == 12
    x = torch.rand(33, 3)
    out = enc(x)
    assert out.shape == (33, 12)
    (out * torch.randn_like(out)).sum().backward()
    for p in enc.parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0
    # each point touches at most 8 rows per hashed level
    hashed = enc.levels - enc.n_dense
    assert (enc.table.grad.abs().sum(1) > 0).sum() <= 33 * 8 * hashed


def test_hashgrid_accepts_points_on_the_upper_box_faces():
    for size, res in ((15, 31), (10, 64)):  # (31 + 1)^3 = 2^15 exactly fills the table: dense; 64: hashed
        enc = HashGridEncoding(levels=1, features=2, log2_table_size=size, base_resolution=res, max_resolution=res)
        x = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.5, 0.5], [0.3, 0.2, 1.0], [1.2, -0.1, 0.5]])
        out = enc(x)  # points on (or beyond, after clamping) the max faces of the scene box
        assert out.shape == (4, 2) and torch.isfinite(out).all()


# -- dense grid ------------------------------------------------------------------------------
def test_dense_grid_vertices_match_stored_values_align_corners():
    torch.manual_seed(0)
    enc = DenseGridEncoding(resolutions=(5, 9), features=2)
    with torch.no_grad():
        for g in enc.grids:
            g.normal_()
    for level, r in enumerate((5, 9)):
        idx = torch.randint(0, r, (40, 3))  # (i, j, k) along (x, y, z)
        x = idx.float() / (r - 1)  # align_corners: vertex i sits at i / (R - 1)
        with torch.no_grad():
            out = enc(x)[:, 2 * level : 2 * level + 2]
        grid = enc.grids[level][0]  # (F, D=z, H=y, W=x)
        expected = grid[:, idx[:, 2], idx[:, 1], idx[:, 0]].T
        torch.testing.assert_close(out, expected, atol=1e-5, rtol=1e-5)


def test_dense_grid_is_trilinear_between_vertices():
    torch.manual_seed(1)
    enc = DenseGridEncoding(resolutions=(6,), features=3)
    with torch.no_grad():
        enc.grids[0].normal_()
        r = 6
        idx = torch.randint(0, r - 1, (30, 3))
        a = idx.float() / (r - 1)
        for axis in range(3):
            step = torch.zeros(3)
            step[axis] = 1.0 / (r - 1)
            mid = enc(a + step / 2)
            torch.testing.assert_close(mid, (enc(a) + enc(a + step)) / 2, atol=1e-5, rtol=1e-5)
        # a quarter of the way: 3/4 of one neighbour + 1/4 of the other
        step = torch.tensor([1.0 / (r - 1), 0, 0])
        torch.testing.assert_close(enc(a + step / 4), 0.75 * enc(a) + 0.25 * enc(a + step), atol=1e-5, rtol=1e-5)


def test_dense_grid_out_dim_and_gradients():
    enc = DenseGridEncoding(resolutions=(4, 8, 16), features=2)
    assert enc.out_dim == 6
    x = torch.rand(20, 3)
    out = enc(x)
    assert out.shape == (20, 6)
    out.sum().backward()
    for g in enc.grids:
        assert g.grad is not None and g.grad.abs().sum() > 0
        # trilinear weights sum to one per point: d(sum out)/d(grid) sums to the point count
        torch.testing.assert_close(g.grad.sum(), torch.tensor(20.0 * 2))


# -- frequency encoding -------------------------------------------------------------------------
def test_frequency_encoding_values_and_out_dim():
    enc = FrequencyEncoding(3, 4)
    assert enc.out_dim == 3 * (2 * 4 + 1)
    assert FrequencyEncoding(3, 10, include_input=False).out_dim == 60
    x = torch.tensor([[0.25, -0.5, 0.1]])
    out = enc(x)
    assert out.shape == (1, enc.out_dim)
    torch.testing.assert_close(out[:, :3], x)
    # layout after the input: sin of (coordinate, frequency) pairs, then cos
    freqs = [2.0**k * math.pi for k in range(4)]
    sines = torch.tensor([[math.sin(c * f) for c in x[0].tolist() for f in freqs]])
    cosines = torch.tensor([[math.cos(c * f) for c in x[0].tolist() for f in freqs]])
    torch.testing.assert_close(out[:, 3:15], sines)
    torch.testing.assert_close(out[:, 15:], cosines)


# -- coarse-to-fine levels (issue 30) ---------------------------------------------------------------
def test_coarse_to_fine_weights_ramp_the_levels_in_coarsest_first():
    field = make_field("hashgrid", AABB, levels=8, log2_table_size=12, max_resolution=256)
    assert field.level_weights("cpu") is None
    for share, expected in ((0.0, [1, 0, 0, 0, 0, 0, 0, 0]), (0.5, [1, 1, 1, 1, 0.5, 0, 0, 0]),
                            (3 / 7, [1, 1, 1, 1, 0, 0, 0, 0])):
        field.enable_levels(share)
        torch.testing.assert_close(field.level_weights("cpu"), torch.tensor(expected, dtype=torch.float32),
                                   atol=1e-6, rtol=0)
    field.enable_levels(1.0)
    assert field.level_weights("cpu") is None


@pytest.mark.parametrize("name", ["grid", "hashgrid"])
def test_levels_that_are_off_change_nothing_the_field_returns(name):
    """With only the coarsest level on, the finer levels' parameters do not reach the density
    or the colour, and get no gradient; turned on again, they do."""
    kwargs = {"resolutions": (8, 16, 32)} if name == "grid" else {"levels": 4, "log2_table_size": 13,
                                                                  "max_resolution": 64}
    field = make_field(name, AABB, **kwargs)
    enc = field.encoding
    finer = list(enc.grids[1:]) if name == "grid" else [enc.table]  # hash grid: level 0 dense, 1-3 hashed
    assert name == "grid" or len(enc.dense.grids) == 1
    x = points_in_and_out(64)[0]
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    field.enable_levels(0.0)
    sigma, rgb = field(x, d)
    (sigma.sum() + rgb.sum()).backward()
    assert all(p.grad is None or not p.grad.any() for p in finer)
    with torch.no_grad():
        for p in finer:
            p.add_(torch.randn_like(p))
    sigma2, rgb2 = field(x, d)
    torch.testing.assert_close(sigma2, sigma)
    torch.testing.assert_close(rgb2, rgb)
    field.enable_levels(None)
    assert not torch.allclose(field(x, d)[0], sigma)


@pytest.mark.parametrize("bf16, native_here, expected", [
    (None, True, torch.bfloat16), (None, False, torch.float32),  # auto follows the hardware
    ("omitted", True, torch.bfloat16), ("omitted", False, torch.float32),  # a field's default is auto, as the config's
    (True, False, torch.bfloat16), (False, True, torch.float32),  # an explicit choice is kept
])
def test_bf16_mlps_run_where_asked_and_by_default_only_where_the_device_has_them(bf16, native_here, expected,
                                                                                 monkeypatch):
    from open3d_pnerf.fields import fields as fields_module

    monkeypatch.setattr(fields_module, "native_bf16", lambda device_type: native_here)
    chosen = {} if bf16 == "omitted" else {"bf16": bf16}
    field = HashGridField(torch.tensor([[-1.0] * 3, [1.0] * 3]), levels=2, log2_table_size=8, max_resolution=8,
                          **chosen)
    x = torch.zeros(4, 3)
    with field.mlp_precision(x):
        assert torch.nn.functional.linear(x, torch.ones(2, 3)).dtype == expected


def test_the_bf16_setting_takes_none_true_or_false_and_nothing_else():
    from open3d_pnerf import ReconstructionConfig
    from open3d_pnerf.errors import ConfigError

    assert ReconstructionConfig().runtime.bf16_mlp is None
    for value in (None, True, False):
        assert ReconstructionConfig().replace(**{"runtime.bf16_mlp": value}).runtime.bf16_mlp is value
    with pytest.raises(ConfigError, match="bf16_mlp"):
        ReconstructionConfig().replace(**{"runtime.bf16_mlp": "yes"})
