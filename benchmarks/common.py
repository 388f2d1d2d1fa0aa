"""What the benchmarks share: the data they read (../shared/data, and the synthetic room rendered once
into a cache), the poses they train on, fresh processes for each run, result files, the machine and
commit they ran on, and an earlier revision of the library run beside today's."""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
OUT = REPO / "benchmarks" / "results"
CACHE = OUT / "cache"  # gitignored: the rendered synthetic room, tracked poses
PATHS = {"tum": SHARED / "tum_rgbd" / "rgbd_dataset_freiburg1_xyz",
         "7scenes": SHARED / "7scenes_redkitchen" / "frames_150-199",
         "7scenes_every10": SHARED / "7scenes_redkitchen" / "every10th_0-990",
         "fern": SHARED / "llff_fern" / "nerf_llff_data" / "fern"}
HOLDOUT_EVERY = {"fern": 8}  # the LLFF protocol; every 4th frame for the RGB-D datasets
IMAGE_SCALE = {"fern": 1.0}  # 504x378 (images_8, nerf-pytorch's Fern); 320x240 for the RGB-D datasets
TRAIN_VIEWS = {"synthetic": 10, "synthetic_all": 0, "tum": 0, "7scenes": 0, "tum_10": 10,
               "7scenes_10": 10}  # the scenes' training views, evenly spaced (0: every frame not held out)


def machine() -> str:
    """One line naming this machine: platform, cores, torch and Open3D versions."""
    import open3d
    import torch

    return (f"{platform.platform()}, {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} "
            f"threads), open3d {open3d.__version__}")


def commit() -> str:
    """The short hash of the checkout's HEAD (with '+' when the code has uncommitted changes; the
    result files themselves do not count)."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO).stdout
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                            ":(exclude)benchmarks/results"], capture_output=True, text=True, cwd=REPO).stdout.strip()
    return head.strip() + ("+" if dirty else "")


def require_shared(*names: str) -> None:
    """Exit with a message when a dataset of ../shared/data that a benchmark reads is absent."""
    missing = [n for n in names if n in PATHS and not PATHS[n].is_dir()]
    if missing:
        sys.exit(f"shared data not found for {missing} (expected under {SHARED})")


def run_in_processes(run_one, specs: list[dict], jobs: int, summary) -> list[dict]:
    """run_one(spec) for every spec, each in a fresh process (so peak RSS and timings are per run),
    `jobs` at once; prints summary(result) as each ends; returns the results in the order of `specs`."""
    with ProcessPoolExecutor(jobs, multiprocessing.get_context("spawn"), max_tasks_per_child=1) as pool:
        futures = [pool.submit(run_one, spec) for spec in specs]
        for future in as_completed(futures):
            print(summary(future.result()), flush=True)
    return [f.result() for f in futures]


def write_result(name: str, report: dict, text: str) -> None:
    """Write results/<name>.json (the report) and results/<name>.md (`text`), and print the text."""
    OUT.mkdir(exist_ok=True)
    (OUT / f"{name}.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    (OUT / f"{name}.md").write_text(text)
    print(text)


# -- data and poses ---------------------------------------------------------------------------------
def synthetic_room(frames: int = 48, size: tuple[int, int] = (640, 480)) -> str:
    """Render the synthetic room once into the cache (a Redwood folder: PNG colour, depth in mm) with its
    exact visible surface (reference.ply, points) and whole exact mesh (surface.ply), so that runs read
    frames instead of rendering them; the folder's name carries a hash of synthetic.py (a changed
    generator renders anew). Returns the dataset's name for :func:`load`."""
    import open3d as o3d

    from open3d_pnerf import synthetic
    from open3d_pnerf.data import write_sequence

    digest = hashlib.sha1(Path(synthetic.__file__).read_bytes()).hexdigest()[:8]
    name = f"synthetic_{frames}_{size[0]}_{digest}"
    folder = CACHE / name
    if not (folder / "surface.ply").is_file():  # written last: marks a complete folder
        data = synthetic.synthetic_sequence(frames, *size, seed=0)
        write_sequence(data.sequence, folder)
        o3d.io.write_point_cloud(str(folder / "reference.ply"), data.reference_points(stride=2))
        o3d.io.write_triangle_mesh(str(folder / "surface.ply"), synthetic.room_scene(seed=0).mesh)
    return name


def load(dataset: str):
    """(sequence, reference points or None) of a dataset: a key of PATHS, or a synthetic room's name."""
    import open3d as o3d

    import open3d_pnerf as pn

    if dataset.startswith("synthetic"):
        folder = CACHE / dataset
        return pn.load_sequence(folder), o3d.io.read_point_cloud(str(folder / "reference.ply"))
    return pn.load_sequence(PATHS[dataset]), None


def exact_surface(dataset: str):
    """The synthetic room's whole exact mesh (an o3d.geometry.TriangleMesh), None for a real dataset."""
    import open3d as o3d

    path = CACHE / dataset / "surface.ply"
    return o3d.io.read_triangle_mesh(str(path)) if dataset.startswith("synthetic") else None


def poses_for(dataset: str, seq, kind: str = "gt"):
    """(sequence, poses, covariances) to train on: the ground truth's poses with zero covariance
    ("gt"), or the tracker's as reconstruct() trains on them ("tracked": tracked once per dataset,
    cached, aligned to the ground truth's world frame so geometry metrics use the exact mesh's
    frame; where the tracker placed colour cameras, their poses, with each depth image moved into
    its colour camera); (sequence, None, None) for an image-only sequence (its SfM poses)."""
    if not seq.has_depth:
        return seq, None, None
    if kind == "gt":
        return seq, seq.gt_poses, np.zeros((len(seq), 6, 6))
    file = CACHE / f"tracked_{dataset}.npz"
    if not file.is_file():
        import open3d_pnerf as pn

        traj = pn.track(seq, progress=False)
        ate = pn.absolute_trajectory_error(traj.poses, seq.gt_poses)
        offsets = {} if traj.color_offsets is None else {"color_offsets": traj.color_offsets}
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(file, poses=ate["alignment"] @ traj.poses, covariances=traj.covariances, ate=ate["rmse"], **offsets)
    z = np.load(file)
    if "color_offsets" not in z:
        return seq, z["poses"], z["covariances"]
    from open3d_pnerf.data.derived import depth_in_color_cameras

    return depth_in_color_cameras(seq, z["color_offsets"]), z["poses"] @ z["color_offsets"], z["covariances"]


# -- an earlier revision beside today's -------------------------------------------------------------
class Revision:
    """The library at an earlier git revision, in a temporary worktree, run beside today's:
    ``with Revision("c330ed1") as old: old.python(["-m", "open3d_pnerf.cli", ...])`` (or
    ``old.run(SCRIPT, args)``, a script that prints ``RESULT <json>``)."""

    def __init__(self, rev: str):
        self.rev = rev
        self.tmp = Path(tempfile.mkdtemp(prefix="pnerf-revision-"))
        self.tree = self.tmp / "tree"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(self.tree), rev], check=True,
                       capture_output=True)

    def python(self, args: list[str], **kwargs) -> subprocess.CompletedProcess:
        """This interpreter with the revision's package first on its path, run with `args`."""
        env = {**os.environ, "PYTHONPATH": str(self.tree)}
        return subprocess.run([sys.executable, *args], cwd=self.tree, env=env, **kwargs)

    def run(self, script: str, args: dict) -> dict:
        """Python source `script` run at the revision: it reads `args` as JSON from ``sys.argv[1]`` and
        prints one line ``RESULT <json>``, which comes back as a dict."""
        done = self.python(["-c", script, json.dumps(args)], capture_output=True, text=True)
        line = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
        if done.returncode != 0 or not line:
            raise RuntimeError(f"revision {self.rev} failed: {done.stderr[-2000:]}")
        return json.loads(line[0][len("RESULT "):])

    def save(self, name: str, array: np.ndarray) -> str:
        """Store an array beside the worktree for a script to load; returns its path."""
        path = self.tmp / f"{name}.npy"
        np.save(path, array)
        return str(path)

    def close(self) -> None:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(self.tree)], capture_output=True)
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "Revision":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
