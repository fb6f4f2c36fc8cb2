"""Baselines (rootshape_jax.baselines): QED, father–child SRVF, tree edit distance, shrinkage.

References here are written from the definitions (numpy, sharing no code with the library's
father–child decomposition): arc-length landmarks by `np.interp` on the original polylines,
single-pair DPs, and a memoised recursive ordered-forest edit distance.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
import pytest
from helpers import random_root, reference_dp

import rootshape_jax as rs
from rootshape_jax import baselines as bl
from rootshape_jax._curves import srvf, srvf_to_curve
from rootshape_jax._warp import apply_warp_srvf
from rootshape_jax.baselines._fc_srvf import _register_pair

L = 12  # landmarks per edge in the QED tests
T = 16  # points per edge in the fc-SRVF tests (small: the numpy DP reference is slow)
NB = 3  # DP neighbourhood in the fc-SRVF tests (7 moves)


# ------------------------------------------------------------------------------------------
# Independent references


def _interp(points, lengths):
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return np.stack([np.interp(lengths, cum, points[:, k]) for k in range(points.shape[1])], 1), cum[-1]


def ref_edges(root, capacity, n):
    """Father–child edges on ``n`` points uniform in arc length, relative to their start, padded
    with zeros: main edge k between the k-th and (k+1)-th attachment (sorted), then laterals."""
    d = root.dim
    order = np.argsort(root.attach, kind="stable")
    f = np.concatenate([[0.0], np.asarray(root.attach)[order], [1.0]])
    _, total = _interp(root.main, [0.0])
    out = np.zeros((2 * capacity + 1, n, d))
    absolute_main = []
    for k in range(len(f) - 1):
        pts, _ = _interp(root.main, np.linspace(f[k], f[k + 1], n) * total)
        out[k] = pts - pts[0]
        absolute_main.append(pts if k == 0 else pts[1:])
    lats = []
    for k, idx in enumerate(order):
        lat = root.laterals[idx]
        _, length = _interp(lat, [0.0])
        pts, _ = _interp(lat, np.linspace(0, length, n))
        out[capacity + 1 + k] = pts - pts[0]
        lats.append(pts)
    return out, np.vstack(absolute_main), lats


def path_root_edges(root, n):
    """Edges of a root built by the baselines (main edges of ``n`` points end to end)."""
    C = root.n_laterals
    m = root.main
    main = [m[k * (n - 1) : (k + 1) * (n - 1) + 1] - m[k * (n - 1)] for k in range(C + 1)]
    return np.stack(main + [lat - lat[0] for lat in root.laterals])


def point_to_polyline(p, poly):
    best = np.linalg.norm(poly[0] - p)
    for s0, s1 in zip(poly[:-1], poly[1:]):
        v = s1 - s0
        u = np.clip(np.dot(p - s0, v) / np.dot(v, v), 0, 1) if np.dot(v, v) > 0 else 0.0
        best = min(best, np.linalg.norm(s0 + u * v - p))
    return best


def ref_ted(a_lengths, a_children, b_lengths, b_children):
    """Ordered-forest edit distance by the textbook recursion on rightmost roots (memoised)."""

    def tree(lengths, children, i):
        return (lengths[i], tuple(tree(lengths, children, c) for c in children[i]))

    def size(forest):
        return sum(t[0] + size(t[1]) for t in forest)

    @functools.lru_cache(maxsize=None)
    def dist(F, G):
        if not F:
            return size(G)
        if not G:
            return size(F)
        (lv, cv), (lw, cw) = F[-1], G[-1]
        return min(
            dist(F[:-1] + cv, G) + lv,
            dist(F, G[:-1] + cw) + lw,
            dist(cv, cw) + dist(F[:-1], G[:-1]) + abs(lv - lw),
        )

    return dist((tree(a_lengths, a_children, 0),), (tree(b_lengths, b_children, 0),))


def straight_root(main_length, laterals=()):
    """Main root along +y from the origin; laterals = [(fraction, length, side)] along ±x."""
    main = np.stack([np.zeros(11), np.linspace(0, main_length, 11)], 1)
    lats, attach = [], []
    for f, length, side in laterals:
        base = np.array([0.0, f * main_length])
        lats.append(base + np.stack([side * np.linspace(0, length, 5), np.zeros(5)], 1))
        attach.append(f)
    return rs.Root(main=main, laterals=lats, attach=attach)


def population(d, counts=(3, 1, 4, 0, 2), seed=0):
    rng = np.random.default_rng(seed)
    return [random_root(rng, n_laterals=n, d=d) for n in counts]


# ------------------------------------------------------------------------------------------
# QED


@pytest.mark.parametrize("d", [2, 3])
def test_qed_matches_reference_and_is_a_metric(d):
    roots = population(d)
    C = max(r.n_laterals for r in roots)
    X = np.stack([ref_edges(r, C, L + 1)[0][:, 1:] for r in roots])
    np.testing.assert_allclose(bl.qed_vectors(roots, n_landmarks=L), X, atol=1e-12)
    ref = np.sqrt(((X[:, None] - X[None]) ** 2).sum(axis=(2, 3, 4)))
    D = bl.qed_distance_matrix(roots, n_landmarks=L)
    np.testing.assert_allclose(D, ref, atol=1e-10)
    for i, j in itertools.combinations(range(len(roots)), 2):
        dij = bl.qed_distance(roots[i], roots[j], n_landmarks=L)
        assert dij == pytest.approx(D[i, j], abs=1e-10)
        assert dij == bl.qed_distance(roots[j], roots[i], n_landmarks=L)
    assert all(bl.qed_distance(r, r, n_landmarks=L) == 0.0 for r in roots)
    assert np.all(D == D.T) and np.all(np.diag(D) == 0)
    for i, j, k in itertools.permutations(range(len(roots)), 3):
        assert D[i, k] <= D[i, j] + D[j, k] + 1e-12


def test_qed_hand_computed():
    # Straight main roots of lengths 1 and 2, no laterals: one edge, landmarks j/L·(0, ℓ).
    a, b = straight_root(1.0), straight_root(2.0)
    expected = np.sqrt(sum((j / L) ** 2 for j in range(1, L + 1)))
    assert bl.qed_distance(a, b, n_landmarks=L) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_qed_geodesic_is_the_straight_line(d):
    rng = np.random.default_rng(1)
    a, b = random_root(rng, n_laterals=3, d=d), random_root(rng, n_laterals=1, d=d)
    n_steps = 5
    path = bl.qed_geodesic(a, b, n_steps=n_steps, n_landmarks=L)
    assert len(path) == n_steps and all(r.n_laterals == 3 for r in path)
    # Endpoints: a and b at their landmarks, exactly (b padded with collapsed laterals).
    for root, end in ((a, path[0]), (b, path[-1])):
        _, main_ref, lats_ref = ref_edges(root, 3, L + 1)
        m = len(main_ref)  # b's main edges after its own are collapsed at its tip
        np.testing.assert_allclose(end.main[:m], main_ref, atol=1e-10)
        np.testing.assert_allclose(end.main[m:], np.broadcast_to(main_ref[-1], end.main[m:].shape), atol=1e-10)
        for k, lat in enumerate(lats_ref):
            np.testing.assert_allclose(end.laterals[k], lat, atol=1e-10)
    for lat in path[-1].laterals[1:]:
        assert np.ptp(lat, axis=0).max() < 1e-12  # b's padding: collapsed at its node
    # Every step is the straight line in edge space; the midpoint is equidistant.
    Xa, Xb = ref_edges(a, 3, L + 1)[0], ref_edges(b, 3, L + 1)[0]
    for tau, root in zip(np.linspace(0, 1, n_steps), path):
        np.testing.assert_allclose(path_root_edges(root, L + 1), (1 - tau) * Xa + tau * Xb, atol=1e-10)
    mid = path_root_edges(path[n_steps // 2], L + 1)
    dab = np.sqrt(((Xa - Xb) ** 2).sum())
    assert np.sqrt(((Xa - mid) ** 2).sum()) == pytest.approx(dab / 2, rel=1e-10)
    assert np.sqrt(((mid - Xb) ** 2).sum()) == pytest.approx(dab / 2, rel=1e-10)
    assert dab == pytest.approx(bl.qed_distance(a, b, n_landmarks=L), rel=1e-10)
    # Base interpolated; attachment fractions are the nodes' fractions along the main root.
    np.testing.assert_allclose(path[2].main[0], 0.5 * (a.main[0] + b.main[0]), atol=1e-12)
    for r in path:
        for k, lat in enumerate(r.laterals):
            cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(r.main, axis=0), axis=1))])
            node = r.main[(k + 1) * L]
            assert r.attach[k] == pytest.approx(cum[(k + 1) * L] / cum[-1], abs=1e-12)
            np.testing.assert_allclose(lat[0], node, atol=1e-12)


def test_qed_mean_is_the_euclidean_average():
    roots = population(2)
    C = max(r.n_laterals for r in roots)
    X = np.stack([ref_edges(r, C, L + 1)[0] for r in roots])
    mean = bl.qed_mean(roots, n_landmarks=L)
    assert mean.n_laterals == C
    np.testing.assert_allclose(path_root_edges(mean, L + 1), X.mean(0), atol=1e-10)
    np.testing.assert_allclose(mean.main[0], np.mean([r.main[0] for r in roots], 0), atol=1e-12)
    one = bl.qed_mean([roots[0]] * 3, n_landmarks=L)
    C0 = roots[0].n_laterals
    np.testing.assert_allclose(path_root_edges(one, L + 1), ref_edges(roots[0], C0, L + 1)[0], atol=1e-12)


# ------------------------------------------------------------------------------------------
# Father–child SRVF


def _sq_norm(q):
    w = np.full(q.shape[0], 1.0 / (q.shape[0] - 1))
    w[[0, -1]] /= 2
    return float(np.sum(np.sum(q * q, axis=-1) * w))


def ref_fc_energy(a, b, n):
    """Σ over edge slots of the plain-numpy DP minimum (collapsed edge: the other's ||q||²),
    with the elastic lower bound Σ(||qa|| − ||qb||)² and the unwarped Σ||qa − qb||²."""
    C = max(a.n_laterals, b.n_laterals)
    Ea, Eb = ref_edges(a, C, n)[0], ref_edges(b, C, n)[0]
    total, lower, upper = 0.0, 0.0, 0.0
    for ea, eb in zip(Ea, Eb):
        qa, qb = np.asarray(srvf(ea)), np.asarray(srvf(eb))
        na, nb = _sq_norm(qa), _sq_norm(qb)
        total += reference_dp(qa, qb, NB)[1] if na > 0 and nb > 0 else na + nb
        lower += (np.sqrt(na) - np.sqrt(nb)) ** 2
        upper += _sq_norm(qa - qb)
    return total, lower, upper


def _fc_distance_checks(roots):
    D = bl.fc_srvf_distance_matrix(roots, n_points=T, neighbourhood=NB)
    assert np.all(D == D.T) and np.all(np.diag(D) == 0)
    for i, j in itertools.combinations(range(len(roots)), 2):
        energy, lower, upper = ref_fc_energy(roots[i], roots[j], T)
        dij = bl.fc_srvf_distance(roots[i], roots[j], n_points=T, neighbourhood=NB)
        assert dij == pytest.approx(np.sqrt(energy), rel=1e-9)
        assert D[i, j] == pytest.approx(dij, rel=1e-9)
        # Elastic bounds: (||qa|| − ||qb||)² per edge below, the unwarped L2 above.
        assert lower - 1e-12 <= dij**2 <= upper + 1e-12
        assert dij**2 < upper - 1e-6  # warping helps on random curves
        # The DP is symmetric only up to the grid.
        dji = bl.fc_srvf_distance(roots[j], roots[i], n_points=T, neighbourhood=NB)
        assert abs(dij - dji) <= 0.05 * max(dij, dji)
    for r in roots:
        assert bl.fc_srvf_distance(r, r, n_points=T, neighbourhood=NB) < 1e-12


def test_fc_srvf_distance_matches_numpy_dp_reference():
    # 4 roots, 6 pairs, > 16 real-real edge DPs: several padded chunks of the batched DP.
    _fc_distance_checks(population(2, counts=(2, 0, 3, 3), seed=4))


@pytest.mark.slow
def test_fc_srvf_distance_matches_numpy_dp_reference_3d():
    _fc_distance_checks(population(3, counts=(2, 0, 3), seed=4))


def _through_srvf(edges):
    return np.asarray(srvf_to_curve(srvf(edges)))


def test_fc_srvf_geodesic_endpoints():
    rng = np.random.default_rng(5)
    a, b = random_root(rng, n_laterals=2), random_root(rng, n_laterals=1)
    path = bl.fc_srvf_geodesic(a, b, n_steps=3, n_points=T, neighbourhood=NB)
    assert len(path) == 3 and all(r.n_laterals == 2 for r in path)
    np.testing.assert_array_equal(path[0].main[0], a.main[0])
    np.testing.assert_array_equal(path[-1].main[0], b.main[0])
    Ea, Eb = ref_edges(a, 2, T)[0], ref_edges(b, 2, T)[0]
    # First step: a's resampled edges through their SRVFs and back; close to the edges
    # themselves up to the round trip's second-order error.
    first = path_root_edges(path[0], T)
    np.testing.assert_allclose(first, _through_srvf(Ea), atol=1e-10)
    np.testing.assert_allclose(first, Ea, atol=2e-2)
    # Last step: b's edges registered (warped by the DP) onto a's.
    _, _, _, gamma, _ = _register_pair(a, b, n_points=T, neighbourhood=NB, what="test")
    assert not np.allclose(gamma, np.linspace(0, 1, T))  # the warps do something
    qb = np.asarray(srvf(Eb))
    registered = np.stack([np.asarray(apply_warp_srvf(q, g)) for q, g in zip(qb, gamma)])
    last = path_root_edges(path[-1], T)
    np.testing.assert_allclose(last, np.asarray(srvf_to_curve(registered)), atol=1e-10)
    # Geometrically the last step is b: every point lies on b's edge (reparameterised), up to
    # the SRVF warp's discretisation on this coarse grid (T = 16: ~2% of the main root's length).
    for e_last, e_b in zip(last, Eb):
        assert max(point_to_polyline(p, e_b) for p in e_last) < 0.03
    # The middle step is the SRVF midpoint of a's and registered b's edges, integrated.
    mid = np.asarray(srvf_to_curve(0.5 * (np.asarray(srvf(Ea)) + registered)))
    np.testing.assert_allclose(path_root_edges(path[1], T), mid, atol=1e-10)


def test_fc_srvf_mean():
    roots = population(2, counts=(2, 1, 2), seed=6)
    mean = bl.fc_srvf_mean(roots, n_points=T, max_steps=6, neighbourhood=NB)
    energies = mean.metadata["energies"]
    D = bl.fc_srvf_distance_matrix(roots, n_points=T, neighbourhood=NB)
    medoid = (D**2).mean(1).min()
    assert energies[-1] < medoid  # the mean beats every sample as a centre
    assert energies[-1] <= energies[0]
    same = bl.fc_srvf_mean([roots[0]] * 3, n_points=T, max_steps=3, neighbourhood=NB)
    assert same.metadata["energies"][-1] < 1e-12
    np.testing.assert_allclose(path_root_edges(same, T), _through_srvf(ref_edges(roots[0], 2, T)[0]), atol=1e-10)


# ------------------------------------------------------------------------------------------
# Tree edit distance


def test_tree_edit_distance_hand_computed():
    a = straight_root(1.0)
    b = straight_root(1.0, [(0.5, 0.3, 1.0)])
    lengths, children = bl.edit_tree(b)
    np.testing.assert_allclose(lengths, [0.5, 0.5, 0.3], atol=1e-12)
    assert children == [[1, 2], [], []]
    # Map a's single edge (1.0) onto either main segment (0.5), insert the rest: 0.5 + 0.8.
    assert bl.tree_edit_distance(a, b) == pytest.approx(1.3, abs=1e-12)
    # Same topology, lateral moved from 0.5 to 0.6 and to the other side: relabel 0.1 + 0.1.
    c = straight_root(1.0, [(0.6, 0.3, -1.0)])
    assert bl.tree_edit_distance(b, c) == pytest.approx(0.2, abs=1e-12)
    # Two laterals against one. e: e0 0.5 → [e1 0.2 → [e2 0.3, lat 0.1], lat 0.3];
    # b: e0 0.5 → [e1 0.5, lat 0.3]. Best: delete e1 (0.2) and the short lateral (0.1), relabel
    # e2 → b's e1 (0.2); keeping e1 instead costs 0.3 + 0.3 + 0.1.
    e = straight_root(1.0, [(0.5, 0.3, 1.0), (0.7, 0.1, 1.0)])
    assert bl.tree_edit_distance(e, b) == pytest.approx(0.5, abs=1e-12)


def test_tree_edit_distance_matches_recursive_reference_and_is_a_metric():
    rng = np.random.default_rng(7)
    roots = [random_root(rng, n_laterals=n) for n in (0, 1, 2, 3, 3, 2)]
    D = bl.tree_edit_distance_matrix(roots)
    assert np.all(D == D.T) and np.all(np.diag(D) == 0)
    for i, j in itertools.combinations(range(len(roots)), 2):
        ref = ref_ted(*bl.edit_tree(roots[i]), *bl.edit_tree(roots[j]))
        assert bl.tree_edit_distance(roots[i], roots[j]) == pytest.approx(ref, abs=1e-12)
        assert bl.tree_edit_distance(roots[j], roots[i]) == pytest.approx(ref, abs=1e-12)
        assert D[i, j] == pytest.approx(ref, abs=1e-12)
    assert all(bl.tree_edit_distance(r, r) == 0 for r in roots)
    for i, j, k in itertools.permutations(range(len(roots)), 3):
        assert D[i, k] <= D[i, j] + D[j, k] + 1e-12


# ------------------------------------------------------------------------------------------
# Shrinkage


def test_shrinkage_hand_computed():
    path = [straight_root(1.0, [(0.5, 0.2, 1)]), straight_root(0.5, [(0.5, 0.2, 1)]), straight_root(2.0)]
    s = bl.geodesic_shrinkage(path)
    np.testing.assert_allclose(s.lengths, [1.2, 0.7, 2.0], atol=1e-12)
    np.testing.assert_allclose(s.interpolated, [1.2, 1.6, 2.0], atol=1e-12)
    assert s.min_ratio == pytest.approx(0.7 / 1.6, abs=1e-12)
    assert s.mean_shortfall == pytest.approx(1 - 0.7 / 1.6, abs=1e-12)
    # A batched RootTree of the same straight roots gives the same lengths.
    tree = rs.batch(path, n_points=11, max_laterals=2)
    np.testing.assert_allclose(bl.geodesic_shrinkage(tree).lengths, s.lengths, atol=1e-12)


def test_qed_geodesic_shrinks_opposite_laterals_exactly():
    # The paper's Fig. 2 failure: laterals on opposite sides are matched by order, so the QED
    # midpoint has a zero-length lateral: total 1.0 against the interpolated 1.4.
    a = straight_root(1.0, [(0.5, 0.4, 1.0)])
    b = straight_root(1.0, [(0.5, 0.4, -1.0)])
    s = bl.geodesic_shrinkage(bl.qed_geodesic(a, b, n_steps=5, n_landmarks=L))
    assert s.min_ratio == pytest.approx(1.0 / 1.4, abs=1e-12)


def l_shaped_pair():
    """An L-shaped main root (down 1, then right 1) with one straight lateral of length 0.4
    pointing down-left, attached at 1/4 of the main root in a and at 3/4 in b."""
    t = np.linspace(0, 1, 21)
    main = np.vstack([np.stack([0 * t, t], 1), np.stack([t[1:], 1 + 0 * t[1:]], 1)])
    direction = np.array([-1.0, 1.0]) / np.sqrt(2)
    lat = 0.4 * np.linspace(0, 1, 9)[:, None] * direction
    a = rs.Root(main=main, laterals=[lat + [0.0, 0.5]], attach=[0.25])
    b = rs.Root(main=main, laterals=[lat + [0.5, 1.0]], attach=[0.75])
    return a, b


def test_father_child_geodesics_shrink_when_a_lateral_moves():
    a, b = l_shaped_pair()
    qed = bl.geodesic_shrinkage(bl.qed_geodesic(a, b, n_steps=9, n_landmarks=L))
    fc = bl.geodesic_shrinkage(bl.fc_srvf_geodesic(a, b, n_steps=9, n_points=T, neighbourhood=NB))
    for s in (qed, fc):
        np.testing.assert_allclose(s.lengths[[0, -1]], s.interpolated[[0, -1]], rtol=1e-12)
        assert s.min_ratio < 0.96 and s.mean_shortfall > 0.03


@pytest.mark.slow
def test_our_geodesic_does_not_shrink_when_a_lateral_moves():
    # Main-side branching: the lateral keeps its SRVF and only its attachment fraction moves.
    a, b = l_shaped_pair()
    ta, tb = rs.unstack(rs.batch([a, b], n_points=50, max_laterals=2))
    ours = bl.geodesic_shrinkage(rs.geodesic(ta, tb, n_steps=9))
    qed = bl.geodesic_shrinkage(bl.qed_geodesic(a, b, n_steps=9, n_landmarks=L))
    assert ours.min_ratio > 0.999 and abs(ours.mean_shortfall) < 1e-3
    assert qed.min_ratio < ours.min_ratio - 0.04


# ------------------------------------------------------------------------------------------
# Errors


def test_bad_input_raises_library_errors():
    rng = np.random.default_rng(8)
    a, b = random_root(rng, n_laterals=2), random_root(rng, n_laterals=1)
    a.main[3, 0] = np.nan  # Root arrays are plain numpy: re-validated on every call
    for fn in (bl.qed_distance, bl.fc_srvf_distance, bl.tree_edit_distance, bl.qed_geodesic, bl.fc_srvf_geodesic):
        with pytest.raises(rs.InvalidRootError, match="NaN"):
            fn(a, b)
    with pytest.raises(rs.InvalidRootError, match="NaN"):
        bl.qed_mean([b, a])
    c3 = random_root(rng, n_laterals=1, d=3)
    with pytest.raises(rs.InvalidRootError, match="dimensions"):
        bl.qed_distance_matrix([b, c3])
    with pytest.raises(TypeError, match="Root"):
        bl.qed_distance(b, b.main)
    with pytest.raises(ValueError, match="n_landmarks"):
        bl.qed_distance(b, b, n_landmarks=0)
    with pytest.raises(ValueError, match="n_steps"):
        bl.fc_srvf_geodesic(b, b, n_steps=1)
    with pytest.raises(ValueError, match="at least one"):
        bl.tree_edit_distance_matrix([])
    with pytest.raises(ValueError, match="at least 2 steps"):
        bl.geodesic_shrinkage([b])
    with pytest.raises(TypeError, match="single Root"):
        bl.geodesic_shrinkage(b)
