"""Group labels in figures: colour strips beside heat maps and dendrograms, MDS scatter plots."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._mds import MDS
from .._pca import TangentPCA
from ._draw import as_float_array, new_figure

# Categorical colours (matplotlib's tab10, then tab20's lighter halves, without their greys,
# which read as the dendrogram's neutral links): distinct, print-safe.
_GROUP_COLORS = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#d62728",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#bcbd22",
    "#17becf",
    "#aec7e8",
    "#ffbb78",
    "#98df8a",
    "#ff9896",
    "#c5b0d5",
    "#c49c94",
    "#f7b6d2",
    "#dbdb8d",
    "#9edae5",
)


def label_colors(values: Sequence[Any]) -> dict[str, str]:
    """One colour per distinct label value, in sorted order of the values (so the same
    labels get the same colours in every figure of a run)."""
    groups = sorted({str(v) for v in values})
    return {g: _GROUP_COLORS[i % len(_GROUP_COLORS)] for i, g in enumerate(groups)}


def check_strips(strips: Mapping[str, Sequence[Any]] | None, n: int, what: str) -> dict[str, list[str]]:
    """`strips` as ``{label name: [value per root]}`` (strings), or a ValueError."""
    if strips is None:
        return {}
    if not isinstance(strips, Mapping):
        raise ValueError(
            f"{what}: strips must be a dict {{label name: one value per root}}, got {type(strips).__name__}."
        )
    out = {}
    for name, values in strips.items():
        values = [str(v) for v in values]
        if len(values) != n:
            raise ValueError(f"{what}: strip {name!r} has {len(values)} values for {n} roots.")
        out[str(name)] = values
    return out


def draw_strip(
    ax, legend_ax, values_in_order: Sequence[str], name: str, *, centers=None, width: float = 1.0
) -> dict[str, str]:
    """One row of coloured cells (a bar per root, in the order given) with the label's name on
    the left, and its legend in `legend_ax` (an Axes of the layout to the strip's right, drawn
    without axes). Returns the colours used ``{value: colour}``.

    Each cell is a bar whose ``gid`` is its value, so tests and tools can read the strip back
    from ``ax.patches``; the legend is ``legend_ax.get_legend()``."""
    colors = label_colors(values_in_order)
    n = len(values_in_order)
    x = np.arange(n, dtype=float) if centers is None else np.asarray(centers, dtype=float)
    bars = ax.bar(x, 1.0, width=width, bottom=0.0, color=[colors[v] for v in values_in_order], linewidth=0)
    for bar, v in zip(bars, values_in_order):
        bar.set_gid(v)
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    ax.set_xticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)
    ax.set_ylabel(name, rotation=0, ha="right", va="center", fontsize=8)
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=c, label=g) for g, c in colors.items()]
    # The legend belongs to its own Axes in the layout (a column right of the colour bar): the
    # layout makes room for it, so a saved figure holds it whole (bbox_inches="tight" too), and
    # the panels keep their widths.
    legend_ax.set_axis_off()
    legend_ax.legend(
        handles=handles,
        loc="center left",
        bbox_to_anchor=(0.0, 0.5),
        fontsize=7,
        frameon=False,
        ncol=max(1, min(len(handles), 6)),
        handlelength=1.0,
        columnspacing=0.8,
        borderaxespad=0.0,
    )
    return colors


def plot_mds(
    embedding: Any,
    labels: Sequence[Any] | None = None,
    *,
    names: Sequence[str] | None = None,
    explained: Sequence[float] | None = None,
    label_name: str = "group",
    ax=None,
    title: str | None = "Roots in two dimensions (classical MDS of the distances)",
):
    """Scatter plot of an MDS embedding, one colour per label value with a legend; `names`
    annotate the points (up to 40 roots); `explained` (``MDS.proportion_explained``) goes into
    the axis names.

    `embedding` is an `MDS` result (``rootshape_jax.mds(D)``; its `proportion_explained` is
    the default `explained`) or its ``(n, 2)`` coordinates (``rootshape_jax.mds(D).embedding``).

    **Returns** ``(fig, ax)``. Each group is one scatter collection whose label is the group."""
    if isinstance(embedding, MDS):
        if explained is None:
            explained = embedding.proportion_explained
        embedding = embedding.embedding
    X = as_float_array(
        embedding, what="plot_mds", expected="an MDS (rootshape_jax.mds) or an (n, 2) array of coordinates"
    )
    if X.ndim != 2 or X.shape[1] < 2:
        raise ValueError(f"plot_mds: expected an (n, 2) embedding (mds(D, n_components=2)), got shape {X.shape}.")
    n = X.shape[0]
    fig, ax, values = _scatter_figure(ax, labels, n, f"plot_mds: {{}} labels for {n} points.")
    _scatter_groups(ax, X[:, :2], values, names, labelled=labels is not None, label_name=label_name)
    for k, setter in enumerate((ax.set_xlabel, ax.set_ylabel)):
        text = f"MDS axis {k + 1}"
        if explained is not None:
            text += f" ({100 * float(explained[k]):.0f} % of the positive eigenvalues)"
        setter(text + " (distance units)")
    ax.set_aspect("equal", adjustable="datalim")
    if title:
        ax.set_title(title, fontsize=11)
    return fig, ax


def _scatter_figure(ax, labels, n: int, message: str):
    """``(fig, ax, one label per point)``: a new figure unless `ax` is given; every point
    labelled "all" without `labels`; a ValueError (`message`, formatted with the count of
    labels) when their count is not `n`."""
    values = ["all"] * n if labels is None else [str(v) for v in labels]
    if len(values) != n:
        raise ValueError(message.format(len(values)))
    if ax is None:
        fig = new_figure((6.4, 5.2))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    return fig, ax, values


def _scatter_groups(ax, X, values: list[str], names, *, labelled: bool, label_name: str) -> None:
    """One scatter collection per label value (its label: the value and its count), names
    beside the points (up to 40 roots), a legend when the points are `labelled`, and light
    axes through 0."""
    colors = label_colors(values)
    for g, c in colors.items():
        idx = [i for i, v in enumerate(values) if v == g]
        ax.scatter(X[idx, 0], X[idx, 1], s=36, color=c, label=f"{g} (n = {len(idx)})", edgecolor="white", linewidth=0.5)
    if names is not None and len(values) <= 40:
        for (x, y), name in zip(X, names):
            ax.annotate(str(name), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points", color="#444444")
    if labelled:
        ax.legend(title=label_name, fontsize=8, title_fontsize=8, frameon=False, loc="best")
    ax.axhline(0, color="#dddddd", linewidth=0.6, zorder=0)
    ax.axvline(0, color="#dddddd", linewidth=0.6, zorder=0)
    ax.spines[["top", "right"]].set_visible(False)


def plot_pca_scores(
    pca: TangentPCA,
    labels: Sequence[Any] | None = None,
    *,
    components: tuple[int, int] = (0, 1),
    names: Sequence[str] | None = None,
    label_name: str = "group",
    ax=None,
    title: str | None = "Roots on two principal components",
):
    """Scatter plot of the samples' scores on two principal components (``pca.scores``, the
    standardised coefficients that `rootshape_jax.reconstruct` and `rootshape_jax.project`
    use), one colour per label value with a legend; `names` annotate the points (up to 40
    roots). The axis names give each component's share of the variance.

    - `components`: the two components, counted from 0 as in `rootshape_jax.modes`
      (default the first two).

    **Returns** ``(fig, ax)``. Each group is one scatter collection whose label is the group."""
    if not isinstance(pca, TangentPCA):
        raise TypeError(
            f"plot_pca_scores: expected a TangentPCA (rootshape_jax.tangent_pca), got {type(pca).__name__}."
        )
    scores = np.asarray(pca.scores, dtype=float)
    n, m = scores.shape
    if (
        not isinstance(components, (tuple, list))
        or len(components) != 2
        or not all(isinstance(c, (int, np.integer)) and not isinstance(c, bool) for c in components)
    ):
        raise ValueError(f"plot_pca_scores: components must be two component numbers, e.g. (0, 1), got {components!r}.")
    i, j = (int(c) for c in components)
    if not (0 <= i < m and 0 <= j < m) or i == j:
        raise ValueError(
            f"plot_pca_scores: components {components!r} must be two different components in 0 … {m - 1} "
            f"(the PCA of {n} samples has {m})."
        )
    if names is not None and len(names) != n:
        raise ValueError(f"plot_pca_scores: {len(names)} names for the {n} samples of the PCA.")
    fig, ax, values = _scatter_figure(ax, labels, n, f"plot_pca_scores: {{}} labels for the {n} samples of the PCA.")
    _scatter_groups(ax, scores[:, [i, j]], values, names, labelled=labels is not None, label_name=label_name)
    ratio = np.asarray(pca.explained_variance_ratio, dtype=float)
    for k, setter in zip((i, j), (ax.set_xlabel, ax.set_ylabel)):
        setter(f"PC{k + 1} score ({100 * ratio[k]:.0f} % of the variance; standard deviations)")
    if title:
        ax.set_title(title, fontsize=11)
    return fig, ax
