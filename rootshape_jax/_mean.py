"""Karcher mean of a population of roots (docs/design.md §6, paper §4).

The mean minimises ``F(μ) = (1/n) Σ_i min_g d²(μ, g·x_i)`` over SRVF trees μ, where g ranges
over rotations, reparameterisations and lateral correspondences (`register`).

The mean has the samples' K lateral slots, all treated as *real* while fitting (mask True).
A sample's null lateral matched to a slot of μ costs ``λs ||q_μ||²`` and sits at μ's position;
a slot that no sample's real lateral reaches shrinks to zero length. With the registrations
fixed, ``F`` is a weighted sum of squares in μ, minimised exactly by

- ``q0_μ = mean_i q0_i``, ``q_μk = mean_i q_ik`` (nulls count as 0), and
- ``s_μk`` = the mean attachment of the samples whose slot k is a real lateral
  (the position term only counts where both laterals are real).

At depth D > 2 (docs/design.md §11) the same holds level by level: every branch slot of μ
(second-order laterals included) is the mean of the registered samples' branches in that slot,
its attachment the mean over the samples whose slot is real. The registrations carried by the
fixed point and the rotation refit cover every level's matched branches, as the engine's.

Two solvers, both optimistix:

- ``method="fixed_point"`` (an `optx.AbstractFixedPointSolver`, by default
  `optx.FixedPointIteration`): block-coordinate descent on the joint energy
  ``J(μ, g_1..g_n)``. The iterate is μ with every sample's rotation and current registration.
  A step solves every sample's warps and lateral correspondence afresh for its rotation (one
  batched engine call, in blocks of samples through the executor) and keeps them where they
  beat the carried ones, moves μ to the exact minimiser above, and refits each rotation by
  weighted Kabsch. No sub-step can raise J, so the recorded energy never increases. Before
  it, a warm-up of Karcher steps registers every sample afresh (rotation search included) at
  every step, until F falls by less than 1 % in a step (a step that would raise F is not
  taken): carried from the start, registrations would keep each sample's rotation in the
  basin it had against the start, and the fixed point would stop in a worse local minimum.
  For small populations (`n_starts`) the warm-up runs from several central samples and the
  solve continues from the lowest F.
  The step loop is written once, on the host: the solver's `step`/`terminate` run there, so
  the per-sample work can run here or on a Dask cluster alike (docs/design.md §13).
- ``method="gradient"`` (`optx.minimise`, gradient descent by default, any optimistix
  minimiser accepted): minimises ``F`` itself, every evaluation registering all samples
  afresh under `stop_gradient` (envelope theorem), in whitened coordinates
  ``z = W^{1/2} μ`` (`_tangent.whitening`) so that a unit gradient step is the metric's own
  Karcher step; the default learning rate 1/2 moves q0 and q exactly to the mean of the
  registered samples.

Both stop when ``F`` changes by less than ``rtol`` (relative) between two steps, or when the
given optimistix solver's own criterion fires. Finally every sample is registered onto the
mean with a full registration (for the fixed point also its carried registration; the better
of the two is kept), mean laterals shorter than a threshold are dropped and reported.

The start is the medoid — under `distances` when given (e.g. from `pairwise_distances`),
otherwise under the exact lower bound of the elastic distance that needs no DP (lateral
lengths and positions, see `lower_bound_distances`) — so the result does not depend on the
order of the input. The mean's origin (SRVFs forget translation) is the mean of the samples'
origins.
"""

from __future__ import annotations

from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int
from tqdm.auto import tqdm

from ._assignment import solve
from ._curves import l2_norm_squared
from ._engine import (
    MEAN_REGISTRATION,
    RegistrationOptions,
    descendant_norms,
    register_pairs,
    registration_options,
    rotate_batch,
)
from ._errors import ConvergenceError, as_count, as_flag
from ._executor import LocalExecutor, executor_for
from ._metric import Weights, as_weights, level_weight, null_costs, pair_lower_bounds, preshape_terms, system_weights
from ._rotation import kabsch
from ._tangent import LevelParams, TreeParams, branch_weight, params_of, params_to_tree, unwhiten, whiten, whitening
from ._tree import RootTree, SRVFLevel, SRVFTree, batch_size, check_compatible, is_traced, to_curves, to_srvf

# --------------------------------------------------------------------------------------------
# Result


class KarcherMean(eqx.Module):
    """Result of `karcher_mean`.

    **Fields**

    - `mean`: the mean root's curves (`RootTree`, ``to_curves(mean_srvf)``); dropped
      laterals are null slots. Back to SRVFs and registered onto `mean_srvf` it is not at
      distance 0: on the grid, `srvf` (node values from the two adjacent segments) and its
      inverse (trapezoid integration of q|q|) are not exact inverses — a T-point polyline has
      (T − 1)·d free values, an SRVF T·d — and the mean, an average of warped SRVFs, is not the
      SRVF of any polyline. The error sits in the main and lateral terms of every real slot
      (mostly the laterals; the attachments round-trip exactly) and is of the same size as a
      sample's own curves-to-SRVF round trip. Measured (float64, relative to the median
      sample-to-mean distance): 0.27 % on the bundled 53 roots (T = 100), 0.51 % on CPlantBox
      taproots (T = 100), 2.2 % on RootNav (T = 50), 3.2 % on the arabidopsis plate (T = 100).
      Use `mean_srvf` (or `fitted`) for further computation, `mean` to draw and save.
    - `mean_srvf`: the mean as an `SRVFTree`. Its `mask` is False for dropped slots (their
      `q` is 0, their `s` is kept); every other slot is a real lateral.
    - `fitted`: the mean as fitted, every slot real and nothing dropped: the point the
      samples are registered to (and the tangent point of `tangent_pca`).
    - `registered`: ``[n]`` batched `SRVFTree`, every sample registered onto `fitted`
      (rotated, reparameterised, permuted into the mean's slot order).
    - `energies`: ``[n]`` squared distance of each sample to the fitted mean.
    - `energy`: ``F = mean(energies)``, the Karcher objective at the fitted mean.
    - `energy_trace`: F at the start and after each step (for the fixed point: the joint
      energy, an upper bound of F at that iterate), ending with the final `energy`.
    - `steps`: solver steps taken. `result`: the optimistix status (`optx.RESULTS`).
    - `init_index`: index of the sample the solver started from (the medoid, or with
      `n_starts` the central sample whose warm-up reached the lowest F), or None when it
      started from a tree given as `init`.
    - `lateral_lengths`: ``[K]`` length of each lateral of the fitted mean (before dropping).
    - `dropped`: ``[K]`` True where a fitted lateral was shorter than the threshold and dropped.
    - `weights`: the metric weights used (for `tangent_pca`); `registration`: the
      registration options used (for `project`).
    - `child_lengths`, `child_dropped` (depth D > 2): one entry per deeper level ℓ = 2 … D−1,
      shaped ``[K1, …, Kℓ]``, as `lateral_lengths` and `dropped` for that level's branches of
      the fitted mean (a dropped branch drops its children). ``()`` at depth 2.
    """

    mean: RootTree
    mean_srvf: SRVFTree
    fitted: SRVFTree
    registered: SRVFTree
    energies: Float[Array, " n"]
    energy: Float[Array, ""]
    energy_trace: Float[Array, " S"]
    steps: Int[Array, ""]
    result: optx.RESULTS
    init_index: int | None = eqx.field(static=True)
    lateral_lengths: Float[Array, " K"]
    dropped: Bool[Array, " K"]
    weights: Weights
    registration: RegistrationOptions
    child_lengths: tuple = ()
    child_dropped: tuple = ()


# --------------------------------------------------------------------------------------------
# The objective (public, differentiable in mu)


def broadcast_tree(tree, n: int):
    """`tree` repeated along a new leading axis of size n."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), tree)


def register_onto(mu: SRVFTree, samples: SRVFTree, weights: Weights, opts: RegistrationOptions, active=None):
    """Every sample registered onto the single tree mu: (registered batch, energies, rotations).
    Inactive samples (padding) do no DP work. Runs inside the caller's jit, on one device."""
    reg = register_pairs(broadcast_tree(mu, samples.q0.shape[0]), samples, weights, opts, active, split=False)
    return reg.registered, reg.energy, reg.rotation


@eqx.filter_jit
def _objective(mu: SRVFTree, samples: SRVFTree, weights: Weights, opts: RegistrationOptions):
    _, energies, _ = register_onto(mu, samples, weights, opts)
    return jnp.mean(energies)


def karcher_objective(
    mu: SRVFTree | RootTree,
    samples: SRVFTree | RootTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | dict | None = None,
) -> Float[Array, ""]:
    """The Karcher objective ``F(μ) = (1/n) Σ_i min_g d²(μ, g·x_i)``.

    `mu` is one tree, `samples` a batch with the same capacities. Every sample is registered
    onto `mu` (`registration`: a `RegistrationOptions` or a dict of its fields; default
    `MEAN_REGISTRATION`); the registrations are held under `stop_gradient`, so ``jax.grad``
    with respect to `mu` (or the weights) is the envelope-theorem gradient of F. Slots of `mu`
    count as real laterals where ``mu.mask`` is True (`karcher_mean` fits a mean with every
    slot real).
    """
    weights = as_weights(weights)
    mu = to_srvf(mu, weights=weights)
    samples = to_srvf(samples, weights=weights)
    _check_samples(samples, "karcher_objective: samples")
    if mu.batch_shape != ():
        raise ValueError(f"karcher_objective: mu must be a single tree, got batch shape {mu.batch_shape}.")
    check_compatible(mu, samples, "karcher_objective: mu and samples")
    opts = registration_options(registration, base=MEAN_REGISTRATION)
    return _objective(mu, samples, weights, opts)


def _check_samples(samples: SRVFTree, what: str) -> int:
    n = batch_size(samples)
    if n < 1:
        raise ValueError(f"{what}: empty batch; give at least one root.")
    return n


# --------------------------------------------------------------------------------------------
# Start: the medoid


def _lower_bound_energy(a: SRVFTree, b: SRVFTree, weights: Weights, assignment: str):
    """A lower bound of ``min_g d²(a, g·b)`` needing no DP: ``λm(||q0a|| − ||q0b||)²`` plus the
    optimal assignment of the laterals' lower bounds (exact null and DP-free pair costs).
    Cauchy–Schwarz bounds every DP term from below for any rotation and reparameterisation."""
    weights = system_weights(weights, a)  # a plant's axes weigh as main roots (§11)
    lam_m = level_weight(weights, "main", a.q0.dtype)
    La = l2_norm_squared(a.q) * a.mask
    Lb = l2_norm_squared(b.q) * b.mask
    both = a.mask[:, None] & b.mask[None, :]
    cauchy_schwarz = (jnp.sqrt(La)[:, None] - jnp.sqrt(Lb)[None, :]) ** 2  # of ||qa − w||², any warp
    others = null_costs(weights, a, b, La, Lb)
    if a.deeper:
        # Depth D > 2: a real lateral left unmatched also costs its whole subtree (exact).
        sub_a, sub_b = descendant_norms(a.deeper, weights, 2), descendant_norms(b.deeper, weights, 2)
        others = others + jnp.where(a.mask[:, None], sub_a[:, None], jnp.where(b.mask[None, :], sub_b[None, :], 0.0))
    C = jnp.where(both, pair_lower_bounds(weights, a, b, cauchy_schwarz), others)
    perm = solve(C, method=assignment)
    lap = jnp.sum(jnp.take_along_axis(C, perm[:, None], axis=1))
    L0a = l2_norm_squared(a.q0)
    L0b = l2_norm_squared(b.q0)
    return lam_m * (jnp.sqrt(L0a) - jnp.sqrt(L0b)) ** 2 + lap


@eqx.filter_jit
def lower_bound_distances(samples: SRVFTree, weights: Weights, assignment: str = "jax"):
    """(n, n) DP-free lower bounds of the elastic distances (symmetrised)."""
    row = jax.vmap(_lower_bound_energy, in_axes=(None, 0, None, None))
    e = jax.lax.map(lambda a: row(a, samples, weights, assignment), samples)
    e = 0.5 * (e + e.T)
    return jnp.sqrt(jnp.maximum(e, 0.0))


@eqx.filter_jit
def _zero_tree_energy(samples: SRVFTree, weights: Weights):
    """Mean squared distance of the samples from the zero tree (no registration): F's scale."""
    weights = system_weights(weights, samples)
    dtype = samples.q0.dtype
    lam_m = level_weight(weights, "main", dtype)
    lam_s = level_weight(weights, "lateral", dtype)
    e = lam_m * l2_norm_squared(samples.q0) + lam_s * jnp.sum(l2_norm_squared(samples.q), axis=-1)
    for level, lv in enumerate(samples.deeper, start=2):
        lam = branch_weight(weights, level, dtype)
        e = e + lam * jnp.sum(l2_norm_squared(lv.q).reshape(e.shape + (-1,)), axis=-1)
    return jnp.mean(e)


def _medoid(distances, n: int) -> int:
    if np.shape(distances) != (n, n):
        raise ValueError(f"distances has shape {np.shape(distances)}, expected ({n}, {n}) for {n} samples.")
    D = np.asarray(distances, dtype=np.float64)  # as given: the medoid of the matrix itself
    if not np.all(np.isfinite(D)):
        raise ValueError("distances contains NaN or inf; pass a finite distance matrix.")
    if np.any(D < 0):
        raise ValueError("distances must be non-negative (a distance matrix, e.g. from pairwise_distances).")
    return int(np.argmin(np.sum(D**2, axis=1)))


# --------------------------------------------------------------------------------------------
# Fixed point: the iterate and its two halves


class CarriedLevel(eqx.Module):
    """One deeper level ℓ ≥ 2 of each sample's carried registration, without its rotation:
    warped branches in the mean's slots ``[n, K1, …, Kℓ, T, C]``, their attachments and 1.0
    where the slot holds a real branch ``[n, K1, …, Kℓ]`` (floats, as every iterate leaf:
    fixed-point solvers do arithmetic on the iterate)."""

    warped_q: Float[Array, "n *P K T C"]
    reg_s: Float[Array, "n *P K"]
    reg_real: Float[Array, "n *P K"]


class FPIterate(eqx.Module):
    """The fixed point's iterate: the mean, each sample's rotation, and each sample's current
    registration without its rotation (warped main root, warped laterals permuted into the
    mean's slots, their attachments, 1.0 where the slot holds a real lateral, with a
    thickness channel the registered starting radii, and at depth D > 2 one `CarriedLevel`
    per deeper level)."""

    mu: TreeParams
    rotations: Float[Array, "n d d"]
    warped_q0: Float[Array, "n T C"]
    warped_q: Float[Array, "n K T C"]
    reg_s: Float[Array, "n K"]
    reg_real: Float[Array, "n K"]
    reg_base: Float[Array, "n K1"] | None
    reg_deeper: tuple[CarriedLevel, ...] = ()


def _carry_deeper(registered: SRVFTree, O_inv) -> tuple[CarriedLevel, ...]:
    """The deeper levels of registered trees as carried (rotation `O_inv` undoes theirs)."""
    return tuple(CarriedLevel(rotate_batch(lv.q, O_inv), lv.s, lv.mask.astype(lv.s.dtype)) for lv in registered.deeper)


def _start_iterate(mu: TreeParams, registered: SRVFTree, O) -> FPIterate:
    q0, q = rotate_batch(registered.q0, _transpose(O)), rotate_batch(registered.q, _transpose(O))
    real = registered.mask.astype(mu.q0.dtype)
    deeper = _carry_deeper(registered, _transpose(O))
    return FPIterate(mu, O, q0, q, registered.s, real, registered.base_radius, deeper)


def _transpose(O):
    return jnp.swapaxes(O, -1, -2)


def _carried(y: FPIterate, mu: SRVFTree, O, samples: SRVFTree) -> SRVFTree:
    """The carried registrations, rotated, as registered trees in mu's slot order."""
    real = y.reg_real > 0.5
    q0 = rotate_batch(y.warped_q0, O)
    q = rotate_batch(y.warped_q, O) * real[..., None, None]
    s = jnp.where(real, y.reg_s, mu.s[None])
    deeper = []
    for cl, lm, lv in zip(y.reg_deeper, mu.deeper, samples.deeper):
        r = cl.reg_real > 0.5
        deeper.append(
            SRVFLevel(
                q=rotate_batch(cl.warped_q, O) * r[..., None, None],
                s=jnp.where(r, cl.reg_s, lm.s[None]),
                mask=r,
                base_radius=lv.base_radius,
            )
        )
    return SRVFTree(
        q0=q0,
        q=q,
        s=s,
        mask=real,
        origin=samples.origin,
        base_radius=y.reg_base,
        thickness_scale=samples.thickness_scale,
        deeper=tuple(deeper),
        virtual_main=samples.virtual_main,
    )


def _pick(better, new, old):
    n = better.shape[0]
    return jax.tree.map(lambda u, v: jnp.where(better.reshape((n,) + (1,) * (u.ndim - 1)), u, v), new, old)


def _project_rotation(O):
    """Nearest proper rotation (polar factor, determinant corrected); a no-op on rotations.
    Guards against solvers that average iterates (e.g. a damped fixed point)."""
    U, _, Vt = jnp.linalg.svd(O)
    det = jnp.linalg.det(U @ Vt)
    D = jnp.ones(O.shape[:-1], O.dtype).at[..., -1].set(jnp.where(det < 0, -1.0, 1.0))
    return (U * D[..., None, :]) @ Vt


def _mean_attachment(mask, s, fallback):
    """Mean attachment over the samples whose slot is real; `fallback` where none is."""
    m = mask.astype(s.dtype)
    count = jnp.sum(m, axis=0)
    s_sum = jnp.sum(m * s, axis=0)
    return jnp.where(count > 0, s_sum / jnp.maximum(count, 1), fallback)


def _exact_update(registered: SRVFTree, mu_s, deeper_s=None) -> TreeParams:
    """The minimiser of F over mu for fixed registrations (module docstring), level by level:
    q the mean of the registered branches (nulls count 0), s the mean attachment of the samples
    whose slot is real, or mu's own where none is (`mu_s`, and `deeper_s` one per deeper
    level; by default the registered trees', which hold mu's attachment in null slots)."""
    s = _mean_attachment(registered.mask, registered.s, mu_s)
    if deeper_s is None:
        deeper_s = tuple(lv.s[0] for lv in registered.deeper)
    deeper = tuple(
        LevelParams(jnp.mean(lv.q, axis=0), _mean_attachment(lv.mask, lv.s, fallback))
        for lv, fallback in zip(registered.deeper, deeper_s)
    )
    return TreeParams(jnp.mean(registered.q0, axis=0), jnp.mean(registered.q, axis=0), s, deeper)


def _rotate_samples(samples: SRVFTree, O) -> SRVFTree:
    """Every branch of every sample rotated by its rotation (spatial channels)."""
    out = eqx.tree_at(lambda t: (t.q0, t.q), samples, (rotate_batch(samples.q0, O), rotate_batch(samples.q, O)))
    if not samples.deeper:
        return out
    deeper = tuple(eqx.tree_at(lambda lv: lv.q, lv, rotate_batch(lv.q, O)) for lv in samples.deeper)
    return eqx.tree_at(lambda t: t.deeper, out, deeper)


def fp_register(y: FPIterate, samples: SRVFTree, mu_like: SRVFTree, weights: Weights, opts, active=None):
    """Per-sample half of a fixed-point step (a block of samples, with their rows of y): each
    sample's registration onto the current mean, and its energy.

    Three programs, not one: the fresh registration is `_full_registration`'s own program (the
    rotation off is a traced option), so the engine, most of the mean's compile time, is
    compiled once for the warm-up's full registrations and the fixed point's steps."""
    old, e_old, xb = _fp_carried(y, samples, mu_like, weights)
    # ... against warps and correspondence solved afresh for the current rotation. The DP is
    # exact for its own discretisation of the warp energy, not for the grid energy used here,
    # so the fresh solution is kept only where it is better: the energy never increases.
    new, e_new, _ = _full_registration(y.mu, xb, mu_like, weights, opts.without_rotation(), active)
    return _keep_better(new, e_new, old, e_old)


@eqx.filter_jit
def _fp_carried(y: FPIterate, samples: SRVFTree, mu_like: SRVFTree, weights: Weights):
    """The carried registration at the current mean and rotation, its energy, and the samples
    turned by their rotations (what a fresh registration without rotation search starts from)."""
    n = samples.q0.shape[0]
    mu = params_to_tree(y.mu, mu_like)
    O = _project_rotation(y.rotations)
    old = _carried(y, mu, O, samples)
    e_old = preshape_terms(broadcast_tree(mu, n), old, weights).total
    return old, e_old, _rotate_samples(samples, O)


@eqx.filter_jit
def _keep_better(new: SRVFTree, e_new, old: SRVFTree, e_old):
    better = e_new < e_old
    return _pick(better, new, old), jnp.where(better, e_new, e_old)


@eqx.filter_jit
def fp_update(y: FPIterate, registered: SRVFTree, energies, weights: Weights):
    """Global half of a fixed-point step: the exact mean update and each rotation's refit."""
    O = _project_rotation(y.rotations)
    energy = jnp.mean(energies)
    mu_new = _exact_update(registered, y.mu.s, tuple(lp.s for lp in y.mu.deeper))
    d = O.shape[-1]
    # Refit each rotation (weighted Kabsch, spatial channels) against the new mean, over every
    # matched branch of every level (the mean's slots are all real), as the engine's refit.
    w0, wq = rotate_batch(registered.q0, _transpose(O)), rotate_batch(registered.q, _transpose(O))
    deeper = _carry_deeper(registered, _transpose(O))
    dtype = mu_new.q0.dtype
    T, C = mu_new.q0.shape
    A = jnp.concatenate([mu_new.q0[None], mu_new.q] + [lp.q.reshape(-1, T, C) for lp in mu_new.deeper], axis=0)
    A = A[..., :d]
    # The refit weighs branches as the engine does: a plant's axes as main roots (§11).
    weights = system_weights(weights, registered)
    lam_m = branch_weight(weights, 0, dtype)
    lam_s = branch_weight(weights, 1, dtype)
    lam_deeper = [branch_weight(weights, level, dtype) for level in range(2, 2 + len(deeper))]

    def refit(b0, bq, mask, bdeep, O_old):
        Bm = jnp.concatenate([b0[None], bq] + [cl.warped_q.reshape(-1, T, C) for cl in bdeep], axis=0)[..., :d]
        w = jnp.concatenate(
            [lam_m[None], lam_s * mask.astype(dtype)]
            + [lam * (cl.reg_real > 0.5).reshape(-1).astype(dtype) for lam, cl in zip(lam_deeper, bdeep)]
        )
        O_new = kabsch(A, Bm, w)
        # Degenerate data (all weights zero) gives no information: keep the old rotation.
        return jnp.where(jnp.sum(w) > 0, O_new, O_old)

    O_new = jax.vmap(refit)(w0, wq, registered.mask, deeper, O)
    real = registered.mask.astype(dtype)
    return FPIterate(mu_new, O_new, w0, wq, registered.s, real, registered.base_radius, deeper), energy


# --------------------------------------------------------------------------------------------
# Blocks of samples through the executor (docs/design.md §13)


def _tree_to_dict(prefix: str, tree) -> dict:
    leaves = jax.tree.leaves(tree)
    return {f"{prefix}{i}": np.asarray(x) for i, x in enumerate(leaves)}


def _dict_to_tree(prefix: str, d: dict, like):
    leaves, treedef = jax.tree.flatten(like)
    return jax.tree.unflatten(treedef, [d[f"{prefix}{i}"] for i in range(len(leaves))])


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


def mean_step_block(idx, n_valid, y_rows, samples, mu, mu_like, weights, opts) -> dict:
    """Block function: one fixed-point registration step for the samples `idx` (padded)."""
    y = FPIterate(mu, *y_rows)
    active = jnp.arange(len(idx)) < n_valid
    registered, energies = fp_register(y, _take(samples, idx), mu_like, weights, opts, active)
    out = _tree_to_dict("reg_", _take(registered, slice(0, n_valid)))
    out["energies"] = np.asarray(energies)[:n_valid]
    return out


def mean_full_block(idx, n_valid, samples, mu, mu_like, weights, opts) -> dict:
    """Block function: full registration (rotation search) of the samples `idx` onto mu."""
    active = jnp.arange(len(idx)) < n_valid
    registered, energies, O = _full_registration(mu, _take(samples, idx), mu_like, weights, opts, active)
    out = _tree_to_dict("reg_", _take(registered, slice(0, n_valid)))
    out["energies"] = np.asarray(energies)[:n_valid]
    out["rotations"] = np.asarray(O)[:n_valid]
    return out


@eqx.filter_jit
def _full_registration(mu: TreeParams, samples, mu_like, weights, opts, active=None):
    return register_onto(params_to_tree(mu, mu_like), samples, weights, opts, active)


class _SampleBlocks:
    """The samples cut into blocks of `block_size` (padded with the block's first sample, as
    inactive lanes that do no work, so every block has one shape and one compiled program),
    mapped by an executor; with `progress`, a bar of samples per registration pass."""

    def __init__(self, executor, samples: SRVFTree, block_size: int | None, *, progress: bool = False):
        n = samples.q0.shape[0]
        size = n if block_size is None else min(block_size, n)
        self.executor = executor
        self.samples = samples
        self.spans = [(a, min(a + size, n)) for a in range(0, n, size)]
        self.size = size
        self.progress = progress

    def _index(self, a, z):
        return np.concatenate([np.arange(a, z), np.full(self.size - (z - a), a)]).astype(np.int32)

    def map(self, fn, per_block, shared, like):
        blocks = [(self._index(a, z), z - a, *per_block(a, z)) for a, z in self.spans]
        results, _ = self.executor.map_blocks(
            fn,
            blocks,
            shared=(self.samples, *shared),
            sizes=[z - a for a, z in self.spans],
            progress=self.progress and len(self.spans) > 1,
            desc="registering",
            unit="root",
            leave=False,
        )
        merged = {k: np.concatenate([r[k] for r in results]) for k in results[0]}
        registered = jax.tree.map(jnp.asarray, _dict_to_tree("reg_", merged, like))
        rest = {k: jnp.asarray(v) for k, v in merged.items() if not k.startswith("reg_")}
        return registered, rest

    def full_registration(self, mu, mu_like, weights, opts):
        registered, rest = self.map(mean_full_block, lambda a, z: (), (mu, mu_like, weights, opts), self.samples)
        return registered, rest["energies"], rest["rotations"]

    def step(self, y: FPIterate, mu_like, weights, opts):
        rows = (y.rotations, y.warped_q0, y.warped_q, y.reg_s, y.reg_real, y.reg_base, y.reg_deeper)

        def per_block(a, z):
            return (_take(rows, self._index(a, z)),)

        return self.map(mean_step_block, per_block, (y.mu, mu_like, weights, opts), self.samples)


# --------------------------------------------------------------------------------------------
# The fixed-point loop (once, on the host)


def _flat(trace, atol, rtol) -> bool:
    return len(trace) >= 2 and abs(trace[-2] - trace[-1]) <= atol + rtol * abs(trace[-1])


def _solve_fixed_point(y, blocks: _SampleBlocks, mu_like, weights, opts, solver, *, rtol, atol, max_steps, bar):
    """Run an optimistix fixed-point solver's init/step/terminate with our step function,
    stopping also when F changes by at most ``atol + rtol|F|``. Returns (y, F trace, steps,
    result)."""

    def fn(y, args):
        registered, rest = blocks.step(y, mu_like, weights, opts)
        return fp_update(y, registered, rest["energies"], weights)

    f_struct, aux_struct = jax.eval_shape(lambda: (y, jnp.zeros((), y.mu.q0.dtype)))
    tags = frozenset()
    state = solver.init(fn, y, None, {}, f_struct, aux_struct, tags)
    trace: list[float] = []
    result = optx.RESULTS.nonlinear_max_steps_reached
    for _ in range(max_steps):
        y, state, energy = solver.step(fn, y, None, {}, state, tags)
        trace.append(float(energy))
        bar.set_postfix_str(f"F = {trace[-1]:.6g}")
        bar.update(1)
        done, res = solver.terminate(fn, y, None, {}, state, tags)
        if _flat(trace, atol, rtol):
            result = optx.RESULTS.successful
            break
        if bool(done):
            result = res
            break
    return y, trace, len(trace), result


# Rounds of the fixed point: after a solve, a full registration (rotation search included) at
# its result may find better registrations; the solve then restarts from them.
_MAX_ROUNDS = 4


@eqx.filter_jit
def _combine(y: FPIterate, full, samples: SRVFTree, mu_like, weights):
    """The better of the carried registration and a full registration, per sample."""
    registered, energies, O = full
    n = samples.q0.shape[0]
    mu = params_to_tree(y.mu, mu_like)
    O_c = _project_rotation(y.rotations)
    carried = _carried(y, mu, O_c, samples)
    e_c = preshape_terms(broadcast_tree(mu, n), carried, weights).total
    better = energies < e_c
    return (
        _pick(better, registered, carried),
        jnp.where(better, energies, e_c),
        _pick(better, O, O_c),
        jnp.mean(e_c),
    )


# Warm-up: while the mean still moves far, every sample is registered afresh (rotation search
# included) at every step; carried registrations would lock each sample's rotation into the
# basin it had against the start (the medoid), and the fixed point then settles in a worse
# local minimum (on 3D taproots, ~2 % above; see BENCHMARKS.md, "Karcher mean optimum").
_WARMUP_RTOL = 1e-2

_exact_update_jit = eqx.filter_jit(_exact_update)


def _warm_up(mu0, blocks, mu_like, weights, opts, *, atol, n_steps, bar, label="warm-up"):
    """Karcher steps with fresh full registrations until F falls by less than
    ``_WARMUP_RTOL`` (relative) in a step, or stops falling (that step is undone). Returns the
    mean, its full registrations and the F trace."""
    registered, energies, O = blocks.full_registration(mu0, mu_like, weights, opts)
    mu, F = mu0, float(jnp.mean(energies))
    trace = [F]
    for k in range(n_steps):
        mu_new = _exact_update_jit(registered, mu.s, tuple(lp.s for lp in mu.deeper))
        reg_new, e_new, O_new = blocks.full_registration(mu_new, mu_like, weights, opts)
        F_new = float(jnp.mean(e_new))
        if not F_new < F - atol:
            break
        mu, registered, energies, O = mu_new, reg_new, e_new, O_new
        trace.append(F_new)
        bar.set_postfix_str(f"F = {F_new:.6g} ({label}, step {k + 1})")
        if F - F_new <= _WARMUP_RTOL * abs(F_new):
            break
        F = F_new
    return mu, registered, O, trace


def _fixed_point(
    mu0s, samples, mu_like, weights, opts, solver, *, rtol, atol, max_steps, throw, blocks, progress, warm_up_steps
):
    """`mu0s`: candidate starts; each is warmed up and the solve continues from the one with the
    lowest F. Returns (..., index of the chosen start in `mu0s`)."""
    with tqdm(desc="mean (fixed point)", unit="step", disable=not progress) as bar:
        best = None
        for i, mu0 in enumerate(mu0s):
            # The bar counts the chosen start's steps only (as `steps` does); a warm-up shows
            # its progress in the bar's text.
            label = f"warm-up of start {i + 1}/{len(mu0s)}" if len(mu0s) > 1 else "warm-up"
            cand = _warm_up(mu0, blocks, mu_like, weights, opts, atol=atol, n_steps=warm_up_steps, bar=bar, label=label)
            if best is None or cand[3][-1] < best[1][3][-1]:
                best = (i, cand)
        chosen, (mu, registered, O, warm) = best
        bar.update(len(warm) - 1)
        y = _start_iterate(mu, registered, O)
        # The solve's first record is the energy at the warm-up's last mean: not twice.
        traces, steps = list(warm[:-1]), len(warm) - 1
        for _ in range(_MAX_ROUNDS):
            y, trace, n_steps, result = _solve_fixed_point(
                y, blocks, mu_like, weights, opts, solver, rtol=rtol, atol=atol, max_steps=max_steps, bar=bar
            )
            traces += trace
            steps += n_steps
            full = blocks.full_registration(y.mu, mu_like, weights, opts)
            registered, energies, O, e_carried = _combine(y, full, samples, mu_like, weights)
            F, F_carried = float(jnp.mean(energies)), float(e_carried)
            if result != optx.RESULTS.successful or F >= F_carried - (atol + rtol * abs(F_carried)):
                break
            y = _start_iterate(y.mu, registered, O)
    if throw and result != optx.RESULTS.successful:
        raise ConvergenceError(
            f"karcher_mean: the fixed point reached the maximum number of steps ({max_steps}) "
            f"without converging ({result}); raise max_steps or rtol, or pass throw=False."
        )
    return y.mu, np.asarray(traces), steps, result, registered, energies, chosen


# --------------------------------------------------------------------------------------------
# Gradient


class _MonitorState(eqx.Module):
    inner: Any
    trace: Float[Array, " S"]
    count: Int[Array, ""]


class _MonitoredMinimiser(optx.AbstractMinimiser):
    """Wraps an optimistix minimiser: records F at every accepted iterate (a rejected line
    search step leaves the iterate unchanged and is not recorded) and also stops when F
    changes by less than ``atol + rtol|F|`` between two accepted iterates."""

    inner: optx.AbstractMinimiser
    rtol: float
    atol: float
    size: int = eqx.field(static=True)
    norm: Any = optx.max_norm  # unused; optimistix solvers declare one

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _MonitorState(inner, jnp.full((self.size,), jnp.nan, aux_struct.dtype), jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        y_new, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        # The energy of the returned iterate: optimistix's gradient / quasi-Newton solvers keep
        # it in `f_info`; their returned aux may belong to the previous iterate.
        f_info = getattr(inner, "f_info", None)
        energy = f_info.f if f_info is not None and hasattr(f_info, "f") else aux
        moved = jnp.any(jnp.stack([jnp.any(a != b) for a, b in zip(jax.tree.leaves(y_new), jax.tree.leaves(y))]))
        record = (state.count == 0) | moved
        trace = jnp.where(record, state.trace.at[state.count].set(energy, mode="drop"), state.trace)
        return y_new, _MonitorState(inner, trace, state.count + record.astype(state.count.dtype)), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        k = state.count
        last = state.trace[jnp.maximum(k - 1, 0)]
        prev = state.trace[jnp.maximum(k - 2, 0)]
        flat = (k >= 2) & (jnp.abs(prev - last) <= self.atol + self.rtol * jnp.abs(last))
        return done | flat, optx.RESULTS.where(flat, optx.RESULTS.successful, result)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


def _gradient_fn(z: TreeParams, args):
    samples, mu_like, weights, opts, c = args
    _, energies, _ = register_onto(params_to_tree(unwhiten(z, c), mu_like), samples, weights, opts)
    f = jnp.mean(energies)
    return f, jax.lax.stop_gradient(f)


@eqx.filter_jit
def _solve_gradient(mu0: TreeParams, samples, mu_like, weights, opts, solver, max_steps, throw):
    c = whitening(system_weights(weights, mu_like), mu0.q0.shape[0], mu0.q0.dtype, depth=2 + len(mu0.deeper))
    sol = optx.minimise(
        _gradient_fn,
        solver,
        whiten(mu0, c),
        (samples, mu_like, weights, opts, c),
        has_aux=True,
        max_steps=max_steps,
        throw=throw,
    )
    return unwhiten(sol.value, c), sol.state.trace, sol.state.count, sol.stats["num_steps"], sol.result


# --------------------------------------------------------------------------------------------
# Driver


def _start_indices(init, distances, samples, weights, opts, n, n_starts: int) -> list[int]:
    """The start (an index), or the `n_starts` most central samples, the medoid first."""
    if isinstance(init, (int, np.integer)) and not isinstance(init, bool):
        if not 0 <= init < n:
            raise ValueError(f"init index {init} is out of range for {n} samples.")
        return [int(init)]
    if init == "medoid":
        if distances is None:
            distances = lower_bound_distances(samples, weights, opts.assignment)
        medoid = _medoid(distances, n)
        D = np.asarray(distances, dtype=np.float64)
        order = [i for i in np.argsort(np.sum(D**2, axis=1), kind="stable") if i != medoid]
        return [medoid] + [int(i) for i in order[: n_starts - 1]]
    raise ValueError(f"init must be 'medoid', a sample index or a single tree, got {init!r}.")


def _start_tree(init: RootTree | SRVFTree, samples: SRVFTree, weights: Weights) -> SRVFTree:
    """`init` given as a tree, checked against the samples and as an SRVF tree."""
    tree = to_srvf(init, weights=weights)
    if tree.batch_shape != ():
        raise ValueError(
            f"karcher_mean: init must be a single tree, got a batch of shape {tree.batch_shape}; "
            "pick one with jax.tree.map(lambda x: x[i], trees)."
        )
    check_compatible(tree, samples, "karcher_mean: init and trees")
    if tree.q0.dtype != samples.q0.dtype:
        raise ValueError(
            f"karcher_mean: init has dtype {tree.q0.dtype} and the trees {samples.q0.dtype}; "
            "build both with the same dtype (batch(..., dtype=...))."
        )
    return tree


# Populations up to this size are warmed up from several central samples by default: the
# start decides the basin (measured: 1.7 % apart on 15 arabidopsis seedlings), and for small
# n the extra warm-ups are cheap.
_MULTI_START_MAX_N = 16
_MULTI_STARTS = 4
# Largest local block of samples: a full registration of 32 CPlantBox pea roots (T = 100, ~20
# laterals) takes ~5 s on one core, so the progress bar moves at least that often.
_LOCAL_BLOCK = 32


def _base_radius_mean(registered: SRVFTree):
    if registered.base_radius is None:
        return None
    m = jnp.concatenate([jnp.ones_like(registered.mask[:, :1]), registered.mask], axis=1).astype(registered.s.dtype)
    count = jnp.sum(m, axis=0)
    return jnp.where(count > 0, jnp.sum(m * registered.base_radius, axis=0) / jnp.maximum(count, 1), 0.0)


def _drop_deeper(fitted: SRVFTree, lengths, keep, min_lateral_length):
    """Lengths and kept branches of the fitted mean's deeper levels: a branch is kept when at
    least `min_lateral_length` long (default 2 % of its parent's length, as the laterals
    against the main root) and its parent is kept."""
    out_lengths, out_keep = [], []
    parent_len, parent_keep = lengths, keep
    for lv in fitted.deeper:
        L = l2_norm_squared(lv.q)
        thr = 0.02 * parent_len[..., None] if min_lateral_length is None else jnp.asarray(min_lateral_length)
        k = (L >= thr) & parent_keep[..., None]
        out_lengths.append(L)
        out_keep.append(k)
        parent_len, parent_keep = L, k
    return tuple(out_lengths), tuple(out_keep)


def karcher_mean(
    trees: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    method: Literal["fixed_point", "gradient"] = "fixed_point",
    solver: optx.AbstractFixedPointSolver | optx.AbstractMinimiser | None = None,
    rtol: float = 1e-4,
    atol: float = 0.0,
    max_steps: int = 50,
    throw: bool = True,
    init: Literal["medoid"] | int | RootTree | SRVFTree = "medoid",
    distances: Array | np.ndarray | None = None,
    min_lateral_length: float | None = None,
    registration: RegistrationOptions | dict | None = None,
    warm_up_steps: int = 10,
    n_starts: int | None = None,
    client=None,
    block_size: int = 64,
    progress: bool = False,
) -> KarcherMean:
    """Karcher mean of a batch of roots: ``argmin_μ (1/n) Σ_i min_g d²(μ, g·x_i)``.

    **Arguments**

    - `trees`: a batched `RootTree` or `SRVFTree` (`rootshape_jax.batch(roots)`); the mean
      has the same capacities (T, K, d) and dtype.
    - `weights`: metric weights λ (`Weights`).
    - `method`: ``"fixed_point"`` (default; carried registrations, one registration pass per
      step, energy never increases) or ``"gradient"`` (`optx.minimise` on F, a full
      registration per evaluation).
    - `solver`: an optimistix fixed-point solver (fixed point; default
      ``optx.FixedPointIteration`` with tolerances 0, so F's relative change decides) or
      minimiser (gradient; default ``optx.GradientDescent(learning_rate=0.5)`` in whitened
      coordinates, where 0.5 is the exact Karcher step). Either stops when the solver's own
      criterion or the relative change of F fires.
    - `rtol`, `atol`: stop when ``|ΔF| <= atol + rtol·|F|`` between two steps (plus 10 ε times
      the samples' mean squared norm, below which a change is rounding).
    - `max_steps`, `throw`: step limit per solve; at the limit, ``throw=True`` raises
      `ConvergenceError` and ``throw=False`` returns with `result` =
      ``optx.RESULTS.nonlinear_max_steps_reached``. The fixed point ends each solve with a
      full registration of every sample onto its result; where that finds better
      registrations the solve restarts from them (at most 4 solves). `steps` counts them all.
    - `warm_up_steps`: the fixed point first takes up to this many Karcher steps with every
      sample registered afresh (rotation search included), until F falls by less than 1 % in
      a step; only then does it carry registrations from step to step. Carried from the very
      start, each sample's rotation stays in the basin it had against the start (the medoid)
      and the fixed point can settle in a worse local minimum (measured: 1.7 % above gradient
      descent on CPlantBox taproots in 3D; BENCHMARKS.md). 0 turns the warm-up off.
    - `n_starts`: with ``init="medoid"`` (fixed point), warm up from the medoid and the next
      most central samples, this many in all, and continue from the one with the lowest F
      (the start can decide the local minimum). Default 4 for at most 16 samples, else 1.
    - `init`: ``"medoid"``, the index of the sample to start from, or a single tree (a
      `RootTree` or `SRVFTree` with the samples' capacities and dtype, e.g. another mean's
      `fitted`) to start from; its null slots start as zero-length laterals, as a sample's.
    - `distances`: an ``(n, n)`` distance matrix (e.g. `pairwise_distances(trees)`) for the
      medoid; without it the medoid of the DP-free lower bound of the elastic distance is used.
    - `min_lateral_length`: mean laterals shorter than this are dropped at the end; default
      2 % of the mean's main-root length (for plants' systems, ``read_rsml(..., by="plant")``:
      2 % of the mean's longest axis). At depth D > 2 the same applies to every branch
      against its parent (default 2 % of the parent's length; one value given applies to
      every level), and a dropped branch drops its children.
    - `registration`: a `RegistrationOptions` (or a dict of its fields, on top of
      `MEAN_REGISTRATION`, the default), used for every registration.
    - `client`: a ``dask.distributed.Client`` (extra ``rootshape_jax[dask]``): the fixed
      point's registrations of every sample onto the current mean run on the cluster, in
      blocks of `block_size` samples, through the same functions as the local path. Fixed
      point only. The default medoid start is computed locally (O(n²) assignments): for large
      n pass `distances` or `init`.
    - `progress`: show a progress bar of the fixed point's steps with the current F.

    **Returns** a `KarcherMean`: the mean (`mean`, curves in the trees' frame and unit),
    each root's squared distance to it (`energies`) at the registrations it was fitted with
    (`registered`), the objective, the solver's status and steps. The metric ignores
    rotation, so the mean's orientation is that of its starting root, as moved by the fit:
    `upright_rotation(result.mean, trees)` and `turn_about_base` point it like the roots.
    For a root's distance to the mean, read `energies`: `distance(result.mean, x)` registers
    again with `register`'s options and may land in another local optimum.
    """
    weights = as_weights(weights)
    if method not in ("fixed_point", "gradient"):
        raise ValueError(f"method must be 'fixed_point' or 'gradient', got {method!r}.")
    max_steps = as_count(max_steps, "max_steps")
    warm_up_steps = as_count(warm_up_steps, "warm_up_steps", minimum=0)
    if not (rtol >= 0 and atol >= 0):
        raise ValueError(f"rtol and atol must be >= 0, got rtol={rtol!r}, atol={atol!r}.")
    if not isinstance(trees, (RootTree, SRVFTree)):
        raise TypeError(
            f"karcher_mean: trees must be a batched RootTree or SRVFTree (rootshape_jax.batch), "
            f"got {type(trees).__name__}."
        )
    if is_traced(trees, weights, init, distances):
        raise TypeError(
            "karcher_mean cannot run under jax.jit or jax.vmap: its steps are driven from Python (progress, "
            "convergence checks, blocks on worker threads), each a compiled program already. Call it "
            "outside jit; for a differentiable objective inside your own code use karcher_objective."
        )
    samples = to_srvf(trees, weights=weights)
    n = _check_samples(samples, "karcher_mean: trees")
    opts = registration_options(registration, base=MEAN_REGISTRATION)
    if client is not None:
        if method != "fixed_point":
            raise ValueError(f"karcher_mean: client= runs method='fixed_point' only (got method={method!r}).")
        block_size = as_count(block_size, "block_size")
    executor = executor_for(client)
    if n_starts is None:
        n_starts = _MULTI_STARTS if n <= _MULTI_START_MAX_N else 1
    n_starts = as_count(n_starts, "n_starts")
    throw = as_flag(throw, "karcher_mean: throw")
    if min_lateral_length is not None and not (
        np.ndim(min_lateral_length) == 0 and float(min_lateral_length) >= 0  # NaN fails too
    ):
        raise ValueError(f"karcher_mean: min_lateral_length must be a number >= 0, got {min_lateral_length!r}.")
    if isinstance(init, (RootTree, SRVFTree)):
        first = _start_tree(init, samples, weights)
        starts, candidates = [None], [first]
    else:
        starts = _start_indices(init, distances, samples, weights, opts, n, n_starts if method == "fixed_point" else 1)
        candidates = [jax.tree.map(lambda x, i=i: x[i], samples) for i in starts]
        first = candidates[0]
    start = starts[0]
    mu0 = params_of(first)
    origin = jnp.mean(samples.origin, axis=0)
    mu_like = eqx.tree_at(lambda t: t.origin, first, origin)
    # Tolerances: below ~10 ε times the problem's scale (the energy of the zero tree) a change
    # of F is rounding.
    dtype = samples.q0.dtype
    scale = float(_zero_tree_energy(samples, weights))
    tol_a = float(atol) + 10 * float(jnp.finfo(dtype).eps) * scale
    if method == "fixed_point":
        inner = solver if solver is not None else optx.FixedPointIteration(rtol=0.0, atol=0.0)
        if not isinstance(inner, optx.AbstractFixedPointSolver):
            raise TypeError(
                "method='fixed_point' needs an optimistix fixed-point solver (e.g. "
                f"optx.FixedPointIteration), got {type(inner).__name__}."
            )
        # Locally one block per worker thread (every core), at most _LOCAL_BLOCK samples so that
        # progress moves every few seconds; on a cluster blocks of `block_size`.
        if isinstance(executor, LocalExecutor):
            size = min(-(-n // executor.n_workers()), _LOCAL_BLOCK)
        else:
            size = block_size
        blocks = _SampleBlocks(executor, samples, size, progress=progress)
        mu0s = [params_of(c) for c in candidates]
        mu, trace, steps, result, registered, energies, chosen = _fixed_point(
            mu0s,
            samples,
            mu_like,
            weights,
            opts,
            inner,
            rtol=float(rtol),
            atol=tol_a,
            max_steps=max_steps,
            throw=throw,
            blocks=blocks,
            progress=progress,
            warm_up_steps=warm_up_steps,
        )
        start = starts[chosen]
    else:
        inner = solver if solver is not None else optx.GradientDescent(learning_rate=0.5, rtol=0.0, atol=0.0)
        if not isinstance(inner, optx.AbstractMinimiser):
            raise TypeError(
                "method='gradient' needs an optimistix minimiser (e.g. optx.GradientDescent, "
                f"optx.BFGS), got {type(inner).__name__}."
            )
        wrapped = _MonitoredMinimiser(inner, jnp.asarray(rtol, dtype), jnp.asarray(tol_a, dtype), max_steps + 1)
        # optimistix's own throw raises inside jit (an EquinoxRuntimeError); raise ours instead.
        mu, trace, count, steps, result = _solve_gradient(
            mu0, samples, mu_like, weights, opts, wrapped, max_steps, False
        )
        if throw and result != optx.RESULTS.successful:
            raise ConvergenceError(
                f"karcher_mean: gradient descent reached the maximum number of steps ({max_steps}) "
                f"without converging ({result}); raise max_steps or rtol, or pass throw=False."
            )
        trace = np.asarray(trace)[: int(count)]
        registered, energies, _ = _full_registration(mu, samples, mu_like, weights, opts)

    energy = jnp.mean(energies)
    trace = jnp.concatenate([jnp.asarray(trace, energy.dtype), energy[None]])
    fitted = params_to_tree(mu, mu_like, base_radius=_base_radius_mean(registered))
    lengths = l2_norm_squared(fitted.q)
    # Laterals shorter than 2 % of the main root are dropped; a plant's axes (its main root is
    # virtual, of length 0) against the longest axis, so one axis per plant is the taproot's.
    main_length = jnp.max(lengths) if fitted.virtual_main else l2_norm_squared(fitted.q0)
    threshold = 0.02 * main_length if min_lateral_length is None else jnp.asarray(min_lateral_length)
    keep = lengths >= threshold
    mean_srvf = eqx.tree_at(lambda t: (t.q, t.mask), fitted, (fitted.q * keep[:, None, None], keep))
    child_lengths, child_keep = _drop_deeper(fitted, lengths, keep, min_lateral_length)
    if fitted.deeper:
        deeper = tuple(
            eqx.tree_at(lambda lv: (lv.q, lv.mask), lv, (lv.q * k[..., None, None], k))
            for lv, k in zip(fitted.deeper, child_keep)
        )
        mean_srvf = eqx.tree_at(lambda t: t.deeper, mean_srvf, deeper)
    return KarcherMean(
        mean=to_curves(mean_srvf),
        mean_srvf=mean_srvf,
        fitted=fitted,
        registered=registered,
        energies=energies,
        energy=energy,
        energy_trace=trace,
        steps=jnp.asarray(steps),
        result=result,
        init_index=start,
        lateral_lengths=lengths,
        dropped=~keep,
        weights=weights,
        registration=opts,
        child_lengths=child_lengths,
        child_dropped=tuple(~k for k in child_keep),
    )
