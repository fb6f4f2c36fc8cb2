"""Exact linear assignment (minimum-cost perfect matching on a square cost matrix).

Used by the registration (docs/design.md §4) to match the laterals of two trees through their
K×K cost matrix. Two interchangeable solvers, both exact:

- ``method="callback"`` (default): `scipy.optimize.linear_sum_assignment` on the host through
  `jax.pure_callback`. A vmapped batch, however deeply nested, is a single host call that loops
  over the batch (docs/design.md §8).
- ``method="jax"``: a pure-JAX shortest-augmenting-path (Hungarian / Jonker–Volgenant) solver
  with dual potentials, O(K³), written with `lax` loops so that it jits and vmaps without a host
  round trip (for accelerators or exported programs where a callback is unwanted).

Neither solver is differentiable (the argmin is piecewise constant); both run on
``stop_gradient(cost)``. Differentiate the optimal value with `assignment_cost`, which gathers
the matched entries in JAX: by the envelope theorem its gradient is the 0/1 permutation matrix.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jaxtyping import Array, ArrayLike, Float, Int

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


def _solve_jax(cost: Float[Array, "K K"]) -> Int[Array, " K"]:
    """Shortest augmenting path with potentials (the O(n³) Hungarian algorithm of
    Jonker–Volgenant / e-maxx). Rows are added one at a time; for each new row a Dijkstra
    search over reduced costs finds the cheapest augmenting path, the dual potentials are
    updated so reduced costs stay >= 0, and the matching is flipped along the path.

    1-indexed internally: column 0 is a virtual column holding the row being inserted, and
    row 0 is a dummy (p[j] == 0 means column j is free).
    """
    n = cost.shape[0]
    dtype = cost.dtype
    inf = jnp.array(jnp.inf, dtype)
    a = jnp.zeros((n + 1, n + 1), dtype).at[1:, 1:].set(cost)
    cols = jnp.arange(n + 1)

    def add_row(i, state):
        u, v, p, way = state
        p = p.at[0].set(i)
        minv = jnp.full((n + 1,), inf)
        used = jnp.zeros((n + 1,), bool)

        # Dijkstra over columns. Every pass marks one new column used, so at most n + 1
        # passes; the counter also guarantees termination should the costs be non-finite
        # (possible only when the NaN/inf check has been disabled via EQX_ON_ERROR).
        def search_cond(carry):
            _, _, _, _, _, j0, it = carry
            return (p[j0] != 0) & (it <= n)

        def search_body(carry):
            u, v, minv, way, used, j0, it = carry
            # `p` is fixed during the search, so closing over it is fine.
            used = used.at[j0].set(True)
            i0 = p[j0]
            cur = a[i0] - u[i0] - v
            better = (~used) & (cur < minv)
            minv = jnp.where(better, cur, minv)
            way = jnp.where(better, j0, way)
            masked = jnp.where(used, inf, minv)
            j1 = jnp.argmin(masked)
            delta = masked[j1]
            # Used columns' rows are distinct (column 0 holds row i), so the scatter is a
            # plain per-row update; free columns (p[j] == 0) only touch the dummy row 0.
            u = u.at[p].add(jnp.where(used, delta, 0))
            v = jnp.where(used, v - delta, v)
            minv = jnp.where(used, minv, minv - delta)
            return u, v, minv, way, used, j1, it + 1

        u, v, _, way, _, j0, _ = lax.while_loop(
            search_cond, search_body, (u, v, minv, way, used, jnp.array(0), jnp.array(0))
        )

        # Flip the matching along the path back to the virtual column 0.
        def flip_cond(carry):
            _, j0, it = carry
            return (j0 != 0) & (it <= n)

        def flip_body(carry):
            p, j0, it = carry
            j1 = way[j0]
            p = p.at[j0].set(p[j1])
            return p, j1, it + 1

        p, _, _ = lax.while_loop(flip_cond, flip_body, (p, j0, jnp.array(0)))
        return u, v, p, way

    init = (
        jnp.zeros((n + 1,), dtype),
        jnp.zeros((n + 1,), dtype),
        jnp.zeros((n + 1,), cols.dtype),
        jnp.zeros((n + 1,), cols.dtype),
    )
    _, _, p, _ = lax.fori_loop(1, n + 1, add_row, init)
    # p[j] = row (1-based) matched to column j (1-based); invert to perm[row] = column.
    perm = jnp.zeros((n,), jnp.int32).at[p[1:] - 1].set(jnp.arange(n, dtype=jnp.int32))
    return perm


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
    if method == "callback":
        return _solve_callback(cost)
    return _solve_jax(cost)


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
    return jnp.sum(jnp.take_along_axis(cost, perm[:, None], axis=1))
