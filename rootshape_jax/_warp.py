"""Exact dynamic-programming reparameterisation of one SRVF onto another (DESIGN.md §4, §8).

Discretisation. ``q1`` and ``q2`` are sampled on the grid ``t = linspace(0, 1, T)`` and
linearly interpolated between nodes. A warp ``γ`` is piecewise linear between its values on
the grid. Its energy

    E(γ) = ∫ |q1(t) − √γ'(t) q2(γ(t))|² dt

is computed with the trapezoid rule on the *merged* breakpoints: the grid nodes of ``t`` and
the points where ``γ(t)`` crosses a grid node of ``q2``. Every node of both curves is visited,
so a steep warp cannot skip a feature of ``q2`` between two samples; with ``γ = id`` the energy
is exactly the grid trapezoid ``||q1 − q2||²`` used everywhere else in the library.

The DP searches the paths on the T×T grid from (0, 0) to (T−1, T−1) made of the moves
``(a, b)`` (``a`` steps in ``t``, ``b`` in ``γ``) with ``1 <= a, b <= neighbourhood`` and
``gcd(a, b) = 1``. A move's cost is the energy above over its segment, whose breakpoints are
``i/a`` and ``j/b`` of the way along it: on a uniform grid that is a fixed stencil per move.
Expanding ``|x − √s y|² = |x|² + s|y|² − 2√s x·y`` turns the stencil into

    cost[m, k, l] = R1[m, k] + R2[m, l] − 2 Σ_(r, o) K[m, r, o] · G[k − r, l − o],

with ``G = q1 q2ᵀ`` the Gram matrix of node values and ``K`` a small sparse kernel per move.
A ``lax.scan`` over the rows ``k`` carries the last ``neighbourhood`` rows of the cost table
and evaluates all moves and all columns at once; a second scan follows the back-pointers.
The DP is exact for this discretisation: `warp_energy` of the returned warp is the DP's
minimum (tests check both against a plain-numpy DP and against brute force).
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._errors import InvalidRootError


# ---------------------------------------------------------------------------------------------
# Move set and stencils (numpy, built once per (neighbourhood, T) at trace time)
# ---------------------------------------------------------------------------------------------


def dp_moves(neighbourhood: int) -> np.ndarray:
    """The DP's moves ``(a, b)``: ``1 <= a, b <= neighbourhood`` with ``gcd(a, b) = 1``."""
    n = _check_neighbourhood(neighbourhood)
    return np.array(
        [(a, b) for a in range(1, n + 1) for b in range(1, n + 1) if math.gcd(a, b) == 1],
        dtype=np.int64,
    ).reshape(-1, 2)


def _check_neighbourhood(neighbourhood) -> int:
    if isinstance(neighbourhood, bool) or not isinstance(neighbourhood, (int, np.integer)):
        raise ValueError(
            f"neighbourhood must be a Python int >= 1 (the largest step of a DP move), got "
            f"{neighbourhood!r}. It is static: pass a plain int, not an array."
        )
    if neighbourhood < 1:
        raise ValueError(f"neighbourhood must be >= 1, got {neighbourhood}.")
    return int(neighbourhood)


def segment_points(a: int, b: int) -> list[Fraction]:
    """Breakpoints of move ``(a, b)`` as fractions of the segment: ``{i/a} ∪ {j/b}``, sorted."""
    return sorted({Fraction(i, a) for i in range(a + 1)} | {Fraction(j, b) for j in range(b + 1)})


class _Stencil:
    """Per-move coefficients of the expanded segment cost (index units, times the grid step).

    For the move ending at (k, l):
    - ``R1[m, k] = Σ_r n1[m, r] |q1[k−r]|² + Σ_r p1[m, r] q1[k−r]·q1[k−r+1]``;
    - ``R2[m, l] = Σ_o n2[m, o] |q2[l−o]|² + Σ_o p2[m, o] q2[l−o]·q2[l−o+1]``;
    - cross term ``Σ_u kern[m, u] G[k − r_u, l − o_u]`` over the pairs ``(r_u, o_u)``.
    """

    def __init__(self, neighbourhood: int, n_points: int):
        moves = dp_moves(neighbourhood)
        n = neighbourhood
        h = 1.0 / (n_points - 1)
        m_count = len(moves)
        n1 = np.zeros((m_count, n + 1))
        p1 = np.zeros((m_count, n + 1))
        n2 = np.zeros((m_count, n + 1))
        p2 = np.zeros((m_count, n + 1))
        cross: dict[tuple[int, int], np.ndarray] = {}

        def add_cross(m, r, o, c):
            cross.setdefault((r, o), np.zeros(m_count))[m] += c

        for m, (a, b) in enumerate(moves):
            a, b = int(a), int(b)
            slope = b / a
            rs = math.sqrt(slope)
            pts = segment_points(a, b)
            for i, sig in enumerate(pts):
                lo = pts[i - 1] if i > 0 else sig
                hi = pts[i + 1] if i + 1 < len(pts) else sig
                w = float(hi - lo) / 2 * a * h  # trapezoid weight in t
                x, y = a * sig, b * sig  # offsets from the segment start, in grid steps
                # Linear interpolation: node ``x0`` with weight 1 − fx, node ``x0 + 1`` with fx.
                x0, fx = int(math.floor(x)), float(x - math.floor(x))
                y0, fy = int(math.floor(y)), float(y - math.floor(y))
                r0, o0 = a - x0, b - y0  # row / column offsets back from (k, l)
                # |lerp|² = (1−f)²|v0|² + 2f(1−f) v0·v1 + f²|v1|²
                n1[m, r0] += w * (1 - fx) ** 2
                if fx:
                    n1[m, r0 - 1] += w * fx**2
                    p1[m, r0] += w * 2 * fx * (1 - fx)
                n2[m, o0] += w * slope * (1 - fy) ** 2
                if fy:
                    n2[m, o0 - 1] += w * slope * fy**2
                    p2[m, o0] += w * slope * 2 * fy * (1 - fy)
                for dr, cx in ((0, 1 - fx), (1, fx)):
                    for do, cy in ((0, 1 - fy), (1, fy)):
                        if cx and cy:
                            add_cross(m, r0 - dr, o0 - do, w * rs * cx * cy)
        keys = sorted(cross)
        self.neighbourhood = n
        self.moves = moves
        self.n1, self.p1, self.n2, self.p2 = n1, p1, n2, p2
        self.pairs = np.array(keys, dtype=np.int64).reshape(-1, 2)
        self.kern = np.stack([cross[k] for k in keys], axis=1)  # (M, U)


@functools.lru_cache(maxsize=64)
def _stencil(neighbourhood: int, n_points: int) -> _Stencil:
    return _Stencil(neighbourhood, n_points)


# ---------------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------------


def _check_srvf_pair(q1, q2, what: str):
    q1 = jnp.asarray(q1)
    q2 = jnp.asarray(q2)
    for name, q in (("q1", q1), ("q2", q2)):
        if q.ndim != 2:
            raise InvalidRootError(
                f"{what}: {name} must be a (T, d) array of SRVF values on the grid, got shape "
                f"{q.shape}. Use jax.vmap (or dp_warp_batch) for batches."
            )
        if not jnp.issubdtype(q.dtype, jnp.floating):
            raise InvalidRootError(f"{what}: {name} must be floating point, got {q.dtype}.")
    if q1.shape != q2.shape:
        raise InvalidRootError(
            f"{what}: q1 and q2 must share the shape (T, d), got {q1.shape} and {q2.shape}. "
            "Resample both curves to the same number of points first."
        )
    if q1.shape[0] < 2:
        raise InvalidRootError(f"{what}: needs T >= 2 grid points, got T = {q1.shape[0]}.")
    dtype = jnp.result_type(q1, q2)
    return q1.astype(dtype), q2.astype(dtype)


def _check_gamma(gamma, n_points: int, dtype, what: str):
    gamma = jnp.asarray(gamma)
    if gamma.shape != (n_points,):
        raise InvalidRootError(
            f"{what}: gamma must be the warp sampled on the grid, shape ({n_points},), got "
            f"{gamma.shape}."
        )
    return gamma.astype(dtype)


def _check_finite(x: Array, what: str) -> Array:
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{what}: input contains NaN or inf.")


# ---------------------------------------------------------------------------------------------
# The DP
# ---------------------------------------------------------------------------------------------


def _shift_rows(x: Array, n: int) -> Array:
    """``out[r, i] = x[i − r]`` for r = 0..n (zero where ``i − r < 0``); x has shape (T,)."""
    size = x.shape[0]
    xp = jnp.concatenate([jnp.zeros((n,), x.dtype), x])
    return jnp.stack([xp[n - r : n - r + size] for r in range(n + 1)])


def _edge_terms(q: Array, n_coef: np.ndarray, p_coef: np.ndarray) -> Array:
    """``Σ_r n[m, r]|q[i−r]|² + Σ_r p[m, r] q[i−r]·q[i−r+1]`` for all moves m and nodes i."""
    n = n_coef.shape[1] - 1
    sq = jnp.sum(q * q, axis=-1)
    nxt = jnp.sum(q[:-1] * q[1:], axis=-1)
    nxt = jnp.concatenate([nxt, jnp.zeros((1,), q.dtype)])
    dt = q.dtype
    return jnp.asarray(n_coef, dt) @ _shift_rows(sq, n) + jnp.asarray(p_coef, dt) @ _shift_rows(
        nxt, n
    )


def _dp_tables(q1: Array, q2: Array, neighbourhood: int):
    """Forward pass: best cost to (T−1, T−1) and the back-pointer (move index) of every cell."""
    size = q1.shape[0]
    dtype = q1.dtype
    st = _stencil(neighbourhood, size)
    n = neighbourhood
    a = st.moves[:, 0]
    b = st.moves[:, 1]
    m_count = len(a)
    inf = jnp.asarray(jnp.inf, dtype)

    r1 = _edge_terms(q1, st.n1, st.p1).T  # (T, M): row part, scanned over
    r2 = _edge_terms(q2, st.n2, st.p2)  # (M, T): column part, constant
    gram = q1 @ q2.T  # (T, T)
    # n zero rows on top and n zero columns on the left, so every window is a static slice.
    gpad = jnp.pad(gram, ((n, 0), (n, 0)))
    kern = jnp.asarray(st.kern, dtype)  # (M, U)
    pairs = st.pairs

    def row(carry, xs):
        hist = carry  # hist[j] = cost row k−1−j, padded with n inf columns on the left
        k, r1_k = xs
        win = jax.lax.dynamic_slice_in_dim(gpad, k, n + 1, axis=0)  # rows k−n .. k
        cols = jnp.stack([win[n - r, n - o : n - o + size] for r, o in pairs])  # (U, T)
        cross = kern @ cols  # (M, T)
        prev = jnp.stack([hist[a[m] - 1, n - b[m] : n - b[m] + size] for m in range(m_count)])
        cand = prev + (r1_k[:, None] + r2 - 2 * cross)
        best = jnp.min(cand, axis=0)
        arg = jnp.argmin(cand, axis=0).astype(jnp.int32)
        new_row = jnp.concatenate([jnp.full((n,), inf), best])
        hist = jnp.concatenate([new_row[None], hist[:-1]], axis=0)
        return hist, arg

    row0 = jnp.concatenate([jnp.full((n,), inf), jnp.zeros((1,), dtype), jnp.full((size - 1,), inf)])
    hist0 = jnp.concatenate([row0[None], jnp.full((n - 1, n + size), inf)], axis=0)
    ks = jnp.arange(1, size)
    hist, back = jax.lax.scan(row, hist0, (ks, r1[1:]))
    back = jnp.concatenate([jnp.zeros((1, size), jnp.int32), back], axis=0)  # (T, T)
    return hist[0, -1], back


def _backtrack(back: Int[Array, "T T"], neighbourhood: int, dtype) -> Array:
    """Warp on the grid from the back-pointers: linear along each move of the optimal path."""
    size = back.shape[0]
    moves = dp_moves(neighbourhood)
    a_of = jnp.asarray(moves[:, 0], jnp.int32)
    b_of = jnp.asarray(moves[:, 1], jnp.int32)
    last = size - 1

    def step(carry, k):
        ke, le, a, b = carry  # current move ends at (ke, le) and spans (a, b)
        # γ index at row k, as an exact integer ratio: le − (ke − k)·b/a.
        num = le * a - (ke - k) * b
        value = num.astype(dtype) / (a * last).astype(dtype)
        at_start = (k == ke - a) & (k > 0)
        le_new = jnp.where(at_start, le - b, le)
        ke_new = jnp.where(at_start, k, ke)
        m = back[ke_new, le_new]
        a_new = jnp.where(at_start, a_of[m], a)
        b_new = jnp.where(at_start, b_of[m], b)
        return (ke_new, le_new, a_new, b_new), value

    m0 = back[last, last]
    init = (jnp.int32(last), jnp.int32(last), a_of[m0], b_of[m0])
    _, gamma_rev = jax.lax.scan(step, init, jnp.arange(last, -1, -1, dtype=jnp.int32))
    return gamma_rev[::-1]


def _dp_warp_and_cost(q1: Array, q2: Array, neighbourhood: int):
    cost, back = _dp_tables(q1, q2, neighbourhood)
    gamma = _backtrack(back, neighbourhood, q1.dtype)
    return gamma, cost


@eqx.filter_jit
def dp_warp_and_energy(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], *, neighbourhood: int = 7
) -> tuple[Float[Array, " T"], Float[Array, ""]]:
    """`dp_warp` and the DP's minimum energy (equal to ``warp_energy(q1, q2, gamma)``)."""
    q1, q2 = _check_srvf_pair(q1, q2, "dp_warp")
    _check_neighbourhood(neighbourhood)
    q1 = _check_finite(q1, "dp_warp (q1)")
    q2 = _check_finite(q2, "dp_warp (q2)")
    # Moves longer than the grid can never be used; dropping them changes nothing.
    return _dp_warp_and_cost(q1, q2, min(neighbourhood, q1.shape[0] - 1))


def dp_warp(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], *, neighbourhood: int = 7
) -> Float[Array, " T"]:
    """Optimal warp ``γ`` of ``q2`` onto ``q1`` by exact dynamic programming.

    Minimises ``∫|q1(t) − √γ'(t) q2(γ(t))|² dt`` (see the module docstring for the exact
    discretisation) over the strictly increasing paths of the T×T grid built from the coprime
    moves of ``neighbourhood`` (7 by default; fdasrsf uses 10 for curves).

    **Arguments**

    - `q1`, `q2`: SRVFs on ``linspace(0, 1, T)``, shape ``(T, d)``, same dtype (float32/64).
    - `neighbourhood`: largest step of a move along either axis (static Python int).

    **Returns** ``γ`` on the grid, shape ``(T,)``: ``γ[0] = 0``, ``γ[-1] = 1``, increasing,
    linear between the path's vertices. Compiles once per ``(T, d, dtype, neighbourhood)``;
    use `jax.vmap` or `dp_warp_batch` for batches.
    """
    return dp_warp_and_energy(q1, q2, neighbourhood=neighbourhood)[0]


# ---------------------------------------------------------------------------------------------
# Applying a warp, and its energy
# ---------------------------------------------------------------------------------------------


def _lerp(values: Array, x: Array) -> Array:
    """Linear interpolation of node values (T, ...) at fractional indices ``x`` in [0, T−1]."""
    size = values.shape[0]
    x = jnp.clip(x, 0, size - 1)
    i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    f = (x - i0.astype(x.dtype)).reshape(x.shape + (1,) * (values.ndim - 1))
    return values[i0] * (1 - f) + values[i0 + 1] * f


def _safe_sqrt(x: Array) -> Array:
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1)), 0)


def _check_monotone(gamma: Array, what: str) -> Array:
    tol = 16 * jnp.finfo(gamma.dtype).eps
    bad = jnp.any(jnp.diff(gamma) < -tol) | (jnp.abs(gamma[0]) > tol) | (jnp.abs(gamma[-1] - 1) > tol)
    return eqx.error_if(
        gamma, bad, f"{what}: gamma must be nondecreasing from gamma[0] = 0 to gamma[-1] = 1."
    )


def warp_samples(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]
) -> tuple[Float[Array, "N 2 d"], Float[Array, "N 2 d"], Float[Array, " N"]]:
    """The quadrature behind `warp_energy`, interval by interval.

    Returns ``(A, B, w)`` with ``A[i, e] = q1(τ)``, ``B[i, e] = √γ'·q2(γ(τ))`` at the two ends
    ``e`` of the i-th interval between merged breakpoints (grid nodes of t, and the points where
    γ crosses a grid node of q2), and ``w[i]`` its length, so that
    ``warp_energy = Σ_i w_i (|A_i0 − B_i0|² + |A_i1 − B_i1|²) / 2``. This is a trapezoid
    rule per interval, which is what `optimal_rotation` computes on a 2-point "grid": passing
    ``(A, B, w)`` to it gives the rotation that exactly minimises `warp_energy` for fixed γ.
    """
    q1, q2 = _check_srvf_pair(q1, q2, "warp_energy")
    size = q1.shape[0]
    gamma = _check_gamma(gamma, size, q1.dtype, "warp_energy")
    gamma = _check_monotone(gamma, "warp_energy")
    last = size - 1
    x_grid = jnp.arange(size, dtype=q1.dtype)
    g = gamma * last  # γ in index units
    # Where γ crosses each node of q2's grid (γ is nondecreasing, so interp inverts it).
    x_cross = jnp.interp(x_grid, g, x_grid)
    x = jnp.sort(jnp.concatenate([x_grid, x_cross]))
    x0, x1 = x[:-1], x[1:]
    # The t-interval holding each merged interval fixes its slope (γ is linear inside).
    seg = jnp.clip(jnp.floor(0.5 * (x0 + x1)).astype(jnp.int32), 0, last - 1)
    slope = g[seg + 1] - g[seg]
    rs = _safe_sqrt(slope)[:, None, None]
    ends = jnp.stack([x0, x1], axis=1)  # (N, 2)
    y = g[seg][:, None] + slope[:, None] * (ends - seg[:, None].astype(q1.dtype))
    A = _lerp(q1, ends)
    B = rs * _lerp(q2, y)
    w = (x1 - x0) / last
    return A, B, w


def warp_energy(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]
) -> Float[Array, ""]:
    """``∫ |q1(t) − √γ'(t) q2(γ(t))|² dt`` for ``γ`` piecewise linear on the grid.

    Trapezoid rule on the merged breakpoints (grid nodes of t and the crossings of q2's grid
    nodes), with q1, q2 linear between nodes and γ' constant on each grid interval. This is the
    quantity `dp_warp` minimises exactly; with ``γ = id`` it equals the grid trapezoid
    ``||q1 − q2||²``.
    """
    A, B, w = warp_samples(q1, q2, gamma)
    diff = A - B
    return jnp.sum(w * 0.5 * jnp.sum(diff * diff, axis=(1, 2)))


def _sqrt_speed(gamma: Array) -> Array:
    """√γ' at the grid nodes: the mean of the one-sided √(finite differences)."""
    last = gamma.shape[0] - 1
    rs = _safe_sqrt(jnp.diff(gamma) * last)
    left = jnp.concatenate([rs[:1], rs])
    right = jnp.concatenate([rs, rs[-1:]])
    return 0.5 * (left + right)


def apply_warp_srvf(q: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]) -> Float[Array, "T d"]:
    """``(q∘γ)·√γ'`` on the grid: q linearly interpolated at γ(t_i); √γ' at a node is the mean
    of the square roots of the two adjacent finite differences (one at the ends), which is 0
    where γ is flat and has a finite gradient there."""
    q = jnp.asarray(q)
    if q.ndim != 2 or q.shape[0] < 2:
        raise InvalidRootError(f"apply_warp_srvf: q must have shape (T, d), T >= 2; got {q.shape}.")
    gamma = _check_gamma(gamma, q.shape[0], q.dtype, "apply_warp_srvf")
    gamma = _check_monotone(gamma, "apply_warp_srvf")
    last = q.shape[0] - 1
    return _lerp(q, gamma * last) * _sqrt_speed(gamma)[:, None]


def apply_warp_curve(
    beta: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]
) -> Float[Array, "T d"]:
    """``β∘γ`` on the grid (linear interpolation of β at γ(t_i))."""
    beta = jnp.asarray(beta)
    if beta.ndim != 2 or beta.shape[0] < 2:
        raise InvalidRootError(
            f"apply_warp_curve: beta must have shape (T, d), T >= 2; got {beta.shape}."
        )
    gamma = _check_gamma(gamma, beta.shape[0], beta.dtype, "apply_warp_curve")
    return _lerp(beta, gamma * (beta.shape[0] - 1))


def dp_warp_batch(
    q1s: Float[ArrayLike, "B T d"], q2s: Float[ArrayLike, "B T d"], *, neighbourhood: int = 7
) -> Float[Array, "B T"]:
    """`dp_warp` over a leading batch axis of pairs."""
    return jax.vmap(lambda a, b: dp_warp(a, b, neighbourhood=neighbourhood))(q1s, q2s)
