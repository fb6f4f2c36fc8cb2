"""Registration of whole root systems (issue 15, docs/design.md §11): depth 3 equals the slow
recursive reference (tests/helpers.reference_tree_distance), with and without pruning, and has
the metric's invariances."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from helpers import reference_tree_distance
from test_hierarchy import deep_root

import rootshape_jax as rs

T = 10
NB = 4  # DP neighbourhood (small grid, small moves: a fast reference)
CAPACITIES = (8, 6)  # one shape for every tree here: one compilation
W = rs.Weights(main=0.3, lateral=1.0, position=0.7)


def _batch(roots):
    return rs.batch(roots, n_points=T, depth=3, max_children=CAPACITIES, dtype=np.float64)


@pytest.fixture(scope="module")
def systems():
    rng = np.random.default_rng(12)
    return [deep_root(rng, n_laterals=3, max_sub=2) for _ in range(4)]


def _register(a, b, **kw):
    ta, tb = rs.unstack(_batch([a, b]))
    return rs.register(ta, tb, weights=W, neighbourhood=NB, **kw)


def _rigid(root: rs.Root, angle: float, shift) -> rs.Root:
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])

    def move(r):
        return dataclasses.replace(
            r,
            main=r.main @ R.T + shift,
            laterals=tuple(lat @ R.T + shift for lat in r.laterals),
            children=tuple(move(k) for k in r.children),
        )

    return move(root)


def _reversed_children(root: rs.Root) -> rs.Root:
    """The same system with the children listed in reverse order at every level."""
    kids = [_reversed_children(k) for k in root.children]
    order = list(range(root.n_laterals))[::-1]
    flipped = root.select_laterals(order)
    return dataclasses.replace(flipped, children=tuple(kids[::-1])) if kids else flipped


@pytest.mark.parametrize("pair", [(0, 1), (2, 3)])
def test_depth_three_equals_the_recursive_reference(systems, pair):
    a, b = (systems[i] for i in pair)
    e_ref, info = reference_tree_distance(a, b, W, 3, n_points=T, neighbourhood=NB, max_children=CAPACITIES)
    reg = _register(a, b)
    assert abs(float(reg.energy) - e_ref) < 1e-9, (float(reg.energy), e_ref)
    assert info["n_dp"][2] > 0  # the pair has second-order laterals to match
    # The registered tree holds b's branches in a's slots at every level.
    assert reg.registered.depth == 3 and len(reg.child_permutations) == 1
    assert reg.n_deeper_dp.shape == (1,)


@pytest.mark.slow
def test_pruning_changes_no_distance_and_saves_dps(systems):
    n_pruned = n_full = 0
    for i, j in [(0, 1), (1, 2), (2, 3), (0, 3)]:
        pruned = _register(systems[i], systems[j])
        full = _register(systems[i], systems[j], prune=False)
        assert abs(float(pruned.energy) - float(full.energy)) < 1e-12
        n_pruned += int(pruned.n_lateral_dp) + int(np.sum(pruned.n_deeper_dp))
        n_full += int(full.n_lateral_dp) + int(np.sum(full.n_deeper_dp))
    assert n_pruned < n_full


def test_invariances_and_self_distance(systems):
    a, b = systems[0], systems[1]
    e = float(_register(a, b).energy)
    assert float(_register(a, a).energy) == pytest.approx(0.0, abs=1e-12)
    # Rigid motion of b, and the order of the children at every level.
    moved = _rigid(b, 0.9, np.array([40.0, -25.0]))
    assert float(_register(a, moved).energy) == pytest.approx(e, abs=1e-9)
    assert float(_register(a, _reversed_children(b)).energy) == pytest.approx(e, abs=1e-9)
    assert float(_register(_reversed_children(a), b).energy) == pytest.approx(e, abs=1e-9)


def test_reparameterising_a_branch_changes_the_distance_little(systems):
    # SRVF level: a warp of one second-order lateral of b (norm kept) is undone by its DP, up
    # to the DP's discretisation; the distance changes by far less than the branch's size.
    a, b = systems[0], systems[1]
    t = rs.to_srvf(_batch([a, b]))
    ta, tb = rs.unstack(t)
    lv = tb.deeper[0]
    k = tuple(np.argwhere(np.asarray(lv.mask))[0])
    from rootshape_jax._engine import warp_preserving_norm

    gamma = np.linspace(0.0, 1.0, T) ** 1.3
    q = lv.q.at[k].set(warp_preserving_norm(lv.q[k], gamma))
    warped = dataclasses.replace(tb, deeper=(dataclasses.replace(lv, q=q),))
    e0 = float(rs.register(ta, tb, weights=W, neighbourhood=NB).energy)
    e1 = float(rs.register(ta, warped, weights=W, neighbourhood=NB).energy)
    size = float(rs.l2_norm_squared(lv.q[k]))
    assert abs(e1 - e0) < 0.1 * size, (e0, e1, size)


def test_distance_matrix_at_depth_three(systems):
    trees = _batch(systems)
    D = np.asarray(rs.pairwise_distances(trees, weights=W, neighbourhood=NB, chunk_size=4, progress=False))
    np.testing.assert_allclose(D, D.T, atol=0)
    assert np.all(np.diag(D) == 0)
    one = float(rs.distance(*rs.unstack(jax.tree.map(lambda x: x[:2], trees)), weights=W, neighbourhood=NB))
    assert D[0, 1] == pytest.approx(one, rel=1e-12)
    assert np.all(D[np.triu_indices(4, 1)] > 0)


@pytest.mark.slow
def test_depth_three_without_second_order_is_depth_two(systems):
    flat = [dataclasses.replace(r, children=()) for r in systems[:2]]
    d3 = rs.distance(*rs.unstack(_batch(flat)), weights=W, neighbourhood=NB)
    d2 = rs.distance(
        *rs.unstack(rs.batch(flat, n_points=T, max_laterals=8, dtype=np.float64)), weights=W, neighbourhood=NB
    )
    assert float(d3) == pytest.approx(float(d2), abs=1e-12)


def _deviation(points: np.ndarray, curves: np.ndarray) -> float:
    """Largest distance from `points` [n, d] to the nearest of the polylines `curves` [m, T, d]
    (each densely resampled)."""
    t = np.linspace(0.0, 1.0, 400)
    dense = np.concatenate(
        [np.stack([np.interp(t, np.linspace(0, 1, len(c)), c[:, k]) for k in range(c.shape[1])], 1) for c in curves]
    )
    return float(np.max(np.min(np.linalg.norm(points[:, None] - dense[None], axis=-1), axis=1)))


@pytest.mark.slow
def test_geodesic_at_depth_three_runs_between_the_systems(systems):
    # In place, the path starts at a and ends at b as given, at every level: each real branch
    # of either end lies on a branch of the same order of that system as the SRVFs represent
    # it (`to_curves(to_srvf(·))`). At b's end the branches are b's reparameterised by the
    # registration's warps, which the coarse DP here (T = 30, neighbourhood 4) resolves to a
    # few per cent of the length: measured 2.6 % on the main root, hence 5 %.
    trees = rs.batch(systems[:2], n_points=30, depth=3, max_children=CAPACITIES, dtype=np.float64)
    a, b = rs.unstack(trees)
    path = rs.geodesic(a, b, n_steps=5, weights=W, neighbourhood=NB, in_place=True)
    assert path.depth == 3
    scale = float(np.sum(np.linalg.norm(np.diff(np.asarray(a.main), axis=0), axis=1)))
    for end, tree in ((0, rs.to_curves(rs.to_srvf(a))), (-1, rs.to_curves(rs.to_srvf(b)))):
        assert _deviation(np.asarray(path.main[end]), np.asarray(tree.main)[None]) < 0.05 * scale
        curves = np.asarray(path.deeper[0].curves[end])
        # Branches of the other system only (zero length at this end) sit on their parent.
        length = np.sum(np.linalg.norm(np.diff(curves, axis=-2), axis=-1), axis=-1)
        got = curves[np.asarray(path.deeper[0].mask[end]) & (length > 1e-9)]
        want = np.asarray(tree.deeper[0].curves)[np.asarray(tree.deeper[0].mask)]
        assert got.shape == want.shape
        assert _deviation(got.reshape(-1, 2), want) < 0.05 * scale


@pytest.mark.parametrize("pair", [(1, 2), (2, 3)])
def test_kept_children_assignments_equal_solving_the_children_again(systems, pair):
    # The lateral assignment keeps each nested children's assignment; the matched pairs'
    # children registrations are built from them (only their DPs run again). Solving each
    # matched pair's children again must give the same real-real matches, with warps of the
    # same energy (a null slot's partner may differ: those are ties of equal cost).
    import jax.numpy as jnp

    from rootshape_jax import _engine
    from rootshape_jax._warp import warp_energy

    a, b = rs.unstack(rs.to_srvf(_batch([systems[i] for i in pair])))
    a, b = (jax.tree.map(lambda x: x[None], t) for t in (a, b))
    options = rs.RegistrationOptions(neighbourhood=NB)
    p = _engine.prepare(a, b, W)
    O = _engine.starting_rotation(p.a, p.b)
    rows = jnp.ones((1,), bool)
    _, perm, _, _, _, _, _, kept = _engine.assign_at(p, O, rows, options, with_main=True)
    matched = _engine.matched_slots(p, perm, rows)
    ((new_perm, new_warp),) = _engine.child_registrations(p, O, perm, matched, options, kept)[0]
    ((old_perm, old_warp),) = _engine.child_registrations(p, O, perm, matched, options)[0]
    ma, mb = np.asarray(p.a.deeper[0].mask[0]), np.asarray(p.b.deeper[0].mask[0])
    n_real_real = 0
    for i in np.flatnonzero(np.asarray(matched[0])):
        j = int(perm[0, i])
        for k in np.flatnonzero(ma[i]):
            new_l, old_l = int(new_perm[0, i, k]), int(old_perm[0, i, k])
            assert mb[j, new_l] == mb[j, old_l]
            if not mb[j, new_l]:
                continue
            assert new_l == old_l
            n_real_real += 1
            qa = p.a.deeper[0].q[0, i, k]
            qb = _engine.rotate_srvf(p.b.deeper[0].q[0, j, new_l], O[0])
            e_new = warp_energy(qa, qb, new_warp[0, i, k])
            e_old = warp_energy(qa, qb, old_warp[0, i, k])
            assert abs(float(e_new) - float(e_old)) < 1e-12
    assert n_real_real > 0  # the pair has matched second-order laterals
