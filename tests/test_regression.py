"""Trait regression: M = B P⁺, synthesis from traits, and the trait report."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import linear_srvf_population, random_root, tree_allclose

import rootshape_jax as rs
from rootshape_jax import l2_norm_squared
from rootshape_jax._mean import karcher_mean
from rootshape_jax._pca import tangent_pca
from rootshape_jax._regression import PAPER_TRAITS, TraitRegression

# The synthesis maths is checked on values far outside the training roots on purpose; the
# warning about that has its own test (the last one), which records or raises it itself.
pytestmark = pytest.mark.filterwarnings("ignore::rootshape_jax.ExtrapolationWarning")

T = 30


@pytest.fixture(scope="module")
def linear():
    rng = np.random.default_rng(31)
    base = rs.to_srvf(rs.batch(random_root(rng, n_laterals=2), n_points=T, max_laterals=4))
    coef = np.stack([rng.normal(0, 0.5, 8), rng.normal(0, 0.3, 8)], axis=1)
    x = linear_srvf_population(base, coef)
    m = karcher_mean(x, max_steps=20)
    # The regression's own accuracy, also outside the training range: without the plausibility
    # limits that tangent_pca puts on synthesised laterals by default (tested in test_pca).
    pc = tangent_pca(m, min_lateral_length=0.02 * float(l2_norm_squared(m.fitted.q0)), max_lateral_length=float("inf"))
    return base, coef, pc


def test_recovers_a_known_linear_relation(linear):
    base, coef, pc = linear
    reg = TraitRegression.fit(pc, traits=(), covariates=coef, covariate_names=["a", "b"])
    assert reg.names == ("a", "b") and reg.n_components == 2
    # New covariates, inside and outside the training range: the synthesised SRVF tree is
    # the true one, base + a Δ1 + b Δ2.
    new = np.array([[0.3, -0.2], [-0.8, 0.4], [1.5, 0.0]])
    got = reg.synthesize(new, srvf=True)
    want = linear_srvf_population(base, new)
    np.testing.assert_allclose(got.q0, want.q0, atol=1e-9)
    np.testing.assert_allclose(got.q, want.q, atol=1e-9)
    real = np.asarray(want.mask)
    np.testing.assert_allclose(np.asarray(got.s)[real], np.asarray(want.s)[real], atol=1e-9)


def test_matrix_is_the_least_squares_solution(linear):
    _, coef, pc = linear
    rng = np.random.default_rng(0)
    cov = np.concatenate([coef, rng.normal(size=(8, 1))], axis=1)
    reg = TraitRegression.fit(pc, traits=(), covariates=cov)
    # Reference: each coefficient regressed on [z, 1] (standardised values) by numpy's least
    # squares; the fitted values equal those of the regression on [p, 1].
    mu, sd = cov.mean(axis=0), cov.std(axis=0)
    Z = np.concatenate([(cov - mu) / sd, np.ones((8, 1))], axis=1)
    X = np.concatenate([cov, np.ones((8, 1))], axis=1)
    B = np.asarray(pc.scores[:, : pc.n_components])
    ref_z, *_ = np.linalg.lstsq(Z, B, rcond=None)
    ref, *_ = np.linalg.lstsq(X, B, rcond=None)
    np.testing.assert_allclose(np.asarray(reg.matrix), ref_z.T, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(reg.trait_mean, mu, rtol=1e-12)
    np.testing.assert_allclose(reg.trait_scale, sd, rtol=1e-12)
    np.testing.assert_allclose(reg.coefficients(cov), X @ ref, rtol=1e-8, atol=1e-10)


@pytest.fixture(scope="module")
def linear3d():
    rng = np.random.default_rng(32)
    base = rs.to_srvf(rs.batch(random_root(rng, n_laterals=3, d=3), n_points=T, max_laterals=4))
    coef = np.stack([rng.normal(0, 0.5, 8), rng.normal(0, 0.3, 8)], axis=1)
    pc = tangent_pca(karcher_mean(linear_srvf_population(base, coef), max_steps=20))
    return base, coef, pc


@pytest.mark.parametrize("population", ["linear", "linear3d"])
def test_synthesis_equals_the_pca_reconstruction(population, request):
    # The precomputed affine map and the stacked curve integration against the slow path:
    # coefficients → reconstruct (PCA basis, per-curve to_curves); d = 2 and 3.
    from rootshape_jax._pca import reconstruct

    _, coef, pc = request.getfixturevalue(population)
    reg = TraitRegression.fit(pc, traits=(), covariates=coef)
    new = np.array([[0.3, -0.2], [-0.8, 0.4], [1.5, 0.0], [-3.0, 2.0]])
    got = reg.synthesize(new)
    want = reconstruct(pc, reg.coefficients(new))
    assert tree_allclose(got, want, rtol=1e-10, atol=1e-12)
    assert tree_allclose(
        reg.synthesize(new, srvf=True), reconstruct(pc, reg.coefficients(new), srvf=True), rtol=1e-10, atol=1e-12
    )
    assert tree_allclose(reg.synthesize(new[1]), jax.tree.map(lambda x: x[1], got), rtol=1e-12, atol=1e-14)


def test_large_sweeps_are_chunked_and_keep_their_batch_shape(linear):
    # Above _SWEEP_CHUNK roots the synthesis runs in chunks (lax.map, with a remainder): every
    # root must equal its own single-root synthesis, for a flat and a (3, 50) batch shape.
    from rootshape_jax._regression import _SWEEP_CHUNK

    _, coef, pc = linear
    reg = TraitRegression.fit(pc, traits=(), covariates=coef)
    n = 2 * _SWEEP_CHUNK + 22  # not a multiple of the chunk
    new = np.random.default_rng(8).normal(0, 0.6, size=(n, 2))
    got = reg.synthesize(new)
    assert got.main.shape[0] == n
    for i in (0, _SWEEP_CHUNK - 1, _SWEEP_CHUNK, n - 1):
        one = reg.synthesize(new[i])
        assert tree_allclose(jax.tree.map(lambda x: x[i], got), one, rtol=1e-12, atol=1e-14)
    grid = reg.synthesize(new[:150].reshape(3, 50, 2), srvf=True)
    flat = reg.synthesize(new[:150], srvf=True)
    assert grid.q.shape[:2] == (3, 50)
    regrid = jax.tree.map(lambda x: x.reshape((150,) + x.shape[2:]), grid)
    assert tree_allclose(regrid, flat, rtol=1e-12, atol=1e-14)


def test_constant_trait_is_ignored_and_float32_keeps_its_digits(linear):
    # A trait constant up to rounding (main-root length after scale normalisation) is collinear
    # with the intercept: P⁺ gives it huge cancelling coefficients, which used to make a float32
    # synthesis wrong by the size of the answer. It is now ignored, with a warning.
    _, coef, pc = linear
    rng = np.random.default_rng(5)
    const = 1.0 + 1e-8 * rng.normal(size=(8, 1))
    with pytest.warns(UserWarning, match="do not vary"):
        reg = TraitRegression.fit(
            pc, traits=(), covariates=np.concatenate([const, coef], axis=1), covariate_names=["length", "a", "b"]
        )
    assert reg.ignored == ("length",)
    plain = TraitRegression.fit(pc, traits=(), covariates=coef)
    new = np.array([[1.0, 0.3, -0.2], [1.0, -0.8, 0.4]])
    np.testing.assert_allclose(reg.coefficients(new), plain.coefficients(new[:, 1:]), atol=1e-12)
    moved = new.copy()
    moved[:, 0] = 2.0
    assert tree_allclose(reg.synthesize(moved), reg.synthesize(new), rtol=0, atol=0)
    # float32: the same PCA cast down; the synthesis agrees with float64 to float32 precision.
    pc32 = jax.tree.map(lambda x: x.astype(np.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, pc)
    with pytest.warns(UserWarning, match="do not vary"):
        reg32 = TraitRegression.fit(pc32, traits=(), covariates=np.concatenate([const, coef], axis=1))
    got = reg32.synthesize(new)
    want = reg.synthesize(new)
    assert got.main.dtype == np.float32
    np.testing.assert_allclose(got.main, want.main, atol=1e-5)
    np.testing.assert_allclose(got.laterals, want.laterals, atol=1e-5)
    np.testing.assert_allclose(got.attach, want.attach, atol=1e-5)


def test_synthesize_does_not_retrace(linear):
    from rootshape_jax import _regression

    _, coef, pc = linear
    reg = TraitRegression.fit(pc, traits=(), covariates=coef)
    reg.synthesize(coef[0])
    before = _regression._synthesize._cache_size()
    for row in coef[1:4]:
        reg.synthesize(row)
    assert _regression._synthesize._cache_size() == before


@pytest.fixture(scope="module")
def roots_population():
    rng = np.random.default_rng(41)
    roots = [
        random_root(rng, n_laterals=int(k), main_length=float(L))
        for k, L in zip([3, 2, 3, 3, 2, 3, 2, 3], rng.uniform(0.7, 1.3, 8))
    ]
    trees = rs.batch(roots, n_points=T, max_laterals=6)
    return trees


def test_paper_traits_synthesis_and_report(roots_population):
    trees = roots_population
    # 5 training roots with K = 6, T = 30: the shapes of test_mean's population (shared
    # compiled programs when the suite runs in one process).
    train = jax.tree.map(lambda x: x[:5], trees)
    test = jax.tree.map(lambda x: x[5:], trees)
    pc = tangent_pca(karcher_mean(train, max_steps=15, throw=False))
    reg = TraitRegression.fit(pc, train)
    assert reg.names == PAPER_TRAITS
    measured = np.array([[r[k] for k in PAPER_TRAITS] for r in rs_traits(train)])
    one = reg.synthesize(measured[0])
    assert one.main.shape == (T, 2) and one.laterals.shape == (6, T, 2)
    many = reg.synthesize(measured)
    for leaf in (many.main, many.laterals, many.attach):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # On the training roots the fit reproduces the main-root length closely (it is nearly a
    # linear function of the main SRVF's norm over this small range).
    rep_train = reg.report(train)
    assert rep_train["main_length"]["mean_relative_error"] < 0.1
    rep = reg.report(test)
    for name in PAPER_TRAITS:
        assert set(rep[name]) == {"r2", "mean_relative_error", "requested", "synthesised"}
        assert rep[name]["requested"].shape == (3,)
        assert np.all(np.isfinite(rep[name]["synthesised"]))
    np.testing.assert_allclose(rep["main_length"]["requested"], [r["main_length"] for r in rs_traits(test)])


def rs_traits(trees):
    return rs_traits_fn()(rs.to_roots(trees))


def rs_traits_fn():
    from rootshape_jax._traits import traits

    return traits


def test_bad_input(linear, roots_population):
    _, coef, pc = linear
    with pytest.raises(ValueError, match="training roots"):
        TraitRegression.fit(pc)
    with pytest.raises(ValueError, match="covariates"):
        TraitRegression.fit(pc, traits=(), covariates=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="at least one"):
        TraitRegression.fit(pc, traits=())
    reg = TraitRegression.fit(pc, traits=(), covariates=coef)
    with pytest.raises(ValueError, match="shape"):
        reg.synthesize(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        reg.synthesize([np.nan, 0.0])


def test_requests_far_outside_the_training_roots_are_named(linear):
    _, coef, pc = linear
    reg = TraitRegression.fit(pc, traits=(), covariates=coef)
    mean, sd = coef.mean(axis=0), coef.std(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", rs.ExtrapolationWarning)
        reg.synthesize(mean + 2.5 * sd)  # inside 3 SD: nothing to say
        reg.synthesize(coef)  # the training values themselves
    far = np.array(mean)
    far[1] = mean[1] + 22 * sd[1]
    with pytest.warns(rs.ExtrapolationWarning, match=r"covariate_1 = ") as rec:
        reg.synthesize(far)
    assert "22.0 SD" in str(rec[0].message) and len(rec) == 1
