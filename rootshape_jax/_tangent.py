"""The tangent space of SRVF trees: free parameters, whitening, flatten, log and exp maps.

The pre-shape metric is a weighted L2 norm in SRVF-tree coordinates, so the space is flat:
the tangent vector of a registered sample x at μ is ``x − μ`` (log map) and the exponential
map is addition. Vectors are whitened by the metric, ``v = W^{1/2}(x − μ)``: each metric term
with a `tangent_block` scales its block by ``√λ`` (times the square roots of the trapezoid
weights on the L2 blocks q0 and q). Euclidean geometry of the flattened ``v`` is then the
metric's own, ``|v|² = d²(μ, x)``. A thickness channel lies inside q0 and q and is whitened
with them. Used by the Karcher mean's gradient solver, tangent PCA and trait regression.

Trees of depth D > 2 (docs/design.md §11) carry one `LevelParams` (branch SRVFs and
attachment fractions) per deeper level ℓ = 2 … D−1, whitened with that level's weights
(`term_weight`); flattened vectors list them after the depth-2 blocks.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._curves import l2_norm_squared, trapezoid_weights
from ._metric import TERMS, Weights, lateral_weight, level_weight
from ._tree import SRVFLevel, SRVFTree


class LevelParams(eqx.Module):
    """The free parts of one deeper level ℓ ≥ 2: branch SRVFs ``[*B, K1, …, Kℓ, T, C]`` and
    attachment fractions ``[*B, K1, …, Kℓ]`` (or their whitening scales)."""

    q: Float[Array, "*B *P K T C"]
    s: Float[Array, "*B *P K"]


class TreeParams(eqx.Module):
    """The free parts of an SRVF tree: main SRVF, lateral SRVFs, attachment fractions, and at
    depth D > 2 one `LevelParams` per deeper level (a batch adds leading axes). Also used for
    per-coordinate whitening scales."""

    q0: Float[Array, "*B T C"]
    q: Float[Array, "*B K T C"]
    s: Float[Array, "*B K"]
    deeper: tuple[LevelParams, ...] = ()


def term_weight(weights: Weights, name: str, level: int):
    """The weight λ of term `name` at branch level `level` (0 = main root, 1 = first-order
    laterals, ...): the lateral and position terms take that level's own weights
    (`Weights.at_level`, docs/design.md §11), the other terms their one weight."""
    if level >= 1 and name in ("lateral", "position"):
        return weights.at_level(level)[0 if name == "lateral" else 1]
    return weights[name]


def branch_weight(weights: Weights, level: int, dtype) -> Array:
    """Weight of the branch DPs at `level` (0 = main root, else laterals of that order): the
    weight of the rotation fit's terms there (`_metric.level_weight` at levels 0 and 1, that
    level's λs below)."""
    if level <= 1:
        return level_weight(weights, "main" if level == 0 else "lateral", dtype)
    return lateral_weight(weights, level, dtype)


def level_value(x: Array, level: int) -> Array:
    """A per-level limit at branch level `level` ≥ 1: `x` itself when a scalar (one value for
    every level), else ``x[level − 1]``."""
    x = jnp.asarray(x)
    return x if x.ndim == 0 else x[level - 1]


def level_min(min_length, level: int) -> Array:
    """The lower length limit at branch level `level`: per slot when `min_length` is a tuple
    (one array per level, `TangentPCA.slot_min_lengths`), else as `level_value`."""
    return min_length[level - 1] if isinstance(min_length, tuple) else level_value(min_length, level)


def params_of(tree: SRVFTree) -> TreeParams:
    return TreeParams(tree.q0, tree.q, tree.s, tuple(LevelParams(lv.q, lv.s) for lv in tree.deeper))


def params_to_tree(p: TreeParams, like: SRVFTree, origin=None, base_radius=None) -> SRVFTree:
    """A tree with every slot real (a mean, as fitted) from free parameters, with `like`'s
    thickness scale; `origin` and `base_radius` default to `like`'s (deeper levels keep
    `like`'s starting radii)."""
    origin = like.origin if origin is None else origin
    if like.thickness_scale is not None and base_radius is None:
        base_radius = like.base_radius
    deeper = tuple(
        SRVFLevel(q=lp.q, s=lp.s, mask=jnp.ones(lp.s.shape, bool), base_radius=lv.base_radius)
        for lp, lv in zip(p.deeper, like.deeper)
    )
    return SRVFTree(
        q0=p.q0,
        q=p.q,
        s=p.s,
        mask=jnp.ones(p.s.shape, bool),
        origin=origin,
        base_radius=base_radius,
        thickness_scale=like.thickness_scale,
        deeper=deeper,
        virtual_main=like.virtual_main,
    )


def whitening(weights: Weights, T: int, dtype, *, depth: int = 2) -> TreeParams:
    """Per-coordinate scales c with ``z = c·μ`` (√λ of the block's term, times √trapezoid
    weight on L2 blocks; 1 where λ = 0 so the map stays invertible), for trees of `depth`."""
    sqrt_tw = jnp.sqrt(trapezoid_weights(T, dtype))

    def scale(lam):
        lam = jnp.asarray(lam, dtype)
        return jnp.where(lam > 0, jnp.sqrt(jnp.where(lam > 0, lam, 1.0)), 1.0)

    def blocks(level):
        return {
            t.tangent_block: scale(term_weight(weights, t.name, level)) for t in TERMS if t.tangent_block is not None
        }

    top = blocks(1)
    deeper = []
    for level in range(2, depth):
        b = blocks(level)
        deeper.append(LevelParams((b["q"] * sqrt_tw)[:, None], b["s"]))
    return TreeParams((top["q0"] * sqrt_tw)[:, None], (top["q"] * sqrt_tw)[None, :, None], top["s"], tuple(deeper))


def whiten(p: TreeParams, c: TreeParams) -> TreeParams:
    deeper = tuple(LevelParams(lp.q * lc.q, lp.s * lc.s) for lp, lc in zip(p.deeper, c.deeper))
    return TreeParams(p.q0 * c.q0, p.q * c.q, p.s * c.s, deeper)


def unwhiten(z: TreeParams, c: TreeParams) -> TreeParams:
    deeper = tuple(LevelParams(lz.q / lc.q, lz.s / lc.s) for lz, lc in zip(z.deeper, c.deeper))
    return TreeParams(z.q0 / c.q0, z.q / c.q, z.s / c.s, deeper)


def flatten(v: TreeParams) -> Array:
    """One vector per tree: q0, then q, then s, then each deeper level's q and s (leading batch
    axes kept)."""
    lead = v.q0.shape[:-2]
    parts = [v.q0.reshape(lead + (-1,)), v.q.reshape(lead + (-1,)), v.s.reshape(lead + (-1,))]
    for lv in v.deeper:
        parts += [lv.q.reshape(lead + (-1,)), lv.s.reshape(lead + (-1,))]
    return jnp.concatenate(parts, axis=-1)


def unflatten(x: Array, T: int, K: int | tuple[int, ...], C: int) -> TreeParams:
    """Inverse of `flatten` for trees with T points, C channels per point and K lateral slots
    (an int), or capacities ``(K1, …, K(D−1))`` per level for a tree of depth D."""
    caps = (K,) if isinstance(K, int) else tuple(int(k) for k in K)
    lead = x.shape[:-1]
    n0 = T * C
    n1 = caps[0] * T * C
    out = TreeParams(
        x[..., :n0].reshape(lead + (T, C)),
        x[..., n0 : n0 + n1].reshape(lead + (caps[0], T, C)),
        x[..., n0 + n1 : n0 + n1 + caps[0]].reshape(lead + (caps[0],)),
    )
    at = n0 + n1 + caps[0]
    deeper = []
    for level in range(2, len(caps) + 1):
        slots = caps[:level]
        n_s = 1
        for k in slots:
            n_s *= k
        q = x[..., at : at + n_s * T * C].reshape(lead + slots + (T, C))
        at += n_s * T * C
        s = x[..., at : at + n_s].reshape(lead + slots)
        at += n_s
        deeper.append(LevelParams(q, s))
    return eqx.tree_at(lambda t: t.deeper, out, tuple(deeper)) if deeper else out


def log_map(registered: SRVFTree, mean: SRVFTree, c: TreeParams) -> Array:
    """Flattened whitened tangent vectors ``W^{1/2}(registered − mean)`` (batched). A null
    branch of a sample sits at the mean's position, so it adds no position difference."""
    deeper = tuple(
        LevelParams(lc.q * (lr.q - lm.q), lc.s * (lr.s - lm.s))
        for lr, lm, lc in zip(registered.deeper, mean.deeper, c.deeper)
    )
    return flatten(
        TreeParams(
            c.q0 * (registered.q0 - mean.q0),
            c.q * (registered.q - mean.q),
            c.s * (registered.s - mean.s),
            deeper,
        )
    )


def limit_lengths(q: Array, min_length, max_length, parent_real=None):
    """Branches longer than `max_length` (if given) scaled down to it (``q·√(max/L)``: the same
    shape, shorter); shorter than `min_length`, or under a null parent, they become nulls."""
    length = l2_norm_squared(q)
    if max_length is not None:
        too_long = length > max_length
        q = q * jnp.where(too_long, jnp.sqrt(max_length / jnp.where(too_long, length, 1.0)), 1.0)[..., None, None]
    real = length >= min_length
    if parent_real is not None:
        real = real & parent_real[..., None]
    return q * real[..., None, None], real


def exp_map(
    mean: SRVFTree,
    c: TreeParams,
    min_lateral_length: Array | tuple[Array, ...],
    v: Array,
    max_lateral_length: Array | None = None,
) -> SRVFTree:
    """SRVF trees ``μ + W^{-1/2} v`` for flattened whitened tangent vectors v (batched).
    Laterals shorter than `min_lateral_length` become nulls (a scalar, one value per level
    ``[D − 1]``, or a tuple with one array of per-slot values per level); laterals longer than
    `max_lateral_length` (if given) are scaled down to it (``q·√(max/L)``: the same shape,
    shorter); attachments are clipped to [0, 1]. At depth D > 2 the limits are scalars (every
    level) or one per level ``[D − 1]``, and the children of a null branch are nulls."""
    T, C = mean.q0.shape
    u = unflatten(v, T, mean.capacities, C)
    q0 = mean.q0 + u.q0 / c.q0
    q = mean.q + u.q / c.q
    s = jnp.clip(mean.s + u.s / c.s, 0.0, 1.0)

    def limits(level):
        hi = None if max_lateral_length is None else level_value(max_lateral_length, level)
        return level_min(min_lateral_length, level), hi

    q, real = limit_lengths(q, *limits(1))
    lead = q0.shape[:-2]
    deeper, parent = [], real
    for level, (lm, lu, lc) in enumerate(zip(mean.deeper, u.deeper, c.deeper), start=2):
        ql, rl = limit_lengths(lm.q + lu.q / lc.q, *limits(level), parent)
        sl = jnp.clip(lm.s + lu.s / lc.s, 0.0, 1.0)
        base = None if lm.base_radius is None else jnp.broadcast_to(lm.base_radius, lead + lm.base_radius.shape)
        deeper.append(SRVFLevel(q=ql, s=sl, mask=rl, base_radius=base))
        parent = rl
    origin = jnp.broadcast_to(mean.origin, lead + mean.origin.shape)
    base = scale = None
    if mean.thickness_scale is not None:
        base = jnp.broadcast_to(mean.base_radius, lead + mean.base_radius.shape)
        scale = jnp.broadcast_to(mean.thickness_scale, lead)
    return SRVFTree(
        q0=q0,
        q=q,
        s=s,
        mask=real,
        origin=origin,
        base_radius=base,
        thickness_scale=scale,
        deeper=tuple(deeper),
        virtual_main=mean.virtual_main,
    )
