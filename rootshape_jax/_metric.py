"""The elastic pre-shape metric on SRVF trees and its weights (DESIGN.md §4)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._curves import l2_norm_squared
from ._tree import SRVFTree


def _as_weight(x) -> Array:
    return jnp.asarray(x)


class Weights(eqx.Module):
    """Weights ``λ = (λm, λs, λp)`` of the three terms of the pre-shape metric.

    - `main` (λm): main-root bending and stretching, ``||q0a − q0b||²``.
    - `lateral` (λs): lateral bending/stretching and growth, ``Σ ||qa_k − qb_k||²``.
    - `position` (λp): movement of attachment points, ``Σ (sa_k − sb_k)²``.

    The paper's figures use ``(0.02, 1, 1)`` — the default. The fields are JAX arrays, so
    weights can be learned by differentiating through `distance`.
    """

    main: Float[Array, ""] = eqx.field(converter=_as_weight, default=0.02)
    lateral: Float[Array, ""] = eqx.field(converter=_as_weight, default=1.0)
    position: Float[Array, ""] = eqx.field(converter=_as_weight, default=1.0)

    def __check_init__(self):
        for name in ("main", "lateral", "position"):
            v = getattr(self, name)
            if isinstance(v, jax.core.Tracer) or not isinstance(v, (jax.Array, np.ndarray)):
                continue
            if v.shape != () or not np.isfinite(v) or v < 0:
                raise ValueError(
                    f"Weights.{name} must be a finite non-negative scalar, got {v!r}."
                )


class MetricTerms(eqx.Module):
    """The weighted terms of the squared pre-shape distance (each already multiplied by λ)."""

    main: Float[Array, "*B"]
    lateral: Float[Array, "*B"]
    position: Float[Array, "*B"]

    @property
    def total(self) -> Float[Array, "*B"]:
        return self.main + self.lateral + self.position


def preshape_terms(a: SRVFTree, b: SRVFTree, weights: Weights | None = None) -> MetricTerms:
    """Weighted terms of ``d2 = λm||Δq0||² + λs Σ||Δq_k||² + λp Σ(Δs_k)²`` slot by slot.

    No registration: slot k of `a` is compared with slot k of `b`. A position difference counts
    only where both slots are real laterals: a null lateral has no length, so it sits at its
    partner's attachment point (DESIGN.md §4: real vs null costs ``λs||q||²`` only).
    """
    weights = Weights() if weights is None else weights
    main = weights.main * l2_norm_squared(a.q0 - b.q0)
    lateral = weights.lateral * jnp.sum(l2_norm_squared(a.q - b.q), axis=-1)
    both = jnp.logical_and(a.mask, b.mask)
    position = weights.position * jnp.sum(jnp.where(both, (a.s - b.s) ** 2, 0.0), axis=-1)
    return MetricTerms(main=main, lateral=lateral, position=position)


def preshape_distance_squared(a: SRVFTree, b: SRVFTree, weights: Weights | None = None) -> Float[Array, "*B"]:
    """Squared pre-shape distance (no registration). See `preshape_terms`."""
    return preshape_terms(a, b, weights).total
