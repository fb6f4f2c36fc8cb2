"""The terms of the elastic metric, each a part with one obvious home (docs/design.md §4, §11).

The squared pre-shape distance is a sum of weighted terms. Each term is a small strategy
object that says, for its own part of the metric:

- `name`: its field in `Weights` and in `MetricTerms`, and `default_weight`;
- `energy`: its weighted energy between two trees compared slot by slot;
- `dp_level`: which branch DP its weight multiplies (``"main"``, ``"lateral"`` or None) —
  registration solves one DP per branch pair and weights its energy by the sum of the
  weights of the terms at that level;
- `pair_cost`: the part of a lateral pair's cost that needs no DP (exact, so it is also its
  own pruning lower bound), or None; `pair_lower_bound`: its share of the DP-free lower bound
  of a lateral pair's cost that lets registration skip DPs exactly;
- `tangent_block`: the block of the tangent space (``"q0"``, ``"q"``, ``"s"``) it whitens,
  with ``√λ`` (times the trapezoid weights for the L2 blocks), or None.

Registration, the Karcher mean, tangent PCA, regression and the command line loop over
`_metric.TERMS`; adding a term means writing one class (in its own module if it brings data,
as `_thickness` does) and listing it in `TERMS`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._curves import l2_norm_squared

if TYPE_CHECKING:
    from ._metric import Weights
    from ._tree import SRVFTree


class MetricTerm:
    """Base class of a metric term (stateless; one instance per term in `TERMS`)."""

    name: ClassVar[str]
    default_weight: ClassVar[float]
    description: ClassVar[str]
    dp_level: ClassVar[str | None] = None
    tangent_block: ClassVar[str | None] = None

    def energy(self, weights: Weights, a: SRVFTree, b: SRVFTree) -> Float[Array, "*B"]:
        """Weighted energy between `a` and `b` slot by slot (no registration)."""
        raise NotImplementedError

    def pair_cost(self, weights: Weights, a: SRVFTree, b: SRVFTree) -> Float[Array, "*B K K"] | None:
        """DP-free part of the cost of matching real lateral i of a with real lateral j of b
        (exact: it is its own lower bound when pruning)."""
        return None

    def pair_lower_bound(self, weights: Weights, a: SRVFTree, b: SRVFTree, dp_bound: Array):
        """This term's share of a lower bound of a lateral pair's cost, without any DP, given
        `dp_bound`, a DP-free lower bound of the lateral branch energy ``||qa − w||²`` (see
        `_engine.lower_bounds`): λ times it for a term weighting the lateral DPs, the exact
        DP-free cost for the others, 0 when the term has no part in lateral pair costs."""
        if self.dp_level == "lateral":
            return weights[self.name] * dp_bound
        cost = self.pair_cost(weights, a, b)
        return 0.0 if cost is None else cost

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def spatial(q: Array, d: int) -> Array:
    """The spatial channels of an SRVF (the first d; a thickness channel may follow)."""
    return q[..., :d]


class MainTerm(MetricTerm):
    name = "main"
    default_weight = 0.02
    description = "main-root bending and stretching, ||q0a − q0b||²"
    dp_level = "main"
    tangent_block = "q0"

    def energy(self, weights, a, b):
        return weights.main * l2_norm_squared(spatial(a.q0 - b.q0, a.dim))


class LateralTerm(MetricTerm):
    name = "lateral"
    default_weight = 1.0
    description = "lateral bending, stretching and growth, Σ ||qa_k − qb_k||²"
    dp_level = "lateral"
    tangent_block = "q"

    def energy(self, weights, a, b):
        total = weights.lateral * jnp.sum(l2_norm_squared(spatial(a.q - b.q, a.dim)), axis=-1)
        # Deeper orders (docs/design.md §11), each level with its own λs.
        for ell, (la, lb) in enumerate(zip(a.deeper, b.deeper), start=2):
            e = l2_norm_squared(spatial(la.q - lb.q, a.dim))
            total = total + weights.at_level(ell)[0] * jnp.sum(e.reshape(e.shape[: total.ndim] + (-1,)), axis=-1)
        return total


class PositionTerm(MetricTerm):
    name = "position"
    default_weight = 1.0
    description = "movement of attachment points, Σ (sa_k − sb_k)²"
    tangent_block = "s"

    def energy(self, weights, a, b):
        # Only where both slots are real: a null lateral has no length and sits at its
        # partner's attachment point (real vs null costs λs||q||² only).
        both = jnp.logical_and(a.mask, b.mask)
        total = weights.position * jnp.sum(jnp.where(both, (a.s - b.s) ** 2, 0.0), axis=-1)
        for ell, (la, lb) in enumerate(zip(a.deeper, b.deeper), start=2):
            e = jnp.where(la.mask & lb.mask, (la.s - lb.s) ** 2, 0.0)
            total = total + weights.at_level(ell)[1] * jnp.sum(e.reshape(e.shape[: total.ndim] + (-1,)), axis=-1)
        return total

    def pair_cost(self, weights, a, b):
        return weights.position * (a.s[..., :, None] - b.s[..., None, :]) ** 2
