"""Ties among interchangeable slots are settled one fixed way (`_engine.canonical_matching`).

Null slots, and a Karcher mean's zero-length slots with equal attachments, have equal cost rows,
so an optimal assignment may permute their partners at exactly the same cost. The solver's pick
then rests on rounding noise elsewhere in the matrix, and a mean, which averages slot by slot,
took another path from inputs differing by 1e-16. The engine now returns one canonical choice.
"""

from __future__ import annotations

import itertools

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root
from test_axes import _taproots
from test_hierarchy import deep_root

import rootshape_jax as rs
from rootshape_jax._engine import canonical_matching, tie_classes

T = 12
NB = 4
W = rs.Weights(main=0.3, lateral=1.0, position=0.7)


# --------------------------------------------------------------------------------------------
# The canonical choice, against every optimal assignment found by brute force


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    "class_a, class_b",
    [
        ([0, 1, 1, 3, 3, 3], [0, 1, 2, 2, 4, 4]),
        ([0, 0, 0, 0, 4, 5], [0, 1, 2, 3, 3, 3]),
        ([0, 1, 2, 3, 4, 5], [0, 0, 2, 2, 2, 5]),
    ],
)
def test_every_optimal_assignment_settles_to_one(seed, class_a, class_b):
    rng = np.random.default_rng(seed)
    class_a, class_b = np.array(class_a), np.array(class_b)
    K = class_a.size
    real_b = (rng.random(K) < 0.6)[class_b]  # a class is all real or all null
    # Integer costs, equal within a class of rows or columns, so tied sums are exactly equal.
    table = rng.integers(0, 1000, size=(K, K)).astype(np.float64)
    cost = table[class_a][:, class_b]
    totals = {p: cost[np.arange(K), p].sum() for p in itertools.permutations(range(K))}
    best = min(totals.values())
    optima = [np.array(p) for p, c in totals.items() if c == best]
    assert len(optima) > 1  # the cases do have ties
    settled = {}
    for p in optima:
        new, rows_from, cols_from = (
            np.asarray(x)
            for x in canonical_matching(jnp.asarray(p), jnp.asarray(class_a), jnp.asarray(class_b), jnp.asarray(real_b))
        )
        assert sorted(new.tolist()) == list(range(K))
        assert cost[np.arange(K), new].sum() == best
        # Each new pair stands for an old pair of the same classes.
        np.testing.assert_array_equal(cols_from[new], p[rows_from])
        np.testing.assert_array_equal(class_a[rows_from], class_a)
        np.testing.assert_array_equal(class_b[cols_from], class_b)
        # Optima that match the same classes (they differ only within classes) settle to one.
        classes = tuple(sorted(zip(class_a.tolist(), class_b[p].tolist())))
        settled.setdefault(classes, set()).add(tuple(new.tolist()))
    assert all(len(s) == 1 for s in settled.values()), settled


def test_tie_classes_group_only_empty_equal_slots():
    tree = rs.to_srvf(rs.batch([random_root(np.random.default_rng(0), n_laterals=3)], n_points=T, max_laterals=7))
    classes = np.asarray(tie_classes(tree))[0]
    np.testing.assert_array_equal(classes, [0, 1, 2, 3, 3, 3, 3])  # real laterals apart, nulls together
    # A mean's unreached slots: real, zero length; alike only with the same attachment.
    mean_like = eqx.tree_at(
        lambda t: (t.mask, t.s),
        tree,
        (jnp.ones_like(tree.mask), tree.s.at[0, 5].set(0.5)),
    )
    np.testing.assert_array_equal(np.asarray(tie_classes(mean_like))[0], [0, 1, 2, 3, 3, 5, 3])
    # A zero-length real slot is not a null one.
    mixed = eqx.tree_at(lambda t: t.mask, tree, tree.mask.at[0, 4].set(True))
    np.testing.assert_array_equal(np.asarray(tie_classes(mixed))[0], [0, 1, 2, 3, 4, 3, 3])


# --------------------------------------------------------------------------------------------
# Through the engine


def _pair(depth: int):
    rng = np.random.default_rng(11)
    if depth == 2:
        ra, rb = random_root(rng, n_laterals=2), random_root(rng, n_laterals=5)
        return rs.to_srvf(rs.batch([ra, rb], n_points=T, max_laterals=8, dtype=np.float64))
    ra, rb = deep_root(rng, n_laterals=2), deep_root(rng, n_laterals=4, max_sub=2)
    return rs.to_srvf(rs.batch([ra, rb], n_points=T, depth=3, max_children=(7, 3), dtype=np.float64))


def _perturbed(t, eps):
    return eqx.tree_at(lambda x: x.q, t, t.q * (1 + eps))


@pytest.mark.parametrize("depth", [2, 3])
@pytest.mark.parametrize("template", ["nulls", "mean-like"])
def test_unmatched_laterals_fill_the_free_slots_in_order_whatever_the_noise(depth, template):
    a, b = rs.unstack(_pair(depth))
    if template == "mean-like":
        # As a Karcher mean fits: every slot real, the unreached ones of zero length at 0.
        a = eqx.tree_at(lambda t: t.mask, a, jnp.ones_like(a.mask))
    free = ~np.asarray(rs.to_srvf(rs.unstack(_pair(depth))[0]).mask)
    real_b = np.asarray(b.mask)
    results = []
    for eps in (0.0, 1e-15, -1e-15, 3e-15, -4e-15):
        reg = rs.register(a, _perturbed(b, eps), weights=W, neighbourhood=NB, progress=False)
        perm = np.asarray(reg.permutation)
        # The free slots take b's remaining real laterals in b's order, then b's nulls in order.
        held = perm[free]
        n_real = int(real_b[held].sum())
        assert real_b[held][:n_real].all() and not real_b[held][n_real:].any()
        assert np.all(np.diff(held[:n_real]) > 0) and np.all(np.diff(held[n_real:]) > 0)
        # The stored warps and children moved with their pairs: the registered tree's energy
        # is the engine's.
        np.testing.assert_allclose(float(reg.terms.total), float(reg.energy), rtol=1e-12, atol=1e-14)
        results.append(reg)
    for reg in results[1:]:
        np.testing.assert_array_equal(np.asarray(reg.permutation), np.asarray(results[0].permutation))
        for x, y in zip(reg.child_permutations, results[0].child_permutations):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        np.testing.assert_allclose(float(reg.energy), float(results[0].energy), rtol=1e-12)


def test_karcher_mean_is_the_same_from_inputs_differing_by_rounding():
    # The regression: 1e-15 in the samples sent sample 3's laterals to other null slots of the
    # medoid, and the mean down another path (F 0.4349 against 0.4298).
    roots = _taproots()
    taps = rs.to_srvf(rs.batch(roots, n_points=T, dtype=np.float64))
    opts = dict(weights=W, registration={"neighbourhood": NB}, n_starts=1, progress=False)
    base = rs.karcher_mean(taps, **opts)
    for eps in (1e-15, -2e-15):
        other = rs.karcher_mean(_perturbed(taps, eps), **opts)
        assert int(other.steps) == int(base.steps)
        np.testing.assert_allclose(np.asarray(other.energy_trace), np.asarray(base.energy_trace), rtol=1e-9)
