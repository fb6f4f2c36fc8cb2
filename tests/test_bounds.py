"""The DP-free lower bounds that let the engine skip lateral DPs: each is checked against the
energy of actual warps (random monotone warps and the DP's own), and pruning with them against
running every DP, on roots with many similar laterals (the hard case for the bounds)."""

import itertools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root, rotation_matrix, smooth_curve
from test_hierarchy import deep_root

import rootshape_jax as rs
from rootshape_jax._curves import l2_norm_squared, srvf
from rootshape_jax._engine import (
    N_BLOCKS,
    _cone_cap,
    block_cones,
    children_of,
    lower_bounds,
    prepare,
    refined_child_energy_bounds,
    refined_energy_bounds,
    rotate_batch,
    warp_preserving_norm,
)
from rootshape_jax._warp import dp_warp

T = 40


def _random_warp(rng, T):
    # A random strictly increasing γ: cumulative positive steps, some very steep or flat.
    steps = rng.gamma(0.3, size=T - 1) + 1e-3
    g = np.concatenate([[0.0], np.cumsum(steps)])
    return g / g[-1]


def _pair_batch(seed, d, n_laterals):
    rng = np.random.default_rng(seed)
    ra = random_root(rng, n_laterals=n_laterals, d=d)
    rb = random_root(rng, n_laterals=n_laterals, d=d)
    a, b = rs.unstack(rs.batch([ra, rb], n_points=T, max_laterals=2 * n_laterals))
    add = lambda t: jax.tree.map(lambda x: x[None], t)  # noqa: E731
    return rs.to_srvf(add(a)), rs.to_srvf(add(b)), rng


def test_block_cones_hold_every_interpolated_direction():
    rng = np.random.default_rng(0)
    for d in (2, 3):
        q = jnp.asarray(srvf(jnp.asarray(smooth_curve(rng, n=T, d=d, bend=4.0))))
        axes, half = block_cones(q, N_BLOCKS)
        edges = np.round(np.linspace(0, T - 1, N_BLOCKS + 1)).astype(int)
        for t in range(T - 1):
            # The block that holds both ends of the segment [t, t+1].
            j = int(np.searchsorted(edges, t, side="right") - 1)
            assert edges[j] <= t and t + 1 <= edges[j + 1]
            for f in np.linspace(0, 1, 7):
                v = (1 - f) * q[t] + f * q[t + 1]
                u = v / np.linalg.norm(v)
                angle = np.arccos(np.clip(float(u @ axes[j]), -1, 1))
                assert angle <= float(half[j]) + 1e-9


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cone_cap_is_above_the_exact_cap_of_the_true_angle(dtype):
    # Unit directions and cone half-angles drawn in float64 (the truth), the cap computed from
    # their rounded cosine in `dtype`, as the engine does; many nearly parallel and
    # antiparallel pairs, where the cosine carries the most error.
    rng = np.random.default_rng(5)
    n = 200_000
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    tilt = np.concatenate(
        [rng.uniform(0, np.pi, n // 2), rng.uniform(0, 1e-3, n // 4), np.pi - rng.uniform(0, 1e-3, n // 4)]
    )
    v = np.cos(tilt)[:, None] * u + np.sin(tilt)[:, None] * np.cross(u, rng.normal(size=(n, 3)))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    half = np.concatenate([rng.uniform(0, 1.5, n - n // 8), rng.uniform(0, 1e-4, n // 8)])
    true_angle = np.arccos(np.clip(np.sum(u * v, axis=1), -1, 1))
    exact = np.maximum(np.cos(np.maximum(true_angle - half, 0.0)), 0.0)  # a cap of cosines ≥ 0
    ur, vr = u.astype(dtype), v.astype(dtype)
    cos_rounded = jnp.sum(jnp.asarray(ur) * jnp.asarray(vr), axis=1)
    cap = np.asarray(_cone_cap(cos_rounded, jnp.asarray(half.astype(dtype)), dtype), np.float64)
    assert np.all(cap >= exact)
    # ... and not much above it: the safety margins are a few √ε.
    assert np.max(cap - exact) <= 8 * np.sqrt(np.finfo(dtype).eps)


@pytest.mark.parametrize("seed", [4, 5])
def test_refined_child_bounds_equal_the_refined_bounds_of_the_children_and_stay_below_their_warp_energies(seed):
    rng = np.random.default_rng(seed)
    roots = [deep_root(rng, n_laterals=4, max_sub=3) for _ in range(2)]
    trees = rs.to_srvf(rs.batch(roots, n_points=T, depth=3, max_children=(8, 6), dtype=np.float64))
    a, b = (jax.tree.map(lambda x, k=k: x[k : k + 1], trees) for k in range(2))
    p = prepare(a, b, rs.Weights())
    O = jnp.asarray(rotation_matrix(rng, 2))[None]
    K = p.La.shape[1]
    lanes = jnp.arange(K * K)
    got = np.asarray(refined_child_energy_bounds(p, O, lanes))  # [K·K, K2, K2]
    zero = jnp.zeros_like(lanes)
    ca, cb = children_of(p.a, zero, lanes // K), children_of(p.b, zero, lanes % K)
    pc = prepare(ca, cb, rs.Weights())
    K2 = pc.La.shape[1]
    Os = jnp.broadcast_to(O, (K * K, 2, 2))
    want = np.asarray(refined_energy_bounds(pc, rotate_batch(pc.blocks_b[0], Os), jnp.arange(K * K * K2 * K2)))
    real = np.asarray(pc.both)
    np.testing.assert_allclose(got[real], want.reshape(real.shape)[real], rtol=1e-12, atol=1e-14)
    assert np.all(got[~real] == 0)
    assert real.sum() > 20  # the roots have children pairs to bound
    qb = rotate_batch(cb.q, Os)
    for s, k, m in zip(*np.nonzero(real)):
        q1, q2 = ca.q[s, k], qb[s, m]
        warps = [_random_warp(rng, T) for _ in range(5)] + [np.asarray(dp_warp(q1, q2))]
        energy = min(float(l2_norm_squared(q1 - warp_preserving_norm(q2, jnp.asarray(g)))) for g in warps)
        assert got[s, k, m] <= energy + 1e-10


@pytest.mark.parametrize("d,seed", list(itertools.product([2, 3], [1, 2, 3])))
def test_refined_bound_is_below_every_warp_energy(d, seed):
    a, b, rng = _pair_batch(seed, d, 4)
    p = prepare(a, b, rs.Weights())
    O = jnp.asarray(rotation_matrix(rng, d))[None]
    K = p.La.shape[1]
    qb = rotate_batch(b.q, O)
    axes_b = rotate_batch(p.blocks_b[0], O)
    lanes = jnp.arange(K * K)
    refined = np.asarray(refined_energy_bounds(p, axes_b, lanes)).reshape(K, K)
    cone = np.asarray(lower_bounds(p, O))[0]
    both = np.asarray(p.both[0])
    tightened = 0
    for i, j in zip(*np.nonzero(both)):
        qa_i, qb_j = a.q[0, i], qb[0, j]
        warps = [_random_warp(rng, T) for _ in range(30)] + [np.asarray(dp_warp(qa_i, qb_j)), np.linspace(0, 1, T)]
        energies = [float(l2_norm_squared(qa_i - warp_preserving_norm(qb_j, jnp.asarray(g)))) for g in warps]
        assert refined[i, j] <= min(energies) + 1e-10
        assert cone[i, j] <= min(energies) + 1e-10
        tightened += refined[i, j] > cone[i, j] + 1e-9
    # It is a real improvement on the single-cone bound for some pairs.
    assert tightened > 0


@pytest.mark.parametrize("seed", [11, 12])
def test_pruning_equals_every_dp_on_many_similar_laterals(seed):
    # Many laterals of similar length and direction: the bounds are loose, the assignment
    # needs many DPs to certify, and the refined bound is used a lot.
    rng = np.random.default_rng(seed)
    roots = [random_root(rng, n_laterals=8, d=3) for _ in range(2)]
    a, b = rs.unstack(rs.batch(roots, n_points=T, max_laterals=16))
    w = rs.Weights(main=0.5, lateral=1.0, position=0.05)
    full = rs.register(a, b, weights=w, prune=False)
    pruned = rs.register(a, b, weights=w, prune=True)
    assert int(pruned.n_lateral_dp) < int(full.n_lateral_dp)
    assert float(pruned.energy) == pytest.approx(float(full.energy), rel=1e-12)
    np.testing.assert_allclose(np.asarray(pruned.rotation), np.asarray(full.rotation), atol=1e-12)


SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _real_population(name):
    if name == "rootnav":
        files = sorted((SHARED / "rsml" / "rootnav_osr").glob("*.rsml"))[:3]
        if not files:
            pytest.skip("../shared/data is absent")
        from rootshape_jax.io import read_rsml

        return [r for f in files for r in read_rsml(f)]
    pytest.importorskip("plantbox", reason="CPlantBox (the sim extra)")
    from rootshape_jax.datasets import simulated_roots

    return simulated_roots("pea", 3, days=10, seed=0)


@pytest.mark.slow
@pytest.mark.parametrize("name,normalise", list(itertools.product(["rootnav", "pea"], [False, True])))
def test_pruning_equals_every_dp_on_real_populations(name, normalise):
    # The populations users have (real tracings in pixels, CPlantBox taproots in mm with ~20
    # similar laterals): pruned registration equals running every DP, in float64.
    roots = _real_population(name)
    trees = rs.batch(roots, n_points=50, normalise_scale=normalise)
    parts = rs.unstack(trees)
    for i, j in [(0, 1), (1, 2)]:
        full = rs.register(parts[i], parts[j], prune=False)
        pruned = rs.register(parts[i], parts[j], prune=True)
        assert int(pruned.n_lateral_dp) < int(full.n_lateral_dp)
        assert float(pruned.energy) == pytest.approx(float(full.energy), rel=1e-12)
