"""The tangent space of SRVF trees: free parameters, whitening, flatten, log and exp maps.

The pre-shape metric is a weighted L2 norm in SRVF-tree coordinates, so the space is flat:
the tangent vector of a registered sample x at μ is ``x − μ`` (log map) and the exponential
map is addition. Vectors are whitened by the metric, ``v = W^{1/2}(x − μ)``: each metric term
with a `tangent_block` scales its block by ``√λ`` (times the square roots of the trapezoid
weights on the L2 blocks q0 and q). Euclidean geometry of the flattened ``v`` is then the
metric's own, ``|v|² = d²(μ, x)``. A thickness channel lies inside q0 and q and is whitened
with them. Used by the Karcher mean's gradient solver, tangent PCA and trait regression.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._curves import l2_norm_squared, trapezoid_weights
from ._metric import TERMS, Weights
from ._tree import SRVFTree


class TreeParams(eqx.Module):
    """The free parts of an SRVF tree: main SRVF, lateral SRVFs, attachment fractions (a batch
    adds leading axes). Also used for per-coordinate whitening scales."""

    q0: Float[Array, "*B T C"]
    q: Float[Array, "*B K T C"]
    s: Float[Array, "*B K"]


def params_of(tree: SRVFTree) -> TreeParams:
    return TreeParams(tree.q0, tree.q, tree.s)


def params_to_tree(p: TreeParams, like: SRVFTree, origin=None, base_radius=None) -> SRVFTree:
    """A tree with every slot real (a mean, as fitted) from free parameters, with `like`'s
    thickness scale; `origin` and `base_radius` default to `like`'s."""
    origin = like.origin if origin is None else origin
    if like.thickness_scale is not None and base_radius is None:
        base_radius = like.base_radius
    return SRVFTree(
        q0=p.q0,
        q=p.q,
        s=p.s,
        mask=jnp.ones(p.s.shape, bool),
        origin=origin,
        base_radius=base_radius,
        thickness_scale=like.thickness_scale,
    )


def whitening(weights: Weights, T: int, dtype) -> TreeParams:
    """Per-coordinate scales c with ``z = c·μ`` (√λ of the block's term, times √trapezoid
    weight on L2 blocks; 1 where λ = 0 so the map stays invertible)."""
    sqrt_tw = jnp.sqrt(trapezoid_weights(T, dtype))

    def scale(lam):
        lam = jnp.asarray(lam, dtype)
        return jnp.where(lam > 0, jnp.sqrt(jnp.where(lam > 0, lam, 1.0)), 1.0)

    blocks = {t.tangent_block: scale(weights[t.name]) for t in TERMS if t.tangent_block is not None}
    return TreeParams((blocks["q0"] * sqrt_tw)[:, None], (blocks["q"] * sqrt_tw)[None, :, None], blocks["s"])


def whiten(p: TreeParams, c: TreeParams) -> TreeParams:
    return TreeParams(p.q0 * c.q0, p.q * c.q, p.s * c.s)


def unwhiten(z: TreeParams, c: TreeParams) -> TreeParams:
    return TreeParams(z.q0 / c.q0, z.q / c.q, z.s / c.s)


def flatten(v: TreeParams) -> Array:
    """One vector per tree: q0, then q, then s (leading batch axes kept)."""
    lead = v.q0.shape[:-2]
    return jnp.concatenate([v.q0.reshape(lead + (-1,)), v.q.reshape(lead + (-1,)), v.s.reshape(lead + (-1,))], axis=-1)


def unflatten(x: Array, T: int, K: int, C: int) -> TreeParams:
    """Inverse of `flatten` for trees with T points, K slots and C channels per point."""
    lead = x.shape[:-1]
    n0 = T * C
    n1 = K * T * C
    return TreeParams(
        x[..., :n0].reshape(lead + (T, C)),
        x[..., n0 : n0 + n1].reshape(lead + (K, T, C)),
        x[..., n0 + n1 :].reshape(lead + (K,)),
    )


def log_map(registered: SRVFTree, mean: SRVFTree, c: TreeParams) -> Array:
    """Flattened whitened tangent vectors ``W^{1/2}(registered − mean)`` (batched). A null
    lateral of a sample sits at the mean's position, so it adds no position difference."""
    return flatten(
        TreeParams(
            c.q0 * (registered.q0 - mean.q0),
            c.q * (registered.q - mean.q),
            c.s * (registered.s - mean.s),
        )
    )


def exp_map(
    mean: SRVFTree, c: TreeParams, min_lateral_length: Array, v: Array, max_lateral_length: Array | None = None
) -> SRVFTree:
    """SRVF trees ``μ + W^{-1/2} v`` for flattened whitened tangent vectors v (batched).
    Laterals shorter than `min_lateral_length` become nulls; laterals longer than
    `max_lateral_length` (if given) are scaled down to it (``q·√(max/L)``: the same shape,
    shorter); attachments are clipped to [0, 1]."""
    T, C = mean.q0.shape
    K = mean.q.shape[0]
    u = unflatten(v, T, K, C)
    q0 = mean.q0 + u.q0 / c.q0
    q = mean.q + u.q / c.q
    s = jnp.clip(mean.s + u.s / c.s, 0.0, 1.0)
    length = l2_norm_squared(q)
    if max_lateral_length is not None:
        too_long = length > max_lateral_length
        q = (
            q
            * jnp.where(too_long, jnp.sqrt(max_lateral_length / jnp.where(too_long, length, 1.0)), 1.0)[..., None, None]
        )
    real = length >= min_lateral_length
    q = q * real[..., None, None]
    lead = q0.shape[:-2]
    origin = jnp.broadcast_to(mean.origin, lead + mean.origin.shape)
    base = scale = None
    if mean.thickness_scale is not None:
        base = jnp.broadcast_to(mean.base_radius, lead + mean.base_radius.shape)
        scale = jnp.broadcast_to(mean.thickness_scale, lead)
    return SRVFTree(q0=q0, q=q, s=s, mask=real, origin=origin, base_radius=base, thickness_scale=scale)
