"""Curves as users batch them (issue 21, item 5): the public batched call
`rootshape_jax.elastic_curve_distances` and ``jax.vmap(rootshape_jax.elastic_curve_distance)``
with Python defaults (one XLA device, nothing configured), against fdasrsf in the same run.

    python benchmarks/bench_curves_public.py [--batch 256] [--T 100] [--rounds 5]

Same curves and settings as `bench_curves.py` (random smooth curves, ``scale=True``, rotation
alternated with the DP, rtol 1e-4, up to 10 iterations). Each call is warmed up first (its
compile time is reported apart). Then `--rounds` interleaved rounds, each timing the public
call (best of 3), the plain ``vmap`` (best of 3) and fdasrsf (float64, its C DP, one pair at
a time on 40 of the pairs), so that every ratio to fdasrsf compares runs seconds apart: on a
shared VM the speed of the host drifts by tens of percent within minutes, and single runs'
ratios ranged from 23× to 52×. The median ratio over rounds is the result; the
spread (min–max) is reported with it. Writes ``results/curves_public.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, write_json  # noqa: E402
from bench_curves import _curves, _per_pair_time  # noqa: E402


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _best(fn, *args, repeats=3):
    import jax

    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--T", type=int, default=100)
    p.add_argument("--rounds", type=_positive, default=5, help="interleaved timing rounds (median ratio reported)")
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import rootshape_jax as rs

    rng = np.random.default_rng(0)
    b1, b2 = _curves(rng, args.batch, args.T)
    c1, c2 = jnp.asarray(b1, jnp.float32), jnp.asarray(b2, jnp.float32)
    opts = dict(scale=True, n_samples=args.T)
    results = {"machine": machine(), "batch": args.batch, "T": args.T, "rounds": args.rounds, "rows": []}
    public = lambda a, b: rs.elastic_curve_distances(a, b, **opts).distance
    vmapped = jax.jit(jax.vmap(lambda a, b: rs.elastic_curve_distance(a, b, **opts).distance))
    calls = {
        "rs.elastic_curve_distances (public, default)": public,
        "jax.jit(jax.vmap(rs.elastic_curve_distance))": vmapped,
    }
    first = {name: _best(fn, c1, c2, repeats=1) for name, fn in calls.items()}  # compilation included
    try:
        import fdasrsf.curve_functions as cf
    except ImportError:
        cf = None
        print("fdasrsf not installed (pip install 'rootshape_jax[bench]'): no peer timing.")
    peer = "fdasrsf elastic_distance_curve (one pair at a time)"
    if cf is not None:
        pa = [np.asarray(x, float).T.copy() for x in b1[:40]]
        pb = [np.asarray(x, float).T.copy() for x in b2[:40]]
        calls[peer] = lambda: _per_pair_time(lambda a, b: cf.elastic_distance_curve(a.copy(), b.copy()), pa, pb)
    rates = {name: [] for name in calls}  # pairs per second, per round
    for r in range(args.rounds):
        for name, fn in calls.items():
            rates[name].append(1.0 / fn() if name == peer else args.batch / _best(fn, c1, c2))
        print(f"round {r + 1}: " + ", ".join(f"{v[-1]:.1f}" for v in rates.values()) + " pairs/s", flush=True)
    for name, v in rates.items():
        row = {
            "method": name,
            "batch": 1 if name == peer else args.batch,
            "first_call_s": first.get(name),
            "pairs_per_s_rounds": v,
            "pairs_per_s": float(np.median(v)),
        }
        if peer in rates:
            ratios = np.asarray(v) / np.asarray(rates[peer])  # each round against its own peer timing
            row.update(
                x_fdasrsf=float(np.median(ratios)), x_fdasrsf_min=float(ratios.min()), x_fdasrsf_max=float(ratios.max())
            )
        results["rows"].append(row)
        text = f"{name:<52} {row['pairs_per_s']:8.1f} pairs/s (median of {args.rounds})"
        if "x_fdasrsf" in row:
            text += f", {row['x_fdasrsf']:5.1f}x fdasrsf (rounds {row['x_fdasrsf_min']:.1f}–{row['x_fdasrsf_max']:.1f})"
        if first.get(name) is not None:
            text += f", first call {first[name]:.1f} s"
        print(text, flush=True)
    write_json("curves_public", results)
    return results


if __name__ == "__main__":
    main()
