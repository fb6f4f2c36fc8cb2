"""The DP warp: exact against plain-numpy and brute-force references, batching, errors."""

import logging
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    all_grid_paths,
    path_to_gamma,
    reference_dp,
    reference_moves,
    reference_warp_energy,
    smooth_curve,
)

from rootshape_jax import _warp
from rootshape_jax._curves import l2_norm_squared, srvf
from rootshape_jax._errors import InvalidRootError
from rootshape_jax._warp import (
    apply_warp_curve,
    apply_warp_srvf,
    dp_moves,
    dp_warp,
    dp_warp_and_energy,
    dp_warp_batch,
    warp_energy,
    warp_samples,
)


def _random_pair(seed, T, d=2):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(T, d)), rng.normal(size=(T, d))


def _smooth_pair(seed, T, d=2):
    """SRVFs of two different smooth curves (the realistic case: near-ties are rare)."""
    rng = np.random.default_rng(seed)
    c1 = smooth_curve(rng, n=T, d=d, bend=1.5)
    c2 = smooth_curve(rng, n=T, d=d, bend=1.5)
    return np.asarray(srvf(c1)), np.asarray(srvf(c2))


def _random_gamma(rng, T, *, flat=False):
    inc = rng.exponential(size=T - 1)
    if flat:
        inc[rng.choice(T - 1, size=(T - 1) // 3, replace=False)] = 0.0
    g = np.concatenate([[0.0], np.cumsum(inc)])
    return g / g[-1]


# --- move set ---------------------------------------------------------------------------------


@pytest.mark.parametrize("n, count", [(1, 1), (2, 3), (3, 7), (7, 35), (10, 63)])
def test_moves_are_the_coprime_pairs(n, count):
    # Counts are OEIS A018805, the size of fdasrsf's neighbourhood for the same n.
    moves = dp_moves(n)
    assert len(moves) == count
    assert sorted(map(tuple, moves.tolist())) == sorted(reference_moves(n))


# --- exactness --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "T, n, d, seed",
    [(2, 7, 2, 0), (3, 7, 2, 1), (5, 2, 1, 2), (9, 3, 3, 3), (12, 7, 2, 4), (16, 4, 2, 5)],
)
def test_dp_equals_plain_numpy_dp(T, n, d, seed):
    q1, q2 = _random_pair(seed, T, d)
    gamma, cost = dp_warp_and_energy(q1, q2, neighbourhood=n)
    ref_gamma, ref_cost = reference_dp(q1, q2, n)
    assert abs(float(cost) - ref_cost) < 1e-9
    np.testing.assert_allclose(np.asarray(gamma), ref_gamma, atol=1e-12)
    # The reported minimum is the energy of the returned warp.
    assert abs(float(warp_energy(q1, q2, gamma)) - ref_cost) < 1e-9


@pytest.mark.parametrize("T, n, seed", [(6, 7, 0), (7, 3, 1), (6, 2, 2)])
def test_dp_equals_brute_force_over_all_paths(T, n, seed):
    q1, q2 = _random_pair(seed, T)
    energies = [reference_warp_energy(q1, q2, path_to_gamma(p, T)) for p in all_grid_paths(T, n)]
    assert len(energies) > 10
    _, cost = dp_warp_and_energy(q1, q2, neighbourhood=n)
    assert abs(float(cost) - min(energies)) < 1e-9


def test_dp_on_smooth_srvfs_matches_reference():
    q1, q2 = _smooth_pair(11, 20)
    gamma, cost = dp_warp_and_energy(q1, q2)
    ref_gamma, ref_cost = reference_dp(q1, q2, 7)
    assert abs(float(cost) - ref_cost) < 1e-9
    np.testing.assert_allclose(np.asarray(gamma), ref_gamma, atol=1e-12)


@pytest.mark.parametrize("flat", [False, True])
def test_warp_energy_matches_reference_for_any_monotone_warp(flat):
    rng = np.random.default_rng(3)
    q1, q2 = _random_pair(4, 15)
    for _ in range(5):
        g = _random_gamma(rng, 15, flat=flat)
        assert abs(float(warp_energy(q1, q2, g)) - reference_warp_energy(q1, q2, g)) < 1e-12


def test_warp_energy_at_identity_is_the_grid_l2_distance():
    q1, q2 = _random_pair(5, 30, 3)
    identity = np.linspace(0, 1, 30)
    assert abs(float(warp_energy(q1, q2, identity)) - float(l2_norm_squared(q1 - q2))) < 1e-12


@pytest.mark.parametrize("kind", ["random", "flat", "dp"])
def test_warp_samples_reproduce_the_energy(kind):
    # The intervals are found without sorting: check them against a plain-numpy merge (np.sort
    # of grid nodes and crossings) and the energy against the numpy reference, for warps with
    # flat parts and for DP warps, whose crossings fall exactly on grid nodes (ties).
    T = 12
    q1, q2 = _random_pair(6, T)
    rng = np.random.default_rng(0)
    if kind == "dp":
        g = np.asarray(dp_warp(q1, q2, neighbourhood=4))
    else:
        g = _random_gamma(rng, T, flat=kind == "flat")
    A, B, w = warp_samples(q1, q2, g)
    e = np.sum(np.asarray(w) * 0.5 * np.sum((np.asarray(A) - np.asarray(B)) ** 2, axis=(1, 2)))
    assert abs(e - reference_warp_energy(q1, q2, g)) < 1e-12
    assert abs(e - float(warp_energy(q1, q2, g))) < 1e-12
    w = np.asarray(w)
    assert np.all(w >= 0) and abs(float(np.sum(w)) - 1.0) < 1e-12
    grid = np.arange(T, dtype=float)
    merged = np.sort(np.concatenate([grid, np.interp(grid, g * (T - 1), grid)]))
    want = np.diff(merged) / (T - 1)
    np.testing.assert_allclose(np.sort(w[w > 1e-14]), np.sort(want[want > 1e-14]), atol=1e-14)


# --- properties -------------------------------------------------------------------------------


def test_dp_output_is_a_valid_warp_and_beats_identity_and_random_paths():
    T = 20
    q1, q2 = _smooth_pair(7, T)
    gamma, cost = dp_warp_and_energy(q1, q2)
    g = np.asarray(gamma)
    assert g[0] == 0.0 and g[-1] == 1.0 and np.all(np.diff(g) > 0)
    assert float(cost) <= float(warp_energy(q1, q2, np.linspace(0, 1, T))) + 1e-12
    rng = np.random.default_rng(0)
    moves = reference_moves(7)
    # Cells from which (T−1, T−1) can still be reached, so random walks never get stuck.
    end = (T - 1, T - 1)
    good = {end}
    for k in range(T - 1, -1, -1):
        for l in range(T - 1, -1, -1):
            if any((k + a, l + b) in good for a, b in moves):
                good.add((k, l))
    for _ in range(20):  # random grid paths with the same moves
        path = [(0, 0)]
        while path[-1] != end:
            k, l = path[-1]
            ok = [(a, b) for a, b in moves if (k + a, l + b) in good]
            a, b = ok[rng.integers(len(ok))]
            path.append((k + a, l + b))
        assert float(cost) <= reference_warp_energy(q1, q2, path_to_gamma(path, T)) + 1e-12


def test_larger_neighbourhood_never_costs_more():
    # The move sets are nested, so the optimum can only fall.
    q1, q2 = _smooth_pair(8, 20)
    costs = [float(dp_warp_and_energy(q1, q2, neighbourhood=n)[1]) for n in (2, 7, 10)]
    assert all(b <= a + 1e-12 for a, b in zip(costs, costs[1:]))
    assert costs[-1] < costs[0]


def test_identical_srvfs_give_identity_and_zero():
    q, _ = _smooth_pair(9, 20)
    gamma, cost = dp_warp_and_energy(q, q)
    np.testing.assert_allclose(np.asarray(gamma), np.linspace(0, 1, 20), atol=1e-12)
    assert abs(float(cost)) < 1e-12


def test_known_warp_is_recovered_within_the_grid_resolution():
    # q2 is q1 reparameterised by φ; the DP should find γ ≈ φ⁻¹ and an energy within the
    # grid's reach of the true warp sampled on the grid (not 0; docs/design.md §4: 2–4× above).
    T = 60
    rng = np.random.default_rng(10)
    curve = smooth_curve(rng, n=400, bend=1.5)
    t = np.linspace(0, 1, T)
    phi = lambda x: (np.exp(1.2 * x) - 1) / (np.exp(1.2) - 1)  # noqa: E731
    phi_inv = lambda y: np.log1p(y * (np.exp(1.2) - 1)) / 1.2  # noqa: E731
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    arc /= arc[-1]
    at = lambda s: np.stack([np.interp(s, arc, curve[:, k]) for k in range(2)], 1)  # noqa: E731
    q1 = np.asarray(srvf(at(t)))
    q2 = np.asarray(srvf(at(phi(t))))
    gamma, cost = dp_warp_and_energy(q1, q2)
    true_energy = float(warp_energy(q1, q2, phi_inv(t)))
    assert true_energy > 0
    assert float(cost) <= 5 * true_energy
    assert np.max(np.abs(np.asarray(gamma) - phi_inv(t))) < 3.0 / (T - 1)


def test_float32_and_float64_are_respected_and_agree():
    q1, q2 = _smooth_pair(12, 20)
    g64, c64 = dp_warp_and_energy(q1, q2)
    g32, c32 = dp_warp_and_energy(q1.astype(np.float32), q2.astype(np.float32))
    assert g64.dtype == jnp.float64 and c64.dtype == jnp.float64
    assert g32.dtype == jnp.float32 and c32.dtype == jnp.float32
    e32 = float(warp_energy(q1, q2, np.asarray(g32, np.float64)))
    assert e32 <= float(c64) * (1 + 1e-4) + 1e-6


# --- batching and compilation -----------------------------------------------------------------


def _batch(seed, B, T, d=2):
    pairs = [_smooth_pair(seed + i, T, d) for i in range(B)]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


def test_vmap_and_batch_equal_a_python_loop():
    q1s, q2s = _batch(20, 5, 20)
    loop = np.stack([np.asarray(dp_warp(a, b)) for a, b in zip(q1s, q2s)])
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(dp_warp))(q1s, q2s)), loop)
    np.testing.assert_array_equal(np.asarray(dp_warp_batch(q1s, q2s)), loop)
    # Nested vmaps are flattened into one batch.
    nested = jax.vmap(jax.vmap(dp_warp))(q1s[:4].reshape(2, 2, 20, 2), q2s[:4].reshape(2, 2, 20, 2))
    np.testing.assert_array_equal(np.asarray(nested).reshape(4, 20), loop[:4])
    # An unbatched argument is broadcast.
    one = jax.vmap(dp_warp, in_axes=(0, None))(q1s, q2s[0])
    np.testing.assert_array_equal(np.asarray(one[2]), np.asarray(dp_warp(q1s[2], q2s[0])))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_active", [1, 4, 8, 11, 13, 21])
def test_each_pair_gets_the_same_warp_alone_in_a_block_or_in_the_remainder(monkeypatch, n_active, dtype):
    # Blocks of 8, a remainder of 5 or more as a block, fewer pair by pair: every active pair's
    # warp equals, bit for bit, what it gets alone, and its DP minimum up to rounding (the
    # engine's results must not depend on how many DPs a loop step happens to have; it uses
    # the warps).
    monkeypatch.setattr(_warp, "_block_size", lambda size: 8)
    monkeypatch.setattr(_warp, "_SINGLES_BELOW", 5)
    q1s, q2s = (x.astype(dtype) for x in _batch(40 + n_active, 24, 17, d=3))
    active = np.zeros(24, bool)
    active[np.random.default_rng(n_active).permutation(24)[:n_active]] = True
    fn = jax.jit(jax.vmap(lambda a, b, m: _warp.dp_warp_if(a, b, m, neighbourhood=7)))
    gammas, costs = fn(q1s, q2s, active)
    for i in range(24):
        if active[i]:
            g, c = dp_warp_and_energy(q1s[i], q2s[i])
            np.testing.assert_array_equal(np.asarray(gammas[i]), np.asarray(g))
            np.testing.assert_allclose(np.asarray(costs[i]), np.asarray(c), rtol=8 * np.finfo(dtype).eps)
        else:
            np.testing.assert_array_equal(np.asarray(gammas[i]), np.linspace(0, 1, 17, dtype=dtype))


def test_blocked_and_masked_batches_equal_a_python_loop(monkeypatch):
    # Small blocks so that a small test batch spans several (packed) blocks; a remainder of
    # fewer than `_SINGLES_BELOW` pairs runs pair by pair.
    monkeypatch.setattr(_warp, "_block_size", lambda size: 3)
    monkeypatch.setattr(_warp, "_SINGLES_BELOW", 2)
    monkeypatch.setattr(_warp, "_MIN_BLOCK", 2)
    q1s, q2s = _batch(30, 8, 13)
    active = np.array([True, False, True, True, False, True, True, False])
    loop = [dp_warp_and_energy(a, b) for a, b in zip(q1s, q2s)]
    fn = jax.jit(jax.vmap(lambda a, b, m: _warp.dp_warp_if(a, b, m, neighbourhood=7)))
    gammas, costs = fn(q1s, q2s, active)
    for i, (g, c) in enumerate(loop):
        if active[i]:
            np.testing.assert_array_equal(np.asarray(gammas[i]), np.asarray(g))
            assert float(costs[i]) == pytest.approx(float(c), abs=1e-12)
        else:  # skipped lanes: identity, cost 0
            np.testing.assert_array_equal(np.asarray(gammas[i]), np.linspace(0, 1, 13))
            assert float(costs[i]) == 0.0
    all_on = jax.jit(jax.vmap(dp_warp))(q1s, q2s)
    np.testing.assert_array_equal(np.asarray(all_on), np.stack([np.asarray(g) for g, _ in loop]))


def test_no_retrace_or_recompile_for_same_shapes(monkeypatch):
    calls = []
    forward = _warp._forward
    monkeypatch.setattr(_warp, "_forward", lambda *a: calls.append(1) or forward(*a))
    q1s, q2s = _batch(40, 3, 17)
    dp_warp(q1s[0], q2s[0], neighbourhood=6)
    dp_warp_batch(q1s, q2s, neighbourhood=6)
    n_traces = len(calls)
    assert n_traces >= 2
    dp_warp(q1s[1], q2s[1], neighbourhood=6)
    dp_warp(q1s[2] * 2.0, q2s[0], neighbourhood=6)
    dp_warp_batch(q2s, q1s, neighbourhood=6)
    assert len(calls) == n_traces


def test_no_recompile_logged_for_same_shapes(caplog):
    q1s, q2s = _batch(50, 2, 20)
    dp_warp(q1s[0], q2s[0])
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        caplog.clear()
        dp_warp(q1s[1], q2s[1])
        dp_warp(q2s[0], q1s[1])
    assert not [r for r in caplog.records if "Compiling" in r.getMessage()]


# --- applying warps ---------------------------------------------------------------------------


def test_apply_warp_identity_is_a_no_op():
    q, _ = _random_pair(60, 20, 3)
    identity = np.linspace(0, 1, 20)
    np.testing.assert_allclose(np.asarray(apply_warp_srvf(q, identity)), q, atol=1e-14)
    np.testing.assert_allclose(np.asarray(apply_warp_curve(q, identity)), q, atol=1e-14)


def test_apply_warp_matches_numpy():
    rng = np.random.default_rng(61)
    T = 25
    q, _ = _random_pair(61, T)
    g = _random_gamma(rng, T, flat=True)
    t = np.linspace(0, 1, T)
    moved = np.stack([np.interp(g, t, q[:, k]) for k in range(2)], 1)
    np.testing.assert_allclose(np.asarray(apply_warp_curve(q, g)), moved, atol=1e-14)
    rs = np.sqrt(np.diff(g) * (T - 1))
    speed = 0.5 * (np.concatenate([rs[:1], rs]) + np.concatenate([rs, rs[-1:]]))
    expected = moved * speed[:, None]
    np.testing.assert_allclose(np.asarray(apply_warp_srvf(q, g)), expected, atol=1e-14)


def test_apply_warp_srvf_is_safe_where_the_warp_is_flat():
    q, _ = _random_pair(62, 12)
    g = np.array([0, 0, 0, 0.1, 0.3, 0.3, 0.3, 0.5, 0.8, 0.9, 1.0, 1.0])
    out = apply_warp_srvf(q, g)
    assert np.all(np.isfinite(np.asarray(out)))
    grad = jax.grad(lambda gg: jnp.sum(apply_warp_srvf(q, gg) ** 2) + warp_energy(q, q, gg))(g)
    assert np.all(np.isfinite(np.asarray(grad)))


def test_gradient_flows_through_the_energy_not_the_warp():
    q1, q2 = _smooth_pair(63, 20)

    def energy(x):
        gamma = dp_warp(x, q2)
        return warp_energy(x, q2, gamma)

    g = jax.grad(energy)(jnp.asarray(q1))
    gamma = dp_warp(q1, q2)
    expected = jax.grad(lambda x: warp_energy(x, q2, gamma))(jnp.asarray(q1))
    np.testing.assert_allclose(np.asarray(g), np.asarray(expected), atol=1e-14)


# --- errors -----------------------------------------------------------------------------------


def test_clear_errors_for_bad_input():
    q = np.zeros((10, 2))
    with pytest.raises(InvalidRootError, match="share the shape"):
        dp_warp(q, np.zeros((11, 2)))
    with pytest.raises(InvalidRootError, match=r"\(T, d\)"):
        dp_warp(np.zeros((3, 10, 2)), np.zeros((3, 10, 2)))
    with pytest.raises(InvalidRootError, match="T >= 2"):
        dp_warp(np.zeros((1, 2)), np.zeros((1, 2)))
    with pytest.raises(InvalidRootError, match="floating point"):
        dp_warp(np.zeros((10, 2), int), np.zeros((10, 2), int))
    for bad in (0, 2.5, True, jnp.asarray(3)):
        with pytest.raises(ValueError, match="neighbourhood"):
            dp_warp(q, q, neighbourhood=bad)
    with pytest.raises(InvalidRootError, match=r"\(B, T, d\)"):
        dp_warp_batch(q, q)
    with pytest.raises(InvalidRootError, match="gamma must be"):
        warp_energy(q, q, np.linspace(0, 1, 9))
    with pytest.raises(InvalidRootError, match="gamma must be"):
        apply_warp_curve(q, np.linspace(0, 1, 9))


def test_batch_gives_nan_warps_for_non_finite_pairs():
    q1s, q2s = _batch(70, 3, 20)
    q1s[1, 5, 0] = np.inf
    g = np.asarray(dp_warp_batch(q1s, q2s))
    assert np.all(np.isnan(g[1]))
    np.testing.assert_array_equal(g[[0, 2]], np.stack([dp_warp(q1s[i], q2s[i]) for i in (0, 2)]))


_TWO_DEVICES = """
import jax
jax.config.update("jax_num_cpu_devices", 2)
jax.config.update("jax_enable_x64", True)
import numpy as np
from rootshape_jax._warp import dp_warp, dp_warp_batch
assert len(jax.devices()) == 2
rng = np.random.default_rng(0)
q1, q2 = rng.normal(size=(2, 7, 15, 2))  # odd batch: padded to 8, split 4 + 4
q1[6, 3, 1] = np.nan
g = np.asarray(dp_warp_batch(q1, q2))
assert np.all(np.isnan(g[6])), g[6]
loop = np.stack([np.asarray(dp_warp(a, b)) for a, b in zip(q1[:6], q2[:6])])
assert np.array_equal(g[:6], loop)
print("ok")
"""


@pytest.mark.slow
def test_batch_split_over_two_devices_equals_a_loop():
    # Several host devices must be configured before JAX starts: use a fresh interpreter.
    out = subprocess.run([sys.executable, "-c", _TWO_DEVICES], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_runtime_errors_for_bad_values():
    q = np.ones((10, 2))
    bad = q.copy()
    bad[3, 1] = np.nan
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):
        dp_warp(bad, q)
    decreasing = np.linspace(0, 1, 10)[::-1]
    with pytest.raises(eqx.EquinoxRuntimeError, match="nondecreasing"):
        warp_energy(q, q, decreasing)
    with pytest.raises(eqx.EquinoxRuntimeError, match="nondecreasing"):
        apply_warp_srvf(q, np.linspace(0, 0.5, 10))
