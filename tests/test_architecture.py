"""The architecture's rules, checked on the source: layers, the scale-out seam, private names,
global configuration, and the one registration engine with its options."""

from __future__ import annotations

import ast
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root

import rootshape_jax as rs

PKG = Path(rs.__file__).resolve().parent
MODULES = sorted(p for p in PKG.rglob("*.py"))
# Edges that may touch Dask or JAX's global configuration (docs/design.md §10, §13).
DASK_OK = {"_dask.py"}
# _devices.use_all_cores changes it only when the user calls it (the documented way to use
# every core from Python); a Dask worker matches its client's float width.
CONFIG_OK = {"_dask.py", "_devices.py"}


def _name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _module_imports(path: Path) -> list[tuple[str, list[str], bool]]:
    """(imported module, imported names, at module level) of every import in a file."""
    tree = ast.parse(path.read_text())
    package = _name(path) if path.name == "__init__.py" else _name(path).rsplit(".", 1)[0]
    top = set(id(n) for n in tree.body)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((mod, [a.name for a in node.names], id(node) in top))
        elif isinstance(node, ast.Import):
            for a in node.names:
                out.append((a.name, [], id(node) in top))
    return out


def _is_cli(path: Path) -> bool:
    return "_cli" in path.relative_to(PKG).parts[0]


def test_no_maths_or_statistics_module_imports_dask():
    for path in MODULES:
        if path.name in DASK_OK or _is_cli(path):
            continue
        for mod, _, _ in _module_imports(path):
            assert mod.split(".")[0] not in ("dask", "distributed"), f"{path.name} imports {mod}"
            assert mod != "rootshape_jax._dask" or path.name == "__init__.py", f"{path.name} imports _dask"


def test_module_level_imports_have_no_cycle():
    graph = {}
    for path in MODULES:
        me = _name(path)
        deps = set()
        for mod, names, top in _module_imports(path):
            if not top or not mod.startswith("rootshape_jax"):
                continue
            deps.add(mod)
            deps.update(f"{mod}.{n}" for n in names)
        graph[me] = {d for d in deps if d != me}
    names = set(graph)
    graph = {
        k: {d for d in v if d in names and not k.startswith(d + ".") and d != "rootshape_jax"} for k, v in graph.items()
    }

    state = {}

    def visit(n, stack):
        state[n] = 1
        for m in graph.get(n, ()):
            if state.get(m) == 1:
                raise AssertionError(f"import cycle: {' -> '.join(stack + [n, m])}")
            if m not in state:
                visit(m, stack + [n])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])


def test_no_module_imports_another_modules_underscore_names():
    for path in MODULES:
        for mod, names, _ in _module_imports(path):
            if not mod.startswith("rootshape_jax"):
                continue
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            # Importing a private *module* of a package (from . import _dask) is how packages
            # are built; importing a private *name* from another module is not.
            private = [n for n in private if not (PKG / (n + ".py")).exists() and not (PKG / n).is_dir()]
            assert not private, f"{path.relative_to(PKG)} imports {private} from {mod}"


def test_library_never_changes_jax_global_config():
    for path in MODULES:
        if path.name in CONFIG_OK or _is_cli(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                target = ast.unparse(node.func)
                assert target not in ("jax.config.update", "config.update"), (
                    f"{path.relative_to(PKG)}:{node.lineno} changes JAX's global config"
                )


def test_one_safe_sqrt_and_one_device_splitter():
    defs = {}
    for path in MODULES:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef):
                defs.setdefault(node.name.lstrip("_"), []).append(path.name)
    assert defs["safe_sqrt"] == ["_curves.py"]
    assert defs["split_over_devices"] == ["_devices.py"]


# --------------------------------------------------------------------------------------------
# Options and terms


def test_registration_options_validate_and_round_trip():
    o = rs.RegistrationOptions(max_iterations=3, rtol=1e-3, prune=False)
    assert int(o.max_iterations) == 3 and o.prune is False and o.assignment == "jax"
    for bad, match in [
        (dict(max_iterations=0), "max_iterations"),
        (dict(neighbourhood=1.5), "neighbourhood"),
        (dict(dp_batch_size=0), "dp_batch_size"),
        (dict(assignment="hungarian"), "assignment"),
        (dict(rtol=-1.0), "rtol"),
    ]:
        with pytest.raises(ValueError, match=match):
            rs.RegistrationOptions(**bad)
    # The mean's own settings are a named, documented value.
    m = rs.MEAN_REGISTRATION
    assert (int(m.max_iterations), float(m.rtol), m.dp_batch_size) == (5, 1e-6, 256)
    with pytest.raises(ValueError, match="unknown"):
        rs.register(*_pair(), max_iters=3)


def _pair():
    rng = np.random.default_rng(3)
    t = rs.batch([random_root(rng, n_laterals=2), random_root(rng, n_laterals=3)], n_points=24)
    return rs.unstack(t)


def test_options_value_equals_keyword_shorthand():
    a, b = _pair()
    r1 = rs.register(a, b, max_iterations=2, prune=False)
    r2 = rs.register(a, b, registration=rs.RegistrationOptions(max_iterations=2, prune=False))
    assert float(r1.energy) == float(r2.energy)
    with pytest.raises(ValueError, match="not both"):
        rs.register(a, b, registration=rs.RegistrationOptions(), prune=False)


def test_weights_are_one_field_per_term():
    assert [t.name for t in rs.TERMS] == ["main", "lateral", "position", "thickness"]
    w = rs.Weights(0.1, 2.0, 0.5)
    assert (float(w.main), float(w.lateral), float(w.position), float(w.thickness)) == (0.1, 2.0, 0.5, 0.0)
    assert float(rs.Weights(thickness=0.3)["thickness"]) == pytest.approx(0.3)
    with pytest.raises(TypeError, match="unknown term"):
        rs.Weights(bend=1.0)
    with pytest.raises(TypeError, match="given twice"):
        rs.Weights(0.1, main=0.2)
    with pytest.raises(ValueError, match="non-negative"):
        rs.Weights(main=-1.0)
    with pytest.raises(ValueError, match=r"Weights.thickness must be a finite non-negative scalar, got -1\.$"):
        rs.Weights(thickness=-1)  # the number, not Array(-1, dtype=int32, weak_type=True)


def test_preshape_terms_match_a_numpy_reference():
    rng = np.random.default_rng(0)
    t = rs.batch([random_root(rng, n_laterals=k) for k in (2, 3)], n_points=30, max_laterals=6)
    a, b = rs.unstack(rs.to_srvf(t))
    w = rs.Weights(0.3, 1.5, 0.7)
    terms = rs.register(a, b, weights=w, rotation=False).terms
    T = 30
    tw = np.full(T, 1 / (T - 1))
    tw[[0, -1]] /= 2
    reg = rs.register(a, b, weights=w, rotation=False).registered
    qa0, qb0 = np.asarray(a.q0), np.asarray(reg.q0)
    main = 0.3 * np.sum(np.sum((qa0 - qb0) ** 2, -1) * tw)
    lat = 1.5 * np.sum(np.sum((np.asarray(a.q) - np.asarray(reg.q)) ** 2, -1) * tw)
    both = np.asarray(a.mask) & np.asarray(reg.mask)
    pos = 0.7 * np.sum(np.where(both, (np.asarray(a.s) - np.asarray(reg.s)) ** 2, 0.0))
    np.testing.assert_allclose(
        [terms.main, terms.lateral, terms.position, terms.thickness], [main, lat, pos, 0.0], rtol=1e-10, atol=1e-14
    )
    assert float(terms.total) == pytest.approx(main + lat + pos, rel=1e-12)


def test_local_store_resumes_without_recomputing(tmp_path):
    rng = np.random.default_rng(5)
    t = rs.batch([random_root(rng, n_laterals=k) for k in (1, 2, 2, 3, 1)], n_points=20, normalise_scale=True)
    D0 = np.asarray(rs.pairwise_distances(t, chunk_size=2, progress=False))
    store = tmp_path / "store"
    D1, s1 = rs.pairwise_distances(t, chunk_size=2, progress=False, store=store, return_stats=True)
    assert np.array_equal(np.asarray(D1), D0)
    assert s1["blocks"] == s1["blocks_computed"] == 5 and s1["blocks_from_store"] == 0
    (store / "block_0000003.npz").unlink()  # as if interrupted before that block finished
    D2, s2 = rs.pairwise_distances(t, chunk_size=2, progress=False, store=store, return_stats=True)
    assert np.array_equal(np.asarray(D2), D0)
    assert (s2["blocks_computed"], s2["blocks_from_store"]) == (1, 4)
    with pytest.raises(rs.StoreMismatchError, match="holds another run"):
        rs.pairwise_distances(t, chunk_size=2, progress=False, store=store, weights=rs.Weights(main=0.5))
    assert jnp.allclose(D2, D2.T)
    # A store written before the metric changed (no metric_revision: session 22 and earlier)
    # is refused rather than mixed with today's distances.
    import json

    manifest = json.loads((store / "manifest.json").read_text())
    del manifest["metric_revision"]
    (store / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(rs.StoreMismatchError, match="metric_revision: stored None vs now"):
        rs.pairwise_distances(t, chunk_size=2, progress=False, store=store)


def test_use_all_cores_before_and_after_jax_starts():
    import subprocess
    import sys

    code = (
        "import warnings, rootshape_jax as rs, jax\n"
        "n = rs.use_all_cores(2)\n"
        "assert n == 2 and jax.local_device_count() == 2, jax.devices()\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    assert rs.use_all_cores(1) == 2\n"
        "assert any('already started' in str(x.message) for x in w)\n"
        "import rootshape_jax._devices as d\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr
