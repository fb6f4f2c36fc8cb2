"""Root, RootTree, SRVFTree: construction, padding, conversions, batching and input errors."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root, tree_allclose

import rootshape_jax as rs
from rootshape_jax._metric import preshape_terms
from rootshape_jax._tree import normalising_length


def test_attach_computed_by_projection():
    main = np.stack([np.zeros(11), np.linspace(0, 10, 11)], 1)
    lat = np.array([[0.2, 2.5], [3.0, 3.0]])  # starts near y = 2.5
    r = rs.Root(main=main, laterals=[lat])
    assert r.attach[0] == pytest.approx(0.25)
    assert r.n_laterals == 1 and r.dim == 2
    assert r.main_length == pytest.approx(10.0)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(main=np.zeros((1, 2))), "at least 2 points"),
        (dict(main=np.array([[0, 0], [np.nan, 1.0]])), "NaN or inf"),
        (dict(main=np.array([[0, 0], [np.inf, 1.0]])), "NaN or inf"),
        (dict(main=np.zeros((3, 4))), "2D or 3D"),
        (dict(main=np.zeros((3, 2)), laterals=[np.zeros((3, 3))]), "dimension 3"),
        (dict(main=np.zeros((3, 2)), laterals=[np.zeros((3, 2))], attach=[1.5]), r"\[0, 1\]"),
        (dict(main=np.zeros((3, 2)), laterals=[np.zeros((3, 2))], attach=[0.1, 0.2]), "one per lateral"),
        (dict(main=np.zeros((3, 2)), laterals=[np.zeros((1, 2))]), "lateral 0"),
        (dict(main=[["a", "b"], ["c", "d"]]), "numbers"),
    ],
)
def test_root_errors_are_clear(kwargs, match):
    with pytest.raises(rs.InvalidRootError, match=match):
        rs.Root(**kwargs)


def test_capacity_error_and_mixed_dimensions():
    rng = np.random.default_rng(0)
    r = random_root(rng, n_laterals=5)
    with pytest.raises(rs.CapacityError, match="capacity is K = 3"):
        rs.batch([r], max_laterals=3)
    r3 = random_root(rng, n_laterals=2, d=3)
    with pytest.raises(rs.InvalidRootError, match="mix dimensions"):
        rs.batch([r, r3])
    with pytest.raises(ValueError, match="empty"):
        rs.batch([])


@pytest.mark.parametrize("d", [2, 3])
def test_batch_shapes_padding_and_lateral_bases(d):
    rng = np.random.default_rng(d)
    roots = [random_root(rng, n_laterals=n, d=d) for n in (0, 3, 6)]
    t = rs.batch(roots, n_points=25)
    assert t.main.shape == (3, 25, d)
    assert t.laterals.shape == (3, 12, 25, d)  # K = 2 × 6 by default
    np.testing.assert_array_equal(np.asarray(t.mask.sum(1)), [0, 3, 6])
    assert np.all(np.isfinite(np.asarray(t.laterals)))
    s = rs.to_srvf(t)
    # Null slots are exact zeros (finite padding, never NaN).
    assert np.all(np.asarray(s.q)[~np.asarray(s.mask)] == 0)
    # Every real lateral starts on the main root at its attachment fraction.
    from rootshape_jax._curves import interpolate_at_fraction

    for i, k in itertools.product(range(3), range(12)):
        if t.mask[i, k]:
            base = interpolate_at_fraction(t.main[i], t.attach[i, k])
            np.testing.assert_allclose(t.laterals[i, k, 0], base, atol=1e-9)


def test_normalise_scale():
    rng = np.random.default_rng(1)
    r = random_root(rng, n_laterals=2, main_length=7.0)
    t = rs.batch(r, normalise_scale=True)
    assert float(rs.curve_length(t.main)) == pytest.approx(1.0, rel=1e-9)
    # Each root is divided by its length about (0, 0): a root scaled about (0, 0) gives the
    # same tree, and the base moves to seed / length.
    big = rs.batch(r.scaled_about(np.zeros(r.dim), 3.0), normalise_scale=True)
    assert tree_allclose(t, big, atol=1e-12)
    np.testing.assert_allclose(t.main[0], r.main[0] / normalising_length(r, 100), rtol=1e-12)


@pytest.mark.parametrize("plant", [False, True])
def test_normalising_length_takes_a_normalised_tree_back_to_the_input(plant):
    # The CLI writes normalised results back in the input's units by this length (a coarse
    # resampling makes it differ from the polyline's own length, so the two must be one rule).
    from rootshape_jax._tree import normalising_length
    from rootshape_jax.io import plant_system

    rng = np.random.default_rng(3)
    r = random_root(rng, n_laterals=3, main_length=7.0)
    if plant:
        r = plant_system([r, random_root(rng, n_laterals=2, main_length=9.0)])
    kw = dict(n_points=12, dtype=np.float64, depth=3 if plant else 2)
    length = normalising_length(r, 12)
    assert length < (9.0 if plant else 7.0) - 1e-3  # 12 points cut the corners
    # Normalisation divides about (0, 0): the base goes back to the seed with `base=`.
    back = rs.scale_tree(rs.batch(r, normalise_scale=True, **kw), length, base=r.main[0])
    assert tree_allclose(back, rs.batch(r, **kw), atol=1e-9)


def test_srvf_curves_round_trip_and_to_roots():
    rng = np.random.default_rng(2)
    roots = [random_root(rng, n_laterals=n) for n in (1, 4)]
    t = rs.batch(roots, n_points=200)
    back = rs.to_curves(rs.to_srvf(t))
    # The inputs are polylines with corners (80 and 30 vertices), so the bisector directions
    # at the corners cost a little: a few tenths of a percent of the unit main-root length.
    assert np.abs(np.asarray(back.main - t.main)).max() < 3e-3
    m = np.asarray(t.mask)
    assert np.abs(np.asarray(back.laterals - t.laterals))[m].max() < 3e-3
    again = rs.to_roots(t)
    assert [r.n_laterals for r in again] == [1, 4]
    np.testing.assert_allclose(again[1].attach, roots[1].attach, atol=1e-12)


def test_stack_unstack_round_trip_and_errors():
    rng = np.random.default_rng(3)
    t = rs.batch([random_root(rng, n_laterals=2) for _ in range(3)], n_points=20)
    parts = rs.unstack(t)
    assert len(parts) == 3 and parts[0].main.shape == (20, 2)
    assert tree_allclose(rs.stack(parts), t)
    other = rs.batch([random_root(rng, n_laterals=5)], n_points=20)
    with pytest.raises(ValueError, match="different capacities"):
        rs.stack([parts[0], rs.unstack(other)[0]])


def test_module_shape_checks():
    with pytest.raises(ValueError, match="laterals has shape"):
        rs.RootTree(jnp.zeros((5, 2)), jnp.zeros((3, 4, 2)), jnp.zeros(3), jnp.zeros(3, bool))
    with pytest.raises(ValueError, match="mask must be boolean"):
        rs.RootTree(jnp.zeros((5, 2)), jnp.zeros((3, 5, 2)), jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="non-negative"):
        rs.Weights(main=-1.0)


def test_preshape_metric_gradient_matches_finite_differences_and_is_finite_at_zero_speed():
    rng = np.random.default_rng(4)
    roots = [random_root(rng, n_laterals=2) for _ in range(2)]
    a, b = rs.unstack(rs.batch(roots, n_points=15))
    w = rs.Weights(main=0.3, lateral=1.0, position=2.0)

    def f(lat_a):
        ta = a.__class__(a.main, lat_a, a.attach, a.mask)
        return preshape_terms(rs.to_srvf(ta), rs.to_srvf(b), w).total

    x = np.asarray(a.laterals)
    g = np.asarray(jax.grad(f)(jnp.asarray(x)))
    v = rng.normal(size=x.shape) * np.asarray(a.mask)[:, None, None]
    eps = 1e-6
    fd = (f(x + eps * v) - f(x - eps * v)) / (2 * eps)
    assert float(np.sum(g * v)) == pytest.approx(float(fd), rel=1e-6)
    # Null laterals are collapsed to a point (zero speed everywhere): gradients stay finite.
    assert np.all(np.isfinite(g))
    zero = jnp.zeros_like(a.laterals)
    assert np.all(np.isfinite(np.asarray(jax.grad(f)(zero))))


def test_float32_respected():
    rng = np.random.default_rng(5)
    t = rs.batch([random_root(rng, n_laterals=1)], dtype=np.float32)
    assert t.main.dtype == np.float32
    assert rs.to_srvf(t).q.dtype == np.float32
