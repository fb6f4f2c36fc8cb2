"""Distance matrices and geodesics."""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root, record_bars

import rootshape_jax as rs
from rootshape_jax import _pairwise

T = 30
K = 10  # the capacity the registration tests use: shared compilations
W = rs.Weights(main=0.5, lateral=1.0, position=1.0)


@pytest.fixture(scope="module")
def trees():
    rng = np.random.default_rng(0)
    roots = [random_root(rng, n_laterals=n) for n in (0, 2, 3, 4, 2)]
    return rs.batch(roots, n_points=T, max_laterals=K, normalise_scale=True)


def test_matrix_equals_pair_by_pair_calls(trees):
    D = np.asarray(rs.pairwise_distances(trees, weights=W, chunk_size=4, progress=False))
    n = D.shape[0]
    assert np.all(np.diag(D) == 0)
    np.testing.assert_array_equal(D, D.T)
    parts = rs.unstack(trees)
    for i in range(n):
        for j in range(i + 1, n):
            d = float(rs.distance(parts[i], parts[j], weights=W))
            assert D[i, j] == pytest.approx(d, rel=1e-10)


def test_cross_distances_and_stats(trees):
    A = jax.tree.map(lambda x: x[:2], trees)
    C = np.asarray(rs.cross_distances(A, trees, weights=W, chunk_size=4, progress=False))
    D, stats = rs.pairwise_distances(trees, weights=W, chunk_size=4, progress=False, return_stats=True)
    np.testing.assert_allclose(C[:, 2:], np.asarray(D)[:2, 2:], rtol=1e-10)
    assert C[0, 0] < 1e-7 and C[1, 1] < 1e-7
    assert stats["pairs"] == 10 and stats["lateral_dp"] > 0


def test_cross_distances_bar_moves_after_every_chunk(trees, monkeypatch):
    """Issue 17, item 6: a long matrix shows progress per chunk (each chunk is a block), so the
    bar moves at least as often as a chunk finishes."""
    made = record_bars(monkeypatch)
    A = jax.tree.map(lambda x: x[:2], trees)
    rs.cross_distances(A, trees, weights=W, chunk_size=4)  # 10 pairs: chunks of 4, 4, 2
    (bar,) = made
    assert bar.kwargs["total"] == 10 and not bar.kwargs["disable"]
    assert sorted(bar.updates) == [2, 4, 4]


def test_no_retrace_across_chunks(trees, monkeypatch):
    counted = eqx.filter_jit(eqx.debug.assert_max_traces(_pairwise.chunk_energies.__wrapped__, max_traces=1))
    monkeypatch.setattr(_pairwise, "chunk_energies", counted)
    # 10 pairs in chunks of 4: three chunks, one compiled program (the last chunk is padded).
    rs.pairwise_distances(trees, weights=W, chunk_size=4, progress=False)


def test_bad_inputs(trees):
    with pytest.raises(TypeError, match="batched RootTree"):
        rs.pairwise_distances([1, 2])
    with pytest.raises(ValueError, match="one leading axis"):
        rs.pairwise_distances(rs.unstack(trees)[0])
    other = rs.batch([random_root(np.random.default_rng(1), n_laterals=9)], n_points=T)
    with pytest.raises(ValueError, match="different capacities"):
        rs.cross_distances(trees, other)
    with pytest.raises(ValueError, match="chunk_size"):
        rs.pairwise_distances(trees, chunk_size=0)


# ---------------------------------------------------------------------------------- geodesics


def test_geodesic_endpoints_midpoint_and_colours(trees):
    a, b = rs.unstack(trees)[2], rs.unstack(trees)[3]
    reg = rs.register(a, b, weights=W)
    path = rs.geodesic(a, b, n_steps=5, weights=W, registration=reg, in_place=False)
    assert path.main.shape == (5, T, 2) and path.laterals.shape[:2] == (5, a.capacity)
    # Endpoints (in_place=False): a itself (its curves rebuilt from its SRVFs) and b rotated
    # and permuted as registered, not reparameterised (its own SRVFs' curves).
    from rootshape_jax._geodesic import unwarped_end

    start = rs.to_curves(rs.to_srvf(a))
    np.testing.assert_allclose(np.asarray(path.main[0]), np.asarray(start.main), atol=1e-12)
    end = rs.to_curves(unwarped_end(rs.to_srvf(a), rs.to_srvf(b), reg))
    np.testing.assert_allclose(np.asarray(path.main[-1]), np.asarray(end.main), atol=1e-12)
    m = np.asarray(end.mask)
    np.testing.assert_allclose(np.asarray(path.laterals[-1])[m], np.asarray(end.laterals)[m], atol=1e-12)
    # The midpoint of the straight line is equidistant from both ends (pre-shape metric).
    from rootshape_jax._geodesic import geodesic_srvf

    line = geodesic_srvf(rs.to_srvf(a), reg.registered, jnp.array([0.0, 0.5, 1.0]))
    ends = rs.unstack(line)
    d0 = rs.preshape_distance_squared(ends[0], ends[1], W)
    d1 = rs.preshape_distance_squared(ends[1], ends[2], W)
    assert float(d0) == pytest.approx(float(d1), rel=1e-12)
    assert float(d0) == pytest.approx(float(reg.energy) / 4, rel=1e-9)


def test_geodesic_ends_at_b_not_at_b_rebuilt_from_its_warped_srvfs():
    """From an audit on RootNav tracings: the last step was b's warped SRVF rebuilt as curves; a
    steep warp skips b's nodes, so the rebuilt lateral cut corners (8 % shorter on RootNav).
    Now the last step is b's own SRVF rotated back in place: b's round trip, as step 0 is a's."""
    main = np.stack([np.zeros(60), np.linspace(0, 1, 60)], 1)

    def bent(frac):  # a lateral going right with a bump at `frac` of its length
        t = np.linspace(0, 1, 60)
        return np.stack([0.4 * t, 0.5 + 0.06 * np.exp(-(((t - frac) / 0.03) ** 2))], 1)

    roots = [rs.Root(main=main, laterals=[bent(f)], attach=[0.5]) for f in (0.15, 0.85)]
    a, b = rs.unstack(rs.batch(roots, n_points=T, max_laterals=K, dtype=np.float64))
    reg = rs.register(a, b, weights=W)
    assert float(np.max(np.diff(np.asarray(reg.lateral_warps[0])))) * (T - 1) > 3  # a steep warp
    path = rs.geodesic(a, b, n_steps=5, weights=W, registration=reg)
    own = rs.to_curves(rs.to_srvf(b))  # b's own round trip
    np.testing.assert_allclose(np.asarray(path.main[-1]), np.asarray(own.main), atol=1e-12)
    np.testing.assert_allclose(np.asarray(path.laterals[-1, 0]), np.asarray(own.laterals[0]), atol=1e-12)
    warped = float(rs.curve_length(rs.to_curves(reg.registered).laterals[0]))
    kept = float(rs.curve_length(path.laterals[-1, 0]))
    assert kept == pytest.approx(float(rs.curve_length(own.laterals[0])), rel=1e-12)
    assert kept - warped > 0.01 * kept  # what the old end lost
    # Distances along the path: the end is as far from b as b's own round trip.
    ends = rs.unstack(path)
    assert float(rs.distance(ends[-1], b, weights=W)) == pytest.approx(float(rs.distance(own, b, weights=W)), abs=1e-9)


def test_lateral_added_grows_from_zero():
    main = np.stack([np.zeros(30), np.linspace(0, 1, 30)], 1)
    lat = np.stack([np.linspace(0, 0.3, 20), np.zeros(20)], 1)
    r1 = rs.Root(main=main, laterals=[lat + [0, 0.3]], attach=[0.3])
    r2 = rs.Root(main=main, laterals=[lat + [0, 0.3], -lat + [0, 0.7]], attach=[0.3, 0.7])
    a, b = rs.unstack(rs.batch([r1, r2], n_points=T, max_laterals=K))
    path = rs.geodesic(a, b, n_steps=5, weights=W)
    lengths = np.asarray(rs.curve_length(path.laterals))  # (steps, K)
    grown = int(np.argmax(lengths[-1] * (lengths[0] < 1e-12)))
    assert lengths[0, grown] < 1e-12
    assert np.all(np.diff(lengths[:, grown]) > 0)
    assert lengths[-1, grown] == pytest.approx(0.3, rel=1e-6)
    # It grows at a fixed position: its base stays at the attachment fraction 0.7.
    np.testing.assert_allclose(np.asarray(path.attach[:, grown]), 0.7, atol=1e-12)
    np.testing.assert_allclose(np.asarray(path.laterals[1:, grown, 0, 1]), 0.7, atol=1e-6)
    # At a's end it is a's null, not a real lateral of length 0 (traits counted 11 laterals at
    # both ends of a plate geodesic from 4 to 11): the ends have the inputs' laterals.
    mask = np.asarray(path.mask)
    assert not mask[0, grown] and mask[1:, grown].all()
    assert [r.n_laterals for r in rs.to_roots(path)] == [1, 2, 2, 2, 2]
    back = rs.geodesic(b, a, n_steps=5, weights=W)
    assert [r.n_laterals for r in rs.to_roots(back)] == [2, 2, 2, 2, 1]
    assert [t["n_laterals"] for t in rs.traits(rs.to_roots(back))] == [2, 2, 2, 2, 1]


def test_geodesic_in_3d_and_errors(monkeypatch):
    rng = np.random.default_rng(3)
    t = rs.batch([random_root(rng, n_laterals=2, d=3) for _ in range(2)], n_points=T, max_laterals=K)
    a, b = rs.unstack(t)
    path = rs.geodesic(a, b, n_steps=3, weights=W)
    assert path.main.shape == (3, T, 3)
    assert np.all(np.isfinite(np.asarray(path.laterals)))
    with pytest.raises(ValueError, match="n_steps"):
        rs.geodesic(a, b, n_steps=1)
    # Refused before any registration (a batch registered every pair first, with a progress
    # bar; sizes of one number failed in tuple unpacking).
    from rootshape_jax import _geodesic

    def no_register(*args, **kwargs):
        raise AssertionError("registered before checking the input")

    monkeypatch.setattr(_geodesic, "register", no_register)
    with pytest.raises(ValueError, match=r"a is a batch of shape \(2,\).*unstack"):
        rs.geodesic(t, t)
    with pytest.raises(ValueError, match="sizes must be two positive"):
        rs.geodesic(a, b, sizes=(500.0,))
    with pytest.raises(TypeError, match="b must be a RootTree"):
        rs.geodesic(a, [b])


def test_worker_threads_give_the_same_matrix():
    # Local blocks run on worker threads by default (every core without a global JAX setting);
    # the matrix does not depend on how many.
    from rootshape_jax import LocalExecutor

    rng = np.random.default_rng(5)
    roots = [random_root(rng, n_laterals=3) for _ in range(6)]
    trees = rs.batch(roots, n_points=20, max_laterals=8, normalise_scale=True)
    one = rs.pairwise_distances(trees, chunk_size=4, progress=False, client=LocalExecutor(workers=1))
    three = rs.pairwise_distances(trees, chunk_size=4, progress=False, client=LocalExecutor(workers=3))
    np.testing.assert_array_equal(np.asarray(one), np.asarray(three))


def _sleepy_block(i, delay):
    start = time.perf_counter()
    time.sleep(delay)
    return {"i": np.asarray(i), "span": np.asarray([start, time.perf_counter()])}


def test_local_blocks_overlap_once_the_function_has_run():
    # The first block of a new block function runs alone (its compilation is then shared);
    # called again with the same shapes, every block starts at once on the worker threads.
    from rootshape_jax import LocalExecutor

    ex = LocalExecutor(workers=2)
    spans = []
    for _ in range(2):
        results, _ = ex.map_blocks(_sleepy_block, [(0,), (1,)], shared=(0.3,), progress=False)
        assert sorted(int(r["i"]) for r in results) == [0, 1]
        spans.append(sorted(tuple(r["span"]) for r in results))
    (a0, a1), (b0, b1) = spans[0]
    assert b0 >= a1  # first call: one after the other
    (a0, a1), (b0, b1) = spans[1]
    assert b0 < a1  # second call: together


def test_scipy_and_warm_started_jax_assignments_give_the_same_matrix_and_objective():
    """Both solvers are exact: the registration's default (pure JAX, each solve of a lazy
    assignment warm-started from the last) reaches what scipy's reaches, on roots with unequal
    lateral counts (null padding): the matrix, and the Karcher objective at a fixed tree (the
    mean's registrations). (Whole Karcher means may part: the fixed point's keep-or-replace
    choices compare energies equal to the last bit, and on these 5 roots the two paths' summed
    energies were 0.4 % apart after 4 steps; on the 53 CPlantBox pea roots they reached the
    same F in 24 steps.)"""
    rng = np.random.default_rng(11)
    roots = [random_root(rng, n_laterals=n) for n in (2, 5, 7, 4, 6)]
    trees = rs.batch(roots, n_points=20)
    scipy_opts = rs.RegistrationOptions(assignment="callback")
    D_jax = np.asarray(rs.pairwise_distances(trees, progress=False))
    D_scipy = np.asarray(rs.pairwise_distances(trees, registration=scipy_opts, progress=False))
    np.testing.assert_allclose(D_jax, D_scipy, rtol=1e-9, atol=1e-12)
    mu = rs.unstack(trees)[2]
    F_jax = rs.karcher_objective(mu, trees, registration=rs.RegistrationOptions())
    F_scipy = rs.karcher_objective(mu, trees, registration=scipy_opts)
    np.testing.assert_allclose(F_jax, F_scipy, rtol=1e-10)
