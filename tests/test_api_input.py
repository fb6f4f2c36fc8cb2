"""What the Python API says to a user who passes the wrong thing: an error at the call that
names the problem, never a finite wrong number or a failure deep inside JAX."""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root

import rootshape_jax as rs
from rootshape_jax import InvalidRootError, MissingRadiusWarning


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(0)
    roots = [random_root(rng, n_laterals=3) for _ in range(2)]
    return rs.unstack(rs.batch(roots, n_points=12))


@pytest.mark.parametrize("field", ["main", "laterals", "attach"])
def test_nan_in_a_tree_is_refused_not_measured(pair, field):
    # The norms treat NaN as 0, so a NaN tree used to give a finite distance (0.41 against
    # 0.39 for the clean pair on two plate plants).
    a, b = pair
    bad = eqx.tree_at(lambda t: getattr(t, field), a, getattr(a, field).at[0].set(jnp.nan))
    for call in (
        lambda: rs.distance(bad, b),
        lambda: rs.distance(b, bad),
        lambda: rs.pairwise_distances(rs.stack([bad, b]), progress=False),
        lambda: rs.to_srvf(bad),
    ):
        with pytest.raises(InvalidRootError, match=f"RootTree.{field} holds NaN"):
            call()
    with pytest.raises(InvalidRootError, match="NaN"):
        rs.curve_length(jnp.array([[0.0, 0.0], [np.nan, 1.0], [0.0, 2.0]]))
    with pytest.raises(InvalidRootError, match="NaN"):
        rs.srvf(jnp.array([[0.0, 0.0], [np.inf, 1.0], [0.0, 2.0]]))
    assert np.isfinite(float(rs.distance(a, b)))


def test_numpy_integers_are_counts_and_bools_floats_are_not(pair):
    rng = np.random.default_rng(1)
    roots = [random_root(rng, n_laterals=2) for _ in range(2)]
    t = rs.batch(roots, n_points=np.int32(10))
    assert t.main.shape[-2] == 10
    a, b = pair
    assert rs.geodesic(a, b, n_steps=np.int64(3)).main.shape[0] == 3
    for bad in (10.0, True, "10", 1):
        with pytest.raises(ValueError, match="n_points must be an integer >= 2"):
            rs.batch(roots, n_points=bad)
    with pytest.raises(ValueError, match="max_iterations must be an integer >= 1"):
        rs.RegistrationOptions(max_iterations=0)
    b1 = np.stack([np.linspace(0, 1, 20), np.sin(np.linspace(0, 3, 20))], axis=1)
    got = rs.elastic_curve_distance(b1, b1[::-1].copy(), n_samples=np.int64(30), max_iterations=np.int32(2))
    ref = rs.elastic_curve_distance(b1, b1[::-1].copy(), n_samples=30, max_iterations=2)
    assert float(got.distance) == pytest.approx(float(ref.distance))


def test_rotation_option_must_be_a_bool():
    assert bool(rs.RegistrationOptions(rotation=np.bool_(False)).rotation) is False
    for bad in ("no", "False", 0, None):
        with pytest.raises(TypeError, match="rotation must be True or False"):
            rs.RegistrationOptions(rotation=bad)


def test_weights_must_be_weights(pair):
    a, b = pair
    for bad in ((0.02, 1, 1), {"main": 0.02}, [0.02, 1, 1]):
        with pytest.raises(TypeError, match=r"weights must be a rootshape_jax.Weights.*Weights\(0.02, 1, 1\)"):
            rs.distance(a, b, weights=bad)
        with pytest.raises(TypeError, match="weights must be"):
            rs.pairwise_distances(rs.stack([a, b]), weights=bad, progress=False)
    # learn_weights' result (a Module holding `.weights`) says which field to pass.
    import types

    learned = types.SimpleNamespace(weights=rs.Weights(main=0.01))
    with pytest.raises(TypeError, match=r"got a SimpleNamespace; pass its `.weights`"):
        rs.distance(a, b, weights=learned)


def test_thickness_weight_without_radii_says_it_does_nothing(pair):
    a, b = pair
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = rs.distance(a, b, weights=rs.Weights(thickness=1.0))
    (w,) = [w for w in caught if issubclass(w.category, MissingRadiusWarning) and "no effect" in str(w.message)][:1]
    # Attributed to the caller's line (here), not to a line inside the package.
    assert w.filename == __file__, w.filename
    assert float(d) == pytest.approx(float(rs.distance(a, b)), rel=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MissingRadiusWarning)
        rs.distance(a, b)  # thickness 0: nothing to say


def test_scale_and_key_errors_at_the_call(pair):
    a, _ = pair
    for bad in (-2.0, 0.0, np.nan):
        with pytest.raises(ValueError, match="scales must be finite and > 0"):
            rs.scale_tree(a, bad)
    from rootshape_jax._pca import _check_key

    _check_key(jax.random.key(0))
    _check_key(jax.random.PRNGKey(0))
    _check_key(jax.random.PRNGKey(0, impl="rbg"))  # 4 words
    for bad in (0, np.uint32(3), jnp.zeros(3, jnp.uint32), jax.random.split(jax.random.key(0), 2)):
        with pytest.raises(TypeError, match=r"key must be one JAX random key, e\.g\. jax\.random\.key\(0\)"):
            _check_key(bad)


def test_confusion_matrix_refuses_unequal_lengths():
    C, classes = rs.confusion_matrix([0, 1, 1, 0], [0, 1, 0, 0])
    assert C.tolist() == [[2, 0], [1, 1]] and classes.tolist() == [0, 1]
    with pytest.raises(ValueError, match="one length"):
        rs.confusion_matrix([0, 1, 1, 0], [0, 1])


def test_upright_rotation_is_public_and_points_the_mean_like_the_roots():
    # The CLI turns its means with these; Python users can too (README).
    rng = np.random.default_rng(3)
    roots = [random_root(rng, n_laterals=2) for _ in range(4)]
    trees = rs.batch(roots, n_points=16)
    one = rs.unstack(trees)[0]
    R = rs.upright_rotation(one, trees)
    out = rs.turn_about_base(one, R)
    chords = np.asarray(trees.main[:, -1] - trees.main[:, 0])
    target = np.mean(chords / np.linalg.norm(chords, axis=1)[:, None], axis=0)
    m = np.asarray(out.main[-1] - out.main[0])
    assert m @ target / np.linalg.norm(m) / np.linalg.norm(target) == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="one root"):
        rs.upright_rotation(trees, trees)
    # SRVF trees (karcher_mean takes them) are taken as their curves (integrated back, which
    # smooths a wiggly 16-point root a little: its chord turns by a few degrees).
    R_srvf = rs.upright_rotation(rs.to_srvf(one), rs.to_srvf(trees))
    assert abs(np.degrees(np.arctan2(R_srvf[1, 0], R_srvf[0, 0]) - np.arctan2(R[1, 0], R[0, 0]))) < 5


def test_non_finite_input_under_jit_gives_nan_not_a_distance():
    """Under a caller's jit the concrete checks cannot run, and the engine raises nothing (no
    host callback, so its programs can be cached): a NaN in a tree or a weight must come out
    as a NaN distance, not as the finite result the DP and assignment would give."""
    rng = np.random.default_rng(0)
    trees = rs.to_srvf(rs.batch([random_root(rng, n_laterals=3) for _ in range(2)], n_points=16))
    a, b = rs.unstack(trees)
    bad = eqx.tree_at(lambda t: t.q0, b, b.q0.at[3, 0].set(jnp.nan))
    dist = jax.jit(lambda a, b: rs.distance(a, b))
    assert np.isfinite(dist(a, b))
    assert np.isnan(dist(a, bad))
    by_weight = jax.jit(lambda lam: rs.distance(a, b, weights=rs.Weights(main=lam, lateral=1.0, position=1.0)))
    assert np.isfinite(by_weight(0.02)) and np.isnan(by_weight(jnp.nan))


@pytest.mark.parametrize("field", ["main", "laterals", "attach"])
def test_nan_point_of_a_curve_tree_under_jit_gives_nan(field):
    """Found by a user test: one NaN point in a RootTree under jax.jit gave 8.459 (clean 8.453):
    the SRVF's safe norm turned NaN into 0. Every field of the curves must carry NaN through."""
    rng = np.random.default_rng(1)
    a, b = rs.unstack(rs.batch([random_root(rng, n_laterals=3) for _ in range(2)], n_points=16))
    x = getattr(b, field)
    # An interior point: the first point of the main root becomes the SRVF's origin, and the
    # attachments its `s`, which the engine's own finiteness check already saw; `attach` stays
    # as a guard.
    where = {"main": (8, 0), "laterals": (0, 8, 0), "attach": (0,)}[field]
    bad = eqx.tree_at(lambda t: getattr(t, field), b, x.at[where].set(jnp.nan))
    dist = jax.jit(lambda a, b: rs.distance(a, b))
    assert np.isfinite(dist(a, b))
    assert np.isnan(dist(a, bad))


def test_chunked_python_loops_say_they_cannot_be_jitted():
    """pairwise_distances and karcher_mean drive compiled chunks from Python: under jit they
    raised numpy's TracerArrayConversionError from deep inside; now a TypeError names the way."""
    rng = np.random.default_rng(2)
    trees = rs.batch([random_root(rng, n_laterals=2) for _ in range(3)], n_points=12)
    with pytest.raises(TypeError, match="pairwise_distances cannot run under jax.jit"):
        jax.jit(lambda t: rs.pairwise_distances(t, progress=False))(trees)
    with pytest.raises(TypeError, match="cross_distances cannot run under jax.jit"):
        jax.jit(lambda t: rs.cross_distances(t, t, progress=False))(trees)
    with pytest.raises(TypeError, match="karcher_mean cannot run under jax.jit.*karcher_objective"):
        jax.jit(lambda t: rs.karcher_mean(t, progress=False).energy)(trees)
    # Concrete trees, traced weights (or start): the same clear error, not numpy's from inside.
    with pytest.raises(TypeError, match="pairwise_distances cannot run under jax.jit"):
        jax.jit(lambda lam: rs.pairwise_distances(trees, weights=rs.Weights(main=lam), progress=False))(0.02)
    with pytest.raises(TypeError, match="karcher_mean cannot run under jax.jit"):
        jax.jit(lambda lam: rs.karcher_mean(trees, weights=rs.Weights(main=lam), progress=False).energy)(0.02)
    with pytest.raises(TypeError, match="karcher_mean cannot run under jax.jit"):
        jax.jit(lambda t: rs.karcher_mean(trees, init=t, progress=False).energy)(rs.unstack(trees)[0])


def test_default_chunk_size_follows_the_lateral_slots(monkeypatch):
    """SmartRoot maize (842 slots) with three other roots took 414 s and 5 GB in chunks of 32
    pairs, 33 s in chunks of 1: the default chunk now shrinks with K × K."""
    from rootshape_jax import _pairwise

    assert [_pairwise.default_chunk_size(k) for k in (2, 54, 64, 65, 120, 126, 200, 842)] == [
        32,
        32,
        32,
        16,
        8,
        8,
        2,
        1,
    ]
    # A power of two: it divides the CLI store's block of 64 pairs at every K (a chunk of 9 at
    # K = 120 made `distances --store` refuse its own block size).
    assert all(64 % _pairwise.default_chunk_size(k) == 0 for k in range(1, 1000))
    seen = []

    def record(s, t, I, J, weights, options, chunk_size):
        seen.append(chunk_size)
        return {"energies": np.zeros(len(I)), "lateral_dp": 0, "lateral_skipped": 0, "deeper_dp": []}

    monkeypatch.setattr(_pairwise, "run_pair_chunks", record)
    rng = np.random.default_rng(3)
    roots = [random_root(rng, n_laterals=2) for _ in range(3)]
    rs.pairwise_distances(rs.batch(roots, n_points=8, max_laterals=126), progress=False)
    rs.pairwise_distances(rs.batch(roots, n_points=8), progress=False, chunk_size=5)
    rs.cross_distances(rs.batch(roots, n_points=8), rs.batch(roots, n_points=8), progress=False)
    assert seen == [8, 5, 32]


def test_two_and_three_dimensional_trees_are_named_as_such():
    """A 2-D and a 3-D tree were refused as "different capacities (T, K, d)" with advice about
    n_points and max_laterals, not the dimension."""
    rng = np.random.default_rng(4)
    flat = random_root(rng, n_laterals=2)
    a = rs.batch(flat, n_points=8, max_laterals=4)
    b = rs.batch(random_root(rng, n_laterals=2, d=3), n_points=8, max_laterals=4)
    with pytest.raises(ValueError, match="different dimensions \\(2-D and 3-D\\).*z = 0"):
        rs.distance(a, b)


def test_a_tree_where_roots_or_a_matrix_are_expected_is_named():
    """From a tour of the real files: write_rsml(trees) said "'RootTree' object is not iterable",
    cluster(trees) and mds(trees) failed in float(), to_roots with too few names raised a bare
    IndexError."""
    from rootshape_jax.io import write_rsml

    rng = np.random.default_rng(8)
    trees = rs.batch([random_root(rng, n_laterals=2) for _ in range(3)], n_points=12)
    with pytest.raises(TypeError, match=r"write_rsml writes Roots, got a RootTree.*to_roots\(tree, unit="):
        write_rsml(trees, "never_written.rsml")
    for call in (lambda: rs.cluster(trees), lambda: rs.mds(trees), lambda: rs.loo_accuracy(trees, [0, 0, 1])):
        with pytest.raises(TypeError, match=r"matrix of distances, got RootTree.*pairwise_distances"):
            call()
    with pytest.raises(ValueError, match="2 names for 3 trees"):
        rs.to_roots(trees, names=["a", "b"])
    assert [r.name for r in rs.to_roots(trees, names=("a", "b", "c"))] == ["a", "b", "c"]
    assert rs.to_roots(rs.unstack(trees)[0], names="one")[0].name == "one"
