"""Synthetic conditions and synthesis plausibility on the bundled 53 roots (issue 20, items 3–4).

    python benchmarks/bench_conditions_synthesis.py [--T 50]

1. Separability of the generator's conditions under the elastic metric: LOO 1-NN and
   nearest-class-mean accuracy (`loo_accuracy`), purity of the average-linkage clustering cut
   into 3 clusters, PERMANOVA (`permanova`, 999 permutations), mean distances within and
   between conditions.
2. Plausibility (`plausibility`) of 200 random roots (`sample`) and of the roots at ±2σ along
   each of the first 5 modes (`modes`), with the previous synthesis defaults (laterals below
   2 % of the mean's main-root length dropped, no cap), the data's 10th percentile alone
   (below it dropped, above the data's longest scaled down) and the current ones (the same,
   except that the Karcher mean's own laterals stay down to their length in the mean).

Float64, scale-normalised, default weights. Writes benchmarks/results/conditions_synthesis.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, setup_jax, write_json  # noqa: E402


def purity(labels, clusters) -> float:
    import numpy as np

    total = 0
    for c in np.unique(clusters):
        _, counts = np.unique(labels[clusters == c], return_counts=True)
        total += counts.max()
    return total / len(labels)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--T", type=int, default=50)
    args = p.parse_args(argv)
    jax = setup_jax(1, x64=True)
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax.datasets import default_dataset

    roots = default_dataset()
    y = np.array([r.metadata["condition"] for r in roots])
    trees = rs.batch(roots, n_points=args.T, normalise_scale=True, dtype=np.float64)
    out = {"T": args.T, "n": len(roots), "machine": machine()}

    t0 = time.perf_counter()
    D = np.asarray(rs.pairwise_distances(trees, progress=False))
    D = 0.5 * (D + D.T)
    classes = sorted(set(y))
    cl = rs.cluster(D, n_clusters=3).labels
    pm = rs.permanova(D, y, permutations=999, seed=0)
    out["separability"] = {
        "seconds": time.perf_counter() - t0,
        "loo_nearest_neighbour": rs.loo_accuracy(D, y)["accuracy"],
        "loo_nearest_mean": rs.loo_accuracy(D, y, rule="nearest_mean")["accuracy"],
        "cluster_purity": purity(y, cl),
        "clusters": {c: [int(np.sum(cl[y == c] == k)) for k in range(3)] for c in classes},
        "permanova": {"pseudo_f": pm.pseudo_f, "p_value": pm.p_value, "r2": pm.r2, "permutations": pm.permutations},
        "mean_distance": {
            f"{a}-{b}": float(np.mean(D[np.ix_(y == a, y == b)][np.triu_indices(int(np.sum(y == a)), 1)]))
            if a == b
            else float(np.mean(D[np.ix_(y == a, y == b)]))
            for i, a in enumerate(classes)
            for b in classes[i:]
        },
    }
    print(out["separability"], flush=True)

    t0 = time.perf_counter()
    km = rs.karcher_mean(trees)
    out["mean"] = {"energy": float(km.energy), "seconds": time.perf_counter() - t0}
    main_len = float(rs.l2_norm_squared(km.fitted.q0))
    current = rs.tangent_pca(km)
    pcs = {
        "previous": rs.tangent_pca(km, min_lateral_length=0.02 * main_len, max_lateral_length=float("inf")),
        # Session 30's defaults without the mean's own laterals kept below the percentile.
        "percentile_only": rs.tangent_pca(km, min_lateral_length=float(current.min_lateral_length)),
        "current": current,
    }
    out["plausibility"] = {}
    for name, pc in pcs.items():
        rnd = rs.sample(pc, jax.random.key(0), 200)
        m = rs.modes(pc, [-2.0, 2.0], component=list(range(5)))
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), m)
        res = {}
        for what, t in (("random_200", rnd), ("modes_1to5_pm2sd", flat)):
            pl = rs.plausibility(t, trees)
            res[what] = {
                "rate": pl.rate,
                "lengths_in_range": float(np.mean(pl.lengths_in_range)),
                "no_self_crossing": float(np.mean(pl.no_self_crossing)),
                "ks_statistic": pl.ks_statistic,
                "ks_pvalue": pl.ks_pvalue,
            }
        res["min_lateral_length"] = float(pc.min_lateral_length)
        res["max_lateral_length"] = float(pc.max_lateral_length)
        out["plausibility"][name] = res
        print(name, res, flush=True)
    write_json("conditions_synthesis", out)


if __name__ == "__main__":
    main()
