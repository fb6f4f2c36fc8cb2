"""Thickness, the extended-SRVF metric term (docs/design.md §11): λr = 0 is today's metric bit for
bit, rigid motions leave it invariant, a thinner twin moves away as λr grows, gradients stay
finite at zero radius, and curves with radii come back from the SRVF tree."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root

import rootshape_jax as rs

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


def test_extended_srvf_round_trip_gives_the_radii_back():
    """to_curves(to_srvf(tree)) returns coordinates and radii, converging at second order in T
    as the plain SRVF round trip does (the SRVF discretisation is exact only on straight lines)."""
    errors = []
    for n in (50, 200):
        t = np.linspace(0, 1, n)
        main = np.stack([0.2 * np.sin(3 * t), t], axis=1)
        lat = np.stack([0.3 * t, 0.5 + 0.1 * t**2], axis=1) + main[n // 2]
        tree = rs.RootTree(
            main=jnp.asarray(main),
            laterals=jnp.asarray(lat[None]),
            attach=jnp.asarray([t[n // 2]]),
            mask=jnp.asarray([True]),
            main_radius=jnp.asarray(0.05 * (1.2 - t) + 0.01 * np.sin(5 * t)),
            lateral_radius=jnp.asarray((0.02 * (1.1 - t))[None]),
        )
        s = rs.to_srvf(tree, weights=rs.Weights(thickness=0.5))
        assert s.has_thickness and s.q0.shape[-1] == 3 and s.dim == 2
        back = rs.to_curves(s)
        errors.append(
            [
                np.max(np.abs(np.asarray(back.main) - main)),
                np.max(np.abs(np.asarray(back.main_radius) - np.asarray(tree.main_radius))),
                np.max(np.abs(np.asarray(back.lateral_radius) - np.asarray(tree.lateral_radius))),
            ]
        )
    coarse, fine = np.asarray(errors)
    assert np.all(fine < 1e-4), fine
    assert np.all(fine < coarse / 8), (coarse, fine)  # 4× finer grid: ~16× smaller error


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
    assert ds[0] < 1e-12  # radii are not seen at λr = 0: the twin is the same shape
    assert all(x < y for x, y in zip(ds, ds[1:])), ds


def test_gradients_finite_at_zero_radius(trees):
    _, thick = trees
    a, b = rs.unstack(thick)[:2]
    b = dataclasses.replace(
        b, main_radius=jnp.zeros_like(b.main_radius), lateral_radius=jnp.zeros_like(b.lateral_radius)
    )
    w = rs.Weights(thickness=0.5)

    def dist(r):
        return rs.distance(a, dataclasses.replace(b, main_radius=r), weights=w)

    g = jax.grad(dist)(b.main_radius)
    assert np.all(np.isfinite(np.asarray(g)))
    assert float(rs.distance(b, b, weights=w)) < 1e-12


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
    # The path starts at a (as its SRVF tree gives it back).
    a_back = rs.to_curves(rs.to_srvf(a, weights=w))
    np.testing.assert_allclose(np.asarray(path.main_radius[0]), np.asarray(a_back.main_radius), atol=1e-12)
    np.testing.assert_allclose(np.asarray(path.main[0]), np.asarray(a_back.main), atol=1e-12)


def test_mixing_thickness_settings_is_refused(trees):
    plain, thick = trees
    s = rs.to_srvf(thick, weights=rs.Weights(thickness=0.5))
    with pytest.raises(ValueError, match="thickness weight"):
        rs.register(rs.unstack(s)[0], rs.unstack(s)[1], weights=rs.Weights(thickness=0.2))
    with pytest.raises(ValueError, match="thickness channel"):
        rs.register(rs.unstack(s)[0], rs.unstack(plain)[1], weights=rs.Weights(thickness=0.5))
