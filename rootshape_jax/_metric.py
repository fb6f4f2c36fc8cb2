"""The elastic pre-shape metric on SRVF trees: its terms, their weights and energies (docs/design.md §4).

The metric is the sum of the terms listed in `TERMS` (each defined in `_terms` or its own
module); `Weights` and `MetricTerms` have one field per term, in that order.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._terms import LateralTerm, MainTerm, MetricTerm, PositionTerm
from ._thickness import ThicknessTerm
from ._tree import SRVFTree

TERMS: tuple[MetricTerm, ...] = (MainTerm(), LateralTerm(), PositionTerm(), ThicknessTerm())
TERM_NAMES: tuple[str, ...] = tuple(t.name for t in TERMS)


def _by_name(cls: str, args, kwargs, *, defaults: bool) -> dict:
    if len(args) > len(TERM_NAMES):
        raise TypeError(f"{cls} takes at most {len(TERM_NAMES)} values {TERM_NAMES}, got {len(args)}.")
    values = dict(zip(TERM_NAMES, args))
    for k, v in kwargs.items():
        if k not in TERM_NAMES:
            raise TypeError(f"{cls}: unknown term {k!r}; the terms are {TERM_NAMES}.")
        if k in values:
            raise TypeError(f"{cls}: {k!r} given twice (positionally and by name).")
        values[k] = v
    if defaults:
        return {t.name: values.get(t.name, t.default_weight) for t in TERMS}
    missing = [n for n in TERM_NAMES if n not in values]
    if missing:
        raise TypeError(f"{cls}: missing {missing}.")
    return {n: values[n] for n in TERM_NAMES}


class _ByTerm(eqx.Module):
    """One value per metric term, read as attributes (``w.main``) or by name (``w["main"]``)."""

    values: dict[str, Array]

    def __getattr__(self, name):
        # Only called for names that are not fields; "values" itself is never looked up here
        # except while the instance is half-built (copy, unpickling).
        if name != "values":
            values = self.__dict__.get("values")
            if values is not None and name in values:
                return values[name]
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    def __getitem__(self, name: str) -> Array:
        return self.values[name]

    def items(self):
        return ((n, self.values[n]) for n in TERM_NAMES)

    def __repr__(self) -> str:
        # Concrete scalars print as numbers (``MetricTerms(main=0.0123, ...)``); batches and
        # traced values keep equinox's summary (shapes and dtypes).
        leaves = jax.tree.leaves(self)  # the values and, for Weights, the deeper levels' weights
        if all(isinstance(v, (float, int, np.ndarray, np.generic, jax.Array)) for v in leaves) and all(
            np.ndim(v) == 0 and not isinstance(v, jax.core.Tracer) for v in leaves
        ):
            body = ", ".join(f"{n}={float(self.values[n]):.6g}" for n in TERM_NAMES if n in self.values)
            deeper = getattr(self, "deeper", ())
            if deeper:
                body += ", deeper=" + repr(tuple(tuple(float(x) for x in level) for level in deeper))
            return f"{type(self).__name__}({body})"
        return eqx.tree_pformat(self)


class Weights(_ByTerm):
    """Weights ``λ`` of the terms of the pre-shape metric, one per entry of `TERMS`:

    - `main` (λm, default 0.02): main-root bending and stretching, ``||q0a − q0b||²``.
    - `lateral` (λs, default 1): lateral bending/stretching and growth, ``Σ ||qa_k − qb_k||²``.
    - `position` (λp, default 1): movement of attachment points, ``Σ (sa_k − sb_k)²``.
    - `thickness` (λr, default 0): radius along each branch, through the extended SRVF of
      ``(x, √λr·r)`` (docs/design.md §11); used where trees carry radii. 0 is the paper's metric.
    - `deeper` (keyword only, default ``()``): ``((λs, λp), …)`` of levels 2, 3, … (second-order
      laterals and below, docs/design.md §11: each level has its own weights). A level beyond
      the tuple takes its last entry; with ``()`` every level takes `lateral` and `position`,
      as the paper's first-order laterals do (`Weights.at_level`).

    ``Weights(0.02, 1, 1)`` gives values in that order; names are clearer. The paper's figures
    use ``(0.02, 1, 1)``. The values are JAX arrays, so weights can be learned by
    differentiating through `distance`.
    """

    deeper: tuple[tuple[Array, Array], ...]

    def __init__(self, *args, deeper=(), **kwargs):
        values = _by_name("Weights", args, kwargs, defaults=True)
        for name, v in values.items():
            _require_real(v, f"Weights.{name}")
        self.values = {k: jnp.asarray(v) for k, v in values.items()}
        try:
            pairs = tuple(tuple(p) for p in deeper)
        except TypeError:
            pairs = None
        if pairs is None or any(len(p) != 2 for p in pairs):
            raise ValueError(
                f"Weights.deeper must be a sequence of (λs, λp) pairs, one per level from 2 on; got {deeper!r}."
            )
        for ell, (ls, lp) in enumerate(pairs, start=2):
            _require_real(ls, f"Weights.deeper[{ell - 2}] λs")
            _require_real(lp, f"Weights.deeper[{ell - 2}] λp")
        self.deeper = tuple((jnp.asarray(ls), jnp.asarray(lp)) for ls, lp in pairs)

    def __check_init__(self):
        named = list(self.values.items())
        for ell, (ls, lp) in enumerate(self.deeper, start=2):
            named += [(f"deeper[{ell - 2}] (level {ell}) λs", ls), (f"deeper[{ell - 2}] (level {ell}) λp", lp)]
        for name, v in named:
            if isinstance(v, jax.core.Tracer) or not isinstance(v, (jax.Array, np.ndarray)):
                continue
            if v.shape != () or not np.isfinite(v) or v < 0:
                shown = f"{float(v):g}" if v.shape == () else f"an array of shape {v.shape}"
                raise ValueError(f"Weights.{name} must be a finite non-negative scalar, got {shown}.")

    def at_level(self, level: int) -> tuple[Array, Array]:
        """``(λs, λp)`` of the branches at `level` (1 = the main root's laterals, 2 = their
        laterals, ...): `lateral` and `position` at level 1, ``deeper[level − 2]`` below, the
        last entry of `deeper` beyond it (level 1's when `deeper` is empty)."""
        if level < 1:
            raise ValueError(f"Weights.at_level: level must be >= 1 (1 = first-order laterals), got {level}.")
        if level == 1 or not self.deeper:
            return self.values["lateral"], self.values["position"]
        return self.deeper[min(level - 2, len(self.deeper) - 1)]

    def to_dict(self) -> dict[str, float]:
        """The weights as a flat dict of floats: the terms, then ``lateral_order{ℓ}`` and
        ``position_order{ℓ}`` for each entry of `deeper` (ℓ = 2, 3, …; the last entry also
        weighs the orders below it)."""
        out = {k: float(v) for k, v in self.items()}
        for e, (ls, lp) in enumerate(self.deeper):
            out[f"lateral_order{e + 2}"] = float(ls)
            out[f"position_order{e + 2}"] = float(lp)
        return out


def _require_real(v, name: str) -> None:
    """`TypeError` unless `v` is a real number (or a traced/array value of a real dtype): a
    string fails inside JAX, and a complex weight would give a complex distance."""
    if isinstance(v, jax.core.Tracer):
        kind = np.dtype(v.dtype).kind
    elif isinstance(v, (bool, np.bool_)):
        kind = "b"
    else:
        try:
            kind = np.asarray(v).dtype.kind
        except (TypeError, ValueError):
            kind = "O"
    if kind not in "iuf":
        raise TypeError(f"{name} must be a real number, got {v!r}.")


def as_weights(weights) -> Weights:
    """`weights`, or the paper's `Weights()` for None; `TypeError` for anything else (a tuple
    or dict would otherwise fail deep inside the metric). Traced weights (under jit, where they
    cannot be checked) that are negative become NaN, so the distance is NaN as for a NaN
    weight, not a plausible number."""
    if weights is None:
        return Weights()
    if not isinstance(weights, Weights):
        if isinstance(getattr(weights, "weights", None), Weights):  # e.g. learn_weights' result
            raise TypeError(
                f"weights must be a rootshape_jax.Weights, got a {type(weights).__name__}; pass its "
                "`.weights` (e.g. weights=learned.weights)."
            )
        raise TypeError(
            f"weights must be a rootshape_jax.Weights, got {type(weights).__name__} {weights!r}; "
            "write Weights(0.02, 1, 1) or Weights(main=0.02, lateral=1, position=1)."
        )
    if any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(weights)):
        weights = jax.tree.map(lambda v: jnp.where(v >= 0, v, jnp.nan), weights)
    return weights


def lateral_weight(weights: Weights, level: int, dtype) -> Array:
    """λs of `level` (`Weights.at_level`) as a `dtype` array."""
    return jnp.asarray(weights.at_level(level)[0], dtype)


def child_weights(weights: Weights) -> Weights:
    """The weights seen one level down, from a branch whose children are compared as the
    laterals of a tree (nested registration): level ℓ + 1's weights become level ℓ's."""
    if not weights.deeper:
        return weights
    lam_s, lam_p = weights.deeper[0]
    values = {**dict(weights.items()), "lateral": lam_s, "position": lam_p}
    return Weights(**values, deeper=weights.deeper[1:])


def system_weights(weights: Weights, tree) -> Weights:
    """The weights that `tree`'s levels use (docs/design.md §11).

    A plant's system (`SRVFTree.virtual_main`: a virtual main root of zero length whose
    level-1 branches are the plant's axes, all at s = 0) is weighed as the taproot analysis of
    its axes: the axes take the main root's λm (no position term), level ℓ ≥ 2 the weights of
    level ℓ − 1. One axis per plant then gives exactly the taproot distances. Any other tree:
    `weights` as given.
    """
    return _axes_as_main(weights) if getattr(tree, "virtual_main", False) else weights


def _axes_as_main(weights: Weights) -> Weights:
    values = {**dict(weights.items()), "lateral": weights.main, "position": jnp.zeros_like(weights.position)}
    return Weights(**values, deeper=((weights.lateral, weights.position),) + weights.deeper)


def unit_energies_by_level(a: SRVFTree, b: SRVFTree) -> Float[Array, "*B C"]:
    """The unweighted energies of the linear terms, level by level, slot by slot (no
    registration): column 0 the main root's ``||q0a − q0b||²``, then for each branch level
    ℓ = 1 … D − 1 its lateral ``Σ ||qa − qb||²`` and position ``Σ (sa − sb)²`` energies, so
    ``C = 2D − 1``. For weights without thickness,
    ``preshape_terms(a, b, w).total == unit_energies_by_level(a, b) @ weights_by_level(w, ...)``:
    with the registrations fixed, d² is linear in λ (`learn_weights`). Each column is its
    term's own `energy` at λ = 1 on that level and 0 elsewhere."""
    n_levels = 1 + len(a.deeper)

    def indicator(level: int) -> Weights:  # λ = 1 on one level (0 = the main root), 0 elsewhere
        def on(ell):
            return float(ell == level)

        return Weights(
            main=on(0),
            lateral=on(1),
            position=on(1),
            thickness=0.0,
            deeper=tuple((on(ell), on(ell)) for ell in range(2, n_levels + 1)),
        )

    term = {t.name: t for t in TERMS}
    columns = [term["main"].energy(indicator(0), a, b)]
    for ell in range(1, n_levels + 1):
        w = indicator(ell)
        columns += [term["lateral"].energy(w, a, b), term["position"].energy(w, a, b)]
    return jnp.stack([jnp.asarray(c, a.q0.dtype) for c in columns], axis=-1)


def weights_by_level(weights: Weights, *, depth: int, virtual_main: bool = False) -> Float[Array, " C"]:
    """The weights of the columns of `unit_energies_by_level` for trees of `depth` levels:
    ``[λm, λs(1), λp(1), …, λs(D − 1), λp(D − 1)]`` as the trees' levels use them
    (`Weights.at_level`; a plant's system weighs its axes as main roots, `system_weights`)."""
    w = _axes_as_main(weights) if virtual_main else weights
    lam = [w.main] + [x for ell in range(1, depth) for x in w.at_level(ell)]
    return jnp.stack([jnp.asarray(x) for x in lam])


class MetricTerms(_ByTerm):
    """The weighted terms of the squared pre-shape distance (each already multiplied by λ),
    one per entry of `TERMS` (``terms.main``, ``terms.lateral``, ...)."""

    def __init__(self, *args, **kwargs):
        self.values = _by_name("MetricTerms", args, kwargs, defaults=False)

    @property
    def total(self) -> Float[Array, "*B"]:
        out = None
        for name in TERM_NAMES:
            out = self.values[name] if out is None else out + self.values[name]
        return out


def level_weight(weights: Weights, level: str, dtype) -> Array:
    """Weight of the branch DPs at `level` ("main" or "lateral"): the sum over the terms there."""
    lams = [jnp.asarray(weights[t.name], dtype) for t in TERMS if t.dp_level == level]
    return sum(lams[1:], lams[0])


def pair_costs(weights: Weights, a: SRVFTree, b: SRVFTree) -> Float[Array, "*B K K"]:
    """The DP-free part of every lateral pair's cost (exact), summed over the terms."""
    parts = [c for t in TERMS if (c := t.pair_cost(weights, a, b)) is not None]
    if not parts:
        return jnp.zeros(a.s.shape + a.s.shape[-1:], a.q0.dtype)
    return sum(parts[1:], parts[0])


def pair_lower_bounds(weights: Weights, a: SRVFTree, b: SRVFTree, dp_bound: Array) -> Float[Array, "*B K K"]:
    """A DP-free lower bound of every real–real lateral pair's cost, summed over the terms
    (`MetricTerm.pair_lower_bound`), from `dp_bound`, a lower bound of the branch energy."""
    lower = 0.0
    for term in TERMS:
        lower = lower + term.pair_lower_bound(weights, a, b, dp_bound)
    return lower


def null_costs(weights: Weights, a: SRVFTree, b: SRVFTree, La: Array, Lb: Array) -> Float[Array, "*B K K"]:
    """Exact cost of the lateral pairs that are not both real: a real lateral matched to a null
    costs its whole λ-weighted norm (`La`, `Lb`: lengths ``||q||²``, 0 for nulls); null–null 0.
    (Level-1 weights; the engine adds what lies below.)"""
    lam = level_weight(weights, "lateral", La.dtype)
    return jnp.where(
        a.mask[..., :, None],
        (lam * La)[..., :, None],
        jnp.where(b.mask[..., None, :], (lam * Lb)[..., None, :], 0.0),
    )


def preshape_terms(a: SRVFTree, b: SRVFTree, weights: Weights | None = None) -> MetricTerms:
    """Weighted terms of the squared pre-shape distance, slot by slot (no registration).

    Slot k of `a` is compared with slot k of `b`; every level takes its own weights
    (`Weights.at_level`, and `system_weights` for a plant's system). A position difference counts only where both
    slots are real laterals: a null lateral has no length, so it sits at its partner's
    attachment point (docs/design.md §4: real vs null costs ``λs||q||²`` only).
    """
    weights = system_weights(as_weights(weights), a)
    return MetricTerms(**{t.name: t.energy(weights, a, b) for t in TERMS})


def preshape_distance_squared(a: SRVFTree, b: SRVFTree, weights: Weights | None = None) -> Float[Array, "*B"]:
    """Squared pre-shape distance (no registration). See `preshape_terms`."""
    return preshape_terms(a, b, weights).total
