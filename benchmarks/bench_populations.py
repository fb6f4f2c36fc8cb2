"""What users run, on the roots they have (issue 21): the distance matrix and the Karcher mean
from Python with default settings, on three populations, scale-normalised and not.

    python benchmarks/bench_populations.py [--populations synthetic pea rootnav]
        [--what matrix mean rounds profile dp] [--baseline /path/to/old/checkout] [--paths default all-cores]

Populations:
- ``synthetic``: the bundled 53 (`datasets.default_dataset`, 2D, ~10 laterals);
- ``pea``: 53 CPlantBox pea taproots (`simulated_roots("pea", 53, days=10, seed=0)`: 3D, mm,
  14–27 first-order laterals, mean 20; the `sim` extra);
- ``rootnav``: the RootNav oilseed-rape tracings in ``../shared/data/rsml/rootnav_osr`` (real,
  pixels), when present.
Each at ``T = 100``, with ``normalise_scale`` False and True.

Each measurement is a fresh process that does what a user's script does: ``import
rootshape_jax``, `batch`, then `pairwise_distances(trees)` or `karcher_mean(trees)` with
default options (``progress=False``). The matrix's compile time is the first call on two of
the roots (same chunk shapes), reported apart; the mean's is its first call minus its second.
``--paths all-cores`` runs the same after ``rs.use_all_cores()`` (one XLA device per core).
``rounds``: lateral DPs run and skipped per alternation round, on 32 random pairs (the engine
is deterministic, so round r's counts are the difference of runs capped at r and r − 1 rounds).
``profile``: where the engine's time goes, on 64 random pairs in one call: the engine's time,
its DPs (lateral and main-root), the DP kernel alone on as many random lateral pairs of the
population (its share of the engine's time), and the energy, DPs and time (best of 3) with the
alternation capped at 1–4 rounds against it run to a standstill (12 rounds, no tolerance).
``dp``: the first half of ``profile`` only (the engine call and the DP kernel alone), for
comparing DP kernels with ``--baseline``.
With ``--baseline`` every run is repeated with that checkout of the package, interleaved
(``--repeats N``: alternated N times, the median ratio and its range), and reported as a
ratio (rounds: both DP counts side by side). Results: ``results/populations.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import _common  # noqa: E402
from _common import machine, write_json  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

CHILD = r"""
import json, sys, time, pickle
spec = json.loads(sys.argv[1])
import rootshape_jax as rs
if spec["all_cores"]:
    rs.use_all_cores()
import jax
import numpy as np

__POPULATION__

roots = population(spec["population"], spec["shared"])
trees = rs.batch(roots, n_points=100, normalise_scale=spec["normalise"])
out = {"package": rs.__file__, "n_roots": len(roots), "capacity": int(trees.capacity),
       "laterals_mean": float(np.mean([r.n_laterals for r in roots])), "devices": len(jax.devices())}
what = spec["what"]


def random_pairs(trees, count):
    # The SRVFs, `count` random distinct pairs of them (a, b, their indices) and the seeded
    # generator that drew them.
    s = rs.to_srvf(trees)
    rng = np.random.default_rng(0)
    I, J = np.triu_indices(s.q0.shape[0], 1)
    pick = rng.choice(len(I), size=min(count, len(I)), replace=False)
    return s, jax.tree.map(lambda x: x[I[pick]], s), jax.tree.map(lambda x: x[J[pick]], s), pick, rng


if what == "matrix":
    t0 = time.perf_counter()
    rs.pairwise_distances(jax.tree.map(lambda x: x[:2], trees), progress=False)
    out["compile_s"] = time.perf_counter() - t0
    c0 = time.process_time(); t0 = time.perf_counter()
    D, stats = rs.pairwise_distances(trees, progress=False, return_stats=True)
    D = np.asarray(D)
    out["seconds"] = time.perf_counter() - t0
    out["cpu_seconds"] = time.process_time() - c0
    out["stats"] = stats
    out["checksum"] = float(np.sum(D))
elif what == "mean":
    times = []
    for _ in range(spec["mean_calls"]):
        c0 = time.process_time(); t0 = time.perf_counter()
        res = rs.karcher_mean(trees, progress=False)
        jax.block_until_ready(res.energy)
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    out["first_call_s"] = times[0][0]
    out["seconds"] = times[-1][0]
    out["cpu_seconds"] = times[-1][1]
    if len(times) > 1:
        out["compile_s"] = times[0][0] - times[-1][0]
    out["steps"] = int(res.steps)
    out["objective"] = float(res.energy)
elif what == "rounds":
    from rootshape_jax._engine import RegistrationOptions, register_pairs_jit
    s, a, b, pick, rng = random_pairs(trees, 32)
    prev = np.zeros(2)
    rounds = []
    for r in range(1, 5):
        reg = register_pairs_jit(a, b, rs.Weights(), RegistrationOptions(max_iterations=r))
        now = np.array([np.sum(reg.n_lateral_dp), np.sum(reg.n_lateral_skipped)], float)
        active = int(np.sum(np.asarray(reg.n_iterations) >= r))
        rounds.append({"round": r, "pairs_active": active, "dp_run": int(now[0] - prev[0]),
                       "dp_skipped": int(now[1] - prev[1])})
        prev = now
    out["pairs"] = int(len(pick))
    out["rounds"] = rounds
elif what in ("profile", "dp"):
    import functools
    from rootshape_jax._engine import RegistrationOptions, register_pairs_jit
    from rootshape_jax._warp import dp_warp_if
    s, a, b, pick, rng = random_pairs(trees, 64)
    w = rs.Weights()

    def best_of(f, repeats=3):
        # (best time of `repeats` calls, the result of the untimed warm-up call)
        first = f()
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter(); f(); best = min(best, time.perf_counter() - t0)
        return best, first

    def register(o):
        return jax.block_until_ready(register_pairs_jit(a, b, w, o))

    # The engine on these pairs, as the matrix calls it (default options, one call).
    engine_s, reg = best_of(lambda: register(RegistrationOptions()))
    # Lateral DPs, and one main-root DP per pair and round.
    n_dp = int(np.sum(reg.n_lateral_dp)) + int(np.sum(np.asarray(reg.n_iterations)))
    # The DP kernel alone on as many random real lateral pairs of the population, in slabs of
    # 32 (the engine's default `dp_batch_size`).
    q = np.asarray(s.q).reshape((-1,) + s.q.shape[-2:])[np.asarray(s.mask).reshape(-1)]
    slabs = -(-n_dp // 32)
    L1 = rng.integers(0, len(q), (slabs, 32)); L2 = rng.integers(0, len(q), (slabs, 32))
    kernel = jax.jit(jax.vmap(functools.partial(dp_warp_if, neighbourhood=7, check=False)))
    on = np.ones((32,), bool)
    def dps():
        for k in range(slabs):
            jax.block_until_ready(kernel(q[L1[k]], q[L2[k]], on))
    dp_s, _ = best_of(dps)
    out["pairs"] = int(len(pick))
    out["engine_seconds"] = engine_s
    out["dps"] = n_dp
    out["dp_kernel_seconds"] = dp_s * n_dp / (slabs * 32)
    out["dp_ms_each"] = 1e3 * dp_s / (slabs * 32)
    out["dp_share"] = out["dp_kernel_seconds"] / engine_s
    # What the alternation rounds buy: energy and DPs capped at r rounds, against the
    # alternation run to a standstill (12 rounds, no tolerance).
    caps = []
    for r, rtol in ((1, 1e-4), (2, 1e-4), (3, 1e-4), (4, 1e-4), (12, 0.0)) if what == "profile" else ():
        sec, reg = best_of(lambda: register(RegistrationOptions(max_iterations=r, rtol=rtol)))
        caps.append({"max_iterations": r, "rtol": rtol, "energy": float(np.sum(reg.energy)),
                     "lateral_dps": int(np.sum(reg.n_lateral_dp)), "seconds": sec})
    for c in caps:
        c["energy_above_converged"] = c["energy"] / caps[-1]["energy"] - 1
    if caps:
        out["caps"] = caps
print("RESULT " + json.dumps(out))
"""


# Ratios reported with --baseline: name → the timing it divides (the baseline's over the new
# run's; with --repeats, the median over the repeats and their range).
RATIOS = {"speedup": "seconds", "engine_speedup": "engine_seconds", "dp_kernel_speedup": "dp_ms_each"}


def run_child(spec: dict, package: Path | None) -> dict:
    return _common.run_child(CHILD, spec, package)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--populations", nargs="+", default=["synthetic", "pea", "rootnav"])
    p.add_argument("--what", nargs="+", default=["matrix", "mean", "rounds"])
    p.add_argument("--normalise", nargs="+", default=["no", "yes"], choices=["no", "yes"])
    p.add_argument("--baseline", type=Path, default=None, help="checkout of the package to compare with")
    p.add_argument(
        "--paths",
        nargs="+",
        default=["default"],
        choices=["default", "all-cores"],
        help="Python defaults, and/or after rs.use_all_cores()",
    )
    p.add_argument("--repeats", type=int, default=1, help="with --baseline: alternate the two this many times")
    p.add_argument("--mean-calls", type=int, default=2, help="mean calls per process (the last is timed)")
    p.add_argument("--out", default="populations", help="name of the JSON file in results/")
    args = p.parse_args(argv)

    results = {"machine": machine(), "runs": []}
    for pop in args.populations:
        if pop == "rootnav" and not (SHARED / "rsml" / "rootnav_osr").is_dir():
            print("rootnav: ../shared/data is absent, skipped", flush=True)
            continue
        for norm in args.normalise:
            for what in args.what:
                paths = [p == "all-cores" for p in args.paths] if what not in ("rounds", "profile", "dp") else [False]
                for all_cores in paths:
                    spec = {
                        "population": pop,
                        "normalise": norm == "yes",
                        "what": what,
                        "all_cores": all_cores,
                        "shared": str(SHARED),
                        "mean_calls": args.mean_calls,
                    }
                    versions = [("new", None)]
                    if args.baseline is not None:
                        versions = [("baseline", args.baseline), ("new", None)]
                    row = dict(spec)
                    # Baseline and new alternate, a fresh process each: on a host whose speed
                    # drifts, each ratio compares two neighbouring runs.
                    runs = [
                        {label: run_child(spec, package) for label, package in versions} for _ in range(args.repeats)
                    ]
                    row.update(runs[0])
                    if len(runs) > 1:
                        row["repeats"] = runs
                    if "baseline" in row:
                        for key, timing in RATIOS.items():
                            ratios = [r["baseline"][timing] / r["new"][timing] for r in runs if timing in r["new"]]
                            if ratios:
                                row[key] = statistics.median(ratios)
                                row[key + "_range"] = [min(ratios), max(ratios)]
                    results["runs"].append(row)
                    print(json.dumps(row), flush=True)
                    write_json(args.out, results)
    return results


if __name__ == "__main__":
    main()
