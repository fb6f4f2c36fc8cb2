"""Exact dynamic-programming reparameterisation of one SRVF onto another (docs/design.md §4, §8).

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
A ``lax.scan`` over the rows ``k`` reads the last ``neighbourhood`` rows of the cost table and
evaluates all moves, all columns and a block of pairs (batch-minor layout) in one fused loop;
a second scan walks the optimal path back, recomputing each vertex's move from a small window.
The DP is exact for this discretisation: `warp_energy` of the returned warp is the DP's
minimum (tests check both against a plain-numpy DP and against brute force).

Batching: `jax.vmap(dp_warp)` goes through a `custom_vmap` rule to the batched kernel (blocks of
pairs, inactive lanes skipped); `dp_warp_batch` also splits the batch across devices.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._curves import safe_sqrt
from ._devices import device_vmap
from ._errors import InvalidRootError

# ---------------------------------------------------------------------------------------------
# Move set and stencils (numpy, built once per (neighbourhood, T) at trace time)
# ---------------------------------------------------------------------------------------------


def dp_moves(neighbourhood: int) -> np.ndarray:
    """The DP's moves ``(a, b)``: ``1 <= a, b <= neighbourhood`` with ``gcd(a, b) = 1``."""
    n = check_neighbourhood(neighbourhood)
    return np.array(
        [(a, b) for a in range(1, n + 1) for b in range(1, n + 1) if math.gcd(a, b) == 1],
        dtype=np.int64,
    ).reshape(-1, 2)


def check_neighbourhood(neighbourhood) -> int:
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
        # Cross weights in exact rationals (times √slope·h, applied at the end): weights equal
        # within a move are then bitwise equal floats in float64 too (float32 rounding alone
        # already merged them), which `_forward` factors out.
        cross: dict[tuple[int, int], list[Fraction]] = {}

        def add_cross(m, r, o, c):
            cross.setdefault((r, o), [Fraction(0)] * m_count)[m] += c

        for m, (a, b) in enumerate(moves):
            a, b = int(a), int(b)
            slope = b / a
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
                wq = (hi - lo) / 2 * a  # w / h, exact
                fxq, fyq = x - math.floor(x), y - math.floor(y)
                for dr, cx in ((0, 1 - fxq), (1, fxq)):
                    for do, cy in ((0, 1 - fyq), (1, fyq)):
                        if cx and cy:
                            add_cross(m, r0 - dr, o0 - do, wq * cx * cy)
        keys = sorted(cross)
        scale = np.array([math.sqrt(b / a) * h for a, b in moves])
        self.neighbourhood = n
        self.moves = moves
        self.n1, self.p1, self.n2, self.p2 = n1, p1, n2, p2
        self.pairs = np.array(keys, dtype=np.int64).reshape(-1, 2)
        exact = np.array([[float(c) for c in cross[k]] for k in keys]).T  # (M, U)
        self.kern = exact * scale[:, None]


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
            f"{what}: gamma must be the warp sampled on the grid, shape ({n_points},), got {gamma.shape}."
        )
    return gamma.astype(dtype)


def _check_finite(x: Array, what: str) -> Array:
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{what}: input contains NaN or inf.")


# ---------------------------------------------------------------------------------------------
# The DP
# ---------------------------------------------------------------------------------------------


def _shifted(x: Array, n: int) -> Array:
    """``out[r, i, ...] = x[i − r, ...]`` for r = 0..n, zero where ``i − r < 0``."""
    size = x.shape[0]
    xp = jnp.concatenate([jnp.zeros((n,) + x.shape[1:], x.dtype), x])
    return jnp.stack([xp[n - r : n - r + size] for r in range(n + 1)])


def _edge_terms(q: Array, n_coef: np.ndarray, p_coef: np.ndarray) -> Array:
    """``Σ_r n[m, r]|q[i−r]|² + Σ_r p[m, r] q[i−r]·q[i−r+1]`` for every move m and node i.

    ``q`` has shape (T, B, d) (batch minor); the result has shape (M, T, B).
    """
    n = n_coef.shape[1] - 1
    sq = jnp.sum(q * q, axis=-1)
    nxt = jnp.sum(q[:-1] * q[1:], axis=-1)
    nxt = jnp.concatenate([nxt, jnp.zeros_like(nxt[:1])])
    dt = q.dtype
    return jnp.einsum("mr,rtb->mtb", jnp.asarray(n_coef, dt), _shifted(sq, n)) + jnp.einsum(
        "mr,rtb->mtb", jnp.asarray(p_coef, dt), _shifted(nxt, n)
    )


# Cross terms per fused loop. LLVM stopped vectorising the loop beyond ~600 terms (55 moves;
# measured with one multiply per term, before `_forward` grouped the terms by weight); groups
# of this size vectorise (checked in the dumped IR) and cost one switch branch each.
_TERMS_PER_LOOP = 400


def _move_groups(counts) -> list[list[int]]:
    """Consecutive moves, split so that each group has at most ~_TERMS_PER_LOOP cross terms
    (``counts[m]``: move m's)."""
    groups, current, count = [], [], 0
    for m, c in enumerate(counts):
        if current and count + c > _TERMS_PER_LOOP:
            groups.append(current)
            current, count = [], 0
        current.append(m)
        count += c
    groups.append(current)
    return groups


def _forward(q1: Array, q2: Array, n: int):
    """Cost table of the DP for a batch, laid out batch-minor for vectorisation.

    ``q1``, ``q2``: (B, T, d). Returns ``table`` (T+n, T+n, B) with ``table[k+n, l+n]`` the best
    cost from (0, 0) to (k, l) (inf where unreachable and in the n padding rows/columns), and
    the per-pair pieces of the segment cost: Gram (T, T, B), R1 (M, T, B), R2 (M, T, B).
    """
    batch, size, _ = q1.shape
    dtype = q1.dtype
    st = _stencil(n, size)
    a, b = st.moves[:, 0], st.moves[:, 1]
    inf = jnp.asarray(jnp.inf, dtype)
    q1t = jnp.swapaxes(q1, 0, 1)  # (T, B, d)
    q2t = jnp.swapaxes(q2, 0, 1)
    r1 = _edge_terms(q1t, st.n1, st.p1)
    r2 = _edge_terms(q2t, st.n2, st.p2)
    gram = jnp.einsum("ibd,jbd->ijb", q1t, q2t)
    gpad = jnp.pad(gram, ((n, 0), (n, 0), (0, 0)))
    r1_rows = jnp.moveaxis(r1, 1, 0)  # (T, M, B), scanned over
    # −2·kern: the cross term's factor folded into the coefficients (exact: a power of two),
    # one multiply less per move and cell (~3 % of the row loop).
    kern = (-2 * st.kern).astype(np.dtype(dtype))
    # Per move, its cross terms grouped by weight: c·(G_u + G_v + ...) instead of c·G_u + c·G_v
    # + ... Within a move the weights are small rational multiples of one value (the stencil
    # makes equal weights bitwise equal), so this halves the multiplies (362 → 171 at
    # neighbourhood 7); the row loop is bound by its arithmetic and runs ~1.1–1.2× faster.
    terms = []
    for m in range(len(a)):
        by_weight: dict = {}  # weight (a numpy scalar of the input dtype) → term indices
        for u in np.flatnonzero(kern[m]):
            by_weight.setdefault(kern[m, u], []).append(u)
        terms.append(list(by_weight.items()))

    def window(win, u):
        return win[n - st.pairs[u, 0], n - st.pairs[u, 1] : n - st.pairs[u, 1] + size]

    def group_min(best, win, hist, r1_k, members):
        # One chain of elementwise ops over (T, B): XLA fuses it into a single vectorised loop.
        # (A stacked (M, T, B) array reduced by min *and* argmin is computed twice by XLA.)
        for m in members:
            cross = sum(c * sum(window(win, u) for u in us) for c, us in terms[m])
            prev = hist[n - a[m], n - b[m] : n - b[m] + size]
            best = jnp.minimum(best, prev + (r1_k[m] + r2[m] + cross))
        return best

    groups = _move_groups([sum(len(us) for _, us in t) for t in terms])

    def row(table, xs):
        k, r1_k = xs
        win = jax.lax.dynamic_slice_in_dim(gpad, k, n + 1, axis=0)  # Gram rows k−n .. k
        hist = jax.lax.dynamic_slice_in_dim(table, k, n, axis=0)  # cost rows k−n .. k−1
        best = jnp.full((size, batch), inf)
        if len(groups) == 1:
            best = group_min(best, win, hist, r1_k, groups[0])
        else:
            # Several loops, each a branch of a switch so that XLA cannot fuse them back.
            branches = [functools.partial(group_min, members=g) for g in groups]

            def one_group(j, bst):
                return jax.lax.switch(j, branches, bst, win, hist, r1_k)

            best = jax.lax.fori_loop(0, len(groups), one_group, best)
        # Written from column n on: the n padding columns stay inf from the initial table (a
        # concatenated inf block here made the fused row loop ~8 % slower).
        start = (k + n, jnp.asarray(n, k.dtype), jnp.asarray(0, k.dtype))
        return jax.lax.dynamic_update_slice(table, best[None], start), None

    table = jnp.full((size + n, size + n, batch), inf, dtype).at[n, n].set(0)
    table, _ = jax.lax.scan(row, table, (jnp.arange(1, size), r1_rows[1:]))
    return table, gram, r1, r2


def _backtrack(table: Array, gram: Array, r1: Array, r2: Array, n: int) -> Array:
    """Warp on the grid for one pair, following the optimal path back from (T−1, T−1).

    The forward pass keeps costs only (storing back-pointers too makes XLA evaluate every
    candidate twice); each vertex's move is recomputed here from an (n+1)×(n+1) window.
    ``table`` (T+n, T+n), ``gram`` (T, T), ``r1`` and ``r2`` (M, T) are one pair's.
    """
    size = gram.shape[0]
    last = size - 1
    dtype = table.dtype
    st = _stencil(n, size)
    a_of = jnp.asarray(st.moves[:, 0], jnp.int32)
    b_of = jnp.asarray(st.moves[:, 1], jnp.int32)
    kern = jnp.asarray(st.kern, dtype)  # (M, U)
    wr = jnp.asarray(n - st.pairs[:, 0])
    wo = jnp.asarray(n - st.pairs[:, 1])
    gpad = jnp.pad(gram, ((n, 0), (n, 0)))

    def best_move(k, l):
        gwin = jax.lax.dynamic_slice(gpad, (k, l), (n + 1, n + 1))  # Gram[k−n..k, l−n..l]
        ewin = jax.lax.dynamic_slice(table, (k, l), (n + 1, n + 1))  # cost[k−n..k, l−n..l]
        cand = ewin[n - a_of, n - b_of] + r1[:, k] + r2[:, l] - 2 * (kern @ gwin[wr, wo])
        return jnp.argmin(cand)

    # Walk the path's vertices only (about a third of the rows on typical curves), then
    # interpolate γ linearly between them.
    def walk(state):
        k, l, count, ks, ls = state
        m = best_move(k, l)
        k, l = k - a_of[m], l - b_of[m]
        slot = size - 2 - count  # vertices are stored from the end, so ks ends increasing
        return k, l, count + 1, ks.at[slot].set(k), ls.at[slot].set(l)

    ks0 = jnp.zeros((size,), jnp.int32).at[-1].set(last)
    state = (jnp.int32(last), jnp.int32(last), jnp.int32(0), ks0, ks0)
    _, _, _, ks, ls = jax.lax.while_loop(lambda st: st[0] > 0, walk, state)
    # Unused leading slots hold (0, 0), the path's first vertex. Row k lies on the move from
    # vertex i to i+1; γ there is an exact ratio of integers, so it is bitwise the same in
    # every compiled variant (single pair, vmapped, sharded).
    rows = jnp.arange(size, dtype=jnp.int32)
    i = jnp.clip(jnp.searchsorted(ks, rows, side="right") - 1, 0, size - 2)
    k0, l0 = ks[i], ls[i]
    a, b = ks[i + 1] - k0, ls[i + 1] - l0
    return (l0 * a + (rows - k0) * b).astype(dtype) / (a * last).astype(dtype)


def _dp_block(q1: Array, q2: Array, n: int):
    """Warps (B, T) and DP minima (B,) for a batch of pairs, in one forward scan."""
    table, gram, r1, r2 = _forward(q1, q2, n)
    cost = table[-1, -1]
    gamma = jax.vmap(lambda t, g, x, y: _backtrack(t, g, x, y, n), in_axes=(2, 2, 2, 2))(table, gram, r1, r2)
    return gamma, cost


#: A remainder of fewer active pairs than this is solved pair by pair (`_dp_batched`): on an
#: AMD EPYC at T = 100 one pair alone takes 0.25-0.4 ms and a 16-pair block 2.6-4.0 ms.
_SINGLES_BELOW = 12
#: Blocks narrower than this vectorise badly (a 2-pair block costs more than 2 pairs alone):
#: a batch that small is solved pair by pair.
_MIN_BLOCK = 8


def _block_size(size: int) -> int:
    # Pairs per block of the batched kernel. Small blocks keep the rows of the forward pass in
    # cache and let converged lanes of a vmapped loop be skipped; measured best on an AMD EPYC
    # (Zen 4) at T·B ≈ 1,600 (B = 16 at T = 100), with at least 8 lanes for the vector units.
    return int(min(64, max(8, 1600 // size)))


def _dp_batched(q1: Array, q2: Array, active: Array, n: int):
    """`_dp_block` over the *active* pairs of a batch, one block after another.

    Active pairs are packed into blocks (inactive ones get the identity warp and cost 0), so a
    vmapped loop whose lanes finish at different times (the rotation/warp alternation) pays
    for the lanes still running, not for the whole batch at every step. Blocks run in a
    `fori_loop`, bounding memory. A remainder of fewer than `_SINGLES_BELOW` active pairs is
    solved one pair at a time: a one-pair block vectorises along the curve instead of the
    batch and costs about a tenth of a 16-pair block, which matters in the engine's lazy
    assignments, where a loop step often has one to a few DPs to run. A pair gets the same
    warp either way (the DP minimum may differ in the last bits: XLA rounds a one-pair
    contraction differently; the engine uses the warps).
    """
    batch, size, _ = q1.shape
    block = min(_block_size(size), batch)
    if block < _MIN_BLOCK:
        block = 1
    if batch == 1:
        gamma, cost = _dp_block(q1, q2, n)
        identity = jnp.linspace(0, 1, size, dtype=q1.dtype)
        return jnp.where(active[:, None], gamma, identity), jnp.where(active, cost, 0)
    n_slots = -(-batch // block) * block
    # Active lanes first (a stable sort keeps their order), padded to whole blocks.
    order = jnp.argsort(~active, stable=True)
    pad = n_slots - batch
    order_p = jnp.concatenate([order, jnp.zeros((pad,), order.dtype)]) if pad else order
    q1p, q2p = q1[order_p], q2[order_p]
    n_active = jnp.sum(active, dtype=jnp.int32)
    n_blocks = n_active // block
    rest = n_active - n_blocks * block
    n_blocks = n_blocks + (rest >= min(_SINGLES_BELOW, block)).astype(jnp.int32)

    def solve(width):
        """Loop body: the `width` packed pairs from slot ``s * width`` on."""

        def body(s, out):
            gamma_out, cost_out = out
            x = jax.lax.dynamic_slice_in_dim(q1p, s * width, width)
            y = jax.lax.dynamic_slice_in_dim(q2p, s * width, width)
            gamma, cost = _dp_block(x, y, n)
            return (
                jax.lax.dynamic_update_slice_in_dim(gamma_out, gamma, s * width, axis=0),
                jax.lax.dynamic_update_slice_in_dim(cost_out, cost, s * width, axis=0),
            )

        return body

    identity = jnp.linspace(0, 1, size, dtype=q1.dtype)
    gamma0 = jnp.broadcast_to(identity, (n_slots, size))
    cost0 = jnp.zeros((n_slots,), q1.dtype)
    gamma_p, cost_p = jax.lax.fori_loop(0, n_blocks, solve(block), (gamma0, cost0))
    if block > 1:
        # The active pairs after the whole blocks (none when the last block took them).
        gamma_p, cost_p = jax.lax.fori_loop(n_blocks * block, n_active, solve(1), (gamma_p, cost_p))
    inverse = jnp.argsort(order)
    gamma, cost = gamma_p[inverse], cost_p[inverse]
    return jnp.where(active[:, None], gamma, identity), jnp.where(active, cost, 0)


@functools.lru_cache(maxsize=None)
def _dp_kernel(n: int):
    """The DP for one pair, as a `custom_vmap` whose batching rule runs `_dp_batched`.

    Plain `vmap` of the single-pair scan puts the batch on the leading axis and runs ~5× slower
    than the batch-minor layout of `_forward`; this rule gives `jax.vmap(dp_warp)` the fast
    path. ``active`` (a bool) only matters when batched: inactive pairs are skipped and get
    the identity warp and cost 0. Nested vmaps are flattened into one batch. Not
    differentiable: callers pass `stop_gradient`-ed inputs (γ is piecewise constant in q).
    """

    @jax.custom_batching.custom_vmap
    def single(q1, q2, active):
        gamma, cost = _dp_block(q1[None], q2[None], n)
        return gamma[0], cost[0]

    @single.def_vmap
    def _rule(axis_size, in_batched, q1, q2, active):
        args = _broadcast_unbatched(axis_size, in_batched, (q1, q2, active))
        return _batched_kernel(n)(*args), (True, True)

    return single


@functools.lru_cache(maxsize=None)
def _batched_kernel(n: int):
    """`_dp_batched` on (B, T, d), flattening any further vmapped axes into the batch."""

    @jax.custom_batching.custom_vmap
    def batched(q1, q2, active):
        return _dp_batched(q1, q2, active, n)

    @batched.def_vmap
    def _rule(axis_size, in_batched, q1, q2, active):
        q1, q2, active = _broadcast_unbatched(axis_size, in_batched, (q1, q2, active))
        outer, inner = active.shape
        gamma, cost = batched(q1.reshape((-1,) + q1.shape[2:]), q2.reshape((-1,) + q2.shape[2:]), active.reshape(-1))
        return (gamma.reshape(outer, inner, -1), cost.reshape(outer, inner)), (True, True)

    return batched


def _broadcast_unbatched(axis_size, in_batched, args):
    return tuple(
        x if batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)) for x, batched in zip(args, in_batched)
    )


def _prepare(q1, q2, neighbourhood, what, *, check=True):
    q1, q2 = _check_srvf_pair(q1, q2, what)
    n = check_neighbourhood(neighbourhood)
    # Moves longer than the grid can never be used; dropping them changes nothing.
    n = min(n, q1.shape[0] - 1)
    q1, q2 = jax.lax.stop_gradient((q1, q2))
    if check:
        q1 = _check_finite(q1, f"{what} (q1)")
        q2 = _check_finite(q2, f"{what} (q2)")
    return q1, q2, n


def _dp_warp_nan(q1, q2, *, neighbourhood):
    """`dp_warp` that returns a NaN warp for non-finite input instead of raising.

    For use under `device_vmap`: a runtime error (`eqx.error_if`) raised by one device of a
    multi-device program leaves the others waiting in a collective, and the process aborts.
    """
    q1, q2, n = _prepare(q1, q2, neighbourhood, "dp_warp", check=False)
    ok = jnp.all(jnp.isfinite(q1)) & jnp.all(jnp.isfinite(q2))
    gamma = _dp_kernel(n)(jnp.where(ok, q1, 0), jnp.where(ok, q2, 0), jnp.asarray(True))[0]
    return jnp.where(ok, gamma, jnp.nan)


@eqx.filter_jit
def dp_warp_and_energy(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], *, neighbourhood: int = 7
) -> tuple[Float[Array, " T"], Float[Array, ""]]:
    """`dp_warp` and the DP's minimum (``warp_energy(q1, q2, gamma)`` up to rounding).

    The minimum is computed by the expanded stencil, so in float32 it carries cancellation
    error of order ``1e-7·(||q1||² + ||q2||²)``; recompute `warp_energy` when that matters.
    Neither output carries gradients.
    """
    q1, q2, n = _prepare(q1, q2, neighbourhood, "dp_warp")
    return _dp_kernel(n)(q1, q2, jnp.asarray(True))


def dp_warp_if(q1: Array, q2: Array, active: Array, *, neighbourhood: int, check: bool = True) -> tuple[Array, Array]:
    """`dp_warp_and_energy` for loops under `vmap`: lanes with ``active`` False are skipped
    (identity warp, cost 0) instead of being computed and thrown away. ``check=False`` skips
    the NaN/inf check (an `eqx.error_if`, which is a host callback) for inputs finite by
    construction."""
    q1, q2, n = _prepare(q1, q2, neighbourhood, "dp_warp", check=check)
    return _dp_kernel(n)(q1, q2, jnp.asarray(active, bool))


def dp_warp(q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], *, neighbourhood: int = 7) -> Float[Array, " T"]:
    """Optimal warp ``γ`` of ``q2`` onto ``q1`` by exact dynamic programming.

    Minimises ``∫|q1(t) − √γ'(t) q2(γ(t))|² dt`` (see the module docstring for the exact
    discretisation; `warp_energy` evaluates it) over the strictly increasing paths of the T×T
    grid built from the coprime moves of ``neighbourhood``.

    **Arguments**

    - `q1`, `q2`: SRVFs on ``linspace(0, 1, T)``, shape ``(T, d)``; float32 or float64.
    - `neighbourhood`: largest step of a move along either axis (static Python int; default
      7, fdasrsf uses 10 for curves). Larger is more accurate and slower (35 moves at 7,
      63 at 10).

    **Returns** ``γ`` on the grid, shape ``(T,)``: ``γ[0] = 0``, ``γ[-1] = 1``, increasing,
    linear between the path's vertices; no gradient flows through it. Compiles once per
    ``(T, d, dtype, neighbourhood)``. `jax.vmap` of it runs a batched kernel; `dp_warp_batch`
    also spreads a batch over every device.
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


def _check_monotone(gamma: Array, what: str) -> Array:
    tol = 16 * jnp.finfo(gamma.dtype).eps
    ends_bad = (jnp.abs(gamma[0]) > tol) | (jnp.abs(gamma[-1] - 1) > tol)
    bad = jnp.any(jnp.diff(gamma) < -tol) | ends_bad | ~jnp.all(jnp.isfinite(gamma))
    return eqx.error_if(gamma, bad, f"{what}: gamma must be nondecreasing from gamma[0] = 0 to gamma[-1] = 1.")


def warp_samples(
    q1: Float[ArrayLike, "T d"], q2: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]
) -> tuple[Float[Array, "N 2 d"], Float[Array, "N 2 d"], Float[Array, " N"]]:
    """The quadrature behind `warp_energy`, interval by interval.

    Returns ``(A, B, w)``: ``A[i, e] = q1(τ)`` and ``B[i, e] = √γ'·q2(γ(τ))`` at the two ends
    ``e`` of the i-th interval between merged breakpoints (grid nodes of t, and the points where
    γ crosses a grid node of q2), and ``w[i]`` its length, so that
    ``warp_energy = Σ_i w_i (|A_i0 − B_i0|² + |A_i1 − B_i1|²) / 2``. This is a trapezoid
    rule per interval, which is what `optimal_rotation` computes on a 2-point "grid": passing
    ``(A, B, w)`` to it gives the rotation that exactly minimises `warp_energy` for fixed γ.
    The ``2T`` intervals are unordered, and some have zero length.
    """
    q1, q2 = _check_srvf_pair(q1, q2, "warp_energy")
    size = q1.shape[0]
    gamma = _check_gamma(gamma, size, q1.dtype, "warp_energy")
    gamma = _check_monotone(gamma, "warp_energy")
    return warp_samples_unchecked(q1, q2, gamma)


def warp_samples_unchecked(q1: Array, q2: Array, gamma: Array):
    size = q1.shape[0]
    dtype = q1.dtype
    last = size - 1
    x_grid = jnp.arange(size, dtype=dtype)
    g = gamma * last  # γ in index units
    # Where γ crosses each node of q2's grid (γ is nondecreasing, so interp inverts it).
    x_cross = jnp.interp(x_grid, g, x_grid)
    # Each breakpoint starts one interval, ending at its successor in the merged order (a grid
    # node before a crossing at the same place). Successors are found without sorting the
    # 2T breakpoints (XLA:CPU's sort was 60 % of this function): after grid node i come node
    # i+1 and the first crossing at or beyond i; after crossing j, crossing j+1 and the first
    # node strictly beyond it. The last breakpoints get empty intervals.
    first = jnp.sum(x_cross[None, :] < x_grid[:, None], axis=1)  # first crossing >= node i
    cross_after = jnp.where(first < size, x_cross[jnp.minimum(first, last)], last)
    end_grid = jnp.minimum(jnp.minimum(x_grid + 1, last), cross_after)
    next_cross = jnp.concatenate([x_cross[1:], jnp.full((1,), last, dtype)])
    end_cross = jnp.minimum(next_cross, jnp.minimum(jnp.floor(x_cross) + 1, last))
    x0 = jnp.concatenate([x_grid, x_cross])
    x1 = jnp.concatenate([end_grid, end_cross])
    # The t-interval holding each merged interval fixes its slope (γ is linear inside).
    seg = jnp.clip(jnp.floor(0.5 * (x0 + x1)).astype(jnp.int32), 0, last - 1)
    slope = g[seg + 1] - g[seg]
    rs = safe_sqrt(slope)[:, None, None]
    ends = jnp.stack([x0, x1], axis=1)  # (N, 2)
    y = g[seg][:, None] + slope[:, None] * (ends - seg[:, None].astype(dtype))
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
    rs = safe_sqrt(jnp.diff(gamma) * last)
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
    return warp_srvf(q, gamma)


def warp_srvf(q: Array, gamma: Array) -> Array:
    """`apply_warp_srvf` without its checks, for warps increasing by construction (the DP's):
    no `eqx.error_if` (a host callback) in the programs that call it."""
    return _lerp(q, gamma * (q.shape[0] - 1)) * _sqrt_speed(gamma)[:, None]


def apply_warp_curve(beta: Float[ArrayLike, "T d"], gamma: Float[ArrayLike, " T"]) -> Float[Array, "T d"]:
    """``β∘γ`` on the grid (linear interpolation of β at γ(t_i))."""
    beta = jnp.asarray(beta)
    if beta.ndim != 2 or beta.shape[0] < 2:
        raise InvalidRootError(f"apply_warp_curve: beta must have shape (T, d), T >= 2; got {beta.shape}.")
    gamma = _check_gamma(gamma, beta.shape[0], beta.dtype, "apply_warp_curve")
    gamma = _check_monotone(gamma, "apply_warp_curve")
    return _lerp(beta, gamma * (beta.shape[0] - 1))


@eqx.filter_jit
def dp_warp_batch(
    q1s: Float[ArrayLike, "B T d"], q2s: Float[ArrayLike, "B T d"], *, neighbourhood: int = 7
) -> Float[Array, "B T"]:
    """`dp_warp` for a batch of pairs (leading axis), split across every available device.

    With several devices (``jax.config.update("jax_num_cpu_devices", n)`` before JAX starts)
    each gets an equal share of the batch (`device_vmap`); otherwise it is `jax.vmap(dp_warp)`.
    A pair with NaN or inf values gets a NaN warp (no runtime error: raised on one device of
    a multi-device program, it would leave the other devices waiting forever).
    """
    q1s, q2s = jnp.asarray(q1s), jnp.asarray(q2s)
    if q1s.ndim != 3 or q1s.shape != q2s.shape:
        raise InvalidRootError(
            f"dp_warp_batch: q1s and q2s must share the shape (B, T, d), got {q1s.shape} and {q2s.shape}."
        )
    fn = functools.partial(_dp_warp_nan, neighbourhood=neighbourhood)
    return device_vmap(fn)(q1s, q2s)
