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

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
plotly = pytest.importorskip("plotly")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
EXPECTED_OUTPUTS = {
    "01_quickstart": ["mesh.ply", "point_cloud.ply", "model.pt", "overview.png"],
    "02_uncertainty": ["point_cloud_sigma.ply", "depth_pdfs.png", "calibration.png"],
    "03_compare_tsdf": ["comparison.json", "comparison.md", "tsdf_mesh.ply"],
}
sys.path.insert(0, str(NOTEBOOK_DIR))
from run_notebooks import execute  # noqa: E402  (notebooks/run_notebooks.py: `make notebooks`)

pytestmark = pytest.mark.slow  # every test here executes whole notebooks


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


def plotly_outputs(nb) -> list:
    """The outputs of a notebook that carry a plotly figure."""
    return [o for c in code_cells(nb) for o in c.outputs
            if "application/vnd.plotly.v1+json" in o.get("data", {}) or "Plotly.newPlot" in o.get("data", {}).get(
                "text/html", "")]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_interactive_views_carry_plotly_js_for_readers_of_the_html(path):
    """plotly's JupyterLab mimetype alone is blank once the notebook is exported to HTML (as nbviewer and
    GitHub show it): a view must come as HTML that brings plotly.js, from plotly's CDN, which keeps the
    committed notebook small (open3d_pnerf.viz.notebook_view(..., plotlyjs="cdn"))."""
    for output in plotly_outputs(nbformat.read(path, as_version=4)):
        html = output.get("data", {}).get("text/html", "")
        assert "Plotly.newPlot" in html and CDN_SCRIPT.search(html), "the view must load plotly.js"
        assert len(html) < 1_000_000, "plotly.js inline makes the committed notebook megabytes larger"


CDN_SCRIPT = re.compile(r'<script[^>]+src="(https://cdn\.plot\.ly/plotly-[\d.]+\.min\.js)"')


CHROMIUM = next((c for c in ("chromium", "chromium-browser", "google-chrome") if shutil.which(c)), None)


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium to open the exported HTML in")
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_interactive_views_draw_in_a_browser_from_the_exported_html(path, tmp_path):
    """The committed notebook exported by nbconvert and opened in headless Chromium: every plotly view
    draws (plotly marks a drawn figure's div js-plotly-plot and gives it its WebGL canvas). There is no
    network here: the CDN's plotly.js is served by the installed plotly package's own copy."""
    nb = nbformat.read(path, as_version=4)
    expected = len(plotly_outputs(nb))
    if not expected:
        pytest.skip(f"{path.name} has no interactive view")
    from nbconvert import HTMLExporter

    page = tmp_path / f"{path.stem}.html"
    # the same plotly.js the CDN serves, from the installed package (a file:// page cannot pass the CDN
    # tag's cross-origin integrity check, so the tag is rewritten to a plain one)
    local = (Path(plotly.__file__).parent / "package_data" / "plotly.min.js").as_uri()
    page.write_text(CDN_SCRIPT.sub(f'<script src="{local}"', HTMLExporter().from_notebook_node(nb)[0]),
                    encoding="utf-8")
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000"]
    dom = subprocess.run([CHROMIUM, *flags, "--dump-dom", page.as_uri()], capture_output=True, text=True,
                         timeout=120).stdout
    assert dom.count("js-plotly-plot") >= expected and "<canvas" in dom, "a plotly view stayed blank"
