"""Thickness, the extended-SRVF metric term (DESIGN.md §11): λr = 0 is today's metric bit for
bit, rigid motions leave it invariant, a thinner twin moves away as λr grows, gradients stay
finite at zero radius, and curves with radii come back from the SRVF tree."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rootshape_jax as rs

from helpers import random_root

T, K = 24, 6


def _with_radii(tree: rs.RootTree, rng, *, scale=1.0) -> rs.RootTree:
    """Tapering radii (thick at the base, thin at the tip), different per branch."""
    t = np.linspace(0, 1, T)
    lead = tree.main.shape[:-2]
    r0 = 0.02 * (1.2 - t) * (1 + 0.3 * rng.random(lead + (1,)))
    rl = 0.01 * (1.1 - t) * (1 + 0.5 * rng.random(lead + (K, 1)))
    rl = rl * np.asarray(tree.mask)[..., None]
    return dataclasses.replace(tree, main_radius=jnp.asarray(scale * r0), lateral_radius=jnp.asarray(scale * rl))


@pytest.fixture(scope="module")
def trees():
    rng = np.random.default_rng(2)
    roots = [random_root(rng, n_laterals=k) for k in (2, 3, 1, 3)]
    plain = rs.batch(roots, n_points=T, max_laterals=K, normalise_scale=True)
    return plain, _with_radii(plain, np.random.default_rng(3))


def test_zero_thickness_weight_is_todays_metric_bit_for_bit(trees):
    plain, thick = trees
    w = rs.Weights(thickness=0.0)
    a, b = rs.unstack(plain)[:2]
    ta, tb = rs.unstack(thick)[:2]
    r0, r1 = rs.register(a, b, weights=w), rs.register(ta, tb, weights=w)
    assert not r1.registered.has_thickness
    for x, y in zip(jax.tree.leaves(r0), jax.tree.leaves(r1)):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    D0 = rs.pairwise_distances(plain, weights=w, progress=False)
    D1 = rs.pairwise_distances(thick, weights=w, progress=False)
    assert np.array_equal(np.asarray(D0), np.asarray(D1))
    m0 = rs.karcher_mean(plain, weights=w, max_steps=3, throw=False)
    m1 = rs.karcher_mean(thick, weights=w, max_steps=3, throw=False)
    assert np.array_equal(np.asarray(m0.energy_trace), np.asarray(m1.energy_trace))


def test_extended_srvf_round_trip_gives_the_radii_back(trees):
    _, thick = trees
    s = rs.to_srvf(thick, weights=rs.Weights(thickness=0.5))
    assert s.has_thickness and s.q0.shape[-1] == 3 and s.dim == 2
    back = rs.to_curves(s)
    np.testing.assert_allclose(np.asarray(back.main), np.asarray(thick.main), atol=1e-9)
    np.testing.assert_allclose(np.asarray(back.main_radius), np.asarray(thick.main_radius), atol=1e-9)
    m = np.asarray(thick.mask)
    np.testing.assert_allclose(
        np.asarray(back.lateral_radius)[m], np.asarray(thick.lateral_radius)[m], atol=1e-9
    )


def _rigid(tree: rs.RootTree, angle: float, shift) -> rs.RootTree:
    c, s = np.cos(angle), np.sin(angle)
    R = jnp.asarray([[c, -s], [s, c]])
    move = lambda x: x @ R.T + jnp.asarray(shift)  # noqa: E731
    return dataclasses.replace(tree, main=move(tree.main), laterals=move(tree.laterals))


@pytest.mark.parametrize("angle, shift", [(0.7, (3.0, -2.0)), (-2.1, (100.0, 50.0))])
def test_invariant_to_rigid_motion_with_radii(trees, angle, shift):
    _, thick = trees
    w = rs.Weights(thickness=0.8)
    a, b = rs.unstack(thick)[:2]
    d0 = float(rs.distance(a, b, weights=w))
    d1 = float(rs.distance(a, _rigid(b, angle, shift), weights=w))
    d2 = float(rs.distance(_rigid(a, -angle, shift), b, weights=w))
    assert d0 > 0
    assert d1 == pytest.approx(d0, rel=1e-6)
    assert d2 == pytest.approx(d0, rel=1e-6)
    # Zero self-distance with radii.
    assert float(rs.distance(a, _rigid(a, angle, shift), weights=w)) < 1e-6


def test_thinner_twin_moves_away_as_thickness_weight_grows(trees):
    _, thick = trees
    a = rs.unstack(thick)[1]
    twin = dataclasses.replace(a, main_radius=0.3 * a.main_radius, lateral_radius=0.3 * a.lateral_radius)
    ds = [float(rs.distance(a, twin, weights=rs.Weights(thickness=lam))) for lam in (0.0, 0.1, 0.5, 2.0, 8.0)]
    assert ds[0] == 0.0
    assert all(x < y for x, y in zip(ds, ds[1:])), ds


def test_gradients_finite_at_zero_radius(trees):
    _, thick = trees
    a, b = rs.unstack(thick)[:2]
    b = dataclasses.replace(b, main_radius=jnp.zeros_like(b.main_radius), lateral_radius=jnp.zeros_like(b.lateral_radius))
    w = rs.Weights(thickness=0.5)

    def dist(r):
        return rs.distance(a, dataclasses.replace(b, main_radius=r), weights=w)

    g = jax.grad(dist)(b.main_radius)
    assert np.all(np.isfinite(np.asarray(g)))
    assert float(rs.distance(b, b, weights=w)) == 0.0


def test_mean_pca_geodesic_and_synthesis_with_thickness(trees):
    _, thick = trees
    w = rs.Weights(thickness=0.5)
    m = rs.karcher_mean(thick, weights=w, max_steps=5, throw=False)
    assert m.fitted.has_thickness and m.mean.main_radius is not None
    assert np.all(np.isfinite(np.asarray(m.energy_trace)))
    pc = rs.tangent_pca(m)
    mode = rs.modes(pc, [-1.0, 0.0, 1.0])
    assert mode.main_radius.shape == (3, T)
    a, b = rs.unstack(thick)[:2]
    path = rs.geodesic(a, b, weights=w, n_steps=3)
    np.testing.assert_allclose(np.asarray(path.main_radius[0]), np.asarray(a.main_radius), atol=1e-9)


def test_mixing_thickness_settings_is_refused(trees):
    plain, thick = trees
    s = rs.to_srvf(thick, weights=rs.Weights(thickness=0.5))
    with pytest.raises(ValueError, match="thickness weight"):
        rs.register(rs.unstack(s)[0], rs.unstack(s)[1], weights=rs.Weights(thickness=0.2))
    with pytest.raises(ValueError, match="thickness channel"):
        rs.register(rs.unstack(s)[0], rs.unstack(plain)[1], weights=rs.Weights(thickness=0.5))
