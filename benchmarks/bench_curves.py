"""Curve benchmark (issue 2): DP warp and full elastic curve distance against fdasrsf.

    python benchmarks/bench_curves.py [--quick] [--devices N] [--x64]

For T = 50, 100, 200: pairs per second of the DP warp (`dp_warp`, `dp_warp_batch`) and of the
elastic curve distance (rotation + DP, alternated; `elastic_curve_distance` batched with
`device_vmap`), for a single pair and for batches of 64, 256 and 1024 pairs; compile time is
reported separately (lower + compile), and each batched function is called again on new data
of the same shape to check that it does not recompile. fdasrsf (`optimum_reparam_curve`,
`elastic_distance_curve`, its C DP) is timed in the same run, on the same curves, one pair at
a time as it is used. Results go to benchmarks/results/bench_curves.json and a markdown table
to benchmarks/results/bench_curves.md (for BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import RESULTS, machine, setup_jax, write_json  # noqa: E402


def _curves(rng, n_pairs, T):
    """Random smooth open planar curves, unit length and centred (fdasrsf's conventions)."""
    import numpy as np

    t = np.linspace(0, 1, T)
    out = np.empty((2, n_pairs, T, 2))
    for i in range(2):
        for p in range(n_pairs):
            c = np.stack([t, np.zeros(T)], 1)
            for k in range(1, 4):
                c = c + rng.normal(size=2)[None] * 0.25 * np.sin(np.pi * k * t)[:, None] / k
            if c[1, 0] < c[0, 0]:  # fdasrsf's resamplecurve would reverse it
                c[:, 0] = -c[:, 0]
            c = c / np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))
            out[i, p] = c - c.mean(axis=0)
    return out[0], out[1]


def _compile(fn, *args):
    """(compile seconds, compiled executable) for ``jax.jit(fn)`` at these arguments."""
    import jax

    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return time.perf_counter() - t0, jitted, compiled


def _best_time(compiled, *args, repeats=3):
    import jax

    jax.block_until_ready(compiled(*args))  # warm
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def _per_pair_time(fn, firsts, seconds):
    """Seconds per pair of a one-pair-at-a-time function, averaged over the given pairs."""
    import jax

    # Pre-sliced inputs: eager indexing of a device array inside the loop would be timed too.
    firsts, seconds = list(firsts), list(seconds)
    jax.block_until_ready((firsts, seconds))
    jax.block_until_ready(fn(firsts[0], seconds[0]))  # warm
    t0 = time.perf_counter()
    for a, b in zip(firsts, seconds):
        jax.block_until_ready(fn(a, b))
    return (time.perf_counter() - t0) / len(firsts)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="T = 100, batch 64 only (smoke run)")
    p.add_argument("--devices", type=int, default=None, help="XLA CPU devices (default: all cores)")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    p.add_argument("--neighbourhood", type=int, default=7)
    args = p.parse_args(argv)
    jax = setup_jax(args.devices, x64=args.x64)
    import jax.numpy as jnp
    import numpy as np

    from rootshape_jax._curves import srvf
    from rootshape_jax._devices import device_vmap
    from rootshape_jax._elastic import elastic_curve_distance
    from rootshape_jax._warp import dp_warp, dp_warp_batch

    try:
        import fdasrsf.curve_functions as cf
    except ImportError:  # fdasrsf is in the 'bench' extra
        cf = None
        print("fdasrsf not installed (pip install 'rootshape_jax[bench]'): no peer timings.")

    n = args.neighbourhood
    dtype = jnp.float64 if args.x64 else jnp.float32
    Ts = (100,) if args.quick else (50, 100, 200)
    batches = (64,) if args.quick else (64, 256, 1024)
    n_single = 10 if args.quick else 20
    results = {
        "machine": machine(),
        "dtype": "float64" if args.x64 else "float32",
        "neighbourhood": n,
        "note": "pairs/s; compile = lower+compile of the jitted function; fdasrsf one pair at a "
        "time (float64, its C DP), same curves. Elastic distance: scale=True (unit length), "
        "rotation alternated with the DP, rtol=1e-4, max_iterations=10.",
        "rows": [],
    }
    rng = np.random.default_rng(0)
    rows = results["rows"]

    def add(**row):
        rows.append(row)
        extra = f", compile {row['compile_s']:.1f} s" if row.get("compile_s") is not None else ""
        print(
            f"T={row['T']:4d} {row['what']:<22} {row['method']:<28} batch {row['batch']:5d}: "
            f"{row['pairs_per_s']:10.1f} pairs/s{extra}",
            flush=True,
        )

    for T in Ts:
        big = max(batches)
        b1, b2 = _curves(rng, 2 * big, T)  # two independent batches: checks no recompilation
        c1, c2 = jnp.asarray(b1, dtype), jnp.asarray(b2, dtype)
        q1 = jax.vmap(srvf)(c1)
        q2 = jax.vmap(srvf)(c2)

        # --- DP warp ---------------------------------------------------------------------
        single = functools.partial(dp_warp, neighbourhood=n)
        comp_s, _, exe = _compile(single, q1[0], q2[0])
        sec = _per_pair_time(exe, q1[:n_single], q2[:n_single])
        add(T=T, what="dp_warp", method="rootshape_jax single", batch=1, pairs_per_s=1 / sec, compile_s=comp_s)
        for B in batches:
            fn = functools.partial(dp_warp_batch, neighbourhood=n)
            comp_s, jitted, exe = _compile(fn, q1[:B], q2[:B])
            sec = _best_time(exe, q1[:B], q2[:B])
            jitted(q1[:B], q2[:B]).block_until_ready()
            size = jitted._cache_size()
            jitted(q1[big : big + B], q2[big : big + B]).block_until_ready()  # new data, same shape
            add(
                T=T,
                what="dp_warp",
                method=f"rootshape_jax batched ({len(jax.devices())} dev)",
                batch=B,
                pairs_per_s=B / sec,
                compile_s=comp_s,
                recompiled_on_new_data=jitted._cache_size() != size,
            )
        if cf is not None:

            def fd_srvf(x):
                return np.ascontiguousarray(cf.curve_to_q(np.asarray(x, float).T)[0])

            qa = [fd_srvf(x) for x in b1[:n_single]]
            qb = [fd_srvf(x) for x in b2[:n_single]]
            sec = _per_pair_time(lambda a, b: cf.optimum_reparam_curve(a, b), qa, qb)
            add(
                T=T,
                what="dp_warp",
                method="fdasrsf optimum_reparam_curve",
                batch=1,
                pairs_per_s=1 / sec,
                compile_s=None,
            )

        # --- elastic curve distance ------------------------------------------------------
        elastic = functools.partial(elastic_curve_distance, scale=True, n_samples=T, neighbourhood=n)
        comp_s, _, exe = _compile(elastic, c1[0], c2[0])
        sec = _per_pair_time(exe, c1[:n_single], c2[:n_single])
        add(
            T=T,
            what="elastic_curve_distance",
            method="rootshape_jax single",
            batch=1,
            pairs_per_s=1 / sec,
            compile_s=comp_s,
        )
        for B in batches:
            comp_s, jitted, exe = _compile(device_vmap(elastic), c1[:B], c2[:B])
            sec = _best_time(exe, c1[:B], c2[:B])
            out = jitted(c1[:B], c2[:B])
            size = jitted._cache_size()
            jitted(c1[big : big + B], c2[big : big + B]).energy.block_until_ready()
            add(
                T=T,
                what="elastic_curve_distance",
                method=f"rootshape_jax batched ({len(jax.devices())} dev)",
                batch=B,
                pairs_per_s=B / sec,
                compile_s=comp_s,
                recompiled_on_new_data=jitted._cache_size() != size,
                mean_dp_solves=float(jnp.mean(out.n_iterations)),
                max_dp_solves=int(jnp.max(out.n_iterations)),
            )
        # The cost of the alternation's quality: the two starts only (2 DP solves per pair).
        cheap = functools.partial(elastic, max_iterations=1)
        comp_s, _, exe = _compile(device_vmap(cheap), c1[:big], c2[:big])
        sec = _best_time(exe, c1[:big], c2[:big])
        add(
            T=T,
            what="elastic_curve_distance",
            method=f"rootshape_jax batched, max_iterations=1 ({len(jax.devices())} dev)",
            batch=big,
            pairs_per_s=big / sec,
            compile_s=comp_s,
        )
        if cf is not None:
            pa = [np.asarray(x, float).T.copy() for x in b1[:n_single]]
            pb = [np.asarray(x, float).T.copy() for x in b2[:n_single]]
            # elastic_distance_curve modifies its inputs in place: give it copies.
            sec = _per_pair_time(lambda a, b: cf.elastic_distance_curve(a.copy(), b.copy()), pa, pb)
            add(
                T=T,
                what="elastic_curve_distance",
                method="fdasrsf elastic_distance_curve",
                batch=1,
                pairs_per_s=1 / sec,
                compile_s=None,
            )

    # Ratios against fdasrsf, same T, same run.
    for row in rows:
        peer = [
            r for r in rows if r["T"] == row["T"] and r["what"] == row["what"] and r["method"].startswith("fdasrsf")
        ]
        row["x_fdasrsf"] = row["pairs_per_s"] / peer[0]["pairs_per_s"] if peer else None

    path = write_json("bench_curves", results)
    table = _markdown(results)
    (RESULTS / "bench_curves.md").write_text(table)
    print()
    print(table)
    print(f"wrote {path}")


def _markdown(results) -> str:
    m = results["machine"]
    lines = [
        f"Curves (issue 2): {m['cpu']}, {m['cores']} cores, {m['xla_devices']} XLA CPU devices, "
        f"jax {m['jax']}, {results['dtype']}, neighbourhood {results['neighbourhood']}, "
        f"load average {m['load_average_1min_at_start']}.",
        "",
        "| T | task | method | batch | pairs/s | × fdasrsf | compile (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results["rows"]:
        x = f"{r['x_fdasrsf']:.1f}" if r.get("x_fdasrsf") is not None else ""
        c = f"{r['compile_s']:.1f}" if r.get("compile_s") is not None else ""
        lines.append(f"| {r['T']} | {r['what']} | {r['method']} | {r['batch']} | {r['pairs_per_s']:.1f} | {x} | {c} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
