"""The registration engine: one entry point, `register_pairs`, for a batch of pairs of trees.

Registering b onto a follows the Duncan et al. formulation the paper uses (docs/design.md §4). With
the rotation fixed the problem splits exactly: one DP warp for the main roots, one DP warp per
real–real lateral pair giving the K×K cost matrix (the lateral DP energy weighted by the
lateral terms, plus the DP-free pair costs of the other terms, e.g. ``λp (sa_i − sb_j)²``),
real–null ``λs||q||²``, null–null 0, then one exact linear assignment. The rotation is then
refitted (weighted Kabsch over all matched branches) and the two steps alternate until the
energy stops falling. The parts, each a top-level function:

- `prepare`: per-pair quantities that no rotation changes (lengths, cones, fixed costs);
- `lower_bounds`: a DP-free lower bound of every lateral pair's cost (why pruning is exact);
- `run_dp_slabs`: the DPs of a list of branch pairs, in fixed-size slabs;
- `lazy_assignment`: the assignment solved with bounds, running only the DPs it picks;
- `evaluate`: energy, correspondence and warps at one rotation;
- `refit_rotation`: the rotation's update for a correspondence;
- `search`: the alternation;
- `apply_registration`: b moved into a's slot order (differentiable).

`register`, `distance`, `pairwise_distances`, `cross_distances`, the Karcher mean, PCA
projection and the Dask blocks all call `register_pairs`.

Trees of depth D > 2 (docs/design.md §11): a lateral pair's cost also holds the exact
assignment cost of the two laterals' children (`child_assignment`, the same procedure one
level down), bounded until computed by `child_lower_bounds` and, for pairs the assignment
keeps picking, `child_assignment_bounds`; `child_registrations` gives the
matched children's permutations and warps, and every level enters the rotation's refit.
"""

from __future__ import annotations

import functools
import types
from collections.abc import Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._assignment import HungarianState, assignment_cost, hungarian, solve
from ._curves import l2_norm_squared, safe_norm, safe_normalise, safe_sqrt, tiny, trapezoid_weights
from ._devices import split_over_devices
from ._errors import as_count, is_real_scalar
from ._metric import (
    MetricTerms,
    Weights,
    child_weights,
    lateral_weight,
    level_weight,
    null_costs,
    pair_costs,
    pair_lower_bounds,
    preshape_terms,
    system_weights,
)
from ._rotation import axis_angle_rotation, kabsch, rotation_maximising
from ._tree import SRVFLevel, SRVFTree
from ._warp import dp_warp_if, warp_srvf

# --------------------------------------------------------------------------------------------
# Options and result


class RegistrationOptions(eqx.Module):
    """How registration searches; one value serves every function that registers.

    - `rotation`: optimise over SO(d) (alternating with correspondence); False keeps b's pose.
    - `max_iterations`, `rtol`: the alternation stops after this many rounds or when the
      energy falls by less than `rtol` (relative).
    - `neighbourhood`: DP move set (coprime steps up to this size; fdasrsf uses 10).
    - `prune`: skip lateral DPs that provably cannot change the result (exact; False runs the
      DP of every real–real pair, for reference).
    - `dp_batch_size`: lateral DPs solved per slab (memory vs. padding trade-off).
    - `assignment`: "jax" (default: pure JAX, each solve of a lazy assignment warm-started
      from the last; no host callback, so JAX's persistent compilation cache can keep the
      engine's programs) or "callback" (scipy on the host: 3-4 % faster on the CPlantBox pea
      matrix and mean, but a program with a callback is compiled again in every process).
      Both are exact.

    `rotation`, `max_iterations` and `rtol` are stored as arrays (traced: changing them does not
    recompile); the others shape the compiled program and are static.
    """

    rotation: Bool[Array, ""]
    max_iterations: Int[Array, ""]
    rtol: Float[Array, ""]
    neighbourhood: int = eqx.field(static=True)
    prune: bool = eqx.field(static=True)
    dp_batch_size: int = eqx.field(static=True)
    assignment: str = eqx.field(static=True)

    def __init__(
        self,
        *,
        rotation: bool = True,
        max_iterations: int = 4,
        rtol: float = 1e-4,
        neighbourhood: int = 7,
        prune: bool = True,
        dp_batch_size: int = 32,
        assignment: str = "jax",
    ):
        max_iterations = as_count(max_iterations, "max_iterations")
        neighbourhood = as_count(neighbourhood, "neighbourhood")
        dp_batch_size = as_count(dp_batch_size, "dp_batch_size")
        if not isinstance(rotation, (bool, np.bool_)):
            raise TypeError(f"rotation must be True or False, got {rotation!r}.")
        if assignment not in ("callback", "jax"):
            raise ValueError(f"assignment must be 'callback' or 'jax', got {assignment!r}.")
        if not (is_real_scalar(rtol) and rtol >= 0):
            raise ValueError(f"rtol must be a non-negative number, got {rtol!r}.")
        # numpy, not jnp: arrays (traced under jit) that do not start JAX at import time.
        self.rotation = np.asarray(bool(rotation))
        self.max_iterations = np.asarray(max_iterations, np.int32)
        self.rtol = np.asarray(float(rtol))
        self.neighbourhood = neighbourhood
        self.prune = bool(prune)
        self.dp_batch_size = dp_batch_size
        self.assignment = assignment

    def without_rotation(self) -> "RegistrationOptions":
        """The same options with b's pose kept (rotation search off)."""
        return eqx.tree_at(lambda o: o.rotation, self, jnp.zeros_like(self.rotation, dtype=bool))

    def device_safe(self) -> "RegistrationOptions":
        """With several devices the assignment must run in JAX: a host callback inside a
        multi-device program whose loops run different trip counts per device deadlocks
        XLA:CPU's collectives."""
        if len(jax.devices()) > 1 and self.assignment == "callback":
            return _with_static(self, assignment="jax")
        return self


OPTION_NAMES = ("rotation", "max_iterations", "rtol", "neighbourhood", "prune", "dp_batch_size", "assignment")


def _with_static(o: RegistrationOptions, **static) -> RegistrationOptions:
    # Not through __init__: inside jit the array fields are tracers, which it would not accept.
    new = object.__new__(RegistrationOptions)
    for f in OPTION_NAMES:
        object.__setattr__(new, f, static.get(f, getattr(o, f)))
    return new


#: The Karcher mean's registration settings: more alternation rounds and a tighter tolerance than
#: `register`'s defaults (the mean compares energies across steps, so each must be converged),
#: and larger DP slabs (a step registers every sample at once).
MEAN_REGISTRATION = RegistrationOptions(max_iterations=5, rtol=1e-6, dp_batch_size=256)


def registration_options(
    options: RegistrationOptions | dict | None = None, *, base: RegistrationOptions | None = None, **shorthand
) -> RegistrationOptions:
    """A `RegistrationOptions` from an options value, a dict of its fields, or keyword shorthand
    (the public functions' keyword options), on top of `base` (default `register`'s)."""
    if isinstance(options, RegistrationOptions):
        if shorthand:
            raise ValueError(
                f"give registration options either as `registration=` or as keywords, not both ({sorted(shorthand)})."
            )
        return options
    if options is not None and not isinstance(options, Mapping):
        raise TypeError(
            f"registration must be a rootshape_jax.RegistrationOptions or a dict of its fields, got {options!r}."
        )
    given = dict(options or {})
    unknown = (set(given) | set(shorthand)) - set(OPTION_NAMES)
    if unknown:
        raise ValueError(
            f"registration options {sorted(unknown)} are unknown; use some of {list(OPTION_NAMES)} "
            "(the fields of rootshape_jax.RegistrationOptions)."
        )
    base = RegistrationOptions() if base is None else base
    fields = {f: _concrete(getattr(base, f)) for f in OPTION_NAMES}
    fields.update(given)
    fields.update(shorthand)
    return RegistrationOptions(**fields)


def _concrete(x):
    return x.item() if isinstance(x, (jax.Array, np.ndarray)) else x


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
    - `terms`: the weighted terms of the minimised squared distance (`MetricTerms`).
    - `n_iterations`: rotation ↔ correspondence alternations performed.
    - `n_lateral_dp`: lateral DP warps actually run; `n_lateral_skipped`: real–real lateral
      pairs, summed over rounds, whose DP the exact lower bound made unnecessary.
    - `child_permutations`, `child_warps` (depth D > 2, docs/design.md §11): one entry per
      deeper level ℓ = 2 … D−1, shaped ``[K1, …, Kℓ]`` and ``[K1, …, Kℓ, T]``: under slot
      ``(k1, …)`` of `registered`, child slot kℓ holds child ``child_permutations[ℓ−2][k1, …, kℓ]``
      of the branch placed in the parent slot, warped by the matching warp. ``()`` at depth 2.
    - `n_deeper_dp`: ``[D − 2]`` DP warps run per deeper level (``[0]`` entries at depth 2).
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
    child_permutations: tuple = ()
    child_warps: tuple = ()
    n_deeper_dp: Int[Array, "*B L"] | None = None

    @property
    def energy(self) -> Float[Array, "*B"]:
        """Minimised squared distance ``d²``."""
        return self.terms.total

    @property
    def distance(self) -> Float[Array, "*B"]:
        """Geodesic distance ``sqrt(d²)`` (0 with a zero gradient at coincident roots)."""
        return safe_sqrt(self.terms.total)


# --------------------------------------------------------------------------------------------
# Small geometric helpers


def rotate_srvf(q: Float[Array, "*S C"], O: Float[Array, "d d"]) -> Float[Array, "*S C"]:
    """Rotate SRVF values by O; a thickness channel (beyond d) is left alone (docs/design.md §11)."""
    d = O.shape[-1]
    if q.shape[-1] == d:
        return q @ O.T
    return jnp.concatenate([q[..., :d] @ O.T, q[..., d:]], axis=-1)


def rotate_batch(q: Array, O: Float[Array, "B d d"]) -> Array:
    """Rotate a batch of SRVFs (leading axis B, any middle axes) by per-item rotations."""
    d = O.shape[-1]
    if q.shape[-1] == d:
        return jnp.einsum("b...d,bed->b...e", q, O)
    return jnp.concatenate([jnp.einsum("b...d,bed->b...e", q[..., :d], O), q[..., d:]], axis=-1)


def warp_preserving_norm(q: Float[Array, "T C"], gamma: Float[Array, " T"]) -> Float[Array, "T C"]:
    """``(q∘γ)√γ'`` rescaled so that its L2 norm equals ``||q||``.

    In the continuum the reparameterisation action is an isometry; on the grid the interpolated
    warp changes the norm by O(h²). Restoring it keeps the branch length exact (so registered
    roots keep their lengths) and makes the pruning bound exact.
    """
    w = warp_srvf(q, gamma)
    n2 = l2_norm_squared(q)
    w2 = l2_norm_squared(w)
    ok = w2 > tiny(w.dtype)
    return w * safe_sqrt(jnp.where(ok, n2 / jnp.where(ok, w2, 1.0), 0.0))


def direction_cone(q: Float[Array, "*B T C"]) -> tuple[Array, Array]:
    """Axis (unit chord direction) and half-angle of a cone holding every direction of q.

    Branches with no direction (nulls) get half-angle π: no information.
    """
    n = safe_norm(q)
    u = safe_normalise(q)
    axis = safe_normalise(jnp.sum(q * n[..., None], axis=-2))
    cos = jnp.sum(u * axis[..., None, :], axis=-1)
    # The widest angle is the arccos of the smallest cosine (arccos decreases): one arccos per
    # cone, not per node.
    half = jnp.arccos(jnp.clip(jnp.min(jnp.where(n > 0, cos, 1.0), axis=-1), -1.0, 1.0))
    has_axis = safe_norm(axis) > 0
    return axis, jnp.where(has_axis, half, jnp.pi)


#: Blocks per branch for the refined bound (`refined_energy_bounds`); 8 measured best (fewer
#: DPs saved at 4, no more at 16 on CPlantBox pea).
N_BLOCKS = 8


def block_cones(q: Float[Array, "*B T C"], n_blocks: int) -> tuple[Array, Array]:
    """`direction_cone` of each of `n_blocks` consecutive node ranges of q.

    Block j holds nodes ``e_j … e_{j+1}`` inclusive (``e = round(linspace(0, T−1, n+1))``):
    neighbouring blocks share their end node, so any point interpolated between two adjacent
    nodes lies in one block's cone. Returns axes ``[*B, n, C]`` and half-angles ``[*B, n]``.
    """
    T = q.shape[-2]
    edges = np.round(np.linspace(0, T - 1, n_blocks + 1)).astype(int)
    member = np.zeros((n_blocks, T), bool)
    for j in range(n_blocks):
        member[j, edges[j] : edges[j + 1] + 1] = True
    n = safe_norm(q)
    u = safe_normalise(q)
    axis = safe_normalise(jnp.einsum("jt,...tc->...jc", member.astype(q.dtype), q * n[..., None]))
    cos = jnp.einsum("...tc,...jc->...jt", u, axis)
    half = jnp.arccos(jnp.clip(jnp.min(jnp.where(member & (n[..., None, :] > 0), cos, 1.0), axis=-1), -1.0, 1.0))
    has_axis = safe_norm(axis) > 0
    return axis, jnp.where(has_axis, half, jnp.pi)


def _cone_cap(cos_axes: Array, half: Array, dtype) -> Array:
    """An upper bound of ``max(cos(max(angle − half, 0)), 0)`` at ``angle = arccos(cos_axes)``: a cap of
    the cosine between directions of two convex cones whose axes are that far apart and whose
    half-angles sum to `half` (callers use 1 where a cone is not convex).

    Computed without arccos (the bounds' hot spot: ~3.5× faster than arccos and cos on CPU), as
    ``cos(angle − h) = c cos h + sin(angle) sin h`` for ``angle > h``, with ``c = cos_axes`` and
    ``sin(angle) = √((1 − c)(1 + c))``. Why it stays an upper bound: (1) `cos_axes` carries a
    few ε of rounding, which moves the angle it stands for by up to ~√(8ε) near ±1, so `half`
    is widened by ``4√ε`` (a wider cone only raises the cap); (2) every operation above rounds
    relatively by ε on terms of magnitude ≤ 1 (``(1 − c)(1 + c)`` has no cancellation), so the
    formula is within ~8ε of its exact value, and 16ε is added."""
    eps = float(jnp.finfo(dtype).eps)
    h = half + 4 * eps**0.5
    cos_h, sin_h = jnp.cos(h), jnp.sin(h)
    c = jnp.clip(cos_axes, -1.0, 1.0)
    sin_angle = jnp.sqrt((1 - c) * (1 + c))
    # angle ≤ h (or a cone as wide as the sphere): no separation, the cap is 1.
    inside = (c >= cos_h) | (h >= jnp.pi)
    return jnp.clip(jnp.where(inside, 1.0, c * cos_h + sin_angle * sin_h + 16 * eps), 0.0, 1.0)


def _identity_grid(T: int, dtype) -> Array:
    return jnp.linspace(0.0, 1.0, T, dtype=dtype)


# --------------------------------------------------------------------------------------------
# The search, in parts


class Prepared(eqx.Module):
    """Per-pair quantities of a batch of B pairs that no rotation changes."""

    a: SRVFTree
    b: SRVFTree
    weights: Weights
    lam_main: Array
    lam_lateral: Array
    La: Array  # [B, K] lateral lengths ||q||² of a (0 for nulls)
    Lb: Array
    fixed: Array  # [B, K, K] DP-free part of each real–real pair's cost (exact)
    others: Array  # [B, K, K] cost of pairs that are not both real (null costs)
    both: Array  # [B, K, K] both slots real
    cone_a: tuple
    cone_b: tuple
    dir_a: Array  # [B, K, T, C] unit direction of each node of a (0 where q = 0)
    mass_a: Array  # [B, K, T] trapezoid weight times |q|² of each node of a
    blocks_b: tuple  # block cones of b (`block_cones`): axes [B, K, N_BLOCKS, C], half-angles
    zero_length: Array  # [B, K, K] real–real pairs with a zero branch (`zero_length_pairs`)
    ties_a: Array  # [B, K] `tie_classes` of a's slots
    ties_b: Array
    # Depth D > 2 only (None otherwise): direction cones of the children of every lateral,
    # and the λ-weighted norms below every lateral (`descendant_norms`).
    child_cone_a: tuple | None = None  # axes [B, K, K2, C], half-angles [B, K, K2]
    child_cone_b: tuple | None = None
    sub_a: Array | None = None  # [B, K]
    sub_b: Array | None = None


def descendant_norms(levels: tuple, weights: Weights, first: int) -> Array | None:
    """λ-weighted squared norms of every branch's descendants, summed per parent slot of
    ``levels[0]`` (shape ``levels[0].mask.shape[:-1]``; ``levels[k]`` is level ``first + k``,
    weighted by its own λs): what leaving the parent unmatched costs below it. None when
    there are no levels."""
    acc = None
    for k, lv in reversed(list(enumerate(levels))):
        own = lateral_weight(weights, first + k, lv.q.dtype) * l2_norm_squared(lv.q) * lv.mask
        acc = own if acc is None else own + jnp.sum(acc, axis=-1)
    return None if acc is None else jnp.sum(acc, axis=-1)


def children_of(t: SRVFTree, bi: Array, i: Array) -> SRVFTree:
    """The children of branch ``(bi[k], i[k])`` of a batch of trees, with their own
    descendants, as a batch of trees without a main root (its slot holds zeros)."""
    lv = t.deeper[0]
    q = lv.q[bi, i]
    q0 = jnp.zeros(q.shape[:1] + q.shape[2:], q.dtype)
    thick = {}
    if t.has_thickness:  # the radius channel rides along (docs/design.md §11)
        base = jnp.concatenate([jnp.zeros_like(lv.base_radius[bi, i][:, :1]), lv.base_radius[bi, i]], axis=1)
        thick = dict(base_radius=base, thickness_scale=t.thickness_scale[bi])
    return SRVFTree(
        q0=q0,
        q=q,
        s=lv.s[bi, i],
        mask=lv.mask[bi, i],
        origin=jnp.zeros(q.shape[:1] + (t.dim,), q.dtype),
        **thick,
        deeper=tuple(
            SRVFLevel(
                q=x.q[bi, i],
                s=x.s[bi, i],
                mask=x.mask[bi, i],
                base_radius=None if x.base_radius is None else x.base_radius[bi, i],
            )
            for x in t.deeper[1:]
        ),
    )


def prepare(a: SRVFTree, b: SRVFTree, weights: Weights) -> Prepared:
    a, b, weights = lax.stop_gradient((a, b, weights))
    weights = system_weights(weights, a)  # a plant's axes weigh as main roots (§11)
    dtype = a.q0.dtype
    lam_m = level_weight(weights, "main", dtype)
    lam_s = level_weight(weights, "lateral", dtype)
    La = l2_norm_squared(a.q) * a.mask
    Lb = l2_norm_squared(b.q) * b.mask
    both = a.mask[:, :, None] & b.mask[:, None, :]
    others = null_costs(weights, a, b, La, Lb)
    below = (None,) * 4
    if a.deeper:
        # A real lateral left unmatched costs its whole subtree (docs/design.md §11).
        sub_a, sub_b = descendant_norms(a.deeper, weights, 2), descendant_norms(b.deeper, weights, 2)
        others = others + jnp.where(
            a.mask[:, :, None], sub_a[:, :, None], jnp.where(b.mask[:, None, :], sub_b[:, None, :], 0.0)
        )
        below = (direction_cone(a.deeper[0].q), direction_cone(b.deeper[0].q), sub_a, sub_b)
    fixed = pair_costs(weights, a, b).astype(dtype)
    T = a.q.shape[-2]
    mass_a = jnp.sum(a.q**2, axis=-1) * trapezoid_weights(T, dtype)
    return Prepared(
        a,
        b,
        weights,
        lam_m,
        lam_s,
        La,
        Lb,
        fixed,
        others,
        both,
        direction_cone(a.q),
        direction_cone(b.q),
        safe_normalise(a.q),
        mass_a,
        block_cones(b.q, min(N_BLOCKS, T - 1)),
        zero_length_pairs(both, La, Lb),
        tie_classes(a),
        tie_classes(b),
        *below,
    )


def lower_bounds(p: Prepared, O: Float[Array, "B d d"]) -> Float[Array, "B K K"]:
    """A lower bound of every lateral pair's branch energy ``||qa − w||²`` at rotations O,
    without any DP (the cost bounds are `bound_costs` of it).

    Why pruning with it is exact: ``||qa − w||² = La + Lb − 2<qa, w>`` for the warped,
    norm-preserved w (`warp_preserving_norm`). Every value of w is a positive multiple of an
    interpolation of values of qb, so its direction lies in the convex cone (half-angle < 90°)
    holding b's directions; with qa's cone, the angle between the two cones caps the cosine:
    ``<qa, w> ≤ max(cos φ, 0) √(La Lb)``, where ``φ = angle(axes) − half_a − half_b``. With
    φ ≤ 0 this is plain Cauchy–Schwarz. Each metric term turns this bound of the branch energy
    into its share of the pair's cost (`MetricTerm.pair_lower_bound`: λ times it for the
    lateral DP terms, the exact DP-free cost for the others), and null costs are exact. So
    every entry is at most the true cost, and an assignment that is optimal with bounds in
    place of unknown costs, and picks only known ones, is optimal for the true costs
    (`lazy_assignment`). `refined_energy_bounds` is a tighter bound, which the assignment
    uses for every real pair.
    """
    (ca, half_a), (cb, half_b) = p.cone_a, p.cone_b
    dtype = p.La.dtype
    if ca.shape[-1] == O.shape[-1]:
        cos_axes = jnp.einsum("bie,bjd,bed->bij", ca, cb, O)
    else:
        cos_axes = jnp.einsum("bie,bje->bij", ca, rotate_batch(cb, O))
    # The angle between the cones is at least the angle of the axes minus both half-angles.
    cos_cap = _cone_cap(cos_axes, half_a[:, :, None] + half_b[:, None, :], dtype)
    convex = (half_a[:, :, None] < jnp.pi / 2) & (half_b[:, None, :] < jnp.pi / 2)
    cos_cap = jnp.where(convex, cos_cap, 1.0)
    sqrt_LaLb = jnp.sqrt(p.La)[:, :, None] * jnp.sqrt(p.Lb)[:, None, :]
    return jnp.maximum(p.La[:, :, None] + p.Lb[:, None, :] - 2 * cos_cap * sqrt_LaLb, 0.0)


def _child_sides(p: Prepared):
    """Per side, what the children's bounds read: (block cones, squared norms, attachments,
    mask, the cost of leaving a child unmatched: its own norm and its whole subtree's), each
    with the layout [B, K, K2, ...]."""
    lam = lateral_weight(p.weights, 2, p.La.dtype)

    def side(tree, cone):
        children = tree.deeper[0]
        L = l2_norm_squared(children.q) * children.mask
        sub = descendant_norms(tree.deeper[1:], p.weights, 3)
        own = lam * L + (0.0 if sub is None else sub)
        return cone, L, children.s, children.mask, own

    return side(p.a, p.child_cone_a), side(p.b, p.child_cone_b)


def child_lower_bounds(p: Prepared, O: Float[Array, "B d d"], sides) -> Float[Array, "B K K"]:
    """Depth D > 2: a lower bound of the exact assignment cost of the children of every
    lateral pair (i, j), without any DP (`sides` from `_child_sides`).

    Why it is a bound: each child pair's cost is bounded below as a lateral pair's is
    (`lower_bounds`, the cone bound of its branch energy, plus its exact DP-free terms; the
    cost of its own children, ≥ 0, is bounded by 0), and a child left unmatched costs its
    exact subtree norm. Every assignment picks one entry per row (and per column) of that
    matrix, so its cost is at least the sum of the row minima, and of the column minima.
    Where one of the two laterals has no children, the children's cost is known exactly: the
    other's children unmatched, ``sub_a + sub_b`` (`lazy_assignment`'s ``alone``). Only the
    rows of laterals of a with children are bounded (a root has many null and childless slots).
    """
    weights = child_weights(p.weights)
    B, K = p.La.shape
    side_a, side_b = sides
    has_a = jnp.any(p.a.deeper[0].mask, axis=-1)
    has_b = jnp.any(p.b.deeper[0].mask, axis=-1)

    def step(lanes, out):
        def one(lane):
            bi, i = jnp.divmod(lane, K)
            a = jax.tree.map(lambda x: x[bi, i][None], side_a)
            b = jax.tree.map(lambda x: x[bi], side_b)
            M = _child_bound_table(weights, a, b, O[bi])[0]  # [K, K2, K2]: lateral i against every j
            return jnp.maximum(jnp.sum(jnp.min(M, axis=2), axis=1), jnp.sum(jnp.min(M, axis=1), axis=1))

        return out.at[lanes].set(jax.vmap(one)(jnp.clip(lanes, 0, B * K - 1)), mode="drop")

    rows = run_in_slabs(has_a.reshape(-1), step, jnp.zeros((B * K, K), p.La.dtype), slab=CHILD_SLAB)
    alone = p.sub_a[:, :, None] + p.sub_b[:, None, :]
    return jnp.where(has_a[:, :, None] & has_b[:, None, :], rows.reshape(B, K, K), alone)


def _child_bound_table(weights, side_a, side_b, O, energy_floor=None):
    """Lower bounds of every child pair's cost (an unmatched child: its exact subtree cost) for
    the lateral pairs of one batch entry (no batch axis); layout [i, j, k, l]: lateral i of a,
    lateral j of b, their children k and l. `energy_floor` (same layout): other lower bounds
    of the child pairs' branch energies, used where larger than the cone bound."""
    ((ca, ha), La, sa, ma, own_a), ((cb, hb), Lb, sb, mb, own_b) = side_a, side_b
    dtype = La.dtype
    if ca.shape[-1] == O.shape[-1]:
        cos_axes = jnp.einsum("ike,jld,ed->ijkl", ca, cb, O)
    else:
        cos_axes = jnp.einsum("ike,jle->ijkl", ca, rotate_srvf(cb, O))
    half_a, half_b = ha[:, None, :, None], hb[None, :, None, :]
    cap = _cone_cap(cos_axes, half_a + half_b, dtype)
    cap = jnp.where((half_a < jnp.pi / 2) & (half_b < jnp.pi / 2), cap, 1.0)
    La, Lb = La[:, None, :, None], Lb[None, :, None, :]
    energy = jnp.maximum(La + Lb - 2 * cap * jnp.sqrt(La * Lb), 0.0)
    if energy_floor is not None:
        energy = jnp.maximum(energy, energy_floor)
    # The terms read only the attachments of the two sides; broadcast to [i, j, k, l].
    real_real = pair_lower_bounds(
        weights, types.SimpleNamespace(s=sa[:, None, :]), types.SimpleNamespace(s=sb[None, :, :]), energy
    )
    ma, mb = ma[:, None, :, None], mb[None, :, None, :]
    return jnp.where(
        ma & mb, real_real, jnp.where(ma, own_a[:, None, :, None], jnp.where(mb, own_b[None, :, None, :], 0.0))
    )


def child_assignment_bounds(
    p: Prepared, O: Float[Array, "B d d"], sides, lanes: Int[Array, " L"], *, method: str
) -> Float[Array, " L"]:
    """Depth D > 2: a tighter lower bound of the children's exact assignment cost of the lateral
    pairs `lanes` (flat indices into ``[B, K, K]``): the optimal assignment (`method`, as the
    registration's) of the children's bound matrix (`_child_bound_table`), without any DP.

    Why it is a bound: every entry of that matrix is at most the cost it stands for, so for any
    assignment the sum of its entries is at most the true cost of that assignment; the
    minimum over assignments is then at most the true optimum. It is at least the row-minima
    and column-minima sums of `child_lower_bounds`, so it only tightens them. Its real–real
    children pairs' branch energies are bounded by `refined_energy_bounds` too
    (`refined_child_energy_bounds`), the larger of the two bounds being kept.
    """
    K = p.La.shape[1]
    weights = child_weights(p.weights)
    side_a, side_b = sides
    floor = refined_child_energy_bounds(p, O, lanes)

    def one(lane, floor):
        bi, rem = jnp.divmod(lane, K * K)
        i, j = jnp.divmod(rem, K)
        a = jax.tree.map(lambda x: x[bi, i][None], side_a)
        b = jax.tree.map(lambda x: x[bi, j][None], side_b)
        M = _child_bound_table(weights, a, b, O[bi], floor[None, None])[0, 0]
        return assignment_cost(M, solve(M, method=method))

    return jax.vmap(one)(lanes, floor)


def refined_child_energy_bounds(p: Prepared, O: Float[Array, "B d d"], lanes: Int[Array, " L"]) -> Array:
    """`refined_energy_bounds` of the branch energy of every real–real pair of children under
    the lateral pairs `lanes` (flat indices into ``[B, K, K]``) at rotations O, shaped
    ``[L, K2, K2]`` (0 where a child slot is null). Only the real pairs are computed, in slabs
    of `REFINE_SLAB` lanes: a children set holds far fewer real pairs than slots."""
    K = p.La.shape[1]
    bi, rem = jnp.divmod(lanes, K * K)
    i, j = jnp.divmod(rem, K)
    lv_a, lv_b = p.a.deeper[0], p.b.deeper[0]
    qa, qb = lv_a.q[bi, i], lv_b.q[bi, j]  # [L, K2, T, C]
    ma, mb = lv_a.mask[bi, i], lv_b.mask[bi, j]
    L, K2, T, _ = qa.shape
    dtype = qa.dtype
    axes_b, half_b = block_cones(qb, min(N_BLOCKS, T - 1))
    axes_b = rotate_batch(axes_b, O[bi])
    dir_a = safe_normalise(qa)
    mass_a = jnp.sum(qa**2, axis=-1) * trapezoid_weights(T, dtype)
    La, Lb = l2_norm_squared(qa) * ma, l2_norm_squared(qb) * mb
    n_pairs = L * K2 * K2
    need = (ma[:, :, None] & mb[:, None, :]).reshape(-1)

    def step(flat, bound):
        s, rem = jnp.divmod(jnp.clip(flat, 0, n_pairs - 1), K2 * K2)
        k, m = jnp.divmod(rem, K2)
        new = _refined_bound(dir_a[s, k], mass_a[s, k], axes_b[s, m], half_b[s, m], La[s, k], Lb[s, m])
        return bound.at[flat].set(new, mode="drop")

    bound = run_in_slabs(need, step, jnp.zeros((n_pairs,), dtype), slab=REFINE_SLAB)
    return bound.reshape(L, K2, K2)


def bound_costs(p: Prepared, energy_bound: Float[Array, "B K K"]) -> Float[Array, "B K K"]:
    """Lower bounds of the pair costs from lower bounds of the branch energies (exact null
    costs where a slot is null)."""
    return jnp.where(p.both, pair_lower_bounds(p.weights, p.a, p.b, energy_bound), p.others)


def refined_energy_bounds(p: Prepared, axes_b: Array, lanes: Array) -> Array:
    """A tighter lower bound of the branch energy of the lateral pairs `lanes` (flat indices
    into ``[B, K, K]``), given b's block-cone axes rotated into place (`axes_b`).

    Why it is a bound: in ``<qa, w> = Σ_t h_t <qa_t, w_t>`` (trapezoid weights h, the grid
    nodes t of a), each w_t is a positive multiple of an interpolation between two adjacent
    nodes of b, so it lies in the cone of one block j(t) of b (`block_cones`), and j(t) can be
    taken nondecreasing in t because the warp is. So ``<qa_t, w_t> ≤ |qa_t| |w_t| c(t, j(t))``
    with ``c`` the cap of the angle between qa_t's direction and block j's cone, and by
    Cauchy–Schwarz ``<qa, w> ≤ √(Σ_t h_t |qa_t|² c²) · √(Σ_t h_t |w_t|²) ≤ √(M Lb)``, where
    ``M`` is the largest ``Σ_t h_t |qa_t|² c(t, j(t))²`` over nondecreasing maps j — a small
    DP over (t, j) — and ``Σ_t h_t |w_t|² = Lb`` since w keeps qb's norm. Hence
    ``||qa − w||² ≥ La + Lb − 2√(M Lb)``, with a margin of a few ε for rounding. Unlike
    `lower_bounds` it sees where along the branches the directions differ.
    """
    B, K = p.La.shape
    bi, rem = jnp.divmod(lanes, K * K)
    i, j = jnp.divmod(rem, K)
    return _refined_bound(
        p.dir_a[bi, i], p.mass_a[bi, i], axes_b[bi, j], p.blocks_b[1][bi, j], p.La[bi, i], p.Lb[bi, j]
    )


def _refined_bound(u, mass, axes, half, La, Lb):
    """`refined_energy_bounds` of S branch pairs: a's unit directions u [S, T, C] and node
    masses [S, T], b's rotated block-cone axes [S, n, C] and half-angles [S, n], and both
    squared norms [S]."""
    dtype = La.dtype
    cap = _cone_cap(jnp.einsum("stc,snc->stn", u, axes), half[:, None, :], dtype)
    cap = jnp.where(half[:, None, :] < jnp.pi / 2, cap, 1.0)
    gain = mass[:, :, None] * cap**2  # [S, T, n]

    def node(best, g):
        return lax.cummax(best, axis=1) + g, None

    best, _ = lax.scan(node, jnp.zeros_like(gain[:, 0]), jnp.moveaxis(gain, 1, 0))
    M = jnp.max(best, axis=1)
    margin = 16 * float(jnp.finfo(dtype).eps) * (La + Lb)
    return jnp.maximum(La + Lb - 2 * jnp.sqrt(Lb * M) - margin, 0.0)


def _slab_size(n_items: int, largest: int) -> int:
    # Small slabs: the DP is as efficient at 32 lanes as at 256, and less padding is solved.
    return min(largest, max(8, -(-n_items // 16)))


def run_in_slabs(need, step, carry, *, slab: int):
    """``step(lanes, carry)`` over the items flagged in `need`, `slab` lanes at a time.

    One call site, compiled once, whatever the number of items needed (a loop with a
    data-dependent trip count): skipped items cost nothing. Padding lanes hold index
    ``len(need)``; `step` clips them for reading and drops them when scattering.
    """
    n_items = need.shape[0]
    n_pad = -(-n_items // slab) * slab
    (lanes_all,) = jnp.nonzero(need, size=n_pad, fill_value=n_items)

    def body(k, carry):
        return step(lax.dynamic_slice(lanes_all, (k * slab,), (slab,)), carry)

    return lax.fori_loop(0, (jnp.sum(need) + slab - 1) // slab, body, carry)


def run_dp_slabs(need, pair_of, store, carry, *, neighbourhood: int, dp_batch_size: int):
    """Solve the DPs of the items flagged in `need` in slabs (`run_in_slabs`).

    `pair_of(lanes)` gives the (q1, q2) of each item; ``store(lanes, energies, warps, carry)``
    puts each item's energy ``||q1 − w||²`` and warp into the carry (padding lanes hold index
    ``len(need)``: drop them).
    """
    n_items = need.shape[0]
    # The engine's SRVFs are finite by construction (`to_srvf` checks its input): no check.
    dp = jax.vmap(functools.partial(dp_warp_if, neighbourhood=neighbourhood, check=False))

    def step(lanes, carry):
        q1, q2 = pair_of(jnp.clip(lanes, 0, n_items - 1))
        # Padding lanes are skipped by the DP kernel (it packs the active lanes into blocks).
        g, _ = dp(q1, q2, lanes < n_items)
        w = jax.vmap(warp_preserving_norm)(q2, g)
        return store(lanes, l2_norm_squared(q1 - w), g, carry)

    return run_in_slabs(need, step, carry, slab=_slab_size(n_items, dp_batch_size))


def zero_length_pairs(both: Array, La: Array, Lb: Array) -> Bool[Array, "B K K"]:
    """Real–real lateral pairs (`both`) where either branch has a zero SRVF (lengths `La`, `Lb`;
    a Karcher mean's unreached slot): the branch energy is the other's whole norm ``La + Lb``
    for every warp (a warp keeps the norm), so no DP is run and the warp is the identity. A DP
    would pick among equal warps by discretisation and rounding, and the registered branch
    with it."""
    return both & ((La == 0)[:, :, None] | (Lb == 0)[:, None, :])


def dps_run(p: Prepared, computed: Array) -> Int[Array, " B"]:
    """The DPs run per pair of trees: the computed lateral pairs but the zero-length ones."""
    ran = computed.reshape(p.both.shape) & ~p.zero_length
    return jnp.sum(ran.reshape(ran.shape[0], -1), axis=1, dtype=jnp.int32)


def tie_classes(t: SRVFTree) -> Int[Array, "B K"]:
    """For every lateral slot of a batch of trees, the first slot that is interchangeable with
    it for the metric (itself if none is).

    Two slots are interchangeable when both are *empty* (every branch of the slot's subtree
    has a zero SRVF) and they hold the same values: null slots all alike, real zero-length
    slots (a Karcher mean's unreached slots) with the same mask, attachment and radius, level by
    level. Their rows of every cost matrix are then equal, so an optimal assignment may hand
    them their partners in any order (`canonical_matching`). Slots with any length are kept
    apart: two equal real laterals are not worth comparing whole curves for.
    """
    B, K = t.mask.shape

    def flat(x):
        return x.reshape(B, K, -1)

    real = t.mask.astype(t.s.dtype)
    empty = jnp.all(flat(t.q * real[..., None, None]) == 0, axis=-1)
    sig = [real[..., None], (t.s * real)[..., None]]
    if t.base_radius is not None:
        sig.append((t.base_radius[..., 1:] * real)[..., None])  # [..., 0] is the main root's
    for lv in t.deeper:
        r = lv.mask.astype(lv.s.dtype)
        empty = empty & jnp.all(flat(lv.q) == 0, axis=-1)
        sig += [flat(r), flat(lv.s * r)]
        if lv.base_radius is not None:
            sig.append(flat(lv.base_radius * r))
    sig = jnp.concatenate(sig, axis=-1)
    same = jnp.all(sig[:, :, None, :] == sig[:, None, :, :], axis=-1) & empty[:, :, None] & empty[:, None, :]
    same = same | jnp.eye(K, dtype=bool)
    return jnp.argmax(same, axis=-1).astype(jnp.int32)


def canonical_matching(
    perm: Int[Array, " K"], class_a: Int[Array, " K"], class_b: Int[Array, " K"], real_b: Bool[Array, " K"]
):
    """An optimal assignment with its free choices made one fixed way.

    Slots in one `tie_classes` class have equal cost rows (a's) or columns (b's), so an
    optimal assignment may permute partners within a class at exactly the same cost, and the
    solver's pick then rests on rounding noise in the other entries: enough for a Karcher
    mean, which averages slot by slot, to take another path from inputs differing by 1e-16.
    Here each class of a's slots, in slot order, takes its partners ordered real laterals of b
    first, then by b's class; then each class of b's slots goes to the rows holding it in slot
    order. The result depends only on which classes are matched with which.

    Returns (the assignment, `rows_from`, `cols_from`): the new pair ``(i, perm'[i])`` stands
    for the old ``(rows_from[i], cols_from[perm'[i]])``, an identical pair, whose stored
    results (warps, children's assignment) it takes.
    """
    K = perm.shape[-1]
    slot = jnp.arange(K, dtype=perm.dtype)
    # a's classes: rows in slot order take their class's partners in key order.
    held = class_b[perm] + K * (~real_b[perm]).astype(perm.dtype)
    by_slot = jnp.lexsort((slot, class_a)).astype(perm.dtype)
    by_key = jnp.lexsort((slot, held, class_a)).astype(perm.dtype)
    rows_from = jnp.zeros_like(perm).at[by_slot].set(by_key)
    perm = perm[rows_from]
    # b's classes: the rows holding a class take its members in slot order.
    by_row = jnp.lexsort((slot, class_b[perm])).astype(perm.dtype)
    by_col = jnp.lexsort((slot, class_b)).astype(perm.dtype)
    cols_from = jnp.zeros_like(perm).at[by_col].set(perm[by_row])
    new = jnp.zeros_like(perm).at[by_row].set(by_col)
    return new, rows_from, cols_from


class _LazyState(NamedTuple):
    """The loop state of `lazy_assignment` (flat item arrays over the B·K·K lateral pairs;
    Em, Gm and pending over the B main-root pairs)."""

    E: Array  # lateral DP energies
    G: Array  # their warps
    Em: Array  # main-root DP energies
    Gm: Array  # their warps
    A: Array  # children's exact assignment costs (depth D > 2)
    counts: Array  # DPs the children's assignments ran, per deeper level
    computed: Array  # the pair's own DP is done
    nested_done: Array  # its children's cost is exact
    child_refined: Array  # its children's tighter bound is in `child_bound`
    child_bound: Array
    pending: Array  # main-root DPs still to run (the first pass)
    child_perm: Array  # the children's optimal assignment of each pair with nested_done (D > 2)
    perm: Array
    chosen: Array  # pairs the last assignment picked that are not exact yet
    cost: Array | None  # the cost matrices last solved (pure-JAX solver; else None)
    duals: HungarianState | None  # their solver state, the next solve's warm start


#: Children sets per slab of the nested assignments (depth D > 2). A slab costs about the same
#: whatever number of its lanes are active (its bounds, assignments and bookkeeping run at full
#: width), and a lazy-assignment step usually needs only one to a few sets: one set in a slab of
#: 32 took 36-50 ms, in a slab of 8 15-23 ms (20-day pea pair, T = 100).
CHILD_SLAB = 8
#: Lateral pairs per slab of the refined bounds (`refined_energy_bounds`), computed for every
#: real–real pair before the first assignment: wide slabs are efficient there (8-lane slabs,
#: right when a loop step refined only the 1-60 pairs it picked, were slower up front).
REFINE_SLAB = 64


def lazy_assignment(
    p: Prepared,
    qb: Array,
    axes_b: Array,
    energy_bound: Array,
    rows: Array,
    options,
    O: Array | None = None,
    child_bound: Array | None = None,
    sides=None,
    main: tuple | None = None,
):
    """Exact optimal lateral correspondence at one rotation, running as few DPs as possible.

    The assignment is solved with lower bounds in place of the lateral costs not computed yet:
    every real–real pair starts at its refined bound (`refined_energy_bounds`, the larger of
    it and `lower_bounds`, all computed before the first assignment: a few µs a pair, where
    refining only the pairs an assignment picks took a loop step of its own for each), and a
    pair the assignment picks gets its DP. The assignment is solved again until it picks only
    computed pairs: it is then optimal for the true costs too, since every uncomputed cost is
    at least its bound. With ``prune=False`` every real–real DP is run up front (the
    reference behaviour). Returns (cost matrix, permutation, pairs computed, their warps
    ``[B, K, K, T]``: kept, so the matched pairs' DPs are not solved twice, DPs run per deeper
    level ``[B, D − 2]``, the main roots' energies and warps (see `main`), and the children's
    optimal assignment of every pair whose nested cost was computed ``[B, K, K, K2]``: kept
    for the same reason; K2 = 0 at depth 2).

    Depth D > 2 (docs/design.md §11): a real–real pair's cost also holds the exact assignment
    cost of the two laterals' children at the rotations O (`child_assignment`, the same
    procedure one level down). Until a pair is computed its bound holds `child_bound`
    (`child_lower_bounds`; `sides`, from `_child_sides`, is what the children's bounds read). A
    pair is made exact in tiers, each only when the assignment picks it again: its own DP (its
    children still by their bound), then the children's tighter bound
    (`child_assignment_bounds`: an assignment of bounds, no DP), then its children's exact
    assignment. So a nested cost is computed only for pairs that still win
    with their own DP and their children's best bound known, and never where a bound already
    loses.

    `main`: the (q1, q2) of the B main-root pairs at this rotation, or None. Their DPs (for the
    `rows`) are run at the same call site as the laterals', in the loop's first pass, and
    their energies and warps are returned last (else zeros and identity warps): each DP call
    site is a kernel of its own to compile (~1 s), so the engine has as few as it can.
    """
    B, K = p.La.shape
    dtype = p.La.dtype
    n_items = B * K * K
    n_main = 0 if main is None else B
    n_below = len(p.a.deeper)
    # With the pure-JAX solver each solve after the first restarts from the last one's matching
    # and potentials, inserting again only the rows whose costs changed (`hungarian`): the
    # picked entries just made exact. The scipy callback solves every matrix from scratch.
    warm_start = options.assignment == "jax"

    def assign(C, last=None):
        """(perm, solver state) of the B cost matrices C; `last` = (the matrices last solved,
        their state) to warm-start from."""
        if not warm_start:
            return jax.vmap(lambda c: solve(c, method=options.assignment))(C), None
        C = lax.stop_gradient(C)
        if last is None:
            return jax.vmap(hungarian)(C)
        last_C, duals = last
        changed = jnp.any(C != last_C, axis=-1)
        return jax.vmap(lambda c, d, ch: hungarian(c, (d, ch)))(C, duals, changed)

    slabs = functools.partial(run_dp_slabs, neighbourhood=options.neighbourhood, dp_batch_size=options.dp_batch_size)

    def branch_pair(lanes):
        # Items 0 … n_items − 1 are the lateral pairs (b, i, j), then the main-root pairs.
        bi, rem = jnp.divmod(jnp.minimum(lanes, n_items - 1), K * K)
        i, j = jnp.divmod(rem, K)
        q1, q2 = p.a.q[bi, i], qb[bi, j]
        if n_main:
            is_main = (lanes >= n_items)[:, None, None]
            m = jnp.clip(lanes - n_items, 0, B - 1)
            q1, q2 = jnp.where(is_main, main[0][m], q1), jnp.where(is_main, main[1][m], q2)
        return q1, q2

    def refine(need, bound):
        def step(lanes, bound):
            safe = jnp.clip(lanes, 0, n_items - 1)
            new = refined_energy_bounds(p, axes_b, safe)
            return bound.at[lanes].set(jnp.maximum(bound[safe], new), mode="drop")

        return run_in_slabs(need, step, bound, slab=REFINE_SLAB)

    # Every real–real pair's refined bound and the cost bound it gives, before the first
    # assignment (loop-invariant).
    bound = energy_bound.reshape(-1)
    if options.prune:
        bound = refine((p.both & rows[:, None, None]).reshape(-1), bound)
    bound_cost = bound_costs(p, bound.reshape(B, K, K))

    if n_below:
        # Pairs where one lateral has no children need no nested assignment: every child of
        # the other is unmatched, at its subtree's exact cost (0 when neither has children).
        has_a = jnp.any(p.a.deeper[0].mask, axis=-1)
        has_b = jnp.any(p.b.deeper[0].mask, axis=-1)
        nested = (has_a[:, :, None] & has_b[:, None, :]).reshape(-1)
        alone = (p.sub_a[:, :, None] + p.sub_b[:, None, :]).reshape(-1)

    def children(need, A, counts, child_perm):
        """The exact assignment cost of the children of the pairs `need` (both have children)."""

        def step(lanes, carry):
            A, counts, child_perm = carry
            safe = jnp.clip(lanes, 0, n_items - 1)
            bi, rem = jnp.divmod(safe, K * K)
            i, j = jnp.divmod(rem, K)
            total, n_dp, perm_c = child_assignment(
                children_of(p.a, bi, i),
                children_of(p.b, bi, j),
                child_weights(p.weights),
                O[bi],
                lanes < n_items,
                options,
            )
            return (
                A.at[lanes].set(total, mode="drop"),
                counts.at[lanes].set(n_dp, mode="drop"),
                child_perm.at[lanes].set(perm_c.astype(child_perm.dtype), mode="drop"),
            )

        return run_in_slabs(need & nested, step, (A, counts, child_perm), slab=CHILD_SLAB)

    def store(lanes, e, g, carry):
        E, G, Em, Gm = carry
        # Lanes past the laterals (main roots, padding) are dropped here, and below from Em.
        E, G = E.at[lanes].set(e, mode="drop"), G.at[lanes].set(g, mode="drop")
        if n_main:
            m = jnp.where(lanes >= n_items, lanes - n_items, n_main)
            Em, Gm = Em.at[m].set(e, mode="drop"), Gm.at[m].set(g, mode="drop")
        return E, G, Em, Gm

    def exact(need, E, G, A, nested_done, main_need, Em, Gm):
        """The DPs of the pairs `need` and of the main roots `main_need`. A pair with no
        children's assignment to do (no deeper levels, or one side childless) is then exact:
        its children's cost is known."""
        E, G, Em, Gm = slabs(jnp.concatenate([need, main_need]), branch_pair, store, (E, G, Em, Gm))
        direct = need & ~nested if n_below else need
        if n_below:
            A = jnp.where(direct, alone, A)
        return E, G, A, nested_done | direct, Em, Gm

    def costs(E, A, computed, nested_done, child_bound):
        known = p.lam_lateral * E.reshape(B, K, K) + p.fixed
        unknown = bound_cost
        if n_below:
            # Bounds; the pair's own DP with its children's bound (row/column minima, then the
            # assignment of bounds once picked); all exact.
            child = jnp.where(p.both, child_bound, 0.0)
            unknown = unknown + child
            known = jnp.where(nested_done.reshape(B, K, K), known + A.reshape(B, K, K), known + child)
        return jnp.where(computed.reshape(B, K, K), known, unknown)

    def picks(perm, done):
        chosen = jax.nn.one_hot(perm, K, dtype=bool)
        return (chosen & p.both & ~done.reshape(B, K, K) & rows[:, None, None]).reshape(-1)

    T = qb.shape[-2]
    E = jnp.zeros((n_items,), dtype)
    G = jnp.zeros((n_items, T), dtype)
    Em = jnp.zeros((n_main,), dtype)
    Gm = jnp.broadcast_to(_identity_grid(T, dtype), (n_main, T))
    A = jnp.zeros((n_items,), dtype)
    counts = jnp.zeros((n_items, n_below), jnp.int32)
    # The children's assignments are kept (they are the registration of a matched pair's
    # children, which `child_registrations` would otherwise solve again).
    K2 = p.a.deeper[0].mask.shape[-1] if n_below else 0
    child_perm = jnp.zeros((n_items, K2), jnp.int8 if K2 <= 127 else jnp.int32)
    # Main-root DPs still to run (in the loop's first pass).
    pending = rows if n_main else jnp.zeros((0,), bool)
    # Pairs with a zero-length branch are exact without a DP (`zero_length_pairs`).
    trivial = (p.zero_length & rows[:, None, None]).reshape(-1)
    E = jnp.where(trivial, (p.La[:, :, None] + p.Lb[:, None, :]).reshape(-1), E)
    G = jnp.where(trivial[:, None], _identity_grid(T, dtype), G)
    computed = trivial
    nested_done = trivial & ~nested if n_below else trivial
    if n_below:
        A = jnp.where(nested_done, alone, A)
    if not options.prune:
        # Every real–real DP up front. (With pruning none is: not traced at all, as each DP
        # call site is its own compiled kernel, and a no-op call would still be compiled.)
        need = (p.both & rows[:, None, None]).reshape(-1) & ~trivial
        E, G, A, nested_done, Em, Gm = exact(need, E, G, A, nested_done, pending, Em, Gm)
        computed = computed | need
        pending = jnp.zeros_like(pending)
        if n_below:
            A, counts, child_perm = children(computed & ~nested_done, A, counts, child_perm)
            nested_done = computed

    def refine_children(need, child_bound):
        def step(lanes, cb):
            safe = jnp.clip(lanes, 0, n_items - 1)
            new = child_assignment_bounds(p, O, sides, safe, method=options.assignment)
            return cb.at[lanes].set(jnp.maximum(cb[safe], new), mode="drop")

        return run_in_slabs(need & nested, step, child_bound, slab=CHILD_SLAB)

    def body(st: _LazyState) -> _LazyState:
        E, G, Em, Gm, A, counts, child_perm = st.E, st.G, st.Em, st.Gm, st.A, st.counts, st.child_perm
        computed, nested_done, chosen = st.computed, st.nested_done, st.chosen
        child_refined, child_bound = st.child_refined, st.child_bound
        # A pair picked for the first time gets its DP, then (depth D > 2, when picked with
        # its DP known) its children's tighter bound, then their exact assignment.
        run_dp = chosen & ~computed
        if n_below:
            tighten = chosen & computed & ~child_refined
            child_bound = refine_children(tighten, child_bound.reshape(-1)).reshape(B, K, K)
            nest = chosen & computed & child_refined & ~nested_done
            A, counts, child_perm = children(nest, A, counts, child_perm)
            nested_done = nested_done | nest
            child_refined = child_refined | (chosen & computed)
        E, G, A, nested_done, Em, Gm = exact(run_dp, E, G, A, nested_done, st.pending, Em, Gm)
        computed = computed | run_dp
        C = costs(E, A, computed, nested_done, child_bound)
        perm, duals = assign(C, (st.cost, st.duals))
        return _LazyState(
            E=E,
            G=G,
            Em=Em,
            Gm=Gm,
            A=A,
            counts=counts,
            computed=computed,
            nested_done=nested_done,
            child_refined=child_refined,
            child_bound=child_bound,
            pending=jnp.zeros_like(st.pending),
            child_perm=child_perm,
            perm=perm,
            chosen=picks(perm, nested_done),
            cost=C if warm_start else None,
            duals=duals,
        )

    if child_bound is None:
        child_bound = jnp.zeros((B, K, K), dtype)
    C = costs(E, A, computed, nested_done, child_bound)
    perm, duals = assign(C)
    st = _LazyState(
        E=E,
        G=G,
        Em=Em,
        Gm=Gm,
        A=A,
        counts=counts,
        computed=computed,
        nested_done=nested_done,
        child_refined=computed,
        child_bound=child_bound,
        pending=pending,
        child_perm=child_perm,
        perm=perm,
        chosen=picks(perm, nested_done),
        cost=C if warm_start else None,
        duals=duals,
    )
    st = lax.while_loop(lambda st: jnp.any(st.chosen) | jnp.any(st.pending), body, st)
    below = jnp.sum(st.counts.reshape(B, K * K, n_below), axis=1, dtype=jnp.int32)
    # The free choices among interchangeable slots made one fixed way; each pair's stored
    # results move with it (the pairs it is swapped with are identical).
    perm, rows_from, cols_from = jax.vmap(canonical_matching)(st.perm, p.ties_a, p.ties_b, p.b.mask)

    def relabel(x):
        x = x.reshape((B, K, K) + x.shape[1:])
        x = jnp.take_along_axis(x, rows_from.reshape((B, K, 1) + (1,) * (x.ndim - 3)), axis=1)
        return jnp.take_along_axis(x, cols_from.reshape((B, 1, K) + (1,) * (x.ndim - 3)), axis=2)

    return (
        relabel(costs(st.E, st.A, st.computed, st.nested_done, st.child_bound).reshape(-1)),
        perm,
        relabel(st.computed),
        relabel(st.G),
        below,
        st.Em,
        st.Gm,
        relabel(st.child_perm.astype(jnp.int32)).reshape(B, K, K, K2),
    )


def assign_at(p: Prepared, O: Array, rows: Array, options, *, with_main: bool = False):
    """`lazy_assignment` of the prepared pairs at rotations O (b's branches and bounds turned);
    `with_main`: also the main roots' DPs."""
    qb = rotate_batch(p.b.q, O)
    axes_b = rotate_batch(p.blocks_b[0], O)
    sides = _child_sides(p) if p.a.deeper else None
    child_bound = child_lower_bounds(p, O, sides) if p.a.deeper else None
    main = (p.a.q0, rotate_batch(p.b.q0, O)) if with_main else None
    return lazy_assignment(p, qb, axes_b, lower_bounds(p, O), rows, options, O, child_bound, sides, main)


def _assign_children(a: SRVFTree, b: SRVFTree, weights: Weights, O: Array, active: Array, options):
    """The lazy assignment of a batch of children sets (b's rotated by O)."""
    p = prepare(a, b, weights)
    return p, assign_at(p, O, active, options)


def child_assignment(a: SRVFTree, b: SRVFTree, weights: Weights, O: Array, active: Array, options):
    """Exact assignment cost of a batch of children sets (`children_of`) at rotations O, the
    DPs it ran per level ``[S, levels below a's top level + 1]``, and the optimal assignment
    ``[S, K2]``."""
    p, (C, perm, computed, _, below, _, _, _) = _assign_children(a, b, weights, O, active, options)
    total = jnp.sum(jnp.take_along_axis(C, perm[:, :, None], axis=2)[:, :, 0], axis=1)
    n_dp = dps_run(p, computed)
    return jnp.where(active, total, 0.0), jnp.concatenate([n_dp[:, None], below], axis=1), perm


def child_registrations(
    p: Prepared, O: Array, perm: Array, matched: Array, options, child_perm: Array | None = None
) -> tuple[list, Array]:
    """Depth D > 2: the children's registrations under every matched real–real lateral pair
    (lateral i of a with ``perm[i]`` of b): one ``(permutation, warps)`` per deeper level,
    shaped ``[B, K, K2, …]`` and ``[B, K, K2, …, T]`` (identity where not matched), and the
    DPs run per deeper level ``[B, D − 2]``.

    `child_perm` ``[B, K, K, K2]``: the children's optimal assignment of every lateral pair
    whose nested cost the lateral assignment computed (`lazy_assignment` keeps them; every
    matched pair is one). Then only the DPs of the matched children pairs are run, for their
    warps; the levels further down, and every level without `child_perm`, are solved again
    (a lazy assignment per children set). No warps of unmatched pairs are kept in memory."""
    B, K = perm.shape
    n_items = B * K
    T = p.a.q.shape[-2]
    dtype = p.La.dtype

    # One row per lateral slot of a (the slab's lanes).
    regs = [
        (pm.reshape((n_items,) + pm.shape[2:]), gm.reshape((n_items,) + gm.shape[2:]))
        for pm, gm in _initial_children(p)
    ]
    counts = jnp.zeros((n_items, len(p.a.deeper)), jnp.int32)

    def step(lanes, carry):
        regs, counts = carry
        safe = jnp.clip(lanes, 0, n_items - 1)
        bi, i = jnp.divmod(safe, K)
        a_c, b_c = children_of(p.a, bi, i), children_of(p.b, bi, perm[bi, i])
        active = lanes < n_items
        if child_perm is None:
            pc, (_, perm_c, computed, G, _, _, _, _) = _assign_children(
                a_c, b_c, child_weights(p.weights), O[bi], active, options
            )
            both = matched_slots(pc, perm_c, active)
            gam = jnp.take_along_axis(G, perm_c[:, :, None, None], axis=2)[:, :, 0]
            n_dp = dps_run(pc, computed)
        else:
            pc = prepare(a_c, b_c, child_weights(p.weights))
            perm_c = child_perm[bi, i, perm[bi, i]]
            both = matched_slots(pc, perm_c, active)
            gam, ran = _matched_warps(pc, O[bi], perm_c, both, options)
            n_dp = jnp.sum(ran, axis=1, dtype=jnp.int32)
        S, K2 = perm_c.shape
        n_dp = n_dp[:, None]
        gam = jnp.where(both[..., None], gam, _identity_grid(T, dtype))
        new = [(perm_c, gam)]
        if a_c.deeper:
            below, below_dp = child_registrations(pc, O[bi], perm_c, both, options)
            new += [(pm.reshape((S, K2) + pm.shape[2:]), gm.reshape((S, K2) + gm.shape[2:])) for pm, gm in below]
            n_dp = jnp.concatenate([n_dp, below_dp], axis=1)
        regs = [
            (pm.at[lanes].set(npm, mode="drop"), gm.at[lanes].set(ngm, mode="drop"))
            for (pm, gm), (npm, ngm) in zip(regs, new)
        ]
        return regs, counts.at[lanes].set(n_dp, mode="drop")

    # Only pairs whose laterals both have children have anything to register below.
    has_a = jnp.any(p.a.deeper[0].mask, axis=-1)
    has_b = jnp.take_along_axis(jnp.any(p.b.deeper[0].mask, axis=-1), perm, axis=1)
    need = (matched & has_a & has_b).reshape(-1)
    regs, counts = run_in_slabs(need, step, (regs, counts), slab=CHILD_SLAB)
    regs = [(pm.reshape((B, K) + pm.shape[1:]), gm.reshape((B, K) + gm.shape[1:])) for pm, gm in regs]
    return regs, jnp.sum(counts.reshape(B, K, -1), axis=1, dtype=jnp.int32)


def matched_slots(p: Prepared, perm: Array, rows: Array) -> Array:
    """``[B, K]``: slot i of a is real and matched with a real slot ``perm[i]`` of b (pairs
    `rows` only)."""
    return jnp.any(jax.nn.one_hot(perm, perm.shape[-1], dtype=bool) & p.both, axis=2) & rows[:, None]


def _matched_warps(p: Prepared, O: Array, perm: Array, matched: Array, options) -> Array:
    """The warps ``[B, K, T]`` of the pairs (i, perm[i]) flagged in `matched` (b's branches
    turned by O, as the assignment saw them; identity for `zero_length_pairs`), other slots
    zeros, and where a DP ran ``[B, K]``."""
    B, K, T, _ = p.a.q.shape
    qb = rotate_batch(p.b.q, O)
    trivial = matched & jnp.take_along_axis(p.zero_length, perm[:, :, None], axis=2)[:, :, 0]

    def pair_of(lanes):
        bi, i = jnp.divmod(lanes, K)
        return p.a.q[bi, i], qb[bi, perm[bi, i]]

    def store(lanes, e, g, G):
        return G.at[lanes].set(g, mode="drop")

    G = jnp.where(trivial.reshape(-1, 1), _identity_grid(T, p.La.dtype), 0.0)
    run = matched & ~trivial
    G = run_dp_slabs(
        run.reshape(-1),
        pair_of,
        store,
        G,
        neighbourhood=options.neighbourhood,
        dp_batch_size=options.dp_batch_size,
    )
    return G.reshape(B, K, T), run


def evaluate(p: Prepared, O: Array, rows: Array, options: RegistrationOptions):
    """Energy, permutation and warps of every pair at rotations O (rows: pairs to do).

    The lateral warps of the matching are those the assignment's DPs found (`lazy_assignment`
    keeps them), and so are the main roots' (run at the same DP call site). Depth D > 2: also the children's
    registrations under every matched lateral pair (`child_registrations`) and the DPs run
    per deeper level.
    """
    a, b = p.a, p.b
    B, K, T, _ = b.q.shape
    dtype = a.q0.dtype
    C, perm, computed, G, below_dp, Em, g0, child_perm = assign_at(p, O, rows, options, with_main=True)
    lap = jnp.sum(jnp.take_along_axis(C, perm[:, :, None], axis=2)[:, :, 0], axis=1)

    # Matched real-real slots take their DP's warp; every other slot the identity.
    identity = _identity_grid(T, dtype)
    matched = matched_slots(p, perm, rows)
    gam = jnp.take_along_axis(G, perm[:, :, None, None], axis=2)[:, :, 0]
    gam = jnp.where(matched[..., None], gam, identity)
    n_dp = dps_run(p, computed)
    children = []
    if a.deeper:
        children, again = child_registrations(p, O, perm, matched, options, child_perm)
        below_dp = below_dp + again
    return p.lam_main * Em + lap, perm, g0, gam, n_dp, children, below_dp


def reorder_level(x: Array, perms: list) -> Array:
    """A deeper level's array ``[B, K1, …, Kℓ, …]`` of b put into a's slot order, given the
    permutations of every level down to ℓ (``perms[k]`` shaped ``[B, K1, …, K(k+1)]``)."""
    for k, pm in enumerate(perms, start=1):
        idx = pm.reshape(pm.shape + (1,) * (x.ndim - pm.ndim))
        x = jnp.take_along_axis(x, idx, axis=k)
    return x


def _warp_all(q: Array, gam: Array) -> Array:
    """`warp_preserving_norm` over any leading axes of q ``[..., T, C]`` and gam ``[..., T]``."""
    flat = jax.vmap(warp_preserving_norm)(q.reshape((-1,) + q.shape[-2:]), gam.reshape((-1, gam.shape[-1])))
    return flat.reshape(q.shape)


def refit_rotation(p: Prepared, perm: Array, g0: Array, gam: Array, children=()) -> Array:
    """Weighted Kabsch over every matched branch (spatial channels, every level), with the
    metric's weights."""
    a, b = p.a, p.b
    B = b.q.shape[0]
    d = a.dim
    dtype = a.q0.dtype
    q0w = jax.vmap(warp_preserving_norm)(b.q0, g0)
    qbp = jnp.take_along_axis(b.q, perm[:, :, None, None], axis=1)
    mbp = jnp.take_along_axis(b.mask, perm, axis=1)
    qw = jax.vmap(jax.vmap(warp_preserving_norm))(qbp, gam)
    A = jnp.concatenate([a.q0[:, None], a.q], axis=1)[..., :d]
    Bm = jnp.concatenate([q0w[:, None], qw], axis=1)[..., :d]
    w = jnp.concatenate([jnp.broadcast_to(p.lam_main, (B, 1)), p.lam_lateral * (a.mask & mbp).astype(dtype)], axis=1)
    perms, matched = [perm], a.mask & mbp
    for ell, (la, lb, (pm, gm)) in enumerate(zip(a.deeper, b.deeper, children), start=2):
        perms.append(pm)
        qb = _warp_all(reorder_level(lb.q, perms), gm)
        matched = matched[..., None] & la.mask & reorder_level(lb.mask, perms)
        A = jnp.concatenate([A, la.q.reshape(B, -1, *la.q.shape[-2:])[..., :d]], axis=1)
        Bm = jnp.concatenate([Bm, qb.reshape(B, -1, *qb.shape[-2:])[..., :d]], axis=1)
        lam = lateral_weight(p.weights, ell, dtype)
        w = jnp.concatenate([w, lam * matched.reshape(B, -1).astype(dtype)], axis=1)
    return jax.vmap(kabsch)(A, Bm, w)


class SearchResult(eqx.Module):
    rotation: Array
    permutation: Array
    main_warp: Array
    lateral_warps: Array
    n_iterations: Array
    n_lateral_dp: Array
    n_lateral_skipped: Array
    children: tuple = ()  # depth D > 2: (permutation, warps) per deeper level
    n_deeper_dp: Array | None = None  # [B, D − 2]


def _initial_children(p: Prepared) -> list:
    B, _, T, _ = p.a.q.shape
    dtype = p.La.dtype
    return [
        (
            jnp.broadcast_to(jnp.arange(lv.mask.shape[-1]), lv.mask.shape),
            jnp.broadcast_to(_identity_grid(T, dtype), lv.mask.shape + (T,)),
        )
        for lv in p.a.deeper
    ]


def starting_rotation(a: SRVFTree, b: SRVFTree) -> Float[Array, "B d d"]:
    """The rotation the alternation starts from: the one aligning the main roots, or for
    plants' systems (zero-length virtual main roots) the one aligning the longest axes
    (``||q||²``, first on ties), which is the taproot's start when each plant has one axis."""
    d = a.dim
    if not a.virtual_main:
        return jax.vmap(kabsch)(a.q0[..., :d], b.q0[..., :d])

    def longest(t):
        L = jnp.where(t.mask, l2_norm_squared(t.q), -1.0)
        return jnp.take_along_axis(t.q, jnp.argmax(L, axis=-1)[:, None, None, None], axis=1)[:, 0, :, :d]

    return jax.vmap(kabsch)(longest(a), longest(b))


def longest_axis_view(t: SRVFTree) -> SRVFTree:
    """A plant's system (batched) as the taproot system of its longest axis (largest
    ``||q||²``, the first on ties): that axis as the main root, its laterals as the laterals.
    With one axis per plant it is the taproot tree itself, so the spins of `spin_start` see
    what a taproot's see (docs/design.md §11: one axis per plant gives the taproot analysis)."""
    B = t.q.shape[0]
    i = jnp.argmax(jnp.where(t.mask, l2_norm_squared(t.q), -1.0), axis=-1)
    view = children_of(t, jnp.arange(B), i)
    return eqx.tree_at(lambda v: v.q0, view, t.q[jnp.arange(B), i])


def _about_axis(axis: Float[Array, "B 3"], angle) -> Float[Array, "B 3 3"]:
    """Rotations by `angle` about each `axis` (normalised here); a zero axis gives the identity."""
    return jax.vmap(axis_angle_rotation, in_axes=(0, None))(safe_normalise(axis), angle)


# The spins tried about the main root in 3D, and the warp-free alternation rounds each gets.
N_SPINS = 8
SPIN_ROUNDS = 2


def spin_start(
    p: Prepared, O_main: Float[Array, "B 3 3"], active: Bool[Array, " B"], options: RegistrationOptions
) -> Float[Array, "B 3 3"]:
    """The rotation a 3D search starts from: the main roots' alignment turned about a's main
    root by the best of `N_SPINS` spins, each first improved by `SPIN_ROUNDS` rounds of the
    alternation without warps.

    Why: aligning the main roots leaves the spin about them almost free when they are nearly
    straight (taproots; 2D tracings lying in a plane), and the alternation of warps,
    correspondence and rotation keeps the spin's basin. From the main-root start alone the
    squared distance of 24 random CPlantBox pea pairs was 29 % above the best of eight
    spin starts on average (plate tracings laid in 3D: 13 %, up to 69 %; BENCHMARKS.md).
    For a plant's system `search` passes the `longest_axis_view` of both trees.

    Each spin ``k`` starts at ``R(axis, 2πk/N_SPINS) O_main``, the axis ``∫ q|q| dt`` of a's
    main root over the spatial channels (its chord when there is no thickness channel). A
    round solves the correspondence of the first-order laterals for identity warps (the
    exact assignment of the pair costs with ``||qa − O qb||²`` as branch energy, no DP;
    deeper levels are left to the search, on both sides: an unmatched lateral costs its own
    norm) and refits the rotation to it (weighted
    Kabsch, main root and matched laterals; a spin with nothing to align keeps its rotation);
    the start is the refitted rotation of the spin whose matching costs least there. The
    spins are defined by a's main root and b's alignment to it, so the start turns with a
    and b: the distance stays invariant to rotations of either root. Spin 0 is the
    main-root start itself, so a pair it suits keeps it (up to its warp-free refinement)."""
    a, b = p.a, p.b
    d = a.dim
    dtype = a.q0.dtype
    T = a.q.shape[-2]
    tw = trapezoid_weights(T, dtype)
    # Inner products at any rotation O from the cross moments: <qa, O qb> = Σ O ∘ N.
    N = jnp.einsum("t,bitn,bjtm->bijnm", tw, a.q[..., :d], b.q[..., :d])
    N0 = jnp.einsum("t,btn,btm->bnm", tw, a.q0[..., :d], b.q0[..., :d])
    # Channels the rotation does not act on (thickness) add a constant.
    extra = jnp.einsum("t,bitc,bjtc->bij", tw, a.q[..., d:], b.q[..., d:])
    extra0 = jnp.einsum("t,btc,btc->b", tw, a.q0[..., d:], b.q0[..., d:])
    L0 = l2_norm_squared(a.q0) + l2_norm_squared(b.q0)
    lam_m, lam_s = p.lam_main, p.lam_lateral
    # Level 1 only, on both sides of the assignment: a real lateral left unmatched costs its own
    # norm here, not its subtree's (`p.others`), as a matched pair's cost leaves out its children.
    others = null_costs(p.weights, a, b, p.La, p.Lb)

    def pair(O, N, N0, extra, extra0, L0, La, Lb, fixed, others, both, act):
        def cost(O):
            inner = jnp.einsum("nm,ijnm->ij", O, N) + extra
            C = jnp.where(both, lam_s * (La[:, None] + Lb[None, :] - 2 * inner) + fixed, others)
            # An inactive pair, or one with non-finite data (its terms become NaN), assigns a
            # zero matrix: no work, and no NaN in the assignment's loops.
            C = jnp.where(act & jnp.all(jnp.isfinite(C)), C, 0.0)
            return C, lam_m * (L0 - 2 * (jnp.sum(O * N0) + extra0))

        def refit(O, _):
            C, _ = cost(O)
            perm = solve(C, method=options.assignment)
            matched = both[jnp.arange(perm.shape[0]), perm]
            K = lam_m * N0.T + lam_s * jnp.einsum(
                "i,inm->mn", matched.astype(dtype), N[jnp.arange(perm.shape[0]), perm]
            )
            # Nothing to align (no matched pair, no main root): keep this spin's rotation.
            return jnp.where(jnp.any(K != 0), rotation_maximising(K), O), perm

        O, perms = lax.scan(refit, O, None, length=SPIN_ROUNDS)
        C, e_main = cost(O)
        # The last matching at the refitted rotation: what this start's alternation would begin below.
        return O, e_main + jnp.sum(C[jnp.arange(C.shape[0]), perms[-1]])

    x0 = a.q0[..., :d]
    axis = jnp.einsum("t,bti->bi", tw, x0 * safe_norm(x0)[..., None])  # a's main-root chord
    starts = jnp.stack([_about_axis(axis, 2 * np.pi * k / N_SPINS) @ O_main for k in range(N_SPINS)])  # [S, B, 3, 3]
    per_pair = jax.vmap(pair)
    O, energy = jax.vmap(per_pair, in_axes=(0,) + (None,) * 11)(
        starts, N, N0, extra, extra0, L0, p.La, p.Lb, p.fixed, others, p.both, active
    )
    best = jnp.argmin(jnp.where(jnp.isnan(energy), jnp.inf, energy), axis=0)  # [B]; the first of equal ones
    O = jnp.take_along_axis(O, best[None, :, None, None], axis=0)[0]
    return jnp.where(jnp.all(jnp.isfinite(O), axis=(-2, -1), keepdims=True), O, O_main)


def search(a: SRVFTree, b: SRVFTree, weights: Weights, active: Array, options: RegistrationOptions) -> SearchResult:
    """Optimal (rotation, permutation, warps) for a batch of B pairs; no gradients.

    Alternates `evaluate` (correspondence and warps at fixed rotation) and `refit_rotation`,
    starting from `starting_rotation`; a pair stops when its energy falls
    by less than `rtol` (relative) or stops falling. Inactive pairs do no work.
    """
    p = prepare(a, b, weights)
    B, K, T, _ = p.b.q.shape
    d = a.dim
    dtype = a.q0.dtype
    identity = _identity_grid(T, dtype)
    eye = jnp.broadcast_to(jnp.eye(d, dtype=dtype), (B, d, d))
    rotation = options.rotation
    start = starting_rotation(p.a, p.b)
    if d == 3 and (a.deeper or not a.virtual_main):
        # A plant's spins are those of its longest axis as a taproot (with its laterals); a
        # plant without deeper levels has nothing to turn its axes by. Pairs that do not search
        # the rotation skip the spins (an inactive pair's lanes do no work in the assignments'
        # loops either).
        spun = p if not a.virtual_main else prepare(longest_axis_view(p.a), longest_axis_view(p.b), weights)
        start = lax.cond(rotation & jnp.any(active), lambda: spin_start(spun, start, active, options), lambda: start)
    O_start = jnp.where(rotation, start, eye)
    n_rounds = jnp.where(rotation, options.max_iterations, 1)

    def cond(state):
        it, done = state[0], state[6]
        return (it < n_rounds) & jnp.any(~done)

    def body(state):
        it, O, E, perm, g0, gam, done, iters, n_dp, children, deeper_dp = state
        # Round 0 evaluates the starting rotation; later rounds refit it to the matching.
        O_new = lax.cond(it == 0, lambda: O_start, lambda: refit_rotation(p, perm, g0, gam, children))
        E_new, perm_new, g0_new, gam_new, n_dp_new, children_new, deeper_new = evaluate(p, O_new, ~done, options)
        better = (E_new < E) & ~done
        rel = jnp.where(jnp.isinf(E), jnp.inf, (E - E_new) / jnp.maximum(E, tiny(dtype)))

        def pick(new, old):
            return jnp.where(better.reshape((B,) + (1,) * (new.ndim - 1)), new, old)

        iters = iters + (~done).astype(jnp.int32)
        done = done | ~better | (rel < options.rtol)
        new = (O_new, E_new, perm_new, g0_new, gam_new)
        old = (O, E, perm, g0, gam)
        O, E, perm, g0, gam = (pick(n, o) for n, o in zip(new, old))
        children = jax.tree.map(pick, children_new, children)
        return it + 1, O, E, perm, g0, gam, done, iters, n_dp + n_dp_new, children, deeper_dp + deeper_new

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
        _initial_children(p),
        jnp.zeros((B, len(a.deeper)), jnp.int32),
    )
    _, O, _, perm, g0, gam, _, iters, n_dp, children, deeper_dp = lax.while_loop(cond, body, state)
    n_real = jnp.sum(p.both.reshape(B, -1), axis=1, dtype=jnp.int32)
    # Lateral DPs skipped: real-real pairs of every round that were never solved.
    n_skipped = jnp.maximum(n_real * iters - n_dp, 0)
    return SearchResult(O, perm, g0, gam, iters, n_dp, n_skipped, tuple(children), deeper_dp)


def apply_registration(a: SRVFTree, b: SRVFTree, O, perm, g0, gam, children=()) -> SRVFTree:
    """b registered into a's slot order (single pair); differentiable in a and b. Deeper
    levels (`children`: one (permutation, warps) per level) follow their parents' slots."""
    q0 = warp_preserving_norm(rotate_srvf(b.q0, O), g0)
    qb = rotate_srvf(b.q, O)[perm]
    mb = b.mask[perm]
    qw = jax.vmap(warp_preserving_norm)(qb, gam) * mb[:, None, None]
    s = jnp.where(mb, b.s[perm], a.s)
    base = None
    if b.base_radius is not None:
        base = jnp.concatenate([b.base_radius[:1], jnp.where(mb, b.base_radius[1:][perm], a.base_radius[1:])])
    deeper, perms = [], [perm[None]]
    for la, lb, (pm, gm) in zip(a.deeper, b.deeper, children):
        perms.append(pm[None])
        m = reorder_level(lb.mask[None], perms)[0]
        q = _warp_all(rotate_srvf(reorder_level(lb.q[None], perms)[0], O), gm) * m[..., None, None]
        s_b = reorder_level(lb.s[None], perms)[0]
        base_b = None
        if lb.base_radius is not None:  # a null takes its partner's starting radius, as at level 1
            base_b = jnp.where(m, reorder_level(lb.base_radius[None], perms)[0], la.base_radius)
        deeper.append(SRVFLevel(q=q, s=jnp.where(m, s_b, la.s), mask=m, base_radius=base_b))
    return SRVFTree(
        q0=q0,
        q=qw,
        s=s,
        mask=mb,
        origin=b.origin,
        base_radius=base,
        thickness_scale=b.thickness_scale,
        deeper=tuple(deeper),
        virtual_main=b.virtual_main,
    )


# --------------------------------------------------------------------------------------------
# Symmetric distances


def _axes_view(t: SRVFTree):
    """A plant's system (batched) seen as a taproot system, for `_order_key` only: the sum of
    its axes as the main root, every deeper level one up (the first two slot axes merged).
    With one axis per plant the key is the taproot's, so both register in the same direction."""
    B, K = t.mask.shape

    def up(x):
        return x.reshape((B, K * x.shape[2]) + x.shape[3:])

    return types.SimpleNamespace(
        q0=jnp.sum(t.q, axis=1),
        q=up(t.deeper[0].q),
        s=up(t.deeper[0].s),
        mask=up(t.deeper[0].mask),
        origin=t.origin,
        deeper=tuple(types.SimpleNamespace(q=up(lv.q)) for lv in t.deeper[1:]),
    )


def _order_key(t: SRVFTree) -> Float[Array, "B F"]:
    """A few numbers read off a tree's content (any fixed function works; only its values on
    the two trees of a pair are compared). The first ones do not change when a root is turned
    or moved (lateral count, main-root length, lateral lengths, attachment positions, deeper
    lengths), so a rotated or translated root keeps its place in the order; the others break
    the remaining ties."""
    if t.virtual_main and t.deeper:
        t = _axes_view(t)
    dtype = t.q0.dtype
    L = l2_norm_squared(t.q) * t.mask
    invariant = [
        jnp.sum(t.mask, axis=-1).astype(dtype),
        l2_norm_squared(t.q0),
        jnp.sum(L, axis=-1),
        jnp.sum(jnp.where(t.mask, t.s, 0.0), axis=-1),
    ]
    invariant += [jnp.sum(lv.q.reshape(lv.q.shape[:1] + (-1,)) ** 2, axis=-1) for lv in t.deeper]
    rest = [
        jnp.sum(t.q0, axis=(-2, -1)),
        jnp.sum(jnp.sum(t.q0, axis=-1) * jnp.linspace(0.0, 1.0, t.q0.shape[-2], dtype=dtype), axis=-1),
        jnp.sum(t.q, axis=(-3, -2, -1)),
        jnp.sum(t.origin, axis=-1),
    ]
    rest += [jnp.sum(lv.q.reshape(lv.q.shape[:1] + (-1,)), axis=-1) for lv in t.deeper]
    return jnp.stack(invariant + rest, axis=-1)


#: Revision of the distance a pair of trees gets, for stores of finished blocks: raised when
#: the SRVF discretisation or the registration's choices change what a pair computes, so a
#: store written before is refused instead of mixing two metrics. 2: SRVF cusps take the
#: outgoing direction; the pair order tolerates rounding (session 23).
METRIC_REVISION = 2

#: Relative difference below which two entries of a pair's order key count as equal (one value
#: for every dtype: float32 rounds the key's sums by ~1e-6 relative).
ORDER_KEY_RTOL = 1e-4


def canonical_pairs(a: SRVFTree, b: SRVFTree) -> tuple[SRVFTree, SRVFTree]:
    """Each pair in a fixed order that does not depend on the argument order: b first where its
    content key is lexicographically smaller than a's.

    The alternation finds a local optimum that can depend on which root is registered onto
    which (up to ~1 % of the distance on real roots). Registering every pair in a canonical
    order makes a distance exactly symmetric, at no extra cost. Key entries within
    `ORDER_KEY_RTOL` of each other (relative; far above float32's rounding of them) count as
    equal: scale-normalised main roots all have length 1, and a comparison decided by
    rounding would flip with a translation of the data, with float32 against float64, or with
    the order of a sum, moving the distance by that ~1 %. The tolerance is the same in every
    dtype, so float32 and float64 order pairs alike. Only when every entry is that close does
    the exact comparison decide.
    """
    ka, kb = _order_key(a), _order_key(b)
    size = jnp.maximum(jnp.maximum(jnp.abs(ka), jnp.abs(kb)), jnp.finfo(ka.dtype).tiny)
    clear = jnp.abs(ka - kb) > ORDER_KEY_RTOL * size
    diff = jnp.where(jnp.any(clear, axis=-1, keepdims=True), clear, ka != kb)
    first = jnp.argmax(diff, axis=-1)[:, None]
    swap = jnp.any(diff, axis=-1) & (
        jnp.take_along_axis(kb, first, axis=-1)[:, 0] < jnp.take_along_axis(ka, first, axis=-1)[:, 0]
    )

    def pick(x, y):
        return jnp.where(swap.reshape(swap.shape + (1,) * (x.ndim - 1)), x, y)

    return jax.tree.map(pick, b, a), jax.tree.map(pick, a, b)


def pair_distances_squared(
    a: SRVFTree, b: SRVFTree, weights: Weights, options: RegistrationOptions, active=None
) -> tuple[Array, Array, Array]:
    """Symmetric squared distances of a batch of pairs (canonical order, `canonical_pairs`):
    (energies, lateral DPs run, lateral DPs skipped, DPs run per deeper level ``[B, D − 2]``).
    Differentiable in a and b."""
    a, b = canonical_pairs(a, b)
    reg = register_pairs(a, b, weights, options, active)
    return reg.energy, reg.n_lateral_dp, reg.n_lateral_skipped, reg.n_deeper_dp


# --------------------------------------------------------------------------------------------
# The entry point


def _search_split(a, b, active, weights, options):
    return search(a, b, weights, active, options)


def register_pairs(
    a: SRVFTree,
    b: SRVFTree,
    weights: Weights,
    options: RegistrationOptions,
    active: Bool[Array, " B"] | None = None,
    *,
    split: bool = True,
) -> Registration:
    """Register b[k] onto a[k] for a batch of pairs (leading axis B): the one engine call.

    Inactive pairs (``active[k] = False``) do no DP work (their result is b as given). With
    ``split=True`` the pairs are spread over every XLA device. Trace-safe: call it inside
    `eqx.filter_jit` functions; `register_pairs_jit` is the compiled entry for eager callers.
    """
    if len(a.deeper) != len(b.deeper):
        raise ValueError(f"trees of depth {a.depth} and {b.depth} cannot be registered: batch them together.")
    if active is None:
        active = jnp.ones(a.q0.shape[:1], bool)
    if split:
        res = split_over_devices(_search_split, (a, b, active), (weights, options.device_safe()))
    else:
        res = search(a, b, weights, active, options)
    registered = jax.vmap(apply_registration)(
        a, b, res.rotation, res.permutation, res.main_warp, res.lateral_warps, res.children
    )
    # The engine raises nothing at run time (no host callback, so its programs can be cached):
    # its inputs are checked where they enter as concrete arrays (`to_srvf`, `Weights`). Under
    # a caller's jit they are not, so a pair with a non-finite input or weight gets NaN terms
    # here, never the finite but arbitrary result the DP and assignment would give.
    finite = _finite_pairs(a, b, weights)
    terms = jax.tree.map(
        lambda t: jnp.where(finite.reshape(finite.shape + (1,) * (t.ndim - 1)), t, jnp.nan),
        preshape_terms(a, registered, weights),
    )
    return Registration(
        registered=registered,
        permutation=res.permutation,
        rotation=res.rotation,
        main_warp=res.main_warp,
        lateral_warps=res.lateral_warps,
        terms=terms,
        n_iterations=res.n_iterations,
        n_lateral_dp=res.n_lateral_dp,
        n_lateral_skipped=res.n_lateral_skipped,
        child_permutations=tuple(pm for pm, _ in res.children),
        child_warps=tuple(gm for _, gm in res.children),
        n_deeper_dp=res.n_deeper_dp,
    )


register_pairs_jit = eqx.filter_jit(register_pairs)


def _finite_pairs(a: SRVFTree, b: SRVFTree, weights: Weights) -> Bool[Array, " B"]:
    """Per pair: every array of a[k] and b[k], and every weight, is finite."""
    B = a.q0.shape[0]
    ok = jnp.ones((B,), bool)
    for leaf in jax.tree.leaves(eqx.filter((a, b), eqx.is_inexact_array)):
        ok = ok & jnp.all(jnp.isfinite(leaf.reshape(B, -1)), axis=1)
    for w in jax.tree.leaves(weights):  # `Weights` holds every λ as an array
        ok = ok & jnp.all(jnp.isfinite(w))
    return ok
