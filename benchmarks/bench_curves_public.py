"""Curves as users batch them (issue 21, item 5): the public batched call
`rootshape_jax.elastic_curve_distances` and ``jax.vmap(rootshape_jax.elastic_curve_distance)``
with Python defaults (one XLA device, nothing configured), against fdasrsf in the same run.

    python benchmarks/bench_curves_public.py [--batch 256] [--T 100]

Same curves and settings as `bench_curves.py` (random smooth curves, ``scale=True``, rotation
alternated with the DP, rtol 1e-4, up to 10 iterations). Each call is warmed up first (its
compile time is reported apart), then the best of 3 timed calls. fdasrsf (float64, its C DP)
runs one pair at a time on 20 of the pairs. Writes ``results/curves_public.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, write_json  # noqa: E402
from bench_curves import _curves, _per_pair_time  # noqa: E402


def _timed(fn, *args, repeats=3):
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return first, best


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--T", type=int, default=100)
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rootshape_jax as rs

    rng = np.random.default_rng(0)
    b1, b2 = _curves(rng, args.batch, args.T)
    c1, c2 = jnp.asarray(b1, jnp.float32), jnp.asarray(b2, jnp.float32)
    opts = dict(scale=True, n_samples=args.T)
    results = {"machine": machine(), "batch": args.batch, "T": args.T, "rows": []}

    def add(method, first, best, batch):
        row = {"method": method, "batch": batch, "first_call_s": first, "seconds": best, "pairs_per_s": batch / best}
        results["rows"].append(row)
        print(f"{method:<48} {row['pairs_per_s']:9.1f} pairs/s (first call {first:.1f} s)", flush=True)

    first, best = _timed(lambda a, b: rs.elastic_curve_distances(a, b, **opts).distance, c1, c2)
    add("rs.elastic_curve_distances (public, default)", first, best, args.batch)
    vmapped = jax.jit(jax.vmap(lambda a, b: rs.elastic_curve_distance(a, b, **opts).distance))
    first, best = _timed(vmapped, c1, c2)
    add("jax.jit(jax.vmap(rs.elastic_curve_distance))", first, best, args.batch)
    try:
        import fdasrsf.curve_functions as cf
    except ImportError:
        cf = None
        print("fdasrsf not installed (pip install 'rootshape_jax[bench]'): no peer timing.")
    if cf is not None:
        pa = [np.asarray(x, float).T.copy() for x in b1[:20]]
        pb = [np.asarray(x, float).T.copy() for x in b2[:20]]
        sec = _per_pair_time(lambda a, b: cf.elastic_distance_curve(a.copy(), b.copy()), pa, pb)
        add("fdasrsf elastic_distance_curve (one pair at a time)", sec, sec, 1)
        peer = results["rows"][-1]["pairs_per_s"]
        for row in results["rows"]:
            row["x_fdasrsf"] = row["pairs_per_s"] / peer
            print(f"{row['method']:<48} {row['x_fdasrsf']:6.1f}x fdasrsf")
    write_json("curves_public", results)
    return results


if __name__ == "__main__":
    main()
