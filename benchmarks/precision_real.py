"""Do distances on real tracings depend on where the roots lie, or on float32 vs float64?

An accuracy check, not a timing: the elastic distance is invariant to translation, and float32
should agree with float64 to rounding. On real pixel tracings (RhizoScan plate, RootNav) each
pairwise matrix (scale-normalised, T = 100, the 8 longest laterals per root) is computed three
ways: as read in float64, as read in float32, and in float64 with every root moved to its base
at (0, 0). Reported: relative differences from the first, per pair.

    python benchmarks/precision_real.py [--baseline /path/to/old/checkout] [--out precision_real]

With ``--baseline`` the same runs use that checkout of the package too (fresh processes).
Needs ``../shared/data``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _common import machine, run_child, setup_jax, write_json

CHILD = r"""
import dataclasses, json, sys, warnings
from pathlib import Path
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
warnings.simplefilter("ignore")
import rootshape_jax as rs
from rootshape_jax.io import read_rsml

spec = json.loads(sys.argv[1])
S = Path(spec["shared"], "rsml")
if spec["set"] == "plate":
    roots = [r for f in sorted((S / "arabidopsis_plate").glob("*.rsml")) for r in read_rsml(f)]
else:
    roots = [read_rsml(f)[0] for f in sorted((S / "rootnav_osr").glob("*.rsml"))[:8]]
roots = [rs.limit_laterals(r, 8) for r in roots]

def at_origin(r):
    o = r.main[0]
    return dataclasses.replace(r, main=r.main - o, laterals=tuple(x - o for x in r.laterals))

out = {"n_roots": len(roots)}
for key, data, dtype in (("as_read_64", roots, np.float64), ("as_read_32", roots, np.float32),
                         ("at_origin_64", [at_origin(r) for r in roots], np.float64)):
    t = rs.batch(data, n_points=100, normalise_scale=True, dtype=dtype)
    D = np.asarray(rs.pairwise_distances(t, progress=False), np.float64)
    out[key] = D[np.triu_indices(len(roots), 1)].tolist()
print("RESULT " + json.dumps(out))
"""


def summary(res: dict) -> dict:
    ref = np.asarray(res["as_read_64"])
    row = {"n_roots": res["n_roots"], "pairs": len(ref)}
    for key, name in (("as_read_32", "float32"), ("at_origin_64", "moved")):
        rel = np.abs(np.asarray(res[key]) / ref - 1)
        row[f"{name}_max"] = float(rel.max())
        row[f"{name}_median"] = float(np.median(rel))
        row[f"{name}_pairs_over_0.1%"] = int(np.sum(rel > 1e-3))
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", type=Path, help="another checkout of the package, run the same way")
    p.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    p.add_argument("--out", default="precision_real")
    args = p.parse_args()
    setup_jax(1)
    payload = {"machine": machine(), "rows": []}
    for name, package in [("this", None)] + ([("baseline", args.baseline)] if args.baseline else []):
        for dataset in ("plate", "rootnav"):
            res = run_child(CHILD, {"set": dataset, "shared": args.shared}, package)
            row = {"package": name, "set": dataset, **summary(res)}
            payload["rows"].append(row)
            print(row, flush=True)
    print(f"wrote {write_json(args.out, payload)}")


if __name__ == "__main__":
    main()
