"""The demo page's figures (issue 17, item 9): the heat map's condition strip agrees with the
roots' labels in distances.csv, the mean figure names its roots without a gap, the variance plot shows every
kept component. The steps run in-process on fake distances / PCA: no registration compiles."""

from __future__ import annotations

import argparse
import csv
import types

import matplotlib
import matplotlib.colors as mcolors
import numpy as np
import pytest

matplotlib.use("Agg")

import rootshape_jax as rs
import rootshape_jax.plot as rplot
from rootshape_jax.datasets import synthetic_roots


def _strip(ax) -> tuple[list[str], list[str]]:
    """(values, colours) of a strip's cells, left to right (each cell is a bar whose gid is its value)."""
    bars = sorted(ax.patches, key=lambda b: b.get_x())
    return [b.get_gid() for b in bars], [mcolors.to_hex(b.get_facecolor()) for b in bars]


def _clustered_distances(groups: list[str], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = {g: 6.0 * rng.normal(size=3) for g in sorted(set(groups))}
    x = np.array([centres[g] for g in groups]) + rng.normal(size=(len(groups), 3))
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def _demo_context(n_per_condition=4, seed=5):
    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._steps import Context

    roots = [
        r
        for c in ("control", "drought", "high_nitrate")
        for r in synthetic_roots(n_per_condition, condition=c, seed=seed)
    ]
    args = argparse.Namespace(
        laterals=4,
        points=12,
        normalise_scale=True,
        quiet=True,
        weights=(0.02, 1.0, 1.0),
        store=None,
        modes=2,
        overwrite=False,
    )
    return Context(prepare(roots, args)), args


def test_demo_heat_map_strip_agrees_with_the_csv(tmp_path, monkeypatch):
    """The distances step's heat map has a condition strip whose colours, read in the matrix's
    row order, match each root's condition (roots named in distances.csv)."""
    from rootshape_jax._cli._report import Output
    from rootshape_jax._cli._steps import run_distances

    ctx, args = _demo_context()
    conditions = {r.name: r.metadata["condition"] for r in ctx.pop.roots}
    D = _clustered_distances([conditions[n] for n in ctx.pop.names])
    monkeypatch.setattr(rs, "pairwise_distances", lambda *a, **kw: (D, {}))
    drawn = {}
    original = rplot.plot_distance_matrix

    def spy(*a, **kw):
        drawn["fig"], drawn["axes"] = original(*a, **kw)
        return drawn["fig"], drawn["axes"]

    monkeypatch.setattr(rplot, "plot_distance_matrix", spy)
    run_distances(ctx, Output(tmp_path / "o", args), args)

    with open(tmp_path / "o" / "distances.csv", newline="") as f:
        csv_names = [row["root"] for row in csv.DictReader(f)]
    assert csv_names == ctx.pop.names
    assert list(drawn["axes"]["strips"]) == ["condition"]
    rows = [t.get_text() for t in drawn["axes"]["matrix"].get_yticklabels()]
    assert sorted(rows) == sorted(csv_names)
    values, colors = _strip(drawn["axes"]["strips"]["condition"])
    assert values == [conditions[n] for n in rows]  # one cell per root, in the matrix's order
    legend = drawn["axes"]["legends"]["condition"].get_legend()
    named = {t.get_text(): mcolors.to_hex(h.get_facecolor()) for t, h in zip(legend.get_texts(), legend.legend_handles)}
    assert colors == [named[v] for v in values] and len(set(named.values())) == 3


def test_mean_figure_names_every_root_without_a_gap():
    roots = [r for c in ("control", "high_nitrate") for r in synthetic_roots(7, condition=c, seed=2)]
    trees = rs.batch(roots, n_points=20)
    names = [r.name for r in roots]
    fig, axes = rplot.plot_mean(trees, rs.unstack(trees)[0], names=names, max_samples=len(names))
    assert [ax.get_title() for ax in axes["samples"]] == names
    fig.canvas.draw()  # constrained layout places the axes
    boxes = [ax.get_position() for ax in axes["samples"]]
    x0 = sorted({round(b.x0, 4) for b in boxes})
    steps = np.diff(x0)
    # Columns equally spaced: no column is widened by a header or a long name.
    assert steps.max() - steps.min() < 0.01, steps
    # The mean panel starts within one column step of the last sample column's right edge.
    right = max(b.x1 for b in boxes)
    mean_left = axes["mean"].get_tightbbox().transformed(fig.transFigure.inverted()).x0
    assert mean_left - right < steps.mean(), (mean_left, right, steps.mean())
    # Roots (not trees) carry their names by default.
    _, axes = rplot.plot_mean(roots[:3], roots[0])
    assert [ax.get_title() for ax in axes["samples"]] == names[:3]
    with pytest.raises(ValueError, match="2 names for 14 samples"):
        rplot.plot_mean(trees, rs.unstack(trees)[0], names=names[:2])


def test_demo_variance_plot_covers_every_kept_component(tmp_path, monkeypatch):
    """More kept components than the plot's default of 30: every one gets its bar."""
    from rootshape_jax._cli._report import Output
    from rootshape_jax._cli._steps import run_pca

    ctx, args = _demo_context()
    eig = np.linspace(1.0, 0.5, 45) ** 2
    eig[-1] = 1e-5
    ratio = eig / eig.sum()
    kept = int(np.searchsorted(np.cumsum(ratio), 0.99) + 1)
    assert kept > 30
    fake = types.SimpleNamespace(
        eigenvalues=eig,
        explained_variance_ratio=ratio,
        n_components=kept,
        variance=float(np.cumsum(ratio)[kept - 1]),
        scores=np.zeros((len(ctx.pop.names), len(eig))),
    )
    monkeypatch.setattr(rs, "tangent_pca", lambda mean: fake)
    monkeypatch.setattr(rs, "modes", lambda *a, **kw: None)
    monkeypatch.setattr(rplot, "plot_modes", lambda *a, **kw: rplot.plot_energy_trace([1.0, 0.5]))
    monkeypatch.setattr(rplot, "plot_pca_scores", lambda *a, **kw: rplot.plot_energy_trace([1.0, 0.5]))
    drawn = {}
    original = rplot.plot_explained_variance

    def spy(*a, **kw):
        drawn["fig"], drawn["ax"] = original(*a, **kw)
        return drawn["fig"], drawn["ax"]

    monkeypatch.setattr(rplot, "plot_explained_variance", spy)
    run_pca(ctx, Output(tmp_path / "o", args), args)
    heights = [p.get_height() for p in drawn["ax"].patches]
    assert len(heights) == kept
    np.testing.assert_allclose(heights, 100 * ratio[:kept])
    with open(tmp_path / "o" / "explained_variance.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == len(eig)


def test_mean_figure_with_a_long_unit_keeps_its_columns_even():
    """The normalised unit's long name goes below the figure, not under a panel's scale bar
    (where it widened one column of the grid)."""
    roots = [r for c in ("control", "high_nitrate") for r in synthetic_roots(7, condition=c, seed=2)]
    trees = rs.batch(roots, n_points=20, normalise_scale=True)
    unit = "normalised (main-root length = 1)"
    fig, axes = rplot.plot_mean(trees, rs.unstack(trees)[0], names=[r.name for r in roots], unit=unit)
    fig.canvas.draw()
    x0 = sorted({round(ax.get_position().x0, 4) for ax in axes["samples"]})
    steps = np.diff(x0)
    assert steps.max() - steps.min() < 0.01, steps
    assert fig.get_supxlabel() == f"scale bars in {unit}"
