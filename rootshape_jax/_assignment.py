"""Exact linear assignment (minimum-cost perfect matching on a square cost matrix).

Used by the registration (docs/design.md §4) to match the laterals of two trees through their
K×K cost matrix. Two interchangeable solvers, both exact:

- ``method="callback"`` (default): `scipy.optimize.linear_sum_assignment` on the host through
  `jax.pure_callback`. A vmapped batch, however deeply nested, is a single host call that loops
  over the batch (docs/design.md §8).
- ``method="jax"``: a pure-JAX shortest-augmenting-path (Hungarian / Jonker–Volgenant) solver
  with dual potentials, O(K³), written with `lax` loops so that it jits and vmaps without a host
  round trip. The registration uses it (`hungarian`, warm-started between the solves of a lazy
  assignment): a program holding a host callback is never written to JAX's persistent
  compilation cache, so with scipy the engine compiled again in every process.

Neither solver is differentiable (the argmin is piecewise constant); both run on
``stop_gradient(cost)``. Differentiate the optimal value with `assignment_cost`, which gathers
the matched entries in JAX: by the envelope theorem its gradient is the 0/1 permutation matrix.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._errors import InvalidCostError

_METHODS = ("callback", "jax")
_NONFINITE_MSG = (
    "cost matrix contains NaN/inf entries; the optimal assignment is undefined. "
    "Replace forbidden pairs by a large finite cost and check how the costs were computed."
)


def _check_cost(cost: ArrayLike, *, what: str = "cost") -> Array:
    cost = jnp.asarray(cost)
    if cost.ndim != 2 or cost.shape[0] != cost.shape[1]:
        raise InvalidCostError(
            f"{what} must be a square (K, K) matrix, got shape {cost.shape}. "
            "Pad a rectangular problem with null rows/columns (constant cost); "
            "use jax.vmap for a batch of matrices."
        )
    if cost.shape[0] == 0:
        raise InvalidCostError(f"{what} must have K >= 1 rows, got shape {cost.shape}.")
    if jnp.issubdtype(cost.dtype, jnp.complexfloating):
        raise InvalidCostError(f"{what} must be real, got dtype {cost.dtype}.")
    if not jnp.issubdtype(cost.dtype, jnp.floating):
        # Integer/bool costs: solve in the default float dtype (exact for integers < 2**24 in
        # float32, < 2**53 in float64).
        cost = cost.astype(jnp.result_type(float))
    return cost


# --------------------------------------------------------------------------- scipy callback


def _scipy_host(cost: np.ndarray) -> np.ndarray:
    """Host side: solve every (K, K) matrix in a (..., K, K) stack with scipy."""
    cost = np.asarray(cost)
    k = cost.shape[-1]
    flat = cost.reshape(-1, k, k)
    out = np.empty((flat.shape[0], k), dtype=np.int32)
    for b in range(flat.shape[0]):
        rows, cols = scipy.optimize.linear_sum_assignment(flat[b])
        # scipy returns rows sorted 0..K-1 for a square matrix; scatter anyway to be safe.
        out[b, rows] = cols
    return out.reshape(cost.shape[:-1])


def _solve_callback(cost: Float[Array, "K K"]) -> Int[Array, " K"]:
    k = cost.shape[0]
    out = jax.ShapeDtypeStruct((k,), jnp.int32)
    # "broadcast_all": under (nested) vmap the host function receives the whole
    # (..., K, K) batch at once and loops over it in numpy: one callback per batch.
    # `_scipy_host` is looked up at trace time so tests can count host calls.
    return jax.pure_callback(_scipy_host, out, cost, vmap_method="broadcast_all")


# --------------------------------------------------------------------------- pure JAX


class HungarianState(NamedTuple):
    """A solved assignment's matching and dual potentials: the warm start of the next solve.

    1-based with a virtual column 0 (the row being inserted), as in the solver below.
    """

    p: Int[Array, " K+1"]  # row (1-based) matched to each column; 0 = free
    u: Float[Array, " K+1"]  # potential of the row matched to each column (stored by column)
    v: Float[Array, " K+1"]  # column potentials


#: Rounds of proposals in the greedy start (each matches more rows on tight entries).
_GREEDY_ROUNDS = 2


def _reduction_start(cost: Float[Array, "K K"]) -> tuple[HungarianState, Bool[Array, " K+1"]]:
    """Row then column reduction, then a greedy matching on the tight entries.

    ``u_i = min_j c_ij`` and ``v_j = min_i (c_ij − u_i)`` are feasible duals (every reduced
    cost ``c_ij − u_i − v_j >= 0``) with a tight (zero) entry in every column. In each of
    `_GREEDY_ROUNDS` rounds every unmatched row proposes to a free column where its entry is
    tight (the first at or after its own index, cyclically, so that rows with equal rows —
    the null laterals — spread over their tied columns), and each column takes its lowest
    proposer: a partial matching on tight entries, which is what the solver needs of the rows
    it starts with. Returns it and the rows left to insert.
    """
    n = cost.shape[0]
    u = jnp.min(cost, axis=1)
    reduced = cost - u[:, None]
    v = jnp.min(reduced, axis=0)
    tight = reduced - v[None, :] <= 0
    k = jnp.arange(n)
    preference = (k[None, :] - k[:, None]) % n  # row i: column i first, then i + 1, ...
    row_of = jnp.full((n,), -1, jnp.int32)  # row matched to each column
    col_of = jnp.full((n,), -1, jnp.int32)  # column matched to each row
    for _ in range(_GREEDY_ROUNDS):
        open_ = tight & (col_of < 0)[:, None] & (row_of < 0)[None, :]
        score = jnp.where(open_, preference, n)
        choice = jnp.argmin(score, axis=1)
        proposes = jnp.min(score, axis=1) < n
        # Each column takes its lowest proposing row.
        proposer = jnp.where(proposes[:, None] & (choice[:, None] == k[None, :]), k[:, None], n)
        taker = jnp.min(proposer, axis=0)
        won = taker < n
        row_of = jnp.where(won, taker, row_of).astype(jnp.int32)
        col_of = col_of.at[jnp.where(won, taker, n)].set(k.astype(jnp.int32), mode="drop")
    zero = jnp.zeros((1,), cost.dtype)
    state = HungarianState(
        p=jnp.concatenate([jnp.zeros((1,), jnp.int32), row_of + 1]),
        u=jnp.concatenate([zero, jnp.where(row_of >= 0, u[jnp.maximum(row_of, 0)], 0)]),
        v=jnp.concatenate([zero, v]),
    )
    return state, jnp.concatenate([jnp.zeros((1,), bool), col_of < 0])


def hungarian(
    cost: Float[Array, "K K"], warm: tuple[HungarianState, Bool[Array, " K"]] | None = None
) -> tuple[Int[Array, " K"], HungarianState]:
    """Exact assignment by shortest augmenting paths with potentials (the O(K³) Hungarian
    algorithm of Jonker–Volgenant / e-maxx), in `lax` loops: no host round trip, so programs
    using it can be cached by JAX's persistent compilation cache.

    Rows are inserted one at a time; for each a Dijkstra search over reduced costs finds the
    cheapest augmenting path, the potentials are updated so reduced costs stay >= 0 and the
    matched entries tight, and the matching is flipped along the path. When every row is in,
    the matching is optimal: it is perfect, and its cost equals the dual bound, the sum of
    ``u + v`` over the real columns 1 … K (column 0 is virtual).

    The insertion is correct from any state in which the rows already matched have feasible
    potentials over all columns and tight matched entries (the new row's own potential may be
    anything: the first pass of its search fixes it). So the solve starts from
    `_reduction_start` (most rows matched before any search), and `warm` = (the state of a
    previous solve, the rows whose costs changed since) restarts from that state with only
    the changed rows taken out and inserted again: the other rows' entries are unchanged, so
    their potentials are still feasible and their matched entries tight. A lazy assignment
    that makes a few picked entries exact between solves re-inserts a few rows, not all.

    Returns (perm, state): row i is assigned to column ``perm[i]``.
    """
    n = cost.shape[0]
    dtype = cost.dtype
    inf = jnp.array(jnp.inf, dtype)
    a = jnp.zeros((n + 1, n + 1), dtype).at[1:, 1:].set(cost)
    cols = jnp.arange(n + 1)
    if warm is None:
        state, pending = _reduction_start(cost)
    else:
        state, changed = warm
        pending = jnp.concatenate([jnp.zeros((1,), bool), changed])
        state = state._replace(p=jnp.where(pending[state.p] & (state.p > 0), 0, state.p))

    def insert_row(carry):
        p, u, v, pending, n_rows = carry
        i = jnp.argmax(pending).astype(jnp.int32)
        pending = pending.at[i].set(False)
        p, u = p.at[0].set(i), u.at[0].set(0)

        # Dijkstra over columns. Every pass marks one new column used, so at most n + 1
        # passes; the counter also guarantees termination should the costs be non-finite.
        def search_cond(c):
            p, _, _, _, _, _, j0, it = c
            return (p[j0] != 0) & (it <= n)

        def search_body(c):
            p, u, v, minv, way, used, j0, it = c
            used = used | (cols == j0)
            reduced = a[p[j0]] - u[j0] - v
            better = (~used) & (reduced < minv)
            minv = jnp.where(better, reduced, minv)
            way = jnp.where(better, j0, way)
            masked = jnp.where(used, inf, minv)
            j1 = jnp.argmin(masked).astype(jnp.int32)
            delta = masked[j1]
            # Used columns hold distinct rows (column 0 the new one): their potentials move
            # together, by column.
            u = jnp.where(used, u + delta, u)
            v = jnp.where(used, v - delta, v)
            minv = jnp.where(used, minv, minv - delta)
            return p, u, v, minv, way, used, j1, it + 1

        minv = jnp.full((n + 1,), inf)
        used = jnp.zeros((n + 1,), bool)
        way = jnp.zeros((n + 1,), jnp.int32)
        zero = jnp.array(0, jnp.int32)
        p, u, v, _, way, _, j0, _ = lax.while_loop(search_cond, search_body, (p, u, v, minv, way, used, zero, zero))

        # Flip the matching along the path back to the virtual column 0; each row's potential
        # moves with it.
        def flip_cond(c):
            _, _, j0, it = c
            return (j0 != 0) & (it <= n)

        def flip_body(c):
            p, u, j0, it = c
            j1 = way[j0]
            return p.at[j0].set(p[j1]), u.at[j0].set(u[j1]), j1, it + 1

        p, u, _, _ = lax.while_loop(flip_cond, flip_body, (p, u, j0, zero))
        return p, u, v, pending, n_rows + 1

    p, u, v, _, _ = lax.while_loop(
        lambda c: jnp.any(c[3]) & (c[4] < n), insert_row, (*state, pending, jnp.array(0, jnp.int32))
    )
    # p[j] = row (1-based) matched to column j (1-based); invert to perm[row] = column.
    perm = jnp.zeros((n,), jnp.int32).at[p[1:] - 1].set(jnp.arange(n, dtype=jnp.int32))
    return perm, HungarianState(p, u, v)


def solve(cost: Float[Array, "K K"], *, method: str) -> Int[Array, " K"]:
    """`linear_assignment` without its checks, for costs finite by construction (the
    registration's): no `eqx.error_if` (a host callback) in the programs that call it."""
    if method == "callback":
        return _solve_callback(lax.stop_gradient(cost))
    return hungarian(lax.stop_gradient(cost))[0]


# --------------------------------------------------------------------------- public


def linear_assignment(
    cost: Float[ArrayLike, "K K"],
    *,
    method: Literal["callback", "jax"] = "callback",
) -> Int[Array, " K"]:
    """Exact minimum-cost assignment of a square cost matrix.

    **Arguments:**

    - `cost`: a `(K, K)` real matrix, `K >= 1`, all entries finite. Integer costs are solved in
      the default float dtype. For a batch, use `jax.vmap`.
    - `method`: `"callback"` (scipy on the host via `jax.pure_callback`; a vmapped batch is one
      host call) or `"jax"` (pure-JAX shortest augmenting path, no host round trip). Both are
      exact; among several optimal assignments they may return different ones.

    **Returns:**

    `perm`, int32 of shape `(K,)`: row `i` is assigned to column `perm[i]`, and
    `sum_i cost[i, perm[i]]` is minimal. Not differentiable; use `assignment_cost` for the
    differentiable optimal value.

    **Raises:**

    `InvalidCostError` (a `ValueError`) at trace time for a non-square, empty or complex
    matrix or an unknown method; at run time (also inside `jit`/`vmap`) an error saying the
    "cost matrix contains NaN/inf" if any entry is not finite.
    """
    if method not in _METHODS:
        raise InvalidCostError(f"method must be one of {_METHODS}, got {method!r}.")
    cost = _check_cost(cost)
    cost = lax.stop_gradient(cost)
    # Data dependence orders the check before the solve, so scipy never sees NaN/inf.
    cost = eqx.error_if(cost, ~jnp.all(jnp.isfinite(cost)), _NONFINITE_MSG)
    return solve(cost, method=method)


def assignment_cost(cost: Float[ArrayLike, "K K"], perm: Int[ArrayLike, " K"]) -> Float[Array, ""]:
    """Total cost `sum_i cost[i, perm[i]]` of an assignment, gathered in JAX.

    Differentiable in `cost`: the gradient is the 0/1 matrix with ones at `(i, perm[i])`.
    With `perm = linear_assignment(cost)` this is the optimal value, and (envelope theorem)
    its gradient is exact wherever the optimum is unique.
    """
    cost = _check_cost(cost)
    perm = jnp.asarray(perm)
    k = cost.shape[0]
    if perm.shape != (k,) or not jnp.issubdtype(perm.dtype, jnp.integer):
        raise InvalidCostError(
            f"perm must be an integer array of shape ({k},) matching cost {cost.shape}, "
            f"got shape {perm.shape} and dtype {perm.dtype}."
        )
    if not isinstance(perm, jax.core.Tracer) and sorted(np.asarray(perm).tolist()) != list(range(k)):
        raise InvalidCostError(
            f"perm must be a permutation of 0..{k - 1} (each column once, as linear_assignment "
            f"returns), got {np.asarray(perm).tolist()}."
        )
    return jnp.sum(jnp.take_along_axis(cost, perm[:, None], axis=1))
