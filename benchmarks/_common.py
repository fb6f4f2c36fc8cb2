"""Shared benchmark utilities: device setup, timing, machine description, JSON output.

Benchmarks are scripts, not tests. Each one sets the number of XLA CPU devices *before* JAX
initialises (the library itself never touches global configuration), warms up, times compiled
calls with `block_until_ready`, and reports compile time separately.
"""

from __future__ import annotations

import inspect
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results"


# The paper's Section 6.5 timings (Matlab, i5-4460), quoted by bench_stats and
# paper_reproduction.
PAPER_STATS = {
    "karcher_mean_s": 9 * 3600 + 4 * 60,
    "pca_s": 1.1,
    "random_root_s": 0.22,
    "regression_fit_s": 0.01,
    "regressed_root_s": 0.001,
}


POPULATIONS = ("synthetic", "pea", "rootnav")


def population(name: str, shared: str | None = None) -> list:
    """The benchmark populations (issue 21): the bundled synthetic set, 53 CPlantBox pea
    taproots (the `sim` extra, ~20 laterals, not designed by us) and the real RootNav
    tracings in ``../shared/data`` (when present). Self-contained: bench_populations runs its
    source in a child process against any checkout of the package."""
    from pathlib import Path

    if name == "synthetic":
        from rootshape_jax.datasets import default_dataset

        return default_dataset()
    if name == "pea":
        from rootshape_jax.datasets import simulated_roots

        return simulated_roots("pea", 53, days=10, seed=0)
    if name == "rootnav":
        from rootshape_jax.io import read_rsml

        if shared is None:
            shared = str(Path(__file__).resolve().parents[2] / "shared" / "data")
        files = sorted(Path(shared, "rsml", "rootnav_osr").glob("*.rsml"))
        if not files:
            raise FileNotFoundError(f"no RootNav tracings under {shared}/rsml/rootnav_osr (../shared/data)")
        roots = []
        for f in files:
            roots += read_rsml(f)
        return roots
    raise ValueError(f"unknown population {name!r}; choose synthetic, pea or rootnav")


def run_child(child: str, spec: dict, package: Path | None = None, env: dict | None = None) -> dict:
    """Run the script `child` in a fresh Python process with the package checkout `package`
    (default: this one) and return the dict it prints on its ``RESULT `` line. The child gets
    `population`'s source where it says ``__POPULATION__`` and `spec` (JSON) as ``argv[1]``;
    `env` adds to (or, with None values, removes from) its environment."""
    env = {k: v for k, v in {**os.environ, **(env or {})}.items() if v is not None}
    # Run from the checkout itself: `python -c` puts the working directory first on sys.path,
    # ahead of PYTHONPATH and of the editable install.
    package = Path(package) if package is not None else Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = str(package)
    source = child.replace("__POPULATION__", inspect.getsource(population))
    proc = subprocess.run(
        [sys.executable, "-c", source, json.dumps(spec)], capture_output=True, text=True, env=env, cwd=package
    )
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"child failed ({spec}):\n{proc.stderr[-3000:]}")


def setup_jax(n_devices: int | None = None, *, x64: bool = False):
    """Import JAX with `n_devices` CPU devices (default: every core) and optional float64."""
    import jax

    n = n_devices or os.cpu_count() or 1
    jax.config.update("jax_num_cpu_devices", n)
    if x64:
        jax.config.update("jax_enable_x64", True)
    return jax


def machine() -> dict:
    import jax
    import numpy as np

    cpu = platform.processor() or ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "xla_devices": len(jax.devices()),
        "load_average_1min_at_start": load,
        "git": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def timed(fn, *args, repeats: int = 3, **kwargs):
    """(first-call seconds, best warm seconds, result): the first call includes compilation."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args, **kwargs))
        best = min(best, time.perf_counter() - t0)
    return first, best, out


def write_json(name: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2, default=float))
    return path
