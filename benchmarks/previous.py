"""The library as it was at an earlier git revision, run beside today's in one benchmark.

    with PreviousRelease("e7fdb54") as previous:
        result = previous.run(SCRIPT, {"data": ..., "threads": 2})

SCRIPT is Python source run in a subprocess of this interpreter with a temporary worktree of that
revision first on its path; it reads its arguments as JSON from ``sys.argv[1]`` and prints one
line ``RESULT <json>``, which run() returns as a dict. ``previous.save(name, array)`` stores an
array beside the worktree for the script to load (returns the path).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


class PreviousRelease:
    def __init__(self, rev: str):
        self.rev = rev
        self.tmp = Path(tempfile.mkdtemp(prefix="pnerf-previous-"))
        self.tree = self.tmp / "tree"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(self.tree), rev], check=True,
                       capture_output=True)

    def save(self, name: str, array: np.ndarray) -> str:
        path = self.tmp / f"{name}.npy"
        np.save(path, array)
        return str(path)

    def run(self, script: str, args: dict) -> dict:
        env = {**os.environ, "PYTHONPATH": str(self.tree)}
        done = subprocess.run([sys.executable, "-c", script, json.dumps(args)], cwd=self.tree, env=env,
                              capture_output=True, text=True)
        line = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
        if done.returncode != 0 or not line:
            raise RuntimeError(f"revision {self.rev} failed: {done.stderr[-2000:]}")
        return json.loads(line[0][len("RESULT "):])

    def close(self) -> None:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(self.tree)], capture_output=True)
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "PreviousRelease":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
