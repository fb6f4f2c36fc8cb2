"""The demo's section on whole root systems (docs/design.md §11): a CPlantBox pea population
with second-order laterals compared at depth 3 and at depth 2, a depth-3 geodesic, per-order
traits, and a look for real RSML files that hold second-order laterals."""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path

import numpy as np

import rootshape_jax as rs
from rootshape_jax._traits import deepest_order
from rootshape_jax.io import unit_label

from ._common import fmt, make_weights, say
from ._report import Output, html_table, write_dict_csv

# Pea plants 14 to 20 days old: the older ones have second-order laterals, the youngest few.
DAYS = (14.0, 20.0)
# Longest first-order laterals kept per plant (their own laterals come along): keeps the
# section near a minute on 2 busy cores; --laterals overrides it.
SYSTEM_LATERALS = 10


def pea_population(n: int, args) -> list[rs.Root]:
    """`n` CPlantBox pea plants, 2D (front view), ages evenly spread over `DAYS`."""
    from rootshape_jax.datasets import simulated_roots

    plants = []
    for i, days in enumerate(np.linspace(*DAYS, n)):
        (p,) = simulated_roots("pea", 1, days=float(days), seed=1000 * args.seed + i, dim=2)
        p = rs.limit_laterals(p, args.laterals or SYSTEM_LATERALS)
        plants.append(dataclasses.replace(p, name=f"pea_{days:.0f}d_{i}"))
    return plants


def shared_rsml_folder() -> Path:
    """``../shared/data/rsml`` beside the repository (present on the development machine)."""
    return Path(rs.__file__).resolve().parents[1].parent / "shared" / "data" / "rsml"


def real_multi_order_files(folder: Path) -> tuple[list[tuple[Path, rs.Root]], list[tuple[Path, int]]]:
    """(files holding second-order laterals, with their deepest root; every file read, with its
    deepest order)."""
    from rootshape_jax.io import read_rsml

    found, seen = [], []
    for path in sorted(folder.rglob("*.rsml")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                roots = read_rsml(path)
            except Exception:  # noqa: BLE001 - a file without geometry is just not an example
                continue
        if not roots:
            continue
        best = max(roots, key=deepest_order)
        seen.append((path, deepest_order(best)))
        if deepest_order(best) >= 2:
            found.append((path, best))
    return found, seen


def _distances(tree, args) -> tuple[np.ndarray, dict, float]:
    start = time.perf_counter()
    D, stats = rs.pairwise_distances(tree, weights=make_weights(args), progress=not args.quiet, return_stats=True)
    D = np.asarray(D, dtype=np.float64)
    return D, stats, time.perf_counter() - start


def _comparison_figure(D3: np.ndarray, D2: np.ndarray, names: list[str]):
    from matplotlib.figure import Figure
    from scipy.cluster import hierarchy
    from scipy.spatial.distance import squareform

    from rootshape_jax.plot import plot_distance_matrix

    fig = Figure(figsize=(13.0, 4.4), layout="constrained")
    axes = fig.subplots(1, 3)
    # One row order (from depth 3) for both heat maps, so the cells compare one to one.
    Z = hierarchy.linkage(squareform(D3, checks=False), "average")
    plot_distance_matrix(D3, labels=names, linkage=Z, ax=axes[0], title="depth 3 (with second-order laterals)")
    plot_distance_matrix(D2, labels=names, linkage=Z, ax=axes[1], title="depth 2 (main root + laterals)")
    iu = np.triu_indices(len(D3), 1)
    ax = axes[2]
    ax.scatter(D2[iu], D3[iu], s=14, color="#1f77b4")
    top = float(max(D2[iu].max(), D3[iu].max())) * 1.05
    ax.plot([0, top], [0, top], color="#999999", lw=0.8, ls="--")
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_aspect("equal")
    ax.set_xlabel("distance at depth 2")
    ax.set_ylabel("distance at depth 3")
    ax.set_title("every pair of plants", fontsize=10)
    return fig


def run_whole_systems(out: Output, args) -> None:
    """The demo's whole-root-system section; skipped with a note without CPlantBox."""
    from rootshape_jax.plot import plot_geodesic

    with out.step("Whole root systems: second-order laterals (depth 3)") as sec:
        n = args.plants
        try:
            plants = pea_population(n, args)
        except rs.MissingDependencyError:
            sec.notes.append(
                "skipped the CPlantBox pea population: CPlantBox (the 'sim' extra) is not installed; "
                "pip install 'rootshape_jax[sim]' to include it."
            )
            plants = []
        if plants:
            _pea_section(out, sec, plants, args, plot_geodesic)
        _real_files_note(out, sec, args)


def _pea_section(out: Output, sec, plants: list, args, plot_geodesic) -> None:
    names = [p.name for p in plants]
    unit = plants[0].metadata.get("unit")
    rows = []
    for r, p in zip(rs.traits(plants, orders=2), plants):
        r["days"] = p.metadata.get("days")
        rows.append({rs.trait_column(k, unit): v for k, v in r.items()})
    out.write("systems_traits.csv", lambda p: write_dict_csv(p, rows))
    show = ["name", "days"] + [
        rs.trait_column(k, unit) for k in ("n_laterals_order1", "n_laterals_order2", "length_order1", "length_order2")
    ]
    out.file(
        sec,
        "systems_traits.csv",
        f"traits of the {len(plants)} simulated pea plants, with per-order columns (order 1: laterals of "
        f"the tap root, order 2: their laterals; lengths in {unit_label(unit)})",
        "table",
        html_table(show, [[r[k] for k in show] for r in rows], max_rows=12),
    )
    say(args, f"Registering every pair of {len(plants)} pea plants at depth 3, then at depth 2...")
    T = args.points
    tree3 = rs.batch(plants, n_points=T, normalise_scale=args.normalise_scale, depth=3)
    tree2 = rs.batch(plants, n_points=T, normalise_scale=args.normalise_scale)
    D3, st3, t3 = _distances(tree3, args)
    D2, st2, t2 = _distances(tree2, args)
    for D, depth in ((D3, 3), (D2, 2)):
        out.csv(
            sec,
            f"systems_distances_depth{depth}.csv",
            ["root"] + names,
            [[nm] + list(row) for nm, row in zip(names, D)],
            f"elastic distances between the pea plants at depth {depth}",
        )
    fig = _comparison_figure(D3, D2, names)
    out.figure(
        sec,
        fig,
        "systems_distances.png",
        "distance matrices at depth 3 and depth 2 (same row order, each with its own colour scale) and every "
        "pair at both depths (dashed: equal)",
    )
    iu = np.triu_indices(len(D3), 1)
    r = float(np.corrcoef(D3[iu], D2[iu])[0, 1]) if len(iu[0]) > 1 else float("nan")
    ratio = D3[iu] / np.maximum(D2[iu], np.finfo(float).tiny)
    sec.notes.append(
        f"{len(plants)} CPlantBox pea plants ({DAYS[0]:g}–{DAYS[1]:g} days, the {args.laterals or SYSTEM_LATERALS} "
        f"longest laterals of each with their own laterals; {int(sum(deepest_order(p) >= 2 for p in plants))} have "
        f"second-order laterals), T = {T}, capacities {tree3.capacities} at depth 3. Distance matrix in "
        f"{t3:.1f} s at depth 3 and {t2:.1f} s at depth 2 (same run, compilation included: "
        f"{t3 / t2:.2f}×); depth 3 / depth 2 distance ratio {fmt(ratio.min(), 3)}–{fmt(ratio.max(), 3)} "
        f"(median {fmt(np.median(ratio), 3)}), correlation {fmt(r, 3)}. DPs run: laterals "
        f"{st3.get('lateral_dp')} (skipped by the exact bound {st3.get('lateral_skipped')}), second-order "
        f"laterals {list(st3.get('deeper_dp', []))}."
    )
    # The youngest and the oldest plant: the second-order laterals grow in along the path.
    a, b = 0, len(plants) - 1
    ta, tb = rs.unstack(tree3)[a], rs.unstack(tree3)[b]
    reg = rs.register(ta, tb, weights=make_weights(args))
    sizes = None
    if args.normalise_scale:
        sizes = (rs.normalising_length(plants[a], T), rs.normalising_length(plants[b], T))
    path = rs.geodesic(ta, tb, n_steps=args.steps, weights=make_weights(args), registration=reg, sizes=sizes)
    fig, _ = plot_geodesic(
        path,
        title=f"{names[a]} → {names[b]} at depth 3 (colour = matched branch; second-order laterals in lighter shades)",
        unit=unit_label(unit),
    )
    out.figure(
        sec,
        fig,
        "systems_geodesic.png",
        f"optimal deformation of {names[a]} into {names[b]} at depth 3: each lateral keeps its colour, and each "
        "second-order lateral a lighter shade of its parent's",
    )
    sec.notes.append(f"distance {names[a]} → {names[b]}: {fmt(float(reg.distance))} at depth 3.")


def _real_files_note(out: Output, sec, args) -> None:
    from rootshape_jax.plot import plot_root

    folder = shared_rsml_folder()
    if not folder.is_dir():
        sec.notes.append(f"no folder of real RSML files at {folder}: no real multi-order file shown.")
        return
    found, seen = real_multi_order_files(folder)
    if not found:
        orders = sorted({d for _, d in seen})
        sec.notes.append(
            f"real files: none of the {len(seen)} RSML files with geometry in {folder} holds second-order "
            f"laterals (deepest lateral order found: {', '.join(map(str, orders)) or 'none'}; the SmartRoot "
            "lupin and maize tracings have first-order laterals only), so no real multi-order file is shown."
        )
        return
    path, root = found[0]
    fig, _ = plot_root(root, title=f"{path.name}: {root.name}")
    out.figure(sec, fig, "systems_real.png", f"{path.name}: a real root system with second-order laterals")
    sec.notes.append(
        f"real files: {len(found)} of {len(seen)} RSML files in {folder} hold second-order laterals; "
        f"drawn: {path.name} (deepest order {deepest_order(root)})."
    )
