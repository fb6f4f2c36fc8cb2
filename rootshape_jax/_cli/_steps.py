"""The analyses, each writing its tables and figures into the output folder.

Every ``run_*`` step takes the shared `Context` (so the demo computes the distances and the
mean once) and adds one section to the report.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections.abc import Sequence

import numpy as np

import rootshape_jax as rs
from rootshape_jax._learn import check_labels
from rootshape_jax.io import NORMALISED_UNIT, is_plant_system, unit_label
from rootshape_jax.io._units import PIXEL_UNITS

from ._common import PAPER_TRAITS, CLIError, fmt, make_weights, say, ticking, warn
from ._inputs import (
    Population,
    common_unit,
    covariate_columns,
    covariate_matrix,
    in_input_units,
    mean_size,
    prepare,
    to_output_roots,
    turn,
)
from ._report import Output, html_table, write_dict_csv


@dataclasses.dataclass
class Context:
    """Results carried from one step to the next (the demo reuses them)."""

    pop: Population
    distances: np.ndarray | None = None
    mean: object = None  # KarcherMean
    pca: object = None  # TangentPCA
    # The rotation that sets the mean upright like the inputs (`rootshape_jax.upright_rotation`); the roots
    # built on the mean (modes, random and predicted roots) turn with it.
    turn: object = None


@contextlib.contextmanager
def at_depth(pop: Population, what: str):
    """Turn the library's refusal of a deep tree (`NotImplementedError`: an analysis that does
    not handle second-order laterals yet) into one clear line. Written for any analysis, so
    it works unchanged once the library handles them."""
    try:
        yield
    except NotImplementedError:
        depth = int(pop.tree.depth)
        if pop.tree.virtual_main:
            raise CLIError(
                f"{what} does not work on plants' systems (--per plant) in this version of rootshape_jax "
                "yet; run it with --per root (one system per axis). distances, compare, cluster, "
                "geodesic and traits work on plants' systems."
            ) from None
        if depth <= 2:
            raise
        raise CLIError(
            f"{what} does not work on whole root systems (--depth {depth}) in this version of "
            "rootshape_jax yet; run it with --depth 2 (the default: main root + laterals). "
            "distances, compare, cluster, geodesic and traits work at every depth."
        ) from None


# Pairs per stored block with --store: at most this much work is lost to an interruption.
STORE_BLOCK = 64


# Scale bars of scale-normalised roots: "0.1 × main-root length" (the captions say
# NORMALISED_UNIT in full; a long bar label would run over the panels).
NORMALISED_BAR = "× main-root length"


def figure_unit(pop: Population) -> str:
    """The unit of drawn analysis coordinates: scale-normalised roots are in main-root lengths."""
    return NORMALISED_BAR if pop.normalised else unit_label(pop.unit)


def figure_note(pop: Population) -> str:
    """What a figure's coordinates are, for its caption."""
    return f" (coordinates {NORMALISED_UNIT})" if pop.normalised else f" (coordinates in {unit_label(pop.unit)})"


def run_distances(ctx: Context, out: Output, args) -> None:
    from rootshape_jax.plot import plot_distance_matrix

    pop = ctx.pop
    with out.step("Distance matrix") as sec:
        n = len(pop.names)
        say(args, f"Registering every pair of {n} roots ({n * (n - 1) // 2} pairs)...")
        store = getattr(args, "store", None)
        # With --store every finished block is saved atomically; a rerun computes only the rest.
        D, stats = rs.pairwise_distances(
            pop.tree,
            weights=make_weights(args),
            progress=not args.quiet,
            return_stats=True,
            store=store,
            block_size=STORE_BLOCK if store else None,
        )
        D = np.asarray(D, dtype=np.float64)
        ctx.distances = D
        out.csv(
            sec,
            "distances.csv",
            ["root"] + pop.names,
            [[n] + list(row) for n, row in zip(pop.names, D)],
            f"elastic distance between every pair of roots ({len(D)} × {len(D)})",
        )
        # Ordered by the linkage `cluster` uses (--linkage), so heat map and dendrogram agree.
        method = getattr(args, "linkage", None) or "average"
        fig, axes = plot_distance_matrix(D, labels=pop.names, strips=pop.labels or None, method=method)
        axes["colorbar"].set_ylabel(
            "distance (scale normalised)" if pop.normalised else f"distance (lengths in {unit_label(pop.unit)})"
        )
        out.figure(
            sec,
            fig,
            "distances.png",
            "heat map of the distance matrix, rows ordered by hierarchical clustering"
            + (f" (colour strips: {', '.join(pop.labels)})" if pop.labels else ""),
        )
        done = stats.get("lateral_dp")
        skipped = stats.get("lateral_skipped", stats.get("lateral_pruned"))
        note = f"{len(D) * (len(D) - 1) // 2} pairs registered"
        if done is not None and skipped is not None:
            note += (
                f"; {done} lateral-pair alignments computed, {skipped} skipped by an exact "
                "bound (they could not change the result)"
            )
        if store:
            note += (
                f"; --store {store}: {stats['blocks_from_store']} of {stats['blocks']} blocks "
                f"of {STORE_BLOCK} pairs read from earlier runs, {stats['blocks_computed']} computed"
            )
        sec.notes.append(note + ".")
        if not pop.normalised:
            # The metric's shape terms are lengths (|q|² of a branch is its length); its
            # lateral-position term is a fraction of the main root, unitless.
            sec.notes.append(
                f"without scale normalisation the shape terms grow with the length unit ({unit_label(pop.unit)} "
                "here) while the lateral-position term is unitless, so the balance of the terms, and the "
                "distances, depend on the unit: compare distances computed in the same unit."
            )


def run_mean(ctx: Context, out: Output, args) -> None:
    import optimistix as optx

    from rootshape_jax.plot import plot_energy_trace, plot_mean

    pop = ctx.pop
    with out.step("Mean root (Karcher mean)") as sec:
        say(
            args,
            f"Fitting the mean root of {len(pop.names)} roots (each step registers every root "
            "onto the current mean)...",
        )
        with at_depth(pop, "the mean root (and the modes, random roots and regression built on it)"):
            km = rs.karcher_mean(
                pop.tree,
                weights=make_weights(args),
                distances=ctx.distances,
                max_steps=args.max_steps,
                throw=False,
                progress=not args.quiet,
            )
        ctx.mean = km
        ctx.turn = rs.upright_rotation(km.mean, pop.tree)
        mean_tree = turn(km.mean, ctx.turn)
        trace = np.asarray(km.energy_trace, dtype=np.float64)
        mean_roots = to_output_roots(in_input_units(rs.stack([mean_tree]), pop, mean_size(km.mean, pop)), pop, ["mean"])
        out.rsml(sec, mean_roots, "mean.rsml", "the mean root (RSML)", unit=pop.output_unit)
        out.csv(
            sec, "mean_energy.csv", ["step", "energy"], list(enumerate(trace)), "Karcher energy F(μ) after each step"
        )
        fig, _ = plot_mean(
            pop.tree,
            mean_tree,
            names=pop.names,
            max_samples=len(pop.names),
            title=f"Mean of {len(pop.names)} roots",
            unit=figure_unit(ctx.pop),
        )
        out.figure(
            sec,
            fig,
            "mean.png",
            "input roots (left, named) and their mean root (right, at its own scale)" + figure_note(pop),
        )
        fig, _ = plot_energy_trace(trace)
        out.figure(sec, fig, "mean_energy.png", "mean squared distance to the mean at each solver step (must fall)")
        n_drop = int(np.sum(np.asarray(km.dropped)))
        n_kept = int(np.sum(np.asarray(km.mean.mask)))
        branch = ("axis", "axes") if pop.tree.virtual_main else ("lateral", "laterals")
        sec.notes.append(
            f"{int(km.steps)} steps, final energy {fmt(trace[-1])} (start {fmt(trace[0])}); "
            f"started from root {pop.names[km.init_index]!r} (a central root: the medoid, or of several "
            f"central starts the one whose warm-up reached the lowest energy); {n_drop} near-empty "
            f"slot{'s' * (n_drop != 1)} dropped; mean has {n_kept} {branch[n_kept != 1]}."
        )
        if not bool(np.asarray(km.result == optx.RESULTS.successful)):
            sec.notes.append(f"the solver stopped at the step limit ({args.max_steps}) before converging.")


def run_pca(ctx: Context, out: Output, args) -> None:
    from rootshape_jax.plot import plot_explained_variance, plot_modes

    with out.step("Modes of variation (tangent PCA)") as sec, ticking(args, "tangent PCA and modes"):
        with at_depth(ctx.pop, "tangent PCA"):
            pc = rs.tangent_pca(ctx.mean)
        ctx.pca = pc
        eig = np.asarray(pc.eigenvalues, dtype=np.float64)
        ratio = np.asarray(pc.explained_variance_ratio, dtype=np.float64)
        rows = [[i + 1, eig[i], ratio[i], float(np.sum(ratio[: i + 1]))] for i in range(len(eig))]
        header = ["component", "variance", "explained_ratio", "cumulative_ratio"]
        out.csv(
            sec,
            "explained_variance.csv",
            header,
            rows,
            "variance explained by each principal component",
            table_html=html_table(header, rows, max_rows=8),
        )
        kept = max(int(pc.n_components), 1)
        # Every kept component gets its bar (the plot's default stops at 30).
        fig, _ = plot_explained_variance(eig, max_components=kept)
        out.figure(
            sec,
            fig,
            "explained_variance.png",
            f"variance explained by each of the {kept} kept components, and cumulated",
        )
        _pca_scores(ctx, out, sec, pc, kept)
        n_modes = max(1, min(args.modes, len(eig)))
        alphas = [-2.0, -1.0, 0.0, 1.0, 2.0]
        trees = turn(rs.modes(pc, alphas, component=list(range(n_modes))), ctx.turn)
        fig, _ = plot_modes(trees, alphas, explained=ratio[:n_modes], unit=figure_unit(ctx.pop))
        out.figure(
            sec,
            fig,
            "modes.png",
            f"first {n_modes} modes: mean ± 1 and 2 standard deviations along each component" + figure_note(ctx.pop),
        )
        sec.notes.append(
            f"{pc.n_components} components explain {100 * pc.variance:.0f} % of the variance "
            f"(first: {100 * ratio[0]:.1f} %)."
        )


def _pca_scores(ctx: Context, out: Output, sec, pc, kept: int) -> None:
    """Each root's scores on the kept components (CSV, with the roots' labels) and the first
    two as a scatter plot coloured by the --by label (default condition)."""
    from rootshape_jax.plot import plot_pca_scores

    pop = ctx.pop
    scores = np.asarray(pc.scores)[:, :kept]  # in the computation's precision (`cell`)
    header = ["root", *pop.labels, *(f"PC{k + 1}" for k in range(kept))]
    rows = [[name, *(v[i] for v in pop.labels.values()), *scores[i]] for i, name in enumerate(pop.names)]
    out.csv(
        sec,
        "pca_scores.csv",
        header,
        rows,
        f"each root's score on the {kept} kept component{'s' * (kept != 1)}, in standard deviations of that "
        "component (mean 0 and variance 1 over the roots): the coefficients rootshape_jax.reconstruct and "
        "rootshape_jax.project use",
        table_html=html_table(header, rows, max_rows=8),
    )
    if kept < 2:
        sec.notes.append("one component is kept, so no score plot (pca_scores.png needs two).")
        return
    fig, _ = plot_pca_scores(
        pc,
        pop.conditions,
        names=pop.names,
        label_name=pop.label_name,
        title=f"{len(pop.names)} roots on the first two principal components",
    )
    by = f", coloured by {pop.label_name}" if pop.conditions is not None else ""
    out.figure(sec, fig, "pca_scores.png", f"each root's scores on the first two components{by} (pca_scores.csv)")


def run_sample(ctx: Context, out: Output, args) -> None:
    import jax

    from rootshape_jax.plot import plot_samples_by_distance

    pop, pc = ctx.pop, ctx.pca
    with out.step("Random roots from the fitted model") as sec, ticking(args, "random roots"):
        n, m = args.n, pc.n_components
        # Random coefficients b ~ N(0, I) (as `rootshape_jax.sample`), kept so that each root's
        # distance to the mean in the model, sqrt(sum_i sigma_i b_i^2), needs no registration.
        key = jax.random.key(args.seed)
        if args.truncate is None:
            b = jax.random.normal(key, (n, m), pc.mean.q0.dtype)
        else:
            b = jax.random.truncated_normal(key, -args.truncate, args.truncate, (n, m), pc.mean.q0.dtype)
        trees = turn(rs.reconstruct(pc, b), ctx.turn)
        sigma = np.asarray(pc.eigenvalues, np.float64)[:m]
        d = np.sqrt(np.sum(np.asarray(b, np.float64) ** 2 * sigma, axis=1))
        names = [f"random_{i:03d}" for i in range(n)]
        roots = to_output_roots(in_input_units(trees, pop, mean_size(ctx.mean.mean, pop)), pop, names)
        out.rsml(sec, roots, "random_roots.rsml", f"{n} random roots (RSML)", unit=pop.output_unit)
        out.csv(
            sec,
            "random_roots.csv",
            ["root", "model_distance_to_mean"],
            list(zip(names, d)),
            "distance of each random root to the mean in the PCA model",
        )
        fig, _ = plot_samples_by_distance(trees, d, n_groups=min(3, n), unit=figure_unit(ctx.pop))
        out.figure(
            sec,
            fig,
            "random_roots.png",
            "random roots, in rows of increasing distance to the mean (in the PCA model)" + figure_note(pop),
        )
        sec.notes.append(
            f"coefficients drawn from N(0, 1) on the {m} kept components"
            + (f", truncated to ±{args.truncate}" if args.truncate else "")
            + f", seed {args.seed}; "
            "the distance to the mean is measured in the model, sqrt(Σ σ_i b_i²)."
        )


def trait_matrix(roots, names: Sequence[str] = PAPER_TRAITS) -> np.ndarray:
    return np.array([[float(r[k]) for k in names] for r in rs.traits(roots)], dtype=np.float64)


#: Mean relative miss of a requested trait, measured on the predicted roots, above which
#: `regress` says the roots do not have the traits asked for.
REGRESSION_MISS = 0.25


def run_regress(ctx: Context, out: Output, args) -> None:
    from rootshape_jax.plot import plot_regression_sweep

    pop = ctx.pop
    with out.step("Roots predicted from traits (regression)") as sec, ticking(args, "regression"):
        # Traits in the input's units, measured on the roots as read. With scale normalisation
        # the model predicts the shape, and each predicted root is scaled to its requested
        # main-root length (so that trait is matched exactly by construction).
        # Extra covariates (regress --by): numeric label columns of the metadata table.
        extra = covariate_columns(args)
        T = trait_matrix(pop.roots)
        P = np.hstack([T, covariate_matrix(pop.roots, extra)]) if extra else T
        names_all = list(PAPER_TRAITS) + extra
        reg = rs.TraitRegression.fit(ctx.pca, None, traits=(), covariates=P, covariate_names=names_all)

        def predict(values: np.ndarray, names: list[str]):
            with warnings.catch_warnings():  # said below, against the inputs' range
                warnings.simplefilter("ignore", rs.ExtrapolationWarning)
                trees = turn(reg.synthesize(values), ctx.turn)
            if pop.normalised:
                lengths = np.linalg.norm(np.diff(np.asarray(trees.main, np.float64), axis=1), axis=-1).sum(-1)
                trees = in_input_units(trees, pop, values[:, 0] / np.maximum(lengths, 1e-12))
            return trees, to_output_roots(trees, pop, names)

        # How well the model reproduces the training roots' own traits.
        _, fitted = predict(P, [f"fit_{i}" for i in range(len(P))])
        got = trait_matrix(fitted)
        report = []
        for j, name in enumerate(PAPER_TRAITS):
            y, yhat = T[:, j], got[:, j]
            ss = float(np.sum((y - y.mean()) ** 2))
            r2 = 1.0 - float(np.sum((yhat - y) ** 2)) / ss if ss > 0 else float("nan")
            rel = float(np.mean(np.abs(yhat - y) / np.maximum(np.abs(y), 1e-12)))
            report.append([name, r2, rel])
        header = ["trait", "r2_requested_vs_measured", "mean_relative_error"]
        out.csv(
            sec,
            "regression_report.csv",
            header,
            report,
            "traits requested (those of the input roots) vs traits measured on the predicted roots",
            table_html=html_table(header, report),
        )

        if getattr(args, "requested_values", None) is not None:
            values, vary = args.requested_values, None
            lo, hi = P.min(axis=0), P.max(axis=0)
            outside = [
                f"{name} {v:.4g} (the inputs' range: {lo[j]:.4g} to {hi[j]:.4g})"
                for j, name in enumerate(names_all)
                for v in values[:, j]
                if not lo[j] <= v <= hi[j]
            ]
            if outside:
                warn(
                    f"requested traits outside the inputs' range: {'; '.join(outside[:5])}"
                    + (f"; and {len(outside) - 5} more" if len(outside) > 5 else "")
                    + ". The linear model extrapolates there; compare the requested and measured columns "
                    "of predicted_roots.csv."
                )
        else:
            # Sweep one trait from its 10th to its 90th percentile, the others at their median.
            vary = PAPER_TRAITS.index(args.vary)
            values = np.tile(np.median(P, axis=0), (5, 1))
            values[:, vary] = np.percentile(P[:, vary], [10, 30, 50, 70, 90])
        names = [f"predicted_{i:03d}" for i in range(len(values))]
        trees, roots = predict(values, names)
        out.rsml(
            sec,
            roots,
            "predicted_roots.rsml",
            f"{len(roots)} roots predicted from requested traits (RSML)",
            unit=pop.unit,
        )
        measured = trait_matrix(roots)
        for j, name in enumerate(PAPER_TRAITS):
            if vary is not None and j != vary:
                continue  # traits held at their median are not requested
            # Relative to the requested value, or to the inputs' typical value where that is ~0.
            scale = np.maximum(np.abs(values[:, j]), np.median(np.abs(T[:, j])))
            miss = float(np.mean(np.abs(measured[:, j] - values[:, j]) / np.maximum(scale, 1e-12)))
            if miss > REGRESSION_MISS:
                warn(
                    f"the predicted roots miss the requested {name.replace('_', ' ')} by {100 * miss:.0f} % on "
                    f"average (requested vs measured in predicted_roots.csv; on the input roots the model "
                    f"reproduces it with R² {fmt(report[j][1])}): treat these roots as the model's trend, "
                    "not as roots with those traits."
                )
        rows = [[n] + list(v) + list(m) for n, v, m in zip(names, values, measured)]
        header = (
            ["root"]
            + [f"requested_{rs.trait_column(k, pop.unit)}" for k in names_all]
            + [f"measured_{rs.trait_column(k, pop.unit)}" for k in PAPER_TRAITS]
        )
        out.csv(sec, "predicted_roots.csv", header, rows, "requested and measured traits of each predicted root")
        k = 0 if vary is None else vary
        fig, _ = plot_regression_sweep(
            trees,
            values[:, k],
            trait_name=PAPER_TRAITS[k].replace("_", " "),
            unit=unit_label(pop.unit),
            trait_unit=unit_label(pop.unit) if k < len(PAPER_TRAITS) else None,
            measured=measured[:, k],
        )
        what = (
            "requested" if vary is None else f"{PAPER_TRAITS[k].replace('_', ' ')} varied, other traits at their median"
        )
        out.figure(sec, fig, "predicted_roots.png", f"roots predicted from traits ({what}); measured value below")
        if pop.normalised:
            sec.notes.append(
                "shapes were compared at equal main-root length; each predicted root is scaled to its "
                "requested main-root length, so that trait matches by construction."
            )


def cluster_number(label: int) -> int:
    """The number a cluster has in every output: 1, 2, ... left to right in the dendrogram,
    as `rootshape_jax.plot.plot_dendrogram` labels and colours them (`Clustering.labels` + 1)."""
    return int(label) + 1


def run_cluster(ctx: Context, out: Output, args) -> None:
    from rootshape_jax.plot import plot_dendrogram

    pop = ctx.pop
    with out.step("Clusters and classification") as sec, ticking(args, "clusters"):
        D = ctx.distances
        known = sorted(set(pop.conditions)) if pop.conditions else []
        k = args.clusters or (len(known) if len(known) >= 2 else 2)
        k = min(k, len(pop.names))
        # One clustering for the CSV, the table and the figure: the figure is drawn from its
        # linkage with its number of clusters, so leaf order and cluster numbers are the same.
        cl = rs.cluster(D, n_clusters=k, method=args.linkage)
        numbers = [cluster_number(c) for c in cl.labels]
        header = ["root", "cluster"] + ([pop.label_name] if pop.conditions else [])
        rows = [
            [n, c] + ([pop.conditions[i]] if pop.conditions else []) for i, (n, c) in enumerate(zip(pop.names, numbers))
        ]
        item = out.csv(
            sec,
            "clusters.csv",
            header,
            rows,
            f"cluster of each root ({cl.n_clusters} clusters, {args.linkage} linkage; numbered "
            "left to right in the dendrogram)",
        )
        fig, _ = plot_dendrogram(
            cl.linkage,
            labels=pop.names,
            n_clusters=cl.n_clusters,
            roots=pop.tree,
            strips=pop.labels or None,
            unit=figure_unit(pop),
        )
        out.figure(
            sec,
            fig,
            "dendrogram.png",
            "dendrogram of the distance matrix, coloured by cluster, with members of each cluster",
        )
        if len(known) >= 2:
            # Which conditions ended up in which cluster (the CSV has the same per root).
            cond, num = np.asarray(pop.conditions), np.asarray(numbers)
            groups = [cluster_number(g) for g in range(cl.n_clusters)]
            table = [[c] + [int(np.sum((cond == c) & (num == g))) for g in groups] for c in known]
            item.html = html_table([pop.label_name] + [f"cluster {g}" for g in groups], table)
            acc_rows = []
            for rule, label in (("nearest_neighbour", "nearest neighbour"), ("nearest_mean", "nearest class mean")):
                res = rs.loo_accuracy(D, np.asarray(pop.conditions), rule=rule)
                acc_rows.append([label, res["accuracy"], int(np.sum(res["correct"])), len(pop.names)])
            header = ["rule", "accuracy", "correct", "roots"]
            out.csv(
                sec,
                "classification.csv",
                header,
                acc_rows,
                f"leave-one-out classification of {pop.label_name} ({', '.join(known)}) from distances alone",
                table_html=html_table(header, acc_rows),
            )
            sec.notes.append(
                "classification accuracy (leave-one-out): "
                + "; ".join(f"{r[0]} {100 * r[1]:.0f} %" for r in acc_rows)
                + f" (chance ≈ {100 / len(known):.0f} %)."
            )


def run_traits(roots: list, out: Output, args) -> None:
    with out.step("Root traits") as sec:
        unit = common_unit(roots)
        window = getattr(args, "angle_window", None)
        if window is not None and unit is None:
            raise CLIError(
                f"--angle-window {window:g} is a length in the roots' unit, and these roots are in different "
                "units; convert them to one with --unit (and --pixel-size for pixels) first."
            )
        if unit is None:
            warn(
                "the roots are in different units ("
                + ", ".join(sorted({str(r.metadata.get("unit")) for r in roots}))
                + "); trait columns name no unit (see the unit column). Convert them to one unit with "
                "--unit, or analyse them separately."
            )
        rows = []
        # --depth D: per-order columns for the lateral orders the analysis keeps (default: the
        # deepest present): 1 … D−1, or 1 … D−2 for plants, whose level 1 is their axes.
        depth = getattr(args, "depth", None)
        plants = any(is_plant_system(r) for r in roots)
        orders = None if depth is None else max(depth - (2 if plants else 1), 0)
        flat = all(root.dim == 2 for root in roots)
        if window is None and unit is not None and unit.lower() in PIXEL_UNITS:
            sec.notes.append(
                "insertion angles come from each lateral's first segment, a few pixels long on pixel "
                "tracings, so they take few values (e.g. 45, 90 degrees); set --angle-window (e.g. 20, "
                "in pixels) to measure them over a chord, or --pixel-size to work in mm."
            )
        for r, root in zip(rs.traits(roots, orders=orders, window=window), roots):
            if flat:
                del r["convex_hull_volume"]  # NaN for every 2D tracing: no column
            for key in ("condition", *root.metadata.get("label_columns", ()), "unit", "source_file"):
                if key in root.metadata:
                    r[key] = root.metadata[key]
            # Every length column names its unit: main_length_mm, convex_hull_area_px2, ...
            rows.append({rs.trait_column(k, unit): v for k, v in r.items()})
        out.write("traits.csv", lambda p: write_dict_csv(p, rows))
        show = [
            rs.trait_column(k, unit)
            for k in ("name", *(("n_axes",) if plants else ()), "main_length", "n_laterals", "mean_lateral_length")
            + ("total_length", "depth", "width")
        ]
        out.file(
            sec,
            "traits.csv",
            f"architecture traits of the {len(rows)} input {'plants' if plants else 'roots'} "
            + (
                f"(lengths in {unit_label(unit)}; column names carry the unit)"
                if unit is not None
                else "(the roots are in different units: each row's lengths are in its unit column)"
            ),
            "table",
            html_table(show, [[r[k] for k in show] for r in rows], max_rows=10),
        )


def run_geodesic(a_root, b_root, out: Output, args) -> None:
    from rootshape_jax.plot import plot_geodesic

    pop = prepare([a_root, b_root], args, min_roots=2)
    pair = pop.roots
    with out.step("Geodesic (optimal deformation)") as sec, ticking(args, "registering the pair and drawing the path"):
        a, b = rs.unstack(pop.tree)
        reg = rs.register(a, b, weights=make_weights(args))
        sizes = None
        if pop.normalised and not pop.mixed_units:
            # The lengths batch() divided out (a plant's: its longest axis), so the path is
            # scaled back exactly: it starts at a and ends at b, in the input's units.
            sizes = tuple(rs.normalising_length(r, args.points) for r in pair)
        # in_place: the registration's rotation is undone along the path, so it ends at b as given.
        path_out = rs.geodesic(
            a, b, n_steps=args.steps, weights=make_weights(args), registration=reg, in_place=True, sizes=sizes
        )
        names = [f"step_{i:02d}" for i in range(args.steps)]
        for i, r in enumerate(to_output_roots(path_out, pop, names)):
            out.rsml(None, [r], f"geodesic_step_{i:02d}.rsml", "", unit=pop.output_unit)
        out.file(
            sec,
            "geodesic_step_00.rsml",
            f"each step of the deformation as RSML: geodesic_step_00.rsml … geodesic_step_{args.steps - 1:02d}.rsml",
        )
        fig, _ = plot_geodesic(
            path_out,
            title=f"{pair[0].name} → {pair[1].name}: optimal deformation (colour = corresponding lateral)",
            unit=figure_unit(pop) if pop.mixed_units else unit_label(pop.unit),
        )
        out.figure(
            sec,
            fig,
            "geodesic.png",
            f"optimal deformation of {pair[0].name} into {pair[1].name}, one colour per matched lateral",
        )
        sec.notes.append(f"elastic distance {pair[0].name} → {pair[1].name}: {fmt(float(reg.distance))}.")


def group_labels(pop: Population, command: str = "compare") -> list[str]:
    """The groups of `compare` (the classes of `learn-weights`): the --by label (default
    condition), at least two of them."""
    if pop.conditions is None:
        table = "--labels" if command == "learn-weights" else "--metadata"
        raise CLIError(
            f"{command} needs a {'class' if command == 'learn-weights' else 'group'} for every root: give "
            f"{table} TABLE.csv --by COLUMN (or roots that carry a 'condition')."
        )
    labels = [str(c) for c in pop.conditions]
    if command == "learn-weights":
        return labels  # learn_weights names its own problems with classes (LabelError)
    groups = sorted(set(labels))
    if len(groups) < 2:
        raise CLIError(
            f"--by {pop.label_name}: every root has the same value ({groups[0]!r}); comparing needs at least two groups."
        )
    if len(groups) >= len(labels):
        raise CLIError(f"--by {pop.label_name}: every root is its own group; groups need at least two members to test.")
    alone = [g for g in groups if labels.count(g) == 1]
    if alone:
        # PERMANOVA runs (its permutations move every root), but a one-root group has no spread
        # of its own, and its pairwise tests have almost no permutations.
        warn(
            f"--by {pop.label_name}: group(s) {', '.join(map(repr, alone))} have one root; their tests "
            "say little (a one-root group has no spread of its own). Add roots or merge groups."
        )
    return labels


def permanova_text(label: str, rows: list[list]) -> str:
    """The PERMANOVA table as markdown (printed and written to permanova.md)."""
    lines = [
        f"| test ({label}) | roots | pseudo-F | R² | p | p (Holm) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for test, n, f, r2, p, q in rows:
        lines.append(f"| {test} | {n} | {f:.3f} | {r2:.3f} | {p:.4f} | {'' if q is None else f'{q:.4f}'} |")
    return "\n".join(lines)


def run_compare(ctx: Context, out: Output, args) -> None:
    from rootshape_jax.plot import plot_mds

    pop = ctx.pop
    labels = group_labels(pop)
    D = ctx.distances
    with out.step(f"Group comparison by {pop.label_name}") as sec, ticking(args, "PERMANOVA and MDS"):
        say(args, f"PERMANOVA with {args.permutations} permutations, overall and for every pair of groups...")
        overall = rs.permanova(D, labels, permutations=args.permutations, seed=args.seed)
        pairs = rs.pairwise_permanova(D, labels, permutations=args.permutations, seed=args.seed + 1)
        counts = {g: labels.count(g) for g in sorted(set(labels))}
        rows = [
            [
                f"all groups ({', '.join(f'{g} n={c}' for g, c in counts.items())})",
                len(labels),
                overall.pseudo_f,
                overall.r2,
                overall.p_value,
                None,
            ]
        ]
        rows += [
            [f"{t.group_a} vs {t.group_b}", t.n_a + t.n_b, t.pseudo_f, t.r2, t.p_value, t.p_adjusted] for t in pairs
        ]
        header = ["test", "roots", "pseudo_F", "R2", "p_value", "p_holm"]
        out.csv(
            sec,
            "permanova.csv",
            header,
            rows,
            f"PERMANOVA of the distances by {pop.label_name} ({args.permutations} permutations, seed "
            f"{args.seed}); pairwise p-values adjusted with Holm's method (family-wise error)",
            table_html=html_table(header, rows),
        )
        text = permanova_text(pop.label_name, rows)
        out.write("permanova.md", lambda p: p.write_text(text + "\n", encoding="utf-8"))
        out.file(sec, "permanova.md", "the same table in markdown")
        print(text)
        emb = rs.mds(D, n_components=2)
        ratio = np.asarray(emb.proportion_explained)
        out.csv(
            sec,
            "mds.csv",
            ["root", pop.label_name, "mds_1", "mds_2"],
            [[n, g, *xy] for n, g, xy in zip(pop.names, labels, np.asarray(emb.embedding))],
            "classical MDS coordinates of each root (in distance units)",
        )
        fig, _ = plot_mds(
            emb.embedding,
            labels,
            names=pop.names,
            explained=ratio,
            label_name=pop.label_name,
            title=f"{len(labels)} roots by {pop.label_name} (classical MDS of the elastic distances)",
        )
        out.figure(sec, fig, "mds.png", f"roots in two dimensions (classical MDS), coloured by {pop.label_name}")
        eig = np.asarray(emb.eigenvalues)
        positive = float(np.sum(eig[eig > 0]))
        negative = float(-np.sum(eig[eig < 0]))
        note = (
            f"PERMANOVA by {pop.label_name}: pseudo-F {overall.pseudo_f:.3f}, R² {overall.r2:.3f}, "
            f"p = {overall.p_value:.4f} ({args.permutations} permutations). MDS axes 1-2 show "
            f"{100 * ratio.sum():.0f} % of the positive eigenvalues"
        )
        if negative > 1e-9 * positive:
            note += (
                f" (the negative eigenvalues sum to {100 * negative / positive:.1f} % of the positive ones: "
                "the distances are not exactly Euclidean)"
            )
        sec.notes.append(note + ".")


def _penalty(values: tuple[float, ...]) -> float | list[float]:
    # One value is used as given; several go to the inner cross-validation as a list.
    return values[0] if len(values) == 1 else list(values)


def run_learn_weights(ctx: Context, out: Output, args) -> None:
    """Learn λ from the --by labels, then score it by nested cross-validation (held-out folds)."""
    import matplotlib.pyplot as plt

    pop = ctx.pop
    labels = group_labels(pop, "learn-weights")
    # Classes too small for the folds are refused now, not after learning (LabelError).
    check_labels(labels, len(labels), min_per_class=args.folds or 2)
    start = make_weights(args)
    with out.step(f"Learned metric weights (classes: {pop.label_name})") as sec:
        say(args, f"Learning the weights from {len(labels)} roots ({len(set(labels))} classes)...")
        with at_depth(pop, "learn-weights"):
            res = rs.learn_weights(
                pop.tree,
                labels,
                weights=start,
                max_reregistrations=args.reregistrations,
                regularisation=_penalty(args.regularisation),
                progress=not args.quiet,
            )
        # The terms, then (λs, λp) per order from the second where --level-weights gave them.
        learned, given = res.weights.to_dict(), start.to_dict()
        # In the computation's precision, so a float32 0.02 is written as 0.02 (`cell`).
        real = np.float64 if getattr(args, "float64", False) else np.float32
        rows = [[name, real(given[name]), real(v)] for name, v in learned.items()]
        header = ["term", "start", "learned"]
        out.csv(
            sec,
            "weights.csv",
            header,
            rows,
            "metric weights: the starting (given) values and the learned ones (lateral held fixed: "
            "only ratios matter); the other commands take this file: --weights weights.csv",
            table_html=html_table(header, rows),
        )
        from matplotlib.ticker import MaxNLocator

        fig, ax = plt.subplots(figsize=(4.5, 3.2))
        loss = np.asarray(res.loss_trace)
        x = np.arange(len(loss))
        kept = res.kept()
        best = loss[np.maximum.accumulate(np.where(kept, x, 0))]  # the last kept entry's loss
        ax.step(x, best, where="post", color="C0", label="best so far")
        ax.plot(x[kept], loss[kept], "o", color="C0", label="kept")
        if not kept.all():
            ax.plot(x[~kept], loss[~kept], "o", mfc="none", color="C3", label="tried, not kept")
        ax.legend(fontsize="small", frameon=False)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # registrations are whole numbers
        ax.set_xlim(-0.5, max(len(loss) - 1, 1) + 0.5)  # whole-number ticks for a one-entry trace too
        ax.set_xlabel("registration (0 = starting weights)")
        ax.set_ylabel("soft nearest-neighbour loss")
        ax.set_title("learning the weights")
        fig.tight_layout()
        out.figure(
            sec,
            fig,
            "loss_trace.png",
            "loss at the registered distances after each re-registration; a try whose loss was not "
            "below the best so far is not kept (the fit steps back toward the best weights or stops)",
        )
        w = ",".join(f"{float(v):.4g}" for _, v in res.weights.items()) + " (main, lateral, position, thickness)"
        if res.weights.deeper:
            w += ", --level-weights " + ";".join(f"{float(ls):.4g},{float(lp):.4g}" for ls, lp in res.weights.deeper)
        sec.notes.append(
            f"learned weights {w}; status {res.status} after "
            f"{res.n_reregistrations} re-registrations and {res.steps} optimiser steps (regularisation "
            f"{res.regularisation:g}). Accuracy on these same roots would flatter the weights: "
            + (
                "see the cross-validation below."
                if args.folds
                else "run with --folds K (K >= 2) to measure it honestly."
            )
        )
        if args.folds:
            splits = f"{args.folds} folds" + (f", {args.repeats} repeats" if args.repeats > 1 else "")
            say(args, f"Nested cross-validation ({splits}): learning on the training folds only...")
            try:
                cv = rs.nested_cv_accuracy(
                    pop.tree,
                    labels,
                    n_folds=args.folds,
                    seed=args.seed,
                    n_repeats=args.repeats,
                    weights=start,
                    max_reregistrations=args.reregistrations,
                    regularisation=_penalty(args.regularisation),
                    progress=not args.quiet,
                )
            except rs.LabelError as e:
                sec.notes.append(f"cross-validation skipped: {e}")
                return
            header = [
                "repeat",
                "fold",
                "held_out",
                "learned_1nn",
                "learned_class_mean",
                "start_1nn",
                "start_class_mean",
            ]
            header += ["learned_log_loss", "start_log_loss"]
            # The learned weights (lateral is held fixed), every order's where they are learned.
            names = [k for k in cv.weights[0] if k != "lateral"]
            header += [f"lambda_{k}" for k in names]
            cv_rows = [
                [cv.repeats[f] + 1, f % args.folds + 1, len(cv.folds[f]), cv.learned_nn[f], cv.learned_mean[f]]
                + [cv.paper_nn[f], cv.paper_mean[f], cv.learned_log_loss[f], cv.paper_log_loss[f]]
                + [cv.weights[f][k] for k in names]
                for f in range(len(cv.folds))
            ]
            s = cv.summary()
            scores = ("learned_nn", "learned_mean", "paper_nn", "paper_mean", "learned_log_loss", "paper_log_loss")
            # Over every fold of every repeat; a root is held out once per repeat.
            cv_rows.append(["", "mean", sum(len(f) for f in cv.folds)] + [s[k][0] for k in scores] + [""] * len(names))
            cv_rows.append(["", "sd", ""] + [s[k][1] for k in scores])
            cv_rows[-1] += [""] * len(names)
            out.csv(
                sec,
                "cross_validation.csv",
                header,
                cv_rows,
                f"scores on held-out roots, {args.folds} stratified folds (seed {args.seed}"
                + (
                    f"; {args.repeats} repeats, seeds {args.seed}–{args.seed + args.repeats - 1}"
                    if args.repeats > 1
                    else ""
                )
                + "): weights "
                "learned on the other folds vs the starting weights; 1-NN and nearest-class-mean "
                "accuracy, and the NCA log-loss the learning minimises (lower is better); mean and sd "
                "over every fold (held_out: roots held out, once per repeat)",
                # The mean and sd first: the report's table shows the first 20 rows only.
                table_html=html_table(header, cv_rows[-2:] + cv_rows[:-2]),
            )
            comparison = cv.fold_comparison()  # folds better / the same / worse, per score
            t_tests = cv.t_tests()
            sec.notes.append(
                "held-out accuracy (mean ± sd over folds): learned "
                f"1-NN {100 * s['learned_nn'][0]:.0f} ± {100 * s['learned_nn'][1]:.0f} %, class mean "
                f"{100 * s['learned_mean'][0]:.0f} ± {100 * s['learned_mean'][1]:.0f} %; starting weights "
                f"1-NN {100 * s['paper_nn'][0]:.0f} ± {100 * s['paper_nn'][1]:.0f} %, class mean "
                f"{100 * s['paper_mean'][0]:.0f} ± {100 * s['paper_mean'][1]:.0f} %. Held-out log-loss "
                f"(lower is better): learned {s['learned_log_loss'][0]:.3f}, starting weights "
                f"{s['paper_log_loss'][0]:.3f}. Folds where the learned weights do better / the same / worse: "
                + "; ".join(
                    f"{name} {' / '.join(map(str, comparison[key]))}"
                    for name, key in (("1-NN", "nn"), ("class mean", "mean"), ("log-loss", "log_loss"))
                )
                + ". Corrected paired t-test over the folds (Nadeau & Bengio; two-sided, per score): "
                + "; ".join(
                    f"{name} p = {t_tests[key].p_value:.3g}"
                    if t_tests[key].p_value == t_tests[key].p_value
                    else f"{name} p undefined (every fold differs by the same amount)"
                    for name, key in (("1-NN", "nn"), ("class mean", "mean"), ("log-loss", "log_loss"))
                )
                + "."
            )
