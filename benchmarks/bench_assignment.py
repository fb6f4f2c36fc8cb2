"""Linear assignment: scipy via pure_callback vs the pure-JAX solver vs scipy directly.

Times one K×K solve and a vmapped batch of 64 for K = 10, 20, 40, 80 (float64, random normal
costs, seeded). Compile time is reported separately (lower + compile); run times are the median
over repeats of warmed-up, block_until_ready'd calls. Writes benchmarks/results/assignment.json
and prints a markdown table.

    .venv/bin/python benchmarks/bench_assignment.py
"""

import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.optimize  # noqa: E402

from rootshape_jax._assignment import linear_assignment  # noqa: E402

SIZES = (10, 20, 40, 80)
BATCH = 64
REPEATS = 7


def _median_time(fn, *, min_time=0.2):
    """Median seconds per call of ``fn()`` over REPEATS rounds of enough calls for ``min_time``."""
    fn()  # warm up
    t0 = time.perf_counter()
    fn()
    one = max(time.perf_counter() - t0, 1e-7)
    number = max(1, int(min_time / REPEATS / one))
    rounds = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        rounds.append((time.perf_counter() - t0) / number)
    return statistics.median(rounds)


def _compiled(fn, example):
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(example).compile()
    return compiled, time.perf_counter() - t0


def _cpu_name():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def main():
    rng = np.random.default_rng(0)
    rows = []
    for k in SIZES:
        one = rng.normal(size=(k, k))
        batch = rng.normal(size=(BATCH, k, k))
        one_j, batch_j = jnp.asarray(one), jnp.asarray(batch)
        row = {"K": k}

        row["scipy_single_s"] = _median_time(lambda: scipy.optimize.linear_sum_assignment(one))
        row["scipy_batch_s"] = _median_time(lambda: [scipy.optimize.linear_sum_assignment(c) for c in batch])
        expected = np.stack([scipy.optimize.linear_sum_assignment(c)[1] for c in batch])

        for method in ("callback", "jax"):
            single, t_single = _compiled(lambda c: linear_assignment(c, method=method), one_j)
            vmapped, t_batch = _compiled(jax.vmap(lambda c: linear_assignment(c, method=method)), batch_j)
            # Correctness guard: a benchmark of a wrong answer is worthless.
            np.testing.assert_array_equal(np.asarray(vmapped(batch_j)), expected)
            row[f"{method}_compile_single_s"] = t_single
            row[f"{method}_compile_batch_s"] = t_batch
            row[f"{method}_single_s"] = _median_time(lambda: jax.block_until_ready(single(one_j)))
            row[f"{method}_batch_s"] = _median_time(lambda: jax.block_until_ready(vmapped(batch_j)))
        rows.append(row)
        print(f"K={k} done", flush=True)

    machine = {
        "cpu": _cpu_name(),
        "logical_cpus": os.cpu_count(),
        "jax_devices": [str(d) for d in jax.devices()],
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "dtype": "float64",
        "batch": BATCH,
        "note": "shared 2-core machine, other jobs running; medians of warmed-up calls",
    }
    out = Path(__file__).parent / "results" / "assignment.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))

    us = 1e6
    print()
    print(
        f"Machine: {machine['cpu']}, {machine['logical_cpus']} logical CPUs, "
        f"jax {machine['jax']}, scipy {machine['scipy']}, float64."
    )
    print()
    print(
        "| K | scipy direct | callback | jax | callback / scipy | jax / scipy "
        f"| scipy ×{BATCH} loop | callback vmap ×{BATCH} | jax vmap ×{BATCH} "
        "| jax vmap / callback vmap | compile callback / jax (single, batch) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['K']} | {r['scipy_single_s'] * us:.1f} µs "
            f"| {r['callback_single_s'] * us:.1f} µs "
            f"| {r['jax_single_s'] * us:.1f} µs "
            f"| {r['callback_single_s'] / r['scipy_single_s']:.1f}× "
            f"| {r['jax_single_s'] / r['scipy_single_s']:.1f}× "
            f"| {r['scipy_batch_s'] * 1e3:.2f} ms | {r['callback_batch_s'] * 1e3:.2f} ms "
            f"| {r['jax_batch_s'] * 1e3:.2f} ms "
            f"| {r['jax_batch_s'] / r['callback_batch_s']:.1f}× "
            f"| {r['callback_compile_single_s']:.2f} / {r['jax_compile_single_s']:.2f} s, "
            f"{r['callback_compile_batch_s']:.2f} / {r['jax_compile_batch_s']:.2f} s |"
        )
    print(f"\nWrote {out}")


if __name__ == "__main__":
    main()
