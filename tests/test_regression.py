"""Trait regression: M = B P⁺, synthesis from traits, and the trait report."""

import jax
import numpy as np
import pytest

import rootshape_jax as rs
from rootshape_jax._mean import karcher_mean
from rootshape_jax._pca import tangent_pca
from rootshape_jax._regression import PAPER_TRAITS, TraitRegression

from helpers import linear_srvf_population, random_root

T = 30


@pytest.fixture(scope="module")
def linear():
    rng = np.random.default_rng(31)
    base = rs.to_srvf(rs.batch(random_root(rng, n_laterals=2), n_points=T, max_laterals=4))
    coef = np.stack([rng.normal(0, 0.5, 8), rng.normal(0, 0.3, 8)], axis=1)
    x = linear_srvf_population(base, coef)
    pc = tangent_pca(karcher_mean(x, max_steps=20))
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
    # Reference: each coefficient regressed on [p, 1] by numpy's least squares.
    X = np.concatenate([cov, np.ones((8, 1))], axis=1)
    B = np.asarray(pc.scores[:, : pc.n_components])
    ref, *_ = np.linalg.lstsq(X, B, rcond=None)
    np.testing.assert_allclose(np.asarray(reg.matrix), ref.T, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(reg.coefficients(cov), X @ ref, rtol=1e-8, atol=1e-10)


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
