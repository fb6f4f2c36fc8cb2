"""Registering root b onto root a, and the elastic distance (docs/design.md §4).

The work is done by the engine (`_engine.register_pairs`): rotation, reparameterisations and
lateral correspondence, with exact pruning of lateral DPs. This module checks the user's
input and options.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._curves import safe_sqrt
from ._engine import Registration, RegistrationOptions, pair_distances_squared, register_pairs_jit, registration_options
from ._errors import as_count, user_stacklevel
from ._executor import LocalExecutor
from ._metric import Weights, as_weights
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
        raise ValueError(
            f"{what}: a and b have different dtypes ({a.q0.dtype} vs {b.q0.dtype}); build both "
            "in one call to batch(), or cast one with jax.tree.map(lambda x: x.astype(...), tree) "
            "on its floating-point leaves."
        )
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
    warn_forced_matches(a, b, what, pairs="each")
    return a, b, single


def _largest_child_counts(t: SRVFTree) -> list[tuple[int, np.ndarray]]:
    """Per level ℓ = 1, 2, …: (Kℓ, the most real children any one branch of each tree has at
    that level), the latter of shape (N,) for a batch of N trees."""
    masks = [t.mask] + [lv.mask for lv in t.deeper]
    out = []
    for m in masks:
        counts = np.asarray(m).sum(axis=-1)  # [N, K1, …, K(ℓ−1)]: children per parent branch
        out.append((m.shape[-1], counts.reshape(counts.shape[0], -1).max(axis=1, initial=0)))
    return out


def warn_forced_matches(a: SRVFTree, b: SRVFTree, what: str, *, pairs: str) -> None:
    """Warn when two branches registered together can carry more real children than slots
    (``n_a + n_b > Kℓ`` at some level ℓ): then some children of one must be matched with
    children of the other even where leaving both unmatched costs less, so the distance is an
    upper bound of the elastic distance. `batch` leaves room for any two of its roots; a smaller
    `max_laterals` / `max_children`, or a Karcher mean's `fitted` tree (every slot real), may not.

    `pairs`: "each" (a[i] with b[i]), "all" (every i < j of a = b) or "cross" (every a[i] with
    every b[j]). Deeper levels count each tree's fullest branch, which another pair of branches
    may be matched instead: there the warning says "can"."""
    if any(isinstance(t.mask, jax.core.Tracer) for t in (a, b)):
        return
    for ell, ((K, ca), (_, cb)) in enumerate(zip(_largest_child_counts(a), _largest_child_counts(b)), start=1):
        if pairs == "each":
            n = int((ca + cb).max())
        elif pairs == "cross":
            n = int(ca.max() + cb.max())
        elif len(ca) < 2:
            n = 0
        else:  # the two fullest different trees
            top = np.sort(ca)[-2:]
            n = int(top.sum())
        if n <= K:
            continue
        where = "a pair has" if ell == 1 else f"at level {ell}, two matched branches can have"
        room = "max_laterals" if ell == 1 else f"max_children (K{ell})"
        warnings.warn(
            f"{what}: {where} {n} real {'laterals' if ell == 1 else 'children'} for {K} slots "
            f"(registration needs K{ell} >= n_a + n_b), so some are forced into matches and the "
            f"distance can be too large. Batch the roots with a larger {room}, or leave it to its "
            "default. For a Karcher mean: km.energies holds the samples' squared distances to it; "
            "compare other roots with km.mean_srvf (short laterals dropped) rather than km.fitted "
            "(every slot real), or if that is still too full, batch its curves with them "
            "(rs.to_roots(km.mean), then rs.batch with the options the trees were built with).",
            UserWarning,
            stacklevel=user_stacklevel(),
        )
        return  # one warning: the first level that can be forced


# Pairs per block when `register` gets long batches: a block of large roots (pea, K = 54)
# registers in seconds, so the progress bar moves at least every few seconds.
REGISTER_BLOCK = 8


def register_block(idx, n_valid: int, a: SRVFTree, b: SRVFTree, weights: Weights, opts) -> dict:
    """The registrations of pairs `idx` (padded to one block size, so one compilation serves
    every block; padded pairs are inactive), as a dict of their leaves, real rows only."""
    take = lambda t: jax.tree.map(lambda x: x[idx], t)  # noqa: E731
    active = jnp.asarray(np.arange(len(idx)) < n_valid)
    reg = register_pairs_jit(take(a), take(b), weights, opts, active)
    return {str(i): np.asarray(leaf)[:n_valid] for i, leaf in enumerate(jax.tree.leaves(reg))}


def register(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | None = None,
    progress: bool = True,
    block_size: int = REGISTER_BLOCK,
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
    - `progress`, `block_size`: batches longer than `block_size` pairs are registered in
      blocks of that many on worker threads (every core), with a progress bar that moves
      after every block. Under `jax.jit`/`jax.grad` the batch is one call.
    """
    weights = as_weights(weights)
    opts = registration_options(registration, **options)
    block_size = as_count(block_size, "register: block_size")
    a, b, single = as_pair_batch(a, b, weights)
    n = a.batch_shape[0]
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((a, b, weights)))
    if n <= block_size or traced:
        reg = register_pairs_jit(a, b, weights, opts, jnp.ones(a.batch_shape, bool))
    else:
        reg = _register_in_blocks(a, b, weights, opts, block_size, progress)
    if single:
        reg = jax.tree.map(lambda x: x[0], reg)
    return reg


def _register_in_blocks(a, b, weights, opts, block_size: int, progress: bool) -> Registration:
    n = a.batch_shape[0]
    blocks = [
        (np.minimum(np.arange(s, s + block_size), n - 1), min(block_size, n - s)) for s in range(0, n, block_size)
    ]
    # The result's structure, without compiling (the call below reuses this trace).
    first = jax.tree.map(lambda x: x[:block_size], (a, b))
    shape = eqx.filter_eval_shape(register_pairs_jit, *first, weights, opts, jnp.ones(block_size, bool))
    results, _ = LocalExecutor().map_blocks(
        register_block,
        blocks,
        shared=(a, b, weights, opts),
        sizes=[v for _, v in blocks],
        progress=progress,
        desc="registering",
        unit="pair",
    )
    leaves = [jnp.asarray(np.concatenate([r[str(i)] for r in results])) for i in range(len(results[0]))]
    return jax.tree.unflatten(jax.tree.structure(shape), leaves)


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
    optimum may differ the other way round: on 15 Arabidopsis plate tracings, T = 48, the
    canonical order was above the better of the two orders in about half of the 105 pairs,
    by 0.07 % at the median and 4.4 % at most; on 9 plate tracings at T = 50 `register(a, b)`
    was 5.9 % below to 4.2 % above it; `min(register(a, b).distance, register(b, a)
    .distance)` is the better local optimum, at twice the cost). Equals `pairwise_distances` and
    `cross_distances`, which use the same order, up to rounding (a pair alone is rounded
    otherwise than in a batch: 2.5e-6 relative seen on one plate pair in float64). Differentiable with respect to both roots'
    coordinates (and the weights): the registration is held fixed under `stop_gradient`
    (envelope theorem).

    `weights`: the metric's λ, a `Weights` (default the paper's, ``Weights(0.02, 1, 1)``).
    **Units**: the distance is the square root of the weighted sum of the metric's terms,
    ``λm ||q0a − q0b||² + λs Σ ||qa − qb||² + λp Σ (sa − sb)²``; the SRVF terms scale with the
    roots' length (``||q||²`` is a length), the position term does not (attachment fractions).
    For trees of `batch(normalise_scale=True)` (every main root of length 1) it is unitless;
    otherwise it depends on the coordinates' unit, and so does the balance of the terms:
    compare distances computed in one unit (docs/metadata.md).
    """
    weights = as_weights(weights)
    opts = registration_options(registration, **options)
    a, b, single = as_pair_batch(a, b, weights, "distance")
    d = _distances(a, b, weights, opts)
    return d[0] if single else d


@eqx.filter_jit
def _distances(a, b, weights, opts):
    energy = pair_distances_squared(a, b, weights, opts)[0]
    return safe_sqrt(energy)
