"""Elastic curve distance: alternating rotation / DP warp on open curves."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import rotation_matrix, smooth_curve

import rootshape_jax as rs
from rootshape_jax._curves import resample_curve, srvf
from rootshape_jax._elastic import CurveRegistration, _register, elastic_curve_distance
from rootshape_jax._errors import InvalidRootError
from rootshape_jax._rotation import optimal_rotation
from rootshape_jax._warp import dp_warp_and_energy, warp_energy, warp_samples


def _at_fraction(curve, s):
    """Points of a dense polyline at arc-length fractions s."""
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    arc /= arc[-1]
    return np.stack([np.interp(s, arc, curve[:, k]) for k in range(curve.shape[1])], axis=1)


def _phi(x):
    return (np.exp(1.2 * x) - 1) / (np.exp(1.2) - 1)


def _phi_inv(y):
    return np.log1p(y * (np.exp(1.2) - 1)) / 1.2


def _angle(O):
    return np.arctan2(O[1, 0], O[0, 0])


def test_known_rotation_warp_and_translation_are_recovered():
    # β2(t) = R β(φ(t)) + c: the registration should find O ≈ Rᵀ and γ ≈ φ⁻¹, with an
    # energy comparable to that of the true (O, γ) sampled on the grid (not 0).
    T = 60
    rng = np.random.default_rng(0)
    dense = smooth_curve(rng, n=400, bend=1.5)
    R = rotation_matrix(rng, 2)
    t = np.linspace(0, 1, T)
    beta1 = _at_fraction(dense, t)
    beta2 = _at_fraction(dense, _phi(t)) @ R.T + np.array([3.0, -2.0])
    q1, q2 = srvf(beta1), srvf(beta2)
    O, gamma, energy, n_it = _register(q1, q2, rotation=True, neighbourhood=7, max_iterations=10, rtol=1e-6)
    # The grid optimum at the true rotation (O = Rᵀ, so q2 Oᵀ = q2 R) ...
    _, grid_optimum = dp_warp_and_energy(q1, q2 @ R)
    assert float(energy) <= float(grid_optimum) * (1 + 1e-9)
    # ... is a few times the energy of the true warp sampled on the grid (docs/design.md §4: 2–4×).
    true_energy = float(warp_energy(q1, q2 @ R, _phi_inv(t)))
    assert 0 < float(energy) <= 5 * true_energy
    assert abs(_angle(np.asarray(O)) - _angle(R.T)) < 0.02
    assert np.max(np.abs(np.asarray(gamma) - _phi_inv(t))) < 3.0 / (T - 1)
    assert 2 <= int(n_it) <= 11


def test_distance_is_invariant_to_rotation_translation_and_parameterisation():
    rng = np.random.default_rng(1)
    dense = smooth_curve(rng, n=400, bend=1.5)
    other = smooth_curve(rng, n=400, bend=1.5)
    t = np.linspace(0, 1, 150)
    beta = _at_fraction(dense, t)
    R = rotation_matrix(rng, 2)
    moved = _at_fraction(dense, _phi(t)) @ R.T + np.array([-1.0, 5.0])
    same = float(elastic_curve_distance(beta, moved, n_samples=40).distance)
    different = float(elastic_curve_distance(beta, _at_fraction(other, t), n_samples=40).distance)
    assert different > 0.2
    assert same < 0.03 * different


def test_reported_energy_is_the_warp_energy_of_the_returned_registration():
    rng = np.random.default_rng(2)
    b1, b2 = smooth_curve(rng, n=50, bend=2.0), smooth_curve(rng, n=70, bend=2.0)
    res = elastic_curve_distance(b1, b2, n_samples=40)
    assert isinstance(res, CurveRegistration)
    q1 = srvf(resample_curve(b1, 40))
    q2 = srvf(resample_curve(b2, 40))
    O = np.asarray(res.rotation)
    np.testing.assert_allclose(O @ O.T, np.eye(2), atol=1e-12)
    assert np.linalg.det(O) == pytest.approx(1.0)
    expected = float(warp_energy(q1, q2 @ O.T, res.gamma))
    assert float(res.energy) == pytest.approx(expected, rel=1e-12)
    assert float(res.distance) == pytest.approx(np.sqrt(expected), rel=1e-12)
    assert res.gamma.shape == (40,)


def test_rotation_step_is_exact_for_a_fixed_warp():
    # Kabsch on the quadrature samples beats every angle of a fine grid for the same γ.
    rng = np.random.default_rng(3)
    T = 30
    q1 = srvf(smooth_curve(rng, n=T, bend=2.0))
    q2 = srvf(smooth_curve(rng, n=T, bend=2.0))
    g = np.linspace(0, 1, T) ** 1.3
    A, B, w = warp_samples(q1, q2, g)
    O = optimal_rotation(A, B, w)
    best = float(warp_energy(q1, q2 @ O.T, g))
    for th in np.linspace(-np.pi, np.pi, 721):
        Rt = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        assert best <= float(warp_energy(q1, q2 @ Rt.T, g)) + 1e-12


def test_alternation_is_monotone_and_rotation_helps():
    rng = np.random.default_rng(4)
    b1, b2 = smooth_curve(rng, n=60, bend=2.5), smooth_curve(rng, n=60, bend=2.5)
    run = functools.partial(elastic_curve_distance, b1, b2, n_samples=40, rtol=0.0)
    energies = [float(run(max_iterations=k).energy) for k in (1, 2, 3, 5, 8)]
    assert all(b <= a + 1e-12 for a, b in zip(energies, energies[1:]))
    no_rotation = float(run(rotation=False).energy)
    assert energies[-1] <= no_rotation + 1e-12
    assert int(run(rotation=False).n_iterations) == 1


def test_scale_option():
    rng = np.random.default_rng(5)
    b = smooth_curve(rng, n=60, bend=2.0)
    big = 3.0 * b + 1.0
    assert float(elastic_curve_distance(b, big, scale=True, n_samples=40).distance) < 1e-6
    # Without scale normalisation the size difference counts: ||q||² is the length.
    assert float(elastic_curve_distance(b, big, n_samples=40).distance) > 0.5
    other = smooth_curve(rng, n=60, bend=2.0)
    res = elastic_curve_distance(b, other, scale=True, n_samples=40)
    assert 0 < float(res.distance) < 2  # a chord of the unit sphere


def test_vmap_equals_a_python_loop():
    rng = np.random.default_rng(6)
    b1 = np.stack([smooth_curve(rng, n=45, bend=2.0) for _ in range(4)])
    b2 = np.stack([smooth_curve(rng, n=45, bend=2.0) for _ in range(4)])
    f = functools.partial(elastic_curve_distance, n_samples=40)
    batched = jax.jit(jax.vmap(f))(b1, b2)
    for i in range(4):
        single = f(b1[i], b2[i])
        assert float(batched.energy[i]) == pytest.approx(float(single.energy), rel=1e-12)
        for field in ("gamma", "rotation"):
            got, want = getattr(batched, field)[i], getattr(single, field)
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-12)
        assert int(batched.n_iterations[i]) == int(single.n_iterations)


def test_three_dimensional_and_float32_curves():
    rng = np.random.default_rng(7)
    b1, b2 = smooth_curve(rng, n=40, d=3, bend=2.0), smooth_curve(rng, n=40, d=3, bend=2.0)
    R = rotation_matrix(rng, 3)
    res = elastic_curve_distance(b1, b2, n_samples=40)
    assert res.rotation.shape == (3, 3)
    moved = elastic_curve_distance(b1, b2 @ R.T, n_samples=40)
    # Rotating one input changes nothing but the rotation found (up to the search's tolerance).
    assert float(moved.energy) == pytest.approx(float(res.energy), rel=1e-3)
    res32 = elastic_curve_distance(b1.astype(np.float32), b2.astype(np.float32), n_samples=40)
    assert res32.energy.dtype == jnp.float32 and res32.gamma.dtype == jnp.float32
    assert float(res32.energy) == pytest.approx(float(res.energy), rel=1e-3)


def test_gradient_matches_finite_differences():
    rng = np.random.default_rng(8)
    b1, b2 = smooth_curve(rng, n=30, bend=2.0), smooth_curve(rng, n=30, bend=2.0)
    f = jax.jit(lambda x: elastic_curve_distance(x, b2, n_samples=40).distance)
    grad = np.asarray(jax.grad(f)(jnp.asarray(b1)))
    assert np.all(np.isfinite(grad)) and np.any(grad != 0)
    direction = rng.normal(size=b1.shape)
    eps = 1e-6
    fd = (float(f(b1 + eps * direction)) - float(f(b1 - eps * direction))) / (2 * eps)
    assert np.sum(grad * direction) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_clear_errors():
    b = np.zeros((10, 2))
    b[:, 0] = np.arange(10)
    with pytest.raises(InvalidRootError, match="same dimension"):
        elastic_curve_distance(b, np.zeros((10, 3)))
    with pytest.raises(InvalidRootError, match="n_points"):
        elastic_curve_distance(b[:, 0], b[:, 0])
    with pytest.raises(InvalidRootError, match="2D or 3D"):
        elastic_curve_distance(np.zeros((10, 4)), np.zeros((10, 4)))
    with pytest.raises(ValueError, match="n_samples"):
        elastic_curve_distance(b, b, n_samples=1)
    with pytest.raises(ValueError, match="max_iterations"):
        elastic_curve_distance(b, b, max_iterations=0)
    with pytest.raises(ValueError, match="neighbourhood"):
        elastic_curve_distance(b, b, neighbourhood=0)
    bad = b.copy()
    bad[2, 1] = np.inf
    with pytest.raises(InvalidRootError, match="beta1 holds NaN or inf"):  # at the call
        elastic_curve_distance(bad, b)
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):  # under jit, when it runs
        eqx.filter_jit(lambda x: elastic_curve_distance(x, b).distance)(bad)


def test_batched_curve_distances_equal_vmap_and_any_worker_count():
    # The public batched call (chunks on worker threads) gives what jax.vmap of the single-pair
    # call gives, whatever the number of threads; the padding of the last chunk is dropped.
    rng = np.random.default_rng(3)
    A = np.cumsum(rng.normal(size=(9, 25, 2)), axis=1)
    B = np.cumsum(rng.normal(size=(9, 31, 2)), axis=1)
    ref = jax.vmap(lambda a, b: rs.elastic_curve_distance(a, b, n_samples=20))(jnp.asarray(A), jnp.asarray(B))
    for workers in (1, 2, 4):
        got = rs.elastic_curve_distances(A, B, n_samples=20, workers=workers)
        assert got.distance.shape == (9,)
        np.testing.assert_allclose(np.asarray(got.distance), np.asarray(ref.distance), rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(np.asarray(got.gamma), np.asarray(ref.gamma))


def test_batched_curve_distances_reject_mismatched_batches():
    with pytest.raises(ValueError, match="same N"):
        rs.elastic_curve_distances(np.zeros((3, 10, 2)), np.zeros((4, 10, 2)))
    with pytest.raises(ValueError, match="workers"):
        rs.elastic_curve_distances(np.ones((2, 10, 2)), np.ones((2, 10, 2)), workers=0)
