"""benchmarks/paper_reproduction.py runs end to end on its tiny configuration (issue 7).

Run as a user runs it, in a subprocess (the script sets JAX's device count before JAX starts,
which this test process cannot do). Checks the report, not the numbers: the markdown exists,
every figure it references exists, the shrinkage table has one row per geodesic, and the
JSON has the accuracies of every method. The cache is tested in process: a result is reused
only under the same key (configuration, inputs and library source).
"""

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).parent.parent / "benchmarks" / "paper_reproduction.py"
METHODS = ("ours", "qed", "fc_srvf", "ted", "tmd")


def _run(out: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), "--tiny", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=900,
    )


def _table_rows(text: str, heading: str) -> list[list[str]]:
    """Body rows of the first markdown table after `heading`."""
    after = text.split(heading, 1)[1]
    block = []
    for ln in after.splitlines():
        if ln.startswith("|"):
            block.append(ln)
        elif block:
            break
    assert len(block) >= 2, f"no table after {heading!r}"
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in block[2:]]


@pytest.mark.slow
def test_tiny_reproduction(tmp_path):
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    md = tmp_path / "paper_reproduction.md"
    assert md.is_file()
    text = md.read_text()
    for section in ("## (a)", "## (b)", "## (c)", "## (d)", "## (e)", "## (f)", "## (g)", "## (h)"):
        assert section in text, section

    # Every referenced figure exists and is a non-empty PNG.
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(figures) >= 10
    result = json.loads((tmp_path / "paper_reproduction.json").read_text())
    assert sorted(figures) == sorted(result["figures"])  # every figure saved is referenced (and parsed)
    for rel in figures:
        path = tmp_path / rel
        assert path.is_file(), rel
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel

    # One shrinkage row per geodesic: three methods per pair of (a), four λ of (b).
    n_pairs = result["config"]["n_pairs"]
    expected = 3 * n_pairs + 4
    rows = _table_rows(text, "## Shrinkage of every geodesic")
    assert len(rows) == expected
    ids = [r[0] for r in rows]
    assert len(set(ids)) == expected
    assert sorted(ids) == sorted(g["id"] for g in result["geodesics"])
    for p in range(1, n_pairs + 1):
        for m in ("ours", "qed", "fc_srvf"):
            assert f"a{p}-{m}" in ids
    geodesic_strips = [f for f in figures if "geodesic_pair" in f]
    assert len(geodesic_strips) == n_pairs
    for g in result["geodesics"]:
        assert g["steps"] == result["config"]["n_steps"]
        assert 0 < g["min_ratio"] < 10

    # Classification of both labelled sets by every method, accuracies in [0, 1].
    for tag in ("conditions", "species"):
        for m in METHODS:
            acc = result["classification"][tag][m]
            for rule in ("nearest_neighbour", "nearest_mean", "cluster_purity"):
                assert 0.0 <= acc[rule] <= 1.0


def _script_module():
    spec = importlib.util.spec_from_file_location("paper_reproduction", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_cache_reuses_only_the_same_key(tmp_path):
    pr = _script_module()
    cache = pr.Cache(tmp_path, enabled=True, base={"version": 1, "library": "abc"})
    key = {"roots": "r1", "T": 20}
    assert cache.load("distances", key) is None
    cache.save("distances", key, {"D": np.arange(4.0)})
    hit = cache.load("distances", key)
    np.testing.assert_array_equal(hit["D"], np.arange(4.0))
    assert cache.hits == ["distances"]
    assert cache.load("distances", {"roots": "r1", "T": 50}) is None  # other configuration
    assert cache.load("distances", {"roots": "r2", "T": 20}) is None  # other inputs
    other_library = pr.Cache(tmp_path, enabled=True, base={"version": 1, "library": "xyz"})
    assert other_library.load("distances", key) is None  # library source changed
    disabled = pr.Cache(tmp_path, enabled=False, base={"version": 1, "library": "abc"})
    assert disabled.load("distances", key) is None  # --no-cache


def test_fingerprints_see_every_coordinate():
    import dataclasses

    from rootshape_jax.datasets import synthetic_roots

    pr = _script_module()
    roots = synthetic_roots(3, seed=0)
    f = pr.fingerprint_roots(roots)
    assert pr.fingerprint_roots(synthetic_roots(3, seed=0)) == f
    lat = roots[2].laterals[-1].copy()
    lat[-1, 0] += 1e-9
    moved = roots[:2] + [dataclasses.replace(roots[2], laterals=roots[2].laterals[:-1] + (lat,))]
    assert pr.fingerprint_roots(moved) != f
    assert pr.fingerprint_roots(pr.limit_laterals(roots, 1)) != f
