"""One rank of a data-parallel reconstruct() on the bundled sample, for tests/test_distributed.py.

    python tests/distributed_worker.py OUT_DIR '{"max_steps": 6, ...}'

Run alone it is a single process; run under torchrun (or with RANK, WORLD_SIZE, LOCAL_RANK,
MASTER_ADDR, MASTER_PORT set) it is one rank. The JSON holds overrides of the "test" preset.
Poses are the sample's ground truth; checkpoints go to OUT_DIR/checkpoints. Writes
OUT_DIR/rank{RANK}.pt (rank 0 when alone) with the trained field's state_dict, the training
stats, and the number of rays every render_rays call of training received (the real
function, wrapped to count); after Ctrl-C (TrainingInterrupted) only the step it stopped after.
"""

import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

import open3d_pnerf.model as model
from open3d_pnerf import ReconstructionConfig, load_sample, reconstruct
from open3d_pnerf.errors import TrainingInterrupted


def main(out: Path, overrides: dict) -> None:
    rays_per_call = []
    real_render_rays = model.render_rays

    def counting_render_rays(field, rays, *args, **kwargs):
        rays_per_call.append(len(rays))
        return real_render_rays(field, rays, *args, **kwargs)

    model.render_rays = counting_render_rays
    seq = load_sample()
    config = ReconstructionConfig.preset("test", **{"progress": False, **overrides})
    rank = int(os.environ.get("RANK", 0))
    try:
        recon = reconstruct(seq, config, poses=seq.gt_poses, covariances=np.zeros((len(seq), 6, 6)),
                            checkpoint_dir=out / "checkpoints")
    except TrainingInterrupted as stop:
        torch.save({"interrupted_after": stop.step}, out / f"rank{rank}.pt")
        return
    torch.save({"field": recon.field.state_dict(), "stats": recon.stats["training"], "rays_per_call": rays_per_call,
                "exported": recon.mesh is not None}, out / f"rank{rank}.pt")


if __name__ == "__main__":
    main(Path(sys.argv[1]), json.loads(sys.argv[2]) if len(sys.argv) > 2 else {})
