"""Execute the notebooks top to bottom, headless, and save them with their outputs.

    python notebooks/run_notebooks.py [NOTEBOOK ...]     (default: every notebook here; `make notebooks`)

The notebooks are committed executed (full runs, not the test suite's small mode), so that a
reader who opens them on the web sees the figures and tables. Each runs with this folder's
parent as its working directory (it writes under out/<notebook name>/).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import nbformat

HERE = Path(__file__).resolve().parent


def execute(path: Path, cwd: Path, timeout: int = 3600):
    """Run a notebook in a kernel of this interpreter (sys.executable), whatever kernel specs are
    installed, and return it with its outputs.

    With no kernel directories the spec manager only knows ipykernel's built-in "python3", which
    launches sys.executable, so a user- or system-wide "python3" spec for another Python cannot
    take over (and a fresh clone needs no `ipykernel install`).
    """
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager
    from nbclient import NotebookClient

    nb = nbformat.validator.normalize(nbformat.read(path, as_version=4))[1]  # cell ids, as nbformat 4.5 wants
    km = KernelManager(kernel_name="python3", kernel_spec_manager=KernelSpecManager(kernel_dirs=[]))
    try:
        NotebookClient(nb, km=km, timeout=timeout, resources={"metadata": {"path": str(cwd)}}).execute()
    finally:  # nbclient leaves a kernel it did not create running
        if km.has_kernel:
            km.shutdown_kernel(now=True)
    return nb


def main(paths: list[str]) -> None:
    os.environ.pop("PNERF_NOTEBOOK_SMALL", None)  # full runs
    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend keeps the figures in the notebook
    for path in [Path(p) for p in paths] or sorted(HERE.glob("*.ipynb")):
        print(f"executing {path.name} ...", flush=True)
        nb = execute(path, HERE.parent)
        nbformat.write(nb, path)


if __name__ == "__main__":
    main(sys.argv[1:])
