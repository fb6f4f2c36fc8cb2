"""Roots from real photographs against their hand tracings (issue 19).

    python benchmarks/bench_images.py [--no-baseline] [--no-elastic] [--only NAME ...]

Data: the 11 image–tracing pairs of ../shared/data (the Arabidopsis plate photograph with
rsml/arabidopsis_plate/2012_11_19_18h00_chl110_1_1.rsml, and the 10 RootNav oilseed-rape
photographs images/rootnav_osr/*.jpg with rsml/rootnav_osr/*.rsml). For each photograph:
`roots_from_image` with default settings (timed, one call, after a warm-up call on a small
synthetic image so that skan's JIT compilation is not counted), then `compare_to_tracing`.
The baseline is the implementation this issue started from (commit f73dc8b,
rootshape_jax/io/_image.py: Otsu threshold + skeleton, default settings), loaded from git.

Per image: plants (extracted / traced), total-length ratio (all extracted length / all traced
length), first-order lateral counts (summed over plants), elastic distance (mean over matched
plants, each system scaled to unit main-root length), seconds. Targets of the issue are
evaluated at the end. Writes benchmarks/results/images.json and prints a markdown table.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
BASELINE_COMMIT = "f73dc8b"


def pairs() -> list[tuple[str, Path, Path]]:
    out = []
    plate = "2012_11_19_18h00_chl110_1_1"
    out.append(
        (
            "plate",
            DATA / "images" / "arabidopsis_plate" / f"{plate}.jpg",
            DATA / "rsml" / "arabidopsis_plate" / f"{plate}.rsml",
        )
    )
    for img in sorted((DATA / "images" / "rootnav_osr").glob("*.jpg")):
        out.append(("osr", img, DATA / "rsml" / "rootnav_osr" / f"{img.stem}.rsml"))
    return out


def load_baseline():
    """The issue's starting implementation of roots_from_image, from git."""
    src = subprocess.run(
        ["git", "show", f"{BASELINE_COMMIT}:rootshape_jax/io/_image.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    src = src.replace("from .._errors import", "from rootshape_jax._errors import").replace(
        "from .._root import", "from rootshape_jax._root import"
    )
    path = Path(tempfile.mkdtemp()) / "baseline_image.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("baseline_image", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.roots_from_image


def run_one(fn, kind, img, rsml, *, elastic):
    from rootshape_jax.io import compare_to_tracing, read_rsml, total_length

    traced = read_rsml(rsml)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ex = fn(img)
        err = None
    except Exception as e:  # reported as a failed row
        ex, err = [], f"{type(e).__name__}: {e}"
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    cmp = compare_to_tracing(ex, traced, elastic=elastic and bool(ex))
    ed = [p.elastic_distance for p in cmp.plants]
    lat_e = sum(r.n_laterals for r in ex)
    lat_t = sum(r.n_laterals for r in traced)
    return {
        "image": img.name,
        "kind": kind,
        "plants_extracted": len(ex),
        "plants_traced": len(traced),
        "plants_matched": len(cmp.plants),
        "total_length_extracted": sum(total_length(r) for r in ex),
        "total_length_traced": sum(total_length(r) for r in traced),
        "total_length_ratio": cmp.total_length_ratio,
        "main_length_ratios": [p.main_length_ratio for p in cmp.plants],
        "laterals_extracted": lat_e,
        "laterals_traced": lat_t,
        "lateral_count_error": abs(lat_e - lat_t) / lat_t if lat_t else float("nan"),
        "elastic_distance_mean": float(np.mean(ed)) if ed and elastic else float("nan"),
        "seconds": seconds,
        "cpu_seconds": cpu,
        "recall_8px": cmp.recall,
        "precision_8px": cmp.precision,
        "traced_overlap_5px": traced_overlap(traced),
        "error": err,
    }


def traced_overlap(traced, radius=5.0, skip=16.0):
    """Fraction of the traced length lying within `radius` px of another traced branch
    (ignoring each lateral's first `skip` px, its junction): roots traced separately where
    they touch, which a skeleton of the photograph shows as one line."""
    from scipy.spatial import cKDTree

    from rootshape_jax.io._compare import sample_branches

    branches = [b for r in traced for b in (r.main, *r.laterals)]
    pts = [sample_branches([type(traced[0])(main=b)], 2.0) for b in branches]
    lab = np.concatenate([np.full(len(p), i) for i, p in enumerate(pts)])
    allp = np.concatenate(pts)
    tree = cKDTree(allp)
    shared = total = 0
    for i, p in enumerate(pts):
        q = p[int(skip / 2) :] if i else p
        for near in tree.query_ball_point(q, radius):
            total += 1
            shared += bool(np.any(lab[near] != i))
    return shared / max(total, 1)


def targets(rows):
    n = len(rows)
    plates = [r for r in rows if r["kind"] == "plate"]
    osr = [r for r in rows if r["kind"] == "osr"]
    within20 = sum(abs(r["total_length_ratio"] - 1) <= 0.2 for r in rows)
    lat30 = sum(r["lateral_count_error"] <= 0.3 for r in rows)
    return {
        "plants_exact_on_every_plate": all(r["plants_extracted"] == r["plants_traced"] for r in plates),
        "plants_exact_all_images": sum(r["plants_extracted"] == r["plants_traced"] for r in rows),
        "total_within_20pct": f"{within20}/{n}",
        "total_within_20pct_pass": within20 >= 0.8 * n,
        "laterals_within_30pct": f"{lat30}/{n}",
        "laterals_within_30pct_pass": lat30 >= 0.7 * n,
        "max_seconds_2500x1900": max((r["seconds"] for r in osr), default=float("nan")),
        "max_cpu_seconds_2500x1900": max((r["cpu_seconds"] for r in osr), default=float("nan")),
        "speed_pass": max((r["seconds"] for r in osr), default=0.0) <= 10.0,
    }


def table(rows, base=None) -> str:
    head = "| image | plants (ex/tr) | total-length ratio | laterals (ex/tr) | elastic dist. | s (CPU s) | recall / precision @8 px | traced overlap |"
    sep = "|---|---:|---:|---:|---:|---:|---:|---:|"
    if base:
        head += " baseline plants | baseline total ratio | baseline laterals | baseline s |"
        sep += "---:|---:|---:|---:|"
    lines = [head, sep]
    for k, r in enumerate(rows):
        line = (
            f"| {r['image']} | {r['plants_extracted']}/{r['plants_traced']} | {r['total_length_ratio']:.2f} | "
            f"{r['laterals_extracted']}/{r['laterals_traced']} | {r['elastic_distance_mean']:.3f} | {r['seconds']:.1f} ({r['cpu_seconds']:.1f}) | "
            f"{r['recall_8px']:.2f} / {r['precision_8px']:.2f} | {r['traced_overlap_5px']:.2f} |"
        )
        if base:
            b = base[k]
            line += f" {b['plants_extracted']} | {b['total_length_ratio']:.2f} | {b['laterals_extracted']} | {b['seconds']:.1f} |"
        lines.append(line)
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--no-elastic", action="store_true")
    ap.add_argument("--only", nargs="*", default=None)
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"shared data not found at {DATA}")
    from tqdm import tqdm

    from rootshape_jax.io import roots_from_image

    # Warm-up: skan compiles its numba kernels on first use.
    yy, xx = np.mgrid[:120, :120]
    roots_from_image(np.where(np.abs(xx - 60 - 8 * np.sin(yy / 15)) < 3, 0.2, 0.8))
    todo = [p for p in pairs() if not args.only or any(o in p[1].name for o in args.only)]
    rows = [run_one(roots_from_image, k, i, r, elastic=not args.no_elastic) for k, i, r in tqdm(todo, desc="new")]
    base = None
    if not args.no_baseline:
        old = load_baseline()
        base = [run_one(old, k, i, r, elastic=False) for k, i, r in tqdm(todo, desc="baseline")]
    out = {
        "machine": machine(),
        "rows": rows,
        "targets": targets(rows),
        "baseline_rows": base,
        "baseline_targets": targets(base) if base else None,
    }
    path = write_json("images", out)
    print(table(rows, base))
    print(out["targets"])
    if base:
        print("baseline:", out["baseline_targets"])
    print("wrote", path)


if __name__ == "__main__":
    main()
