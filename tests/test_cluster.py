"""Hierarchical clustering and leave-one-out classification from distance matrices."""

import numpy as np
import pytest
import scipy.cluster.hierarchy as sch
import scipy.spatial.distance as ssd
from helpers import random_root, rotation_matrix

import rootshape_jax as rs
from rootshape_jax._cluster import (
    Clustering,
    class_mean_distances,
    cluster,
    confusion_matrix,
    loo_accuracy,
)


def _points(seed=0, n=(5, 7), sep=3.0, dim=4):
    rng = np.random.default_rng(seed)
    X = np.concatenate([rng.normal(size=(k, dim)) + sep * c for c, k in enumerate(n)])
    y = np.repeat(np.arange(len(n)), n)
    return X, y


def _D(X):
    return ssd.squareform(ssd.pdist(X))


def _same_partition(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.array_equal(a[:, None] == a[None], b[:, None] == b[None])


@pytest.mark.parametrize("method", ["single", "complete", "average", "weighted", "ward"])
def test_cluster_matches_scipy(method):
    X, _ = _points(1, (4, 5, 6), sep=1.0)
    D = _D(X)
    res = cluster(D, n_clusters=3, method=method)
    assert isinstance(res, Clustering) and res.n_clusters == 3
    # Leaves in optimal order (as the heat maps): the same merges, so the same partition.
    Z = sch.linkage(ssd.pdist(X), method=method, optimal_ordering=True)
    np.testing.assert_allclose(res.linkage, Z)
    plain = sch.linkage(ssd.pdist(X), method=method)
    np.testing.assert_allclose(np.sort(res.linkage[:, 2]), np.sort(plain[:, 2]))
    assert _same_partition(res.labels, sch.fcluster(Z, 3, "maxclust"))
    assert _same_partition(res.labels, sch.fcluster(plain, 3, "maxclust"))
    np.testing.assert_array_equal(res.order, sch.leaves_list(Z))
    # Labels are numbered by first appearance along the dendrogram.
    first = [res.labels[i] for i in res.order]
    assert first[0] == 0 and sorted(set(first)) == [0, 1, 2]


def test_cut_at_height():
    X, y = _points(2, (4, 4), sep=10.0)
    res = cluster(_D(X), n_clusters=None, height=8.0, method="complete")
    assert _same_partition(res.labels, y)


def test_loo_nearest_neighbour_matches_brute_force():
    X, y = _points(3, (6, 6), sep=1.2)
    D = _D(X)
    out = loo_accuracy(D, y)
    pred = []
    for i in range(len(y)):
        best, lab = np.inf, None
        for j in range(len(y)):
            if j != i and D[i, j] < best:
                best, lab = D[i, j], y[j]
        pred.append(lab)
    np.testing.assert_array_equal(out["predicted"], pred)
    np.testing.assert_allclose(out["accuracy"], np.mean(np.array(pred) == y))


def test_nearest_mean_is_exact_for_euclidean_points():
    X, y = _points(4, (5, 6, 4), sep=1.0, dim=3)
    D = _D(X)
    d2, classes = class_mean_distances(D, y, leave_out=True)
    for i in range(len(y)):
        for c, cls in enumerate(classes):
            members = [j for j in range(len(y)) if y[j] == cls and j != i]
            m = X[members].mean(axis=0)
            np.testing.assert_allclose(d2[i, c], np.sum((X[i] - m) ** 2), rtol=1e-9, atol=1e-12)
    out = loo_accuracy(D, y, rule="nearest_mean")
    ref = classes[np.argmin(d2, axis=1)]
    np.testing.assert_array_equal(out["predicted"], ref)


def test_confusion_matrix():
    C, classes = confusion_matrix(["a", "a", "b", "b"], ["a", "b", "b", "b"])
    np.testing.assert_array_equal(classes, ["a", "b"])
    np.testing.assert_array_equal(C, [[1, 1], [0, 2]])


def test_confusion_matrix_refuses_cluster_numbers_for_classes():
    """Found on the plate: dates (strings) against cluster numbers raised KeyError: 0."""
    dates = np.array(["19 Nov", "19 Nov", "20 Nov", "21 Nov", "21 Nov"])
    with pytest.raises(ValueError, match="contingency_table"):
        confusion_matrix(dates, np.array([0, 0, 1, 1, 2]))
    with pytest.raises(ValueError, match="not among classes"):
        confusion_matrix(["a", "b"], ["a", "c"], classes=["a", "b"])
    # Integer classes predicted as integer classes stay a confusion matrix.
    C, classes = confusion_matrix([1, 2, 2], [1, 1, 3])
    np.testing.assert_array_equal(classes, [1, 2, 3])
    np.testing.assert_array_equal(C, [[1, 0, 0], [1, 0, 1], [0, 0, 0]])


def test_contingency_table_against_counting():
    rng = np.random.default_rng(5)
    dates = rng.choice(["19 Nov", "20 Nov", "21 Nov"], size=40)
    clusters = rng.integers(0, 4, size=40)
    T, classes, ids = rs.contingency_table(dates, clusters)
    assert classes.tolist() == sorted(set(dates.tolist())) and ids.tolist() == sorted(set(clusters.tolist()))
    for i, c in enumerate(classes):
        for j, k in enumerate(ids):
            assert T[i, j] == np.sum((dates == c) & (clusters == k))
    assert T.sum() == 40
    # From a real clustering: each cluster's column counts its members.
    pts, labels = _points()
    cl = cluster(_D(pts), n_clusters=3)
    T, classes, ids = rs.contingency_table(labels, cl.labels)
    np.testing.assert_array_equal(T.sum(axis=0), np.bincount(cl.labels))
    with pytest.raises(ValueError, match="one length"):
        rs.contingency_table(dates, clusters[:5])


def test_bad_input():
    D = _D(_points()[0])
    with pytest.raises(ValueError, match="square"):
        cluster(D[:3])
    bad = D.copy()
    bad[0, 1] += 1
    with pytest.raises(ValueError, match="symmetric"):
        cluster(bad)
    bad = D.copy()
    bad[0, 1] = bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        cluster(bad)
    with pytest.raises(ValueError, match="method"):
        cluster(D, method="kmeans")
    with pytest.raises(ValueError, match="exactly one"):
        cluster(D, n_clusters=2, height=1.0)
    with pytest.raises(ValueError, match="rule"):
        loo_accuracy(D, np.zeros(len(D)), rule="svm")
    with pytest.raises(ValueError, match="labels"):
        loo_accuracy(D, np.zeros(3))


def _condition(rng, template, n):
    """n members of a condition: the template turned at random, lateral lengths and
    positions perturbed a little."""
    out = []
    for _ in range(n):
        O = rotation_matrix(rng, 2)
        o = template.main[0]
        rot = lambda p: (p - o) @ O.T + o  # noqa: E731
        lats = [rot(lat[0] + (lat - lat[0]) * rng.uniform(0.9, 1.1)) for lat in template.laterals]
        attach = np.clip(template.attach + rng.normal(0, 0.02, template.n_laterals), 0.05, 0.95)
        out.append(rs.Root(main=rot(template.main), laterals=lats, attach=attach))
    return out


def test_two_conditions_are_separated_perfectly():
    """Elastic distances between two synthetic conditions: one short lateral vs. four long
    ones, members varying in pose, lateral lengths and positions."""
    rng = np.random.default_rng(51)
    sparse = random_root(rng, n_laterals=1)
    dense = random_root(rng, n_laterals=4)
    dense = rs.Root(
        main=dense.main, laterals=[lat[0] + (lat - lat[0]) * 2.0 for lat in dense.laterals], attach=dense.attach
    )
    roots = _condition(rng, sparse, 3) + _condition(rng, dense, 3)
    labels = np.array([0, 0, 0, 1, 1, 1])
    trees = rs.batch(roots, n_points=30)
    D = np.asarray(rs.pairwise_distances(trees, progress=False))
    for method in ("average", "complete", "single"):
        assert _same_partition(cluster(D, n_clusters=2, method=method).labels, labels)
    assert loo_accuracy(D, labels)["accuracy"] == 1.0
    assert loo_accuracy(D, labels, rule="nearest_mean")["accuracy"] == 1.0


@pytest.mark.parametrize("method", ["average", "complete", "single"])
def test_heat_map_and_dendrogram_show_one_leaf_order(method):
    """`rootshape cluster` draws distances.png and dendrogram.png: both in the leaf order of
    the clustering's linkage, and every cluster's colour under its leaves (one-root ones too)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rootshape_jax.plot import plot_dendrogram, plot_distance_matrix

    X, _ = _points(2, (5, 6, 1), sep=1.5)
    D = _D(X)
    names = [f"r{i}" for i in range(len(D))]
    res = cluster(D, n_clusters=3, method=method)
    fig1, axes = plot_distance_matrix(D, labels=names, method=method)
    heat = [t.get_text() for t in axes["matrix"].get_yticklabels()]
    fig2, dax = plot_dendrogram(res.linkage, labels=names, n_clusters=3)
    tree = [t.get_text() for t in dax["dendrogram"].get_xticklabels()]
    assert heat == tree == [names[i] for i in res.order]
    dots = dax["dendrogram"].collections[-1].get_facecolors()
    assert len(dots) == len(D) and len({tuple(c) for c in dots}) == 3  # a colour per cluster
    plt.close(fig1)
    plt.close(fig2)


def test_dendrogram_clusters_take_the_colour_of_their_label():
    """With a label strip, a cluster made mostly of one label value is drawn in that value's
    strip colour (one-to-one pairing); the clusters left over get colours no value uses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt

    from rootshape_jax.plot import label_colors, plot_dendrogram
    from rootshape_jax.plot._clusters import cluster_colors

    # Four groups; the labels name three of them in an order unlike the clusters' left-to-right one.
    X, y = _points(3, (5, 6, 4, 3), sep=6.0)
    names = np.array(["zinc", "alpha", "mid", "mid"])[y]
    names[y == 3] = np.array(["zinc", "alpha", "mid"])[np.arange(3)]  # the 4th group is mixed
    res = cluster(_D(X), n_clusters=4)
    fig, axes = plot_dendrogram(
        res.linkage, labels=[f"r{i}" for i in range(len(y))], n_clusters=4, strips={"treatment": list(names)}
    )
    colors = axes["cluster_colors"]
    strip = label_colors(names)
    for c in range(4):
        members = names[res.labels == c]
        values, counts = np.unique(members, return_counts=True)
        if counts.max() == len(members):  # a pure cluster: its value's colour
            assert colors[c] == strip[values[0]]
    assert len(set(colors)) == 4
    # "mid" pairs with its pure cluster, so the mixed one takes a colour no value uses.
    mixed = [c for c in range(4) if len(set(names[res.labels == c])) > 1]
    assert len(mixed) == 1 and colors[mixed[0]] not in strip.values()
    # The tree's dots under the leaves use the same colours.
    dots = [mcolors.to_hex(c) for c in axes["dendrogram"].collections[-1].get_facecolors()]
    assert dots == [colors[res.labels[i]] for i in res.order]
    plt.close(fig)
    # Without a strip: the fixed palette in cluster order.
    from rootshape_jax.plot import slot_color

    assert cluster_colors(np.array([0, 1, 2, 1])) == [slot_color(k) for k in range(3)]
