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
    # A negative weight cannot be refused under jit either: NaN, not the plausible 0.0 that a
    # negative energy clipped at 0 gave (an audit found it).
    assert np.isnan(by_weight(-1.0))


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


# --------------------------------------------------------------------------------------------
# From an audit of bad input across the public API (session 31): each of these returned a NaN,
# a complex number or a plausible wrong value, or failed inside JAX/numpy with a message that
# did not name the problem.


@pytest.fixture(scope="module")
def small_pca():
    from rootshape_jax.datasets import synthetic_roots

    trees = rs.batch(synthetic_roots(5, seed=0), n_points=12, normalise_scale=True)
    km = rs.karcher_mean(trees, max_steps=5, throw=False)
    return trees, rs.tangent_pca(km), km


def test_pca_coefficients_must_be_finite_real_and_sized(small_pca):
    trees, pc, km = small_pca
    m = pc.n_components
    for bad in (np.full(m, np.nan), np.full(m, np.inf), jnp.full(m, jnp.nan)):
        with pytest.raises(ValueError, match="reconstruct: coefficients contains NaN or inf"):
            rs.reconstruct(pc, bad)
    with pytest.raises(ValueError, match="NaN or inf"):
        rs.modes(pc, [np.nan])
    with pytest.raises(ValueError, match="overflow"):
        rs.reconstruct(pc, np.full(m, 1e200))
    with pytest.raises(TypeError, match="real numbers"):
        rs.reconstruct(pc, np.ones(m) * 1j)
    with pytest.raises(ValueError, match="modes: component must be an integer"):
        rs.modes(pc, [1.0], component=1.5)
    for bad in (-1, 2.7):
        with pytest.raises(ValueError, match="project: n_components must be an integer >= 0"):
            rs.project(pc, trees, n_components=bad, progress=False)
    with pytest.raises(ValueError, match="project: n_components must be in"):
        rs.project(pc, trees, n_components=pc.components.shape[0] + 1, progress=False)
    # A traced NaN is caught when the program runs.
    with pytest.raises(Exception, match="NaN or inf"):
        jax.block_until_ready(jax.jit(lambda b: rs.reconstruct(pc, b).main)(jnp.full(m, jnp.nan)))


def test_trait_values_are_checked_whatever_their_array_type(small_pca):
    trees, pc, km = small_pca
    reg = rs.TraitRegression.fit(pc, trees, traits="n_laterals")  # one name is one trait
    assert reg.names == ("n_laterals",) or list(reg.names) == ["n_laterals"]
    for bad in (np.array([np.nan]), jnp.array([jnp.nan]), jnp.array([jnp.inf])):
        with pytest.raises(ValueError, match="trait values contain NaN or inf"):
            reg.synthesize(bad)
    ok = reg.synthesize(jnp.array([float(np.mean([len(r.laterals) for r in rs.to_roots(trees)]))]))
    assert np.all(np.isfinite(np.asarray(ok.main)))


def test_weights_are_real_numbers_and_trees_stay_in_range(pair):
    a, b = pair
    for bad in (dict(main=1j), dict(main="0.5"), dict(lateral=True)):
        with pytest.raises(TypeError, match=r"Weights\.\w+ must be a real number"):
            rs.Weights(**bad)
    with pytest.raises(TypeError, match="must be a real number"):
        rs.Weights(deeper=((1.0, 1j),))
    huge = rs.scale_tree(rs.stack([a, b]), jnp.array([1e200, 1.0]))
    with pytest.raises(rs.CoordinateRangeError, match="RootTree.main: coordinates reach"):
        rs.distance(*rs.unstack(huge))
    as_int = jax.tree.map(lambda x: x.astype(jnp.int32) if jnp.issubdtype(x.dtype, jnp.floating) else x, a)
    with pytest.raises(TypeError, match="RootTree has int32 values; the metric needs float32 or float64"):
        rs.distance(as_int, as_int)
    # An SRVFTree cast to float16 gave float16 distances.
    half = jax.tree.map(lambda x: x.astype(jnp.float16) if jnp.issubdtype(x.dtype, jnp.floating) else x, rs.to_srvf(a))
    with pytest.raises(TypeError, match="SRVFTree has float16 values; the metric needs float32 or float64"):
        rs.distance(half, half)


def test_assignments_labels_and_unstack_name_their_problem():
    from rootshape_jax import InvalidCostError, LabelError

    with pytest.raises(InvalidCostError, match="permutation of 0..1"):
        rs.assignment_cost(np.eye(2), np.array([5, 7]))
    with pytest.raises(InvalidCostError, match="permutation"):
        rs.assignment_cost(np.eye(2), np.array([0, 0]))
    assert float(rs.assignment_cost(np.eye(2), np.array([1, 0]))) == 0.0
    D = np.array([[0, 1, 4, 4], [1, 0, 4, 4], [4, 4, 0, 1], [4, 4, 1, 0]], float)
    for bad in ([1.0, np.nan, 2.0, 2.0], ["a", None, "b", "b"]):
        with pytest.raises(LabelError, match=r"labels of roots \[1\] are missing"):
            rs.loo_accuracy(D, bad)
    assert rs.loo_accuracy(D, [1, 1, 2, 2])["accuracy"] == 1.0
    rng = np.random.default_rng(2)
    one = rs.unstack(rs.batch([random_root(rng, n_laterals=2) for _ in range(2)], n_points=10))[0]
    with pytest.raises(ValueError, match="unstack: this RootTree is a single tree"):
        rs.unstack(one)


def test_curves_take_integers_and_refuse_what_is_not_a_real_number():
    x = np.stack([np.arange(6), np.arange(6) ** 2], axis=1)
    assert np.allclose(rs.srvf(x), rs.srvf(x.astype(float)))
    assert float(rs.curve_length(x)) == pytest.approx(float(rs.curve_length(x.astype(float))))
    line = np.stack([np.linspace(0, 1, 10), np.zeros(10)], axis=1)
    for bad in (line.astype(complex), line > 0.5, line.astype(str)):
        with pytest.raises(TypeError, match="coordinates must be real numbers"):
            rs.elastic_curve_distance(bad, line)
        with pytest.raises(TypeError, match="coordinates must be real numbers"):
            rs.srvf(bad)


def test_boolean_options_refuse_truthy_strings(pair, tmp_path):
    from rootshape_jax.io import read_rsml, roots_from_image, write_rsml

    rng = np.random.default_rng(5)
    roots = [random_root(rng, n_laterals=2) for _ in range(2)]
    with pytest.raises(TypeError, match="normalise_scale must be True or False, got 'False'"):
        rs.batch(roots, n_points=10, normalise_scale="False")  # a string is truthy: it normalised
    line = np.stack([np.linspace(0, 1, 10), np.zeros(10)], axis=1)
    with pytest.raises(TypeError, match="rotation must be True or False"):
        rs.elastic_curve_distance(line, line, rotation="no")
    with pytest.raises(TypeError, match="throw must be True or False"):
        rs.karcher_mean(rs.batch(roots, n_points=10), throw="no")
    path = tmp_path / "r.rsml"
    write_rsml(roots, path)
    with pytest.raises(TypeError, match="strict must be True or False"):
        read_rsml(path, strict="no")
    for bad in (5, None):
        with pytest.raises(TypeError, match="read_rsml: path must be a file name or an open file"):
            read_rsml(bad)
    with pytest.raises(IsADirectoryError, match="read_folder"):
        read_rsml(tmp_path)
    img = np.zeros((40, 40))
    for kw, msg in (
        (dict(spacing=0), "spacing must be a positive"),
        (dict(spacing=-1), "spacing must be a positive"),
        (dict(roi=(0, 0, 10)), "roi must be"),
        (dict(sensitivity=5), "sensitivity must be"),
        (dict(smooth=None), "smooth must be"),
    ):
        with pytest.raises(ValueError, match=msg):
            roots_from_image(img, **kw)
    with pytest.raises(TypeError, match="invert must be True or False"):
        roots_from_image(img, invert="yes")
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="batch\\(\\): max_laterals must be an integer >= 0"):
            rs.batch(roots, n_points=10, max_laterals=bad)


def test_geodesic_takes_registration_options_as_register_does(pair):
    a, b = pair
    by_keyword = rs.geodesic(a, b, n_steps=3, rotation=False)
    by_options = rs.geodesic(a, b, n_steps=3, registration=rs.RegistrationOptions(rotation=False))
    assert np.array_equal(np.asarray(by_keyword.main), np.asarray(by_options.main))
    by_dict = rs.geodesic(a, b, n_steps=3, registration={"rotation": False})
    assert np.array_equal(np.asarray(by_keyword.main), np.asarray(by_dict.main))
    with pytest.raises(TypeError, match="registration must be the Registration of b onto a"):
        rs.geodesic(a, b, registration="rotation=False")
    # A Registration of another pair, of the other order or at other weights has the same
    # shapes; it gave a path between other shapes without an error.
    reg = rs.register(a, b)
    np.testing.assert_array_equal(
        rs.geodesic(a, b, n_steps=3, registration=reg).main, rs.geodesic(a, b, n_steps=3).main
    )
    for wrong, kwargs in ((rs.register(b, a), {}), (reg, {"weights": rs.Weights(main=1.0, position=5.0)})):
        with pytest.raises(ValueError, match="registration is not the registration of b onto a at these weights"):
            rs.geodesic(a, b, n_steps=3, registration=wrong, **kwargs)
    # Plants' systems: the virtual main root's SRVF is all zeros, the laterals' set the
    # scale of the check (a review found every plant refused, its own registration too).
    from rootshape_jax.io import plant_system

    rng = np.random.default_rng(5)
    plants = [plant_system([random_root(rng, n_laterals=2) for _ in range(2)]) for _ in range(2)]
    with pytest.warns(UserWarning, match="left out"):  # the axes' laterals: depth 2 is enough here
        pa, pb = rs.unstack(rs.batch(plants, n_points=12))
    assert pa.virtual_main
    preg = rs.register(pa, pb)
    np.testing.assert_array_equal(
        rs.geodesic(pa, pb, n_steps=3, registration=preg).main, rs.geodesic(pa, pb, n_steps=3).main
    )
    with pytest.raises(ValueError, match="registration is not the registration of b onto a"):
        rs.geodesic(pa, pb, n_steps=3, registration=rs.register(pb, pa))


def test_out_of_range_options_of_statistics_are_refused(small_pca):
    trees, pc, km = small_pca
    line = np.stack([np.linspace(0, 1, 10), np.zeros(10)], axis=1)
    for bad in (0, 1, 2.5):
        with pytest.raises(ValueError, match="resample_curve: n_points must be an integer >= 2"):
            rs.resample_curve(line, bad)
    for bad in ([0.01, np.nan], [0.5, -0.1], [0.2, 1.5]):
        with pytest.raises(ValueError, match="holm: p_values must be"):
            rs.holm(bad)
    D = np.array([[0.0, 1.0, 3.0], [1.0, 0.0, 2.0], [3.0, 2.0, 0.0]])
    for bad in (np.nan, -1.0, "1"):
        with pytest.raises(ValueError, match="height must be a finite distance >= 0"):
            rs.cluster(D, n_clusters=None, height=bad)
    off = np.ones((5, 5)) - np.eye(5)
    with pytest.raises(ValueError, match="non-negative"):  # (not symmetric is fine: a start only)
        rs.karcher_mean(trees, distances=-off)
    # Scalars of numpy and JAX, sequences and mappings that worked before still work.
    assert rs.cluster(D, n_clusters=None, height=jnp.asarray(1.5)).n_clusters == 2
    assert rs.cluster(D, n_clusters=None, height=np.array(1.5)).n_clusters == 2
    assert rs.modes(pc, [1.0], component=jnp.arange(2)).main.shape[:2] == (2, 1)
    import types

    opts = rs.RegistrationOptions(rotation=False)
    assert rs.register(*rs.unstack(trees)[:2], registration=types.MappingProxyType({"rotation": False})).distance == (
        rs.register(*rs.unstack(trees)[:2], registration=opts).distance
    )
    for bad in (-1.0, np.nan):
        with pytest.raises(ValueError, match="min_lateral_length must be a number >= 0"):
            rs.karcher_mean(trees, min_lateral_length=bad)
    with pytest.raises(ValueError, match="min_lateral_length .* is above max_lateral_length"):
        rs.tangent_pca(km, min_lateral_length=5.0, max_lateral_length=1.0)
    with pytest.raises(ValueError, match="min_lateral_length must be >= 0"):
        rs.tangent_pca(km, min_lateral_length=np.nan)


def test_roots_and_options_of_the_wrong_kind_are_named(pair):
    line = np.stack([np.linspace(0, 1, 10), np.zeros(10)], axis=1)
    lat = line[:4] * 0.3
    child = rs.Root(main=lat)
    for kw, msg in (
        (dict(laterals=[lat], attach=np.array(["a"])), "attach must hold numbers"),
        (dict(metadata=[1, 2]), "metadata must be a dict"),
        (dict(laterals=[lat], children=child), "children` must be a tuple of Roots"),
        (dict(laterals=[lat], children=(1,)), r"children \[0\] are not Roots"),
    ):
        with pytest.raises(InvalidRootError, match=msg):
            rs.Root(main=line, **kw)
    assert rs.Root(main=line, laterals=[lat], children=[child]).children == (child,)
    a, b = pair
    with pytest.raises(TypeError, match="registration must be a rootshape_jax.RegistrationOptions or a dict"):
        rs.distance(a, b, registration="x")
    with pytest.raises(ValueError, match="rtol must be a non-negative number, got 'x'"):
        rs.distance(a, b, rtol="x")
    with pytest.raises(ValueError, match="n >= 1"):
        rs.cluster(np.zeros((0, 0)))


def test_the_early_ctrl_c_handler_is_only_for_the_rootshape_program(monkeypatch):
    """A review found that any `python -m mypkg` whose package imports rootshape_jax got the
    handler (sys.argv[0] is "-m" while -m's package imports): Ctrl-C then ended that program."""
    import sys

    from rootshape_jax import _early_interrupt as early

    for argv, orig, expected in (
        (["-m"], ["python", "-m", "rootshape_jax", "traits"], True),
        (["-m"], ["python", "-X", "dev", "-W", "error", "-mrootshape_jax"], True),
        (["-m"], ["python", "-m", "mypkg"], False),
        (["-m"], ["python", "-c", "import x", "-m", "rootshape_jax"], False),
        (["/venv/bin/rootshape", "traits"], ["python", "/venv/bin/rootshape", "traits"], True),
        (["/venv/bin/pytest"], ["python", "/venv/bin/pytest"], False),
        (["ipykernel_launcher.py"], ["python", "-m", "ipykernel_launcher"], False),
    ):
        monkeypatch.setattr(sys, "argv", argv)
        monkeypatch.setattr(sys, "orig_argv", orig)
        assert early.is_the_program() is expected, (argv, orig)


def test_seeds_tolerances_diagonals_and_warps_are_checked(small_pca):
    # Each of these was accepted and failed later (numpy's message about seeds), ran with a
    # meaningless value (a negative tolerance), or silently changed the input (a similarity
    # matrix's diagonal of ones set to 0; a reversed warp read backwards).
    trees, _, _ = small_pca
    labels = [0, 0, 1, 1, 1]
    for bad in (-1, np.nan, "0.1"):
        with pytest.raises(ValueError, match="tol must be a number >= 0"):
            rs.learn_weights(trees, labels, tol=bad, progress=False)
        with pytest.raises(ValueError, match="tol must be a number >= 0"):
            rs.nested_cv_accuracy(trees, labels, n_folds=2, tol=bad, progress=False)
    for bad in (-1, "x", 1.5):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            rs.nested_cv_accuracy(trees, labels, n_folds=2, seed=bad, progress=False)
    D = np.array([[0.0, 1.0, 3.0, 3.0], [1.0, 0.0, 3.0, 3.0], [3.0, 3.0, 0.0, 1.0], [3.0, 3.0, 1.0, 0.0]])
    for bad in ("x", -2):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            rs.permanova(D, [0, 0, 1, 1], seed=bad)
    assert rs.permanova(D, [0, 0, 1, 1], seed=np.int64(3), permutations=9).pseudo_f > 0
    similarity = np.exp(-D)  # ones on the diagonal
    for call in (lambda M: rs.cluster(M), lambda M: rs.permanova(M, [0, 0, 1, 1]), lambda M: rs.mds(M)):
        with pytest.raises(ValueError, match=r"non-zero diagonal \(1 at row 0"):
            call(similarity)
    # A diagonal at the registration's discretisation error is a distance matrix's.
    near = D + 1e-6 * np.eye(4)
    np.testing.assert_array_equal(rs.cluster(near).labels, rs.cluster(D).labels)
    beta = np.stack([np.linspace(0.0, 1.0, 6), np.zeros(6)], axis=1)
    gamma = np.linspace(0.0, 1.0, 6)
    np.testing.assert_allclose(rs.apply_warp_curve(beta, gamma), beta)
    for bad in (gamma[::-1], np.r_[gamma[:-1], np.nan]):
        with pytest.raises(Exception, match="gamma must be nondecreasing from gamma"):
            rs.apply_warp_curve(beta, bad)
