"""Thickness: the extended SRVF of (x, √λr·r) (docs/design.md §11).

Each branch with radius ``r(t)`` along it is the curve ``(x(t), c·r(t))`` in R^(d+1), with
``c = √λr``; its SRVF is taken as usual, and the extra channel rides along in `SRVFTree.q0`
and `SRVFTree.q` (so registration, means, PCA and geodesics treat it like any coordinate).
Rotations act on the d spatial channels only. Reparameterisation acts on the whole extended
curve, so a warp that aligns shapes also aligns radius profiles.

Like translation for x, the SRVF forgets each branch's starting radius: the metric compares
how radius changes along a branch (tapering), not a constant offset. The starting radii are
kept in `SRVFTree.base_radius` (as the origin keeps the position) so curves and radii can be
rebuilt.

With λr = 0 (the default) or a tree without radii no channel is added, so every result is
today's, bit for bit. A tree built with one λr cannot be compared with a tree built with
another: `to_srvf(tree, weights=...)` fixes it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._curves import l2_norm_squared, srvf, srvf_to_curve
from ._terms import MetricTerm


class ThicknessTerm(MetricTerm):
    name = "thickness"
    default_weight = 0.0
    description = (
        "change of radius along each branch (extended SRVF of (x, √λr·r)); its energy is the "
        "thickness channel's share of the main and lateral terms"
    )

    def energy(self, weights, a, b):
        d = a.dim
        if a.q0.shape[-1] == d:
            return jnp.zeros(a.q0.shape[:-2], a.q0.dtype)
        main = weights.main * l2_norm_squared(a.q0[..., d:] - b.q0[..., d:])
        lateral = weights.lateral * jnp.sum(l2_norm_squared(a.q[..., d:] - b.q[..., d:]), axis=-1)
        # Deeper levels (docs/design.md §11): the channel's share of each level's λs term.
        for ell, (la, lb) in enumerate(zip(a.deeper, b.deeper), start=2):
            e = l2_norm_squared(la.q[..., d:] - lb.q[..., d:])
            lateral = lateral + weights.at_level(ell)[0] * jnp.sum(e.reshape(e.shape[: main.ndim] + (-1,)), axis=-1)
        return main + lateral


def wants_thickness(tree, weights) -> bool:
    """True when `tree` has radii and λr is not a concrete zero (a traced λr always counts)."""
    if getattr(tree, "main_radius", None) is None or weights is None:
        return False
    lam = weights.thickness
    if isinstance(lam, jax.core.Tracer):
        return True
    return bool(np.asarray(lam) > 0)


def extended_srvf(main, laterals, main_radius, lateral_radius, mask, lam_r):
    """(q0, q, base_radius, c) of a (batched) tree with radii: SRVFs of ``(x, c·r)``."""
    c = jnp.sqrt(jnp.asarray(lam_r, main.dtype))
    main_ext = jnp.concatenate([main, c * main_radius[..., None]], axis=-1)
    lat_ext = jnp.concatenate([laterals, c * lateral_radius[..., None]], axis=-1)
    q0 = srvf(main_ext)
    q = srvf(lat_ext) * mask[..., None, None]
    base = jnp.concatenate([main_radius[..., :1], lateral_radius[..., 0]], axis=-1)
    return q0, q, base, jnp.broadcast_to(c, main.shape[:-2])


def split_channel(curve_ext: Float[Array, "*B T D"], d: int, c) -> tuple[Array, Array]:
    """Spatial curve and radius from an integrated extended curve (radius 0 where c = 0)."""
    c = jnp.asarray(c)[..., None]
    ok = c > 0
    radius = jnp.where(ok, curve_ext[..., d] / jnp.where(ok, c, 1.0), 0.0)
    return curve_ext[..., :d], radius


def integrate_branch(q_ext, start_x, start_radius, c):
    """Integrate one extended SRVF from (start_x, c·start_radius): (curve [T, d], radius [T])."""
    d = start_x.shape[-1]
    start = jnp.concatenate([start_x, (c * start_radius)[..., None]], axis=-1)
    return split_channel(srvf_to_curve(q_ext, start), d, c)
