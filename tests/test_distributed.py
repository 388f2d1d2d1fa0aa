"""Tests of data-parallel training (open3d_pnerf.distributed) on CPU with gloo over loopback.

The multi-process tests start real ranks: under torchrun, or as two processes given the
variables torchrun sets (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT), so that a
test can kill, stop or interrupt one of them. Each runs tests/distributed_worker.py (the
"test" preset on the bundled sample, 64 rays a step) in a few seconds per rank.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist

from open3d_pnerf import cli
from open3d_pnerf.batches import RayBatcher
from open3d_pnerf.config import ReconstructionConfig
from open3d_pnerf.data import load_sample
from open3d_pnerf.distributed import ENV_KEYS, DistributedContext, init_distributed, launch_environment
from open3d_pnerf.errors import ConfigError, DistributedError
from open3d_pnerf.losses import total_loss
from open3d_pnerf.model import PNeRFModel, build_model
from open3d_pnerf.scene import scene_box
from open3d_pnerf.rendering import BatchShare, SamplingConfig, render_rays
from open3d_pnerf.targets import depth_targets
from open3d_pnerf.training import Trainer

WORKER = Path(__file__).with_name("distributed_worker.py")
# float32 MLPs: bfloat16 products round a half batch differently from the whole one
SMALL = {"optimizer.rays_per_batch": 64, "export.calibrate_depth_sigma": False, "export.max_views": 2,
         "runtime.bf16_mlp": False}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def base_env() -> dict:
    """This process's environment without a launch, one thread, gloo on the loopback interface."""
    env = {k: v for k, v in os.environ.items() if k not in (*ENV_KEYS, "MASTER_ADDR", "MASTER_PORT")}
    return {**env, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}


def start_ranks(out: Path, overrides: dict, world: int = 2) -> list[subprocess.Popen]:
    """`world` worker processes joined as torchrun would join them (stderr in out/rankN.err)."""
    port = free_port()
    procs = []
    for rank in range(world):
        env = {**base_env(), "RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank),
               "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
        with open(out / f"rank{rank}.err", "w") as err:
            procs.append(subprocess.Popen([sys.executable, str(WORKER), str(out), json.dumps(overrides)],
                                          env=env, stdout=subprocess.DEVNULL, stderr=err))
    return procs


def stop_all(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def wait_for(path: Path, procs, seconds: float = 60.0) -> None:
    """Until `path` exists (training is under way); fails if a rank exits first."""
    end = time.monotonic() + seconds
    while not path.exists():
        assert all(p.poll() is None for p in procs), "a rank exited before training started"
        assert time.monotonic() < end, f"{path} did not appear within {seconds} s"
        time.sleep(0.1)


def result(out: Path, rank: int) -> dict:
    return torch.load(out / f"rank{rank}.pt", weights_only=True)


def assert_same_fields(a: dict, b: dict, exact: bool = False) -> None:
    """Equal, or equal to within 1% of one Adam step (lr 1e-2): Adam divides each gradient by its
    own size, so an entry whose gradient is nearly zero turns the summation-order rounding of
    the two runs into up to a few 1e-5; a wrong gradient sum moves entries by whole steps."""
    assert a.keys() == b.keys()
    for k in a:
        if exact:
            assert torch.equal(a[k], b[k]), k
        else:
            torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-4, msg=lambda m, k=k: f"{k}: {m}")


# -- ranks, shares and the loss normalisation (one process) --------------------------------------
@pytest.mark.parametrize("world", [1, 2, 3, 4])
def test_shares_partition_a_batch_into_contiguous_near_equal_rows(world):
    for n in (world, 7, 64, 513):
        rows = [DistributedContext(rank, world).share(n) for rank in range(world)]
        assert rows[0].start == 0 and rows[-1].stop == n
        assert all(a.stop == b.start for a, b in zip(rows, rows[1:]))
        sizes = [r.stop - r.start for r in rows]
        assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1


def test_device_of_a_rank_is_its_local_gpu():
    ctx = DistributedContext(rank=5, world_size=8, local_rank=1)
    assert ctx.device("cuda") == ctx.device("cuda:3") == "cuda:1"
    assert ctx.device("cpu") == "cpu" and DistributedContext().device("cuda:3") == "cuda:3"
    assert not ctx.is_main and DistributedContext().is_main and not DistributedContext().enabled


@pytest.fixture(scope="module")
def scene():
    """The sample at half resolution, a test-preset field and 64 rays of the seed-0 batcher."""
    seq = load_sample().at_scale(0.5)
    targets = depth_targets(seq, poses=seq.gt_poses, progress=False)
    aabb = scene_box(targets, seq.gt_poses, seq.K)
    # float32 MLPs: bfloat16 products round each share differently from the whole batch
    cfg = ReconstructionConfig.preset("test", progress=False, **{"runtime.bf16_mlp": False})
    model = build_model(cfg, aabb, seq.gt_poses, seq.K, np.zeros((len(seq), 6, 6)))
    field = model.field
    batcher = RayBatcher(seq, targets, "cpu", seed=0)
    batch = batcher.sample(64, torch.Generator().manual_seed(0))
    rays, rgb, mean, sigma = model.rays(batch), batch.rgb, batch.mean, batch.sigma
    assert 0 < torch.isfinite(mean).sum() < 64  # rays with and without depth targets
    return field, rays, rgb, mean, sigma


def render(field, rays, mean, sigma, generator):
    return render_rays(field, rays, SamplingConfig(16, 16, 8), mean, sigma, generator, with_coarse=True)


def test_a_batch_share_is_sampled_exactly_as_inside_the_whole_batch(scene):
    field, rays, _, mean, sigma = scene
    whole, _ = render(field, rays, mean, sigma, torch.Generator().manual_seed(7))
    for rank in range(3):
        rows = DistributedContext(rank, 3).share(len(rays))
        share = BatchShare(torch.Generator().manual_seed(7), len(rays), rows.start, rows.stop)
        part, _ = render(field, rays[rows], mean[rows], sigma[rows], share)
        torch.testing.assert_close(part.t, whole.t[rows], rtol=0, atol=1e-6)
        torch.testing.assert_close(part.color, whole.color[rows], rtol=1e-5, atol=1e-6)
        if rank:  # a plain generator would sample these rows differently
            alone, _ = render(field, rays[rows], mean[rows], sigma[rows], torch.Generator().manual_seed(7))
            assert (alone.t - whole.t[rows]).abs().max() > 1e-3
    with pytest.raises(ValueError, match=r"rows \[0, 5\)"):
        render(field, rays[:4], mean[:4], sigma[:4], BatchShare(torch.Generator(), 64, 0, 5))


@pytest.mark.parametrize("kind", ["pnerf", "dsnerf", "photometric"])
def test_share_losses_and_gradients_add_up_to_the_whole_batch(scene, kind):
    field, rays, rgb, mean, sigma = scene
    params = list(field.parameters())

    def loss_and_grads(rows, **whole):  # the samples of these rows inside the whole batch
        noise = BatchShare(torch.Generator().manual_seed(3), len(rays), rows.start, rows.stop)
        fine, coarse = render(field, rays[rows], mean[rows], sigma[rows], noise)
        loss = total_loss(kind, [fine, coarse], rgb[rows], mean[rows], sigma[rows], **whole)["loss"]
        return loss.detach(), torch.autograd.grad(loss, params)

    loss, grads = loss_and_grads(slice(0, len(rays)))
    counts = {"n_rays": len(rays), "n_target": int(torch.isfinite(mean).sum())}
    shares = [loss_and_grads(DistributedContext(r, 3).share(len(rays)), **counts) for r in range(3)]
    torch.testing.assert_close(sum(s[0] for s in shares), loss, rtol=1e-5, atol=1e-7)
    for k, g in enumerate(grads):
        torch.testing.assert_close(sum(s[1][k] for s in shares), g, rtol=1e-4, atol=1e-8)
    if kind != "photometric":  # per-share means (each share's own target count) would not add up
        local = sum(loss_and_grads(DistributedContext(r, 3).share(len(rays)))[0] for r in range(3)) / 3
        assert abs(float(local - loss)) > 1e-4


def test_trainer_needs_a_ray_per_rank(scene):
    field, *_ = scene
    seq = load_sample().at_scale(0.5)
    batcher = RayBatcher(seq, None, "cpu", seed=0)
    cfg = ReconstructionConfig.preset("test", progress=False, **{"optimizer.rays_per_batch": 3})
    with pytest.raises(ConfigError, match="rays_per_batch=3.*4 ranks"):
        Trainer(PNeRFModel(field, cfg.sampling), batcher, cfg, dist=DistributedContext(0, 4))


# -- joining ------------------------------------------------------------------------------------------
@pytest.fixture
def no_launch(monkeypatch):
    for key in (*ENV_KEYS, "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(key, raising=False)
    return monkeypatch


def test_without_a_launch_everything_is_one_process(no_launch):
    assert launch_environment() is None
    assert init_distributed() == DistributedContext()
    for key, value in {"RANK": "0", "WORLD_SIZE": "1", "LOCAL_RANK": "0"}.items():
        no_launch.setenv(key, value)
    assert launch_environment() == (0, 1, 0)
    assert init_distributed() == DistributedContext()  # torchrun with one process: no process group
    assert not dist.is_initialized()


@pytest.mark.parametrize("env, match", [
    ({"RANK": "2", "WORLD_SIZE": "2"}, "RANK=2, WORLD_SIZE=2"),
    ({"RANK": "one", "WORLD_SIZE": "2"}, "must be integers"),
    ({"LOCAL_RANK": "0"}, "not both RANK and WORLD_SIZE"),
])
def test_an_inconsistent_launch_environment_is_a_distributed_error(no_launch, env, match):
    for key, value in env.items():
        no_launch.setenv(key, value)
    with pytest.raises(DistributedError, match=match):
        init_distributed()


def test_bad_backends_and_timeouts_are_config_errors(no_launch):
    with pytest.raises(ConfigError, match="'mpi'"):
        init_distributed(backend="mpi")
    for timeout in (0, -5.0, "10", True, None):
        with pytest.raises(ConfigError, match="timeout"):
            init_distributed(timeout_s=timeout)
    with pytest.raises(ConfigError, match=r"dist_backend="):
        ReconstructionConfig.preset("test", **{"runtime.dist_backend": "mpi"})
    for timeout in (0, -1.0, "600"):
        with pytest.raises(ConfigError, match=r"dist_timeout_s="):
            ReconstructionConfig.preset("test", **{"runtime.dist_timeout_s": timeout})
    for key, value in {"RANK": "0", "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}.items():
        no_launch.setenv(key, value)
    with pytest.raises(ConfigError, match="'nccl' needs a CUDA device"):
        init_distributed(device="cpu", backend="nccl")
    assert not dist.is_initialized()


@pytest.mark.slow
def test_joining_without_the_other_ranks_times_out_with_a_clear_error(no_launch):
    for key, value in {"RANK": "0", "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(free_port())}.items():
        no_launch.setenv(key, value)
    start = time.monotonic()
    with pytest.raises(DistributedError, match=r"rank 0 of 2 could not join the gloo process group at 127\.0\.0\.1"):
        init_distributed(timeout_s=1.5)
    assert time.monotonic() - start < 20
    assert not dist.is_initialized()


# -- real ranks ---------------------------------------------------------------------------------------
@pytest.mark.slow
def test_two_ranks_train_the_same_parameters_as_one_process(tmp_path):
    overrides = {**SMALL, "max_steps": 6}
    alone, pair = tmp_path / "alone", tmp_path / "pair"
    alone.mkdir(), pair.mkdir()
    subprocess.run([sys.executable, str(WORKER), str(alone), json.dumps(overrides)], env=base_env(), check=True,
                   capture_output=True, timeout=120)
    launch = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-addr", "127.0.0.1",
              "--master-port", str(free_port()), str(WORKER), str(pair), json.dumps(overrides)]
    run = subprocess.run(launch, env=base_env(), capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    one, rank0, rank1 = result(alone, 0), result(pair, 0), result(pair, 1)
    # each rank rendered half of every 64-ray batch; the single process all of it
    assert one["rays_per_call"][:6] == [64] * 6
    assert rank0["rays_per_call"][:6] == rank1["rays_per_call"][:6] == [32] * 6
    # the same weights on both ranks, and those of the single process up to rounding
    assert_same_fields(rank0["field"], rank1["field"], exact=True)
    assert_same_fields(rank0["field"], one["field"])
    for key in ("steps", "loss", "psnr"):
        assert rank0["stats"][key] == pytest.approx(one["stats"][key], rel=1e-3)
    # training moved the weights much further than the tolerance
    initial = ReconstructionConfig.preset("test", **overrides).build_field(one["field"]["aabb"].numpy()).state_dict()
    assert max((one["field"][k] - initial[k]).abs().max() for k in initial) > 1e-2
    # only rank 0 exported and checkpointed
    assert rank0["exported"] and not rank1["exported"]
    assert [p.name for p in (pair / "checkpoints").iterdir()] == ["checkpoint.pt"]
    assert torch.load(pair / "checkpoints" / "checkpoint.pt", weights_only=True)["step"] == 6


@pytest.mark.slow
def test_cli_reconstruct_under_torchrun_matches_one_process(tmp_path, no_launch):
    args = ["--quiet", "reconstruct", "sample", "--preset", "test", "--gt-poses", "--max-steps", "4",
            "--rays-per-batch", "96", "--set", "runtime.bf16_mlp=false"]  # float32: see SMALL
    assert cli.main([*args, "--out", str(tmp_path / "one")]) == cli.EXIT_OK
    launch = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-addr", "127.0.0.1",
              "--master-port", str(free_port()), "-m", "open3d_pnerf.cli", *args, "--out", str(tmp_path / "two")]
    run = subprocess.run(launch, env=base_env(), capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    one, two = (torch.load(tmp_path / d / "model.pt", weights_only=True) for d in ("one", "two"))
    assert_same_fields(one, two)
    report = json.loads((tmp_path / "two" / "report.json").read_text())
    assert report["training"]["steps"] == 4
    config = json.loads((tmp_path / "two" / "run_config.json").read_text())["config"]
    assert config["optimizer"]["rays_per_batch"] == 96 and config["runtime"]["dist_timeout_s"] == 600.0
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == sorted(p.name for p in (tmp_path / "one").iterdir())


@pytest.mark.slow
def test_a_rank_that_dies_makes_the_other_fail_fast_with_a_clear_error(tmp_path):
    procs = start_ranks(tmp_path, {**SMALL, "max_steps": 10**6, "runtime.checkpoint_every": 1, "runtime.dist_timeout_s": 10})
    try:
        wait_for(tmp_path / "checkpoints" / "checkpoint.pt", procs)
        procs[1].kill()
        start = time.monotonic()
        assert procs[0].wait(timeout=30) != 0
        assert time.monotonic() - start < 10  # the broken connection is seen at once, before the timeout
    finally:
        stop_all(procs)
    err = (tmp_path / "rank0.err").read_text()
    # the step's gradient sum or the clock agreement after it, whichever rank 0 was in
    assert re.search(r"DistributedError: rank 0 of 2: the (gradient sum of|clock agreement after) step \d+ failed", err)
    assert "another rank has probably died or hung" in err


@pytest.mark.slow
def test_a_hung_rank_makes_the_other_time_out_with_a_clear_error(tmp_path):
    procs = start_ranks(tmp_path, {**SMALL, "max_steps": 10**6, "runtime.checkpoint_every": 1, "runtime.dist_timeout_s": 3})
    try:
        wait_for(tmp_path / "checkpoints" / "checkpoint.pt", procs)
        procs[1].send_signal(signal.SIGSTOP)  # alive, holding its connections, never answering
        start = time.monotonic()
        assert procs[0].wait(timeout=60) != 0
        waited = time.monotonic() - start
    finally:
        stop_all(procs)
    assert 2.5 < waited < 15
    err = (tmp_path / "rank0.err").read_text()
    assert "did not complete within 3 s (dist_timeout_s)" in err and "Timed out" in err


@pytest.mark.slow
def test_ctrl_c_on_one_rank_stops_every_rank_after_the_same_step(tmp_path):
    procs = start_ranks(tmp_path, {**SMALL, "max_steps": 10**6, "runtime.checkpoint_every": 1})
    try:
        wait_for(tmp_path / "checkpoints" / "checkpoint.pt", procs)
        procs[1].send_signal(signal.SIGINT)
        assert [p.wait(timeout=60) for p in procs] == [0, 0]
    finally:
        stop_all(procs)
    # both ranks stopped after the same step, and rank 0's checkpoint holds it
    steps = [result(tmp_path, r)["interrupted_after"] for r in (0, 1)]
    assert steps[0] == steps[1] < 10**6
    assert torch.load(tmp_path / "checkpoints" / "checkpoint.pt", weights_only=True)["step"] == steps[0]


@pytest.mark.slow
def test_a_time_budget_stops_every_rank_after_the_same_step(tmp_path):
    procs = start_ranks(tmp_path, {**SMALL, "max_steps": 10**6, "time_budget_s": 1.5})
    try:
        assert [p.wait(timeout=90) for p in procs] == [0, 0]
    finally:
        stop_all(procs)
    rank0, rank1 = result(tmp_path, 0), result(tmp_path, 1)
    assert 1 < rank0["stats"]["steps"] == rank1["stats"]["steps"] < 10**6
    assert rank0["stats"]["seconds"] == rank1["stats"]["seconds"] >= 1.5  # rank 0's clock on both
    assert_same_fields(rank0["field"], rank1["field"], exact=True)
    assert np.isfinite(rank0["stats"]["loss"])
