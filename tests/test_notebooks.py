"""Every notebook in notebooks/ runs top to bottom, headless, in its small mode.

The contract for a notebook (01_quickstart, 02_uncertainty, and any added later):
  * its first code cell is the parameter cell and reads PNERF_NOTEBOOK_SMALL ("1": a run of a
    minute or so on one CPU thread, e.g. the "test" preset with few steps);
  * it writes its files under out/<notebook name>/ relative to the working directory;
  * it is committed without outputs.
EXPECTED_OUTPUTS lists the files a notebook must write; a notebook not listed only has to run.
"""

from __future__ import annotations

from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
EXPECTED_OUTPUTS = {
    "01_quickstart": ["mesh.ply", "point_cloud.ply", "model.pt", "overview.png"],
    "02_uncertainty": ["point_cloud_sigma.ply", "depth_pdfs.png", "calibration.png"],
    "03_compare_tsdf": ["comparison.json", "comparison.md", "tsdf_mesh.ply"],
}


def code_cells(nb) -> list:
    return [cell for cell in nb.cells if cell.cell_type == "code"]


def execute(path: Path, cwd: Path):
    """Run a notebook in a kernel of this interpreter (sys.executable), whatever kernel specs are installed.

    With no kernel directories the spec manager only knows ipykernel's built-in "python3", which
    launches sys.executable, so a user- or system-wide "python3" spec for another Python cannot
    take over (and a fresh clone needs no `ipykernel install`).
    """
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    km = KernelManager(kernel_name="python3", kernel_spec_manager=KernelSpecManager(kernel_dirs=[]))
    try:
        NotebookClient(nb, km=km, timeout=600, resources={"metadata": {"path": str(cwd)}}).execute()
    finally:  # nbclient leaves a kernel it did not create running
        if km.has_kernel:
            km.shutdown_kernel(now=True)
    return nb


def test_there_are_notebooks():
    assert {p.stem for p in NOTEBOOKS} >= set(EXPECTED_OUTPUTS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_committed_clean_with_a_small_switch(path):
    nb = nbformat.read(path, as_version=4)
    cells = code_cells(nb)
    assert cells and "PNERF_NOTEBOOK_SMALL" in cells[0].source, "the first code cell must be the parameter cell"
    assert all(not c.outputs and c.execution_count is None for c in cells), "clear the outputs before committing"


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs_in_small_mode(path, tmp_path, monkeypatch):
    pytest.importorskip("nbclient")
    monkeypatch.setenv("PNERF_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")  # no display needed; the kernel inherits the environment
    nb = execute(path, tmp_path)
    cells = code_cells(nb)
    assert all(c.execution_count is not None for c in cells)
    assert not [o for c in cells for o in c.outputs if o.output_type == "error"]
    for name in EXPECTED_OUTPUTS.get(path.stem, []):
        file = tmp_path / "out" / path.stem / name
        assert file.is_file() and file.stat().st_size > 0, f"{path.name} did not write {file}"
