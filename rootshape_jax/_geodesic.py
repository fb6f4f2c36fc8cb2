"""Geodesics between roots: straight lines in SRVF-tree space, mapped back to curves."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._engine import Registration
from ._metric import Weights
from ._registration import register
from ._tree import RootTree, SRVFTree, to_curves, to_srvf


def geodesic_srvf(a: SRVFTree, registered_b: SRVFTree, taus) -> SRVFTree:
    """Points ``(1 − τ) a + τ b`` of the straight line between a and registered b.

    A null lateral takes its partner's attachment fraction at both ends, so a lateral that
    exists on one side only grows from (or shrinks to) zero length at a fixed position.
    The result has a leading axis over `taus`.
    """
    s_a = jnp.where(a.mask, a.s, registered_b.s)
    s_b = jnp.where(registered_b.mask, registered_b.s, s_a)
    mask = a.mask | registered_b.mask

    def point(tau):
        lerp = lambda x, y: (1 - tau) * x + tau * y  # noqa: E731
        base = None
        if a.base_radius is not None:
            # A lateral present on one side only keeps its partner's starting radius.
            base_b = jnp.where(
                jnp.concatenate([jnp.ones(1, bool), registered_b.mask]), registered_b.base_radius, a.base_radius
            )
            base_a = jnp.where(jnp.concatenate([jnp.ones(1, bool), a.mask]), a.base_radius, base_b)
            base = lerp(base_a, base_b)
        return SRVFTree(
            q0=lerp(a.q0, registered_b.q0),
            q=lerp(a.q, registered_b.q),
            s=lerp(s_a, s_b),
            mask=mask,
            origin=lerp(a.origin, registered_b.origin),
            base_radius=base,
            thickness_scale=a.thickness_scale,
        )

    return jax.vmap(point)(jnp.asarray(taus, a.q0.dtype))


def geodesic(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    n_steps: int = 9,
    weights: Weights | None = None,
    registration: Registration | None = None,
    **options,
) -> RootTree:
    """The geodesic from root a to root b as a batched `RootTree` of `n_steps` roots.

    Slot k of every step is the same lateral along the path (the correspondence colour); a
    lateral present on one side only grows from zero length at its partner's position. Pass a
    precomputed `registration` (of b onto a) to skip registering again; other options as in
    `register`.
    """
    if not isinstance(n_steps, int) or n_steps < 2:
        raise ValueError(f"n_steps must be an integer >= 2, got {n_steps!r}.")
    if registration is None:
        registration = register(a, b, weights=weights, **options)
    if a.batch_shape != ():
        raise ValueError("geodesic works on one pair of roots; loop or vmap over pairs.")
    weights = Weights() if weights is None else weights
    # Whether a has a thickness channel is decided here, on concrete weights (static below).
    thick = registration.registered.has_thickness
    return _geodesic_curves(a, registration.registered, n_steps, weights if thick else None)


@eqx.filter_jit
def _geodesic_curves(a: RootTree | SRVFTree, rb: SRVFTree, n_steps: int, weights: Weights | None) -> RootTree:
    # One compiled program, SRVF conversion included (eagerly it costs more than the path).
    sa = to_srvf(a, weights=weights)
    taus = jnp.linspace(0.0, 1.0, n_steps, dtype=sa.q0.dtype)
    return to_curves(geodesic_srvf(sa, rb, taus))
