"""Tests of open3d_pnerf.config and open3d_pnerf.training on the bundled sample.

Every Trainer here uses the "test" preset at half resolution (160x120) and runs at most a
dozen steps (~0.1 s a step on one core).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex

import numpy as np
import pytest
import torch

import open3d_pnerf.model as model_module
from open3d_pnerf.batches import RayBatcher
from open3d_pnerf.config import ReconstructionConfig
from open3d_pnerf.data import load_sample
from open3d_pnerf.errors import CheckpointError, ConfigError, TrainingError
from open3d_pnerf.losses import LossWeights
from open3d_pnerf.model import build_model
from open3d_pnerf.scene import scene_box
from open3d_pnerf.rendering import Rays, make_rays
from open3d_pnerf.targets import depth_targets
from open3d_pnerf.targets.storage import allocate
from open3d_pnerf.training import CHECKPOINT_VERSION, Trainer, safe_torch_load


# -- config ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["fast", "quality", "forward_facing", "test"])
def test_presets_exist_and_apply_their_values(name):
    cfg = ReconstructionConfig.preset(name)
    assert isinstance(cfg, ReconstructionConfig)
    for key, value in ReconstructionConfig.PRESETS[name].items():
        assert dotted(cfg, key) == value
    cfg.validate()
    over = ReconstructionConfig.preset(name, max_steps=7, loss="dsnerf")
    assert over.max_steps == 7 and over.loss == "dsnerf"


def test_test_preset_is_small():
    cfg = ReconstructionConfig.preset("test")
    assert cfg.max_steps <= 100 and cfg.optimizer.rays_per_batch <= 256
    assert cfg.grid.resolutions == (16, 32, 64, 128)


def test_unknown_preset_raises_config_error_naming_it():
    with pytest.raises(ConfigError, match="'turbo'"):
        ReconstructionConfig.preset("turbo")


def test_unknown_field_raises_config_error_naming_it():
    with pytest.raises(ConfigError, match=r"\['max_step'\]"):
        ReconstructionConfig.from_dict({"max_step": 10})
    with pytest.raises(ConfigError, match="learning_rate"):
        ReconstructionConfig.preset("test", learning_rate=1.0)
    with pytest.raises(ConfigError, match="colour"):
        ReconstructionConfig.from_dict({"objective": {"weights": {"colour": 1.0}}})
    with pytest.raises(ConfigError, match="n_corse"):
        ReconstructionConfig.preset("test", **{"sampling.n_corse": 8})
    with pytest.raises(ConfigError, match="sampling=3"):
        ReconstructionConfig.from_dict({"sampling": 3})


@pytest.mark.parametrize(
    "field, value",
    [
        ("loss", "l2"), ("field", "mlp"), ("max_steps", 0), ("max_steps", 2.5), ("time_budget_s", -1.0),
        ("image_scale", 1.5), ("image_scale", 0.0), ("holdout_every", -1), ("optimizer.rays_per_batch", 0),
        ("sampling.n_coarse", 1), ("sampling.n_fine", -1), ("sampling.n_guided", -2), ("optimizer.lr", 0.0),
        ("optimizer.lr_final_factor", 2.0), ("optimizer.adam_beta2", 1.0),
        ("grid.resolutions", ()), ("grid.resolutions", (16, 1)), ("runtime.cache_frames", 0),
        ("export.scale", 0.0), ("export.mesh_voxel_size", 0.0), ("device", "tpu"),
    ],
)
def test_bad_values_raise_config_error_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=rf"\b{field}="):
        ReconstructionConfig.preset("test", **{field: value})
    with pytest.raises(ConfigError, match=rf"\b{field}="):
        ReconstructionConfig().replace(**{field: value})


@pytest.mark.parametrize("field, value", [("optimizer.lr", "fast"), ("image_scale", None),
                                          ("optimizer.rays_per_batch", "512")])
def test_values_of_the_wrong_type_raise_config_error(field, value):
    with pytest.raises(ConfigError, match=rf"\b{field}="):
        ReconstructionConfig.preset("test", **{field: value})


@pytest.mark.parametrize("field", ["runtime.eval_every", "runtime.checkpoint_every", "grid.features",
                                   "hashgrid.levels"])
def test_zero_counts_are_rejected(field):
    with pytest.raises(ConfigError, match=rf"\b{field}="):
        ReconstructionConfig.preset("test", **{field: 0})


def test_config_dict_json_round_trip():
    cfg = ReconstructionConfig.preset(
        "quality", holdout_every=3, time_budget_s=12.5, loss="dsnerf",
        **{"objective.weights": LossWeights(color=2.0, depth_pdf=0.3, depth=0.7, dsnerf=0.01)},
    )
    data = json.loads(json.dumps(cfg.to_dict()))  # JSON: tuples become lists, weights a dict
    assert isinstance(data["grid"]["resolutions"], list) and isinstance(data["objective"]["weights"], dict)
    back = ReconstructionConfig.from_dict(data)
    assert back == cfg
    assert isinstance(back.objective.weights, LossWeights) and back.objective.weights.depth_pdf == 0.3
    assert back.grid.resolutions == (16, 32, 64, 128, 256, 384)
    assert isinstance(back.grid.resolutions, tuple)
    assert back.replace(seed=3).seed == 3 and back.seed == cfg.seed
    assert dataclasses.asdict(back) == cfg.to_dict()


def test_defaults_are_valid_and_presets_are_independent():
    # every field at its default is valid, and presets do not share mutable state
    ReconstructionConfig().validate()
    a, b = ReconstructionConfig.preset("test"), ReconstructionConfig.preset("test")
    assert a == b and a is not b and a.sampling is not b.sampling
    # reconstruct(seq) uses ReconstructionConfig(): the defaults are the "fast" preset
    assert ReconstructionConfig() == ReconstructionConfig.preset("fast")


def test_nested_dicts_dotted_names_and_field_configs():
    cfg = ReconstructionConfig.from_dict({"sampling": {"n_coarse": 24}, "hashgrid.levels": 6, "field": "grid",
                                          "grid": {"resolutions": [8, 16]}})
    assert cfg.sampling.n_coarse == 24 and cfg.sampling.n_fine == ReconstructionConfig().sampling.n_fine
    assert cfg.hashgrid.levels == 6 and cfg.field_config is cfg.grid and cfg.grid.resolutions == (8, 16)
    field = cfg.build_field(np.array([[0, 0, 0], [1, 1, 1]], np.float32))
    assert [g.shape[-1] for g in field.encoding.grids] == [8, 16]
    assert cfg.replace(**{"objective.weights.depth_pdf": 0.2}).objective.weights == LossWeights(depth_pdf=0.2)


def dotted(obj, name: str):
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


# -- fixtures on the bundled sample ----------------------------------------------------------------
@pytest.fixture(scope="module")
def scene():
    """The sample at half resolution (160x120), its depth targets and scene box."""
    seq = load_sample().at_scale(0.5)
    targets = depth_targets(seq, poses=seq.gt_poses, progress=False)
    aabb = scene_box(targets, seq.gt_poses, seq.K)
    return seq, targets, aabb


def config(**overrides) -> ReconstructionConfig:
    return ReconstructionConfig.preset("test", progress=False, **overrides)


def make_model(scene, cfg):
    seq, _, aabb = scene
    return build_model(cfg, aabb, seq.gt_poses, seq.K, np.zeros((len(seq), 6, 6)))


def make_trainer(scene, cfg, cache_frames=64, checkpoint_dir=None, eval_rays=None):
    seq, targets, aabb = scene
    batcher = RayBatcher(seq, targets, "cpu", cfg.seed, cache_frames)
    return Trainer(make_model(scene, cfg), batcher, cfg, eval_rays, checkpoint_dir)


def params(trainer):
    return [p.detach().clone() for p in trainer.model.field.parameters()]


class CountingSequence:
    """A proxy of an RGBDSequence that records which frames are decoded."""

    def __init__(self, seq):
        self.seq, self.reads = seq, []

    def __len__(self):
        return len(self.seq)

    def __getitem__(self, i):
        self.reads.append(int(i))
        return self.seq[i]

    def __getattr__(self, name):
        return getattr(self.seq, name)


def frame_of_origins(origins: torch.Tensor, poses: np.ndarray) -> np.ndarray:
    centres = torch.as_tensor(poses[:, :3, 3], dtype=torch.float32)
    dist = (origins[:, None, :] - centres[None, :, :]).norm(dim=-1)
    assert (dist.min(1).values < 1e-5).all()
    return dist.argmin(1).numpy()


def pixels_of(rays: Rays, frames: np.ndarray, poses: np.ndarray, K: np.ndarray):
    R = torch.as_tensor(poses[frames, :3, :3], dtype=torch.float32)
    d_cam = (R.transpose(1, 2) @ rays.directions[..., None])[..., 0]
    u = K[0, 0] * d_cam[:, 0] / d_cam[:, 2] + K[0, 2]
    v = K[1, 1] * d_cam[:, 1] / d_cam[:, 2] + K[1, 2]
    return torch.round(u).long().numpy(), torch.round(v).long().numpy(), (u, v)


# -- RayBatcher -----------------------------------------------------------------------------
def test_ray_batcher_returns_rays_colours_and_targets_of_the_drawn_pixels(scene):
    seq, targets, aabb = scene
    batcher = RayBatcher(seq, targets, "cpu", seed=0)
    batch = batcher.sample(500, torch.Generator().manual_seed(0))
    rays, rgb, mean, sigma = make_model(scene, config()).rays(batch), batch.rgb, batch.mean, batch.sigma
    assert isinstance(rays, Rays) and len(rays) == 500 and len(batch) == 500
    assert rays.origins.shape == (500, 3) and rays.directions.shape == (500, 3)
    assert rgb.shape == (500, 3) and mean.shape == (500,) and sigma.shape == (500,)
    assert (rgb >= 0).all() and (rgb <= 1).all()
    assert (rays.far > rays.near).all() and (rays.near >= 0.05).all()
    frames = frame_of_origins(rays.origins, seq.gt_poses)
    np.testing.assert_array_equal(batch.frames.numpy(), frames)  # the model's rays start at the pixels' frames
    u, v, (uf, vf) = pixels_of(rays, frames, seq.gt_poses, seq.K)
    torch.testing.assert_close(uf, batch.u, atol=1e-3, rtol=0)  # ... and pass through the drawn pixels' centres
    torch.testing.assert_close(vf, batch.v, atol=1e-3, rtol=0)
    np.testing.assert_array_equal(batch.u.numpy(), u)
    h, w = seq.image_size
    assert (u >= 0).all() and (u < w).all() and (v >= 0).all() and (v < h).all()
    # colours are the frames' pixels / 255
    colors = {int(i): seq[int(i)].color for i in np.unique(frames)}
    expected_rgb = np.stack([colors[int(f)][y, x] for f, x, y in zip(frames, u, v)]) / 255.0
    np.testing.assert_allclose(rgb.numpy(), expected_rgb, atol=1e-6)
    # targets: NaN exactly where the depth target is invalid
    valid = targets.valid[frames, v, u]
    assert valid.mean() > 0.5
    np.testing.assert_array_equal(np.isfinite(mean.numpy()), valid)
    assert (sigma.numpy()[valid] > 0).all()
    # mean and sigma carry the same per-ray unit factor as the target's z mean and sigma
    ratio = (sigma / mean).numpy()[valid]
    z_ratio = targets.sigma[frames, v, u][valid] / targets.mean[frames, v, u][valid]
    np.testing.assert_allclose(ratio, z_ratio, rtol=1e-5)
    z = targets.mean[frames, v, u][valid]
    factor = mean.numpy()[valid] / z
    assert (factor >= 1 - 1e-6).all() and (factor < 1.5).all()


def test_ray_batcher_targets_lie_on_the_observed_surface(scene):
    seq, targets, aabb = scene
    batcher = RayBatcher(seq, targets, "cpu", seed=0)
    batch = batcher.sample(500, torch.Generator().manual_seed(1))
    rays, mean = make_model(scene, config()).rays(batch), batch.mean
    frames = frame_of_origins(rays.origins, seq.gt_poses)
    np.testing.assert_array_equal(batch.frames.numpy(), frames)  # each ray knows its frame
    u, v, _ = pixels_of(rays, frames, seq.gt_poses, seq.K)
    valid = np.isfinite(mean.numpy())
    K = seq.K
    z = targets.mean[frames, v, u]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    world = np.einsum("nij,nj->ni", seq.gt_poses[frames, :3, :3], cam) + seq.gt_poses[frames, :3, 3]
    # the point at the target's ray parameter is the back-projected depth of the pixel
    at_target = (rays.origins + mean[:, None] * rays.directions).numpy()
    np.testing.assert_allclose(at_target[valid], world[valid], atol=2e-3)


def test_ray_batcher_without_targets_gives_nan_targets(scene):
    seq, _, aabb = scene
    batcher = RayBatcher(seq, None, "cpu", seed=0)
    batch = batcher.sample(64, torch.Generator().manual_seed(0))
    rgb, mean, sigma = batch.rgb, batch.mean, batch.sigma
    assert len(batch) == 64 and rgb.shape == (64, 3)
    assert torch.isnan(mean).all() and torch.isnan(sigma).all()


def sparse_scene_targets(seq, every: int = 97):
    """Sparse targets on the sample: every `every`-th pixel of each frame keeps its dense
    target, with an offset (0.3, -0.2) px and weight 0.5 (as SfM points would have)."""
    dense = depth_targets(seq, poses=seq.gt_poses, progress=False)
    t = allocate(len(seq), *seq.image_size, sparse=True)
    keep = np.zeros(seq.image_size, bool)
    keep.flat[::every] = True
    t.valid[:] = dense.valid & keep
    t.mean[:] = np.where(t.valid, dense.mean, 0)
    t.sigma[:] = np.where(t.valid, dense.sigma, 0)
    t.weight[t.valid] = 0.5
    t.offset[t.valid] = [0.3, -0.2]
    return t


def test_ray_batcher_draws_its_target_share_from_sparse_targets(scene):
    seq, _, _ = scene
    targets = sparse_scene_targets(seq)
    covered = targets.valid.mean()
    assert covered < 0.02
    g = torch.Generator().manual_seed(0)
    batch = RayBatcher(seq, targets, "cpu", seed=0, target_share=0.5).sample(400, g)
    has = torch.isfinite(batch.mean)
    assert has.sum() >= 200 and has.sum() < 200 + 20  # the share, plus the few uniform rays that hit one
    uniform = RayBatcher(seq, targets, "cpu", seed=0).sample(400, torch.Generator().manual_seed(0))
    assert torch.isfinite(uniform.mean).sum() < 20
    # target rays go through the targets' exact spots, with their weights and bilinear colours
    torch.testing.assert_close(batch.u[has] - batch.u[has].round(), torch.full((int(has.sum()),), 0.3))
    torch.testing.assert_close(batch.v[has] - batch.v[has].round(), torch.full((int(has.sum()),), -0.2))
    assert (batch.weight[has] == 0.5).all() and (batch.weight[~has] == 0).all()
    frame = int(batch.frames[has][0])
    col, row = int(batch.u[has][0].round()), int(batch.v[has][0].round())
    image = seq.color_on_depth_grid(seq[frame].color, seq[frame].depth).astype(np.float64) / 255
    # u = col + 0.3, v = row - 0.2: 30% of the next column, 20% of the row above
    expected = (0.2 * (0.7 * image[row - 1, col] + 0.3 * image[row - 1, col + 1])
                + 0.8 * (0.7 * image[row, col] + 0.3 * image[row, col + 1]))
    np.testing.assert_allclose(batch.rgb[has][0].numpy(), expected, atol=1e-6)
    # the target's ray distance is its z-depth times the norm of K^-1 [u, v, 1] at the exact spot
    K = seq.K
    u0, v0 = float(batch.u[has][0]), float(batch.v[has][0])
    norm = np.linalg.norm([(u0 - K[0, 2]) / K[0, 0], (v0 - K[1, 2]) / K[1, 1], 1])
    assert float(batch.mean[has][0]) == pytest.approx(targets.mean[frame, row, col] * norm, rel=1e-6)


def test_ray_batcher_with_dense_targets_ignores_the_share(scene):
    """RGB-D targets cover more than the share: batches are drawn as without it."""
    seq, targets, _ = scene
    a = RayBatcher(seq, targets, "cpu", seed=0, target_share=0.5).sample(256, torch.Generator().manual_seed(4))
    b = RayBatcher(seq, targets, "cpu", seed=0).sample(256, torch.Generator().manual_seed(4))
    for f in dataclasses.fields(a):
        torch.testing.assert_close(getattr(a, f.name), getattr(b, f.name), equal_nan=True)
    assert (a.weight == 1).all()


def test_ray_batcher_cache_is_bounded_and_rotates(scene):
    seq, targets, aabb = scene
    counting = CountingSequence(seq)
    batcher = RayBatcher(counting, targets, "cpu", seed=0, cache_frames=3, refresh_every=4)
    assert len(batcher.cache) == 3 and len(counting.reads) == 3
    g = torch.Generator().manual_seed(0)
    cached_history = []
    for draw in range(1, 37):
        before = list(batcher.cache)
        batch = batcher.sample(64, g)
        assert len(batcher.cache) == 3
        frames = set(batch.frames.tolist())
        assert frames <= set(batcher.cache)  # rays come from decoded frames only
        if draw % 4 == 0:
            assert list(batcher.cache)[:2] == before[1:]  # the oldest frame left
            assert list(batcher.cache)[2] not in before[1:]
            if draw <= 32:  # still walking the first permutation: a frame not seen yet
                assert list(batcher.cache)[2] not in counting.reads[:-1]
        else:
            assert list(batcher.cache) == before
        cached_history.append(set(batcher.cache))
        assert len(counting.reads) == 3 + draw // 4
    # the first 8 rotations walked through a permutation: every frame decoded exactly once
    assert sorted(counting.reads[:11]) == list(range(11))
    assert set().union(*cached_history) == set(range(11))


# -- Trainer ---------------------------------------------------------------------------------
def test_trainer_with_a_fixed_seed_is_reproducible(scene):
    cfg = config(max_steps=5)
    a, b = make_trainer(scene, cfg), make_trainer(scene, cfg)
    torch.testing.assert_close(params(a), params(b), rtol=0, atol=0)
    stats_a, stats_b = a.train(), b.train()
    assert stats_a["steps"] == stats_b["steps"] == 5
    assert stats_a["loss"] == stats_b["loss"]
    for p, q in zip(params(a), params(b)):
        assert torch.equal(p, q)
    # the run changed the field, and a different seed gives a different run
    c = make_trainer(scene, cfg.replace(seed=1))
    c.train()
    assert any(not torch.equal(p, q) for p, q in zip(params(a), params(c)))


def interrupt_at(trainer, step):
    """Make trainer.train() see a Ctrl-C when it reaches `step` (before the step runs)."""
    real = trainer.train_step

    def train_step():
        if trainer.step == step:
            raise KeyboardInterrupt
        return real()

    trainer.train_step = train_step


@pytest.mark.parametrize(
    "cache_frames",
    [
        64,
        3,
    ],
)
def test_checkpoint_resume_equals_a_straight_run(scene, tmp_path, cache_frames):
    cfg = config(max_steps=10)
    straight = make_trainer(scene, cfg, cache_frames)
    straight.train()
    assert straight.step == 10

    first = make_trainer(scene, cfg, cache_frames, checkpoint_dir=tmp_path)
    interrupt_at(first, 5)
    stats = first.train()
    assert stats["interrupted"] and stats["steps"] == 5
    path = tmp_path / "checkpoint.pt"
    assert path.is_file()

    second = make_trainer(scene, cfg, cache_frames, checkpoint_dir=tmp_path)
    second.load_checkpoint(path)
    assert second.step == 5 and second.samples_seen == first.samples_seen
    second.train()
    assert second.step == 10
    for p, q in zip(params(straight), params(second)):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-7)
    assert len(second.history) == len(straight.history)


def test_checkpoint_is_a_weights_only_file(scene, tmp_path):
    trainer = make_trainer(scene, config(max_steps=2), checkpoint_dir=tmp_path)
    trainer.train()
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["version"] == CHECKPOINT_VERSION and state["step"] == 2
    assert set(state["field"]) == set(trainer.model.field.state_dict())
    for k, v in trainer.model.field.state_dict().items():
        assert torch.equal(state["field"][k], v)
    assert not list(tmp_path.glob(".*tmp*"))  # the atomic write left no temporary file
    assert safe_torch_load(tmp_path / "checkpoint.pt")["step"] == 2


class Payload:
    """Unpickling this runs a shell command (what a crafted checkpoint would do)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(self.marker)}",))


def test_malicious_checkpoint_is_rejected_without_running_code(scene, tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "checkpoint.pt"
    torch.save({"version": CHECKPOINT_VERSION, "field": Payload(marker)}, path)
    trainer = make_trainer(scene, config(max_steps=2))
    with pytest.raises(CheckpointError, match="checkpoint.pt"):
        trainer.load_checkpoint(path)
    assert not marker.exists()
    with pytest.raises(CheckpointError):
        safe_torch_load(path)
    assert not marker.exists()
    # the payload is real: an unsafe load would have run it
    torch.load(path, weights_only=False)
    assert marker.exists()


def test_bad_checkpoints_raise_checkpoint_error(scene, tmp_path):
    trainer = make_trainer(scene, config(max_steps=1), checkpoint_dir=tmp_path)
    with pytest.raises(CheckpointError, match="not found"):
        trainer.load_checkpoint(tmp_path / "missing.pt")
    trainer.train()
    good = tmp_path / "checkpoint.pt"
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(CheckpointError):
        trainer.load_checkpoint(truncated)
    state = torch.load(good, weights_only=True)
    state["version"] = CHECKPOINT_VERSION + 1
    torch.save(state, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="version"):
        trainer.load_checkpoint(tmp_path / "future.pt")
    # a checkpoint of another field configuration does not load into this one
    other = make_trainer(scene, config(max_steps=1, **{"hashgrid.levels": 4}))
    with pytest.raises(CheckpointError, match="does not match"):
        other.load_checkpoint(good)


def test_nan_loss_raises_training_error_and_writes_no_checkpoint(scene, tmp_path):
    trainer = make_trainer(scene, config(max_steps=5), checkpoint_dir=tmp_path)
    with torch.no_grad():
        trainer.model.field.sigma_net[-1].bias.fill_(float("nan"))  # NaN density everywhere
    with pytest.raises(TrainingError, match="lower lr"):
        trainer.train()
    assert trainer.step == 0
    assert not (tmp_path / "checkpoint.pt").exists()


def test_time_budget_stops_training_early(scene):
    trainer = make_trainer(scene, config(max_steps=1000, time_budget_s=1e-3))
    stats = trainer.train()
    assert 1 <= stats["steps"] < 1000 and not stats["interrupted"]


def test_training_improves_the_psnr_of_evaluation_rays(scene):
    seq, _, aabb = scene
    frame = seq[5]
    h, w = seq.image_size
    g = np.random.default_rng(0)
    pix = g.choice(h * w, 300, replace=False)
    K = torch.as_tensor(seq.K, dtype=torch.float32)
    rays = make_rays(torch.as_tensor(seq.gt_poses[5], dtype=torch.float32), K,
                     torch.as_tensor(pix % w, dtype=torch.float32), torch.as_tensor(pix // w, dtype=torch.float32),
                     torch.as_tensor(aabb))
    rgb = torch.as_tensor(frame.color.reshape(-1, 3)[pix] / 255.0, dtype=torch.float32)
    trainer = make_trainer(scene, config(max_steps=12, **{"runtime.eval_every": 6}), eval_rays=(rays, rgb))
    before = trainer.evaluate()["eval_psnr"]
    stats = trainer.train()
    assert [hst["step"] for hst in trainer.history] == [6, 12]
    assert all(np.isfinite(hst["loss"]) and "eval_psnr" in hst for hst in trainer.history)
    assert stats["eval_psnr"] > before + 1.0
    assert stats["samples_per_s"] > 0


def test_model_render_is_chunk_independent_and_deterministic(scene):
    seq, _, aabb = scene
    model = make_model(scene, config())
    u = torch.arange(0, 160, 7, dtype=torch.float32)
    v = torch.full_like(u, 60.0)
    rays = model.camera_rays(seq.gt_poses[0], seq.K, u, v)
    a = model.render(rays, chunk=5)
    b = model.render(rays)
    assert set(a) == {"color", "depth", "depth_var", "opacity"}
    for k in a:
        torch.testing.assert_close(a[k], b[k])
    assert a["color"].shape == (len(rays), 3) and a["depth"].shape == (len(rays),)


def test_every_depth_weight_decays_to_the_final_factor_and_colour_stays(scene, monkeypatch):
    cfg = config(max_steps=100, objective={"weights": {"color": 1.0, "depth_pdf": 0.5, "depth": 0.4, "dsnerf": 0.2},
                                           "depth_weight_final_factor": 0.1})
    trainer = make_trainer(scene, cfg)
    for step, factor in ((0, 1.0), (50, 0.1 ** 0.5), (100, 0.1)):
        trainer.step = step
        g = trainer.loss_weights()
        assert g.color == 1.0
        # every depth term on the same schedule, the DS-NeRF baseline's too
        np.testing.assert_allclose([g.depth_pdf, g.depth, g.dsnerf], np.array([0.5, 0.4, 0.2]) * factor, rtol=1e-12)
    seen = []
    real = model_module.total_loss
    monkeypatch.setattr(model_module, "total_loss", lambda *a, **kw: seen.append(a[5]) or real(*a, **kw))
    trainer.step = 100
    trainer.train_step()
    assert seen[-1].depth == pytest.approx(0.04)  # the step uses the decayed gains


def test_adam_uses_the_configured_second_moment_decay(scene):
    for beta2 in (0.99, 0.999):
        trainer = make_trainer(scene, config(**{"optimizer.adam_beta2": beta2}))
        assert [g["betas"] for g in trainer.optimizer.param_groups] == [(0.9, beta2)] * 2  # field, exposure gains


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_training_on_cuda_draws_the_same_rays_as_on_cpu(scene):
    """The trainer's generator lives on the CPU: a seeded run on CUDA draws the same rays."""
    seq, targets, aabb = scene
    cfg = config(max_steps=3)
    pixels = []
    for device in ("cpu", "cuda"):
        batcher = RayBatcher(seq, targets, device, cfg.seed)
        batch = batcher.sample(64, torch.Generator().manual_seed(0))
        pixels.append(torch.stack([batch.u, batch.v, batch.frames.float()]).cpu())
    torch.testing.assert_close(pixels[0], pixels[1])
    cuda = cfg.replace(device="cuda")
    model = make_model(scene, cuda)
    trainer = Trainer(model, RayBatcher(seq, targets, model.device, cfg.seed), cuda)
    assert trainer.train()["steps"] == 3


def test_coarse_to_fine_turns_the_levels_on_over_its_share_of_training_and_all_at_the_end(scene, monkeypatch):
    cfg = config(max_steps=10, **{"optimizer.coarse_to_fine": 0.5})
    trainer = make_trainer(scene, cfg)
    seen = []
    real = trainer.train_step
    monkeypatch.setattr(trainer, "train_step", lambda: seen.append(trainer.model.field.levels_on) or real())
    trainer.train()
    assert seen[:5] == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8]) and seen[5:] == [None] * 5  # step / (0.5 x 10)
    assert trainer.model.field.levels_on is None  # saved and rendered with every level
    with pytest.raises(ConfigError, match="optimizer.coarse_to_fine=0.5 needs a grid field"):
        config(field="vanilla", **{"optimizer.coarse_to_fine": 0.5})


def test_coarse_color_scores_the_coarse_renders_colour_and_not_its_depth(scene):
    """objective.coarse_color: the model renders the coarse pass too; the loss adds its colour term
    and keeps the depth terms of the fine render alone (objective.coarse_terms: of both)."""
    seq, targets, _ = scene
    batch = RayBatcher(seq, targets, "cpu", seed=0).sample(256, torch.Generator().manual_seed(0))
    losses = {}
    for name, overrides in (("fine", {}), ("coarse colour", {"objective.coarse_color": True}),
                            ("coarse terms", {"objective.coarse_terms": True})):
        model = make_model(scene, config(**overrides))
        renders = model(batch, torch.Generator().manual_seed(1))
        assert len(renders) == (1 if name == "fine" else 2)
        losses[name] = model.loss(renders, batch, LossWeights())
    for term in ("depth_pdf", "depth"):
        torch.testing.assert_close(losses["coarse colour"][term], losses["fine"][term])
        assert losses["coarse terms"][term].item() > losses["fine"][term].item()
    assert losses["coarse colour"]["color"].item() > losses["fine"]["color"].item()
