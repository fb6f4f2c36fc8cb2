"""Classical MDS (`rootshape_jax.mds`) and pairwise group tests with Holm's correction."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import rootshape_jax as rs


def euclidean(X):
    return np.linalg.norm(X[:, None, :] - X[None, :, :], axis=-1)


def reference_mds(D, k):
    """Torgerson MDS written out with the centring matrix J (the textbook form)."""
    n = D.shape[0]
    J = np.eye(n) - np.ones((n, n)) / n
    B = -0.5 * J @ (D**2) @ J
    w, V = np.linalg.eigh(B)
    idx = np.argsort(w)[::-1][:k]
    return V[:, idx] * np.sqrt(np.maximum(w[idx], 0)), w[np.argsort(w)[::-1]]


@pytest.mark.parametrize("dim", [2, 3])
def test_recovers_a_euclidean_configuration_up_to_rigid_motion(dim):
    rng = np.random.default_rng(dim)
    X = rng.normal(size=(9, dim)) * [3.0, 1.0, 0.3][:dim]
    D = euclidean(X)
    res = rs.mds(D, n_components=dim)
    E = res.embedding
    assert E.shape == (9, dim)
    np.testing.assert_allclose(euclidean(E), D, atol=1e-10)
    # Orthogonal Procrustes: the centred configuration is E rotated / reflected.
    Xc = X - X.mean(0)
    U, _, Vt = np.linalg.svd(E.T @ Xc)
    np.testing.assert_allclose(E @ (U @ Vt), Xc, atol=1e-10)
    np.testing.assert_allclose(np.sum(res.proportion_explained), 1.0, atol=1e-12)
    assert np.all(np.abs(res.eigenvalues[dim:]) < 1e-9)


def test_agrees_with_the_numpy_reference_on_non_euclidean_distances():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(12, 5))
    D = np.abs(X[:, None, :] - X[None, :, :]).sum(-1) ** 1.5  # not Euclidean-embeddable
    res = rs.mds(D, n_components=3)
    ref, w = reference_mds(D, 3)
    np.testing.assert_allclose(res.eigenvalues, w, atol=1e-10)
    assert np.any(res.eigenvalues < -1e-6)  # non-Euclidean: negative eigenvalues are kept
    for j in range(3):  # eigenvectors up to sign
        s = np.sign(res.embedding[:, j] @ ref[:, j])
        np.testing.assert_allclose(res.embedding[:, j], s * ref[:, j], atol=1e-9)
    np.testing.assert_allclose(res.proportion_explained, w[:3] / w[w > 0].sum(), atol=1e-12)


def test_deterministic_sign_and_one_component():
    X = np.array([[0.0], [1.0], [3.0], [7.0]])
    res = rs.mds(euclidean(X), n_components=1)
    assert res.n_components == 1
    e = res.embedding[:, 0]
    assert e[np.argmax(np.abs(e))] > 0
    np.testing.assert_allclose(np.abs(e[:, None] - e[None, :]), euclidean(X), atol=1e-12)


@pytest.mark.parametrize(
    ("D", "k", "fragment"),
    [
        (np.zeros((3, 4)), 2, "square"),
        (np.array([[0.0, 1.0, 2.0], [1.5, 0.0, 1.0], [2.0, 1.0, 0.0]]), 2, "symmetric"),
        (np.array([[0.0, np.nan], [np.nan, 0.0]]), 1, "NaN"),
        (np.array([[0.0, -1.0], [-1.0, 0.0]]), 1, "non-negative"),
        (np.zeros((3, 3)), 3, "between 1 and n - 1"),
        (np.zeros((3, 3)), 0, "between 1 and n - 1"),
        (np.zeros((3, 3)), 1.5, "whole number"),
    ],
)
def test_bad_input(D, k, fragment):
    with pytest.raises(ValueError, match=fragment):
        rs.mds(D, n_components=k)


def test_holm_matches_a_brute_force_reference():
    rng = np.random.default_rng(1)
    for m in (1, 2, 5, 9):
        p = rng.uniform(0, 0.2, size=m)
        order = np.argsort(p)
        ref = np.empty(m)
        running = 0.0
        for i, j in enumerate(order):
            running = max(running, min(1.0, (m - i) * p[j]))
            ref[j] = running
        np.testing.assert_allclose(rs.holm(p), ref)


def test_pairwise_permanova_runs_each_pair_on_its_submatrix():
    rng = np.random.default_rng(3)
    X = np.concatenate([rng.normal(size=(6, 2)), rng.normal(size=(6, 2)) + [4, 0], rng.normal(size=(6, 2)) + [4.2, 0]])
    D = euclidean(X)
    labels = np.array(["a"] * 6 + ["b"] * 6 + ["c"] * 6)
    tests = rs.pairwise_permanova(D, labels, permutations=199, seed=5)
    assert [(t.group_a, t.group_b) for t in tests] == list(itertools.combinations("abc", 2))
    for k, t in enumerate(tests):
        idx = np.flatnonzero(np.isin(labels, [t.group_a, t.group_b]))
        one = rs.permanova(D[np.ix_(idx, idx)], labels[idx], permutations=199, seed=5 + k)
        assert (t.pseudo_f, t.p_value, t.r2) == (one.pseudo_f, one.p_value, one.r2)
        assert t.n_a == t.n_b == 6
    np.testing.assert_allclose([t.p_adjusted for t in tests], rs.holm([t.p_value for t in tests]))
    by = {(t.group_a, t.group_b): t for t in tests}
    assert by[("a", "b")].p_adjusted < 0.05 and by[("b", "c")].p_value > 0.05  # far apart vs overlapping
