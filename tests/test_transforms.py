"""`limit_laterals` (Root) and `scale_tree` (RootTree): checked against plain numpy loops."""

from __future__ import annotations

import numpy as np
import pytest

import rootshape_jax as rs
from rootshape_jax.datasets import synthetic_roots


def _lengths(lat):
    return float(np.sum(np.linalg.norm(np.diff(lat, axis=0), axis=1)))


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("n", [0, 1, 3, 6])
def test_limit_laterals_keeps_longest_as_subsequence(seed, n):
    root = synthetic_roots(1, seed=seed)[0]
    kept = rs.limit_laterals(root, n)
    m = root.n_laterals
    assert kept.n_laterals == min(n, m)
    # Reference: indices of the laterals kept, found by matching arrays (brute force).
    idx = [next(i for i in range(m) if np.array_equal(root.laterals[i], lat)) for lat in kept.laterals]
    assert idx == sorted(idx)  # original order
    dropped = [i for i in range(m) if i not in idx]
    if idx and dropped:
        assert min(_lengths(root.laterals[i]) for i in idx) >= max(_lengths(root.laterals[i]) for i in dropped)
    np.testing.assert_array_equal(kept.attach, root.attach[idx])
    np.testing.assert_array_equal(kept.main, root.main)
    assert kept.name == root.name and kept.metadata == root.metadata


def test_limit_laterals_ties_keep_the_earlier_and_children_follow():
    main = np.array([[0.0, 0.0], [0.0, 10.0]])
    lats = tuple(np.array([[0.0, y], [L, y]]) for y, L in [(1, 2.0), (2, 3.0), (3, 2.0), (4, 1.0)])
    children = tuple(rs.Root(main=lat, name=f"c{i}") for i, lat in enumerate(lats))
    root = rs.Root(main=main, laterals=lats, children=children)
    kept = rs.limit_laterals(root, 2)
    assert [c.name for c in kept.children] == ["c0", "c1"]  # lengths 2, 3 (c2 ties c0, later)
    assert rs.limit_laterals(root, None) is root
    assert rs.limit_laterals(root, 4) is root


@pytest.mark.parametrize("bad", [-1, 1.5, "2", True])
def test_limit_laterals_rejects_bad_n(bad):
    root = synthetic_roots(1, seed=0)[0]
    with pytest.raises(ValueError, match="whole number"):
        rs.limit_laterals(root, bad)


def test_scale_tree_matches_a_loop():
    rng = np.random.default_rng(0)
    tree = rs.batch(synthetic_roots(3, seed=2), n_points=15)
    scales = rng.uniform(0.3, 3.0, size=3)
    got = rs.scale_tree(tree, scales)
    main, lats = np.asarray(tree.main), np.asarray(tree.laterals)
    for b in range(3):
        o = main[b, 0]
        for t in range(main.shape[1]):
            np.testing.assert_allclose(np.asarray(got.main)[b, t], o + scales[b] * (main[b, t] - o), rtol=1e-12)
        for k in range(lats.shape[1]):
            for t in range(lats.shape[2]):
                np.testing.assert_allclose(
                    np.asarray(got.laterals)[b, k, t], o + scales[b] * (lats[b, k, t] - o), rtol=1e-12, atol=1e-12
                )
    np.testing.assert_array_equal(np.asarray(got.attach), np.asarray(tree.attach))
    np.testing.assert_array_equal(np.asarray(got.mask), np.asarray(tree.mask))


def test_scale_tree_lengths_scale_and_single_tree_takes_a_scalar():
    root = synthetic_roots(1, seed=4)[0]
    tree = rs.unstack(rs.batch([root], n_points=30))[0]
    got = rs.scale_tree(tree, 2.5)
    length = lambda m: np.sum(np.linalg.norm(np.diff(np.asarray(m), axis=0), axis=1))  # noqa: E731
    assert length(got.main) == pytest.approx(2.5 * length(tree.main), rel=1e-12)
    np.testing.assert_allclose(np.asarray(got.main)[0], np.asarray(tree.main)[0])


def test_scale_tree_keeps_dtype_and_checks_input():
    tree = rs.batch(synthetic_roots(2, seed=0), n_points=12)
    import jax
    import jax.numpy as jnp

    t32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, tree)
    assert rs.scale_tree(t32, [1.0, 2.0]).main.dtype == jnp.float32
    with pytest.raises(ValueError, match="one factor per root"):
        rs.scale_tree(tree, [1.0, 2.0, 3.0])
    with pytest.raises(Exception, match="finite and > 0"):
        rs.scale_tree(tree, [1.0, -2.0])
    with pytest.raises(TypeError, match="RootTree"):
        rs.scale_tree(rs.to_srvf(tree), [1.0, 2.0])


def test_scale_tree_moves_bases_as_a_loop():
    rng = np.random.default_rng(1)
    tree = rs.batch(synthetic_roots(3, seed=5), n_points=11, depth=3)
    scales = rng.uniform(0.3, 3.0, size=3)
    bases = rng.uniform(-1e3, 1e3, size=(3, 2))
    for base in (bases, bases[0]):  # one per root, or one for all
        got = rs.scale_tree(tree, scales, base=base)
        to = np.broadcast_to(base, (3, 2))
        main, lats = np.asarray(tree.main), np.asarray(tree.laterals)
        curves = np.asarray(tree.deeper[0].curves) if tree.deeper else None
        for b in range(3):
            o = main[b, 0]
            np.testing.assert_allclose(np.asarray(got.main)[b], to[b] + scales[b] * (main[b] - o), rtol=1e-12)
            np.testing.assert_allclose(
                np.asarray(got.laterals)[b], to[b] + scales[b] * (lats[b] - o), rtol=1e-12, atol=1e-9
            )
            if curves is not None:
                np.testing.assert_allclose(
                    np.asarray(got.deeper[0].curves)[b], to[b] + scales[b] * (curves[b] - o), rtol=1e-12, atol=1e-9
                )
    with pytest.raises(ValueError, match="base of shape"):
        rs.scale_tree(tree, scales, base=np.zeros((2, 2)))
