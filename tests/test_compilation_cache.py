"""The registration engine's programs hold no host callbacks, so JAX's persistent compilation
cache keeps them: a second process (a user's next script, the next test module) reads them
from disk instead of compiling them again (~5 s each)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = r"""
import json, logging, sys
import jax

jax.config.update("jax_explain_cache_misses", True)
jax.config.update("jax_log_compiles", True)
messages = []


class Keep(logging.Handler):
    def emit(self, record):
        messages.append(record.getMessage())


logging.getLogger("jax._src.compiler").addHandler(Keep(level=logging.DEBUG))
logging.getLogger("jax._src.compiler").setLevel(logging.DEBUG)

import numpy as np
import pytest
import rootshape_jax as rs

sys.path.insert(0, sys.argv[1])
from helpers import random_root

rng = np.random.default_rng(0)
trees = rs.batch([random_root(rng, n_laterals=3) for _ in range(3)], n_points=16)
rs.pairwise_distances(trees, progress=False)
rs.karcher_mean(trees, progress=False)
rs.distance(rs.unstack(trees)[0], rs.unstack(trees)[1])


def named(text):
    return sorted({m.split("'")[1] for m in messages if text in m})


def count(text):
    names = [m.split("'")[1] for m in messages if text in m]
    return {n: names.count(n) for n in names}


print(json.dumps({"callbacks": named("uses host callbacks"), "hits": named("cache hit"), "misses": count("CACHE MISS")}))
"""


def _run(cache: Path) -> dict:
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(Path(__file__).parent)],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_engine_programs_are_kept_by_the_persistent_compilation_cache(tmp_path):
    first = _run(tmp_path)
    # Before, the scipy assignment callback and eqx.error_if checks were in these programs.
    assert first["callbacks"] == [], first
    engine = {"jit_chunk_energies", "jit__full_registration"}
    assert engine <= set(first["misses"]), first
    # The mean's full registrations and its fixed-point steps (rotation off, a traced option)
    # share one engine program: compiled once, not once per kind of step.
    assert first["misses"]["jit__full_registration"] == 1, first
    assert "jit__full_registration" not in first["hits"], first  # not compiled again and read back
    assert "jit_fp_register" not in first["misses"], first
    second = _run(tmp_path)
    assert engine <= set(second["hits"]), second
    assert not engine & set(second["misses"]), second


@pytest.mark.slow
def test_cli_keeps_compiled_programs_between_runs(tmp_path):
    """Run as the program, the CLI turns the cache on in $XDG_CACHE_HOME/rootshape_jax/xla:
    the second run reads the engine's program instead of compiling it."""
    from rootshape_jax.datasets import synthetic_roots
    from rootshape_jax.io import write_rsml

    write_rsml(synthetic_roots(3, condition="control", seed=1), tmp_path / "roots.rsml")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    # JAX's 1 s threshold would skip a program compiled faster on a fast machine.
    env.update(
        XDG_CACHE_HOME=str(tmp_path / "cache"),
        ROOTSHAPE_COMPILATION_CACHE="1",
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
    )
    folder = tmp_path / "cache" / "rootshape_jax" / "xla"

    def distances(out):
        cmd = [sys.executable, "-m", "rootshape_jax", "distances", str(tmp_path / "roots.rsml")]
        proc = subprocess.run(
            [*cmd, "--points", "12", "--quiet", "--out", str(tmp_path / out)],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        return np.loadtxt(tmp_path / out / "distances.csv", delimiter=",", skiprows=1, usecols=range(1, 4))

    first = distances("one")
    entries = {p: p.stat().st_mtime_ns for p in folder.glob("jit_chunk_energies-*-cache")}
    assert entries, sorted(p.name for p in folder.iterdir())
    again = distances("two")
    np.testing.assert_array_equal(first, again)
    # Read, not compiled and written again: the same entries, untouched.
    assert {p: p.stat().st_mtime_ns for p in folder.glob("jit_chunk_energies-*-cache")} == entries
