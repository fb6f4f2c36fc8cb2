"""Where `roots_from_image` starts each main root, against the hand tracings (BENCHMARKS.md,
"Where the main root starts").

    python benchmarks/image_bases.py [--package DIR] [--elastic] --out results/NAME.json

`--package` runs another checkout's package (e.g. a `git worktree` of an older commit) for a
before/after comparison in one session. Needs ../shared/data (the RootNav photographs and
tracings, and the Arabidopsis plate).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# The plate needs the options of tests/test_real_data.py (its region, background flattening).
PLATE_OPTS = dict(roi=(450, 1200, 1450, 2950), background=15, threshold="triangle", min_root_length=150, close_gaps=7)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--package", default=None, help="a checkout whose rootshape_jax to run")
    p.add_argument("--elastic", action="store_true", help="also the elastic distance to the tracing")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    if args.package:
        sys.path.insert(0, args.package)
    import rootshape_jax
    from rootshape_jax.io import compare_to_tracing, read_rsml, roots_from_image

    warnings.simplefilter("ignore")
    out = {"package": rootshape_jax.__file__, "photographs": {}}
    for image in sorted((DATA / "images" / "rootnav_osr").glob("*.jpg")):
        t = time.perf_counter()
        ex = roots_from_image(image)
        tr = read_rsml(DATA / "rsml" / "rootnav_osr" / f"{image.stem}.rsml")
        c = compare_to_tracing(ex, tr, elastic=args.elastic)
        d = dataclasses.asdict(c.plants[0]) if c.plants else {}
        row = {
            "base_offset_px": float(np.linalg.norm(ex[0].main[0] - tr[0].main[0])),
            "main_length_ratio": d.get("main_length_ratio"),
            "elastic_distance": d.get("elastic_distance") if args.elastic else None,
            "recall": c.recall,
            "precision": c.precision,
            "seconds": time.perf_counter() - t,
        }
        out["photographs"][image.stem] = row
        print(image.stem, {k: round(v, 3) for k, v in row.items() if v is not None}, flush=True)
    plate = "2012_11_19_18h00_chl110_1_1"
    ex = roots_from_image(DATA / "images" / "arabidopsis_plate" / f"{plate}.jpg", **PLATE_OPTS)
    tr = read_rsml(DATA / "rsml" / "arabidopsis_plate" / f"{plate}.rsml")
    c = compare_to_tracing(ex, tr, elastic=False)
    out["plate"] = {
        "matched": len(c.plants),
        "recall": c.recall,
        "precision": c.precision,
        "base_offsets_px": [float(np.linalg.norm(ex[q.extracted].main[0] - tr[q.traced].main[0])) for q in c.plants],
    }
    print("plate", out["plate"])
    Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
