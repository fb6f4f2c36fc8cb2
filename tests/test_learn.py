"""Learning the metric weights (docs/design.md §12): loss, gradient, synthetic signal, errors."""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import smooth_curve

import rootshape_jax as rs
import rootshape_jax._learn as learn
from rootshape_jax import LabelError, Root, Weights
from rootshape_jax._executor import LocalExecutor
from rootshape_jax._learn import PairRegistrations, learn_loss, nca_loss, stratified_folds


def numpy_nca(D2: np.ndarray, y: np.ndarray, tau: float) -> float:
    """The NCA log-loss written out with loops (reference)."""
    n = len(y)
    total, count = 0.0, 0
    for i in range(n):
        others = [j for j in range(n) if j != i]
        w = np.array([np.exp(-D2[i, j] / tau) for j in others])
        p = w / w.sum()
        p_same = sum(pk for pk, j in zip(p, others) if y[j] == y[i])
        if any(y[j] == y[i] for j in others):
            total += -np.log(p_same)
            count += 1
    return total / count


def fake_problem(rng, n=9, n_classes=3, signal="position"):
    """Unit energies (no registration) where one term carries the class signal."""
    y = np.repeat(np.arange(n_classes), n // n_classes)
    li, lj = np.triu_indices(n, 1)
    P = len(li)
    # main: noise that swamps the signal at λ_main = 0.02; the signal overlaps a little, so
    # that the loss has a finite optimum (separable classes send τ to 0).
    E = np.abs(rng.normal(size=(P, 3))) * np.array([100.0, 0.2, 0.2])
    between = y[li] != y[lj]
    col = ("main", "lateral", "position").index(signal)  # the columns at depth 2
    E[:, col] = np.where(between, 1.0, 0.3) + 0.5 * np.abs(rng.normal(size=P))
    regs = PairRegistrations(
        first=li,
        second=lj,
        permutation=np.zeros((P, 1), np.int64),
        rotation=np.zeros((P, 2, 2)),
        main_warp=np.zeros((P, 2)),
        lateral_warps=np.zeros((P, 1, 2)),
        energy=E @ np.array([0.02, 1.0, 1.0]),
        unit_energies=E,
    )
    same = (y[:, None] == y[None, :]) & ~np.eye(n, dtype=bool)
    problem = learn._Problem(
        names=("main", "position"),
        start=Weights(main=0.02, lateral=1.0, position=1.0, thickness=0.0),
        log0=jnp.log(jnp.asarray([0.02, 1.0])),
        local_i=jnp.asarray(li),
        local_j=jnp.asarray(lj),
        same=jnp.asarray(same),
        n=n,
        regularisation=1e-3,
        softness=0.3,
    )
    return y, E, regs, problem


def test_inner_loss_matches_numpy_reference():
    rng = np.random.default_rng(0)
    y, E, regs, problem = fake_problem(rng)
    theta = np.array([np.log(0.3), np.log(2.0)])
    lam = np.array([0.3, 1.0, 2.0])
    d2 = E @ lam
    D2 = np.zeros((len(y), len(y)))
    D2[problem.local_i, problem.local_j] = d2
    D2 = D2 + D2.T
    penalty = 1e-3 * ((np.log(0.3) - np.log(0.02)) ** 2 + (np.log(2.0) - 0.0) ** 2)
    expected = numpy_nca(D2, y, 0.3 * d2.mean()) + penalty
    got = float(learn_loss(jnp.asarray(theta), problem, None, regs))
    assert got == pytest.approx(expected, rel=1e-12)


def test_nca_loss_skips_roots_without_a_partner():
    D2 = np.array([[0, 1.0, 4.0], [1.0, 0, 2.0], [4.0, 2.0, 0]])
    y = np.array([0, 0, 1])
    same = (y[:, None] == y[None, :]) & ~np.eye(3, dtype=bool)
    assert float(nca_loss(jnp.asarray(D2), jnp.asarray(same), 1.3)) == pytest.approx(numpy_nca(D2, y, 1.3), rel=1e-12)


def test_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    _, _, regs, problem = fake_problem(rng)
    theta = jnp.asarray([np.log(0.1), np.log(0.5)])
    g = np.asarray(jax.grad(learn_loss)(theta, problem, None, regs))
    h = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fd = (float(learn_loss(theta + e, problem, None, regs)) - float(learn_loss(theta - e, problem, None, regs))) / (
            2 * h
        )
        assert g[k] == pytest.approx(fd, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("signal", ["main", "position"])
def test_inner_solve_upweights_the_term_with_the_signal(signal):
    rng = np.random.default_rng(2)
    y, E, regs, problem = fake_problem(rng, n=12, signal=signal)
    if signal == "main":  # the noise goes to position instead
        E[:, 2] = np.abs(rng.normal(size=len(E))) * 5.0
        regs = eqx.tree_at(lambda r: r.unit_energies, regs, E)
    fitter = learn._Fitter(None, Weights(), None, False, chunk_size=1, progress=False, regularisation=1e-3, softness=0.3,
                           max_steps=200, rtol=1e-8)  # fmt: skip
    theta0 = jnp.asarray([np.log(0.02), 0.0])
    theta, loss, steps = fitter.solve(problem, regs, theta0)
    assert loss < float(learn_loss(theta0, problem, None, regs))
    lam_main, lam_pos = np.exp(np.asarray(theta[:2]))
    ratio0 = 1.0 / 0.02
    if signal == "position":
        assert lam_pos / lam_main > 10 * ratio0
    else:
        assert lam_main / lam_pos > 10 / ratio0


# --------------------------------------------------------------------------------------------
# Real registrations


def point_at(main, f):
    seg = np.linalg.norm(np.diff(main, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    return np.array([np.interp(f, s, main[:, k]) for k in range(main.shape[1])])


def position_signal_roots(n_per_class=4, seed=0):
    """Two classes that differ only in where two identical laterals attach; the main roots
    bend at random (class-free noise)."""
    rng = np.random.default_rng(seed)
    roots, labels = [], []
    for cls, fracs in enumerate(([0.2, 0.45], [0.45, 0.7])):
        for _ in range(n_per_class):
            main = smooth_curve(rng, n=60, bend=2.5)
            lats = []
            for f in fracs:
                base = point_at(main, f + 0.02 * rng.normal())
                t = np.linspace(0, 0.35, 20)[:, None]
                lats.append(base + t * np.array([[1.0, 0.3]]))
            roots.append(Root(main=main, laterals=tuple(lats)))
            labels.append(f"c{cls}")
    return roots, labels


def test_learned_weights_up_weight_position_and_reproduce_the_matrix():
    roots, labels = position_signal_roots()
    trees = rs.batch(roots, n_points=24, normalise_scale=True, dtype=np.float64)
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=2)
    w = res.weights
    assert float(w.position) / float(w.main) > 2 * (1.0 / 0.02)
    assert float(w.lateral) == 1.0
    assert res.status in ("converged", "loss", "max_reregistrations")
    assert 1 <= res.n_reregistrations <= 2
    assert len(res.loss_trace) == res.n_reregistrations + 1
    assert 1 <= len(res.inner_loss_trace) <= res.n_reregistrations  # one per solve; steps back add registrations
    assert len(res.changed_pairs) == len(res.registration_gain) == res.n_reregistrations
    assert min(res.loss_trace) < res.loss_trace[0]
    # The returned matrix is the engine's at the learned weights.
    D = np.asarray(rs.pairwise_distances(trees, weights=w, progress=False))
    np.testing.assert_allclose(res.distances, D, rtol=1e-10, atol=1e-12)
    # Printed, the result shows the learned numbers, not equinox's dtype summaries.
    text = repr(res)
    assert f"main={float(w.main):.6g}" in text and f"status={res.status!r}" in text
    assert f"{res.loss_trace[-1]:.4g}" in text and "weak_f32" not in text and "f64[]" not in text


@pytest.mark.slow
def test_thickness_path_gradient_and_agreement_with_linear_path():
    rng = np.random.default_rng(3)
    roots = []
    for _ in range(4):
        main = smooth_curve(rng, n=40, bend=1.0)
        lat = point_at(main, 0.3 + 0.2 * rng.random()) + np.linspace(0, 0.3, 15)[:, None] * np.array([[1.0, 0.2]])
        r_main = np.linspace(0.05, 0.01 + 0.02 * rng.random(), 40)
        r_lat = np.linspace(0.02, 0.005, 15)
        roots.append(Root(main=main, laterals=(lat,), main_radius=r_main, lateral_radii=(r_lat,)))
    y = np.array([0, 0, 1, 1])
    trees = rs.batch(roots, n_points=16, dtype=np.float64)
    W = Weights(main=0.05, lateral=1.0, position=0.5, thickness=2.0)
    I, J = np.triu_indices(4, 1)
    regs = learn.register_pair_list(
        rs.to_srvf(trees, weights=W), I, J, W, rs.RegistrationOptions(), chunk_size=8, progress=False, desc=""
    )
    same = (y[:, None] == y[None, :]) & ~np.eye(4, dtype=bool)
    problem = learn._Problem(
        names=("main", "position", "thickness"),
        start=W,
        log0=jnp.log(jnp.asarray([0.05, 0.5, 2.0])),
        local_i=jnp.asarray(I),
        local_j=jnp.asarray(J),
        same=jnp.asarray(same),
        n=4,
        regularisation=1e-3,
        softness=0.3,
    )
    theta = jnp.log(jnp.asarray([0.05, 0.5, 2.0]))
    # At the registration's own λ the fixed-registration d² is the engine's energy.
    d2 = learn._d2_thickness(W, trees, regs)
    np.testing.assert_allclose(np.asarray(d2), regs.energy, rtol=1e-10)
    g = np.asarray(jax.grad(learn_loss)(theta, problem, trees, regs))
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (
            float(learn_loss(theta + e, problem, trees, regs)) - float(learn_loss(theta - e, problem, trees, regs))
        ) / (2 * h)
        assert g[k] == pytest.approx(fd, rel=1e-5, abs=1e-8)


# --------------------------------------------------------------------------------------------
# Re-registration through the executor, and when the alternation stops


def test_register_pair_list_same_on_any_executor_and_block_size():
    roots, _ = position_signal_roots(n_per_class=3, seed=4)
    trees = rs.batch(roots, n_points=16, normalise_scale=True, dtype=np.float64)
    W = Weights()
    s = rs.to_srvf(trees, weights=W)
    I, J = np.triu_indices(6, 1)  # 15 pairs: chunks of 4 leave a padded last chunk
    opts = rs.RegistrationOptions()
    kw = dict(chunk_size=4, progress=False, desc="")
    one = learn.register_pair_list(s, I, J, W, opts, client=LocalExecutor(workers=1), **kw)
    two = learn.register_pair_list(s, I, J, W, opts, client=LocalExecutor(workers=2), block_size=8, **kw)
    for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(two)):
        np.testing.assert_array_equal(x, y)
    # The energies are the engine's distances, and the unit energies rebuild them at λ.
    D = np.asarray(rs.pairwise_distances(trees, weights=W, progress=False))
    np.testing.assert_allclose(np.sqrt(one.energy), D[I, J], rtol=1e-10)
    lam = np.array([W.main, W.lateral, W.position])
    np.testing.assert_allclose(one.unit_energies @ lam, one.energy, rtol=1e-10)
    with pytest.raises(ValueError, match="multiple of chunk_size"):
        learn.register_pair_list(s, I, J, W, opts, block_size=6, **kw)


def set_correspondence(first_mask, second_mask, perm):
    """Reference: the set of (slot of the first root, slot of the second) both real."""
    return {(k, int(perm[k])) for k in range(len(perm)) if first_mask[k] and second_mask[perm[k]]}


def test_correspondence_changed_matches_a_set_reference():
    rng = np.random.default_rng(7)
    n, K, P = 5, 6, 40
    mask = rng.random((n, K)) < 0.5
    first = rng.integers(0, n, P)
    second = rng.integers(0, n, P)

    def regs(perm, first=first):
        return PairRegistrations(first, second, perm, *(np.zeros((P, 1)),) * 4, np.zeros((P, 3)))

    old = np.stack([rng.permutation(K) for _ in range(P)])
    new = old.copy()
    for p in range(P):  # shuffle null slots of the second root only, or swap two slots at random
        if p % 2:
            nulls = np.flatnonzero(~mask[second[p]][new[p]])
            new[p, nulls] = new[p, rng.permutation(nulls)]
        else:
            i, j = rng.choice(K, 2, replace=False)
            new[p, [i, j]] = new[p, [j, i]]
    got = learn.correspondence_changed(regs(old), regs(new), mask)
    ref = [
        set_correspondence(mask[first[p]], mask[second[p]], old[p])
        != set_correspondence(mask[first[p]], mask[second[p]], new[p])
        for p in range(P)
    ]
    np.testing.assert_array_equal(got, ref)
    assert not got[1::2].any() and got.any()
    flipped = first.copy()
    flipped[0] = (first[0] + 1) % n
    assert learn.correspondence_changed(regs(old), regs(old, first=flipped), mask)[0]


def test_alternation_stops_when_correspondences_settle():
    roots, labels = position_signal_roots()
    trees = rs.batch(roots, n_points=24, normalise_scale=True, dtype=np.float64)
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=6, tol=0.0)
    assert res.status == "converged"
    assert res.n_reregistrations < 6 and res.changed_pairs[-1] == 0
    assert np.all(res.registration_gain >= -1e-9)  # registering again never does worse than before


def _scramble_registrations(monkeypatch, scramble) -> list:
    """Make `_Fitter.register`'s k-th call (1-based) return registrations that destroy the class
    signal where ``scramble(k)`` (shuffled energies, so the loss goes up; correspondences
    changed, so that the alternation does not stop as settled). Returns the list of the
    weights of every call, filled as the fit runs."""
    calls = []
    real = learn._Fitter.register

    def register(self, weights, I, J, desc):
        regs = real(self, weights, I, J, desc)
        calls.append(weights)
        if not scramble(len(calls)):
            return regs
        E = np.random.default_rng(0).permutation(regs.unit_energies)
        perm = np.roll(regs.permutation, 1, axis=1)
        return eqx.tree_at(
            lambda r: (r.unit_energies, r.energy, r.permutation), regs, (E, E @ np.array([0.02, 1.0, 1.0]), perm)
        )

    monkeypatch.setattr(learn._Fitter, "register", register)
    return calls


def _assert_halfway(calls, best: int, last: int, tried: int):
    """The `tried`-th registration's λ is halfway in log λ between the `best`-th and `last`-th."""
    for term in ("main", "position"):
        half = 0.5 * (np.log(float(getattr(calls[best], term))) + np.log(float(getattr(calls[last], term))))
        assert np.log(float(getattr(calls[tried], term))) == pytest.approx(half, rel=1e-6)


def test_a_worse_re_registration_stops_and_keeps_the_best(monkeypatch):
    roots, labels = position_signal_roots()
    trees = rs.batch(roots, n_points=24, normalise_scale=True, dtype=np.float64)
    calls = _scramble_registrations(monkeypatch, lambda k: k > 1)  # every re-registration
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=6)
    # The solve's λ, then halfway back toward the start twice: every one worse, so it stops.
    assert res.status == "loss" and res.n_reregistrations == 1 + learn._STEPS_BACK == 3
    assert np.all(res.loss_trace[1:] > res.loss_trace[0])
    assert len(res.loss_trace) == 4 and len(res.changed_pairs) == len(res.registration_gain) == 3
    assert len(res.inner_loss_trace) == 1
    assert res.weights == Weights()  # the start: the best entry of the trace
    assert res.kept().tolist() == [True, False, False, False]
    D = np.asarray(rs.pairwise_distances(trees, progress=False))
    np.testing.assert_allclose(res.distances, D, rtol=1e-10, atol=1e-12)
    # Each step back is halfway in log λ between the best (the start) and the last λ tried.
    for k in (2, 3):
        _assert_halfway(calls, 0, k - 1, k)
    # A budget that ends before the steps back do: the fit says so, and keeps the start.
    calls.clear()
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=2)
    assert res.status == "max_reregistrations" and res.n_reregistrations == 2 and len(res.loss_trace) == 3
    assert res.weights == Weights()


def test_kept_is_the_fits_rule():
    """The start, then each entry strictly below the best before it (a tie is not kept; the
    best so far, not the previous entry, is the bar); a NaN loss is never below anything."""
    zeros = np.zeros(0)

    def kept(trace):
        return learn.LearnedWeights(
            weights=Weights(), softness=0.1, loss_trace=np.asarray(trace), inner_loss_trace=zeros,
            status="loss", steps=0, n_reregistrations=len(trace) - 1, distances=np.zeros((2, 2)),
            changed_pairs=zeros, registration_gain=zeros, regularisation=0.0, regularisation_scores=None,
        ).kept().tolist()  # fmt: skip

    assert kept([1.0, 2, 1.5, 0.9, 0.95, 0.9, 0.8]) == [True, False, False, True, False, False, True]
    assert kept([1.0]) == [True]
    assert kept([1.0, np.nan, 0.5]) == [True, False, True]
    assert kept([np.nan, 1.0, 0.5]) == [True, False, False]  # the fit keeps the start then


def test_a_step_back_that_lowers_the_loss_is_kept(monkeypatch):
    """The solve's λ overshoots (its fresh registrations are scrambled, so the loss goes up);
    the λ halfway back registers normally, beats the start and the fit goes on from it."""
    roots, labels = position_signal_roots()
    trees = rs.batch(roots, n_points=24, normalise_scale=True, dtype=np.float64)
    calls = _scramble_registrations(monkeypatch, lambda k: k == 2)  # the first solve's λ
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=3, tol=0.0)
    assert res.loss_trace[1] > res.loss_trace[0] > res.loss_trace[2]
    assert res.n_reregistrations >= 2 and res.weights != Weights()
    # The third registration was at the λ halfway (log scale) between the start and the solve's.
    _assert_halfway(calls, 0, 1, 2)
    # The overshoot is the one try not kept, and what is returned is the last kept entry.
    kept = res.kept()
    assert kept[:3].tolist() == [True, False, True]
    assert calls[np.flatnonzero(kept)[-1]] == res.weights
    # Whatever is returned is the best entry of the trace, with its own registrations.
    D = np.asarray(rs.pairwise_distances(trees, weights=res.weights, progress=False))
    np.testing.assert_allclose(res.distances, D, rtol=1e-6)
    # The fit went on from the accepted step back: a second solve.
    assert len(res.inner_loss_trace) == 2 or res.status == "converged"


def test_a_step_back_starts_from_the_best_lambda_so_far(monkeypatch):
    """When the best λ is not the start (a first solve accepted), a later overshoot steps back
    toward that best λ, not toward the start."""
    roots, labels = position_signal_roots()
    trees = rs.batch(roots, n_points=24, normalise_scale=True, dtype=np.float64)
    calls = _scramble_registrations(monkeypatch, lambda k: k == 3)  # the second solve's λ
    # Every re-registration counts as re-matching pairs, and the second solve moves λ, so the
    # fit does not stop as settled before the overshoot.
    monkeypatch.setattr(learn, "correspondence_changed", lambda old, new, masks: np.ones(len(new.energy), bool))
    real_solve = learn._Fitter.solve
    solves = []

    def moving_solve(self, problem, regs, theta0):
        theta, loss, k = real_solve(self, problem, regs, theta0)
        solves.append(theta)
        return (theta + 0.5 if len(solves) == 2 else theta), loss, k

    monkeypatch.setattr(learn._Fitter, "solve", moving_solve)
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=4, tol=0.0)
    assert res.loss_trace[1] < res.loss_trace[0]  # the first solve's λ was accepted: the best
    assert res.loss_trace[2] > res.loss_trace[1]  # the second solve's (scrambled) was not
    assert res.kept()[:3].tolist() == [True, True, False]
    assert len(calls) >= 4
    _assert_halfway(calls, 1, 2, 3)


def numpy_held_out_loss(D2, y, folds, softness):
    """Reference: inner-CV held-out NCA log-loss of a fixed squared-distance matrix."""
    total = 0.0
    for test in folds:
        train = np.setdiff1d(np.arange(len(y)), test)
        tau = softness * np.mean(D2[np.ix_(train, train)][np.triu_indices(len(train), 1)])
        for i in test:
            w = np.exp(-D2[i, train] / tau)
            total += -np.log(w[y[train] == y[i]].sum() / w.sum())
    return total / len(y)


def test_regularisation_chosen_by_inner_cv():
    roots, labels = position_signal_roots(n_per_class=4, seed=2)
    y = np.asarray(labels)
    trees = rs.batch(roots, n_points=20, normalise_scale=True, dtype=np.float64)
    opts = rs.RegistrationOptions()
    fitter = learn._Fitter(trees, Weights(), opts, False, chunk_size=8, progress=False, regularisation=(1e-3, 1e4),
                           max_steps=200, rtol=1e-8, softness=0.3)  # fmt: skip
    I, J = np.triu_indices(8, 1)
    regs = fitter.register(Weights(), I, J, "")
    r, scores = fitter.choose_regularisation(y, regs)
    # A huge penalty keeps λ at the start: its score is the start matrix's held-out loss.
    D2 = np.zeros((8, 8))
    D2[I, J] = D2[J, I] = regs.energy
    ref = numpy_held_out_loss(D2, y, stratified_folds(y, 3, seed=0), 0.3)
    assert scores[1] == pytest.approx(ref, rel=1e-3)
    # The class signal is in the positions: learning λ lowers the held-out loss, so the weak
    # penalty wins; with equal scores the strong one would.
    assert scores[0] < scores[1] and r == 1e-3
    res = rs.learn_weights(trees, labels, progress=False, max_reregistrations=1, regularisation=[1e4, 1e-3])
    assert res.regularisation == 1e-3 and res.regularisation_scores.shape == (2,)
    with pytest.raises(ValueError, match="regularisation"):
        rs.learn_weights(trees, labels, progress=False, regularisation=[-1.0])


# --------------------------------------------------------------------------------------------
# Folds and cross-validation


def test_stratified_folds_partition_and_balance():
    y = np.array(list("aaaaabbbbbbbccc"))
    folds = stratified_folds(y, 3, seed=4)
    assert np.array_equal(np.sort(np.concatenate(folds)), np.arange(len(y)))
    for cls in "abc":
        counts = [int(np.sum(y[f] == cls)) for f in folds]
        assert max(counts) - min(counts) <= 1
    assert max(map(len, folds)) - min(map(len, folds)) <= 1
    assert all(np.array_equal(a, b) for a, b in zip(folds, stratified_folds(y, 3, seed=4)))


def test_fold_accuracy_reference():
    rng = np.random.default_rng(5)
    X = np.concatenate([rng.normal(0, 1, (6, 2)), rng.normal(3, 1, (6, 2))])
    y = np.repeat([0, 1], 6)
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    acc = rs.fold_accuracy(D, y, n_folds=3, seed=0)
    for k, test in enumerate(stratified_folds(y, 3, seed=0)):
        train = np.setdiff1d(np.arange(12), test)
        nn = [y[train][np.argmin(D[i, train])] for i in test]
        means = [X[train][y[train] == c].mean(0) for c in (0, 1)]  # Euclidean: exact class means
        nm = [int(np.argmin([np.linalg.norm(X[i] - m) for m in means])) for i in test]
        assert acc["nn"][k] == pytest.approx(np.mean(np.array(nn) == y[test]))
        assert acc["mean"][k] == pytest.approx(np.mean(np.array(nm) == y[test]))


def test_fold_accuracy_repeats_are_the_seeds_in_turn():
    rng = np.random.default_rng(6)
    X = np.concatenate([rng.normal(0, 1, (7, 2)), rng.normal(1.5, 1, (8, 2))])
    y = np.repeat(["a", "b"], [7, 8])
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    got = rs.fold_accuracy(D, y, n_folds=np.int64(3), seed=np.int64(4), n_repeats=np.int64(3))
    parts = [rs.fold_accuracy(D, y, n_folds=3, seed=s) for s in (4, 5, 6)]
    for key in ("nn", "mean", "log_loss"):
        np.testing.assert_array_equal(got[key], np.concatenate([p[key] for p in parts]))
    # Different seeds split differently (else the repeats would add nothing).
    assert not all(np.array_equal(a, b) for a, b in zip(stratified_folds(y, 3, seed=4), stratified_folds(y, 3, seed=5)))
    for bad in (0, 1.5, True, -1):
        with pytest.raises(ValueError, match="n_repeats"):
            rs.fold_accuracy(D, y, n_folds=3, n_repeats=bad)
    with pytest.raises(ValueError, match="n_folds"):
        rs.fold_accuracy(D, y, n_folds=1)


def test_fold_comparison_counts_folds_by_direction():
    zeros = np.zeros(4)
    cv = learn.CVAccuracy(
        learned_nn=np.array([1.0, 0.5, 1.0, 1.0]),
        learned_mean=np.array([0.5, 0.5, 0.5, 0.25]),
        paper_nn=np.array([0.75, 0.75, 0.75, 1.0]),
        paper_mean=np.array([0.5, 0.5, 0.5, 0.5]),
        # log-loss: lower is better; within a relative 1e-4 is a tie, however small the loss.
        learned_log_loss=np.array([0.1, 0.3, 0.20000001, 1e-6]),
        paper_log_loss=np.array([0.2, 0.2, 0.2, 2e-6]),
        weights=[{}] * 4,
        folds=[np.arange(2)] * 4,
        n_reregistrations=zeros,
        status=("converged",) * 4,
        seconds_learning=zeros,
        regularisation=zeros,
        repeats=np.array([0, 0, 1, 1]),
    )
    assert cv.fold_comparison() == {"nn": (2, 1, 1), "mean": (0, 3, 1), "log_loss": (2, 1, 1)}
    assert learn.fold_better([0.3, 0.1], [0.2, 0.2], higher_is_better=True) == (1, 0, 1)
    assert learn.fold_better([0.3, 0.1], [0.2, 0.2], higher_is_better=False) == (1, 0, 1)
    assert learn.fold_better([0.3, 0.2], [0.2, 0.2], higher_is_better=False) == (0, 1, 1)
    with pytest.raises(ValueError, match="differ in shape"):
        learn.fold_better([0.3], [0.2, 0.2], higher_is_better=True)
    assert "2 repeats × 2 folds" in repr(cv) and "log_loss 2/1/1" in repr(cv)
    # t_tests: k = folds per repetition (4 folds over 2 repeats: k = 2), learned − paper.
    tests = cv.t_tests()
    assert tests["log_loss"] == rs.fold_t_test(cv.learned_log_loss, cv.paper_log_loss, n_folds=2)
    assert tests["nn"].difference == pytest.approx(np.mean(cv.learned_nn - cv.paper_nn))
    assert f"log_loss {tests['log_loss'].p_value:.3g}" in repr(cv)


def reference_fold_t_test(a, b, k):
    """The corrected resampled t-test written out (Nadeau & Bengio 2003; Bouckaert & Frank
    2004): loops for the moments, the two-sided Student-t tail as a regularised incomplete
    beta function, ``p = I_{ν/(ν+t²)}(ν/2, 1/2)``."""
    import scipy.special

    d = [x - y for x, y in zip(a, b)]
    n = len(d)
    mean = sum(d) / n
    var = sum((x - mean) ** 2 for x in d) / (n - 1)
    t = mean / math.sqrt((1 / n + 1 / (k - 1)) * var)
    nu = n - 1
    return mean, t, float(scipy.special.betainc(nu / 2, 0.5, nu / (nu + t * t)))


@pytest.mark.parametrize("n_folds, n_repeats", [(5, 1), (5, 3), (3, 4), (10, 2)])
def test_fold_t_test_reference_and_properties(n_folds, n_repeats):
    import scipy.stats

    rng = np.random.default_rng(n_folds * 10 + n_repeats)
    n = n_folds * n_repeats
    a = rng.uniform(0.1, 0.4, n)
    b = a + rng.normal(0.03, 0.05, n)
    test = rs.fold_t_test(a, b, n_folds=n_folds)
    mean, t, p = reference_fold_t_test(a, b, n_folds)
    assert test.n == n
    assert test.difference == pytest.approx(mean, rel=1e-12)
    assert test.t == pytest.approx(t, rel=1e-10)
    assert test.p_value == pytest.approx(p, rel=1e-8)
    # The correction only shrinks a plain paired t-test's statistic, by √((1/n) / (1/n + 1/(k−1))).
    plain = scipy.stats.ttest_rel(a, b)
    assert test.t == pytest.approx(plain.statistic * math.sqrt((1 / n) / (1 / n + 1 / (n_folds - 1))), rel=1e-10)
    assert test.p_value > plain.pvalue
    # Swapping the methods flips the sign only; a shift of both scores changes nothing.
    swapped = rs.fold_t_test(b, a, n_folds=n_folds)
    assert (swapped.difference, swapped.t) == pytest.approx((-test.difference, -test.t), rel=1e-12)
    assert swapped.p_value == pytest.approx(test.p_value, rel=1e-12)
    shifted = rs.fold_t_test(a + 3.0, b + 3.0, n_folds=n_folds)
    assert (shifted.t, shifted.p_value) == pytest.approx((test.t, test.p_value), rel=1e-9)


def test_fold_t_test_known_value_and_ties():
    # d = 1..5 over k = 5 folds: mean 3, var 2.5, t = 3 / √((1/5 + 1/4) · 2.5) = 2√2.
    known = rs.fold_t_test(np.arange(1.0, 6.0), np.zeros(5), n_folds=np.int64(5))
    assert known.t == pytest.approx(2 * math.sqrt(2), rel=1e-12)
    assert known.p_value == pytest.approx(0.047421, abs=1e-6)
    assert known.difference == 3.0 and known.n == 5
    same = rs.fold_t_test([1.0, 0.8, 1.0], [1.0, 0.8, 1.0], n_folds=3)
    assert (same.difference, same.t, same.p_value) == (0.0, 0.0, 1.0)
    # Folds equal within fold_better's relative 1e-4 are ties here too: a λ that stayed at the
    # start is no significant difference, however consistent its rounding.
    start = np.array([0.2, 0.3, 0.25, 0.4])
    rounding = rs.fold_t_test(start * (1 + 1e-6), start, n_folds=2)
    assert (rounding.t, rounding.p_value) == (0.0, 1.0) and rounding.difference > 0
    assert learn.fold_better(start * (1 + 1e-6), start, higher_is_better=True) == (0, 4, 0)
    # Every fold better by the same amount: no spread to test against, said as NaN (not p = 0),
    # also when the differences carry the scores' rounding (float64 and float32).
    for dtype in (np.float64, np.float32):
        a = np.array([2 / 3, 1.0, 2 / 3], dtype)
        b = np.array([1 / 3, 2 / 3, 1 / 3], dtype)
        constant = rs.fold_t_test(a, b, n_folds=3)
        assert constant.difference == pytest.approx(1 / 3, rel=1e-6)
        assert math.isnan(constant.t) and math.isnan(constant.p_value), dtype


def test_fold_t_test_counts_repeats_and_bad_input():
    assert rs.fold_t_test([0.1, 0.3, 0.2, 0.5, 0.4, 0.2], [0.2] * 6, n_folds=3).n == 6  # 2 repeats × 3
    with pytest.raises(ValueError, match="same length"):
        rs.fold_t_test([0.1, 0.2], [0.1, 0.2, 0.3], n_folds=2)
    with pytest.raises(ValueError, match="at least 2 folds"):
        rs.fold_t_test([0.1], [0.2], n_folds=2)
    with pytest.raises(rs.InputError, match="finite"):
        rs.fold_t_test([0.1, np.nan], [0.2, 0.3], n_folds=2)
    # k must divide the number of scores (k folds × repetitions).
    for bad in (1, 4, 2.0, True, np.bool_(True)):
        with pytest.raises(ValueError, match="n_folds"):
            rs.fold_t_test([0.1, 0.2, 0.3], [0.2, 0.3, 0.1], n_folds=bad)
    with pytest.raises(ValueError, match="divides"):
        rs.fold_t_test([0.1] * 7, [0.2] * 7, n_folds=3)


def _reference_log_loss(D_tt, D_tr, y_test, y_train, softness):
    # Plain loops, one test root at a time (float64 throughout).
    n = len(y_train)
    tau = softness * np.mean([D_tr[i, j] ** 2 for i in range(n) for j in range(i + 1, n)])
    out = []
    for x in range(len(y_test)):
        logits = [-(D_tt[x, j] ** 2) / tau for j in range(n)]
        top = max(logits)
        total = sum(math.exp(v - top) for v in logits)
        same = sum(math.exp(v - top) for v, c in zip(logits, y_train) if c == y_test[x])
        out.append(-math.log(same / total))
    return float(np.mean(out))


def test_held_out_log_loss_reference_and_invariances():
    rng = np.random.default_rng(7)
    X = np.concatenate([rng.normal(0, 1, (7, 3)), rng.normal(2, 1, (7, 3)), rng.normal(-2, 1, (6, 3))])
    y = np.repeat(["a", "b", "c"], [7, 7, 6])
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    test, train = np.array([0, 8, 15, 3]), np.setdiff1d(np.arange(20), [0, 8, 15, 3])
    args = (D[np.ix_(test, train)], D[np.ix_(train, train)], y[test], y[train])
    got = rs.held_out_log_loss(*args, softness=0.3)
    assert got == pytest.approx(_reference_log_loss(*args, 0.3), rel=1e-12)
    # The temperature is relative: the scale of the distances does not matter; nor the order
    # of the training roots.
    scaled = rs.held_out_log_loss(args[0] * 37.0, args[1] * 37.0, y[test], y[train], softness=0.3)
    assert scaled == pytest.approx(got, rel=1e-12)
    p = rng.permutation(len(train))
    shuffled = rs.held_out_log_loss(args[0][:, p], args[1][np.ix_(p, p)], y[test], y[train][p], softness=0.3)
    assert shuffled == pytest.approx(got, rel=1e-12)
    # Distances that carry no information score log(#classes) when classes are balanced.
    flat = rs.held_out_log_loss(np.ones((3, 6)), 1 - np.eye(6), np.array([0, 1, 2]), np.repeat([0, 1, 2], 2))
    assert flat == pytest.approx(math.log(3), rel=1e-12)
    # A held-out root far from its own class but near another: a large finite loss, not inf
    # (the same-class terms underflow exp in a naive sum).
    far = rs.held_out_log_loss(
        np.array([[40.0, 40.0, 0.1, 0.1]]), 1 - np.eye(4), np.array([0]), np.array([0, 0, 1, 1]), softness=0.1
    )
    assert np.isfinite(far) and far > 1000


def test_held_out_log_loss_extreme_scales_and_bad_input():
    rng = np.random.default_rng(8)
    X = rng.normal(size=(9, 2))
    y = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    test, train = np.array([0, 3, 6]), np.setdiff1d(np.arange(9), [0, 3, 6])
    args = (D[np.ix_(test, train)], D[np.ix_(train, train)], y[test], y[train])
    ref = rs.held_out_log_loss(*args)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow or divide warnings on the way
        for c in (1e160, 1e-160):
            assert rs.held_out_log_loss(args[0] * c, args[1] * c, y[test], y[train]) == pytest.approx(ref, rel=1e-12)
        rs.held_out_log_loss(np.array([[40.0, 40.0, 0.1, 0.1]]), 1 - np.eye(4), np.array([0]), np.array([0, 0, 1, 1]))
    nan = args[0].copy()
    nan[1, 2] = np.nan
    with pytest.raises(rs.InputError, match="finite"):
        rs.held_out_log_loss(nan, args[1], y[test], y[train])
    with pytest.raises(ValueError, match=r"D_test_train must be \[n_test, n_train\]"):
        rs.held_out_log_loss(args[0][:, :-1], args[1], y[test], y[train])
    with pytest.raises(ValueError, match="softness must be a positive number"):
        rs.held_out_log_loss(*args, softness=0.0)
    with pytest.raises(LabelError, match=r"without a training member \(7\)"):
        rs.held_out_log_loss(args[0], args[1], np.array([0, 1, 7]), y[train])
    with pytest.raises(ValueError, match="all at distance 0"):
        rs.held_out_log_loss(np.zeros((3, 6)), np.zeros((6, 6)), y[test], y[train])
    with pytest.raises(rs.InputError, match="fold_accuracy: distances must be finite"):
        rs.fold_accuracy(np.where(np.eye(9, dtype=bool), 0.0, np.nan), y, n_folds=3)


def test_fold_accuracy_log_loss_is_held_out_log_loss_per_fold():
    rng = np.random.default_rng(3)
    X = np.concatenate([rng.normal(0, 1, (6, 2)), rng.normal(2, 1, (6, 2))])
    y = np.repeat([0, 1], 6)
    D = np.linalg.norm(X[:, None] - X[None], axis=-1)
    acc = rs.fold_accuracy(D, y, n_folds=3, seed=2, softness=0.2)
    for k, test in enumerate(stratified_folds(y, 3, seed=2)):
        train = np.setdiff1d(np.arange(12), test)
        ref = _reference_log_loss(D[np.ix_(test, train)], D[np.ix_(train, train)], y[test], y[train], 0.2)
        assert acc["log_loss"][k] == pytest.approx(ref, rel=1e-12)


@pytest.mark.slow
def test_nested_cv_scores_the_paper_weights_like_fold_accuracy():
    roots, labels = position_signal_roots(n_per_class=4, seed=1)
    trees = rs.batch(roots, n_points=20, normalise_scale=True, dtype=np.float64)
    cv = rs.nested_cv_accuracy(trees, labels, n_folds=2, seed=0, n_repeats=2, progress=False, max_reregistrations=1)
    D = np.asarray(rs.pairwise_distances(trees, progress=False))
    # Two repetitions of 2 folds: the splits of seeds 0 and 1, in turn, every score on them.
    ref = rs.fold_accuracy(D, labels, n_folds=2, seed=0, n_repeats=2)
    np.testing.assert_array_equal(cv.repeats, [0, 0, 1, 1])
    want_folds = stratified_folds(labels, 2, seed=0) + stratified_folds(labels, 2, seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(cv.folds, want_folds))
    np.testing.assert_allclose(cv.paper_nn, ref["nn"])
    np.testing.assert_allclose(cv.paper_mean, ref["mean"])
    assert cv.learned_nn.shape == (4,) and np.all((cv.learned_nn >= 0) & (cv.learned_nn <= 1))
    assert all(w["lateral"] == 1.0 for w in cv.weights)
    np.testing.assert_allclose(cv.paper_log_loss, ref["log_loss"], rtol=1e-10)
    # The learned λ's score is on that fold's distances at its own λ (registered afresh).
    for f, test in enumerate(cv.folds):
        train = np.setdiff1d(np.arange(len(labels)), test)
        D_f = np.asarray(rs.pairwise_distances(trees, weights=Weights(**cv.weights[f]), progress=False))
        y = np.asarray(labels)
        want = rs.held_out_log_loss(D_f[np.ix_(test, train)], D_f[np.ix_(train, train)], y[test], y[train])
        assert cv.learned_log_loss[f] == pytest.approx(want, rel=1e-6)
    assert set(cv.summary()) == {
        "learned_nn",
        "learned_mean",
        "paper_nn",
        "paper_mean",
        "learned_log_loss",
        "paper_log_loss",
    }
    m, sd = cv.summary()["learned_nn"]
    assert f"learned_nn={100 * m:.1f} ± {100 * sd:.1f} %" in repr(cv) and "f64[" not in repr(cv)
    m, sd = cv.summary()["paper_log_loss"]
    assert f"paper_log_loss={m:.3f} ± {sd:.3f}" in repr(cv)


# --------------------------------------------------------------------------------------------
# Bad labels: named errors before any registration


@pytest.fixture
def no_registration(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("registered before checking the labels")

    monkeypatch.setattr(learn, "register_pair_list", refuse)


@pytest.mark.parametrize(
    "labels, match",
    [
        (["a"] * 6, "same label"),
        (["a", "a", "a", "b", "b", "c"], "have one member"),
        (["a", "a", "b", "b", "a"], "5 labels for 6 roots"),
        ([0.0, 0.0, 1.0, np.nan, 1.0, 1.0], "missing"),
        (["a", "a", None, "b", "b", "b"], "missing"),
    ],
)
def test_bad_labels_raise_before_registering(labels, match, no_registration):
    roots, _ = position_signal_roots(n_per_class=3)
    trees = rs.batch(roots, n_points=12, dtype=np.float64)
    with pytest.raises(LabelError, match=match):
        rs.learn_weights(trees, labels, progress=False)
    with pytest.raises(LabelError):
        rs.nested_cv_accuracy(trees, labels, progress=False)
    assert issubclass(LabelError, ValueError)


def test_any_hashable_labels_are_classes():
    """From a tour: tuple labels raised "got 15 labels for 15 roots" (numpy made them 2-D) and
    1 and "1" were one class (numpy made both strings)."""
    codes = learn.check_labels([("a", 1), ("a", 1), ("b", 2), ("b", 2)], 4)
    np.testing.assert_array_equal(codes, [0, 0, 1, 1])
    mixed = learn.check_labels([1, 1, "1", "1", 2, 2], 6)
    np.testing.assert_array_equal(mixed, [0, 0, 1, 1, 2, 2])  # three classes, first-seen order
    # Sortable labels keep the sorted class order (the folds deal classes in that order).
    np.testing.assert_array_equal(learn.check_labels(["b", "a", "b", "a"], 4), [1, 0, 1, 0])
    np.testing.assert_array_equal(learn.check_labels(np.array(["b", "a", "b", "a"]), 4), [1, 0, 1, 0])
    with pytest.raises(LabelError, match=r"same label 'a'"):  # a plain 'a', not np.str_('a')
        learn.check_labels(np.array(["a"] * 4), 4)
    with pytest.raises(LabelError, match="hashable.*list"):
        learn.check_labels([["a"], ["a"], ["b"], ["b"]], 4)
    with pytest.raises(LabelError, match="1-D"):
        learn.check_labels(np.zeros((4, 1)), 4)


def test_nested_cv_needs_n_folds_members_per_class(no_registration):
    roots, _ = position_signal_roots(n_per_class=3)
    trees = rs.batch(roots, n_points=12, dtype=np.float64)
    with pytest.raises(LabelError, match="fewer members than the 5 cross-validation folds.*at most 3 folds"):
        rs.nested_cv_accuracy(trees, ["a"] * 3 + ["b"] * 3, n_folds=5, progress=False)
    for bad in (0, 2.0, False):
        with pytest.raises(ValueError, match="n_repeats must be an integer >= 1"):
            rs.nested_cv_accuracy(trees, ["a"] * 3 + ["b"] * 3, n_folds=3, n_repeats=bad, progress=False)
    for bad in (-1, 1.5, None):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            rs.nested_cv_accuracy(trees, ["a"] * 3 + ["b"] * 3, n_folds=3, seed=bad, progress=False)


def test_zero_per_order_start_weight_is_refused_before_registering(no_registration):
    # Per-order weights are learned on a log scale (test_learn_depth): a zero start cannot move.
    roots, _ = position_signal_roots(n_per_class=3)
    trees = rs.batch(roots, n_points=12, dtype=np.float64)
    w = rs.Weights(deeper=((2.0, 0.0),))
    with pytest.raises(ValueError, match=r"order\(s\) \[2\].*positive"):
        rs.learn_weights(trees, ["a"] * 3 + ["b"] * 3, weights=w, progress=False)
    with pytest.raises(ValueError, match=r"order\(s\) \[2\].*positive"):
        rs.nested_cv_accuracy(trees, ["a"] * 3 + ["b"] * 3, weights=w, progress=False)
