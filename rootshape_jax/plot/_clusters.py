"""Distance matrices and hierarchical clustering (scipy.cluster.hierarchy) drawn for reading."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.cluster import hierarchy

from .._cluster import linkage_matrix
from ._draw import (
    NEUTRAL_COLOR,
    SLOT_PALETTE,
    add_scale_bar,
    apply_frame,
    as_drawing_list,
    base_frame,
    check_positive,
    clean_panel,
    common_unit,
    draw,
    new_figure,
    panel_offset,
    panel_size,
    resolve_projection,
    slot_color,
    subplot_kw,
    wrap_name,
)
from ._labels import check_strips, draw_strip, label_colors

# Beyond these sizes tick labels overlap; they are left out.
_MAX_TICK_LABELS = 50
_MAX_LEAF_LABELS = 80


def check_distance_matrix(D: Any, *, what: str) -> np.ndarray:
    """``D`` as a float (N, N) array, or a ValueError saying what is wrong and how to fix it."""
    D = np.asarray(D, dtype=float)
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise ValueError(f"{what}: expected a square (N, N) distance matrix, got shape {D.shape}.")
    if D.shape[0] < 2:
        raise ValueError(f"{what}: need at least 2 roots, got N = {D.shape[0]}.")
    if not np.all(np.isfinite(D)):
        raise ValueError(f"{what}: the distance matrix contains NaN or inf.")
    scale = max(float(np.abs(D).max()), 1e-300)
    if not np.allclose(D, D.T, rtol=1e-6, atol=1e-9 * scale):
        raise ValueError(
            f"{what}: the distance matrix is not symmetric (max |D - D.T| = "
            f"{np.abs(D - D.T).max():.3g}); symmetrise it with (D + D.T) / 2 if that is intended."
        )
    if np.any(D < -1e-12 * scale) or np.any(np.abs(np.diag(D)) > 1e-9 * scale):
        raise ValueError(f"{what}: distances must be >= 0 with a zero diagonal.")
    return np.clip((D + D.T) / 2, 0.0, None)


def _check_linkage(Z: Any, n: int | None, *, what: str) -> np.ndarray:
    Z = np.asarray(Z, dtype=float)
    if Z.ndim != 2 or Z.shape[1] != 4 or not hierarchy.is_valid_linkage(Z):
        raise ValueError(
            f"{what}: not a scipy linkage matrix (shape {Z.shape}); build one with "
            "scipy.cluster.hierarchy.linkage or rootshape_jax.cluster."
        )
    if n is not None and Z.shape[0] != n - 1:
        raise ValueError(f"{what}: the linkage is for {Z.shape[0] + 1} roots but D has N = {n}.")
    return Z


def _check_labels(labels, n: int, what: str) -> list[str] | None:
    if labels is None:
        return None
    labels = [str(x) for x in labels]
    if len(labels) != n:
        raise ValueError(f"{what}: {len(labels)} labels for {n} roots.")
    return labels


def plot_distance_matrix(
    D: Any,
    *,
    labels: Sequence[str] | None = None,
    linkage: Any = None,
    method: str = "average",
    ax=None,
    cmap: str = "viridis",
    show_dendrogram: bool = True,
    strips: Mapping[str, Sequence[Any]] | None = None,
    title: str | None = "Pairwise distances (ordered by hierarchical clustering)",
):
    """Heat map of an (N, N) distance matrix, rows and columns in dendrogram order.

    **Arguments**

    - `D`: symmetric distances with a zero diagonal (e.g. `rootshape_jax.pairwise_distances`).
    - `labels`: one name per root (shown when N ≤ 50).
    - `linkage`: a scipy linkage matrix to order by; default
      ``scipy.cluster.hierarchy.linkage(squareform(D), method)`` (with optimal leaf ordering
      up to N = 300).
    - `method`: linkage method when `linkage` is None (``"average"`` is UPGMA).
    - `ax`: an Axes for the heat map (then no dendrogram is drawn); a new figure when None.
    - `cmap`: colour map; `show_dendrogram`: draw the dendrogram above the heat map.
    - `strips`: ``{label name: one value per root}`` (e.g. condition, genotype): one colour
      strip per label above the heat map, in the heat map's order, with a legend (needs
      ``ax=None``).

    **Returns** ``(fig, axes)`` with ``axes = {"matrix": ax, "colorbar": cax,
    "dendrogram": dax or None, "strips": {name: Axes}, "legends": {name: Axes}}`` (a strip's
    legend is ``axes["legends"][name].get_legend()``). The order used is
    ``scipy.cluster.hierarchy.leaves_list``.
    """
    D = check_distance_matrix(D, what="plot_distance_matrix")
    n = D.shape[0]
    labels = _check_labels(labels, n, "plot_distance_matrix")
    strips = check_strips(strips, n, "plot_distance_matrix")
    if strips and ax is not None:
        raise ValueError("plot_distance_matrix: colour strips need their own figure; pass ax=None.")
    Z = linkage_matrix(D, method) if linkage is None else _check_linkage(linkage, n, what="linkage")
    order = hierarchy.leaves_list(Z)
    ordered = D[np.ix_(order, order)]

    dax = None
    sax: dict = {}
    lax: dict = {}
    if ax is None:
        ns = len(strips)
        fig = new_figure((7.0 + (2.0 if ns else 0.0), (7.4 if show_dendrogram else 6.2) + 0.3 * ns))
        heights = ([1.0] if show_dendrogram else []) + [0.18] * ns + [5.0]
        # A third column holds the strips' legends (the layout widens it to fit them).
        widths = [25, 1] + ([1] if ns else [])
        gs = fig.add_gridspec(len(heights), len(widths), height_ratios=heights, width_ratios=widths)
        row = 0
        if show_dendrogram:
            dax = fig.add_subplot(gs[0, 0])
            row = 1
        for name in strips:
            sax[name] = fig.add_subplot(gs[row, 0])
            lax[name] = fig.add_subplot(gs[row, 2])
            row += 1
        ax = fig.add_subplot(gs[row, 0])
        cax = fig.add_subplot(gs[row, 1])
    else:
        fig = ax.figure
        cax = None
    im = ax.imshow(
        ordered,
        cmap=cmap,
        vmin=0.0,
        interpolation="nearest",
        aspect="auto",
        extent=(-0.5, n - 0.5, n - 0.5, -0.5),
    )
    cbar = fig.colorbar(im, cax=cax, ax=None if cax is not None else ax)
    cbar.set_label("distance")
    cbar.outline.set_visible(False)
    if n <= _MAX_TICK_LABELS:
        names = [labels[i] if labels else str(i) for i in order]
        ax.set_xticks(range(n), names, rotation=90, fontsize=7)
        ax.set_yticks(range(n), names, fontsize=7)
    else:
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel(f"{n} roots, in dendrogram order")
    ax.tick_params(length=0)
    for spine in ax.spines.values():
        spine.set_visible(False)
    if dax is not None:
        hierarchy.dendrogram(Z, ax=dax, no_labels=True, color_threshold=-1, above_threshold_color=NEUTRAL_COLOR)
        dax.set_xlim(0, 10 * n)  # scipy puts leaf i at 10 i + 5: aligned with the cells below
        dax.set_axis_off()
    for name, sx in sax.items():
        draw_strip(sx, lax[name], [strips[name][i] for i in order], name)
        sx.set_xlim(-0.5, n - 0.5)
    if title:
        top = dax if dax is not None else (next(iter(sax.values())) if sax else ax)
        top.set_title(title, fontsize=11)
    return fig, {"matrix": ax, "colorbar": cbar.ax, "dendrogram": dax, "strips": sax, "legends": lax}


def _as_linkage(D_or_linkage: Any, method: str, what: str) -> np.ndarray:
    """A distance matrix is square, symmetric with a zero diagonal; anything else must be a
    valid linkage (a linkage's last column counts ≥ 2 members, so the two cannot be confused)."""
    arr = np.asarray(D_or_linkage, dtype=float)
    if arr.ndim == 2 and arr.shape[0] == arr.shape[1]:
        diag0 = np.all(np.abs(np.diag(arr)) <= 1e-9 * max(float(np.abs(arr).max()), 1e-300))
        if diag0 or arr.shape[1] != 4:
            return linkage_matrix(check_distance_matrix(arr, what=what), method)
    return _check_linkage(arr, None, what=what)


def _clusters(Z: np.ndarray, n_clusters: int | None) -> tuple[np.ndarray, float | None]:
    """Flat cluster ids 0..c-1 numbered left to right in the dendrogram, and a cut height."""
    n = Z.shape[0] + 1
    heights = Z[:, 2]
    if n_clusters is None:
        # scipy's / MATLAB's default colouring rule: cut at 70 % of the highest merge.
        n_clusters = int(hierarchy.fcluster(Z, 0.7 * heights.max(), criterion="distance").max())
    if not isinstance(n_clusters, (int, np.integer)) or not 1 <= n_clusters <= n:
        raise ValueError(f"n_clusters must be an integer between 1 and {n}, got {n_clusters!r}.")
    raw = hierarchy.fcluster(Z, n_clusters, criterion="maxclust")
    order = hierarchy.leaves_list(Z)
    relabel = {}
    for leaf in order:
        relabel.setdefault(raw[leaf], len(relabel))
    ids = np.array([relabel[c] for c in raw])
    cut = None
    k = len(relabel)
    if 1 < k:
        # Between the last merge inside a cluster and the first merge joining two clusters.
        h = np.sort(heights)
        below = h[n - k - 1] if k < n else 0.0
        cut = float((below + h[n - k]) / 2)
    return ids, cut


def cluster_colors(ids: np.ndarray, strip: Sequence[str] | None = None) -> list[str]:
    """One colour per flat cluster (ids 0..k-1).

    Without a label strip, the fixed categorical palette in cluster order. With one, clusters
    and label values are paired one-to-one by how many roots they share (an optimal assignment),
    and a paired cluster takes its value's strip colour: a cluster made of one condition is drawn
    in that condition's colour, so the tree and the strip read together. The other clusters take
    palette colours that no value of the strip uses.
    """
    k = int(ids.max()) + 1
    if strip is None:
        return [slot_color(c) for c in range(k)]
    from scipy.optimize import linear_sum_assignment

    by_value = label_colors(strip)
    values = list(by_value)
    shared = np.zeros((k, len(values)), dtype=int)
    for c, v in zip(ids, strip):
        shared[int(c), values.index(str(v))] += 1
    colors: list[str | None] = [None] * k
    for c, j in zip(*linear_sum_assignment(-shared)):
        if shared[c, j] > 0:
            colors[c] = by_value[values[j]]
    spare = iter([col for col in SLOT_PALETTE if col not in by_value.values()] * (k + 1))
    return [col if col is not None else next(spare) for col in colors]


def plot_dendrogram(
    D_or_linkage: Any,
    *,
    labels: Sequence[str] | None = None,
    n_clusters: int | None = None,
    method: str = "average",
    roots: Any = None,
    max_roots_per_cluster: int = 6,
    ax=None,
    linewidth: float = 1.0,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    strips: Mapping[str, Sequence[Any]] | None = None,
    title: str | None = "Hierarchical clustering of roots",
):
    """Dendrogram coloured by flat cluster, optionally with a row of roots per cluster.

    **Arguments**

    - `D_or_linkage`: an (N, N) distance matrix (linked with `method`) or a scipy linkage.
    - `labels`: one name per root for the leaves (shown when N ≤ 80).
    - `n_clusters`: number of flat clusters (``fcluster(..., criterion="maxclust")``); None
      uses scipy's default cut at 70 % of the highest merge. Clusters are numbered and coloured
      left to right; the cut is drawn as a dashed line.
    - `roots`: the N roots (batched `RootTree` or list) in the order of `D`; when given, each
      cluster gets a row with its first `max_roots_per_cluster` members (dendrogram order),
      drawn in the cluster's colour at one shared scale.
    - `ax`: an Axes for the dendrogram (only without `roots`); a new figure when None.
    - `linewidth`, `invert_y`, `projection`, `unit`: root drawing options, as in `plot_root`.
    - `strips`: ``{label name: one value per root}``: one colour strip per label under the
      leaves, with a legend (needs ``ax=None``); the leaf names then label the last strip.
      Clusters are then coloured to agree with the first strip: a cluster paired with a label
      value (one-to-one, by the roots they share) takes that value's colour (`cluster_colors`).

    **Returns** ``(fig, axes)`` with ``axes = {"dendrogram": ax, "roots": rows of Axes,
    "strips": {name: Axes}, "legends": {name: Axes}, "cluster_colors": [colour of cluster 1,
    ...]}`` (a strip's legend is ``axes["legends"][name].get_legend()``).
    """
    Z = _as_linkage(D_or_linkage, method, "plot_dendrogram")
    n = Z.shape[0] + 1
    labels = _check_labels(labels, n, "plot_dendrogram")
    strips = check_strips(strips, n, "plot_dendrogram")
    if strips and ax is not None:
        raise ValueError("plot_dendrogram: colour strips need their own figure; pass ax=None.")
    ns = len(strips)
    sax: dict = {}
    lax: dict = {}
    ids, cut = _clusters(Z, n_clusters)
    k = int(ids.max()) + 1
    colors = cluster_colors(ids, next(iter(strips.values())) if strips else None)
    drawings = None
    if roots is not None:
        if ax is not None:
            raise ValueError("plot_dendrogram: drawing `roots` needs its own figure; pass ax=None.")
        drawings = as_drawing_list(roots, what="plot_dendrogram: roots")
        if len(drawings) != n:
            raise ValueError(f"plot_dendrogram: {len(drawings)} roots for {n} leaves.")
        if not isinstance(max_roots_per_cluster, int) or max_roots_per_cluster < 1:
            raise ValueError(f"max_roots_per_cluster must be a positive integer, got {max_roots_per_cluster!r}.")
        check_positive("linewidth", linewidth)

    # Leaves under every node, to colour a link by its cluster when it stays inside one.
    members: list[np.ndarray] = [np.array([i]) for i in range(n)]
    for a, b in Z[:, :2].astype(int):
        members.append(np.concatenate([members[a], members[b]]))

    def link_color(node: int) -> str:
        c = np.unique(ids[members[node]])
        return colors[int(c[0])] if c.size == 1 else NEUTRAL_COLOR

    order = hierarchy.leaves_list(Z)
    rows: list[list] = []
    if drawings is None:
        if ax is None:
            fig = new_figure((max(6.0, min(14.0, 0.18 * n + 3)) + (2.0 if ns else 0.0), 4.2 + 0.3 * ns))
            # A second column holds the strips' legends (the layout widens it to fit them).
            gs = fig.add_gridspec(
                1 + ns, 2 if ns else 1, height_ratios=[4.0] + [0.22] * ns, width_ratios=[25, 1][: 1 + (ns > 0)]
            )
            ax = fig.add_subplot(gs[0, 0])
            for j, name in enumerate(strips):
                sax[name] = fig.add_subplot(gs[1 + j, 0])
                lax[name] = fig.add_subplot(gs[1 + j, 1])
        else:
            fig = ax.figure
    else:
        projection = resolve_projection(drawings[0].dim, projection)
        per = [order[ids[order] == c][:max_roots_per_cluster] for c in range(k)]
        ncols = max(len(p) for p in per)
        frame = base_frame(drawings, projection, False)
        w, h = panel_size(frame, 1.5)
        # Room for each member's name above its panel, on up to two lines (about 0.055 inch per
        # character at 7 pt), so long names do not run into their neighbours.
        longest = max((len(str(x)) for x in labels), default=0) if labels else 4
        w = max(w, min(0.055 * (longest + 1) / 2 + 0.05, 2.0))
        name_chars = int((w - 0.05) / 0.055)
        fig_w = max(7.0, ncols * w + 1.6)
        fig = new_figure((fig_w + (2.0 if ns else 0.0), 3.8 + 0.3 * ns + k * (h + 0.15)))
        # With strips, a last narrow column holds their legends (widened by the layout to fit).
        gs = fig.add_gridspec(
            1 + ns + k,
            ncols + (ns > 0),
            height_ratios=[3.2] + [0.22] * ns + [h] * k,
            width_ratios=[1.0] * ncols + ([0.05] if ns else []),
        )
        ax = fig.add_subplot(gs[0, :ncols])
        for j, name in enumerate(strips):
            sax[name] = fig.add_subplot(gs[1 + j, :ncols])
            lax[name] = fig.add_subplot(gs[1 + j, ncols])
        unit = unit if unit is not None else common_unit(drawings)
        for c, idx in enumerate(per):
            row = []
            for j, i in enumerate(idx):
                rax = fig.add_subplot(gs[1 + ns + c, j], **subplot_kw(projection))
                draw(
                    rax,
                    drawings[i],
                    projection=projection,
                    colors=colors[c],
                    linewidth=linewidth,
                )
                apply_frame(
                    rax,
                    frame,
                    projection=projection,
                    invert_y=invert_y,
                    offset=panel_offset(drawings[i], projection),
                )
                clean_panel(rax, projection)
                rax.set_title(wrap_name(labels[i], name_chars) if labels else f"#{i}", fontsize=7, pad=2)
                row.append(rax)
            size = int(np.sum(ids == c))
            if projection != "3d":
                row[0].set_ylabel(
                    f"cluster {c + 1}\nn = {size}",
                    color=colors[c],
                    fontsize=9,
                    rotation=0,
                    ha="right",
                    va="center",
                )
            rows.append(row)
        add_scale_bar(rows[-1][-1], frame, unit, projection=projection)

    show_labels = n <= _MAX_LEAF_LABELS
    hierarchy.dendrogram(
        Z,
        ax=ax,
        labels=labels,
        link_color_func=link_color,
        no_labels=not show_labels or bool(sax),
        leaf_rotation=90,
        leaf_font_size=max(5, min(9, int(500 / n))),
    )
    centers = 10.0 * np.arange(n) + 5.0  # scipy puts leaf i at 10 i + 5
    # A dot in its cluster's colour under every leaf: a one-root cluster has no link of its own,
    # so without it the tree would show that cluster only in the neutral colour.
    ax.scatter(centers, np.zeros(n), s=12, c=[colors[int(ids[i])] for i in order], zorder=3, clip_on=False)
    for name, sx in sax.items():
        draw_strip(sx, lax[name], [strips[name][i] for i in order], name, centers=centers, width=10.0)
        sx.set_xlim(ax.get_xlim())
    if sax and show_labels:
        last = list(sax.values())[-1]
        names = [labels[i] if labels else str(i) for i in order]
        last.set_xticks(centers, names, rotation=90, fontsize=max(5, min(9, int(500 / n))))
        last.tick_params(axis="x", length=0)
    if cut is not None:
        ax.axhline(cut, color="#999999", linestyle="--", linewidth=0.8, zorder=0)
    ax.set_ylabel("distance")
    ax.spines[["top", "right", "bottom"]].set_visible(False)
    ax.tick_params(axis="x", length=0)
    if title:
        ax.set_title(f"{title} ({k} clusters)" if k > 1 else title, fontsize=11)
    return fig, {"dendrogram": ax, "roots": rows, "strips": sax, "legends": lax, "cluster_colors": colors}
