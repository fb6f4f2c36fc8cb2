"""Tangent PCA, modes, projection and random synthesis."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import linear_srvf_population, random_root, record_bars, transformed_copies

import rootshape_jax as rs
from rootshape_jax._mean import karcher_mean
from rootshape_jax._pca import TangentPCA, modes, project, reconstruct, sample, tangent_pca

T = 30


@pytest.fixture(scope="module")
def two_mode():
    """Roots x = base + a Δ1 + b Δ2 in SRVF space (lateral lengths, attachment positions),
    with a, b of very different spreads: exactly two modes of variation."""
    rng = np.random.default_rng(21)
    base = rs.to_srvf(rs.batch(random_root(rng, n_laterals=2), n_points=T, max_laterals=4))
    coef = np.stack([rng.normal(0, 0.6, 8), rng.normal(0, 0.25, 8)], axis=1)
    coef -= coef.mean(axis=0)
    x = linear_srvf_population(base, coef)
    mean = karcher_mean(x, max_steps=20)
    return base, coef, x, mean, tangent_pca(mean)


def _numpy_pca(mean, registered, weights):
    """Slow reference: explicit whitened tangent vectors and the covariance's eigh."""
    mu = jax.tree.map(np.asarray, mean)
    reg = jax.tree.map(np.asarray, registered)
    n = reg.q0.shape[0]
    tw = np.full(T, 1.0 / (T - 1))
    tw[[0, -1]] /= 2
    rows = []
    for i in range(n):
        parts = [np.sqrt(float(weights.main) * tw)[:, None] * (reg.q0[i] - mu.q0)]
        for k in range(mu.q.shape[0]):
            parts.append(np.sqrt(float(weights.lateral) * tw)[:, None] * (reg.q[i, k] - mu.q[k]))
        parts.append(np.sqrt(float(weights.position)) * (reg.s[i] - mu.s))
        rows.append(np.concatenate([p.ravel() for p in parts]))
    V = np.array(rows)
    cov = V.T @ V / (n - 1)
    vals, vecs = np.linalg.eigh(cov)
    return V, vals[::-1], vecs[:, ::-1]


def test_pca_matches_numpy_reference(two_mode):
    _, _, _, mean, pc = two_mode
    assert isinstance(pc, TangentPCA)
    V, vals, vecs = _numpy_pca(mean.fitted, mean.registered, mean.weights)
    m = pc.eigenvalues.shape[0]
    np.testing.assert_allclose(pc.eigenvalues, vals[:m], rtol=1e-8, atol=1e-14)
    for i in range(2):
        dot = abs(float(np.dot(np.asarray(pc.components[i]), vecs[:, i])))
        np.testing.assert_allclose(dot, 1.0, atol=1e-8)
    # |v_i|² is the squared distance to the mean (the whitening is the metric).
    np.testing.assert_allclose(np.sum(V**2, axis=1), mean.energies, rtol=1e-8)
    np.testing.assert_allclose(np.sum(pc.explained_variance_ratio), 1.0, rtol=1e-10)


def test_two_mode_population_has_two_dominant_components(two_mode):
    _, _, _, _, pc = two_mode
    ratio = np.asarray(pc.explained_variance_ratio)
    assert ratio[0] > ratio[1] > 0
    assert ratio[0] + ratio[1] > 0.999, ratio[:4]
    assert pc.n_components == 2


def test_pca_of_copies_has_zero_variance():
    root = random_root(np.random.default_rng(8), n_laterals=2)
    # 8 copies of a 2-lateral root: the shapes (n, K, T) = (8, 4, 30) of `two_mode`, so the
    # compiled programs are shared.
    copies = transformed_copies(root, np.random.default_rng(9), 8, reparam=False)
    mean = karcher_mean(rs.batch(copies, n_points=T), max_steps=10)
    pc = tangent_pca(mean)
    scale = float(rs.l2_norm_squared(mean.fitted.q0))
    assert float(jnp.sum(pc.eigenvalues)) < 1e-18 * scale
    assert pc.n_components == 0
    with pytest.raises(ValueError, match="n_components"):
        rs_fit_regression_on(pc)


def rs_fit_regression_on(pc):
    from rootshape_jax._regression import TraitRegression

    return TraitRegression.fit(pc, traits=(), covariates=np.zeros((8, 1)))


def test_scores_reconstruct_the_samples(two_mode):
    _, _, x, mean, pc = two_mode
    m = pc.components.shape[0]
    back = reconstruct(pc, pc.scores[:, :m], srvf=True)
    # Tangent vectors are rebuilt exactly (uncentred PCA on all components).
    np.testing.assert_allclose(back.q, mean.registered.q * back.mask[..., None, None], atol=1e-10)
    np.testing.assert_allclose(back.q0, mean.registered.q0, atol=1e-10)
    real = np.asarray(mean.registered.mask)
    np.testing.assert_allclose(np.asarray(back.s)[real], np.asarray(mean.registered.s)[real], atol=1e-10)


def test_project_recovers_coefficients(two_mode):
    _, _, x, mean, pc = two_mode
    b = project(pc, x)
    assert b.shape == (8, pc.n_components)
    np.testing.assert_allclose(b, pc.scores[:, : pc.n_components], atol=1e-6)
    one = project(pc, jax.tree.map(lambda t: t[3], x))
    np.testing.assert_allclose(one, b[3], atol=1e-10)


def test_project_in_blocks_moves_the_bar_per_block(two_mode, monkeypatch):
    _, _, x, _, pc = two_mode
    whole = project(pc, x, block_size=8)  # one call, no bar
    made = record_bars(monkeypatch)
    blocks = project(pc, x, block_size=3)  # 8 roots: blocks of 3, 3, 2
    np.testing.assert_allclose(blocks, whole, atol=1e-10)
    (bar,) = made
    assert bar.kwargs["total"] == 8 and sorted(bar.updates) == [2, 3, 3]
    with pytest.raises(ValueError, match="block_size"):
        project(pc, x, block_size=0)


def test_modes(two_mode):
    _, _, _, mean, pc = two_mode
    alphas = [-2.0, 0.0, 2.0]
    m0 = modes(pc, alphas, component=0)
    assert isinstance(m0, rs.RootTree) and m0.main.shape == (3, T, 2)
    # alpha = 0 is the mean itself (laterals below the threshold are nulls, like the mean's).
    centre = jax.tree.map(lambda x: x[1], m0)
    np.testing.assert_allclose(centre.main, mean.mean.main, atol=1e-12)
    np.testing.assert_array_equal(centre.mask, mean.mean_srvf.mask)
    both = modes(pc, alphas, component=[0, 1])
    assert both.main.shape == (2, 3, T, 2)
    # Along mode 0 (lateral lengths) the laterals grow monotonically with alpha.
    lengths = np.asarray(rs.curve_length(m0.laterals)).sum(axis=-1)
    assert lengths[0] < lengths[1] < lengths[2] or lengths[0] > lengths[1] > lengths[2]
    with pytest.raises(ValueError, match="out of range"):
        modes(pc, alphas, component=99)


def test_sample_returns_valid_roots(two_mode):
    _, _, _, mean, pc = two_mode
    roots = sample(pc, jax.random.PRNGKey(0), 16)
    assert roots.main.shape == (16, T, 2) and roots.laterals.shape == (16, 4, T, 2)
    for leaf in (roots.main, roots.laterals, roots.attach):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.all((np.asarray(roots.attach) >= 0) & (np.asarray(roots.attach) <= 1))
    t = rs.to_srvf(roots)
    lengths = np.asarray(rs.l2_norm_squared(t.q))
    assert np.all(lengths[np.asarray(roots.mask)] >= float(pc.min_lateral_length) * 0.999)
    # Null laterals are collapsed onto their attachment point.
    null = ~np.asarray(roots.mask)
    spread = np.ptp(np.asarray(roots.laterals), axis=-2).max(axis=-1)
    assert np.all(spread[null] == 0)
    # Reproducible with the key; different keys differ.
    again = sample(pc, jax.random.PRNGKey(0), 16)
    np.testing.assert_array_equal(again.main, roots.main)
    other = sample(pc, jax.random.PRNGKey(1), 16)
    assert not np.allclose(other.laterals, roots.laterals)
    # Every root is a valid Root again.
    assert len(rs.to_roots(roots)) == 16


def test_sample_truncation_bounds_the_deviation(two_mode):
    _, _, _, mean, pc = two_mode
    c = 0.5
    t = sample(pc, jax.random.PRNGKey(3), 64, truncate=c, srvf=True)
    # Positions are not clipped or masked for real laterals here: |Δs|·√λp <= c·Σ√σ|Λ_s|.
    m = pc.n_components
    bound = c * float(jnp.sum(jnp.sqrt(pc.eigenvalues[:m])))
    dev_s = np.abs(np.asarray(t.s) - np.asarray(pc.mean.s)) * float(pc.scales.s)
    assert dev_s.max() <= bound + 1e-12
    free = sample(pc, jax.random.PRNGKey(3), 64, srvf=True)
    dev_free = np.abs(np.asarray(free.s) - np.asarray(pc.mean.s)) * float(pc.scales.s)
    assert dev_free.max() > dev_s.max()


def test_bad_input(two_mode):
    _, _, _, mean, pc = two_mode
    with pytest.raises(TypeError):
        tangent_pca(pc)
    with pytest.raises(ValueError, match="variance"):
        tangent_pca(mean, variance=1.5)
    for n in (0, True, 2.0):  # a bool or a float is not a count (True was read as 1)
        with pytest.raises(ValueError, match="n must be an integer >= 1"):
            sample(pc, jax.random.PRNGKey(0), n)
    for m in (-1, 1.5, False):  # 1.5 was truncated to 1
        with pytest.raises(ValueError, match="n_components must be an integer >= 0"):
            sample(pc, jax.random.PRNGKey(0), 2, n_components=m)
    with pytest.raises(ValueError, match="coefficients"):
        reconstruct(pc, jnp.zeros((3, 100)))


def test_synthesised_laterals_stay_in_the_data_range(two_mode):
    """Defaults: laterals below the data's 10th percentile of lateral lengths are dropped,
    longer than the data's longest are scaled down to it, so random roots and ±2σ modes
    meet `plausibility`'s length criterion; a slow reference for the two thresholds."""
    _, _, x, mean, pc = two_mode
    reg = jax.tree.map(np.asarray, mean.registered)
    lengths = np.array(
        [
            sum(np.sum(reg.q[i, k] ** 2, axis=-1)[j] * w for j, w in enumerate(_trapezoid(T)))
            for i in range(reg.q.shape[0])
            for k in range(reg.q.shape[1])
            if reg.mask[i, k]
        ]
    )
    np.testing.assert_allclose(float(pc.min_lateral_length), np.quantile(lengths, 0.1), rtol=1e-9)
    np.testing.assert_allclose(float(pc.max_lateral_length), lengths.max(), rtol=1e-9)
    t = sample(pc, jax.random.PRNGKey(5), 64, srvf=True)
    L = np.asarray(rs.l2_norm_squared(t.q))[np.asarray(t.mask)]
    assert L.min() >= float(pc.min_lateral_length) * (1 - 1e-9)
    assert L.max() <= float(pc.max_lateral_length) * (1 + 1e-9)
    # Without the cap (max_lateral_length=inf) the same draw has longer laterals.
    free = tangent_pca(mean, max_lateral_length=float("inf"))
    tf = sample(free, jax.random.PRNGKey(5), 64, srvf=True)
    assert np.asarray(rs.l2_norm_squared(tf.q))[np.asarray(tf.mask)].max() > L.max()
    # The measure agrees: every ±2σ root has its laterals in range (up to polyline rounding).
    p = rs.plausibility(modes(pc, [-2.0, 2.0], component=0), x, tolerance=0.02)
    assert p.lengths_in_range.all()
    with pytest.raises(ValueError, match="max_lateral_length"):
        tangent_pca(mean, max_lateral_length=0.0)


def _trapezoid(n):
    w = np.full(n, 1.0 / (n - 1))
    w[[0, -1]] /= 2
    return w


@pytest.mark.parametrize("seed, dtype", [(2, np.float64), (3, np.float64), (5, np.float64), (3, np.float32)])
def test_zero_coefficients_give_the_karcher_mean_itself(seed, dtype):
    """From an audit on RootNav tracings: with the default thresholds, reconstruct(pc, 0) had 3
    laterals where the Karcher mean has 8 (the data's 10th percentile of lateral lengths is
    above a mean's laterals, which averaging shrinks), so the centre of every modes figure was
    another root than the mean. A lateral that half the roots have makes such a short mean
    lateral here; it must stay, while a lateral the mean dropped stays dropped."""
    main = np.stack([np.zeros(40), np.linspace(0, 1, 40)], 1)
    rng = np.random.default_rng(seed)

    def lateral(y, length, bend):
        t = np.linspace(0, 1, 30)
        return np.stack([length * t, y + bend * t**2], 1)

    roots = []
    for i in range(6):
        lats = [lateral(0.3, 0.3 + 0.02 * rng.normal(), 0.05 * rng.normal())]
        atts = [0.3]
        if i % 2:  # half the roots: a second lateral, so the mean's is short
            lats.append(lateral(0.7, -0.25, 0.03 * rng.normal()))
            atts.append(0.7)
        if i == 0:  # one root: a third one, dropped from the mean (< 2 % of the main root)
            lats.append(lateral(0.5, 0.08, 0.0))
            atts.append(0.5)
        roots.append(rs.Root(main=main, laterals=lats, attach=atts))
    x = rs.batch(roots, n_points=T, max_laterals=6, dtype=dtype)
    km = karcher_mean(x, progress=False)
    kept = np.asarray(km.mean_srvf.mask)
    short = kept & (np.asarray(km.lateral_lengths) < 0.9 * float(tangent_pca(km).min_lateral_length))
    assert short.any() and np.asarray(km.dropped).any()  # the case of the audit, and a dropped slot
    pc = tangent_pca(km)
    zero = reconstruct(pc, np.zeros(pc.components.shape[0]), srvf=True)
    np.testing.assert_array_equal(np.asarray(zero.mask), kept)
    tol = 1e-12 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(np.asarray(zero.q), np.asarray(km.mean_srvf.q), atol=tol)
    np.testing.assert_allclose(np.asarray(zero.q0), np.asarray(km.mean_srvf.q0), atol=tol)
    centre = modes(pc, [0.0])
    np.testing.assert_array_equal(np.asarray(centre.mask[0]), np.asarray(km.mean.mask))
    np.testing.assert_allclose(np.asarray(centre.laterals[0]), np.asarray(km.mean.laterals), atol=100 * tol)
    # Away from the mean the data's percentile still rules the other slots, and a value given
    # is used as it is (no per-slot thresholds).
    assert np.all(np.asarray(pc.slot_min_lengths[0])[~short & kept] == float(pc.min_lateral_length))
    given = tangent_pca(km, min_lateral_length=0.0)
    assert given.slot_min_lengths == ()
    assert bool(np.all(np.asarray(reconstruct(given, np.zeros(2), srvf=True).mask)))  # every fitted slot
