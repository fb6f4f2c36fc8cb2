"""Learning the metric weights λ from labelled roots (docs/design.md §12).

With every registration (rotation, warps, lateral correspondence) held fixed, the squared
distance of a pair is a sum of per-term energies, ``d² = Σ_t λ_t E_t``: linear in λ (the
thickness weight enters through the extended SRVF and is not linear; it is then evaluated
exactly by re-applying the fixed registrations to the SRVFs built at the trial λr). So a
labelled set gives an exact, cheap objective in λ:

- **Loss**: the soft nearest-neighbour (NCA, Goldberger et al. 2005) log-loss over the distance
  matrix, ``L = −mean_i log Σ_{j ≠ i, y_j = y_i} p_ij`` with
  ``p_ij = softmax_{j ≠ i}(−d²_ij / τ)``; roots without a same-class partner are left out.
  The temperature is relative, ``τ = softness · mean_{i<j} d²_ij``, so the loss does not
  depend on the overall scale of λ. (A free τ is degenerate: on training classes that some λ
  separates, the loss falls to 0 as τ → 0 and λ stops moving.)
- **Parameters**: ``log λ_t`` of the learned terms: ``λ_main``, ``λ_position``, ``λ_thickness``
  where radii are present, and, for whole root systems, the (λs, λp) of each entry of
  `Weights.deeper` that the starting weights give (without that entry, every order shares the
  first-order laterals' λs and λp, and so does the learned model). At depth D > 2 the squared
  distance stays linear: each level's lateral and position energies are separate columns
  (`_metric.unit_energies_by_level`), weighted as the trees' levels use λ (a plant's system
  weighs its axes by λ_main). The overall scale of λ is fixed by holding
  ``λ_lateral`` at its starting value (1 for the paper's weights): without thickness, 1-NN and
  class-mean decisions and the loss depend only on the ratios of λ. A weak quadratic penalty
  ``regularisation · Σ (log λ_t − log λ_t⁰)²`` keeps a term that the data do not constrain
  at its starting value.
- **Solve**: BFGS (optimistix) with the registrations fixed, then every pair is registered
  again at the new λ (blocks of pairs mapped by the package's executor: worker threads here,
  Dask with `client=`; progress shown). The alternation stops when
  - no pair's lateral correspondence changed (which real lateral is matched to which; the
    null slot that a deleted lateral sits in is arbitrary and not counted; the rotation and
    warps are continuous and move a little with λ, so they are not compared), or
  - the loss at the fresh registrations improved by less than `tol` (relative): the
    registrations minimise each d², not the loss, so the alternation is no descent method and
    a re-registration can make the loss worse; the best entry is returned. Before stopping on
    a worse loss, λ steps back toward the best λ so far (½, then ¼ of the solve's step in log
    λ) and is registered again: the solve's step is right for the old registrations
    and can overshoot once they move (on CPlantBox species folds the full step's loss was
    worse and the half step's better than the start's), or
  - the inner solve left λ where it was, or after `max_reregistrations`.
  (Before these rules the stop was exact equality of the whole permutation, null slots
  included: null slots are shuffled among themselves at almost every re-registration, so
  every fit ran to `max_reregistrations`.)

`nested_cv_accuracy` is the honest evaluation: λ is learned on the training folds only and
the test roots are classified by 1-NN and by the nearest class mean.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Hashable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.stats
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from ._engine import RegistrationOptions, apply_registration, canonical_pairs, register_pairs, registration_options
from ._errors import InputError, LabelError, as_count, is_real_scalar, require_labels_present
from ._executor import LocalExecutor, executor_for
from ._metric import Weights, as_weights, preshape_terms, unit_energies_by_level, weights_by_level
from ._pairwise import default_chunk_size
from ._tree import RootTree, SRVFTree, batch_size, to_srvf

# --------------------------------------------------------------------------------------------
# Labels


def check_labels(labels, n: int, *, min_per_class: int = 2) -> np.ndarray:
    """The labels as integer class codes ``(n,)``: 0, 1, ... in the labels' sorted order (in
    first-seen order when they do not sort, e.g. 1 and "1", which are two classes), for at
    least two classes of `min_per_class` members; raises `LabelError` naming the problem
    (before anything is registered). Any hashable labels: strings, numbers, tuples."""
    if isinstance(labels, (str, bytes)):
        raise LabelError("labels must be a sequence with one label per root, not a single string.")
    if isinstance(labels, np.ndarray) and labels.ndim != 1:
        raise LabelError(f"labels must be one label per root (a 1-D sequence), got an array of shape {labels.shape}.")
    try:
        values = labels.tolist() if isinstance(labels, np.ndarray) else list(labels)
    except TypeError:
        raise LabelError(f"labels must be a sequence with one label per root, got {type(labels).__name__}.") from None
    if len(values) != n:
        raise LabelError(
            f"got {len(values)} labels for {n} roots; give exactly one label per root, in the order of the batch."
        )
    values = [v.item() if isinstance(v, np.generic) else v for v in values]  # np.str_('a') is 'a'
    require_labels_present(values)
    try:
        classes = list(dict.fromkeys(values))
    except TypeError:
        bad = next(v for v in values if not isinstance(v, Hashable))
        raise LabelError(
            f"labels must be hashable (strings, numbers, tuples), got {type(bad).__name__} {bad!r}."
        ) from None
    try:
        classes = sorted(classes)
    except TypeError:
        pass  # labels of several types: first-seen order
    code = {c: k for k, c in enumerate(classes)}
    y = np.array([code[v] for v in values], dtype=np.int64)
    counts = np.bincount(y, minlength=len(classes))
    if len(classes) < 2:
        raise LabelError(
            f"all {n} roots have the same label {classes[0]!r}; learning a metric needs at least two classes."
        )
    small = [f"{c!r} ({k})" for c, k in zip(classes, counts.tolist()) if k < min_per_class]
    if small and int(counts.min()) >= 2:
        # Every class can learn; the folds ask for more members than the smallest class has.
        raise LabelError(
            f"classes {', '.join(small)} have fewer members than the {min_per_class} cross-validation "
            f"folds, so some folds would hold none of them; use at most {int(counts.min())} folds "
            "(--folds / n_folds), or merge or drop those classes."
        )
    if small:
        lone = [f"{c!r} ({k})" for c, k in zip(classes, counts.tolist()) if k < 2]
        raise LabelError(
            f"classes {', '.join(lone)} have one member, so there is no same-class neighbour to learn "
            "from or cross-validate on; merge or drop them"
            + (
                f" (and the {min_per_class} folds need {min_per_class} members per class)."
                if min_per_class > 2
                else "."
            )
        )
    return y


def stratified_folds(labels, n_folds: int, *, seed: int = 0) -> list[np.ndarray]:
    """Test indices of `n_folds` stratified folds (seeded): each class is shuffled and dealt
    round-robin, starting where the previous class stopped, so fold sizes differ by ≤ 1."""
    y = np.asarray(labels)
    rng = np.random.default_rng(as_count(seed, "seed", minimum=0))
    folds: list[list[int]] = [[] for _ in range(n_folds)]
    start = 0
    for cls in np.unique(y):
        members = rng.permutation(np.flatnonzero(y == cls))
        for k, i in enumerate(members):
            folds[(start + k) % n_folds].append(int(i))
        start = (start + len(members)) % n_folds
    return [np.sort(np.asarray(f, dtype=np.int64)) for f in folds]


# --------------------------------------------------------------------------------------------
# The loss


def nca_loss(d2: Float[Array, "N N"], same: Array, temperature) -> Float[Array, ""]:
    """Soft nearest-neighbour log-loss of a squared-distance matrix (module docstring).

    `same[i, j]`: True where roots i ≠ j share a label (diagonal False)."""
    n = d2.shape[0]
    off = ~jnp.eye(n, dtype=bool)
    logits = jnp.where(off, -d2 / temperature, -jnp.inf)
    log_p = logits - jax.nn.logsumexp(logits, axis=1, keepdims=True)
    has = jnp.any(same, axis=1)
    per_root = jax.nn.logsumexp(jnp.where(same, log_p, -jnp.inf), axis=1)
    per_root = jnp.where(has, per_root, 0.0)
    return -jnp.sum(per_root) / jnp.maximum(jnp.sum(has), 1)


# --------------------------------------------------------------------------------------------
# Registrations of a list of pairs (the chunked engine)


class PairRegistrations(eqx.Module):
    """Registrations of a list of pairs of a batch, each in the engine's canonical order: root
    `second[k]` registered onto root `first[k]` (indices into the batch); `energy` is the
    minimised d² at the weights used, `unit_energies` its unweighted energies level by level
    (`_metric.unit_energies_by_level`: main, then lateral and position per branch level), so
    that ``d²(λ) = unit_energies @ weights_by_level(λ)`` with the registrations fixed, without
    thickness. At depth D > 2, `child_permutations` holds the deeper levels' correspondences
    (one ``[P, K1, …, Kℓ]`` array per level) and `child_warps` their warps, kept only where
    the thickness weight is learned (it rebuilds the SRVFs; the warps are the bulky part)."""

    first: np.ndarray
    second: np.ndarray
    permutation: np.ndarray
    rotation: np.ndarray
    main_warp: np.ndarray
    lateral_warps: np.ndarray
    energy: np.ndarray
    unit_energies: np.ndarray  # (P, 2D − 1): E_main, then E_lateral, E_position per branch level
    child_permutations: tuple = ()
    child_warps: tuple = ()

    def take(self, k: np.ndarray) -> PairRegistrations:
        return jax.tree.map(lambda x: x[k], self)


@eqx.filter_jit
def _register_chunk(a: SRVFTree, b: SRVFTree, active, weights: Weights, options: RegistrationOptions, keep_warps):
    ac, bc = canonical_pairs(a, b)
    # canonical_pairs puts b first where it swaps; read the swap off the content.
    swap = jnp.any(ac.q0 != a.q0, axis=(1, 2)) | jnp.any(ac.q != a.q, axis=(1, 2, 3)) | jnp.any(ac.s != a.s, axis=1)
    reg = register_pairs(ac, bc, weights, options, active)
    E = unit_energies_by_level(ac, reg.registered)
    warps = reg.child_warps if keep_warps else ()
    return (swap, reg.permutation, reg.rotation, reg.main_warp, reg.lateral_warps, reg.energy, E), (
        reg.child_permutations,
        warps,
    )


_KEYS = ("swap", "permutation", "rotation", "main_warp", "lateral_warps", "energy", "unit_energies")


def register_block(
    I, J, s: SRVFTree, weights: Weights, options: RegistrationOptions, chunk_size: int, keep_warps: bool = False
) -> dict:
    """The block function: register the pairs (s[I[k]], s[J[k]]) of one block, `chunk_size`
    per compiled call (one program for every chunk), keeping the registrations (not only the
    energies; the deeper levels' warps only with `keep_warps`). Module-level and pure, so an
    executor can run it on a thread or a Dask worker."""
    I = np.asarray(I, np.int64)
    J = np.asarray(J, np.int64)
    n = len(I)
    parts = []
    for start in range(0, n, chunk_size):
        m = min(start + chunk_size, n) - start
        ii = np.zeros(chunk_size, np.int64)
        jj = np.zeros(chunk_size, np.int64)
        ii[:m] = I[start : start + m]
        jj[:m] = J[start : start + m]
        a = jax.tree.map(lambda x: x[ii], s)
        b = jax.tree.map(lambda x: x[jj], s)
        out, (child_perms, child_warps) = _register_chunk(
            a, b, jnp.asarray(np.arange(chunk_size) < m), weights, options, keep_warps
        )
        parts.append([np.asarray(x)[:m] for x in (*out, *child_perms, *child_warps)])
    keys = _KEYS + tuple(f"child_permutation{k}" for k in range(len(child_perms)))
    keys += tuple(f"child_warp{k}" for k in range(len(child_warps)))
    return {k: np.concatenate(v) for k, v in zip(keys, zip(*parts))}


def register_pair_list(
    s: SRVFTree,
    I,
    J,
    weights: Weights,
    options: RegistrationOptions,
    *,
    chunk_size: int,
    progress: bool,
    desc: str,
    client=None,
    block_size: int | None = None,
    keep_warps: bool = False,
) -> PairRegistrations:
    """Register the pairs (s[I[k]], s[J[k]]) through the package's executor: blocks of
    `block_size` pairs (default one chunk here, ``8 × chunk_size`` on a cluster) mapped by
    `register_block`, on worker threads here or on Dask with `client=`, with a progress bar.
    Every block starts on a chunk boundary, so the registrations do not depend on where the
    blocks run. `keep_warps`: keep the deeper levels' warps (`PairRegistrations`)."""
    I = np.asarray(I, np.int64)
    J = np.asarray(J, np.int64)
    n = len(I)
    if n == 0:
        raise ValueError("no pairs to register.")
    executor = executor_for(client)
    if block_size is None:
        block_size = chunk_size if isinstance(executor, LocalExecutor) else 8 * chunk_size
    if block_size % chunk_size:
        raise ValueError(
            f"block_size ({block_size}) must be a multiple of chunk_size ({chunk_size}), so that every "
            "chunk holds the same pairs wherever it runs."
        )
    spans = [(a, min(a + block_size, n)) for a in range(0, n, block_size)]
    results, _ = executor.map_blocks(
        register_block,
        [(I[a:z], J[a:z]) for a, z in spans],
        shared=(s, weights, options, chunk_size, keep_warps),
        sizes=[z - a for a, z in spans],
        progress=progress,
        desc=desc,
        unit="pair",
    )
    r = {k: np.concatenate([b[k] for b in results]) for k in results[0]}
    swap = r["swap"].astype(bool)
    return PairRegistrations(
        first=np.where(swap, J, I),
        second=np.where(swap, I, J),
        permutation=r["permutation"],
        rotation=r["rotation"],
        main_warp=r["main_warp"],
        lateral_warps=r["lateral_warps"],
        energy=r["energy"],
        unit_energies=r["unit_energies"],
        child_permutations=tuple(r[f"child_permutation{k}"] for k in range(s.depth - 2)),
        child_warps=tuple(r[f"child_warp{k}"] for k in range(s.depth - 2) if keep_warps),
    )


# --------------------------------------------------------------------------------------------
# Learning


class LearnedWeights(eqx.Module):
    """Result of `learn_weights`.

    - `weights`: the learned `Weights` (λ_lateral held at its starting value).
    - `softness`: the loss's relative temperature (``τ = softness · mean d²``).
    - `loss_trace`: the NCA loss (penalty included) at freshly registered distances: entry 0
      at the starting λ and τ, entry k after the k-th re-registration, at the λ that an inner
      solve found or, where that λ's loss was not below the best so far, at a step back
      toward the best λ (½, then ¼ of the solve's step in log λ). Rejected tries are entries
      too, so the trace is not monotone.
    - `inner_loss_trace`: the loss reached by each inner solve (registrations fixed); one entry
      per solve, so shorter than `n_reregistrations` when steps back were taken.
    - `status`: after the steps back, "converged" (no lateral correspondence changed at an
      accepted re-registration, or the inner solve left λ where it was), "loss" (the loss at
      the fresh registrations improved by less than `tol`, relative, or every step back
      registered worse than the best), or "max_reregistrations".
    - `steps`: inner optimiser steps, summed over the solves.
    - `n_reregistrations`: registrations of every pair after the first (steps back included).
    - `distances`: (n, n) matrix at the learned weights (from their registration).
    - `regularisation`: the penalty used; `regularisation_scores`: when several were given,
      each one's inner-CV held-out NCA log-loss (else None).
    - `changed_pairs`: per re-registration, the number of pairs whose lateral correspondence
      (real lateral to real lateral) changed from the registrations the inner solve used.
    - `registration_gain`: per re-registration, the relative decrease of Σ d² that registering
      again at the new λ found over the inner solve's registrations evaluated at that λ.

    `weights` and `distances` are those of the registered loss's best entry (the alternation
    is not a descent method: the registrations minimise each d², not the loss); `kept()` says
    which entries of `loss_trace` the fit kept.
    """

    weights: Weights
    softness: float
    loss_trace: np.ndarray
    inner_loss_trace: np.ndarray
    status: str = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    n_reregistrations: int = eqx.field(static=True)
    distances: np.ndarray
    changed_pairs: np.ndarray
    registration_gain: np.ndarray
    regularisation: float
    regularisation_scores: np.ndarray | None

    def __repr__(self) -> str:
        # The numbers a user looks for first; equinox's default would print `weights` as
        # `weak_f32[]` summaries (the values are arrays, for differentiating through them).
        trace = ", ".join(f"{v:.4g}" for v in np.asarray(self.loss_trace, dtype=float))
        n = np.shape(self.distances)[0]
        return (
            f"LearnedWeights(weights={self.weights!r}, status={self.status!r}, loss_trace=[{trace}], "
            f"steps={self.steps}, n_reregistrations={self.n_reregistrations}, softness={self.softness:.4g}, "
            f"regularisation={self.regularisation:.4g}, distances=<{n}×{n} matrix>)"
        )

    def kept(self) -> np.ndarray:
        """Per entry of `loss_trace`, whether the fit kept it: the start, and every try whose
        loss was below the best before it (the fit's rule; a try that was not is followed by
        a step back or the stop). The last kept entry is the one returned."""
        loss = np.asarray(self.loss_trace, np.float64)
        kept = np.zeros(loss.shape, bool)
        best = np.nan
        for i, value in enumerate(loss):
            # The fit's own comparison, so that a NaN loss is handled as the fit handles it.
            kept[i] = i == 0 or value < best
            best = value if kept[i] else best
        return kept


def _regularisation_candidates(regularisation) -> tuple[float, ...]:
    values = regularisation if isinstance(regularisation, (list, tuple, np.ndarray)) else [regularisation]
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not v >= 0:
            raise ValueError(
                f"regularisation must be a number >= 0 or a sequence of them (chosen by inner "
                f"cross-validation), got {regularisation!r}."
            )
        out.append(float(v))
    if not out:
        raise ValueError("regularisation: give at least one value.")
    return tuple(out)


class _Problem(eqx.Module):
    """What the inner solve needs: which weights are learned (`names`: a term's name, or
    ``("deeper", entry, 0 for λs / 1 for λp)``), the starting weights (the others stay at
    their values), the labels' pair structure and the trees' depth."""

    names: tuple = eqx.field(static=True)
    start: Weights
    log0: Array
    local_i: Array
    local_j: Array
    same: Array
    n: int = eqx.field(static=True)
    regularisation: Array  # a traced scalar: one compiled solve serves every candidate value
    softness: float = eqx.field(static=True)
    depth: int = eqx.field(static=True, default=2)
    virtual_main: bool = eqx.field(static=True, default=False)


def _weights_of(names, log_lam, start: Weights) -> Weights:
    """`start` with the learned weights `names` set to ``exp(log_lam)``."""
    values = dict(start.items())
    deeper = [list(pair) for pair in start.deeper]
    for k, name in enumerate(names):
        if isinstance(name, str):
            values[name] = jnp.exp(log_lam[k])
        else:
            _, entry, which = name
            deeper[entry][which] = jnp.exp(log_lam[k])
    return Weights(**values, deeper=deeper)


def _as_floats(weights: Weights) -> Weights:
    """Concrete weights (Python floats), deeper levels included."""
    return Weights(
        **{k: float(v) for k, v in weights.items()},
        deeper=tuple((float(ls), float(lp)) for ls, lp in weights.deeper),
    )


def pair_d2_linear(lam_by_level: Array, E: Array) -> Array:
    """Squared distances of registered pairs at λ (registrations fixed): ``E @ λ``, with `E`
    the unit energies by level and `lam_by_level` their weights (`weights_by_level`)."""
    return E @ lam_by_level


def _d2_thickness(weights: Weights, tree: RootTree, regs: PairRegistrations) -> Array:
    """Squared distances with the registrations fixed, the SRVFs built at the trial λr."""
    s = to_srvf(tree, weights=weights)
    a = jax.tree.map(lambda x: x[regs.first], s)
    b = jax.tree.map(lambda x: x[regs.second], s)
    children = tuple(zip(regs.child_permutations, regs.child_warps))
    registered = jax.vmap(apply_registration)(
        a, b, regs.rotation, regs.permutation, regs.main_warp, regs.lateral_warps, children
    )
    return preshape_terms(a, registered, weights).total


def _matrix(d2_pairs, li, lj, n):
    D2 = jnp.zeros((n, n), d2_pairs.dtype)
    return D2.at[li, lj].set(d2_pairs).at[lj, li].set(d2_pairs)


def _pair_d2(theta, problem, tree, regs):
    """Squared distances of the registered pairs at ``log λ = theta``, registrations fixed."""
    W = _weights_of(problem.names, theta[: len(problem.names)], problem.start)
    if tree is None:
        lam = weights_by_level(W, depth=problem.depth, virtual_main=problem.virtual_main)
        return pair_d2_linear(lam.astype(theta.dtype), jnp.asarray(regs.unit_energies))
    return _d2_thickness(W, tree, regs)


def _objective(theta, args):
    problem, tree, regs = args
    k = len(problem.names)
    d2 = jnp.maximum(_pair_d2(theta, problem, tree, regs), 0.0)
    D2 = _matrix(d2, problem.local_i, problem.local_j, problem.n)
    loss = nca_loss(D2, problem.same, problem.softness * jnp.mean(d2))
    return loss + problem.regularisation * jnp.sum((theta[:k] - problem.log0) ** 2)


def learn_loss(theta, problem, tree, regs):
    """The inner objective (for tests): NCA loss + penalty at ``theta = log λ_learned``."""
    return _objective(theta, (problem, tree, regs))


def correspondence_changed(old: PairRegistrations, new: PairRegistrations, masks) -> np.ndarray:
    """Per pair, whether the branch correspondence differs: which real lateral of the first
    root is matched to which real lateral of the second, at every level kept. Which null slot
    a deleted or inserted branch sits in is not a correspondence (a real-vs-null slot costs
    its whole weighted norm wherever it sits, docs/design.md §4), so it is ignored. `masks`:
    the batch's real-branch flags, ``(n, K1)`` for the laterals, or one array per level
    ``(n, K1, …, Kℓ)`` (deeper levels are compared where `PairRegistrations.child_permutations`
    holds them). A pair whose canonical order flipped counts as changed."""
    masks = (masks,) if isinstance(masks, np.ndarray) else tuple(masks)

    def partners(r):
        # Per level, the flat index of b's partner of each slot of a, -1 unless both are real.
        perms = (np.asarray(r.permutation),) + tuple(np.asarray(p) for p in r.child_permutations)
        out = []
        parent = np.zeros(len(r.first), np.int64)  # the main root: one parent of level 1
        for mask, perm in zip(masks, perms):
            ma, mb = mask[r.first], mask[r.second]
            n_slots = mb.shape[-1]
            # b's level in a's slot order: under each parent's partner, then the children's own
            # permutation.
            mb = np.take_along_axis(mb.reshape(len(perm), -1, n_slots), parent.reshape(len(perm), -1, 1), axis=1)
            mb = np.take_along_axis(mb.reshape(perm.shape), perm, axis=-1)
            parent = parent[..., None] * n_slots + perm  # flat index into b's level
            out.append(np.where(ma & mb, parent, -1).reshape(len(perm), -1))
        return np.concatenate(out, axis=1)

    flipped = np.asarray(old.first) != np.asarray(new.first)
    return flipped | np.any(partners(old) != partners(new), axis=1)


# The inner solve's λ is the same as the last one (log scale): re-registering would repeat it.
_THETA_ATOL = 1e-8
# When the loss at the fresh registrations is worse than the best so far, λ steps back toward
# the best λ (log scale) this many times, halving the step each time, before the fit stops.
_STEPS_BACK = 2


def _learned_names(learn_thickness: bool, n_deeper: int = 0) -> tuple:
    """The learned weights: λm and λp, each `Weights.deeper` entry's λs and λp, and λr with
    radii (λs of the first-order laterals fixes the scale)."""
    names = ["main", "position"]
    names += [("deeper", e, which) for e in range(n_deeper) for which in (0, 1)]
    if learn_thickness:
        names.append("thickness")
    return tuple(names)


def _start_value(weights: Weights, name) -> float:
    return float(weights[name]) if isinstance(name, str) else float(weights.deeper[name[1]][name[2]])


def _prepare(trees, weights, registration, options):
    weights = as_weights(weights)
    zero = [e + 2 for e, pair in enumerate(weights.deeper) if min(float(v) for v in pair) <= 0]
    if zero:
        # λ is learned on a log scale, and a zero weight means "leave this order out".
        raise ValueError(
            f"learn_weights: the weights of order(s) {zero} in Weights.deeper are 0; a learned weight "
            "starts from a positive value. Give positive starting values, or batch the trees at a "
            "depth that leaves those orders out."
        )
    opts = registration_options(registration, **options)
    if not isinstance(trees, (RootTree, SRVFTree)):
        raise TypeError(
            f"trees must be a batched RootTree or SRVFTree (rootshape_jax.batch(roots)), got {type(trees).__name__}."
        )
    radii = isinstance(trees, RootTree) and trees.main_radius is not None
    return weights, opts, radii


def _start_weights(weights: Weights, radii: bool) -> Weights:
    """Starting λ: the given weights, with λr = 1 where radii are learned from a zero start
    (a log-parameter cannot start at 0)."""
    if radii and float(weights.thickness) <= 0:
        return Weights(**{**dict(weights.items()), "thickness": 1.0}, deeper=weights.deeper)
    return weights


class _Fitter:
    """Alternation of inner solves and re-registrations on the roots `idx` of a batch."""

    def __init__(
        self,
        trees,
        weights,
        opts,
        radii,
        *,
        chunk_size,
        progress,
        regularisation,
        max_steps,
        rtol,
        softness=0.1,
        client=None,
    ):
        if not (isinstance(softness, (int, float)) and softness > 0):
            raise ValueError(f"softness must be a positive number, got {softness!r}.")
        self.softness = float(softness)
        self.trees = trees
        self.opts = opts
        self.radii = radii
        if chunk_size is None:
            chunk_size = default_chunk_size(trees.capacity)
        self.chunk_size = chunk_size
        self.progress = progress
        self.candidates = _regularisation_candidates(regularisation)
        self.max_steps = int(max_steps)
        self.rtol = float(rtol)
        self.start = _start_weights(weights, radii)
        self.client = client
        # Real-branch flags per level: (n, K1), then (n, K1, K2), ...
        self.masks = (
            () if trees is None else (np.asarray(trees.mask),) + tuple(np.asarray(lv.mask) for lv in trees.deeper)
        )

    def srvf(self, weights):
        return to_srvf(self.trees, weights=weights)

    def register(self, weights, I, J, desc):
        return register_pair_list(
            self.srvf(weights),
            I,
            J,
            weights,
            self.opts,
            chunk_size=self.chunk_size,
            progress=self.progress,
            desc=desc,
            client=self.client,
            keep_warps=self.radii,
        )

    def solve(self, problem, regs, theta0):
        tree = self.trees if self.radii else None
        solver = optx.BFGS(rtol=self.rtol, atol=self.rtol)
        sol = optx.minimise(
            _objective, solver, theta0, args=(problem, tree, regs), max_steps=self.max_steps, throw=False
        )
        return sol.value, float(_objective(sol.value, (problem, tree, regs))), int(sol.stats["num_steps"])

    def dtype(self):
        return np.asarray(self.trees.main if isinstance(self.trees, RootTree) else self.trees.q0).dtype

    def problem(self, y, regularisation) -> _Problem:
        n = len(y)
        li, lj = np.triu_indices(n, 1)
        names = _learned_names(self.radii, len(self.start.deeper))
        dtype = self.dtype()
        return _Problem(
            names=names,
            start=self.start,
            log0=jnp.log(jnp.asarray([_start_value(self.start, k) for k in names], dtype)),
            local_i=jnp.asarray(li),
            local_j=jnp.asarray(lj),
            same=jnp.asarray((y[:, None] == y[None, :]) & ~np.eye(n, dtype=bool)),
            n=n,
            regularisation=jnp.asarray(regularisation, dtype),
            softness=self.softness,
            depth=self.trees.depth if self.trees is not None else 2,
            virtual_main=bool(getattr(self.trees, "virtual_main", False)),
        )

    def choose_regularisation(self, y, regs, *, n_inner: int = 3) -> tuple[float, np.ndarray]:
        """The candidate regularisation with the lowest held-out NCA log-loss under an inner
        stratified CV of the training roots, the registrations held at the start λ (so no
        registration is done here: every inner solve and score reuses `regs`). Ties go to
        the stronger penalty (nearer the starting λ). Returns it and the score per candidate."""
        n = len(y)
        li, lj = np.triu_indices(n, 1)
        pos = np.full((n, n), -1, np.int64)
        pos[li, lj] = np.arange(len(li))
        pos[lj, li] = pos[li, lj]
        n_inner = min(n_inner, int(np.unique(y, return_counts=True)[1].min()))
        tree = self.trees if self.radii else None
        folds = stratified_folds(y, n_inner, seed=0)
        scores = np.zeros(len(self.candidates))
        for c, r in enumerate(self.candidates):
            for test in folds:
                train = np.setdiff1d(np.arange(n), test)
                a, b = np.triu_indices(len(train), 1)
                sub = regs.take(pos[train[a], train[b]])
                problem = self.problem(y[train], r)
                theta, _, _ = self.solve(problem, sub, problem.log0)
                tau = self.softness * float(jnp.mean(jnp.maximum(_pair_d2(theta, problem, tree, sub), 0.0)))
                TI, TJ = (x.ravel() for x in np.meshgrid(test, train, indexing="ij"))
                d2 = np.asarray(_pair_d2(theta, problem, tree, regs.take(pos[TI, TJ]))).reshape(len(test), len(train))
                logits = -np.maximum(d2, 0.0) / tau
                same = y[test][:, None] == y[train][None, :]
                top = logits.max(axis=1, keepdims=True)
                log_all = np.log(np.exp(logits - top).sum(axis=1))
                log_same = np.log(np.where(same, np.exp(logits - top), 0.0).sum(axis=1))
                scores[c] += float(np.sum(log_all - log_same)) / n
        low = scores.min() + 1e-12 * max(1.0, abs(scores.min()))
        strongest_first = np.argsort(-np.asarray(self.candidates), kind="stable")
        best = next(c for c in strongest_first if scores[c] <= low)
        return self.candidates[best], scores

    def fit(self, idx, y, *, regs=None, max_reregistrations: int, tol: float):
        idx = np.asarray(idx, np.int64)
        n = len(idx)
        li, lj = np.triu_indices(n, 1)
        I, J = idx[li], idx[lj]
        dtype = self.dtype()
        weights = self.start
        if regs is None:
            regs = self.register(weights, I, J, "registering (start λ)")
        scores = None
        regularisation = self.candidates[0]
        if len(self.candidates) > 1:
            regularisation, scores = self.choose_regularisation(y, regs)
        problem = self.problem(y, regularisation)
        names, log0 = problem.names, problem.log0
        theta = log0
        tree = self.trees if self.radii else None
        loss_trace = [float(_objective(theta, (problem, tree, regs)))]
        inner, steps, n_rereg, status = [], 0, 0, "max_reregistrations"
        changed_trace, gain_trace = [], []
        best = (loss_trace[0], weights, regs, theta)
        bar = tqdm(total=max_reregistrations, desc="learning λ", unit="re-registration", disable=not self.progress)
        try:
            while n_rereg < max_reregistrations:
                theta_old = theta
                theta, loss, k = self.solve(problem, regs, theta)
                inner.append(loss)
                steps += k
                if float(jnp.max(jnp.abs(theta - theta_old))) <= _THETA_ATOL:
                    # λ did not move, so registering again would give the same registrations.
                    status = "converged"
                    break
                best_before = best[0]
                # The inner solve's λ, then, while the loss at fresh registrations is worse than
                # the best so far, halfway back toward the best λ (½, then ¼ of the solve's step):
                # the step is right for the old registrations and may overshoot once they move.
                for back in range(_STEPS_BACK + 1):
                    if back:
                        theta = 0.5 * (best[3] + theta)
                    weights = _as_floats(_weights_of(names, theta[: len(names)], problem.start))
                    new = self.register(weights, I, J, f"re-registering ({n_rereg + 1})")
                    n_rereg += 1
                    bar.update(1)
                    # d² of the old registrations at the new λ: what re-registering improves on.
                    old_d2 = np.asarray(_pair_d2(theta, problem, tree, regs))
                    gain_trace.append(float((old_d2.sum() - new.energy.sum()) / max(old_d2.sum(), 1e-300)))
                    changed_trace.append(int(np.sum(correspondence_changed(regs, new, self.masks))))
                    loss_trace.append(float(_objective(theta, (problem, tree, new))))
                    bar.set_postfix_str(f"loss {loss_trace[-1]:.4g}, {changed_trace[-1]} pairs re-matched")
                    if loss_trace[-1] < best[0]:
                        best = (loss_trace[-1], weights, new, theta)
                        break
                    if n_rereg >= max_reregistrations:
                        break
                if best[0] >= best_before:
                    # Every λ tried registered worse than the best: stop there (the budget may
                    # have ended before the last step back).
                    status = "loss" if back == _STEPS_BACK else "max_reregistrations"
                    break
                regs = new
                if changed_trace[-1] == 0:
                    status = "converged"
                    break
                if loss_trace[-1] > best_before - tol * abs(best_before):
                    status = "loss"
                    break
        finally:
            bar.close()
        _, weights, regs, _ = best
        D = np.zeros((n, n), dtype)
        D[li, lj] = np.sqrt(np.maximum(regs.energy, 0.0))
        D[lj, li] = D[li, lj]
        result = LearnedWeights(
            weights=weights,
            softness=problem.softness,
            loss_trace=np.asarray(loss_trace),
            inner_loss_trace=np.asarray(inner),
            status=status,
            steps=steps,
            n_reregistrations=n_rereg,
            distances=D,
            changed_pairs=np.asarray(changed_trace, np.int64),
            registration_gain=np.asarray(gain_trace),
            regularisation=float(regularisation),
            regularisation_scores=scores,
        )
        return result, regs


def learn_weights(
    trees: RootTree | SRVFTree,
    labels: Sequence,
    *,
    weights: Weights | None = None,
    max_reregistrations: int = 3,
    tol: float = 1e-3,
    regularisation: float | Sequence[float] = 1e-3,
    softness: float = 0.1,
    max_steps: int = 200,
    rtol: float = 1e-6,
    registration: RegistrationOptions | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    client=None,
    **options,
) -> LearnedWeights:
    """Learn the metric weights λ that best separate labelled roots (docs/design.md §12).

    Minimises the soft nearest-neighbour (NCA) loss of the distance matrix over
    ``log λ_main``, ``log λ_position`` (and ``log λ_thickness`` when `trees` is a `RootTree`
    with radii; and each order's ``(λs, λp)`` when the starting weights give
    ``Weights(..., deeper=...)`` for trees batched at depth 3 or 4), with ``λ_lateral`` held at
    its starting value (the overall scale of λ is
    fixed; see the module docstring) and the temperature ``τ = softness · mean d²``. The registrations are held fixed
    during each BFGS solve (then d² is linear in λ), and every pair is registered again at the
    new λ, until no lateral correspondence (real lateral to real lateral) changes, the loss at
    the fresh registrations improves by less than `tol` (relative), or after
    `max_reregistrations`; the λ with the lowest loss at its own registrations is returned.
    A solve's λ whose loss at its fresh registrations is worse than the best so far is
    first stepped back toward the best λ (½, then ¼ of the step in log λ, each a
    re-registration) before the fit stops.

    - `labels`: one label per root (any hashable values); at least two classes, each with
      at least two members. Bad labels raise `LabelError` before anything is registered.
    - `weights`: the starting λ (default the paper's (0.02, 1, 1)); with radii, a thickness
      weight of 0 (the default) starts at 1 (a log-parameter cannot start at 0). The penalty
      ``regularisation · Σ (log λ − log λ_start)²`` keeps unconstrained terms there. Give
      several values (a sequence) to choose among them by a 3-fold inner cross-validation
      of the roots given, scored by held-out NCA log-loss with the registrations held at the
      start λ (cheap: no extra registration); ties go to the stronger penalty. Small
      training sets overfit λ, and a penalty chosen this way does not look at any test root.
    - `max_steps`, `rtol`: of each inner BFGS solve.
    - `registration`, `chunk_size`, `progress`, `client`, `**options`: as in
      `pairwise_distances` (with `client`, a ``dask.distributed.Client``, the registrations run
      on the cluster).

    Returns a `LearnedWeights`. Its accuracy on the training roots is not a result: use
    `nested_cv_accuracy`.
    """
    weights, opts, radii = _prepare(trees, weights, registration, options)
    n = batch_size(trees)
    y = check_labels(labels, n)
    _check_options(max_reregistrations, max_steps, tol)
    fitter = _Fitter(
        trees,
        weights,
        opts,
        radii,
        chunk_size=chunk_size,
        progress=progress,
        regularisation=regularisation,
        max_steps=max_steps,
        rtol=rtol,
        softness=softness,
        client=client,
    )
    result, _ = fitter.fit(np.arange(n), y, max_reregistrations=max_reregistrations, tol=tol)
    return result


def _check_options(max_reregistrations, max_steps, tol):
    as_count(max_reregistrations, "max_reregistrations")
    as_count(max_steps, "max_steps")
    if not is_real_scalar(tol) or not (math.isfinite(float(tol)) and tol >= 0):
        raise ValueError(f"tol must be a number >= 0 (a relative improvement of the loss), got {tol!r}.")


# --------------------------------------------------------------------------------------------
# Evaluation


def fold_predictions(D_test_train: np.ndarray, D_train: np.ndarray, y_train: np.ndarray):
    """Labels of test roots by 1-NN and by the nearest class mean, from distances alone.

    The class mean is the centroid in the distance-matrix (Euclidean-embedding) sense, no
    Karcher mean: ``|x − m_C|² = mean_j d²(x, x_j) − mean_{j,k} d²(x_j, x_k) / 2`` over the
    training members j, k of class C (as `loo_accuracy`'s ``"nearest_mean"``)."""
    nn = y_train[np.argmin(D_test_train, axis=1)]
    classes = np.unique(y_train)
    d2 = np.empty((D_test_train.shape[0], len(classes)))
    for c, cls in enumerate(classes):
        m = np.flatnonzero(y_train == cls)
        spread = (D_train[np.ix_(m, m)] ** 2).sum() / (2 * m.size**2)
        d2[:, c] = (D_test_train[:, m] ** 2).mean(axis=1) - spread
    return nn, classes[np.argmin(d2, axis=1)]


def held_out_log_loss(D_test_train, D_train, y_test, y_train, *, softness: float = 0.1) -> float:
    """The NCA log-loss of held-out roots against training roots, from distances alone.

    ``−mean_x log Σ_{j: y_j = y_x} softmax_j(−d²(x, x_j) / τ)`` over the test roots x and the
    training roots j, with the learning's relative temperature ``τ = softness · mean_{i<j}
    d²(x_i, x_j)`` over the training pairs: the loss `learn_weights` minimises, scored on roots
    it never saw. A proper score of how confidently (not only whether) the held-out roots'
    classes are predicted, the same for distances of any scale. Lower is better; distances
    that carry no information score ``log C`` on C classes of equal size.

    `D_test_train`: ``[n_test, n_train]``; `D_train`: ``[n_train, n_train]``; `y_test`,
    `y_train`: the labels. Every test root's class needs a training member (`LabelError`)."""
    D_tt = np.asarray(D_test_train, np.float64)
    D_tr = np.asarray(D_train, np.float64)
    y_test, y_train = np.asarray(y_test), np.asarray(y_train)
    n_test, n_train = len(y_test), len(y_train)
    if D_tt.shape != (n_test, n_train) or D_tr.shape != (n_train, n_train) or n_train < 2:
        raise ValueError(
            f"held_out_log_loss: D_test_train must be [n_test, n_train] and D_train [n_train, n_train] "
            f"with n_train >= 2, for {n_test} test and {n_train} training labels; got {D_tt.shape} and {D_tr.shape}."
        )
    if not (np.all(np.isfinite(D_tt)) and np.all(np.isfinite(D_tr))) or np.any(D_tt < 0) or np.any(D_tr < 0):
        raise InputError("held_out_log_loss: distances must be finite and non-negative.")
    if isinstance(softness, bool) or not is_real_scalar(softness) or not (math.isfinite(softness) and softness > 0):
        raise ValueError(f"softness must be a positive number, got {softness!r}.")
    train_classes = set(y_train.tolist())
    missing = sorted({c for c in y_test.tolist() if c not in train_classes}, key=str)
    if missing:
        raise LabelError(
            f"held_out_log_loss: test classes without a training member ({', '.join(map(str, missing))}); "
            "split the roots so that every class is in the training roots (stratified folds)."
        )
    pairs = D_tr[np.triu_indices(n_train, 1)]
    top = float(np.max(pairs))
    if not top > 0:
        raise ValueError("held_out_log_loss: the training roots are all at distance 0 from each other.")
    scale = top * math.sqrt(float(np.mean((pairs / top) ** 2)))  # √(mean d²), neither over- nor underflowing
    # d² / τ with the scale divided out first, so that no distance overflows when squared.
    logits = -((D_tt / scale) ** 2) / softness
    same = y_test[:, None] == y_train[None, :]
    return float(np.mean(_log_sum_exp(logits, np.ones_like(same)) - _log_sum_exp(logits, same)))


def _log_sum_exp(x: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Row-wise ``log Σ_{where} exp(x)``, stable (each row shifted by its own maximum)."""
    top = np.max(np.where(where, x, -np.inf), axis=1, keepdims=True)
    return top[:, 0] + np.log(np.sum(np.exp(np.where(where, x - top, -np.inf)), axis=1))


def _fold_scores(D_test_train, D_train, y_test, y_train, softness: float) -> tuple[float, float, float]:
    """One fold's held-out scores from its distances: 1-NN and nearest-class-mean accuracy
    (`fold_predictions`) and the NCA log-loss (`held_out_log_loss`)."""
    p_nn, p_mean = fold_predictions(D_test_train, D_train, y_train)
    loss = held_out_log_loss(D_test_train, D_train, y_test, y_train, softness=softness)
    return float(np.mean(p_nn == y_test)), float(np.mean(p_mean == y_test)), loss


class CVAccuracy(eqx.Module):
    """Result of `nested_cv_accuracy` (accuracies are on the held-out fold only).

    - `learned_nn`, `learned_mean`: per outer fold, 1-NN and nearest-class-mean accuracy with
      λ learned on that fold's training roots.
    - `paper_nn`, `paper_mean`: the same folds at the starting λ (the paper's by default).
    - `learned_log_loss`, `paper_log_loss`: per outer fold, the held-out NCA log-loss
      (`held_out_log_loss`, lower is better) at the learned and the starting λ: the loss the
      learning minimises, on roots it never saw. Accuracy saturates on easy sets (a tie at
      100 % says nothing); this score still tells whether the learned λ generalises.
    - `weights`: per fold, the learned λ as a dict (`Weights.to_dict`); `folds`: the test indices of each fold.
    - `repeats`: per fold, which repetition of the cross-validation it belongs to (0 … n_repeats − 1;
      repetition r splits the roots with seed ``seed + r``). Every per-fold array lists the
      folds of repetition 0 first, then those of repetition 1, and so on.
    - `n_reregistrations`, `status`: per fold, from `learn_weights`.
    - `seconds_learning`: wall time of each fold's learning (registrations included).
    - `regularisation`: per fold, the penalty used (chosen on the training roots when several
      were given).

    `summary()` gives the mean and spread over folds; `fold_comparison()` counts the folds where
    the learned λ does better, the same or worse than the starting λ; `t_tests()` gives a
    p-value for each mean difference against the folds' spread (`fold_t_test`).
    """

    learned_nn: np.ndarray
    learned_mean: np.ndarray
    paper_nn: np.ndarray
    paper_mean: np.ndarray
    learned_log_loss: np.ndarray
    paper_log_loss: np.ndarray
    weights: list
    folds: list
    n_reregistrations: np.ndarray
    status: tuple = eqx.field(static=True)
    seconds_learning: np.ndarray
    regularisation: np.ndarray
    repeats: np.ndarray

    def summary(self) -> dict:
        """Mean and standard deviation over every fold (of every repetition) of each accuracy
        and held-out log-loss."""
        return {
            name: (float(np.mean(v)), float(np.std(v)))
            for name, v in (
                ("learned_nn", self.learned_nn),
                ("learned_mean", self.learned_mean),
                ("paper_nn", self.paper_nn),
                ("paper_mean", self.paper_mean),
                ("learned_log_loss", self.learned_log_loss),
                ("paper_log_loss", self.paper_log_loss),
            )
        }

    def __repr__(self) -> str:
        # The scores, not equinox's array summaries (f64[5](numpy)).
        cells = ", ".join(
            f"{k}={m:.3f} ± {sd:.3f}" if k.endswith("log_loss") else f"{k}={100 * m:.1f} ± {100 * sd:.1f} %"
            for k, (m, sd) in self.summary().items()
        )
        n_repeats = len(np.unique(self.repeats))
        folds = (
            f"{len(self.folds)} folds"
            if n_repeats == 1
            else f"{n_repeats} repeats × {len(self.folds) // n_repeats} folds"
        )
        better = ", ".join(f"{k} {b}/{t}/{w}" for k, (b, t, w) in self.fold_comparison().items())
        p = ", ".join(f"{k} {test.p_value:.3g}" for k, test in self.t_tests().items()) if len(self.folds) > 1 else "—"
        return (
            f"CVAccuracy({cells}; {folds}, held-out scores: mean ± sd over folds; "
            f"folds where learned λ is better/equal/worse: {better}; corrected paired t-test p: {p})"
        )

    def fold_comparison(self) -> dict:
        """For each score, the number of folds where the learned λ is better than, equal to
        and worse than the starting λ on the same held-out roots: ``{"nn": (better, equal,
        worse), "mean": ..., "log_loss": ...}`` (accuracy: higher is better; log-loss: lower).
        Scores within a relative 1e-4 of each other count as equal (`fold_better`), so that
        rounding is not a win. A mean over folds can hide that one fold carries the difference;
        these counts show whether it is consistent."""
        return {
            "nn": fold_better(self.learned_nn, self.paper_nn, higher_is_better=True),
            "mean": fold_better(self.learned_mean, self.paper_mean, higher_is_better=True),
            "log_loss": fold_better(self.learned_log_loss, self.paper_log_loss, higher_is_better=False),
        }

    def t_tests(self) -> dict:
        """For each score, the corrected resampled paired t-test (`fold_t_test`) of the learned
        λ against the starting λ on the same folds: ``{"nn": FoldTest, "mean": ...,
        "log_loss": ...}``; `difference` is learned minus starting (accuracy: > 0 is better;
        log-loss: < 0 is better)."""
        n_folds = len(self.folds) // len(np.unique(self.repeats))
        return {
            key: fold_t_test(learned, paper, n_folds=n_folds)
            for key, learned, paper in (
                ("nn", self.learned_nn, self.paper_nn),
                ("mean", self.learned_mean, self.paper_mean),
                ("log_loss", self.learned_log_loss, self.paper_log_loss),
            )
        }


@dataclasses.dataclass(frozen=True)
class FoldTest:
    """A corrected resampled paired t-test over cross-validation folds (`fold_t_test`).

    - `difference`: the mean over folds of ``scores − reference``.
    - `t`, `p_value`: the corrected statistic and its two-sided p-value (Student's t with
      ``n − 1`` degrees of freedom over the n folds). Both are NaN when every fold differs by
      the same non-zero amount (no spread to test against); ``t = 0``, ``p = 1`` when every
      fold ties (within a relative 1e-4, as `fold_better`).
    - `n`: the number of folds (of every repetition)."""

    difference: float
    t: float
    p_value: float
    n: int


def fold_t_test(scores, reference, *, n_folds: int) -> FoldTest:
    """A p-value for the mean difference between two methods' fold scores: the corrected
    resampled paired t-test of Nadeau & Bengio (2003), in the form of Bouckaert & Frank (2004)
    for repeated k-fold cross-validation.

    The folds of k-fold cross-validation share training roots (and repeated splits share
    everything), so their scores are correlated and a plain paired t-test over folds is far
    too confident. Nadeau & Bengio take the correlation between two folds' differences to be
    ``ρ = n_test / n = 1/k``, which adds ``ρ / (1 − ρ) = n_test/n_train = 1/(k − 1)`` to the
    ``1/n`` of the variance of the mean: ``t = mean(d) / sqrt((1/n + 1/(k − 1)) · var(d))``
    over the n = k·r paired fold scores d = scores − reference of r repetitions (sample
    variance), two-sided p from Student's t with n − 1 degrees of freedom. It is a
    heuristic correction (ρ is assumed, not estimated; 1/(k − 1) is exact for folds of equal
    size), the usual test for comparing learners on one small data set. The p-value is per
    comparison: adjust a family of them (e.g. `holm`) before reading several at once.

    Folds whose two scores are equal within a relative 1e-4 (`fold_better`'s tie) count as a
    difference of 0 in the test, so that a learned λ that stayed at the start is no
    "significant" difference of rounding; `difference` is the plain mean of scores − reference.

    `scores`, `reference`: one score per fold, on the same folds in the same order (from
    `fold_accuracy` or `CVAccuracy`: k·r of them); `n_folds`: k, the folds per repetition."""
    a, b = np.asarray(scores), np.asarray(reference)
    if a.shape != b.shape or a.ndim != 1 or a.size < 2:
        raise ValueError(
            "fold_t_test: scores and reference must be 1-D with one score per fold, the same "
            f"length and at least 2 folds; got shapes {a.shape} and {b.shape}."
        )
    if isinstance(n_folds, bool) or not isinstance(n_folds, (int, np.integer)) or n_folds < 2 or a.size % n_folds:
        raise ValueError(
            f"fold_t_test: n_folds (k, the folds per repetition) must be an integer >= 2 that divides the "
            f"number of scores ({a.size} = k × repetitions), got {n_folds!r}."
        )
    kind = np.result_type(a, b)
    eps = float(np.finfo(kind).eps) if np.issubdtype(kind, np.floating) else float(np.finfo(np.float64).eps)
    a, b = a.astype(np.float64), b.astype(np.float64)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InputError("fold_t_test: fold scores must be finite.")
    n = a.size
    difference = float(np.mean(a - b))
    d = np.where(_fold_ties(a, b), 0.0, a - b)
    if not np.any(d):
        return FoldTest(difference=difference, t=0.0, p_value=1.0, n=n)
    # A spread at the level of the scores' rounding is no spread: every fold differs by the
    # same amount, and any t would be the rounding's.
    if np.std(d) <= 16 * eps * float(max(np.max(np.abs(a)), np.max(np.abs(b)))):
        return FoldTest(difference=difference, t=math.nan, p_value=math.nan, n=n)
    t = float(np.mean(d)) / math.sqrt((1.0 / n + 1.0 / (n_folds - 1)) * float(np.var(d, ddof=1)))
    return FoldTest(difference=difference, t=t, p_value=float(2.0 * scipy.stats.t.sf(abs(t), n - 1)), n=n)


def _fold_ties(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per fold, whether two scores count as equal: within a relative 1e-4 (and 1e-12
    absolute), so that rounding is no win (`fold_better`, `fold_t_test`)."""
    return np.isclose(a, b, rtol=1e-4, atol=1e-12)


def fold_better(scores, reference, *, higher_is_better: bool) -> tuple[int, int, int]:
    """(better, equal, worse): fold by fold, how `scores` compare with `reference` on the same
    folds. Equal means within a relative 1e-4 (and 1e-12 absolute) of each other."""
    a, b = np.asarray(scores, np.float64), np.asarray(reference, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"fold_better: scores and reference differ in shape, {a.shape} and {b.shape}.")
    equal = _fold_ties(a, b)
    up = (a > b) if higher_is_better else (a < b)
    return int(np.sum(up & ~equal)), int(np.sum(equal)), int(np.sum(~up & ~equal))


def fold_accuracy(
    distances, labels, *, n_folds: int = 5, seed: int = 0, n_repeats: int = 1, softness: float = 0.1
) -> dict:
    """Cross-validated scores of a fixed distance matrix (no learning), on the same stratified
    folds as `nested_cv_accuracy` with the same seed and `n_repeats`: ``{"nn": ..., "mean":
    ..., "log_loss": ...}``, one entry per fold (the folds of repetition 0 first): 1-NN and
    nearest-class-mean accuracy, and the held-out NCA log-loss (`held_out_log_loss` at
    `softness`)."""
    D = np.asarray(distances, np.float64)
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise ValueError(f"fold_accuracy: distances must be a square [n, n] matrix, got shape {D.shape}.")
    if not np.all(np.isfinite(D)) or np.any(D < 0):
        raise InputError("fold_accuracy: distances must be finite and non-negative.")
    n_folds, n_repeats, seed = _check_folds(n_folds, n_repeats, seed)
    y = check_labels(labels, D.shape[0], min_per_class=n_folds)
    nn, mean, loss = [], [], []
    for _, test in _repeated_folds(y, n_folds, seed, n_repeats):
        train = np.setdiff1d(np.arange(len(y)), test)
        scores = _fold_scores(D[np.ix_(test, train)], D[np.ix_(train, train)], y[test], y[train], softness)
        for acc, score in zip((nn, mean, loss), scores):
            acc.append(score)
    return {"nn": np.asarray(nn), "mean": np.asarray(mean), "log_loss": np.asarray(loss)}


def nested_cv_accuracy(
    trees: RootTree | SRVFTree,
    labels: Sequence,
    *,
    n_folds: int = 5,
    seed: int = 0,
    n_repeats: int = 1,
    weights: Weights | None = None,
    max_reregistrations: int = 2,
    tol: float = 1e-3,
    regularisation: float | Sequence[float] = 1e-3,
    softness: float = 0.1,
    max_steps: int = 200,
    registration: RegistrationOptions | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    client=None,
    **options,
) -> CVAccuracy:
    """Held-out accuracy of learned λ against the starting (paper's) λ, by cross-validation.

    The roots are split into `n_folds` stratified folds (seeded by `seed`). For each fold, λ is
    learned (`learn_weights`) on the other folds only; the held-out roots are registered onto
    the training roots at that λ and classified by 1-NN and by the nearest class mean
    (`fold_predictions`), and scored by the held-out NCA log-loss (`held_out_log_loss`). The starting λ is scored on the same folds. Every pair is registered
    once at the starting λ (shared by the folds' first inner solves and the starting λ's
    scores); each fold then re-registers its training pairs up to `max_reregistrations` times
    and its test × training pairs once.

    `n_repeats`: repeat the whole cross-validation on this many different splits (repetition
    r uses the seed ``seed + r``; repeated stratified k-fold). On small sets one split's folds
    decide a comparison by a root or two; several splits show whether a difference holds
    beyond one split. The registrations at the starting λ are computed once and shared by
    every repetition; each fold's learning and test registrations are done per fold, so the
    cost of the learning grows with `n_repeats`.

    Every class needs at least `n_folds` members (`LabelError` otherwise, before any work).
    Other options as in `learn_weights`.
    """
    weights, opts, radii = _prepare(trees, weights, registration, options)
    n = batch_size(trees)
    n_folds, n_repeats, seed = _check_folds(n_folds, n_repeats, seed)
    y = check_labels(labels, n, min_per_class=n_folds)
    _check_options(max_reregistrations, max_steps, tol)
    fitter = _Fitter(
        trees,
        weights,
        opts,
        radii,
        chunk_size=chunk_size,
        progress=progress,
        regularisation=regularisation,
        max_steps=max_steps,
        rtol=1e-6,
        softness=softness,
        client=client,
    )
    I, J = np.triu_indices(n, 1)
    position = np.full((n, n), -1, np.int64)
    position[I, J] = np.arange(len(I))
    position[J, I] = position[I, J]
    start = fitter.register(fitter.start, I, J, "registering all pairs (start λ)")
    D0 = np.zeros((n, n))
    D0[I, J] = np.sqrt(np.maximum(start.energy, 0.0))
    D0[J, I] = D0[I, J]
    # The paper's λ is scored at the given weights (λr = 0 means no thickness, as given).
    D_paper = D0 if fitter.start is weights else _matrix_at(fitter, weights, I, J, n)

    out = {k: [] for k in "lnn lmean pnn pmean lloss ploss w folds rereg status sec reg rep".split()}
    for f, (rep, test) in enumerate(_repeated_folds(y, n_folds, seed, n_repeats)):
        train = np.setdiff1d(np.arange(n), test)
        paper = _fold_scores(D_paper[np.ix_(test, train)], D_paper[np.ix_(train, train)], y[test], y[train], softness)
        for key, score in zip(("pnn", "pmean", "ploss"), paper):
            out[key].append(score)
        li, lj = np.triu_indices(len(train), 1)
        t0 = time.perf_counter()
        res, _ = fitter.fit(
            train,
            y[train],
            regs=start.take(position[train[li], train[lj]]),
            max_reregistrations=max_reregistrations,
            tol=tol,
        )
        out["sec"].append(time.perf_counter() - t0)
        TI, TJ = (x.ravel() for x in np.meshgrid(test, train, indexing="ij"))
        name = f"fold {f + 1}" if n_repeats == 1 else f"repeat {rep + 1}, fold {f % n_folds + 1}"
        cross = fitter.register(res.weights, TI, TJ, f"{name}: test × train")
        D_tt = np.sqrt(np.maximum(cross.energy, 0.0)).reshape(len(test), len(train))
        learned = _fold_scores(D_tt, np.asarray(res.distances, np.float64), y[test], y[train], softness)
        for key, score in zip(("lnn", "lmean", "lloss"), learned):
            out[key].append(score)
        out["w"].append(res.weights.to_dict())
        out["folds"].append(test)
        out["rereg"].append(res.n_reregistrations)
        out["status"].append(res.status)
        out["reg"].append(res.regularisation)
        out["rep"].append(rep)
    return CVAccuracy(
        learned_nn=np.asarray(out["lnn"]),
        learned_mean=np.asarray(out["lmean"]),
        paper_nn=np.asarray(out["pnn"]),
        paper_mean=np.asarray(out["pmean"]),
        learned_log_loss=np.asarray(out["lloss"]),
        paper_log_loss=np.asarray(out["ploss"]),
        weights=out["w"],
        folds=out["folds"],
        n_reregistrations=np.asarray(out["rereg"]),
        status=tuple(out["status"]),
        seconds_learning=np.asarray(out["sec"]),
        regularisation=np.asarray(out["reg"]),
        repeats=np.asarray(out["rep"], np.int64),
    )


def _check_folds(n_folds, n_repeats, seed) -> tuple[int, int, int]:
    """The cross-validation's options checked before any work (registrations are slow)."""
    if isinstance(n_folds, bool) or not isinstance(n_folds, (int, np.integer)) or n_folds < 2:
        raise ValueError(f"n_folds must be an integer >= 2, got {n_folds!r}.")
    return int(n_folds), as_count(n_repeats, "n_repeats"), as_count(seed, "seed", minimum=0)


def _repeated_folds(y, n_folds: int, seed: int, n_repeats: int):
    """(repetition, test indices) of every fold: repetition r splits with seed ``seed + r``."""
    for rep in range(n_repeats):
        for test in stratified_folds(y, n_folds, seed=seed + rep):
            yield rep, test


def _matrix_at(fitter, weights, I, J, n):
    regs = fitter.register(weights, I, J, "registering all pairs (paper λ)")
    D = np.zeros((n, n))
    D[I, J] = np.sqrt(np.maximum(regs.energy, 0.0))
    D[J, I] = D[I, J]
    return D
