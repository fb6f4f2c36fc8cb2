"""PERMANOVA against plain numpy / scipy references."""

import itertools

import numpy as np
import pytest
import scipy.spatial.distance as ssd
import scipy.stats

import rootshape_jax as rs


def _groups(seed=0, sizes=(6, 8, 5), shift=1.0, dim=1):
    rng = np.random.default_rng(seed)
    X = np.concatenate([rng.normal(size=(k, dim)) + shift * g for g, k in enumerate(sizes)])
    y = np.repeat(np.arange(len(sizes)), sizes)
    return X, y


def _reference_f(D, y):
    """Anderson (2001) written out with loops."""
    n = len(y)
    groups = np.unique(y)
    ss_t = sum(D[i, j] ** 2 for i in range(n) for j in range(i + 1, n)) / n
    ss_w = 0.0
    for g in groups:
        idx = np.flatnonzero(y == g)
        ss_w += sum(D[i, j] ** 2 for i, j in itertools.combinations(idx, 2)) / len(idx)
    a = len(groups)
    return ((ss_t - ss_w) / (a - 1)) / (ss_w / (n - a)), (ss_t - ss_w) / ss_t


def test_euclidean_pseudo_f_is_the_anova_f():
    X, y = _groups()
    D = ssd.squareform(ssd.pdist(X))
    res = rs.permanova(D, y, permutations=99, seed=1)
    f_ref = scipy.stats.f_oneway(*[X[y == g, 0] for g in np.unique(y)]).statistic
    np.testing.assert_allclose(res.pseudo_f, f_ref, rtol=1e-10)
    # R² = between / total sum of squares of the points.
    total = np.sum((X - X.mean()) ** 2)
    between = sum((y == g).sum() * (X[y == g].mean() - X.mean()) ** 2 for g in np.unique(y))
    np.testing.assert_allclose(res.r2, between / total, rtol=1e-10)
    assert res.n_groups == 3 and res.permutations == 99


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_loop_reference_on_non_euclidean_distances(seed):
    X, y = _groups(seed=seed, dim=3)
    D = ssd.squareform(ssd.pdist(X, "cityblock"))
    f_ref, r2_ref = _reference_f(D, y)
    res = rs.permanova(D, y, permutations=50, seed=seed)
    np.testing.assert_allclose([res.pseudo_f, res.r2], [f_ref, r2_ref], rtol=1e-10)


def test_p_value_is_the_permutation_count():
    X, y = _groups(seed=3, shift=0.3)
    D = ssd.squareform(ssd.pdist(X))
    res = rs.permanova(D, y, permutations=199, seed=7)
    # Plain reference: the same shuffles, one at a time.
    rng = np.random.default_rng(7)
    _, codes = np.unique(y, return_inverse=True)
    f0, _ = _reference_f(D, codes)
    count = sum(_reference_f(D, rng.permutation(codes))[0] >= f0 * (1 - 1e-12) for _ in range(199))
    assert res.p_value == pytest.approx((1 + count) / 200)
    # Separated groups: every shuffle has a smaller F.
    Xs, ys = _groups(seed=3, shift=20.0)
    far = rs.permanova(ssd.squareform(ssd.pdist(Xs)), ys, permutations=99)
    assert far.p_value == pytest.approx(1 / 100) and far.r2 > 0.95
    # Deterministic for a seed.
    assert rs.permanova(D, y, permutations=199, seed=7) == res


def test_bad_input():
    X, y = _groups()
    D = ssd.squareform(ssd.pdist(X))
    with pytest.raises(ValueError, match="groups"):
        rs.permanova(D, np.zeros(len(y)))
    with pytest.raises(ValueError, match="labels"):
        rs.permanova(D, y[:-1])
    with pytest.raises(ValueError, match="permutations"):
        rs.permanova(D, y, permutations=0)
    with pytest.raises(ValueError, match="symmetric"):
        rs.permanova(D + np.triu(np.ones_like(D)), y)
