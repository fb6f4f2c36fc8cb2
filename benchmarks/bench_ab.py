"""Interleaved A/B timing of two checkouts of the package on the same job (refactors must not
slow anything down): the 53-root distance matrix (as `bench_trees.py`) and the default Karcher
mean (fixed point, as `bench_stats.py`), alternating A and B so drifting machine load hits
both alike.

    python benchmarks/bench_ab.py --a /path/to/old/checkout --b . [--rounds 2] [--what matrix mean]

Each run is a fresh process (its own compile, reported apart from the timed call, which is the
second call of the same shapes). Results go to benchmarks/results/ab.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, write_json  # noqa: E402

CHILD = r"""
import json, sys, time
sys.path.insert(0, {bench!r})
from _common import setup_jax
jax = setup_jax({devices}, x64=False)
import numpy as np
import rootshape_jax as rs
from rootshape_jax.datasets import default_dataset

what = {what!r}
trees = rs.batch(default_dataset(), n_points=100, normalise_scale=True)
w = rs.Weights()
out = {{"package": rs.__file__}}
if what == "matrix":
    t0 = time.perf_counter()
    rs.pairwise_distances(jax.tree.map(lambda x: x[:2], trees), weights=w, chunk_size=32, progress=False)
    out["compile_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    D = np.asarray(jax.block_until_ready(rs.pairwise_distances(trees, weights=w, chunk_size=32, progress=False)))
    out["wall_s"] = time.perf_counter() - t0
    out["mean_distance"] = float(D[np.triu_indices(len(D), 1)].mean())
else:
    run = lambda: rs.karcher_mean(trees, weights=w, rtol=1e-4, max_steps=60, throw=False)
    t0 = time.perf_counter(); m = run(); jax.block_until_ready(m.energy)
    first = time.perf_counter() - t0
    t0 = time.perf_counter(); m = run(); jax.block_until_ready(m.energy)
    out["wall_s"] = time.perf_counter() - t0
    out["compile_s"] = max(first - out["wall_s"], 0.0)
    out["energy"] = float(m.energy); out["steps"] = int(m.steps)
print("RESULT " + json.dumps(out))
"""


def _run(checkout: Path, what: str, devices) -> dict:
    env = {**os.environ, "PYTHONPATH": str(checkout.resolve())}
    code = CHILD.format(bench=str(Path(__file__).parent.resolve()), what=what, devices=devices)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT ") :])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--a", required=True, help="checkout A (e.g. a worktree of the old commit)")
    p.add_argument("--b", default=".", help="checkout B (default: this one)")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--what", nargs="+", default=["matrix", "mean"])
    p.add_argument("--devices", type=int, default=None, help="XLA devices (default: every core)")
    args = p.parse_args(argv)
    rows = []
    for what in args.what:
        for r in range(args.rounds):
            for label, checkout in (("A", Path(args.a)), ("B", Path(args.b))):
                res = _run(checkout, what, args.devices)
                rows.append({"what": what, "round": r, "label": label, "checkout": str(checkout), **res})
                print(
                    f"{what} round {r} {label}: {res['wall_s']:.1f} s (compile {res['compile_s']:.1f} s) "
                    + " ".join(f"{k}={v}" for k, v in res.items() if k in ("energy", "steps", "mean_distance")),
                    flush=True,
                )
    summary = {}
    for what in args.what:
        a = [x["wall_s"] for x in rows if x["what"] == what and x["label"] == "A"]
        b = [x["wall_s"] for x in rows if x["what"] == what and x["label"] == "B"]
        summary[what] = {"A_s": a, "B_s": b, "B_over_A_median": sorted(b)[len(b) // 2] / sorted(a)[len(a) // 2]}
        print(f"{what}: A {a} s, B {b} s, B/A (medians) {summary[what]['B_over_A_median']:.3f}")
    write_json("ab", {"machine": machine(), "rows": rows, "summary": summary})


if __name__ == "__main__":
    main()
