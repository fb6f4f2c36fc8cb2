"""Registering root b onto root a, and the elastic distance (docs/design.md §4).

The work is done by the engine (`_engine.register_pairs`): rotation, reparameterisations and
lateral correspondence, with exact pruning of lateral DPs. This module checks the user's
input and options.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._curves import safe_sqrt
from ._engine import Registration, RegistrationOptions, pair_distances_squared, register_pairs_jit, registration_options
from ._metric import Weights
from ._tree import RootTree, SRVFTree, check_compatible, to_srvf


def as_pair_batch(a, b, weights: Weights, what: str = "register") -> tuple[SRVFTree, SRVFTree, bool]:
    """Two trees (or batches) as SRVF batches with one leading axis; True when single."""
    for name, t in (("a", a), ("b", b)):
        if not isinstance(t, (RootTree, SRVFTree)):
            raise TypeError(
                f"{what}: {name} must be a RootTree or SRVFTree, got {type(t).__name__}; "
                "build trees with rootshape_jax.batch(roots)."
            )
    a = to_srvf(a, weights=weights)
    b = to_srvf(b, weights=weights)
    check_compatible(a, b, f"{what}: a and b")
    if a.q0.dtype != b.q0.dtype:
        raise ValueError(f"{what}: a and b have different dtypes ({a.q0.dtype} vs {b.q0.dtype}).")
    if a.batch_shape != b.batch_shape:
        raise ValueError(
            f"{what}: a has batch shape {a.batch_shape} but b has {b.batch_shape}; pass two single "
            "trees, or two batches of the same length (registered element by element)."
        )
    if len(a.batch_shape) > 1:
        raise ValueError(f"{what}: at most one batch axis is supported, got {a.batch_shape}.")
    single = a.batch_shape == ()
    if single:
        a, b = jax.tree.map(lambda x: x[None], (a, b))
    if a.capacity < 1:
        raise ValueError(f"{what}: trees need at least one lateral slot (K >= 1).")
    return a, b, single


def register(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | None = None,
    **options,
) -> Registration:
    """Register root `b` onto root `a` (docs/design.md §4).

    `a` and `b` are single trees, or two batches of the same length registered element by
    element. They must share capacities (T, K, d); registering needs ``K >= n_a + n_b``, which
    `rootshape_jax.batch` guarantees by default.

    **Options**

    - `weights`: λ, default the paper's (0.02, 1, 1) (and thickness 0).
    - `registration`: a `RegistrationOptions`; or its fields as keywords (shorthand):
      `rotation`, `max_iterations`, `rtol`, `neighbourhood`, `prune`, `dp_batch_size`,
      `assignment` — see `RegistrationOptions`.
    """
    weights = Weights() if weights is None else weights
    opts = registration_options(registration, **options)
    a, b, single = as_pair_batch(a, b, weights)
    reg = register_pairs_jit(a, b, weights, opts, jnp.ones(a.batch_shape, bool))
    if single:
        reg = jax.tree.map(lambda x: x[0], reg)
    return reg


def distance(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | None = None,
    **options,
) -> Float[Array, "*B"]:
    """Elastic distance ``sqrt(min d²)`` between roots a and b (options as in `register`).

    Exactly symmetric: the pair is registered in a canonical order that does not depend on the
    argument order (`register` registers b onto a as asked, and the alternation's local
    optimum may differ slightly the other way round). Equals `pairwise_distances` and
    `cross_distances`, which use the same order. Differentiable with respect to both roots'
    coordinates (and the weights): the registration is held fixed under `stop_gradient`
    (envelope theorem).
    """
    weights = Weights() if weights is None else weights
    opts = registration_options(registration, **options)
    a, b, single = as_pair_batch(a, b, weights, "distance")
    d = _distances(a, b, weights, opts)
    return d[0] if single else d


@eqx.filter_jit
def _distances(a, b, weights, opts):
    energy = pair_distances_squared(a, b, weights, opts)[0]
    return safe_sqrt(energy)
