"""Registration of root b onto root a: rotation, reparameterisations and lateral correspondence.

The Duncan et al. formulation the paper follows (DESIGN.md §4). With the rotation fixed the
problem splits exactly: one DP warp for the main roots, one DP warp per real–real lateral pair
giving the K×K cost matrix ``C[i, j] = λs min_γ ||qa_i − (qb_j∘γ)√γ'||² + λp (sa_i − sb_j)²``,
real–null ``λs||q||²``, null–null 0, then one exact linear assignment. The rotation is then
refitted (weighted Kabsch over all matched branches) and the two steps alternate until the energy
stops falling.

Work that cannot change the answer is skipped. By Cauchy–Schwarz
``||qa − qbw||² ≥ (||qa|| − ||qbw||)²`` and warps here preserve the norm (``||qbw|| = ||qb||``,
see `_warp_preserving_norm`), so ``λs(√La − √Lb)² + λp Δs²`` bounds ``C[i, j]`` from below
without any DP. The assignment is first solved with these bounds in place of the lateral costs;
the DPs of the real–real pairs it picks are run, and it is solved again, until it picks only
pairs whose true cost is known. That assignment is optimal for the true matrix as well (every
unknown entry is at least its bound), so the result is exactly that of running every DP — a
test checks it — while most DPs are never run. (DESIGN.md §8's static rule, "skip a pair whose
bound exceeds both-to-nulls", is a special case: such a pair is never picked.)

Lateral DPs are not vmapped over all K² slots: the pairs to solve, across a whole batch of root
pairs, are compacted into one list and solved in fixed-size slabs (a loop with a data-dependent
trip count), so padding and skipped pairs cost nothing and one compiled program serves all.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array, Bool, Float, Int

from ._assignment import linear_assignment
from ._curves import _safe_sqrt, _tiny, l2_norm_squared, safe_norm, safe_normalise
from ._metric import MetricTerms, Weights, preshape_terms
from ._rotation import optimal_rotation
from ._tree import RootTree, SRVFTree, check_compatible, to_srvf
from ._warp import apply_warp_srvf, dp_warp


class Registration(eqx.Module):
    """Result of registering root b onto root a (a batch adds leading axes ``*B``).

    **Fields**

    - `registered`: b rotated, reparameterised and permuted into a's slot order, as an
      `SRVFTree`. A null lateral of b that is matched with a real lateral of a sits at its
      partner's attachment fraction.
    - `permutation`: ``[K]`` — slot k of `registered` is slot ``permutation[k]`` of b.
    - `rotation`: ``[d, d]`` rotation applied to b (about its origin).
    - `main_warp`: ``[T]`` reparameterisation γ of b's main root, on the grid.
    - `lateral_warps`: ``[K, T]`` γ applied to b's lateral ``permutation[k]`` (identity unless
      both slots are real).
    - `terms`: the three weighted terms of the minimised squared distance.
    - `n_iterations`: rotation ↔ correspondence alternations performed.
    - `n_lateral_dp`: lateral DP warps actually run; `n_lateral_skipped`: real–real lateral
      pairs, summed over rounds, whose DP the exact lower bound made unnecessary.
    """

    registered: SRVFTree
    permutation: Int[Array, "*B K"]
    rotation: Float[Array, "*B d d"]
    main_warp: Float[Array, "*B T"]
    lateral_warps: Float[Array, "*B K T"]
    terms: MetricTerms
    n_iterations: Int[Array, "*B"]
    n_lateral_dp: Int[Array, "*B"]
    n_lateral_skipped: Int[Array, "*B"]

    @property
    def energy(self) -> Float[Array, "*B"]:
        """Minimised squared distance ``d²``."""
        return self.terms.total

    @property
    def distance(self) -> Float[Array, "*B"]:
        """Geodesic distance ``sqrt(d²)`` (0 with a zero gradient at coincident roots)."""
        return _safe_sqrt(self.terms.total)


def _rotate(q: Array, O: Array) -> Array:
    return q @ O.T


def _warp_preserving_norm(q: Float[Array, "T d"], gamma: Float[Array, " T"]) -> Float[Array, "T d"]:
    """``(q∘γ)√γ'`` rescaled so that its L2 norm equals ``||q||``.

    In the continuum the reparameterisation action is an isometry; on the grid the interpolated
    warp changes the norm by O(h²). Restoring it keeps the branch length exact (so registered
    roots keep their lengths) and makes the pruning bound above exact.
    """
    w = apply_warp_srvf(q, gamma)
    n2 = l2_norm_squared(q)
    w2 = l2_norm_squared(w)
    ok = w2 > _tiny(w.dtype)
    return w * _safe_sqrt(jnp.where(ok, n2 / jnp.where(ok, w2, 1.0), 0.0))


def _direction_cone(q: Float[Array, "*B T d"]) -> tuple[Array, Array]:
    """Axis (unit chord direction) and half-angle of a cone holding every direction of q.

    Branches with no direction (nulls) get half-angle π: no information.
    """
    n = safe_norm(q)
    u = safe_normalise(q)
    axis = safe_normalise(jnp.sum(q * n[..., None], axis=-2))
    cos = jnp.sum(u * axis[..., None, :], axis=-1)
    angle = jnp.arccos(jnp.clip(cos, -1.0, 1.0))
    half = jnp.max(jnp.where(n > 0, angle, 0.0), axis=-1)
    has_axis = safe_norm(axis) > 0
    return axis, jnp.where(has_axis, half, jnp.pi)


def _identity_grid(T: int, dtype) -> Array:
    return jnp.linspace(0.0, 1.0, T, dtype=dtype)


def _search(
    a: SRVFTree,
    b: SRVFTree,
    weights: Weights,
    active: Bool[Array, " B"],
    dynamic: tuple,
    *,
    neighbourhood: int,
    prune: bool,
    dp_batch_size: int,
    assignment: str,
):
    """Optimal (rotation, permutation, warps) for a batch of B pairs; no gradients.

    `dynamic` = (rotation, max_iterations, rtol) as arrays: traced, so changing them never
    recompiles; the keyword options change the program's structure and are static.
    """
    rotation, max_iterations, rtol = dynamic
    a, b, weights = jax.lax.stop_gradient((a, b, weights))
    B, K, T, d = b.q.shape
    dtype = a.q0.dtype
    lam_m, lam_s, lam_p = (jnp.asarray(w, dtype) for w in (weights.main, weights.lateral, weights.position))

    La = l2_norm_squared(a.q) * a.mask
    Lb = l2_norm_squared(b.q) * b.mask
    pos = lam_p * (a.s[:, :, None] - b.s[:, None, :]) ** 2
    null_a = lam_s * La
    null_b = lam_s * Lb
    both = a.mask[:, :, None] & b.mask[:, None, :]
    others = jnp.where(
        a.mask[:, :, None],
        null_a[:, :, None],
        jnp.where(b.mask[:, None, :], null_b[:, None, :], 0.0),
    )
    ca, half_a = _direction_cone(a.q)
    cb, half_b = _direction_cone(b.q)
    sqrt_LaLb = jnp.sqrt(La)[:, :, None] * jnp.sqrt(Lb)[:, None, :]

    def lower_bounds(O):
        """Exact lower bound of every real-real cost at rotation O, without any DP.

        ``||qa − w||² = La + Lb − 2<qa, w>`` for the warped, norm-preserved w. Every value of w
        is a positive multiple of an interpolation of values of qb, so its direction lies in
        the convex cone (half-angle < 90°) holding b's directions; with qa's cone, the angle
        between the two cones caps the cosine: ``<qa, w> ≤ max(cos φ, 0) √(La Lb)``, where
        ``φ = angle(axes) − half_a − half_b``. With φ ≤ 0 this is plain Cauchy–Schwarz.
        """
        cos_axes = jnp.einsum("bie,bjd,bed->bij", ca, cb, O)
        phi = jnp.arccos(jnp.clip(cos_axes, -1.0, 1.0)) - half_a[:, :, None] - half_b[:, None, :]
        # Rounding margin (arccos near ±1 loses half the digits): keep the bound on the safe side.
        phi = phi - 4 * float(jnp.finfo(dtype).eps) ** 0.5
        convex = (half_a[:, :, None] < jnp.pi / 2) & (half_b[:, None, :] < jnp.pi / 2)
        cos_cap = jnp.where(convex, jnp.clip(jnp.cos(jnp.maximum(phi, 0.0)), 0.0, 1.0), 1.0)
        lower = lam_s * jnp.maximum(La[:, :, None] + Lb[:, None, :] - 2 * cos_cap * sqrt_LaLb, 0.0)
        return jnp.where(both, lower + pos, others)

    n_pairs = B * K * K
    identity = _identity_grid(T, dtype)
    dp = jax.vmap(functools.partial(dp_warp, neighbourhood=neighbourhood))
    solve = jax.vmap(lambda c: linear_assignment(c, method=assignment))

    def run_dps(need, pair_of, E, G=None):
        """Solve the DPs of the items flagged in `need` in slabs of a fixed size.

        `pair_of(lanes)` gives the (q1, q2) of each item. One DP call site, compiled once,
        whatever the number of DPs needed; returns the energies (and warps, when G is given)
        scattered into E (and G).
        """
        n_items = need.shape[0]
        # Small slabs: the DP is as efficient at 32 lanes as at 256, and less padding is solved.
        S = min(dp_batch_size, max(8, -(-n_items // 16)))
        n_pad = -(-n_items // S) * S
        (lanes_all,) = jnp.nonzero(need, size=n_pad, fill_value=n_items)

        def slab(k, carry):
            E, G = carry
            lanes = lax.dynamic_slice(lanes_all, (k * S,), (S,))
            q1, q2 = pair_of(jnp.clip(lanes, 0, n_items - 1))
            g = dp(q1, q2)
            w = jax.vmap(_warp_preserving_norm)(q2, g)
            E = E.at[lanes].set(l2_norm_squared(q1 - w), mode="drop")
            if G is not None:
                G = G.at[lanes].set(g, mode="drop")
            return E, G

        return lax.fori_loop(0, (jnp.sum(need) + S - 1) // S, slab, (E, G))

    def evaluate(O, rows):
        """Energy, permutation and warps of every pair at rotations O (rows: pairs to do).

        Lazy and exact: the assignment is solved with lower bounds in place of the lateral
        costs not computed yet; the DPs of the real-real pairs it picks are run and the
        assignment solved again, until it picks only computed pairs. Then it is optimal for the
        true costs too, since every uncomputed cost is at least its bound. With prune=False every
        real-real DP is run up front (the reference behaviour). Only costs are kept while
        searching; the few warps of the final matching are solved again at the end, which is
        far cheaper than storing a warp for every candidate pair.
        """
        qb0 = jnp.einsum("btd,bed->bte", b.q0, O)
        qb = jnp.einsum("bktd,bed->bkte", b.q, O)

        def lateral_pair(lanes):
            bi, rem = jnp.divmod(lanes, K * K)
            i, j = jnp.divmod(rem, K)
            return a.q[bi, i], qb[bi, j]

        base_cost = lower_bounds(O)

        def costs(E, computed):
            return jnp.where(computed, lam_s * E.reshape(B, K, K) + pos, base_cost)

        def picks(perm, computed):
            chosen = jax.nn.one_hot(perm, K, dtype=bool)
            return chosen & both & ~computed & rows[:, None, None]

        computed = both & rows[:, None, None] if not prune else jnp.zeros_like(both)
        E, _ = run_dps(computed.reshape(-1), lateral_pair, jnp.zeros((n_pairs,), dtype))

        def cond(state):
            return jnp.any(state[-1])

        def body(state):
            E, computed, perm, chosen = state
            E, _ = run_dps(chosen.reshape(-1), lateral_pair, E)
            computed = computed | chosen
            perm = solve(costs(E, computed))
            return E, computed, perm, picks(perm, computed)

        perm = solve(costs(E, computed))
        E, computed, perm, _ = lax.while_loop(cond, body, (E, computed, perm, picks(perm, computed)))
        C = costs(E, computed)
        lap = jnp.sum(jnp.take_along_axis(C, perm[:, :, None], axis=2)[:, :, 0], axis=1)

        # Warps of the final matching: the B main roots, then the matched real-real slots.
        matched = jax.nn.one_hot(perm, K, dtype=bool) & both
        matched_slots = jnp.any(matched, axis=2)  # (B, K): slot k of a has a real partner

        def final_pair(lanes):
            is_main = lanes < B
            bm = jnp.clip(lanes, 0, B - 1)
            bi, k = jnp.divmod(jnp.clip(lanes - B, 0, B * K - 1), K)
            j = perm[bi, k]
            q1 = jnp.where(is_main[:, None, None], a.q0[bm], a.q[bi, k])
            q2 = jnp.where(is_main[:, None, None], qb0[bm], qb[bi, j])
            return q1, q2

        need = jnp.concatenate([rows, (matched_slots & rows[:, None]).reshape(-1)])
        n_final = B + B * K
        Ef, Gf = run_dps(
            need, final_pair, jnp.zeros((n_final,), dtype), jnp.broadcast_to(identity, (n_final, T))
        )
        n_dp = jnp.sum(computed.reshape(B, K * K), axis=1, dtype=jnp.int32)
        return lam_m * Ef[:B] + lap, perm, Gf[:B], Gf[B:].reshape(B, K, T), n_dp

    def refit_rotation(perm, g0, gam):
        q0w = jax.vmap(_warp_preserving_norm)(b.q0, g0)
        qbp = jnp.take_along_axis(b.q, perm[:, :, None, None], axis=1)
        mbp = jnp.take_along_axis(b.mask, perm, axis=1)
        qw = jax.vmap(jax.vmap(_warp_preserving_norm))(qbp, gam)
        A = jnp.concatenate([a.q0[:, None], a.q], axis=1)
        Bm = jnp.concatenate([q0w[:, None], qw], axis=1)
        w = jnp.concatenate(
            [jnp.broadcast_to(lam_m, (B, 1)), lam_s * (a.mask & mbp).astype(dtype)], axis=1
        )
        return jax.vmap(optimal_rotation)(A, Bm, w)

    eye = jnp.broadcast_to(jnp.eye(d, dtype=dtype), (B, d, d))
    # Start from the rotation that aligns the main roots.
    O_start = jnp.where(rotation, jax.vmap(optimal_rotation)(a.q0, b.q0), eye)
    n_rounds = jnp.where(rotation, max_iterations, 1)

    def cond(state):
        it, done = state[0], state[6]
        return (it < n_rounds) & jnp.any(~done)

    def body(state):
        it, O, E, perm, g0, gam, done, iters, n_dp = state
        # Round 0 evaluates the starting rotation; later rounds refit it to the matching.
        O_new = lax.cond(it == 0, lambda: O_start, lambda: refit_rotation(perm, g0, gam))
        E_new, perm_new, g0_new, gam_new, n_dp_new = evaluate(O_new, ~done)
        better = (E_new < E) & ~done
        rel = jnp.where(jnp.isinf(E), jnp.inf, (E - E_new) / jnp.maximum(E, _tiny(dtype)))

        def pick(new, old):
            return jnp.where(better.reshape((B,) + (1,) * (new.ndim - 1)), new, old)

        iters = iters + (~done).astype(jnp.int32)
        done = done | ~better | (rel < rtol)
        return (
            it + 1,
            pick(O_new, O),
            pick(E_new, E),
            pick(perm_new, perm),
            pick(g0_new, g0),
            pick(gam_new, gam),
            done,
            iters,
            n_dp + n_dp_new,
        )

    state = (
        jnp.asarray(0),
        eye,
        jnp.full((B,), jnp.inf, dtype),
        jnp.broadcast_to(jnp.arange(K), (B, K)),
        jnp.broadcast_to(identity, (B, T)),
        jnp.broadcast_to(identity, (B, K, T)),
        ~active,
        jnp.zeros((B,), jnp.int32),
        jnp.zeros((B,), jnp.int32),
    )
    _, O, E, perm, g0, gam, _, iters, n_dp = lax.while_loop(cond, body, state)
    n_real = jnp.sum(both.reshape(B, -1), axis=1, dtype=jnp.int32)
    # Lateral DPs skipped: real-real pairs of every round that were never solved.
    n_skipped = jnp.maximum(n_real * iters - n_dp, 0)
    return O, perm, g0, gam, iters, n_dp, n_skipped


def _device_safe(options: dict) -> dict:
    """With several devices the assignment must run in JAX: a host callback inside a multi-device
    program whose loops run different trip counts per device deadlocks XLA:CPU's collectives."""
    if len(jax.devices()) > 1 and options.get("assignment") == "callback":
        return {**options, "assignment": "jax"}
    return options


def _search_split_args(a, b, active, weights, dynamic, **options):
    return _search(a, b, weights, active, dynamic, **options)


def _apply(a: SRVFTree, b: SRVFTree, O, perm, g0, gam) -> SRVFTree:
    """b registered into a's slot order (single pair); differentiable in a and b."""
    q0 = _warp_preserving_norm(_rotate(b.q0, O), g0)
    qb = _rotate(b.q, O)[perm]
    mb = b.mask[perm]
    qw = jax.vmap(_warp_preserving_norm)(qb, gam) * mb[:, None, None]
    s = jnp.where(mb, b.s[perm], a.s)
    return SRVFTree(q0=q0, q=qw, s=s, mask=mb, origin=b.origin)


def split_over_devices(fn, batched: tuple, shared: tuple = ()):
    """Run ``fn(*batched, *shared)`` with the pairs of `batched` (leading axis) split evenly
    across all devices (`shard_map`); `shared` arguments are replicated.

    Pairs are independent, so no collective runs inside: each device registers its own share
    (host callbacks included). The batch is padded with inactive copies of its first pair; the
    last of `batched` must be the boolean `active` vector. With one device, ``fn`` is called as is.
    """
    devices = jax.devices()
    n_dev = len(devices)
    size = batched[-1].shape[0]
    if n_dev <= 1 or size < n_dev:
        return fn(*batched, *shared)
    pad = (-size) % n_dev
    if pad:
        *data, active = batched
        data = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), data)
        batched = (*data, jnp.concatenate([active, jnp.zeros((pad,), bool)]))
    mesh = Mesh(np.asarray(devices), ("pairs",))
    specs = (PartitionSpec("pairs"),) * len(batched) + (PartitionSpec(),) * len(shared)
    out = jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("pairs"), check_vma=False)(
        *batched, *shared
    )
    return jax.tree.map(lambda x: x[:size], out) if pad else out


@eqx.filter_jit
def _register_batch(
    a: SRVFTree, b: SRVFTree, weights: Weights, active, dynamic, **options
) -> Registration:
    search = functools.partial(_search_split_args, **_device_safe(options))
    O, perm, g0, gam, iters, n_dp, n_skipped = split_over_devices(
        search, (a, b, active), (weights, dynamic)
    )
    registered = jax.vmap(_apply)(a, b, O, perm, g0, gam)
    terms = preshape_terms(a, registered, weights)
    return Registration(
        registered=registered,
        permutation=perm,
        rotation=O,
        main_warp=g0,
        lateral_warps=gam,
        terms=terms,
        n_iterations=iters,
        n_lateral_dp=n_dp,
        n_lateral_skipped=n_skipped,
    )


def _options(
    rotation, max_iterations, rtol, neighbourhood, prune, dp_batch_size, assignment
) -> tuple[tuple, dict]:
    """(dynamic, static) registration options: the dynamic ones are arrays (no recompilation
    when they change), the static ones shape the compiled program."""
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise ValueError(f"max_iterations must be an integer >= 1, got {max_iterations!r}.")
    if not isinstance(neighbourhood, int) or neighbourhood < 1:
        raise ValueError(f"neighbourhood must be an integer >= 1, got {neighbourhood!r}.")
    if not isinstance(dp_batch_size, int) or dp_batch_size < 1:
        raise ValueError(f"dp_batch_size must be an integer >= 1, got {dp_batch_size!r}.")
    if assignment not in ("callback", "jax"):
        raise ValueError(f"assignment must be 'callback' or 'jax', got {assignment!r}.")
    if not rtol >= 0:
        raise ValueError(f"rtol must be a non-negative number, got {rtol!r}.")
    dynamic = (jnp.asarray(bool(rotation)), jnp.asarray(max_iterations, jnp.int32), jnp.asarray(float(rtol)))
    return dynamic, dict(
        neighbourhood=neighbourhood,
        prune=bool(prune),
        dp_batch_size=dp_batch_size,
        assignment=assignment,
    )


def _as_pair_batch(a, b) -> tuple[SRVFTree, SRVFTree, bool]:
    for name, t in (("a", a), ("b", b)):
        if not isinstance(t, (RootTree, SRVFTree)):
            raise TypeError(
                f"register: {name} must be a RootTree or SRVFTree, got {type(t).__name__}; "
                "build trees with rootshape_jax.batch(roots)."
            )
    a = to_srvf(a)
    b = to_srvf(b)
    check_compatible(a, b, "register: a and b")
    if a.q0.dtype != b.q0.dtype:
        raise ValueError(f"register: a and b have different dtypes ({a.q0.dtype} vs {b.q0.dtype}).")
    if a.batch_shape != b.batch_shape:
        raise ValueError(
            f"register: a has batch shape {a.batch_shape} but b has {b.batch_shape}; pass two single "
            "trees, or two batches of the same length (registered element by element)."
        )
    if len(a.batch_shape) > 1:
        raise ValueError(f"register: at most one batch axis is supported, got {a.batch_shape}.")
    single = a.batch_shape == ()
    if single:
        a, b = jax.tree.map(lambda x: x[None], (a, b))
    if a.capacity < 1:
        raise ValueError("register: trees need at least one lateral slot (K >= 1).")
    return a, b, single


def register(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    rotation: bool = True,
    max_iterations: int = 4,
    rtol: float = 1e-4,
    neighbourhood: int = 7,
    prune: bool = True,
    dp_batch_size: int = 32,
    assignment: str = "callback",
) -> Registration:
    """Register root `b` onto root `a` (DESIGN.md §4).

    `a` and `b` are single trees, or two batches of the same length registered element by
    element. They must share capacities (T, K, d); registering needs ``K >= n_a + n_b``, which
    `rootshape_jax.batch` guarantees by default.

    **Options**

    - `weights`: λ = (main, lateral, position), default the paper's (0.02, 1, 1).
    - `rotation`: optimise over SO(d) (alternating with correspondence); False keeps b's pose.
    - `max_iterations`, `rtol`: alternation stops after this many rounds or when the energy
      falls by less than `rtol` (relative).
    - `neighbourhood`: DP move set (coprime steps up to this size; fdasrsf uses 10).
    - `prune`: skip lateral DPs that provably cannot change the result (exact; False runs the
      DP of every real–real pair, for reference).
    - `dp_batch_size`: lateral DPs solved per slab (memory vs. padding trade-off).
    - `assignment`: "callback" (scipy through a host callback) or "jax" (pure-JAX, exact).
    """
    weights = Weights() if weights is None else weights
    dynamic, opts = _options(rotation, max_iterations, rtol, neighbourhood, prune, dp_batch_size, assignment)
    a, b, single = _as_pair_batch(a, b)
    active = jnp.ones(a.batch_shape, bool)
    reg = _register_batch(a, b, weights, active, dynamic, **opts)
    if single:
        reg = jax.tree.map(lambda x: x[0], reg)
    return reg


def distance(
    a: RootTree | SRVFTree, b: RootTree | SRVFTree, *, weights: Weights | None = None, **options
) -> Float[Array, "*B"]:
    """Elastic distance ``sqrt(min d²)`` between roots a and b (see `register` for options).

    Differentiable with respect to both roots' coordinates (and the weights): the registration
    is held fixed under `stop_gradient` (envelope theorem).
    """
    return register(a, b, weights=weights, **options).distance
