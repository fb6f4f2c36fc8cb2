"""Learning the metric weights of whole root systems (issue 15 with docs/design.md §11, §12):
with the registrations fixed, the squared distance stays linear in every level's weights;
plants' systems weigh their axes as main roots; each order's (λs, λp) can be learned; the
thickness path keeps the deeper levels' registrations."""

from __future__ import annotations

import itertools
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import smooth_curve
from test_hierarchy import deep_root
from test_learn import point_at

import rootshape_jax as rs
import rootshape_jax._learn as learn
from rootshape_jax import Root, Weights
from rootshape_jax._metric import preshape_terms, unit_energies_by_level, weights_by_level
from rootshape_jax.io import plant_system, read_rsml

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

SHARED = Weights(main=0.05, lateral=1.3, position=0.7)
ONE_LEVEL = Weights(main=0.05, lateral=1.3, position=0.7, deeper=((2.0, 0.4),))
TWO_LEVELS = Weights(main=0.05, lateral=1.3, position=0.7, deeper=((2.0, 0.4), (0.5, 3.0)))


def systems(kind: str) -> rs.RootTree:
    rng = np.random.default_rng(11)
    if kind == "taproots, depth 3":
        return rs.batch(
            [deep_root(rng, n_laterals=3, max_sub=2) for _ in range(4)], depth=3, n_points=16, dtype=np.float64
        )
    if kind == "taproots, depth 4":
        roots = [deep_root(rng, n_laterals=2, max_sub=2, sub_sub=1) for _ in range(4)]
        return rs.batch(roots, depth=4, n_points=12, dtype=np.float64)
    axes = [deep_root(rng, n_laterals=2, max_sub=1) for _ in range(6)]
    plants = [plant_system(axes[0:2]), plant_system(axes[2:3]), plant_system(axes[3:5]), plant_system(axes[5:6])]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the axes' second-order laterals are left out at depth 3
        return rs.batch(plants, depth=3, n_points=16, dtype=np.float64)


KINDS = ["taproots, depth 3", "taproots, depth 4", "plants, depth 3"]


@pytest.mark.parametrize("kind, weights", list(itertools.product(KINDS, [SHARED, ONE_LEVEL, TWO_LEVELS])))
def test_unit_energies_by_level_rebuild_the_weighted_terms(kind, weights):
    trees = systems(kind)
    s = rs.to_srvf(trees)
    a = jax.tree.map(lambda x: x[:2], s)
    b = jax.tree.map(lambda x: x[2:], s)
    E = np.asarray(unit_energies_by_level(a, b))
    assert E.shape == (2, 2 * trees.depth - 1)
    lam = np.asarray(weights_by_level(weights, depth=trees.depth, virtual_main=trees.virtual_main))
    expected = np.asarray(preshape_terms(a, b, weights).total)
    np.testing.assert_allclose(E @ lam, expected, rtol=1e-12)
    # Every level's branches carry energy here, so a wrong column would show.
    assert np.all(E[:, 1::2].sum(axis=0) > 0)


# Depth 4 is slow (its two engine programs take ~2.5 min to compile): run with the slow tests.
@pytest.mark.parametrize(
    "kind", [pytest.param(k, marks=pytest.mark.slow) if k == "taproots, depth 4" else k for k in KINDS]
)
def test_linear_model_is_the_engine_energy_after_registration(kind):
    """With the registrations fixed, ``unit_energies @ weights_by_level`` is the registered d²
    (for plants' systems this failed before: their axes are weighed by λ_main)."""
    trees = systems(kind)
    W = ONE_LEVEL
    I, J = np.triu_indices(4, 1)
    regs = learn.register_pair_list(
        rs.to_srvf(trees, weights=W), I, J, W, rs.RegistrationOptions(), chunk_size=8, progress=False, desc=""
    )
    lam = np.asarray(weights_by_level(W, depth=trees.depth, virtual_main=trees.virtual_main))
    np.testing.assert_allclose(regs.unit_energies @ lam, regs.energy, rtol=1e-10)
    D = np.asarray(rs.pairwise_distances(trees, weights=W, progress=False))
    np.testing.assert_allclose(np.sqrt(regs.energy), D[I, J], rtol=1e-10)
    assert len(regs.child_permutations) == trees.depth - 2 and regs.child_warps == ()


def test_thickness_path_keeps_the_deeper_registrations():
    """λr rebuilds the SRVFs, so d² at fixed registrations re-applies them, every level's
    included: at the registration's own λ it is the engine's energy."""
    rng = np.random.default_rng(5)
    trees = rs.batch([deep_root(rng, n_laterals=2, max_sub=2, radius=True) for _ in range(3)], depth=3, n_points=12,
                     dtype=np.float64)  # fmt: skip
    W = Weights(main=0.05, lateral=1.0, position=0.5, thickness=2.0, deeper=((1.5, 0.8),))
    I, J = np.triu_indices(3, 1)
    regs = learn.register_pair_list(
        rs.to_srvf(trees, weights=W), I, J, W, rs.RegistrationOptions(), chunk_size=4, progress=False, desc="",
        keep_warps=True,
    )  # fmt: skip
    assert [w.shape for w in regs.child_warps] == [regs.child_permutations[0].shape + (12,)]
    np.testing.assert_allclose(np.asarray(learn._d2_thickness(W, trees, regs)), regs.energy, rtol=1e-10)


# --------------------------------------------------------------------------------------------
# The inner problem with per-order weights


def order_problem(rng, n=12, n_classes=3):
    """Unit energies of depth-3 pairs (main, lateral and position of orders 1 and 2) where the
    second-order positions carry the class signal and the main root swamps it at the start."""
    y = np.repeat(np.arange(n_classes), n // n_classes)
    li, lj = np.triu_indices(n, 1)
    P = len(li)
    E = np.abs(rng.normal(size=(P, 5))) * np.array([100.0, 0.2, 0.2, 0.2, 0.0])
    E[:, 4] = np.where(y[li] != y[lj], 1.0, 0.3) + 0.5 * np.abs(rng.normal(size=P))
    start = Weights(main=0.02, lateral=1.0, position=1.0, thickness=0.0, deeper=((1.0, 1.0),))
    regs = learn.PairRegistrations(
        li, lj, np.zeros((P, 1), np.int64), *(np.zeros((P, 1)),) * 3, E @ np.array([0.02, 1, 1, 1, 1]), E
    )
    problem = learn._Problem(
        names=learn._learned_names(False, 1),
        start=start,
        log0=jnp.log(jnp.asarray([0.02, 1.0, 1.0, 1.0])),
        local_i=jnp.asarray(li),
        local_j=jnp.asarray(lj),
        same=jnp.asarray((y[:, None] == y[None, :]) & ~np.eye(n, dtype=bool)),
        n=n,
        regularisation=1e-3,
        softness=0.3,
        depth=3,
    )
    return regs, problem


def test_per_order_loss_gradient_matches_finite_differences():
    regs, problem = order_problem(np.random.default_rng(1))
    assert problem.names == ("main", "position", ("deeper", 0, 0), ("deeper", 0, 1))
    theta = jnp.log(jnp.asarray([0.1, 0.5, 2.0, 0.7]))
    g = np.asarray(jax.grad(learn.learn_loss)(theta, problem, None, regs))
    for k in range(4):
        e = np.zeros(4)
        e[k] = 1e-6
        fd = (float(learn.learn_loss(theta + e, problem, None, regs)) - float(learn.learn_loss(theta - e, problem, None, regs))) / 2e-6  # fmt: skip
        assert g[k] == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_inner_solve_upweights_the_order_with_the_signal():
    regs, problem = order_problem(np.random.default_rng(2))
    fitter = learn._Fitter(None, problem.start, None, False, chunk_size=1, progress=False, regularisation=1e-3,
                           softness=0.3, max_steps=200, rtol=1e-8)  # fmt: skip
    theta, loss, _ = fitter.solve(problem, regs, problem.log0)
    assert loss < float(learn.learn_loss(problem.log0, problem, None, regs))
    lam = dict(zip(problem.names, np.exp(np.asarray(theta))))
    # Second-order positions up, against the main root and against first-order positions.
    assert lam[("deeper", 0, 1)] / lam["main"] > 10 / 0.02
    assert lam[("deeper", 0, 1)] > 5 * lam["position"]
    W = learn._weights_of(problem.names, theta, problem.start)
    assert float(W.deeper[0][1]) == pytest.approx(lam[("deeper", 0, 1)]) and float(W.lateral) == 1.0


# --------------------------------------------------------------------------------------------
# Correspondences at every level


def set_correspondence(masks_a, masks_b, perm, child_perm):
    """Reference: the matched (branch of a, branch of b) pairs, both real, at levels 1 and 2."""
    out = {((i,), (int(perm[i]),)) for i in range(len(perm)) if masks_a[0][i] and masks_b[0][perm[i]]}
    for i, j in itertools.product(range(child_perm.shape[0]), range(child_perm.shape[1])):
        pi, pj = int(perm[i]), int(child_perm[i, j])
        if masks_a[1][i, j] and masks_b[1][pi, pj]:
            out.add(((i, j), (pi, pj)))
    return out


def test_correspondence_changed_at_depth_3_matches_a_set_reference():
    rng = np.random.default_rng(8)
    n, K1, K2, P = 5, 4, 3, 60
    m1 = rng.random((n, K1)) < 0.7
    m2 = (rng.random((n, K1, K2)) < 0.5) & m1[..., None]
    first, second = rng.integers(0, n, P), rng.integers(0, n, P)

    def regs(perm, child):
        return learn.PairRegistrations(
            first, second, perm, *(np.zeros((P, 1)),) * 4, np.zeros((P, 5)), child_permutations=(child,)
        )

    perm = np.stack([rng.permutation(K1) for _ in range(P)])
    child = np.stack([np.stack([rng.permutation(K2) for _ in range(K1)]) for _ in range(P)])
    new = child.copy()
    for p in range(P):
        i = rng.integers(K1)
        if p % 3 == 0:  # shuffle the null children of b under a's slot i: no change
            nulls = np.flatnonzero(~m2[second[p], perm[p, i]][new[p, i]])
            new[p, i, nulls] = new[p, i, rng.permutation(nulls)]
        else:
            j, k = rng.choice(K2, 2, replace=False)
            new[p, i, [j, k]] = new[p, i, [k, j]]
    got = learn.correspondence_changed(regs(perm, child), regs(perm, new), (m1, m2))
    ref = [
        set_correspondence((m1[first[p]], m2[first[p]]), (m1[second[p]], m2[second[p]]), perm[p], child[p])
        != set_correspondence((m1[first[p]], m2[first[p]]), (m1[second[p]], m2[second[p]]), perm[p], new[p])
        for p in range(P)
    ]
    np.testing.assert_array_equal(got, ref)
    assert not got[::3].any() and got.any()
    # Level 1 alone (the masks of one level) ignores the children.
    assert not learn.correspondence_changed(regs(perm, child), regs(perm, new), m1).any()


# --------------------------------------------------------------------------------------------
# End to end


def order2_signal_roots(n_per_class=4, seed=0):
    """Two classes that differ only in where the second-order laterals attach on their
    (identical) parents; the main roots bend at random (class-free noise)."""
    rng = np.random.default_rng(seed)
    roots, labels = [], []
    for cls, frac in enumerate((0.25, 0.7)):
        for _ in range(n_per_class):
            main = smooth_curve(rng, n=60, bend=2.5)
            lats, kids = [], []
            for f in (0.3, 0.6):
                base = point_at(main, f)
                lat = base + np.linspace(0, 0.35, 20)[:, None] * np.array([[1.0, 0.3]])
                g = frac + 0.03 * rng.normal()
                sub = point_at(lat, g) + np.linspace(0, 0.1, 8)[:, None] * np.array([[-0.3, 1.0]])
                lats.append(lat)
                kids.append(Root(main=lat, laterals=(sub,), attach=np.array([g])))
            roots.append(Root(main=main, laterals=tuple(lats), children=tuple(kids)))
            labels.append(f"c{cls}")
    return roots, labels


def test_learning_per_order_weights_finds_the_second_order_signal():
    roots, labels = order2_signal_roots()
    trees = rs.batch(roots, depth=3, n_points=16, normalise_scale=True, dtype=np.float64)
    start = Weights(deeper=((1.0, 1.0),))
    res = rs.learn_weights(trees, labels, weights=start, progress=False, max_reregistrations=2)
    w = res.weights
    assert len(w.deeper) == 1 and float(w.lateral) == 1.0
    assert float(w.deeper[0][1]) / float(w.main) > 2 * (1.0 / 0.02)
    assert res.loss_trace[-1] < res.loss_trace[0]
    # The returned matrix is the engine's at the learned weights, every order included.
    D = np.asarray(rs.pairwise_distances(trees, weights=w, progress=False))
    np.testing.assert_allclose(res.distances, D, rtol=1e-10, atol=1e-12)
    assert w.to_dict()["position_order2"] == float(w.deeper[0][1])


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED_DATA / "rsml" / "arabidopsis_plate").is_dir(), reason="shared data absent")
def test_real_plate_one_axis_plants_learn_the_taproots_weights():
    """Real seedlings (Arabidopsis plate, label = date): read per plant, each plant is a system
    of one axis, which must learn exactly the weights its taproot learns at one level less."""
    taproots, plants, labels = [], [], []
    for f in sorted((SHARED_DATA / "rsml" / "arabidopsis_plate").glob("*.rsml"))[:2]:
        taproots += read_rsml(f)[:4]
        plants += read_rsml(f, by="plant")[:4]
        labels += [f.name[:16]] * 4
    t = rs.batch(taproots, n_points=16, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deeper orders than kept: none here, but say nothing
        p = rs.batch(plants, n_points=16, depth=3, max_children=(1, t.mask.shape[1]), dtype=np.float64)
    assert p.virtual_main
    a = rs.learn_weights(t, labels, progress=False, max_reregistrations=2)
    b = rs.learn_weights(p, labels, progress=False, max_reregistrations=2)
    for k in ("main", "position"):
        assert float(b.weights[k]) == pytest.approx(float(a.weights[k]), rel=1e-6)
    assert float(a.weights.main) != pytest.approx(0.02, rel=1e-3)  # something was learned
    np.testing.assert_allclose(b.loss_trace, a.loss_trace, rtol=1e-8)
    np.testing.assert_allclose(b.distances, a.distances, rtol=1e-8, atol=1e-10)
