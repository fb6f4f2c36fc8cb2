"""First-call time of the public calls a user's script makes, in a fresh process each.

    python benchmarks/bench_first_call.py [--population rootnav] [--roots 8]
        [--baseline /path/to/old/checkout] [--rounds 2]

A new Python process pays for compilation on every first call at new shapes: XLA compiles
each jitted program, and each eager `jnp` operation is compiled as its own one-op program at
each new shape. This measures, on roots we did not design (CPlantBox pea by default, the `sim`
extra; ``--population rootnav`` for the real tracings, whose 63 laterals per root make the
run, not the compilation, dominate), T = 100, Python defaults: `to_srvf`, `to_curves`,
`pairwise_distances` of 4 roots and `karcher_mean` of `--roots` roots, each first call and then the same call again (warm),
with `block_until_ready`. With ``--baseline`` every child run is repeated with that checkout,
interleaved, and the JSON gives the ratios. Results: benchmarks/results/first_call.json.

``--cache``: JAX's persistent compilation cache on, one new empty folder per checkout (JAX's
default threshold: programs compiled in 1 s or more are kept), as a user who sets
``jax_compilation_cache_dir`` (or runs the CLI) has it. Round 0 then compiles and fills the
cache; later rounds are the user's next scripts. Results: ``first_call_cache.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import _common  # noqa: E402
from _common import machine, write_json  # noqa: E402

CHILD = r"""
import json, sys, time
import jax
import rootshape_jax as rs
__POPULATION__
spec = json.loads(sys.argv[1])
roots = population(spec["population"], spec.get("shared"))[: spec["roots"]]
tree = rs.batch(roots)

def twice(name, fn):
    for label in ("first", "warm"):
        t = time.perf_counter()
        value = jax.block_until_ready(fn())
        out[f"{name}_{label}_s"] = time.perf_counter() - t
    return value

out = {}
s = twice("to_srvf", lambda: rs.to_srvf(tree))
twice("to_curves", lambda: rs.to_curves(s))
D = twice("pairwise_distances_4", lambda: rs.pairwise_distances(rs.batch(roots[:4]), progress=False))
km = twice("karcher_mean", lambda: rs.karcher_mean(tree, progress=False))
out.update(checksum_distances=float(D.sum()), mean_energy=float(km.energy), mean_steps=int(km.steps))
print("RESULT " + json.dumps(out))
"""


def run_child(spec: dict, package: Path | None, cache: Path | None = None) -> dict:
    env = {
        "JAX_COMPILATION_CACHE_DIR": str(cache) if cache else None,
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": None,
    }
    return _common.run_child(CHILD, spec, package, env)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--population", default="pea", choices=_common.POPULATIONS)
    p.add_argument("--roots", type=int, default=8)
    p.add_argument("--baseline", type=Path, default=None, help="checkout of the package to compare with")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--cache", action="store_true", help="persistent compilation cache on (a new folder per checkout)")
    args = p.parse_args(argv)
    caches = {}
    if args.cache:
        root = Path(tempfile.mkdtemp(prefix="rs_cache_"))
        caches = {"baseline": root / "baseline", "new": root / "new"}
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    spec = {"population": args.population, "roots": args.roots, "shared": str(shared)}
    versions = [("new", None)] if args.baseline is None else [("baseline", args.baseline), ("new", None)]
    runs = {name: [] for name, _ in versions}
    for r in range(args.rounds):
        for name, package in versions:
            runs[name].append(run_child(spec, package, caches.get(name)))
            print(f"round {r} {name}: {json.dumps(runs[name][-1])}", flush=True)
    # With the cache, round 0 (filling it) is reported apart: "best" is over the later rounds.
    later = {name: rs_[1:] if args.cache and len(rs_) > 1 else rs_ for name, rs_ in runs.items()}
    best = {name: {k: min(run[k] for run in rs_) for k in rs_[0] if k.endswith("_s")} for name, rs_ in later.items()}
    payload = {"machine": machine(), "spec": {**spec, "cache": args.cache}, "runs": runs, "best": best}
    if args.baseline is not None:
        payload["baseline_over_new"] = {k: best["baseline"][k] / best["new"][k] for k in best["new"]}
    print(json.dumps(payload.get("baseline_over_new", best), indent=1))
    print(write_json("first_call_cache" if args.cache else "first_call", payload))


if __name__ == "__main__":
    main()
