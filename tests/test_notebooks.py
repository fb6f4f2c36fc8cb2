"""The notebooks are stored executed, with their figures, and execute from top to bottom.

Stored outputs let a reader see the figures when browsing the repository; `notebooks/execute.py`
regenerates them. The slow test executes a copy of every notebook with nbclient (nothing is
written back). Its kernel is this interpreter: a kernelspec pointing at `sys.executable` is
written to a temporary Jupyter path, so the test works in any fresh virtualenv
(`pip install -e .[test]`), activated or not.
"""

from __future__ import annotations

import base64
import json
import re
import sys
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
KERNEL = "rootshape-test-kernel"
STEMS = (
    "01_quick_tour",
    "02_gradient_mean_fitting",
    "03_classification_clustering",
    "04_synthesis",
    "05_learning_weights",
    "06_real_data",
)
# Stored figures stay small: the repository must not grow by megabytes per notebook run.
MAX_PNG_BYTES = 150_000
MAX_NOTEBOOK_BYTES = 1_000_000


def _code_cells(path):
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    return [c for c in nb.cells if c.cell_type == "code"], nb


def _text(cell) -> str:
    out = []
    for o in cell.outputs:
        if o.output_type == "stream":
            out.append(o.text)
        elif "data" in o and "text/plain" in o.data:
            out.append(o.data["text/plain"])
    return "".join(out)


def test_every_notebook_is_present():
    assert sorted(p.stem for p in NOTEBOOKS) == sorted(STEMS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_stored_executed_with_small_figures(path):
    cells, _ = _code_cells(path)
    # Executed top to bottom in one kernel, without errors.
    assert [c.execution_count for c in cells] == list(range(1, len(cells) + 1)), (
        f"{path.name}: run notebooks/execute.py"
    )
    assert not [o for c in cells for o in c.outputs if o.output_type == "error"]
    pngs = [o.data["image/png"] for c in cells for o in c.outputs if "data" in o and "image/png" in o.data]
    assert pngs, f"{path.name}: no stored figure"
    for png in pngs:
        raw = base64.b64decode(png)
        assert raw[:8] == b"\x89PNG\r\n\x1a\n" and len(raw) <= MAX_PNG_BYTES, (path.name, len(raw))
    assert path.stat().st_size <= MAX_NOTEBOOK_BYTES
    # Every core by default (blocks on worker threads): no notebook splits calls over XLA
    # devices, which was 1.5 times slower on the pea matrix, nor crops figures by hand.
    source = "\n".join(c.source for c in cells)
    assert "use_all_cores" not in source and "jax_num_cpu_devices" not in source
    assert "bbox_inches" not in source  # strip legends lie inside the layout


def test_quick_tour_claim_matches_its_output():
    """Notebook 01 states no distances in its text; the conclusion it prints follows from the
    numbers it prints (issue 17: the old text claimed two blocks its matrix did not show)."""
    cells, nb = _code_cells(NOTEBOOK_DIR / "01_quick_tour.ipynb")
    prose = " ".join(c.source for c in nb.cells if c.cell_type == "markdown")
    assert "two blocks" not in prose and not re.search(r"\b0\.\d\d\b", prose)
    out = next(_text(c) for c in cells if "mean distance within control" in _text(c))
    w1, w2, b = map(
        float, re.search(r"within control ([\d.]+), within drought ([\d.]+), control-drought ([\d.]+)", out).groups()
    )
    farther = "NOT farther apart" not in out
    assert farther == (b > max(w1, w2))
    lo, hi = map(
        float, re.search(r"closest control-drought pair ([\d.]+), farthest same-condition pair ([\d.]+)", out).groups()
    )
    assert ("single entries overlap" in out) == (lo < hi)


def test_real_data_notebook_says_which_data_it_ran_on():
    cells, nb = _code_cells(NOTEBOOK_DIR / "06_real_data.ipynb")
    prose = " ".join(c.source for c in nb.cells if c.cell_type == "markdown")
    assert "../shared/data" in prose and "stand-in" in prose
    text = "".join(_text(c) for c in cells)
    assert ("REAL DATA:" in text) != ("STAND-IN DATA" in text)
    assert "PERMANOVA by" in text


@pytest.fixture(scope="module")
def kernel_name(tmp_path_factory, request):
    spec_dir = tmp_path_factory.mktemp("jupyter") / "kernels" / KERNEL
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "rootshape test kernel",
        "language": "python",
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    mp = pytest.MonkeyPatch()
    mp.setenv("JUPYTER_PATH", str(spec_dir.parents[1]))
    # Headless plotting in the kernel, whatever the user's matplotlib configuration says.
    mp.setenv("MPLBACKEND", "Agg")
    yield KERNEL
    mp.undo()


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, kernel_name, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(path, as_version=4)
    # The notebook's own folder as working directory (as in Jupyter): 06 finds ../shared/data.
    client = nbclient.NotebookClient(
        nb, kernel_name=kernel_name, timeout=900, resources={"metadata": {"path": str(NOTEBOOK_DIR)}}
    )
    client.execute()  # raises CellExecutionError (with the cell and traceback) on failure
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors


def test_readme_and_extra_say_how_to_open_the_notebooks():
    import tomllib

    root = NOTEBOOK_DIR.parent
    readme = (root / "README.md").read_text()
    assert "pip install -e '.[notebooks]'" in readme and "jupyter lab notebooks/" in readme
    assert all(f"notebooks/{stem}.ipynb" in readme for stem in STEMS)
    assert "synthetic" in readme.split("## In Python")[0]  # the bundled 53, said with the two commands
    assert readme.index("make demo") < readme.index("## In Python")
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(dep.startswith("jupyterlab") for dep in extras["notebooks"])
