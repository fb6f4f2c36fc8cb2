"""Exact linear assignment: both solvers against scipy and a brute-force enumeration."""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from rootshape_jax import _assignment
from rootshape_jax._assignment import InvalidCostError, assignment_cost, linear_assignment

METHODS = ["callback", "jax"]
SIZES = [1, 2, 3, 5, 8, 16, 40, 64]


def _solver(method):
    # A fresh jitted function per call site, so that host-call counting sees a fresh trace.
    return jax.jit(lambda c: linear_assignment(c, method=method))


def _brute_force_cost(cost):
    """Slow obvious reference: enumerate all K! permutations (K <= 8)."""
    k = cost.shape[0]
    perms = np.array(list(itertools.permutations(range(k))))
    return cost[np.arange(k), perms].sum(axis=1).min()


def _scipy_cost(cost):
    rows, cols = scipy.optimize.linear_sum_assignment(cost)
    return cost[rows, cols].sum(), cols


def _matched(cost, perm):
    perm = np.asarray(perm)
    k = cost.shape[0]
    assert perm.shape == (k,)
    assert np.array_equal(np.sort(perm), np.arange(k)), f"not a permutation: {perm}"
    return cost[np.arange(k), perm].sum()


def _block_cost(rng, n_real_a, n_real_b, k):
    """The registration's structure (docs/design.md §4): real-real costs, a real row against a null
    column costs that row's constant (and a null row against a real column that column's
    constant), null-null 0."""
    row_null = rng.uniform(0.5, 3.0, size=k)
    col_null = rng.uniform(0.5, 3.0, size=k)
    c = np.zeros((k, k))
    c[:n_real_a, :n_real_b] = rng.uniform(0.0, 4.0, size=(n_real_a, n_real_b))
    c[:n_real_a, n_real_b:] = row_null[:n_real_a, None]
    c[n_real_a:, :n_real_b] = col_null[None, :n_real_b]
    return c


# --------------------------------------------------------------------------- correctness


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("k", SIZES)
def test_random_matches_scipy(method, k):
    rng = np.random.default_rng(1000 + k)
    solve = _solver(method)
    for _ in range(3):
        cost = rng.normal(size=(k, k))
        ref_cost, ref_perm = _scipy_cost(cost)
        perm = solve(cost)
        # Continuous random entries: the optimum is unique, so the permutation must agree.
        np.testing.assert_array_equal(np.asarray(perm), ref_perm)
        np.testing.assert_allclose(_matched(cost, perm), ref_cost, rtol=1e-13, atol=1e-13)
        if k <= 8:
            np.testing.assert_allclose(ref_cost, _brute_force_cost(cost), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("method", METHODS)
def test_brute_force_small(method):
    rng = np.random.default_rng(7)
    solve = _solver(method)
    for k in range(1, 8):
        for _ in range(5):
            cost = rng.uniform(-5, 5, size=(k, k))
            np.testing.assert_allclose(_matched(cost, solve(cost)), _brute_force_cost(cost), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("k", [2, 5, 8, 16, 40])
def test_ties_integer(method, k):
    # Many equal entries: several optima exist, so compare the optimal COST (exactly: all
    # arithmetic on small integers in float64 is exact).
    rng = np.random.default_rng(2000 + k)
    solve = _solver(method)
    for high in (2, 3, 10):
        cost = rng.integers(0, high, size=(k, k)).astype(np.float64)
        assert _matched(cost, solve(cost)) == _scipy_cost(cost)[0]
        if k <= 8:
            assert _matched(cost, solve(cost)) == _brute_force_cost(cost)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("k", [1, 3, 8, 40])
def test_all_equal(method, k):
    cost = np.full((k, k), 2.5)
    assert _matched(cost, _solver(method)(cost)) == 2.5 * k


@pytest.mark.parametrize("method", METHODS)
def test_integer_dtype_input(method):
    rng = np.random.default_rng(3)
    cost = rng.integers(-20, 20, size=(6, 6))
    perm = _solver(method)(cost)
    assert perm.dtype == jnp.int32
    assert _matched(cost, perm) == _brute_force_cost(cost)


@pytest.mark.parametrize("method", METHODS)
def test_huge_and_tiny(method):
    # 1e12 beside 1e-12: the tiny entries decide the optimum among the cheap permutations
    # while the huge ones must be avoided (or used as few times as possible).
    rng = np.random.default_rng(4)
    solve = _solver(method)
    for _ in range(40):
        k = int(rng.integers(2, 8))
        mask = rng.random((k, k)) < rng.uniform(0.2, 0.8)
        cost = np.where(mask, 1e12 * rng.uniform(1, 2, size=(k, k)), rng.uniform(0, 1e-12, size=(k, k)))
        best = _brute_force_cost(cost)
        np.testing.assert_allclose(_matched(cost, solve(cost)), best, rtol=1e-12, atol=0)
    for k in (16, 40):
        mask = rng.random((k, k)) < 0.5
        cost = np.where(mask, 1e12 * rng.uniform(1, 2, size=(k, k)), rng.uniform(0, 1e-12, size=(k, k)))
        np.testing.assert_allclose(_matched(cost, solve(cost)), _scipy_cost(cost)[0], rtol=1e-12, atol=0)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("k", [3, 8, 40])
def test_negative_entries(method, k):
    rng = np.random.default_rng(5000 + k)
    cost = -rng.uniform(10, 1000, size=(k, k))
    ref_cost, ref_perm = _scipy_cost(cost)
    perm = _solver(method)(cost)
    np.testing.assert_array_equal(np.asarray(perm), ref_perm)
    np.testing.assert_allclose(_matched(cost, perm), ref_cost, rtol=1e-13)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(("n_a", "n_b", "k"), [(0, 0, 4), (3, 0, 5), (3, 5, 8), (8, 8, 8), (7, 12, 16)])
def test_registration_block_structure(method, n_a, n_b, k):
    rng = np.random.default_rng(100 * n_a + n_b)
    solve = _solver(method)
    for _ in range(3):
        cost = _block_cost(rng, n_a, n_b, k)
        got = _matched(cost, solve(cost))
        np.testing.assert_allclose(got, _scipy_cost(cost)[0], rtol=1e-13)
        if k <= 8:
            np.testing.assert_allclose(got, _brute_force_cost(cost), rtol=1e-13)


# --------------------------------------------------------------------------- properties


@pytest.mark.parametrize("method", METHODS)
def test_invariant_to_row_and_column_shifts(method):
    # Adding a constant to a row or column adds the same amount to every assignment.
    rng = np.random.default_rng(6)
    solve = _solver(method)
    cost = rng.normal(size=(12, 12))
    shifted = cost + rng.normal(size=(12, 1)) * 50 + rng.normal(size=(1, 12)) * 50
    np.testing.assert_array_equal(np.asarray(solve(cost)), np.asarray(solve(shifted)))


@pytest.mark.parametrize("method", METHODS)
def test_transpose_gives_inverse(method):
    rng = np.random.default_rng(8)
    solve = _solver(method)
    cost = rng.normal(size=(10, 10))
    perm = np.asarray(solve(cost))
    perm_t = np.asarray(solve(cost.T))
    np.testing.assert_array_equal(perm_t[perm], np.arange(10))


@pytest.mark.parametrize("method", METHODS)
def test_no_improving_swap(method):
    # Local optimality: exchanging the columns of any two rows never lowers the cost.
    rng = np.random.default_rng(9)
    cost = rng.uniform(size=(20, 20))
    perm = np.asarray(_solver(method)(cost))
    base = cost[np.arange(20), perm]
    i, j = np.triu_indices(20, 1)
    swapped = cost[i, perm[j]] + cost[j, perm[i]] - base[i] - base[j]
    assert swapped.min() >= -1e-14


def test_jax_float32():
    # The pure-JAX solver runs in the input dtype; still optimal for well-separated costs.
    rng = np.random.default_rng(10)
    cost = rng.integers(0, 1000, size=(16, 16)).astype(np.float32)
    perm = _solver("jax")(jnp.asarray(cost, jnp.float32))
    assert perm.dtype == jnp.int32
    assert _matched(cost.astype(np.float64), perm) == _scipy_cost(cost.astype(np.float64))[0]


# --------------------------------------------------------------------------- transforms


@pytest.mark.parametrize("method", METHODS)
def test_vmap_equals_loop(method):
    rng = np.random.default_rng(11)
    costs = rng.normal(size=(6, 7, 7))
    batched = jax.jit(jax.vmap(lambda c: linear_assignment(c, method=method)))(costs)
    looped = np.stack([np.asarray(_solver(method)(c)) for c in costs])
    np.testing.assert_array_equal(np.asarray(batched), looped)
    np.testing.assert_array_equal(looped, np.stack([scipy.optimize.linear_sum_assignment(c)[1] for c in costs]))


@pytest.mark.parametrize("method", METHODS)
def test_nested_vmap(method):
    rng = np.random.default_rng(12)
    costs = rng.normal(size=(2, 3, 5, 5))
    f = jax.jit(jax.vmap(jax.vmap(lambda c: linear_assignment(c, method=method))))
    out = np.asarray(f(costs))
    assert out.shape == (2, 3, 5)
    for a in range(2):
        for b in range(3):
            np.testing.assert_array_equal(out[a, b], scipy.optimize.linear_sum_assignment(costs[a, b])[1])


def test_vmapped_batch_is_one_host_call(monkeypatch):
    calls = []
    host = _assignment._scipy_host

    def counting(cost):
        calls.append(np.shape(cost))
        return host(cost)

    monkeypatch.setattr(_assignment, "_scipy_host", counting)
    rng = np.random.default_rng(13)
    f = jax.jit(jax.vmap(lambda c: linear_assignment(c, method="callback")))
    jax.block_until_ready(f(rng.normal(size=(5, 4, 4))))
    assert calls == [(5, 4, 4)]
    calls.clear()
    g = jax.jit(jax.vmap(jax.vmap(lambda c: linear_assignment(c, method="callback"))))
    jax.block_until_ready(g(rng.normal(size=(2, 3, 4, 4))))
    assert calls == [(2, 3, 4, 4)]


@pytest.mark.parametrize("method", METHODS)
def test_jit_does_not_retrace(method):
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def solve(c):
        return linear_assignment(c, method=method)

    rng = np.random.default_rng(14)
    for _ in range(3):
        cost = rng.normal(size=(6, 6))
        np.testing.assert_array_equal(np.asarray(solve(cost)), scipy.optimize.linear_sum_assignment(cost)[1])
    # The guard is live: a new shape is a new trace.
    with pytest.raises(RuntimeError, match="traced"):
        solve(rng.normal(size=(7, 7)))


@pytest.mark.parametrize("method", METHODS)
def test_gradient_is_permutation_indicator(method):
    rng = np.random.default_rng(15)
    cost = rng.normal(size=(9, 9))

    def value(c):
        return assignment_cost(c, linear_assignment(c, method=method))

    grad = np.asarray(jax.jit(jax.grad(value))(cost))
    perm = scipy.optimize.linear_sum_assignment(cost)[1]
    expected = np.zeros((9, 9))
    expected[np.arange(9), perm] = 1.0
    np.testing.assert_array_equal(grad, expected)
    # Envelope theorem: a small perturbation changes the optimal value by <grad, dC>.
    d = rng.normal(size=(9, 9))
    eps = 1e-7
    fd = (value(cost + eps * d) - value(cost - eps * d)) / (2 * eps)
    np.testing.assert_allclose(fd, np.sum(expected * d), rtol=1e-6)


def test_assignment_cost_value():
    rng = np.random.default_rng(16)
    cost = rng.normal(size=(5, 5))
    perm = rng.permutation(5)
    np.testing.assert_allclose(assignment_cost(cost, perm), cost[np.arange(5), perm].sum())


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_raises(method, bad):
    cost = np.random.default_rng(17).normal(size=(4, 4))
    cost[2, 1] = bad
    with pytest.raises(RuntimeError, match="NaN/inf"):
        jax.block_until_ready(_solver(method)(cost))
    with pytest.raises(RuntimeError, match="NaN/inf"):
        jax.block_until_ready(linear_assignment(cost, method=method))
    batch = np.stack([np.eye(4), cost])
    with pytest.raises(RuntimeError, match="NaN/inf"):
        f = jax.jit(jax.vmap(lambda c: linear_assignment(c, method=method)))
        jax.block_until_ready(f(batch))


@pytest.mark.parametrize("shape", [(3,), (3, 4), (2, 3, 3), (0, 0), ()], ids=["1d", "rect", "3d", "empty", "scalar"])
def test_bad_shape_raises(shape):
    with pytest.raises(InvalidCostError, match="cost"):
        linear_assignment(np.zeros(shape))
    # A ValueError, raised at trace time.
    with pytest.raises(ValueError):
        jax.jit(linear_assignment).lower(jax.ShapeDtypeStruct(shape, jnp.float64))


def test_bad_method_and_dtype_raise():
    with pytest.raises(InvalidCostError, match="method"):
        linear_assignment(np.zeros((3, 3)), method="auction")
    with pytest.raises(InvalidCostError, match="real"):
        linear_assignment(np.zeros((3, 3), np.complex128))
    with pytest.raises(InvalidCostError, match="perm"):
        assignment_cost(np.zeros((3, 3)), np.arange(4))
    with pytest.raises(InvalidCostError, match="perm"):
        assignment_cost(np.zeros((3, 3)), np.arange(3.0))


# --------------------------------------------------------------------------------------------
# The registration's solver: `hungarian`, warm-started


def _optimum(cost: np.ndarray) -> float:
    r, c = scipy.optimize.linear_sum_assignment(cost)
    return float(cost[r, c].sum())


def _is_permutation(perm, k: int) -> bool:
    return sorted(np.asarray(perm).tolist()) == list(range(k))


@pytest.mark.parametrize("kind", ["uniform", "integer ties", "null padding"])
def test_hungarian_cold_and_warm_starts_reach_scipys_optimum(kind):
    """From the greedy start, and warm-started after changing some rows (the lazy assignment
    raises picked entries; any change of a row is allowed), against scipy."""
    rng = np.random.default_rng(7)
    solve = jax.jit(_assignment.hungarian)
    for trial in range(60):
        k = int(rng.integers(1, 13))
        if kind == "uniform":
            cost = rng.random((k, k))
        elif kind == "integer ties":
            cost = rng.integers(0, 4, (k, k)).astype(float)
        else:  # real-null entries constant per real lateral, null-null 0 (docs/design.md §4)
            n_a, n_b = int(rng.integers(0, k + 1)), int(rng.integers(0, k + 1))
            cost = np.zeros((k, k))
            cost[:n_a, :n_b] = rng.random((n_a, n_b))
            cost[:n_a, n_b:] = rng.random((n_a, 1))
            cost[n_a:, :n_b] = rng.random((1, n_b))
        perm, state = solve(jnp.asarray(cost))
        assert _is_permutation(perm, k)
        assert np.isclose(cost[np.arange(k), np.asarray(perm)].sum(), _optimum(cost), rtol=1e-12, atol=1e-12)
        changed = np.zeros(k, bool)
        changed[rng.choice(k, size=int(rng.integers(0, k + 1)), replace=False)] = True
        new = cost.copy()
        for i in np.flatnonzero(changed):
            if trial % 2:
                new[i, int(perm[i])] += rng.random()  # a picked entry made exact (larger)
            else:
                new[i] = rng.random(k) * 2  # any new row
        perm2, _ = solve(jnp.asarray(new), (state, jnp.asarray(changed)))
        assert _is_permutation(perm2, k)
        assert np.isclose(new[np.arange(k), np.asarray(perm2)].sum(), _optimum(new), rtol=1e-12, atol=1e-12)


def test_hungarian_warm_start_with_nothing_changed_keeps_the_matching():
    rng = np.random.default_rng(3)
    cost = jnp.asarray(rng.random((9, 9)))
    perm, state = _assignment.hungarian(cost)
    again, state2 = _assignment.hungarian(cost, (state, jnp.zeros(9, bool)))
    np.testing.assert_array_equal(perm, again)
    np.testing.assert_array_equal(state.p, state2.p)


def test_hungarian_chained_warm_starts_in_float32_under_vmap():
    """As in a lazy assignment: a batch of float32 matrices, vmapped, solved again and again,
    each time after raising the picked entries of some rows; every solve reaches scipy's
    optimum of the same float32 matrix (to float32 rounding)."""
    rng = np.random.default_rng(5)
    B, k, n_rounds = 6, 14, 12
    cost = rng.random((B, k, k)).astype(np.float32)
    cost[:, 10:, :] = 0.0  # null rows and columns, as padded laterals
    cost[:, 10:, :10] = rng.random((B, 1, 10)).astype(np.float32)
    cold = jax.jit(jax.vmap(_assignment.hungarian))
    warm = jax.jit(jax.vmap(lambda c, st, ch: _assignment.hungarian(c, (st, ch))))
    perm, state = cold(jnp.asarray(cost))
    for _ in range(n_rounds):
        changed = rng.random((B, k)) < 0.2
        rows = np.nonzero(changed)
        cost[rows[0], rows[1], np.asarray(perm)[rows]] += rng.random(len(rows[0])).astype(np.float32)
        perm, state = warm(jnp.asarray(cost), state, jnp.asarray(changed))
        for b in range(B):
            assert _is_permutation(perm[b], k)
            got = cost[b][np.arange(k), np.asarray(perm[b])].sum(dtype=np.float64)
            assert np.isclose(got, _optimum(cost[b].astype(np.float64)), rtol=1e-5), (b, got)
