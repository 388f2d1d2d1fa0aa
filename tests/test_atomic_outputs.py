"""Outputs are never half-written: a crash mid-save leaves the previous files intact (issue 6).

A writer is made to write part of its file and then fail (an OSError, or Ctrl-C); the folder
must hold exactly its previous files, byte for byte, and no temporary file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny_reconstruction

import open3d_pnerf.storage as storage_module
from open3d_pnerf import Reconstruction, ReconstructionConfig
from open3d_pnerf.batches import RayBatcher
from open3d_pnerf.model import build_model
from open3d_pnerf.scene import scene_box
from open3d_pnerf.targets import depth_targets
from open3d_pnerf.training import Trainer, read_checkpoint


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def half_then(error: BaseException, write, path_arg: int = 0):
    """A writer that lets `write` write its file (argument `path_arg`), cuts it in half, then raises `error`."""

    def crashing(*args, **kwargs):
        write(*args, **kwargs)
        path = Path(args[path_arg])
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        raise error

    return crashing


@pytest.mark.parametrize("failing, error", [("model.pt", KeyboardInterrupt()), ("point_cloud.ply", OSError("disk full"))])
def test_a_crash_mid_save_leaves_the_previous_files_intact(tmp_path, monkeypatch, failing, error):
    folder = tiny_reconstruction().save(tmp_path / "recon")
    before = snapshot(folder)
    assert {"model.pt", "reconstruction.json", "poses.npy", "mesh.ply", "point_cloud.ply", "trajectory.log"} <= set(before)
    if failing == "model.pt":  # the first file written
        monkeypatch.setattr(torch, "save", half_then(error, torch.save, path_arg=1))
    else:  # the last one: every other new file is complete by then
        monkeypatch.setattr(storage_module, "write_point_cloud_ply",
                            half_then(error, storage_module.write_point_cloud_ply))
    newer = tiny_reconstruction(shift=0.5)
    with pytest.raises(type(error)):
        newer.save(folder)
    assert snapshot(folder) == before  # same names (no temporary left) and same bytes
    assert Reconstruction.load(folder).poses[0, 2, 3] == 0.0
    monkeypatch.undo()
    newer.save(folder)  # without the crash every file is replaced
    after = snapshot(folder)
    assert after.keys() == before.keys() and all(after[k] != before[k] for k in before)


def test_a_crash_mid_checkpoint_leaves_the_previous_checkpoint_intact(tmp_path, monkeypatch, plane_scene):
    seq, poses = plane_scene()
    config = ReconstructionConfig.preset("test", field="grid", progress=False, max_steps=2,
                                         **{"grid.resolutions": (8, 16)})
    targets = depth_targets(seq, poses=poses, progress=False)
    model = build_model(config, scene_box(targets, poses, seq.K), poses, seq.K, np.zeros((len(seq), 6, 6)))
    trainer = Trainer(model, RayBatcher(seq, targets, "cpu", config.seed), config, checkpoint_dir=tmp_path)
    trainer.train()
    path = tmp_path / "checkpoint.pt"
    before = path.read_bytes()
    trainer.train_step()
    trainer.step += 1
    monkeypatch.setattr(torch, "save", half_then(KeyboardInterrupt(), torch.save, path_arg=1))
    with pytest.raises(KeyboardInterrupt):
        trainer.save_checkpoint()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]
    assert read_checkpoint(path)["step"] == 2
