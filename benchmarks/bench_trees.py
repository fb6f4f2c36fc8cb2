"""Root registration benchmark (issue 3): time per pair against T and lateral count, the full
53-root distance matrix, and geodesics — beside the paper's Matlab timings.

    python benchmarks/bench_trees.py [--quick] [--x64] [--devices N]
    python benchmarks/bench_trees.py --population pea --normalise no --path default

`--population` picks the roots of the geodesic and the matrix (issue 21): the bundled synthetic
set (default), 53 CPlantBox pea taproots (`sim` extra) or the real RootNav tracings in
../shared/data; `--normalise` whether they are scale-normalised; `--path default` runs as a
user's Python does with nothing configured (one XLA device, blocks on worker threads), and
`--path all-cores` (default, as before) with one XLA device per core.

Paper (Matlab, i5-4460): 147 s to align one pair (23 laterals), 0.04 s per geodesic once aligned,
so the 53-root matrix (1,378 pairs) would take ≈ 56 h.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, population, setup_jax, timed, write_json  # noqa: E402

PAPER_ALIGN_S = 147.0
PAPER_GEODESIC_S = 0.04


def _suffix(args) -> str:
    """Results of the historical setting (synthetic, normalised, all cores) keep their name."""
    if (args.population, args.normalise, args.path) == ("synthetic", "yes", "all-cores"):
        return ""
    return f"_{args.population}_{'normalised' if args.normalise == 'yes' else 'raw'}_{args.path.replace('-', '_')}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    p.add_argument("--x64", action="store_true", help="float64 (default float32)")
    p.add_argument("--devices", type=int, default=None, help="XLA devices for --path all-cores (default: every core)")
    p.add_argument("--population", default="synthetic", choices=["synthetic", "pea", "rootnav"])
    p.add_argument("--normalise", default="yes", choices=["yes", "no"], help="normalise_scale of batch")
    p.add_argument("--path", default="all-cores", choices=["default", "all-cores"])
    p.add_argument(
        "--geodesic-only", action="store_true", help="time only the geodesic; its entry replaces the one in trees.json"
    )
    args = p.parse_args(argv)
    jax = setup_jax(1 if args.path == "default" else args.devices, x64=args.x64)
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax.datasets import synthetic_roots

    normalise = args.normalise == "yes"
    results = {
        "machine": machine(),
        "population": args.population,
        "normalise_scale": normalise,
        "path": args.path,
        "dtype": "float64" if args.x64 else "float32",
        "per_pair": [],
        "paper": {
            "align_one_pair_s": PAPER_ALIGN_S,
            "geodesic_s": PAPER_GEODESIC_S,
            "matrix_53_estimate_h": PAPER_ALIGN_S * 1378 / 3600,
        },
    }
    w = rs.Weights()  # the paper's (0.02, 1, 1)
    name = "trees" + _suffix(args) + ("_quick" if args.quick else "")

    # 1. One registration against T and the number of laterals per root.
    pool = synthetic_roots(12, condition="high_nitrate", seed=1, lateral_density=0.9, max_laterals=40)
    Ts = () if args.geodesic_only else (50,) if args.quick else (50, 100)
    ns = (5, 10) if args.quick else (5, 10, 20, 40)
    for T in Ts:
        for n in ns:
            roots = [r for r in pool if r.n_laterals >= n][:2]
            roots = [rs.Root(main=r.main, laterals=r.laterals[:n], attach=r.attach[:n]) for r in roots]
            t = rs.batch(roots, n_points=T, max_laterals=2 * n, normalise_scale=True)
            a, b = rs.unstack(t)
            first, warm, reg = timed(rs.register, a, b, weights=w)
            row = dict(
                T=T,
                laterals=n,
                K=2 * n,
                first_call_s=first,
                warm_s=warm,
                lateral_dp=int(reg.n_lateral_dp),
                lateral_pruned_per_iter=int(reg.n_lateral_skipped),
                iterations=int(reg.n_iterations),
                distance=float(reg.distance),
                speedup_vs_paper=PAPER_ALIGN_S / warm,
            )
            results["per_pair"].append(row)
            print(
                f"T={T:4d} laterals={n:3d}: {warm * 1e3:8.1f} ms/pair warm (first call {first:.1f} s), "
                f"{row['lateral_dp']} lateral DPs, {row['iterations']} rounds",
                flush=True,
            )

    # 2. Geodesic of 9 steps between two aligned roots.
    data = population(args.population)
    n_roots = 12 if args.quick else len(data)
    data = data[:n_roots]
    T = 50 if args.quick else 100
    trees = rs.batch(data, n_points=T, normalise_scale=normalise)
    print(
        f"{args.population} ({'normalised' if normalise else 'not normalised'}, path {args.path}): {n_roots} roots, laterals per root {min(r.n_laterals for r in data)}–"
        f"{max(r.n_laterals for r in data)} (mean {np.mean([r.n_laterals for r in data]):.1f}), K = {trees.capacity}, T = {T}"
    )
    a, b = rs.unstack(jax.tree.map(lambda x: x[:2], trees))
    reg = rs.register(a, b, weights=w)
    first, warm, _ = timed(rs.geodesic, a, b, n_steps=9, weights=w, registration=reg, repeats=20)
    results["geodesic"] = dict(
        n_steps=9, T=T, K=trees.capacity, first_call_s=first, warm_s=warm, speedup_vs_paper=PAPER_GEODESIC_S / warm
    )
    print(f"geodesic (9 steps, aligned): {warm * 1e3:.2f} ms (paper {PAPER_GEODESIC_S * 1e3:.0f} ms)")
    if args.geodesic_only:
        import json

        path = Path(__file__).parent / "results" / (name + ".json")
        previous = json.loads(path.read_text()) if path.exists() else {}
        previous["geodesic"] = dict(results["geodesic"], machine=results["machine"])
        path.write_text(json.dumps(previous, indent=2))
        print("updated the geodesic entry of", path)
        return

    # 3. The full distance matrix. Compile once on a 2-root batch of the same capacities (same
    #    chunk shape, so the big run reuses the program), then time the whole matrix.
    chunk = 32
    t0 = time.perf_counter()
    rs.pairwise_distances(jax.tree.map(lambda x: x[:2], trees), weights=w, chunk_size=chunk, progress=False)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    D, stats = rs.pairwise_distances(trees, weights=w, chunk_size=chunk, progress=True, return_stats=True)
    D = np.asarray(jax.block_until_ready(D))
    wall = time.perf_counter() - t0
    real_pairs = sum(a.n_laterals * b.n_laterals for i, a in enumerate(data) for b in data[i + 1 :])
    results["matrix"] = dict(
        n_roots=n_roots,
        pairs=stats["pairs"],
        T=T,
        K=trees.capacity,
        chunk_size=chunk,
        compile_plus_first_chunk_s=compile_s,
        wall_s=wall,
        pairs_per_s=stats["pairs"] / wall,
        lateral_dp_run=stats["lateral_dp"],
        lateral_pairs_pruned_per_round=stats["lateral_skipped"],
        real_real_pairs_per_round=real_pairs,
        mean_distance=float(D[np.triu_indices(n_roots, 1)].mean()),
        paper_estimate_s=PAPER_ALIGN_S * stats["pairs"],
    )
    slots = stats["lateral_dp"] + stats["lateral_skipped"]
    results["matrix"]["skipped_fraction"] = stats["lateral_skipped"] / slots
    print(
        f"matrix {n_roots}×{n_roots}: {wall:.1f} s for {stats['pairs']} pairs "
        f"({stats['pairs'] / wall:.1f} pairs/s), compile+first chunk {compile_s:.1f} s; "
        f"lateral DPs run {stats['lateral_dp']} of {slots} real–real pair-rounds "
        f"({stats['lateral_skipped'] / slots:.0%} skipped; {real_pairs} real–real pairs per round)"
    )
    path = write_json(name, results)
    print("wrote", path)


if __name__ == "__main__":
    main()
