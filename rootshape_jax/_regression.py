"""Trait-controlled root synthesis: linear regression from traits to PCA coefficients
(docs/design.md §6, paper §5.2).

Each training root has standardised PCA coefficients ``b`` (`TangentPCA.scores`, the kept
components) and a trait vector ``p`` — by default the paper's main-root length, mean lateral
length and standard deviation of lateral lengths (`rootshape_jax.traits`), plus any user
covariates. The paper's map is ``M = B P⁺`` with ``P = [p; 1]``; we regress on standardised
values ``z = (p − mean) / std`` instead, ``Z = [z; 1]`` (``(l+1) × n``) and ``M = B Z⁺``. The
fitted values are the same, but a trait that is constant in training (main-root length after
scale normalisation) no longer gets cancelling coefficients of ~10⁶ that ruin a float32
synthesis; it is ignored, with a warning. A root with traits p is
``reconstruct(pca, M [z; 1])``.
`TraitRegression.report` measures the traits of synthesised roots and compares them with the
requested ones. Plants' systems are measured as plants (`rootshape_jax.traits`: the longest
axis is the main root, the axes' laterals are the laterals), so their lateral traits need
trees of depth 3 or more; at depth 2 (axes only) they are 0, constant, and ignored.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._curves import cumulative_sum, safe_norm, trapezoid_weights
from ._errors import ExtrapolationWarning, as_count, require_finite_values, user_stacklevel
from ._pca import TangentPCA, min_lengths
from ._tangent import level_min, level_value, limit_lengths, unflatten
from ._traits import traits as measure_traits
from ._tree import RootTree, SRVFLevel, SRVFTree, to_curves, to_roots

PAPER_TRAITS: tuple[str, ...] = ("main_length", "mean_lateral_length", "std_lateral_length")


def _measure(trees: RootTree, names: Sequence[str]) -> np.ndarray:
    if not names:
        n = 1 if trees.batch_shape == () else trees.batch_shape[0]
        return np.zeros((n, 0))
    rows = measure_traits(to_roots(trees))
    for k in names:
        if k not in rows[0] or k in ("name", "unit"):
            raise ValueError(f"unknown trait {k!r}; use names returned by rootshape_jax.traits().")
    return np.array([[float(r[k]) for k in names] for r in rows], dtype=np.float64)


def _as_matrix(x, n: int | None, what: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or (n is not None and x.shape[0] != n):
        raise ValueError(f"{what} must have shape ({n}, c), got {np.shape(x)}.")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} contains NaN or inf.")
    return x


def _standardise(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, scale and a mask of the trait columns constant up to rounding (given scale 1;
    the regression ignores them).

    Without this, a constant column (main-root length after scale normalisation is 1 ± 1e-8)
    is collinear with the intercept: ``P⁺`` gives it coefficients of ~10⁶ that cancel only in
    exact arithmetic, and a float32 synthesis loses every digit.
    """
    mean = p.mean(axis=0)
    scale = p.std(axis=0)
    constant = scale <= 1e-6 * np.maximum(np.abs(mean), np.finfo(np.float64).tiny)
    return mean, np.where(constant, 1.0, scale), constant


def _stacked_to_curves(qa, s, keep, origin):
    """`to_curves` for one tree whose SRVFs are stacked ``(d, T, K+1)``, main root in slot 0.

    The same arithmetic as `to_curves` (cumulative trapezoid, then laterals from the main
    root's point at arc-length fraction s), but every curve in one cumulative sum with the
    curves on the minor axis: a few vectorised XLA:CPU kernels instead of a set per curve
    (with d minor, as in `RootTree`, the same work takes 1.7× longer).
    """
    d, T, _ = qa.shape
    speed = safe_norm(qa, axis=0)  # (T, K+1)
    vel = qa * (speed * keep)
    steps = 0.5 * (vel[:, 1:] + vel[:, :-1]) / (T - 1)  # (d, T-1, K+1)
    seg = safe_norm(steps[:, :, 0], axis=0)  # main-root segment lengths
    flat = jnp.concatenate([*steps, seg[:, None]], axis=1)  # (T-1, d (K+1) + 1)
    flat = cumulative_sum(flat, axis=0)
    flat = jnp.concatenate([jnp.zeros_like(flat[:1]), flat], axis=0)
    cum = flat[:, -1]
    curves = jnp.stack(jnp.split(flat[:, :-1], d, axis=1), axis=-1)  # (T, K+1, d)
    main = curves[:, 0] + origin
    # interpolate_at_fraction(main, s) with the segment lengths already at hand.
    target = s * cum[-1]
    idx = jnp.clip(jnp.sum(cum[None, :] <= target[:, None], axis=1) - 1, 0, T - 2)
    seg_len = seg[idx]
    frac = jnp.where(seg_len > 0, (target - cum[idx]) / jnp.where(seg_len > 0, seg_len, 1.0), 0.0)
    frac = jnp.clip(frac, 0.0, 1.0)[:, None]
    bases = main[idx] * (1 - frac) + main[idx + 1] * frac
    laterals = jnp.swapaxes(curves[:, 1:], 0, 1) + bases[:, None, :]
    return main, laterals


_SWEEP_CHUNK = 64


@functools.partial(jax.jit, static_argnames=("curves", "virtual_main"))
def _synthesize(
    offset,
    slopes,
    s_offset,
    s_slopes,
    origin,
    min_len,
    max_len,
    trait_mean,
    trait_scale,
    v,
    curves,
    thick=None,
    deeper=(),
    virtual_main=False,
):
    # Plain jax.jit on the arrays it needs: one regressed root is dispatch-bound, so no Module
    # flattening, and the affine map is unrolled over the few traits (XLA:CPU's
    # dot for a (l,) × (l, p) product costs more than the whole root).
    def one(v):
        z = (v - trait_mean) / trait_scale
        qa = offset + sum(z[i] * slopes[i] for i in range(slopes.shape[0]))  # (d, T, K+1)
        s = jnp.clip(s_offset + sum(z[i] * s_slopes[i] for i in range(s_slopes.shape[0])), 0.0, 1.0)
        w = trapezoid_weights(qa.shape[1], qa.dtype)
        length = jnp.sum(jnp.sum(qa * qa, axis=0) * w[:, None], axis=0)
        # As `_tangent.exp_map`: laterals longer than the data's longest are scaled down to it.
        lo, hi = level_min(min_len, 1), level_value(max_len, 1)
        too_long = (jnp.arange(qa.shape[-1]) > 0) & (length > hi)
        qa = qa * jnp.where(too_long, jnp.sqrt(hi / jnp.where(too_long, length, 1.0)), 1.0)
        keep = jnp.concatenate([jnp.ones(1, bool), length[1:] >= lo])  # slot 0 is the main root
        real = keep[1:]
        if curves and thick is None and not deeper:
            main, laterals = _stacked_to_curves(qa, s, keep, origin)
            return RootTree(main=main, laterals=laterals, attach=s, mask=real, virtual_main=virtual_main)
        q = jnp.transpose(qa[:, :, 1:], (2, 1, 0)) * real[:, None, None]
        # Deeper levels (depth D > 2) as exp_map does: limits per level, nulls drop children.
        levels, parent = [], real
        for level, (q_off, q_sl, s_off, s_sl) in enumerate(deeper, start=2):
            ql = q_off + sum(z[i] * q_sl[i] for i in range(q_sl.shape[0]))
            sl = jnp.clip(s_off + sum(z[i] * s_sl[i] for i in range(s_sl.shape[0])), 0.0, 1.0)
            ql, parent = limit_lengths(ql, level_min(min_len, level), level_value(max_len, level), parent)
            levels.append(SRVFLevel(q=ql, s=sl, mask=parent))
        base, scale = (None, None) if thick is None else thick
        tree = SRVFTree(
            q0=qa[:, :, 0].T,
            q=q,
            s=s,
            mask=real,
            origin=origin,
            base_radius=base,
            thickness_scale=scale,
            deeper=tuple(levels),
            virtual_main=virtual_main,
        )
        # With a thickness channel the curves come with radii: the general path.
        return to_curves(tree) if curves else tree

    if v.ndim == 1:
        return one(v)
    # A large sweep in one vmap streams every intermediate (~50 kB per root) through memory;
    # chunks of _SWEEP_CHUNK roots stay in cache (1,000 roots: 0.105 -> 0.065-0.085 ms each here).
    flat = v.reshape(-1, v.shape[-1])
    out = jax.lax.map(one, flat, batch_size=_SWEEP_CHUNK) if len(flat) > _SWEEP_CHUNK else jax.vmap(one)(flat)
    return jax.tree.map(lambda x: x.reshape(v.shape[:-1] + x.shape[1:]), out)


def _affine_map(pca: TangentPCA, M: np.ndarray):
    """``M`` composed with the PCA basis and un-whitened, in float64: the SRVF tree of
    ``[z; 1]`` is ``offset + Σ z_i slopes[i]`` (stacked ``(d, T, K+1)``) and its positions
    ``s_offset + Σ z_i s_slopes[i]`` (before clipping to [0, 1]); at depth D > 2 also one
    ``(q_offset, q_slopes, s_offset, s_slopes)`` per deeper level, in the level's own shapes."""
    f64 = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
    m = M.shape[0]
    # Rows sliced before the float64 copy: the basis is (components × p), p = (K+1)·T·d + K.
    components = np.asarray(pca.components)[:m].astype(np.float64)
    G = (M.T * np.sqrt(f64(pca.eigenvalues)[:m])) @ components  # (l+1, p) whitened
    mean, c = pca.mean, pca.scales
    T, C = mean.q0.shape  # C = d, or d + 1 with a thickness channel
    u = unflatten(G, T, mean.capacities, C)
    q0 = f64(u.q0) / f64(c.q0)  # (l+1, T, d)
    q = f64(u.q) / f64(c.q)  # (l+1, K, T, d)
    stacked = np.concatenate([q0[:, None], q], axis=1).transpose(0, 3, 2, 1)  # (l+1, d, T, K+1)
    base = np.concatenate([f64(mean.q0)[None], f64(mean.q)], axis=0).transpose(2, 1, 0)
    s = f64(u.s) / f64(c.s)
    deeper = []
    for lu, lc, lm in zip(u.deeper, c.deeper, mean.deeper):
        ql = f64(lu.q) / f64(lc.q)  # (l+1, K1, …, Kℓ, T, C)
        sl = f64(lu.s) / f64(lc.s)
        deeper.append((f64(lm.q) + ql[-1], ql[:-1], f64(lm.s) + sl[-1], sl[:-1]))
    return base + stacked[-1], stacked[:-1], f64(mean.s) + s[-1], s[:-1], tuple(deeper)


def _check_values(reg: "TraitRegression", values):
    # Host-side checks for host data (no device round trip); a traced array passes through.
    dtype = reg.matrix.dtype
    if np.iscomplexobj(values):
        raise TypeError("synthesize: trait values must be real numbers, got complex ones.")
    if isinstance(values, jax.core.Tracer):
        v = require_finite_values(values.astype(dtype), "synthesize: trait values")
    else:  # host data, or a concrete JAX array: checked here
        v = np.asarray(values, dtype=dtype)
        if not np.all(np.isfinite(v)):
            raise ValueError("trait values contain NaN or inf.")
    if v.ndim == 0 or v.shape[-1] != len(reg.names):
        raise ValueError(f"values must have shape (..., {len(reg.names)}) in the order {reg.names}, got {v.shape}.")
    return v


#: Requested values further than this many training standard deviations from the training
#: mean are named: the linear model is extrapolating there.
_EXTRAPOLATION_SD = 3.0


def _warn_extrapolation(reg: "TraitRegression", v: np.ndarray) -> None:
    mean, scale = np.asarray(reg.trait_mean), np.asarray(reg.trait_scale)
    z = np.abs(v - mean) / np.where(scale > 0, scale, np.inf)
    far = [
        f"{name} = {float(np.ravel(v[..., i])[np.argmax(np.ravel(z[..., i]))]):.4g} "
        f"({float(np.max(z[..., i])):.1f} SD from the training mean {float(mean[i]):.4g})"
        for i, name in enumerate(reg.names)
        if name not in reg.ignored and np.max(z[..., i]) > _EXTRAPOLATION_SD
    ]
    if far:
        warnings.warn(
            f"synthesize: requested values far outside the training roots: {'; '.join(far)}. The "
            "linear model extrapolates there; the roots it gives may be implausible and miss the "
            "requested values (measure them with rootshape_jax.traits).",
            ExtrapolationWarning,
            stacklevel=user_stacklevel(),
        )


def _synthesize_method(reg: "TraitRegression", values, *, srvf: bool = False) -> RootTree | SRVFTree:
    """Roots with the requested trait values (``(l,)`` for one root, ``(N, l)`` for a
    batch), in the order of `names`."""
    pc = reg.pca
    v = _check_values(reg, values)
    if not isinstance(v, jax.core.Tracer):
        _warn_extrapolation(reg, v)
    return _synthesize(
        reg.offset,
        reg.slopes,
        reg.s_offset,
        reg.s_slopes,
        pc.mean.origin,
        min_lengths(pc),
        pc.max_lateral_length,
        reg.trait_mean,
        reg.trait_scale,
        v,
        curves=not srvf,
        thick=None if pc.mean.thickness_scale is None else (pc.mean.base_radius, pc.mean.thickness_scale),
        deeper=reg.deeper,
        virtual_main=pc.mean.virtual_main,
    )


class _PlainMethod:
    """A method whose bound form is a `functools.partial`. Equinox turns every bound method of
    a Module into a `BoundMethod` Module (20–40 µs per attribute access), a cost that one
    regressed root (~0.1 ms, dispatch-bound) cannot carry."""

    def __init__(self, fn):
        self.fn = fn
        functools.update_wrapper(self, fn)

    def __get__(self, obj, objtype=None):
        return self.fn if obj is None else functools.partial(self.fn, obj)


class TraitRegression(eqx.Module):
    """Linear map from traits (and covariates) to PCA coefficients, ``b = M [z; 1]`` with
    standardised values ``z = (p − trait_mean) / trait_scale``.

    Build with `TraitRegression.fit`. **Fields**: `pca`; `matrix` ``M`` (``m × (l+1)``, the
    last column the intercept); `trait_mean`, `trait_scale` (``l``) the training values'
    mean and standard deviation; `names` — the traits then the covariates, the order of the
    values `synthesize` expects; `trait_names` — the measured ones; `ignored` — values that
    did not vary in training (their column of ``M`` is zero); `n_components` ``m``.

    The rest is the whole map from ``z`` to an SRVF tree, precomputed so that one root costs
    ``l`` multiply-adds per SRVF value: ``offset + Σ_i z_i slopes[i]`` stacked ``(d, T, K+1)``
    with the main root in slot 0 of the last axis, and likewise for the attachment positions.
    At depth D > 2, `deeper` holds ``(q_offset, q_slopes, s_offset, s_slopes)`` per deeper
    level, shaped like that level (``[K1, …, Kℓ, T, C]`` and ``[K1, …, Kℓ]``, slopes with a
    leading ``l``).
    """

    pca: TangentPCA
    matrix: Float[Array, "m l1"]
    trait_mean: Float[Array, " l"]
    trait_scale: Float[Array, " l"]
    offset: Float[Array, "d T K1"]
    slopes: Float[Array, "l d T K1"]
    s_offset: Float[Array, " K"]
    s_slopes: Float[Array, "l K"]
    names: tuple[str, ...] = eqx.field(static=True)
    trait_names: tuple[str, ...] = eqx.field(static=True)
    ignored: tuple[str, ...] = eqx.field(static=True)
    n_components: int = eqx.field(static=True)
    deeper: tuple = ()

    @classmethod
    def fit(
        cls,
        pca: TangentPCA,
        trees: RootTree | None = None,
        *,
        traits: Sequence[str] = PAPER_TRAITS,
        covariates=None,
        covariate_names: Sequence[str] | None = None,
        n_components: int | None = None,
    ) -> "TraitRegression":
        """Fit ``M = B Z⁺`` on the PCA's training roots (``Z = [z; 1]``, standardised traits).

        - `trees`: the training roots as a batched `RootTree`, in the order given to
          `karcher_mean` (their traits are measured with `rootshape_jax.traits`). Not needed
          when `traits` is empty.
        - `traits`: trait names (keys of `rootshape_jax.traits`); default the paper's three.
          A trait that does not vary across the training roots (main-root length after scale
          normalisation) cannot be regressed: it is ignored, with a warning.
        - `covariates`: optional ``(n, c)`` user covariates (e.g. treatment, soil humidity),
          with `covariate_names`.
        - `n_components`: PCA components regressed (default `pca.n_components`).
        """
        traits = (traits,) if isinstance(traits, str) else tuple(traits)  # one name is one trait
        n = pca.scores.shape[0]
        m = pca.n_components if n_components is None else as_count(n_components, "n_components")
        if not 1 <= m <= pca.components.shape[0]:
            raise ValueError(
                f"the regression needs 1 <= n_components <= {pca.components.shape[0]}, got {m} "
                "(a PCA of identical roots has no component to regress)."
            )
        columns = []
        if traits:
            if not isinstance(trees, RootTree) or trees.batch_shape != (n,):
                raise ValueError(
                    f"fit needs the {n} training roots as a batched RootTree (the trees given to "
                    "karcher_mean, converted with to_curves if they were SRVF trees)."
                )
            columns.append(_measure(trees, traits))
        names = list(traits)
        if covariates is not None:
            cov = _as_matrix(covariates, n, "covariates")
            columns.append(cov)
            if covariate_names is None:
                covariate_names = [f"covariate_{i}" for i in range(cov.shape[1])]
            if len(covariate_names) != cov.shape[1]:
                raise ValueError("covariate_names must name every covariate column.")
            names += list(covariate_names)
        if not names:
            raise ValueError("fit needs at least one trait or covariate.")
        p = np.concatenate(columns, axis=1)
        mu, sd, constant = _standardise(p)
        ignored = tuple(k for k, c in zip(names, constant) if c)
        if ignored:
            warnings.warn(
                f"trait(s) {ignored} do not vary across the training roots (e.g. main-root "
                "length after scale normalisation), so they cannot be regressed: synthesize "
                "ignores their values. Drop them from `traits` to silence this warning.",
                stacklevel=user_stacklevel(),
            )
        z = np.where(constant, 0.0, (p - mu) / sd)
        Z = np.concatenate([z, np.ones((n, 1))], axis=1).T  # (l+1, n)
        # Host arrays are sliced after the copy: an eager slice of a device array is a
        # dispatched JAX op (~50 µs each here), several times the arithmetic of this fit.
        B = np.asarray(pca.scores, dtype=np.float64)[:, :m].T  # (m, n)
        M = B @ np.linalg.pinv(Z)
        M[:, np.flatnonzero(constant)] = 0.0  # exactly, not 1e-17
        dtype = np.dtype(pca.mean.q0.dtype)
        *affine, deeper = _affine_map(pca, M)
        fields = (M, mu, sd, *affine)
        matrix, trait_mean, trait_scale, offset, slopes, s_offset, s_slopes = jax.device_put(
            tuple(np.asarray(x, dtype) for x in fields)
        )
        deeper = jax.device_put(jax.tree.map(lambda x: np.asarray(x, dtype), deeper))
        return cls(
            pca=pca,
            matrix=matrix,
            trait_mean=trait_mean,
            trait_scale=trait_scale,
            offset=offset,
            slopes=slopes,
            s_offset=s_offset,
            s_slopes=s_slopes,
            deeper=deeper,
            names=tuple(names),
            trait_names=traits,
            ignored=ignored,
            n_components=m,
        )

    def coefficients(self, values) -> Float[Array, "*N m"]:
        """PCA coefficients ``M [z; 1]`` for trait values ``(..., l)`` in the order of `names`."""
        z = (jnp.asarray(_check_values(self, values)) - self.trait_mean) / self.trait_scale
        ones = jnp.ones(z.shape[:-1] + (1,), z.dtype)
        return jnp.concatenate([z, ones], axis=-1) @ self.matrix.T

    synthesize = _PlainMethod(_synthesize_method)

    def report(self, trees: RootTree, *, covariates=None) -> dict:
        """How well synthesised roots reproduce requested traits, on (held-out) roots.

        The traits of `trees` are measured (plus their `covariates`), roots are synthesised
        from them, and the synthesised roots' traits are measured again. Returns a dict per
        measured trait: ``r2`` (coefficient of determination of synthesised vs requested;
        NaN when the requested values do not vary beyond rounding), ``mean_relative_error``,
        ``requested`` and ``synthesised`` arrays.
        """
        if not isinstance(trees, RootTree) or len(trees.batch_shape) != 1:
            raise ValueError("report needs a batched RootTree of roots.")
        n = trees.batch_shape[0]
        requested = _measure(trees, self.trait_names)
        values = [requested]
        if len(self.names) > len(self.trait_names):
            if covariates is None:
                raise ValueError(f"report needs the covariates {self.names[len(self.trait_names) :]}.")
            values.append(_as_matrix(covariates, n, "covariates"))
        with warnings.catch_warnings():  # held-out roots may lie outside: that is the report
            warnings.simplefilter("ignore", ExtrapolationWarning)
            synth = self.synthesize(np.concatenate(values, axis=1))
        got = _measure(synth, self.trait_names)
        out = {}
        for j, name in enumerate(self.trait_names):
            y, yhat = requested[:, j], got[:, j]
            ss = float(np.sum((y - y.mean()) ** 2))
            # Requested values constant up to rounding (e.g. main length after scale
            # normalisation): R² is undefined.
            varies = np.std(y) > 1e-6 * max(float(np.max(np.abs(y))), 1e-300)
            r2 = 1.0 - float(np.sum((yhat - y) ** 2)) / ss if varies else float("nan")
            scale = np.maximum(np.abs(y), 1e-12)
            out[name] = {
                "r2": r2,
                "mean_relative_error": float(np.mean(np.abs(yhat - y) / scale)),
                "requested": y,
                "synthesised": yhat,
            }
        return out
