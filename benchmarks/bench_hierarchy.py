"""Whole root systems (issue 15): registration at depth 3 against depth 2 on the same roots,
and against nested evaluation without pruning (what the authors' public Matlab code for
trees does: a full alignment inside every branch pair, no bounds).

    python benchmarks/bench_hierarchy.py [--n 30] [--species pea] [--days 20] [--unpruned-roots 8]

Roots: CPlantBox simulations (`sim` extra) with second-order laterals; T = 100, not
normalised, Python defaults (one XLA device, blocks on worker threads, default registration
options). Reports one pair (first call and warm), the n-root distance matrix at depth 3 and 2
(compile excluded: a 2-root call of the same chunk shape first), DPs run per level, and the
unpruned nested evaluation on the first `--unpruned-roots` roots (same run, ratio of time and
DPs, largest distance difference). Writes results/hierarchy.json (`--out` names another).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, timed, write_json  # noqa: E402


def _orders(root, level=1, acc=None):
    acc = {} if acc is None else acc
    acc[level] = acc.get(level, 0) + root.n_laterals
    for child in root.children:
        _orders(child, level + 1, acc)
    return acc


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, default=30)
    p.add_argument("--species", default="pea")
    p.add_argument("--days", type=int, default=20)
    p.add_argument("--n-points", type=int, default=100)
    p.add_argument("--unpruned-roots", type=int, default=8)
    p.add_argument("--out", default="hierarchy", help="results/<out>.json")
    args = p.parse_args(argv)
    import jax
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax.datasets import simulated_roots

    roots = simulated_roots(args.species, args.n, days=args.days, seed=0)
    counts = [_orders(r) for r in roots]
    trees = {3: rs.batch(roots, n_points=args.n_points, depth=3), 2: rs.batch(roots, n_points=args.n_points)}
    out = {
        "machine": machine(),
        "population": f"CPlantBox {args.species}, {args.n} plants, {args.days} days, seed 0",
        "T": args.n_points,
        "capacities": {
            str(k): list(t.capacities) if hasattr(t, "capacities") else [t.capacity] for k, t in trees.items()
        },
        "branches_per_root": {
            f"order{o}": float(np.mean([c.get(o, 0) for c in counts])) for o in sorted({o for c in counts for o in c})
        },
    }
    print(out["population"], "| branches per root:", out["branches_per_root"], "| capacities:", out["capacities"])

    # One pair.
    out["pair"] = {}
    for depth in (3, 2):
        a, b = rs.unstack(jax.tree.map(lambda x: x[:2], trees[depth]))
        first, warm, reg = timed(rs.register, a, b, repeats=3)
        row = {
            "first_call_s": first,
            "warm_s": warm,
            "energy": float(reg.energy),
            "lateral_dp": int(reg.n_lateral_dp),
            "deeper_dp": np.asarray(reg.n_deeper_dp).tolist(),
        }
        if depth == 3:
            first_u, warm_u, reg_u = timed(rs.register, a, b, prune=False, repeats=1)
            row["unpruned"] = {
                "first_call_s": first_u,
                "warm_s": warm_u,
                "energy": float(reg_u.energy),
                "lateral_dp": int(reg_u.n_lateral_dp),
                "deeper_dp": np.asarray(reg_u.n_deeper_dp).tolist(),
            }
        out["pair"][str(depth)] = row
        print(f"pair, depth {depth}: {row}", flush=True)

    # The matrix at depth 3 and 2, Python defaults.
    out["matrix"] = {}
    for depth in (3, 2):
        t = trees[depth]
        t0 = time.perf_counter()
        rs.pairwise_distances(jax.tree.map(lambda x: x[:2], t), progress=False)
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        D, stats = rs.pairwise_distances(t, progress=True, return_stats=True)
        D = np.asarray(D)
        wall = time.perf_counter() - t0
        out["matrix"][str(depth)] = {
            "seconds": wall,
            "compile_s": compile_s,
            "pairs": stats["pairs"],
            "lateral_dp": stats["lateral_dp"],
            "lateral_skipped": stats["lateral_skipped"],
            "deeper_dp": stats.get("deeper_dp", []),
            "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
            "checksum": float(D.sum()),
        }
        print(f"matrix, depth {depth}: {out['matrix'][str(depth)]}", flush=True)
        if depth == 3:
            D3 = D
    out["matrix"]["ratio_depth3_to_depth2"] = out["matrix"]["3"]["seconds"] / out["matrix"]["2"]["seconds"]

    # Nested evaluation without pruning, on the first roots, against pruning on the same roots.
    m = args.unpruned_roots
    sub = jax.tree.map(lambda x: x[:m], trees[3])
    rows = {}
    for prune in (True, False):
        rs.pairwise_distances(jax.tree.map(lambda x: x[:2], sub), prune=prune, progress=False)
        t0 = time.perf_counter()
        D, stats = rs.pairwise_distances(sub, prune=prune, progress=True, return_stats=True)
        rows[prune] = (time.perf_counter() - t0, np.asarray(D), stats)
    (tp, Dp, sp), (tu, Du, su) = rows[True], rows[False]
    dps_p = sp["lateral_dp"] + sum(sp["deeper_dp"])
    dps_u = su["lateral_dp"] + sum(su["deeper_dp"])
    out["unpruned"] = {
        "roots": m,
        "pairs": sp["pairs"],
        "pruned_s": tp,
        "unpruned_s": tu,
        "time_ratio": tu / tp,
        "pruned_dp": {"lateral": sp["lateral_dp"], "deeper": sp["deeper_dp"]},
        "unpruned_dp": {"lateral": su["lateral_dp"], "deeper": su["deeper_dp"]},
        "dp_ratio": dps_u / max(dps_p, 1),
        "max_abs_difference": float(np.max(np.abs(Dp - Du))),
        "matches_full_matrix": float(np.max(np.abs(Dp - D3[:m, :m]))),
    }
    print(f"unpruned nested evaluation: {out['unpruned']}", flush=True)
    path = write_json(args.out, out)
    print("wrote", path)


if __name__ == "__main__":
    main()
