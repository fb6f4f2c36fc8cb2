"""rootshape_jax.plot: every function draws, saves a readable PNG, and honours its inputs."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import matplotlib
import matplotlib.colors as mcolors
import matplotlib.image as mimage
import numpy as np
import pytest
from helpers import random_root
from matplotlib.collections import LineCollection
from scipy.cluster import hierarchy
from scipy.spatial.distance import squareform

import rootshape_jax as rs
from rootshape_jax import plot as P
from rootshape_jax._errors import MissingDependencyError
from rootshape_jax._tree import batch, stack, unstack

DPI = 50
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(autouse=True)
def _close_pyplot_figures():
    yield
    if "matplotlib.pyplot" in sys.modules:  # figures are pyplot's only if the user imported it
        sys.modules["matplotlib.pyplot"].close("all")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def roots(rng):
    return [random_root(rng, n_laterals=int(rng.integers(1, 5))) for _ in range(9)]


@pytest.fixture
def trees(roots):
    return batch(roots, n_points=24, max_laterals=8)


@pytest.fixture(scope="module")
def mean():
    """A real, tiny KarcherMean: 4 roots, 12 points per curve, 2 (unconverged) steps."""
    rng = np.random.default_rng(7)
    trees = batch([random_root(rng, n_laterals=2) for _ in range(4)], n_points=12, max_laterals=3)
    return rs.karcher_mean(trees, max_steps=2, throw=False, progress=False)


@pytest.fixture(scope="module")
def pca(mean):
    return rs.tangent_pca(mean)


def check_png(fig, path, n_axes):
    """Save, reload, and check a non-blank PNG of the figure's size with the expected axes."""
    assert len(fig.axes) == n_axes
    fig.savefig(path, dpi=DPI)
    assert path.stat().st_size > 0
    with open(path, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    img = mimage.imread(path)
    w, h = fig.get_size_inches() * DPI
    assert img.ndim == 3 and img.shape[0] > 0 and img.shape[1] > 0
    assert abs(img.shape[0] - h) <= 1 and abs(img.shape[1] - w) <= 1
    assert img[..., :3].std() > 0.01  # something was drawn
    return img


def line_collections(ax):
    return [c for c in ax.collections if isinstance(c, LineCollection)]


def segments_and_colors(ax):
    """(segments, rgba colours) of all lines on ax, one entry per polyline."""
    segs, cols = [], []
    for c in line_collections(ax):
        s = c.get_segments()
        colors = c.get_colors()
        segs += s
        cols += [colors[i % len(colors)] for i in range(len(s))]
    return segs, cols


def lerp_trees(a, b, taus):
    """A fake geodesic: straight line between two trees with the same slots."""
    return stack([jax.tree.map(lambda x, y: (1 - t) * x + t * y if x.dtype != bool else x | y, a, b) for t in taus])


# --------------------------------------------------------------------------------------------
# plot_root


def test_plot_root_root(roots, tmp_path):
    root = roots[0]
    fig, ax = P.plot_root(root)
    check_png(fig, tmp_path / "root.png", 1)
    segs, cols = segments_and_colors(ax)
    assert len(segs) == root.n_laterals + 1
    for k, lat in enumerate(root.laterals):
        assert np.allclose(segs[k], lat)
        assert np.allclose(cols[k], mcolors.to_rgba(P.slot_color(k)))
    assert np.allclose(segs[-1], root.main)
    assert ax.yaxis_inverted()
    assert ax.get_aspect() == 1.0
    _, ax2 = P.plot_root(root, invert_y=False, slot_colors=False)
    assert not ax2.yaxis_inverted()
    _, cols2 = segments_and_colors(ax2)
    assert len({tuple(c) for c in cols2[:-1]}) == 1  # every lateral in one colour


def test_plot_root_tree_respects_mask(roots, trees, tmp_path):
    i = int(np.argmin([r.n_laterals for r in roots]))
    tree = unstack(trees)[i]
    n_real = roots[i].n_laterals
    fig, ax = P.plot_root(tree, show_nulls=True)
    check_png(fig, tmp_path / "tree.png", 1)
    segs, cols = segments_and_colors(ax)
    assert len(segs) == n_real + 1
    mask = np.asarray(tree.mask)
    for seg, k in zip(segs[:-1], np.flatnonzero(mask)):
        assert np.allclose(seg, np.asarray(tree.laterals[k]))
    # Null slots appear as hollow markers only when asked.
    offsets = ax.collections[-1].get_offsets()
    assert offsets.shape == (int((~mask).sum()), 2)
    _, ax2 = P.plot_root(tree)
    assert all(isinstance(c, LineCollection) for c in ax2.collections)


def test_show_nulls_marks_padding_at_every_level(tmp_path):
    from test_hierarchy import deep_root

    rng = np.random.default_rng(2)
    roots = [deep_root(rng, n_laterals=2, max_sub=2), deep_root(rng, n_laterals=3, max_sub=1)]
    tree = unstack(batch(roots, n_points=10, depth=3, max_children=(5, 3)))[0]
    m1, m2 = np.asarray(tree.mask), np.asarray(tree.deeper[0].mask)
    # Reference: first-order nulls, then each real lateral's unused child slots.
    want = [np.asarray(tree.laterals[k, 0]) for k in np.flatnonzero(~m1)]
    want += [np.asarray(tree.deeper[0].curves[k, j, 0]) for k in np.flatnonzero(m1) for j in np.flatnonzero(~m2[k])]
    assert len(want) > int((~m1).sum())  # the test sees deeper nulls
    fig, ax = P.plot_root(tree, show_nulls=True, invert_y=False)
    check_png(fig, tmp_path / "nulls.png", 1)
    np.testing.assert_allclose(ax.collections[-1].get_offsets(), np.stack(want), atol=1e-9)


def test_plot_root_into_given_axes(roots, tmp_path):
    fig, ax = P.plot_root(roots[0])
    P.plot_root(roots[1], ax=ax, colors="#123456")
    check_png(fig, tmp_path / "two.png", 1)
    segs, cols = segments_and_colors(ax)
    assert len(segs) == roots[0].n_laterals + roots[1].n_laterals + 2
    red = mcolors.to_rgba("#123456")
    assert sum(np.allclose(c, red) for c in cols) == roots[1].n_laterals + 1
    assert ax.yaxis_inverted()


def test_plot_root_3d(rng, tmp_path):
    root = random_root(rng, n_laterals=3, d=3)
    fig, ax = P.plot_root(root)  # side view: x against depth z
    check_png(fig, tmp_path / "side.png", 1)
    segs, _ = segments_and_colors(ax)
    assert np.allclose(segs[-1], root.main[:, [0, 2]])
    fig, ax = P.plot_root(root, projection="3d")
    check_png(fig, tmp_path / "3d.png", 1)
    assert ax.name == "3d"
    assert ax.zaxis_inverted()
    with pytest.raises(ValueError, match="projection"):
        P.plot_root(random_root(rng, d=2), projection="3d")


def test_plot_root_bad_input(trees, rng):
    with pytest.raises(ValueError, match="batch"):
        P.plot_root(trees)
    with pytest.raises(TypeError):
        P.plot_root(np.zeros((5, 2)))
    root = random_root(rng, n_laterals=3)
    with pytest.raises(ValueError, match="slot"):
        P.plot_root(root, colors=["red", "blue"])  # slot 2 has no colour
    with pytest.raises(ValueError):
        P.plot_root(root, colors="not-a-colour")


# --------------------------------------------------------------------------------------------
# Figures of several roots


def test_plot_geodesic(trees, tmp_path):
    a, b = unstack(trees)[:2]
    taus = np.linspace(0, 1, 5)
    path = lerp_trees(a, b, taus)
    fig, axes = P.plot_geodesic(path, unit="mm")
    check_png(fig, tmp_path / "geodesic.png", 5)
    mask = np.asarray(path.mask[0])
    for step, ax in enumerate(axes):
        segs, cols = segments_and_colors(ax)
        # Same slot, same colour, at every step.
        for k, c in zip(np.flatnonzero(mask), cols):
            assert np.allclose(c, mcolors.to_rgba(P.slot_color(k)))
        assert np.allclose(segs[-1], np.asarray(path.main[step]))
        # Shared region and scale.
        assert ax.get_xlim() == axes[0].get_xlim() and ax.get_ylim() == axes[0].get_ylim()
    assert axes[0].get_title().endswith("0") and axes[-1].get_title().endswith("1")
    with pytest.raises(ValueError, match="axes"):
        P.plot_geodesic(path, axes=axes[:3])
    with pytest.raises(ValueError, match="batch"):
        P.plot_geodesic(stack([path, path]))


def test_plot_geodesic_into_axes(trees):
    path = lerp_trees(*unstack(trees)[:2], np.linspace(0, 1, 3))
    fig0 = P.plot_root(unstack(trees)[0])[0]
    axes = [fig0.add_subplot(1, 3, j + 1) for j in range(3)]
    fig, out = P.plot_geodesic(path, axes=axes, title=None)
    assert fig is fig0 and out == axes


def test_plot_mean(roots, trees, tmp_path):
    mean = unstack(trees)[0]
    fig, axes = P.plot_mean(trees, mean)
    check_png(fig, tmp_path / "mean.png", len(roots) + 1)
    assert len(axes["samples"]) == len(roots)
    fig, axes = P.plot_mean(roots, roots[0], max_samples=4)
    check_png(fig, tmp_path / "mean4.png", 5)
    fig, axes = P.plot_mean(roots, mean, layout="overlay")
    check_png(fig, tmp_path / "overlay.png", 1)
    # Samples (faint) and the mean: one main root line per sample plus the mean's.
    n_lines = sum(len(c.get_segments()) for c in line_collections(axes["mean"]))
    assert n_lines == sum(r.n_laterals + 1 for r in roots) + int(np.asarray(mean.mask).sum()) + 1
    with pytest.raises(ValueError, match="layout"):
        P.plot_mean(roots, mean, layout="mosaic")


def _longest_chord(ax):
    """Base-to-tip vector of the longest polyline drawn on ax (the main root)."""
    segs, _ = segments_and_colors(ax)
    main = max(segs, key=lambda s: np.sum(np.linalg.norm(np.diff(s, axis=0), axis=1)))
    return main[-1] - main[0]


def _angle(u, v):
    return float(np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))))


def test_plot_mean_turns_a_karcher_mean_upright(mean):
    """The metric ignores rotation, so a mean's SRVF keeps the tilt of its solver's start: drawn
    from a KarcherMean or SRVFTree it is turned to point like the samples (upright=False: as
    fitted); a Root or RootTree mean is the user's own frame, drawn as given."""
    rng = np.random.default_rng(7)  # the samples of the `mean` fixture
    roots = [random_root(rng, n_laterals=2) for _ in range(4)]
    samples = batch(roots, n_points=12, max_laterals=3)
    target = np.mean([r.main[-1] - r.main[0] for r in roots], axis=0)
    assert np.linalg.norm(target) > 0.5 * np.mean([np.linalg.norm(r.main[-1] - r.main[0]) for r in roots])
    t = np.radians(100.0)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    curves = rs.to_curves(mean.mean)
    tilted = rs.turn_about_base(rs.turn_about_base(curves, rs.upright_rotation(curves, samples)), R)
    km = eqx.tree_at(lambda m: m.mean, mean, rs.to_srvf(tilted))  # the fit, 100° off the samples
    for m in (km, km.mean):
        _, axes = P.plot_mean(samples, m)
        assert _angle(_longest_chord(axes["mean"]), target) < 3.0
        _, axes = P.plot_mean(roots, m, upright=False)
        assert _angle(_longest_chord(axes["mean"]), target) > 90.0
    _, axes = P.plot_mean(roots, tilted)
    assert _angle(_longest_chord(axes["mean"]), target) > 90.0


def test_plot_modes_and_samples_turned_by_a_rotation(pca):
    """rotation=R draws every root turned about its base by R: the same segments as drawing
    the trees turned with turn_about_base (how the command line draws them upright)."""
    t = np.radians(35.0)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    alphas = [-1.0, 0.0, 1.0]
    row = rs.modes(pca, alphas, component=0)
    _, turned = P.plot_modes(pca, alphas, components=0, rotation=R)
    _, want = P.plot_modes(rs.turn_about_base(rs.to_curves(row), R), alphas, components=0)
    _, plain = P.plot_modes(pca, alphas, components=0)
    samples = rs.to_curves(rs.modes(pca, [-2.0, -1.0, 1.0, 2.0], component=0))
    dist = [2.0, 1.0, 1.0, 2.0]
    _, s_turned = P.plot_samples_by_distance(samples, dist, n_groups=2, rotation=R)
    _, s_want = P.plot_samples_by_distance(rs.turn_about_base(samples, R), dist, n_groups=2)
    for got_rows, want_rows in ((turned, want), (s_turned, s_want)):
        for a, b in zip(sum(got_rows, []), sum(want_rows, [])):
            (segs_a, _), (segs_b, _) = segments_and_colors(a), segments_and_colors(b)
            assert len(segs_a) == len(segs_b) > 0
            for sa, sb in zip(segs_a, segs_b):
                np.testing.assert_allclose(sa, sb, atol=1e-9)
    # ... and not what is drawn without it.
    assert _angle(_longest_chord(turned[0][1]), _longest_chord(plain[0][1])) == pytest.approx(35.0, abs=0.01)
    with pytest.raises(ValueError, match=r"rotation must be a finite \[2, 2\] matrix"):
        P.plot_modes(pca, alphas, rotation=np.eye(3))


def test_plot_modes(trees, tmp_path):
    t = unstack(trees)
    alphas = [-2.0, -1.0, 0.0, 1.0, 2.0]
    rows = [lerp_trees(t[0], t[c + 1], (np.asarray(alphas) + 2) / 8) for c in range(3)]
    modes = stack(rows)  # batch shape (3 components, 5 alphas)
    fig, grid = P.plot_modes(modes, alphas, explained=[0.5, 0.3, 0.1])
    check_png(fig, tmp_path / "modes.png", 15)
    assert len(grid) == 3 and all(len(r) == 5 for r in grid)
    assert grid[0][2].get_title() == "mean"
    assert "PC 2" in grid[1][0].get_ylabel()
    # A nested list of rows works the same.
    fig, grid = P.plot_modes(rows, alphas)
    assert len(fig.axes) == 15
    with pytest.raises(ValueError, match="alphas"):
        P.plot_modes(modes, alphas[:4])


def test_plot_modes_takes_one_component(pca, tmp_path):
    # modes(..., component=i) has batch shape (n_alphas,): drawn as one row.
    alphas = [-1.0, 0.0, 1.0]
    row = rs.modes(pca, alphas, component=1)
    assert row.batch_shape == (3,)
    fig, grid = P.plot_modes(row, alphas)
    check_png(fig, tmp_path / "mode.png", 3)
    assert len(grid) == 1 and len(grid[0]) == 3
    assert grid[0][1].get_title() == "mean"
    assert "PC 1" in grid[0][0].get_ylabel()
    # `components` names the rows; `explained` is indexed by component.
    ratio = np.asarray(pca.explained_variance_ratio)
    _, grid = P.plot_modes(row, alphas, components=1, explained=ratio)
    assert grid[0][0].get_ylabel() == f"PC 2\n{100 * ratio[1]:.1f} % var."
    _, grid = P.plot_modes(rs.modes(pca, alphas, component=[0, 1]), alphas, components=[0, 1], explained=ratio)
    assert [r[0].get_ylabel().split("\n")[0] for r in grid] == ["PC 1", "PC 2"]
    with pytest.raises(ValueError, match="one per row"):
        P.plot_modes(row, alphas, components=[0, 1])
    with pytest.raises(ValueError, match="explained_variance_ratio"):
        P.plot_modes(row, alphas, components=1, explained=ratio[:1])
    with pytest.raises(TypeError, match="components"):
        P.plot_modes(row, alphas, components=1.0)
    with pytest.raises(ValueError, match=r"\(rows, columns\), or \(columns,\)"):
        P.plot_modes(stack([stack([row])]), alphas)


def test_plots_take_a_karcher_mean_and_a_pca_for_explained(mean, pca, tmp_path):
    """plot_mean(samples, km) and plot_root(km) said "Build a RootTree with batch(roots)";
    plot_modes(..., explained=pc) failed in float()."""
    fig, ax = P.plot_root(mean)
    check_png(fig, tmp_path / "km_root.png", 1)
    _, ax_tree = P.plot_root(mean.mean)
    (a, _), (b, _) = segments_and_colors(ax), segments_and_colors(ax_tree)
    assert len(a) == len(b) > 0 and all(np.allclose(x, y) for x, y in zip(a, b))
    rng = np.random.default_rng(7)
    samples = batch([random_root(rng, n_laterals=2) for _ in range(4)], n_points=12, max_laterals=3)
    fig, axes = P.plot_mean(samples, mean)
    check_png(fig, tmp_path / "km_mean.png", len(fig.axes))
    alphas = [-1.0, 0.0, 1.0]
    ratio = np.asarray(pca.explained_variance_ratio)
    _, grid = P.plot_modes(rs.modes(pca, alphas, component=1), alphas, components=1, explained=pca)
    assert grid[0][0].get_ylabel() == f"PC 2\n{100 * ratio[1]:.1f} % var."


def test_plot_modes_takes_a_tangent_pca(pca, tmp_path):
    # Given the PCA, the rows are labelled by the components drawn and `explained` comes with it.
    alphas = [-1.0, 0.0, 1.0]
    ratio = np.asarray(pca.explained_variance_ratio)
    fig, grid = P.plot_modes(pca, alphas, components=1)
    check_png(fig, tmp_path / "mode_pca.png", 3)
    assert len(grid) == 1 and grid[0][0].get_ylabel() == f"PC 2\n{100 * ratio[1]:.1f} % var."
    # The same drawing as from the tree `modes` returns.
    _, from_tree = P.plot_modes(rs.modes(pca, alphas, component=1), alphas, components=1)
    for a, b in zip(grid[0], from_tree[0]):
        (segs_a, _), (segs_b, _) = segments_and_colors(a), segments_and_colors(b)
        assert len(segs_a) == len(segs_b) > 0
        for sa, sb in zip(segs_a, segs_b):
            np.testing.assert_allclose(sa, sb)
    _, grid = P.plot_modes(pca, alphas)
    n_rows = max(1, min(3, pca.n_components))
    assert [r[0].get_ylabel().split("\n")[0] for r in grid] == [f"PC {i + 1}" for i in range(n_rows)]
    with pytest.raises(ValueError, match="out of range"):
        P.plot_modes(pca, alphas, components=[0, 99])
    with pytest.raises(TypeError, match="components"):
        P.plot_modes(pca, alphas, components=1.0)


def test_plot_samples_by_distance(roots, trees, tmp_path, rng):
    dist = rng.uniform(0, 3, size=len(roots))
    fig, grid = P.plot_samples_by_distance(trees, dist, n_groups=3)
    check_png(fig, tmp_path / "samples.png", len(roots))
    shown = [float(ax.get_title().split("= ")[1]) for row in grid for ax in row]
    assert np.all(np.diff(shown) >= -1e-3)  # closest group first, sorted within groups
    assert np.allclose(sorted(shown), sorted(dist), rtol=5e-3)
    fig, grid = P.plot_samples_by_distance(roots, dist, n_groups=2, max_per_group=2)
    check_png(fig, tmp_path / "samples2.png", 4)
    with pytest.raises(ValueError, match="distances"):
        P.plot_samples_by_distance(roots, dist[:-1])
    with pytest.raises(ValueError, match="n_groups"):
        P.plot_samples_by_distance(roots, dist, n_groups=len(roots) + 1)


def test_plot_regression_sweep(roots, tmp_path):
    values = [10.0, 20.0, 30.0, 40.0]
    fig, axes = P.plot_regression_sweep(
        roots[:4],
        values,
        trait_name="main root length",
        trait_unit="mm",
        measured=[11, 19, 31, 39],
    )
    check_png(fig, tmp_path / "regression.png", 4)
    assert [ax.get_title().split("\n")[0] for ax in axes] == ["10 mm", "20 mm", "30 mm", "40 mm"]
    assert "main root length" in fig.get_suptitle()
    with pytest.raises(ValueError, match="values"):
        P.plot_regression_sweep(roots[:4], values[:3], trait_name="x")


# --------------------------------------------------------------------------------------------
# Distances and clusters


def random_distances(rng, n=7):
    x = rng.normal(size=(n, 3))
    x[: n // 2] += 4.0  # two clear groups
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def test_plot_distance_matrix(rng, tmp_path):
    D = random_distances(rng)
    fig, axes = P.plot_distance_matrix(D, labels=[f"r{i}" for i in range(len(D))])
    check_png(fig, tmp_path / "D.png", 3)
    Z = hierarchy.linkage(squareform(D), method="average", optimal_ordering=True)
    order = hierarchy.leaves_list(Z)
    shown = axes["matrix"].images[0].get_array()
    assert np.allclose(shown, D[np.ix_(order, order)])
    assert [t.get_text() for t in axes["matrix"].get_xticklabels()] == [f"r{i}" for i in order]
    # A given linkage decides the order.
    Zs = hierarchy.linkage(squareform(D), method="single")
    _, axes = P.plot_distance_matrix(D, linkage=Zs, show_dendrogram=False)
    o = hierarchy.leaves_list(Zs)
    assert np.allclose(axes["matrix"].images[0].get_array(), D[np.ix_(o, o)])
    assert len(axes["matrix"].figure.axes) == 2
    bad = D.copy()
    bad[0, 1] += 1.0
    with pytest.raises(ValueError, match="symmetric"):
        P.plot_distance_matrix(bad)
    with pytest.raises(ValueError, match="square"):
        P.plot_distance_matrix(D[:, :-1])


def test_plot_distance_matrix_into_axes(rng):
    D = random_distances(rng)
    fig0, ax0 = P.plot_energy_trace([3.0, 2.0, 1.0])
    fig, axes = P.plot_distance_matrix(D, ax=ax0)
    assert fig is fig0 and axes["dendrogram"] is None and len(fig.axes) == 2


def test_plot_dendrogram(rng, roots, tmp_path):
    D = random_distances(rng, n=len(roots))
    fig, axes = P.plot_dendrogram(D, n_clusters=2)
    check_png(fig, tmp_path / "dendrogram.png", 1)
    fig, axes = P.plot_dendrogram(D, n_clusters=2, roots=roots, max_roots_per_cluster=3)
    Z = hierarchy.linkage(squareform(D), method="average", optimal_ordering=True)
    labels = hierarchy.fcluster(Z, 2, criterion="maxclust")
    sizes = np.bincount(labels)[1:]
    check_png(fig, tmp_path / "dendrogram_roots.png", 1 + int(np.minimum(sizes, 3).sum()))
    # Each row holds members of one flat cluster, all drawn in that cluster's colour.
    for c, row in enumerate(axes["roots"]):
        ids = [int(ax.get_title().lstrip("#")) for ax in row]
        assert len({labels[i] for i in ids}) == 1
        colour = mcolors.to_rgba(P.slot_color(c))
        for ax in row:
            assert all(np.allclose(col, colour) for col in segments_and_colors(ax)[1])
    # A linkage matrix is accepted as well (here 5 roots: a (4, 4) linkage, not a D).
    D5 = random_distances(rng, n=5)
    Z5 = hierarchy.linkage(squareform(D5), method="complete")
    fig, axes = P.plot_dendrogram(Z5)
    assert len(fig.axes) == 1
    dax = axes["dendrogram"]
    tops = [seg[:, 1].max() for c in line_collections(dax) for seg in c.get_segments()]
    assert np.isclose(max(tops), Z5[-1, 2])  # the root link is drawn at the last merge height
    with pytest.raises(ValueError, match="n_clusters"):
        P.plot_dendrogram(D, n_clusters=len(D) + 1)
    with pytest.raises(ValueError, match="roots"):
        P.plot_dendrogram(D, roots=roots[:-1])


def test_dendrogram_input_detection(rng):
    D5 = random_distances(rng, n=5)
    Z5 = hierarchy.linkage(squareform(D5), method="complete")
    from rootshape_jax.plot._clusters import _as_linkage

    assert np.allclose(_as_linkage(Z5, "average", "t"), Z5)
    Zd = hierarchy.linkage(squareform(D5), method="average", optimal_ordering=True)
    assert np.allclose(_as_linkage(D5, "average", "t"), Zd)
    with pytest.raises(ValueError, match="linkage"):
        _as_linkage(np.ones((3, 4)), "average", "t")


# --------------------------------------------------------------------------------------------
# Diagnostics


def test_plot_energy_trace(tmp_path):
    trace = np.array([5.0, 3.0, 2.0, 1.5, 1.4, np.nan, np.nan])
    fig, ax = P.plot_energy_trace(trace)
    check_png(fig, tmp_path / "energy.png", 1)
    (line,) = ax.get_lines()
    assert np.array_equal(line.get_xdata(), np.arange(5))
    assert np.allclose(line.get_ydata(), trace[:5])
    fig, ax = P.plot_energy_trace({"fixed point": trace, "minimise": trace[:4] * 0.9})
    check_png(fig, tmp_path / "energy2.png", 1)
    assert len(ax.get_lines()) == 2 and ax.get_legend() is not None
    _, ax = P.plot_energy_trace([100.0, 10.0, 1.0])
    assert ax.get_yscale() == "log"
    with pytest.raises(ValueError, match="finite"):
        P.plot_energy_trace([np.nan, np.nan])
    with pytest.raises(ValueError, match="1D"):
        P.plot_energy_trace(np.ones((2, 3)))
    with pytest.raises(TypeError, match="KarcherMean"):
        P.plot_energy_trace(object())


def test_plot_energy_trace_takes_a_karcher_mean(mean, tmp_path):
    finite = np.asarray(mean.energy_trace)[np.isfinite(mean.energy_trace)]
    for given in (mean, {"fixed point": mean}):
        fig, ax = P.plot_energy_trace(given)
        check_png(fig, tmp_path / "energy_mean.png", 1)
        (line,) = ax.get_lines()
        np.testing.assert_allclose(line.get_ydata(), finite)


def test_plot_explained_variance(tmp_path):
    ev = np.array([0.5, 5.0, 3.0, 1.0, 0.5])  # any order; ratios .5 .3 .1 .05 .05
    fig, ax = P.plot_explained_variance(ev, threshold=0.9)
    check_png(fig, tmp_path / "ev.png", 1)
    heights = [p.get_height() for p in ax.patches]
    assert np.allclose(heights, [50.0, 30.0, 10.0, 5.0, 5.0])
    cum = [line for line in ax.get_lines() if len(line.get_xdata()) == 5][0]
    assert np.allclose(cum.get_ydata(), [50.0, 80.0, 90.0, 95.0, 100.0])
    assert any("3 components" in t.get_text() for t in ax.texts)
    with pytest.raises(ValueError, match=">= 0"):
        P.plot_explained_variance([1.0, -0.5])


def test_plot_explained_variance_takes_a_tangent_pca(pca, tmp_path):
    fig, ax = P.plot_explained_variance(pca, threshold=0.9)
    check_png(fig, tmp_path / "ev_pca.png", 1)
    ratio = np.sort(np.asarray(pca.explained_variance_ratio))[::-1]
    assert np.allclose([p.get_height() for p in ax.patches], 100 * ratio)
    # The same bars as from the variances themselves.
    _, ax2 = P.plot_explained_variance(np.asarray(pca.eigenvalues), threshold=0.9)
    assert np.allclose([p.get_height() for p in ax2.patches], 100 * ratio)
    with pytest.raises(TypeError, match="TangentPCA"):
        P.plot_explained_variance(rs.mds(random_distances(np.random.default_rng(0))))
    with pytest.raises(TypeError, match="TangentPCA"):
        P.plot_explained_variance({"pc1": 0.5})


def test_plot_mds_takes_an_mds_result(rng, tmp_path):
    result = rs.mds(random_distances(rng))
    labels = ["a"] * 3 + ["b"] * 4
    fig, ax = P.plot_mds(result, labels)
    check_png(fig, tmp_path / "mds.png", 1)
    points = np.concatenate([c.get_offsets() for c in ax.collections])
    expected = np.concatenate([result.embedding[:3], result.embedding[3:]])
    assert np.allclose(points, expected)
    # The result's proportion explained goes into the axis names.
    assert f"({100 * result.proportion_explained[0]:.0f} %" in ax.get_xlabel()
    _, ax2 = P.plot_mds(result.embedding, labels)
    assert np.allclose(np.concatenate([c.get_offsets() for c in ax2.collections]), expected)
    assert "%" not in ax2.get_xlabel()
    with pytest.raises(TypeError, match="MDS"):
        P.plot_mds(object())


def test_plot_pca_scores_draws_the_scores(pca, tmp_path):
    labels = ["a", "b", "a", "b"]
    fig, ax = P.plot_pca_scores(pca, labels, components=(1, 0), names=list("pqrs"))
    check_png(fig, tmp_path / "scores.png", 1)
    scores = np.asarray(pca.scores)
    for coll, idx in zip(ax.collections, ([0, 2], [1, 3])):
        np.testing.assert_allclose(coll.get_offsets(), scores[idx][:, [1, 0]])
    assert [t.get_text() for t in ax.texts] == list("pqrs")
    ratio = np.asarray(pca.explained_variance_ratio)
    assert ax.get_xlabel().startswith(f"PC2 score ({100 * ratio[1]:.0f} %")
    assert ax.get_ylabel().startswith(f"PC1 score ({100 * ratio[0]:.0f} %")
    _, ax2 = P.plot_pca_scores(pca)
    assert len(ax2.collections) == 1 and ax2.get_legend() is None
    np.testing.assert_allclose(ax2.collections[0].get_offsets(), scores[:, :2])
    m = scores.shape[1]
    for bad, match in (
        ((0, m), rf"in 0 … {m - 1}"),
        ((1, 1), "two different components"),
        ((0,), "two component numbers"),
        ((0.0, 1), "two component numbers"),
    ):
        with pytest.raises(ValueError, match=match):
            P.plot_pca_scores(pca, components=bad)
    with pytest.raises(ValueError, match="3 labels for the 4 samples"):
        P.plot_pca_scores(pca, ["a", "b", "c"])
    with pytest.raises(ValueError, match="2 names for the 4 samples"):
        P.plot_pca_scores(pca, names=["a", "b"])
    with pytest.raises(TypeError, match="TangentPCA"):
        P.plot_pca_scores(np.zeros((4, 2)))


# --------------------------------------------------------------------------------------------
# Import behaviour


def _run_fresh(script: str) -> str:
    hidden = ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")
    env = {k: v for k, v in os.environ.items() if k not in hidden}
    env["PYTHONPATH"] = REPO + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


_ROOT = "root = __import__('rootshape_jax').Root(main=np.c_[np.zeros(5), np.arange(5.0)])"


def test_import_and_plot_need_no_display_nor_pyplot(tmp_path):
    """Fresh interpreter, no display: import and plotting resolve no backend, use no pyplot."""
    out = _run_fresh(
        f"""
        import sys
        import numpy as np
        import matplotlib
        raw = matplotlib.rcParams._get_backend_or_none()
        import rootshape_jax.plot as P
        {_ROOT}
        fig, ax = P.plot_root(root)
        fig.savefig({str(tmp_path / "fresh.png")!r})
        assert matplotlib.rcParams._get_backend_or_none() == raw, "backend changed"
        assert "matplotlib.pyplot" not in sys.modules, "pyplot imported"
        print("ok")
        """
    )
    assert out.strip() == "ok"
    assert (tmp_path / "fresh.png").stat().st_size > 0


def test_import_keeps_backend_and_uses_pyplot_when_imported():
    """``matplotlib.get_backend()`` is the same before and after importing and plotting; with
    pyplot imported by the user, figures are pyplot's (so notebooks display them)."""
    out = _run_fresh(
        f"""
        import numpy as np
        import matplotlib
        before = matplotlib.get_backend()
        import rootshape_jax.plot as P
        assert matplotlib.get_backend() == before
        import matplotlib.pyplot as plt
        {_ROOT}
        fig, ax = P.plot_root(root)
        assert fig.number in plt.get_fignums()
        assert matplotlib.get_backend() == before
        print("ok", before)
        """
    )
    assert out.startswith("ok")


def test_import_in_process_keeps_backend(monkeypatch):
    before = matplotlib.get_backend()
    for name in [m for m in sys.modules if m.startswith("rootshape_jax.plot")]:
        monkeypatch.delitem(sys.modules, name)
    importlib.import_module("rootshape_jax.plot")
    assert matplotlib.get_backend() == before


def test_missing_matplotlib_raises_missing_dependency(monkeypatch):
    for name in [m for m in sys.modules if m.startswith("rootshape_jax.plot")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    with pytest.raises(MissingDependencyError, match="matplotlib"):
        importlib.import_module("rootshape_jax.plot")
    with pytest.raises(ImportError):  # still an ImportError for callers that catch that
        importlib.import_module("rootshape_jax.plot")
