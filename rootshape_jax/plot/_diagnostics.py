"""Small diagnostic plots: the Karcher-mean energy trace and the PCA explained variance."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .._mean import KarcherMean
from .._pca import TangentPCA
from ._draw import as_float_array, new_figure, slot_color


def _as_trace(trace: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(trace, KarcherMean):
        trace = trace.energy_trace
    y = as_float_array(trace, what=what, expected="a KarcherMean or a 1D array of energies per iteration")
    if y.ndim != 1:
        raise ValueError(f"{what}: expected a 1D array of energies per iteration, got shape {y.shape}.")
    # Solvers pad the steps they did not take with NaN / inf: those are not iterations.
    steps = np.flatnonzero(np.isfinite(y))
    if steps.size == 0:
        raise ValueError(f"{what}: the trace has no finite value.")
    return steps, y[steps]


def plot_energy_trace(
    trace: Any,
    *,
    ax=None,
    log: bool | None = None,
    ylabel: str = "energy  F(\u03bc)",
    title: str | None = "Karcher mean: energy per iteration",
):
    """Energy per iteration of an optimiser (e.g. the Karcher mean's trace).

    **Arguments**

    - `trace`: a `KarcherMean` (from `rootshape_jax.karcher_mean`; its `energy_trace` is
      drawn), a 1D array (non-finite entries, the padding of unused steps, are skipped), or a
      mapping ``{label: either}`` to compare several runs (e.g. two solvers).
    - `ax`: an Axes to draw into; a new figure when None.
    - `log`: logarithmic energy axis; None chooses it when the energies are positive and span
      more than a factor of 20.

    **Returns** ``(fig, ax)``.
    """
    traces = dict(trace) if isinstance(trace, Mapping) else {None: trace}
    if not traces:
        raise ValueError("plot_energy_trace: no trace given.")
    data = {k: _as_trace(v, f"plot_energy_trace: trace {k!r}" if k else "plot_energy_trace") for k, v in traces.items()}
    if ax is None:
        fig = new_figure((5.5, 3.6))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    allv = np.concatenate([v for _, v in data.values()])
    if log is None:
        log = bool(np.all(allv > 0) and allv.max() / allv.min() > 20)
    for i, (label, (x, y)) in enumerate(data.items()):
        color = "#1a1a1a" if label is None else slot_color(i)
        ax.plot(x, y, marker="o", markersize=3.5, linewidth=1.4, color=color, label=label)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.spines[["top", "right"]].set_visible(False)
    ax.grid(alpha=0.3, linewidth=0.6)
    if any(k is not None for k in data):
        ax.legend(frameon=False)
    if len(data) == 1:
        ((x, y),) = data.values()
        change = (y[0] - y[-1]) / abs(y[0]) if y[0] != 0 else np.nan
        ax.annotate(
            f"{x.size} iterations, final {y[-1]:.4g} ({100 * change:.1f} % below the start)",
            xy=(1, 1),
            xycoords="axes fraction",
            ha="right",
            va="top",
            fontsize=8,
            color="#555555",
        )
    if title:
        ax.set_title(title, fontsize=11)
    return fig, ax


def plot_explained_variance(
    eigenvalues: Any,
    *,
    ax=None,
    threshold: float | None = 0.99,
    max_components: int | None = 30,
    title: str | None = "Tangent PCA: variance explained",
):
    """Bars of the variance explained by each principal component, plus the cumulative curve.

    **Arguments**

    - `eigenvalues`: a `TangentPCA` (from `rootshape_jax.tangent_pca`; its
      `explained_variance_ratio` is drawn), or the PCA variances σ_i as an array (any order;
      sorted descending here), ≥ 0.
    - `threshold`: cumulative fraction marked by a dashed line, with the number of components
      needed to reach it (the default kept by `tangent_pca`); None for no mark.
    - `max_components`: show at most this many components (None: all).
    - `ax`: an Axes to draw into; a new figure when None.

    **Returns** ``(fig, ax)``.
    """
    if isinstance(eigenvalues, TangentPCA):
        eigenvalues = eigenvalues.explained_variance_ratio
    ev = as_float_array(
        eigenvalues,
        what="plot_explained_variance",
        expected="a TangentPCA (rootshape_jax.tangent_pca) or an array of variances",
    ).reshape(-1)
    if ev.size == 0 or not np.all(np.isfinite(ev)):
        raise ValueError("plot_explained_variance: eigenvalues must be a non-empty finite array.")
    if np.any(ev < -1e-12 * max(float(np.abs(ev).max()), 1e-300)):
        raise ValueError(
            f"plot_explained_variance: eigenvalues are variances and must be >= 0, got minimum {ev.min():.3g}."
        )
    ev = np.sort(np.clip(ev, 0.0, None))[::-1]
    if ev.sum() <= 0:
        raise ValueError("plot_explained_variance: all eigenvalues are zero.")
    if threshold is not None and not 0 < threshold <= 1:
        raise ValueError(f"threshold must be in (0, 1], got {threshold!r}.")
    ratio = ev / ev.sum()
    cum = np.cumsum(ratio)
    m = ev.size if max_components is None else min(ev.size, int(max_components))
    x = np.arange(1, m + 1)
    if ax is None:
        fig = new_figure((max(4.5, min(10.0, 0.28 * m + 3)), 3.8))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    ax.bar(x, 100 * ratio[:m], color="#7aa6c8", width=0.8, label="each component")
    ax.plot(
        x,
        100 * cum[:m],
        color="#1a1a1a",
        marker="o",
        markersize=3,
        linewidth=1.3,
        label="cumulative",
    )
    if threshold is not None:
        needed = int(np.searchsorted(cum, threshold - 1e-12) + 1)
        ax.axhline(100 * threshold, color="#c0392b", linestyle="--", linewidth=0.9)
        if needed <= m:
            ax.axvline(needed, color="#c0392b", linestyle=":", linewidth=0.9)
        ax.annotate(
            f"{needed} component{'s' if needed > 1 else ''} explain \u2265 {100 * threshold:g} %",
            xy=(1, 0.5),
            xycoords="axes fraction",
            ha="right",
            va="center",
            fontsize=9,
            color="#c0392b",
        )
    ax.set_xlabel("principal component")
    ax.set_ylabel("variance explained [%]")
    ax.set_ylim(0, 104)
    ax.set_xlim(0.4, m + 0.6)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.spines[["top", "right"]].set_visible(False)
    ax.legend(frameon=False, loc="center right", bbox_to_anchor=(1, 0.3))
    if title:
        ax.set_title(title, fontsize=11)
    return fig, ax
