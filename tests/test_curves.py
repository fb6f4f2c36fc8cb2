"""Curves: resampling, SRVF, inverse SRVF, rotation — against plain numpy references."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import rotation_matrix, smooth_curve

from rootshape_jax._curves import (
    curve_length,
    interpolate_at_fraction,
    l2_norm_squared,
    resample_curve,
    srvf,
    srvf_to_curve,
)
from rootshape_jax._rotation import axis_angle_rotation, optimal_rotation, rotate
from rootshape_jax._tree import resample_polyline


def _analytic(T, d, dtype=np.float64):
    t = np.linspace(0, 1, 4000)
    pts = np.stack([np.cos(2.5 * t), np.sin(2.5 * t) + 0.3 * t**2] + ([0.4 * t**3] if d == 3 else []), 1)
    return resample_polyline(pts, T).astype(dtype)


def _numpy_srvf(beta):
    """Reference: the documented discretisation, written with plain loops."""
    T, d = beta.shape
    h = 1.0 / (T - 1)
    u = [(beta[i + 1] - beta[i]) / h for i in range(T - 1)]
    q = np.zeros_like(beta)
    for i in range(T):
        segs = [k for k in (i - 1, i) if 0 <= k < T - 1]
        speed = np.mean([np.linalg.norm(u[k]) for k in segs])
        units = [u[k] / np.linalg.norm(u[k]) for k in segs if np.linalg.norm(u[k]) > 0]
        if speed == 0 or not units:
            continue
        tang = sum(units)
        if len(units) == 2 and np.linalg.norm(tang) < 2 * np.sin(np.radians(0.5)):
            tang = units[1]  # a cusp (turn > 179°): the outgoing direction
        q[i] = np.sqrt(speed) * tang / np.linalg.norm(tang)
    return q


@pytest.mark.parametrize("d,T", list(itertools.product([2, 3], [20, 100])))
def test_srvf_matches_numpy_reference(d, T):
    beta = _analytic(T, d)
    np.testing.assert_allclose(np.asarray(srvf(beta)), _numpy_srvf(beta), rtol=1e-12, atol=1e-12)


def _stepping_back(d):
    """A pixel tracing that steps back along its row (exact 180° turns) and turns by 179.5°."""
    pts = [[1849.0, 760.0], [1848.0, 760.0], [1853.0, 760.0], [1858.0, 762.0], [1861.0, 762.0], [1859.0, 762.0]]
    pts += [[1864.0, 762.0 + np.tan(np.radians(0.5)) * 5], [1870.0, 770.0]]
    pts = np.array(pts)
    return np.c_[pts, np.linspace(0.0, 3.0, len(pts))] if d == 3 else pts


@pytest.mark.parametrize("d", [2, 3])
def test_srvf_at_cusps_is_the_same_wherever_the_curve_lies(d):
    beta = _stepping_back(d)
    q = np.asarray(srvf(beta))
    np.testing.assert_allclose(q, _numpy_srvf(beta), rtol=1e-12, atol=1e-12)
    # A 2D exact reversal: the node goes the way the curve leaves (+x), not a rounding-noise sign.
    if d == 2:
        assert q[1, 0] > 0 and q[1, 1] == 0 and q[5, 0] > 0
    rng = np.random.default_rng(d)
    for shift in (-beta[0], np.full(d, 1e5), rng.uniform(-1e3, 1e3, d)):
        np.testing.assert_allclose(np.asarray(srvf(beta + shift)), q, atol=1e-9)
    R = rotation_matrix(rng, d)
    np.testing.assert_allclose(np.asarray(srvf((beta - beta[0]) @ R.T)), q @ R.T, atol=1e-9)
    # Float32 (coordinates rounded by ~1e-4 px) keeps the directions.
    q32 = np.asarray(srvf(beta.astype(np.float32)), np.float64)
    np.testing.assert_allclose(q32, q, atol=1e-3 * np.abs(q).max())
    # The length identity holds at cusps too, and gradients stay finite there.
    assert float(l2_norm_squared(srvf(beta))) == pytest.approx(float(curve_length(beta)), rel=1e-12)
    w = rng.normal(size=beta.shape)
    g = np.asarray(jax.grad(lambda b: jnp.sum(srvf(b) * w))(jnp.asarray(beta)))
    assert np.all(np.isfinite(g))


@pytest.mark.parametrize("d,T", list(itertools.product([2, 3], [30, 100, 400])))
def test_norm_squared_is_length(d, T):
    rng = np.random.default_rng(T + d)
    beta = smooth_curve(rng, d=d, length=3.7, n=T)
    # Also a non-uniform parameterisation: the identity must hold for any sampling.
    beta_nonuniform = beta[np.unique(np.round(np.linspace(0, 1, T) ** 1.7 * (T - 1)).astype(int))]
    for b in (beta, beta_nonuniform):
        length = np.sum(np.linalg.norm(np.diff(b, axis=0), axis=1))
        assert abs(float(l2_norm_squared(srvf(b))) - length) <= 1e-6 * length
        assert abs(float(curve_length(b)) - length) <= 1e-12 * length


@pytest.mark.parametrize("d", [2, 3])
def test_round_trip_converges_second_order(d):
    errors = []
    for T in (50, 100, 200, 400):
        beta = _analytic(T, d)
        back = np.asarray(srvf_to_curve(srvf(beta), beta[0]))
        errors.append(np.abs(back - beta).max())
    errors = np.array(errors)
    assert errors[-1] < 5e-5
    # Halving h divides the error by about 4 (second-order discretisation).
    assert np.all(errors[:-1] / errors[1:] > 3.0)


def test_round_trip_exact_on_straight_uniform_lines():
    beta = np.stack([np.linspace(0, 2, 11), np.linspace(1, -3, 11)], 1)
    np.testing.assert_allclose(np.asarray(srvf_to_curve(srvf(beta), beta[0])), beta, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_respected(dtype):
    beta = _analytic(30, 2, dtype)
    assert srvf(beta).dtype == dtype
    assert srvf_to_curve(srvf(beta)).dtype == dtype
    assert resample_curve(beta, 17).dtype == dtype


def test_zero_speed_segments_give_zero_srvf_and_finite_gradients():
    beta = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [2.0, 1.0]])
    q = np.asarray(srvf(beta))
    assert np.all(np.isfinite(q))
    assert np.all(q[3] == 0)  # both adjacent segments have zero length
    zero = jnp.zeros((7, 3))
    for f in (
        lambda b: l2_norm_squared(srvf(b)),
        lambda b: jnp.sum(srvf_to_curve(srvf(b)) ** 2),
        lambda b: curve_length(b),
    ):
        for x in (zero, jnp.asarray(np.c_[beta, np.zeros(6)])):
            g = jax.grad(f)(x)
            assert np.all(np.isfinite(np.asarray(g)))


def test_srvf_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    beta = smooth_curve(rng, n=12, d=2, length=2.0)
    w = rng.normal(size=beta.shape)
    f = lambda b: jnp.sum(srvf(b) * w)  # noqa: E731
    g = np.asarray(jax.grad(f)(jnp.asarray(beta)))
    eps = 1e-6
    fd = np.zeros_like(beta)
    for i, j in itertools.product(range(beta.shape[0]), range(2)):
        e = np.zeros_like(beta)
        e[i, j] = eps
        fd[i, j] = (f(beta + e) - f(beta - e)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("d", [2, 3])
def test_resample_matches_numpy_and_is_uniform(d):
    rng = np.random.default_rng(d)
    pts = smooth_curve(rng, n=37, d=d, length=5.0)
    pts = np.concatenate([pts[:5], pts[4:5], pts[5:]])  # a repeated point
    ours = np.asarray(resample_curve(pts, 50))
    np.testing.assert_allclose(ours, resample_polyline(pts, 50), atol=1e-12)
    # On a straight line sampled irregularly, arc-length resampling gives equal spacing.
    line = np.outer(np.sort(np.r_[0, rng.uniform(0, 1, 20), 1]), np.arange(1, d + 1))
    seg = np.linalg.norm(np.diff(np.asarray(resample_curve(line, 31)), axis=0), axis=1)
    np.testing.assert_allclose(seg, seg.mean(), rtol=1e-10)


def test_interpolate_at_fraction_endpoints_and_midpoint():
    beta = jnp.asarray(np.stack([np.linspace(0, 4, 9), np.zeros(9)], 1))
    np.testing.assert_allclose(interpolate_at_fraction(beta, jnp.array([0.0, 0.5, 1.0])), [[0, 0], [2, 0], [4, 0]])


@pytest.mark.parametrize("d,weighted", list(itertools.product([2, 3], [False, True])))
def test_optimal_rotation_recovers_known_rotation(d, weighted):
    rng = np.random.default_rng(10 + d)
    A = np.stack([np.asarray(srvf(smooth_curve(rng, d=d, n=40))) for _ in range(4)])
    R = rotation_matrix(rng, d)
    B = np.asarray(rotate(A, R.T))  # B = Rᵀ A, so the optimal O is R
    w = rng.uniform(0.1, 2.0, size=4) if weighted else None
    O = np.asarray(optimal_rotation(A, B, w))
    np.testing.assert_allclose(O, R, atol=1e-10)
    assert abs(np.linalg.det(O) - 1) < 1e-12


def test_optimal_rotation_refuses_nan():
    import equinox as eqx

    import rootshape_jax as rs

    rng = np.random.default_rng(2)
    A, B = rng.normal(size=(2, 10, 3))
    for bad_a, bad_b, w in ((A.copy(), B, None), (A, B.copy(), None), (A[None], B[None], np.array([np.nan]))):
        if w is None:
            (bad_a if bad_a is not A else bad_b)[3, 1] = np.nan
        with pytest.raises(rs.InputError, match="NaN or inf"):
            optimal_rotation(bad_a, bad_b, w)
    bad = A.copy()
    bad[0, 0] = np.inf
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):  # under jit, when it runs
        jax.block_until_ready(eqx.filter_jit(optimal_rotation)(bad, B))
    np.testing.assert_allclose(np.asarray(jax.jit(optimal_rotation)(A, B)), np.asarray(optimal_rotation(A, B)))


def test_axis_angle_rotation_is_scipys_rotation_vector():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(-np.pi, np.pi)
        got = np.asarray(axis_angle_rotation(axis, angle))
        np.testing.assert_allclose(got, Rotation.from_rotvec(angle * axis).as_matrix(), atol=1e-12)
        assert got.dtype == np.float64
    # A zero axis is no rotation (the engine's spin about a main root of zero length).
    np.testing.assert_array_equal(np.asarray(axis_angle_rotation(np.zeros(3), 1.0)), np.eye(3))


def test_optimal_rotation_never_reflects_and_is_optimal():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 20, 3))
    B = A.copy()
    B[..., 0] *= -1  # a mirror image: the best proper rotation is not the reflection
    O = np.asarray(optimal_rotation(A, B))
    assert abs(np.linalg.det(O) - 1) < 1e-12
    best = np.sum(A * (B @ O.T))
    for _ in range(200):  # brute force over random rotations never beats it
        R = rotation_matrix(rng, 3)
        assert np.sum(A * (B @ R.T)) <= best + 1e-9


@pytest.mark.parametrize("case", ["random", "mirror", "zero"])
def test_optimal_rotation_2d_closed_form_equals_svd_kabsch(case):
    # d = 2 uses a closed form; the reference is plain-numpy Kabsch (SVD + determinant
    # correction) and a brute-force search over angles.
    rng = np.random.default_rng(17)
    A = rng.normal(size=(3, 25, 2))
    B = rng.normal(size=(3, 25, 2))
    if case == "mirror":
        B = A * np.array([-1.0, 1.0])
    if case == "zero":
        B = np.zeros_like(A)
    w = rng.uniform(0.5, 2.0, size=3)
    O = np.asarray(optimal_rotation(A, B, w))
    if case == "zero":
        np.testing.assert_array_equal(O, np.eye(2))
        # Tiny but non-zero inputs still give the rotation, also in float32 (no underflow).
        R = rotation_matrix(rng, 2)
        A32 = (1e-12 * A).astype(np.float32)
        O32 = np.asarray(optimal_rotation(A32, (A32 @ R).astype(np.float32)))
        np.testing.assert_allclose(O32, R, atol=1e-5)
        return
    tw = np.full(25, 1 / 24)
    tw[[0, -1]] /= 2
    K = np.einsum("k,t,kti,ktj->ij", w, tw, B, A)
    U, _, Vt = np.linalg.svd(K)
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    np.testing.assert_allclose(O, Vt.T @ D @ U.T, atol=1e-12)
    assert abs(np.linalg.det(O) - 1) < 1e-12
    score = lambda R: np.sum(w[:, None, None] * tw[:, None] * A * (B @ R.T))  # noqa: E731
    angles = np.linspace(0, 2 * np.pi, 3601)
    rotations = [np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) for t in angles]
    assert max(score(R) for R in rotations) <= score(O) + 1e-12


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match="T >= 2"):
        srvf(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="same shape"):
        optimal_rotation(np.zeros((5, 2)), np.zeros((5, 3)))
