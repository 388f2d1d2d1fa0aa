"""Every notebook in notebooks/ runs top to bottom, headless, in its small mode; and is committed
executed (a full run), so that readers see its results without running it.

The contract for a notebook (01_quickstart, 02_uncertainty, and any added later):
  * its first code cell is the parameter cell and reads PNERF_NOTEBOOK_SMALL ("1": a run of a
    minute or so on one CPU thread, e.g. the "test" preset with few steps) and prints which run it is;
  * it writes its files under out/<notebook name>/ relative to the working directory;
  * it is committed with the outputs of a full run (`make notebooks` re-executes them).
EXPECTED_OUTPUTS lists the files a notebook must write; a notebook not listed only has to run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
EXPECTED_OUTPUTS = {
    "01_quickstart": ["mesh.ply", "point_cloud.ply", "model.pt", "overview.png"],
    "02_uncertainty": ["point_cloud_sigma.ply", "depth_pdfs.png", "calibration.png"],
    "03_compare_tsdf": ["comparison.json", "comparison.md", "tsdf_mesh.ply"],
}
sys.path.insert(0, str(NOTEBOOK_DIR))
from run_notebooks import execute  # noqa: E402  (notebooks/run_notebooks.py: `make notebooks`)


def code_cells(nb) -> list:
    return [cell for cell in nb.cells if cell.cell_type == "code"]


def test_there_are_notebooks():
    assert {p.stem for p in NOTEBOOKS} >= set(EXPECTED_OUTPUTS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_committed_executed_in_full_with_a_small_switch(path):
    nb = nbformat.read(path, as_version=4)
    cells = code_cells(nb)
    assert cells and "PNERF_NOTEBOOK_SMALL" in cells[0].source, "the first code cell must be the parameter cell"
    assert [c.execution_count for c in cells] == list(range(1, len(cells) + 1)), "run it top to bottom: make notebooks"
    assert not [o for c in cells for o in c.outputs if o.output_type == "error"]
    printed = "".join(o.get("text", "") for o in cells[0].outputs)
    assert "full run" in printed, "commit a full run (make notebooks), not the small test mode"
    assert any(o.output_type == "display_data" and "image/png" in o.data for c in cells for o in c.outputs)


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs_in_small_mode(path, tmp_path, monkeypatch):
    pytest.importorskip("nbclient")
    monkeypatch.setenv("PNERF_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")  # no display needed; the kernel inherits the environment
    nb = execute(path, tmp_path, timeout=600)
    cells = code_cells(nb)
    assert all(c.execution_count is not None for c in cells)
    assert not [o for c in cells for o in c.outputs if o.output_type == "error"]
    for name in EXPECTED_OUTPUTS.get(path.stem, []):
        file = tmp_path / "out" / path.stem / name
        assert file.is_file() and file.stat().st_size > 0, f"{path.name} did not write {file}"
