"""Does the default Karcher mean reach the minimum? (issue 20, item 1)

For each set of roots, the energy F at the end of: the default `karcher_mean`; the fixed point
without its warm-up (the previous default, ``warm_up_steps=0``); gradient descent
(``method="gradient"``); and the default started from each of the three most central samples
after the medoid (ranked by the sum of squared DP-free lower-bound distances, the medoid's own
criterion). Every F is the Karcher objective as each run reports it (each sample's best
registration found onto the fitted mean). Float64, T points per branch, default weights.

    python benchmarks/bench_mean_optimum.py --set bundled [--T 100]
    python benchmarks/bench_mean_optimum.py --report     # merge results, print the markdown

Sets: ``bundled`` (the 53 roots of `default_dataset`, scale-normalised, as bench_stats),
``cplantbox`` (6 lupin + 6 pea taproots, CPlantBox, 7 days, seeds 0–5, 3D, mm, *not*
normalised; needs the ``sim`` extra), ``rootnav`` (the 10 RootNav oilseed-rape RSML files in
../shared/data, scale-normalised: pixel units differ between images) and ``plate`` (the 15
arabidopsis plate seedlings, 3 dates × 5 plants, scale-normalised). Writes
benchmarks/results/mean_optimum_<set>.json; ``--report`` writes mean_optimum.json and prints
the table for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import RESULTS, machine, setup_jax, write_json  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rsml"
SETS = ("bundled", "cplantbox", "rootnav", "plate")


def load(name: str, T: int):
    import numpy as np

    import rootshape_jax as rs

    if name == "bundled":
        from rootshape_jax.datasets import default_dataset

        return rs.batch(default_dataset(), n_points=T, normalise_scale=True, dtype=np.float64)
    if name == "cplantbox":
        from rootshape_jax.datasets import simulated_roots

        roots = simulated_roots("lupin", 6, seed=0, days=7) + simulated_roots("pea", 6, seed=0, days=7)
        return rs.batch(roots, n_points=T, dtype=np.float64)
    from rootshape_jax.io import read_rsml

    folder = {"rootnav": "rootnav_osr", "plate": "arabidopsis_plate"}[name]
    roots = []
    for path in sorted((DATA / folder).glob("*.rsml")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            roots += read_rsml(path)
    if not roots:
        raise SystemExit(f"no RSML found in {DATA / folder}")
    return rs.batch(roots, n_points=T, normalise_scale=True, dtype=np.float64)


def run_set(name: str, T: int, only: list[str] | None = None) -> dict:
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax._mean import lower_bound_distances

    trees = load(name, T)
    samples = rs.to_srvf(trees)
    D = np.asarray(lower_bound_distances(samples, rs.Weights()))
    order = [int(i) for i in np.argsort(np.sum(D**2, axis=1))]
    runs = {
        "default": {},
        "fixed_point_no_warm_up": {"warm_up_steps": 0},
        "gradient": {"method": "gradient"},
    }
    for rank, i in enumerate(order[1:4], start=1):
        runs[f"default_from_central_{rank}"] = {"init": i}
    if only:
        runs = {k: v for k, v in runs.items() if k in only}
    out = {
        "set": name,
        "T": T,
        "n": int(trees.main.shape[0]),
        "K": int(trees.laterals.shape[1]),
        "dim": int(trees.main.shape[-1]),
        "central": order[:4],
        "runs": {},
    }
    for label, kw in runs.items():
        t0 = time.perf_counter()
        km = rs.karcher_mean(trees, throw=False, **kw)
        energy = float(km.energy)
        dt = time.perf_counter() - t0
        out["runs"][label] = {
            "energy": energy,
            "seconds": dt,
            "steps": int(km.steps),
            "init": km.init_index,
            "result": str(km.result),
            "trace": [float(x) for x in np.asarray(km.energy_trace)],
        }
        if label == "default":
            out["round_trip"] = round_trip(km)
            print(f"{name}: to_curves(mean) registered back onto mean_srvf: {out['round_trip']}", flush=True)
        print(f"{name}: {label:28s} F = {energy:.6g}  steps {int(km.steps):3d}  {dt:7.1f} s", flush=True)
    best = min((r["energy"] for k, r in out["runs"].items() if k != "default"), default=float("nan"))
    out["best_other"] = best
    out["default_gap"] = out["runs"]["default"]["energy"] / best - 1
    return out


def round_trip(km) -> dict:
    """Item 2: the mean's curves, back to SRVFs and registered onto `mean_srvf`."""
    import numpy as np

    import rootshape_jax as rs

    back = rs.to_srvf(rs.to_curves(km.mean_srvf))
    reg = rs.register(km.mean_srvf, back, registration=km.registration)
    typical = float(np.median(np.sqrt(np.asarray(km.energies))))
    return {
        "distance": float(reg.distance),
        "typical_sample_to_mean": typical,
        "relative": float(reg.distance) / typical,
        "terms": {k: float(v) for k, v in reg.terms.values.items()},
    }


def report() -> None:
    parts = [
        json.loads((RESULTS / f"mean_optimum_{s}.json").read_text())
        for s in SETS
        if (RESULTS / f"mean_optimum_{s}.json").exists()
    ]
    write_json("mean_optimum", {"sets": parts})
    cols = [
        "default",
        "fixed_point_no_warm_up",
        "gradient",
        "default_from_central_1",
        "default_from_central_2",
        "default_from_central_3",
    ]
    print("| set (n, K, d, T) | " + " | ".join(cols) + " | default vs best other |")
    print("|---|" + "---|" * (len(cols) + 1))
    for p in parts:
        cells = []
        for c in cols:
            r = p["runs"].get(c)
            cells.append("" if r is None else f"{r['energy']:.5g} ({r['seconds']:.0f} s)")
        print(
            f"| {p['set']} ({p['n']}, {p['K']}, {p['dim']}, {p['T']}) | "
            + " | ".join(cells)
            + f" | {100 * p['default_gap']:+.2f} % |"
        )


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--set", choices=SETS)
    p.add_argument("--T", type=int, default=100)
    p.add_argument("--report", action="store_true")
    p.add_argument(
        "--runs",
        nargs="+",
        default=None,
        help="only these runs (default, fixed_point_no_warm_up, gradient, default_from_central_k)",
    )
    args = p.parse_args(argv)
    if args.report:
        report()
        return
    if args.set is None:
        p.error("give --set or --report")
    setup_jax(1, x64=True)
    out = run_set(args.set, args.T, args.runs)
    out["machine"] = machine()
    write_json(f"mean_optimum_{args.set}", out)


if __name__ == "__main__":
    main()
