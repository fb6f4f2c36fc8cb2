"""`distance` is exactly symmetric and agrees with `pairwise_distances` and `cross_distances`
(issue: the alternation's local optimum depended on which root was registered onto which)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import random_root

import rootshape_jax as rs


@pytest.fixture(scope="module")
def trees():
    rng = np.random.default_rng(7)
    roots = [random_root(rng, n_laterals=k) for k in (4, 5, 3, 5, 4, 2)]
    return rs.batch(roots, n_points=30, normalise_scale=True)


def test_distance_is_exactly_symmetric_and_matches_the_matrices(trees):
    singles = rs.unstack(trees)
    n = len(singles)
    D = np.asarray(rs.pairwise_distances(trees, progress=False))
    C = np.asarray(rs.cross_distances(trees, trees, progress=False))
    asymmetric_registrations = 0
    for i in range(n):
        for j in range(i + 1, n):
            dij = float(rs.distance(singles[i], singles[j]))
            dji = float(rs.distance(singles[j], singles[i]))
            assert dij == dji
            np.testing.assert_allclose([D[i, j], C[i, j], C[j, i]], dij, rtol=1e-12, atol=0)
            rij = float(rs.register(singles[i], singles[j]).distance)
            rji = float(rs.register(singles[j], singles[i]).distance)
            asymmetric_registrations += rij != rji
    # The test exercises the problem: some registrations differ with the argument order.
    assert asymmetric_registrations > 0
    np.testing.assert_allclose(C, C.T, rtol=1e-12, atol=0)


def test_batched_distance_is_symmetric(trees):
    a = rs.to_srvf(trees)
    import jax

    b = jax.tree.map(lambda x: x[::-1], a)
    d1 = np.asarray(rs.distance(a, b))
    d2 = np.asarray(rs.distance(b, a))
    assert np.array_equal(d1, d2)


def _root_with_one_lateral(s, length, seed=np.array([300.0, 500.0])):
    main = seed + np.c_[np.zeros(11), -np.linspace(0.0, 10.0, 11)]
    base = main[0] + np.array([0.0, -10.0 * s])
    lateral = base + np.c_[np.linspace(0.0, length, 6), np.zeros(6)]
    return rs.Root(main=main, laterals=(lateral,), attach=np.array([s]))


@pytest.mark.parametrize("delta", [3e-3, 3e-5, 1e-8, 0.0])
def test_pair_order_is_the_same_in_float32_and_float64(delta):
    # Normalised main roots all have length 1: the order is read from the next key entries,
    # with one tolerance for every dtype, so float32 and float64 register the pair alike
    # (a dtype-dependent tolerance ordered such pairs differently).
    from rootshape_jax._engine import canonical_pairs

    a, b = _root_with_one_lateral(0.6, 3.0), _root_with_one_lateral(0.3, 3.0 * (1 + delta))
    first = {}
    for dtype in (np.float32, np.float64):
        ta, tb = (
            rs.stack([t])
            for t in rs.unstack(rs.to_srvf(rs.batch([a, b], n_points=20, normalise_scale=True, dtype=dtype)))
        )
        f_ab, _ = canonical_pairs(ta, tb)
        f_ba, _ = canonical_pairs(tb, ta)
        # Either argument order puts the same root first.
        assert float(f_ab.s[0, 0]) == pytest.approx(float(f_ba.s[0, 0]))
        first[dtype] = round(float(f_ab.s[0, 0]), 3)
    assert first[np.float32] == first[np.float64]
