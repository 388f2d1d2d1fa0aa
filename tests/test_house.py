"""The house's limits, checked so that they cannot drift back: every import goes down the layers and
no two modules import each other in a circle (import-linter's contracts in setup.cfg), and no module
of the package or of the benchmarks is over 400 lines."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 400


def test_imports_go_down_the_layers_and_form_no_cycle():
    lint = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert lint, "import-linter is not installed (pip install -e '.[test]')"
    done = subprocess.run([lint, "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "3 kept, 0 broken" in done.stdout


def test_no_module_is_over_400_lines():
    modules = sorted((ROOT / "open3d_pnerf").rglob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))
    assert len(modules) > 40
    long = {str(p.relative_to(ROOT)): n for p in modules if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_the_readme_cites_result_files_that_exist_and_every_result_file_is_cited():
    """Every file the README's results section names is in benchmarks/results/, and every file there is
    cited by the README or the documentation (an uncited file is an old result that belongs in git)."""
    import re

    results = ROOT / "benchmarks" / "results"
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## How well it works"):readme.index("## Limitations")]
    cited = set(re.findall(r"`([\w.-]+\.(?:md|json|png))`", section))
    assert cited, "the README's results section cites no result file"
    assert not [name for name in cited if not (results / name).is_file()], "cited but missing"
    text = readme + "".join(p.read_text() for p in (ROOT / "docs").rglob("*.md"))
    files = sorted(p.name for p in results.iterdir() if p.is_file())
    assert not [name for name in files if Path(name).stem not in text], "in benchmarks/results/ but cited nowhere"
