"""Karcher mean of a population of roots (DESIGN.md §6, paper §4).

The mean minimises ``F(μ) = (1/n) Σ_i min_g d²(μ, g·x_i)`` over SRVF trees μ, where g ranges
over rotations, reparameterisations and lateral correspondences (`register`).

The mean has the samples' K lateral slots, all treated as *real* while fitting (mask True).
A sample's null lateral matched to a slot of μ costs ``λs ||q_μ||²`` and sits at μ's position;
a slot that no sample's real lateral reaches shrinks to zero length. With the registrations
fixed, ``F`` is a weighted sum of squares in μ, minimised exactly by

- ``q0_μ = mean_i q0_i``, ``q_μk = mean_i q_ik`` (nulls count as 0), and
- ``s_μk`` = the mean attachment of the samples whose slot k is a real lateral
  (the position term only counts where both laterals are real).

Two solvers, both optimistix:

- ``method="fixed_point"`` (`optx.fixed_point`): block-coordinate descent on the joint energy
  ``J(μ, g_1..g_n)``. The iterate is μ with every sample's rotation and current registration.
  A step solves every sample's warps and lateral correspondence afresh for its rotation (one
  batched DP pass, the core of `register`) and keeps them where they beat the carried ones,
  moves μ to the exact minimiser above, and refits each rotation by weighted Kabsch. No
  sub-step can raise J, so the recorded energy never increases. The first registrations
  come from a full `register` (rotation search included) of every sample onto the start.
- ``method="gradient"`` (`optx.minimise`, gradient descent by default, any optimistix
  minimiser accepted): minimises ``F`` itself, every evaluation registering all samples
  afresh under `stop_gradient` (envelope theorem), in whitened coordinates
  ``z = W^{1/2} μ`` (√λ and the trapezoid weights per block) so that a unit gradient step is
  the metric's own Karcher step; the default learning rate 1/2 moves q0 and q exactly to the
  mean of the registered samples.

Both stop when ``F`` changes by less than ``rtol`` (relative) between two steps, or when the
given optimistix solver's own criterion fires. Finally every sample is registered onto the
mean with a full `register` (for the fixed point also its carried registration; the better
of the two is kept), mean laterals shorter than a threshold are dropped and reported.

The start is the medoid — under `distances` when given (e.g. from `pairwise_distances`),
otherwise under the exact lower bound of the elastic distance that needs no DP (lateral
lengths and positions, see `_lower_bound_distances`) — so the result does not depend on the
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

from ._assignment import linear_assignment
from ._curves import l2_norm_squared, trapezoid_weights
from ._metric import Weights, preshape_terms
from ._registration import _apply, _options, _search
from ._rotation import optimal_rotation
from ._tree import RootTree, SRVFTree, batch_size, check_compatible, to_curves, to_srvf


# --------------------------------------------------------------------------------------------
# Result


class KarcherMean(eqx.Module):
    """Result of `karcher_mean`.

    **Fields**

    - `mean`: the mean root's curves (`RootTree`); dropped laterals are null slots.
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
    - `init_index`: index of the sample the solver started from (the medoid).
    - `lateral_lengths`: ``[K]`` length of each lateral of the fitted mean (before dropping).
    - `dropped`: ``[K]`` True where a fitted lateral was shorter than the threshold and dropped.
    - `weights`: the metric weights used (for `tangent_pca`).
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
    init_index: int = eqx.field(static=True)
    lateral_lengths: Float[Array, " K"]
    dropped: Bool[Array, " K"]
    weights: Weights


# --------------------------------------------------------------------------------------------
# The objective (public, differentiable in mu)


def _broadcast(tree, n: int):
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), tree)


def _registered_energies(mu: SRVFTree, samples: SRVFTree, weights: Weights, opts: "_RegOptions"):
    """Every sample registered onto mu (single tree): (registered batch, energies, rotations)."""
    return _register_onto(_broadcast(mu, samples.q0.shape[0]), samples, weights, opts)


def _register_onto(a: SRVFTree, x: SRVFTree, weights: Weights, opts: "_RegOptions"):
    """Register the batch x onto the batch a (element-wise) with `register`'s search (exact
    lazy assignment, any masks). Returns (registered, energies, rotations)."""
    n = x.q0.shape[0]
    active = jnp.ones((n,), bool)
    O, perm, g0, gam, *_ = _search(a, x, weights, active, opts.dynamic, **dict(opts.static))
    registered = jax.vmap(_apply)(a, x, O, perm, g0, gam)
    energies = preshape_terms(a, registered, weights).total
    return registered, energies, O


@eqx.filter_jit
def _objective(mu: SRVFTree, samples: SRVFTree, weights: Weights, opts: "_RegOptions"):
    _, energies, _ = _registered_energies(mu, samples, weights, opts)
    return jnp.mean(energies)


def karcher_objective(
    mu: SRVFTree | RootTree,
    samples: SRVFTree | RootTree,
    *,
    weights: Weights | None = None,
    registration: dict | None = None,
) -> Float[Array, ""]:
    """The Karcher objective ``F(μ) = (1/n) Σ_i min_g d²(μ, g·x_i)``.

    `mu` is one tree, `samples` a batch with the same capacities. Every sample is registered
    onto `mu` (options of `register` in the `registration` dict); the registrations are held
    under `stop_gradient`, so ``jax.grad`` with respect to `mu` (or the weights) is the
    envelope-theorem gradient of F. Slots of `mu` count as real laterals where ``mu.mask`` is
    True (`karcher_mean` fits a mean with every slot real).
    """
    weights = Weights() if weights is None else weights
    mu = to_srvf(mu)
    samples = to_srvf(samples)
    _check_samples(samples, "karcher_objective: samples")
    if mu.batch_shape != ():
        raise ValueError(
            f"karcher_objective: mu must be a single tree, got batch shape {mu.batch_shape}."
        )
    check_compatible(mu, samples, "karcher_objective: mu and samples")
    opts = _registration_options(registration)
    return _objective(mu, samples, weights, opts)


# --------------------------------------------------------------------------------------------
# Energy monitoring around any optimistix solver


class _MonitorState(eqx.Module):
    inner: Any
    trace: Float[Array, " S"]
    count: Int[Array, ""]


def _monitor_init(solver, fn, y, args, options, f_struct, aux_struct, tags):
    inner = solver.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
    dtype = aux_struct.dtype
    return _MonitorState(inner, jnp.full((solver.size,), jnp.nan, dtype), jnp.array(0))


def _monitor_terminate(solver, fn, y, args, options, state, tags):
    done, result = solver.inner.terminate(fn, y, args, options, state.inner, tags)
    k = state.count
    last = state.trace[jnp.maximum(k - 1, 0)]
    prev = state.trace[jnp.maximum(k - 2, 0)]
    flat = (k >= 2) & (jnp.abs(prev - last) <= solver.atol + solver.rtol * jnp.abs(last))
    return done | flat, optx.RESULTS.where(flat, optx.RESULTS.successful, result)


def _record(state: _MonitorState, inner_state, energy, record) -> _MonitorState:
    trace = jnp.where(record, state.trace.at[state.count].set(energy, mode="drop"), state.trace)
    return _MonitorState(inner_state, trace, state.count + record.astype(state.count.dtype))


class _MonitoredFixedPoint(optx.AbstractFixedPointSolver):
    """Wraps an optimistix fixed-point solver: records F (the aux of each step, evaluated at
    the step's input) and also stops when F changes by less than ``atol + rtol|F|``."""

    inner: optx.AbstractFixedPointSolver
    rtol: float
    atol: float
    size: int = eqx.field(static=True)
    norm: Any = optx.max_norm  # unused; optimistix solvers declare one

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return _monitor_init(self, fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        y_new, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        return y_new, _record(state, inner, aux, jnp.array(True)), aux

    def terminate(self, fn, y, args, options, state, tags):
        return _monitor_terminate(self, fn, y, args, options, state, tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


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
        return _monitor_init(self, fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        y_new, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        # The energy of the returned iterate: optimistix's gradient / quasi-Newton solvers keep
        # it in `f_info`; their returned aux may belong to the previous iterate.
        f_info = getattr(inner, "f_info", None)
        energy = f_info.f if f_info is not None and hasattr(f_info, "f") else aux
        moved = jnp.any(
            jnp.stack([jnp.any(a != b) for a, b in zip(jax.tree.leaves(y_new), jax.tree.leaves(y))])
        )
        return y_new, _record(state, inner, energy, (state.count == 0) | moved), aux

    def terminate(self, fn, y, args, options, state, tags):
        return _monitor_terminate(self, fn, y, args, options, state, tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


# --------------------------------------------------------------------------------------------
# Shared pieces


class _Params(eqx.Module):
    """The free parts of the mean: main SRVF, lateral SRVFs, attachment fractions."""

    q0: Float[Array, "T d"]
    q: Float[Array, "K T d"]
    s: Float[Array, " K"]


def _to_tree(p: _Params, origin) -> SRVFTree:
    return SRVFTree(q0=p.q0, q=p.q, s=p.s, mask=jnp.ones(p.s.shape, bool), origin=origin)


def _exact_update(registered: SRVFTree, mu_s) -> _Params:
    """The minimiser of F over mu for fixed registrations (module docstring)."""
    m = registered.mask.astype(registered.s.dtype)
    count = jnp.sum(m, axis=0)
    s_sum = jnp.sum(m * registered.s, axis=0)
    s = jnp.where(count > 0, s_sum / jnp.maximum(count, 1), mu_s)
    return _Params(jnp.mean(registered.q0, axis=0), jnp.mean(registered.q, axis=0), s)


def _rotate_tree(t: SRVFTree, O) -> SRVFTree:
    """Rotate SRVFs (about each tree's origin) by per-tree rotations O [n, d, d]."""
    q0 = jnp.einsum("ntd,ned->nte", t.q0, O)
    q = jnp.einsum("nktd,ned->nkte", t.q, O)
    return eqx.tree_at(lambda x: (x.q0, x.q), t, (q0, q))


def _project_rotation(O):
    """Nearest proper rotation (polar factor, determinant corrected); a no-op on rotations.
    Guards against solvers that average iterates (e.g. a damped fixed point)."""
    U, _, Vt = jnp.linalg.svd(O)
    d = O.shape[-1]
    det = jnp.linalg.det(U @ Vt)
    D = jnp.ones(O.shape[:-1], O.dtype).at[..., -1].set(jnp.where(det < 0, -1.0, 1.0))
    return (U * D[..., None, :]) @ Vt


def _lower_bound(a: SRVFTree, b: SRVFTree, weights: Weights):
    """Per-pair Cauchy–Schwarz lower bound of the lateral costs ``λs(√La − √Lb)² + λp Δs²``."""
    dtype = a.q0.dtype
    lam_s = jnp.asarray(weights.lateral, dtype)
    lam_p = jnp.asarray(weights.position, dtype)
    La = l2_norm_squared(a.q) * a.mask
    Lb = l2_norm_squared(b.q) * b.mask
    pos = lam_p * (a.s[..., :, None] - b.s[..., None, :]) ** 2
    lower = lam_s * (jnp.sqrt(La)[..., :, None] - jnp.sqrt(Lb)[..., None, :]) ** 2 + pos
    both = a.mask[..., :, None] & b.mask[..., None, :]
    return La, Lb, lower, both


def _check_samples(samples: SRVFTree, what: str) -> int:
    n = batch_size(samples)
    if n < 1:
        raise ValueError(f"{what}: empty batch; give at least one root.")
    return n


class _RegOptions(eqx.Module):
    """`register`'s options split as `_registration._options` does: `dynamic` arrays (rotation
    on/off, max_iterations, rtol; traced, no recompilation) and `static` items."""

    dynamic: tuple
    static: tuple = eqx.field(static=True)

    def option(self, name: str):
        return dict(self.static)[name]

    def without_rotation(self) -> "_RegOptions":
        rotation, max_iterations, rtol = self.dynamic
        return _RegOptions((jnp.zeros_like(rotation), max_iterations, rtol), self.static)


def _registration_options(registration: dict | None) -> _RegOptions:
    reg = dict(registration or {})
    allowed = {"rotation", "max_iterations", "rtol", "neighbourhood", "prune", "dp_batch_size", "assignment"}
    unknown = set(reg) - allowed
    if unknown:
        raise ValueError(
            f"registration options {sorted(unknown)} are unknown; use some of {sorted(allowed)} "
            "(the keyword options of rootshape_jax.register)."
        )
    defaults = dict(
        rotation=True, max_iterations=5, rtol=1e-6, neighbourhood=7, prune=True,
        dp_batch_size=256, assignment="callback",
    )
    defaults.update(reg)
    dynamic, static = _options(**defaults)
    return _RegOptions(dynamic, tuple(sorted(static.items())))


# --------------------------------------------------------------------------------------------
# Start: the medoid


def _lower_bound_energy(a: SRVFTree, b: SRVFTree, weights: Weights, assignment: str):
    """A lower bound of ``min_g d²(a, g·b)`` needing no DP: ``λm(||q0a|| − ||q0b||)²`` plus the
    optimal assignment of the laterals' lower bounds (exact null costs). Cauchy–Schwarz bounds
    every term from below for any rotation and reparameterisation."""
    La, Lb, lower, both = _lower_bound(a, b, weights)
    dtype = a.q0.dtype
    lam_s = jnp.asarray(weights.lateral, dtype)
    lam_m = jnp.asarray(weights.main, dtype)
    C = jnp.where(
        both,
        lower,
        jnp.where(a.mask[:, None], lam_s * La[:, None], jnp.where(b.mask[None, :], lam_s * Lb[None, :], 0.0)),
    )
    perm = linear_assignment(C, method=assignment)
    lap = jnp.sum(jnp.take_along_axis(C, perm[:, None], axis=1))
    L0a = l2_norm_squared(a.q0)
    L0b = l2_norm_squared(b.q0)
    return lam_m * (jnp.sqrt(L0a) - jnp.sqrt(L0b)) ** 2 + lap


@eqx.filter_jit
def _lower_bound_distances(samples: SRVFTree, weights: Weights, assignment: str):
    row = jax.vmap(_lower_bound_energy, in_axes=(None, 0, None, None))
    e = jax.lax.map(lambda a: row(a, samples, weights, assignment), samples)
    e = 0.5 * (e + e.T)
    return jnp.sqrt(jnp.maximum(e, 0.0))


@eqx.filter_jit
def _zero_tree_energy(samples: SRVFTree, weights: Weights):
    """Mean squared distance of the samples from the zero tree (no registration): F's scale."""
    dtype = samples.q0.dtype
    lam_m = jnp.asarray(weights.main, dtype)
    lam_s = jnp.asarray(weights.lateral, dtype)
    e = lam_m * l2_norm_squared(samples.q0) + lam_s * jnp.sum(l2_norm_squared(samples.q), axis=-1)
    return jnp.mean(e)


def _medoid(distances, n: int) -> int:
    D = np.asarray(distances, dtype=np.float64)
    if D.shape != (n, n):
        raise ValueError(f"distances has shape {D.shape}, expected ({n}, {n}) for {n} samples.")
    if not np.all(np.isfinite(D)):
        raise ValueError("distances contains NaN or inf; pass a finite distance matrix.")
    return int(np.argmin(np.sum(D**2, axis=1)))


# --------------------------------------------------------------------------------------------
# Fixed point


class _FPIterate(eqx.Module):
    """The fixed point's iterate: the mean, each sample's rotation, and each sample's current
    registration without its rotation (warped main root, warped laterals permuted into the
    mean's slots, their attachments, and 1.0 where the slot holds a real lateral)."""

    mu: _Params
    rotations: Float[Array, "n d d"]
    warped_q0: Float[Array, "n T d"]
    warped_q: Float[Array, "n K T d"]
    reg_s: Float[Array, "n K"]
    reg_real: Float[Array, "n K"]


def _carried(y: _FPIterate, mu: SRVFTree, O, origin) -> SRVFTree:
    """The carried registrations, rotated, as registered trees in mu's slot order."""
    real = y.reg_real > 0.5
    q0 = jnp.einsum("ntd,ned->nte", y.warped_q0, O)
    q = jnp.einsum("nktd,ned->nkte", y.warped_q, O) * real[..., None, None]
    s = jnp.where(real, y.reg_s, mu.s[None])
    return SRVFTree(q0=q0, q=q, s=s, mask=real, origin=origin)


def _unrotated(registered: SRVFTree, O):
    # registered = O·warped(x), so the unrotated warped branches are registered·O.
    q0 = jnp.einsum("nte,ned->ntd", registered.q0, O)
    q = jnp.einsum("nkte,ned->nktd", registered.q, O)
    return q0, q


def _pick(better, new, old):
    n = better.shape[0]
    return jax.tree.map(lambda u, v: jnp.where(better.reshape((n,) + (1,) * (u.ndim - 1)), u, v), new, old)


def _fixed_point_fn(y: _FPIterate, args):
    samples, weights, origin, opts = args
    registered, energies = _fp_register(y, samples, weights, origin, opts)
    return _fp_update(y, registered, energies, weights, origin)


def _fp_register(y: _FPIterate, samples, weights, origin, opts):
    """Per-sample half of a fixed-point step (run in blocks by `karcher_mean(client=...)`):
    each sample's registration onto the current mean, and its energy."""
    n = samples.q0.shape[0]
    mu = _to_tree(y.mu, origin)
    a = _broadcast(mu, n)
    O = _project_rotation(y.rotations)
    # The carried registration at the current mean and rotation ...
    old = _carried(y, mu, O, samples.origin)
    e_old = preshape_terms(a, old, weights).total
    # ... against warps and correspondence solved afresh for the current rotation. The DP is
    # exact for its own discretisation of the warp energy, not for the grid energy used here,
    # so the fresh solution is kept only where it is better: the energy never increases.
    xb = _rotate_tree(samples, O)
    new, e_new, _ = _register_onto(a, xb, weights, opts.without_rotation())
    better = e_new < e_old
    return _pick(better, new, old), jnp.where(better, e_new, e_old)


def _fp_update(y: _FPIterate, registered: SRVFTree, energies, weights, origin):
    """Global half of a fixed-point step: the exact mean update and each rotation's refit."""
    mu = _to_tree(y.mu, origin)
    O = _project_rotation(y.rotations)
    energy = jnp.mean(energies)
    mu_new = _exact_update(registered, mu.s)
    # Refit each rotation (weighted Kabsch) against the new mean with these correspondences.
    w0, wq = _unrotated(registered, O)
    A = jnp.concatenate([mu_new.q0[None], mu_new.q], axis=0)
    dtype = mu_new.q0.dtype
    lam_m = jnp.asarray(weights.main, dtype)
    lam_s = jnp.asarray(weights.lateral, dtype)

    def refit(b0, bq, mask, O_old):
        Bm = jnp.concatenate([b0[None], bq], axis=0)
        w = jnp.concatenate([lam_m[None], lam_s * mask.astype(dtype)])
        O_new = optimal_rotation(A, Bm, w)
        # Degenerate data (all weights zero) gives no information: keep the old rotation.
        return jnp.where(jnp.sum(w) > 0, O_new, O_old)

    O_new = jax.vmap(refit)(w0, wq, registered.mask, O)
    y_new = _FPIterate(mu_new, O_new, w0, wq, registered.s, registered.mask.astype(dtype))
    return y_new, energy


# --------------------------------------------------------------------------------------------
# Gradient


def _whitening(weights: Weights, T: int, dtype) -> _Params:
    """Per-coordinate scales c with z = c·mu (√λ times √trapezoid weight; 1 where λ = 0)."""
    tw = trapezoid_weights(T, dtype)

    def scale(lam):
        lam = jnp.asarray(lam, dtype)
        return jnp.where(lam > 0, jnp.sqrt(jnp.where(lam > 0, lam, 1.0)), 1.0)

    c0 = scale(weights.main) * jnp.sqrt(tw)
    cs = scale(weights.lateral) * jnp.sqrt(tw)
    return _Params(c0[:, None], cs[None, :, None], scale(weights.position))


def _gradient_fn(z: _Params, args):
    samples, weights, origin, opts, c = args
    mu = _Params(z.q0 / c.q0, z.q / c.q, z.s / c.s)
    _, energies, _ = _registered_energies(_to_tree(mu, origin), samples, weights, opts)
    f = jnp.mean(energies)
    return f, jax.lax.stop_gradient(f)


# --------------------------------------------------------------------------------------------
# Driver


# Rounds of the fixed point: after a solve, a full registration (rotation search included) at
# its result may find better registrations; the solve then restarts from them.
_MAX_ROUNDS = 4


def _start(mu: _Params, registered: SRVFTree, O) -> _FPIterate:
    w0, wq = _unrotated(registered, O)
    dtype = mu.q0.dtype
    return _FPIterate(mu, O, w0, wq, registered.s, registered.mask.astype(dtype))


@eqx.filter_jit
def _full_registration(mu: _Params, samples, weights, origin, opts):
    return _registered_energies(_to_tree(mu, origin), samples, weights, opts)


@eqx.filter_jit
def _solve_fixed_point(y0: _FPIterate, samples, weights, origin, opts, solver, max_steps, throw):
    sol = optx.fixed_point(
        _fixed_point_fn, solver, y0, (samples, weights, origin, opts),
        has_aux=True, max_steps=max_steps, throw=throw,
    )
    return sol.value, sol.state.trace, sol.state.count, sol.stats["num_steps"], sol.result


def _best_registration(y: _FPIterate, samples, weights, origin, opts, full_registration=None):
    """The carried registrations at the solve's result against a full `register` of every
    sample: the better of the two for each sample, with its rotation."""
    full_registration = _full_registration if full_registration is None else full_registration
    full = full_registration(y.mu, samples, weights, origin, opts)
    return _combine(y, full, samples, weights, origin)


@eqx.filter_jit
def _combine(y: _FPIterate, full, samples, weights, origin):
    registered, energies, O = full
    n = samples.q0.shape[0]
    mu = _to_tree(y.mu, origin)
    O_c = _project_rotation(y.rotations)
    carried = _carried(y, mu, O_c, samples.origin)
    e_c = preshape_terms(_broadcast(mu, n), carried, weights).total
    better = energies < e_c
    return (
        _pick(better, registered, carried),
        jnp.where(better, energies, e_c),
        _pick(better, O, O_c),
        jnp.mean(e_c),
    )


@eqx.filter_jit
def _solve_gradient(mu0: _Params, samples, weights, origin, opts, solver, max_steps, throw):
    c = _whitening(weights, mu0.q0.shape[0], mu0.q0.dtype)
    z0 = _Params(mu0.q0 * c.q0, mu0.q * c.q, mu0.s * c.s)
    sol = optx.minimise(
        _gradient_fn, solver, z0, (samples, weights, origin, opts, c),
        has_aux=True, max_steps=max_steps, throw=throw,
    )
    z = sol.value
    mu = _Params(z.q0 / c.q0, z.q / c.q, z.s / c.s)
    return mu, sol.state.trace, sol.state.count, sol.stats["num_steps"], sol.result


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
    init: Literal["medoid"] | int = "medoid",
    distances: Array | np.ndarray | None = None,
    min_lateral_length: float | None = None,
    registration: dict | None = None,
    client=None,
    block_size: int = 64,
) -> KarcherMean:
    """Karcher mean of a batch of roots: ``argmin_μ (1/n) Σ_i min_g d²(μ, g·x_i)``.

    **Arguments**

    - `trees`: a batched `RootTree` or `SRVFTree` (`rootshape_jax.batch(roots)`); the mean
      has the same capacities (T, K, d) and dtype.
    - `weights`: metric weights λ = (main, lateral, position).
    - `method`: ``"fixed_point"`` (default; `optx.fixed_point`, carried registrations, one DP
      pass per step, energy never increases) or ``"gradient"`` (`optx.minimise` on F, a full
      registration per evaluation).
    - `solver`: an optimistix fixed-point solver (fixed point; default
      ``optx.FixedPointIteration`` with tolerances 0, so F's relative change decides) or
      minimiser (gradient; default ``optx.GradientDescent(learning_rate=0.5)`` in whitened
      coordinates, where 0.5 is the exact Karcher step). Either stops when the solver's own
      criterion or the relative change of F fires.
    - `rtol`, `atol`: stop when ``|ΔF| <= atol + rtol·|F|`` between two steps (plus 10 ε times
      the samples' mean squared norm, below which a change is rounding).
    - `max_steps`, `throw`: as in optimistix, per solve; with ``throw=False`` check `result`.
      The fixed point ends each solve with a full `register` of every sample onto its
      result; where that finds better registrations the solve restarts from them (at most
      4 solves). `steps` counts them all.
    - `init`: ``"medoid"`` or the index of the sample to start from.
    - `distances`: an ``(n, n)`` distance matrix (e.g. `pairwise_distances(trees)`) for the
      medoid; without it the medoid of the DP-free lower bound of the elastic distance is used.
    - `min_lateral_length`: mean laterals shorter than this are dropped at the end; default
      2 % of the mean's main-root length.
    - `registration`: options of `register` as a dict (``max_iterations``, ``neighbourhood``,
      ``prune``, ...), used for every registration.
    - `client`: a ``dask.distributed.Client`` (extra ``rootshape_jax[dask]``): the fixed
      point's registrations of every sample onto the current mean run on the cluster, in
      blocks of `block_size` samples, through the same functions as the local path (the step
      loop runs on the host). Fixed point with the default solver only. The default medoid
      start is computed locally (O(n²) assignments): for large n pass `distances` or `init`.
    """
    weights = Weights() if weights is None else weights
    if method not in ("fixed_point", "gradient"):
        raise ValueError(f"method must be 'fixed_point' or 'gradient', got {method!r}.")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}.")
    if not (rtol >= 0 and atol >= 0):
        raise ValueError(f"rtol and atol must be >= 0, got rtol={rtol!r}, atol={atol!r}.")
    if not isinstance(trees, (RootTree, SRVFTree)):
        raise TypeError(
            f"karcher_mean: trees must be a batched RootTree or SRVFTree (rootshape_jax.batch), "
            f"got {type(trees).__name__}."
        )
    samples = to_srvf(trees)
    n = _check_samples(samples, "karcher_mean: trees")
    opts = _registration_options(registration)
    full_registration, solve_fixed_point = _full_registration, _solve_fixed_point
    if client is not None:
        if method != "fixed_point" or solver is not None:
            raise ValueError(
                "karcher_mean: client= runs method='fixed_point' with the default solver only "
                f"(got method={method!r}, solver={type(solver).__name__ if solver else None})."
            )
        from ._dask import MeanOnCluster

        cluster = MeanOnCluster(client, samples, block_size=block_size)
        full_registration, solve_fixed_point = cluster.full_registration, cluster.solve_fixed_point

    if isinstance(init, (int, np.integer)) and not isinstance(init, bool):
        if not 0 <= init < n:
            raise ValueError(f"init index {init} is out of range for {n} samples.")
        start = int(init)
    elif init == "medoid":
        if distances is None:
            distances = _lower_bound_distances(samples, weights, opts.option("assignment"))
        start = _medoid(distances, n)
    else:
        raise ValueError(f"init must be 'medoid' or a sample index, got {init!r}.")

    first = jax.tree.map(lambda x: x[start], samples)
    mu0 = _Params(first.q0, first.q, first.s)
    origin = jnp.mean(samples.origin, axis=0)
    size = max_steps + 1
    # Tolerances are arrays (traced, so new values do not recompile). Below ~10 ε times the
    # problem's scale (the energy of the zero tree) a change of F is rounding.
    dtype = samples.q0.dtype
    scale = _zero_tree_energy(samples, weights)
    tol_r = jnp.asarray(rtol, dtype)
    tol_a = jnp.asarray(atol, dtype) + 10 * jnp.finfo(dtype).eps * scale
    if method == "fixed_point":
        inner = solver if solver is not None else optx.FixedPointIteration(rtol=0.0, atol=0.0)
        if not isinstance(inner, optx.AbstractFixedPointSolver):
            raise TypeError(
                "method='fixed_point' needs an optimistix fixed-point solver (e.g. "
                f"optx.FixedPointIteration), got {type(inner).__name__}."
            )
        wrapped = _MonitoredFixedPoint(inner, tol_r, tol_a, size)
        registered, _, O = full_registration(mu0, samples, weights, origin, opts)
        y = _start(mu0, registered, O)
        traces, steps = [], 0
        for _ in range(_MAX_ROUNDS):
            y, trace, count, n_steps, result = solve_fixed_point(
                y, samples, weights, origin, opts, wrapped, max_steps, throw
            )
            traces.append(np.asarray(trace)[: int(count)])
            steps += int(n_steps)
            registered, energies, O, e_carried = _best_registration(
                y, samples, weights, origin, opts, full_registration
            )
            F, F_carried = float(jnp.mean(energies)), float(e_carried)
            if result != optx.RESULTS.successful or F >= F_carried - float(tol_a + tol_r * abs(F_carried)):
                break
            y = _start(y.mu, registered, O)
        mu = y.mu
        trace = np.concatenate(traces)
    else:
        inner = solver if solver is not None else optx.GradientDescent(learning_rate=0.5, rtol=0.0, atol=0.0)
        if not isinstance(inner, optx.AbstractMinimiser):
            raise TypeError(
                "method='gradient' needs an optimistix minimiser (e.g. optx.GradientDescent, "
                f"optx.BFGS), got {type(inner).__name__}."
            )
        wrapped = _MonitoredMinimiser(inner, tol_r, tol_a, size)
        mu, trace, count, steps, result = _solve_gradient(
            mu0, samples, weights, origin, opts, wrapped, max_steps, throw
        )
        trace = np.asarray(trace)[: int(count)]
        registered, energies, _ = _full_registration(mu, samples, weights, origin, opts)

    energy = jnp.mean(energies)
    trace = jnp.concatenate([jnp.asarray(trace, energy.dtype), energy[None]])

    fitted = _to_tree(mu, origin)
    lengths = l2_norm_squared(fitted.q)
    main_length = l2_norm_squared(fitted.q0)
    threshold = 0.02 * main_length if min_lateral_length is None else jnp.asarray(min_lateral_length)
    keep = lengths >= threshold
    mean_srvf = SRVFTree(
        q0=fitted.q0, q=fitted.q * keep[:, None, None], s=fitted.s, mask=keep, origin=origin
    )
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
    )
