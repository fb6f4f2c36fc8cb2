"""Trait-controlled root synthesis: linear regression from traits to PCA coefficients
(DESIGN.md §6, paper §5.2).

Each training root has standardised PCA coefficients ``b`` (`TangentPCA.scores`, the kept
components) and a trait vector ``p`` — by default the paper's main-root length, mean lateral
length and standard deviation of lateral lengths (`rootshape_jax.traits`), plus any user
covariates. With ``P = [p; 1]`` (``(l+1) × n``) and ``B`` (``m × n``) the map is
``M = B P⁺``; a root with traits p is synthesised as ``reconstruct(pca, M [p; 1])``.
`TraitRegression.report` measures the traits of synthesised roots and compares them with the
requested ones.
"""

from __future__ import annotations

from collections.abc import Sequence

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._pca import TangentPCA, _tangent_to_tree
from ._traits import traits as measure_traits
from ._tree import RootTree, SRVFTree, to_curves, to_roots

PAPER_TRAITS: tuple[str, ...] = ("main_length", "mean_lateral_length", "std_lateral_length")


def _measure(trees: RootTree, names: Sequence[str]) -> np.ndarray:
    if not names:
        n = 1 if trees.batch_shape == () else trees.batch_shape[0]
        return np.zeros((n, 0))
    rows = measure_traits(to_roots(trees))
    for k in names:
        if k not in rows[0]:
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


@functools.partial(jax.jit, static_argnames="curves")
def _synthesize(mean, scales, min_lateral_length, G, v, curves: bool):
    # Plain jax.jit on the arrays it needs rather than the whole PCA Module: fewer leaves to
    # flatten per call (one regressed root still costs ~0.5 ms, mostly small XLA:CPU kernels).
    t = _tangent_to_tree(mean, scales, min_lateral_length, v @ G[:-1] + G[-1])
    return to_curves(t) if curves else t


@eqx.filter_jit
def _compose(M, components, eigenvalues):
    """``Mᵀ`` composed with the PCA basis ``√σ_i Λ_i``: an ``(l+1) × p`` matrix."""
    m = M.shape[0]
    return (M.T * jnp.sqrt(eigenvalues[:m])) @ components[:m]


class TraitRegression(eqx.Module):
    """Linear map from traits (and covariates) to PCA coefficients, ``b = M [p; 1]``.

    Build with `TraitRegression.fit`. **Fields**: `pca`; `matrix` ``M`` (``m × (l+1)``, the
    last column the intercept); `linear` — ``Mᵀ`` composed with the PCA basis
    (``(l+1) × p``), the whole map from ``[p, 1]`` to the whitened tangent vector, so that one
    root costs one small product; `names` — the traits then the covariates, the order of the
    values `synthesize` expects; `trait_names` — the measured ones; `n_components` ``m``.
    """

    pca: TangentPCA
    matrix: Float[Array, "m l1"]
    linear: Float[Array, "l1 p"]
    names: tuple[str, ...] = eqx.field(static=True)
    trait_names: tuple[str, ...] = eqx.field(static=True)
    n_components: int = eqx.field(static=True)

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
        """Fit ``M = B P⁺`` on the PCA's training roots.

        - `trees`: the training roots as a batched `RootTree`, in the order given to
          `karcher_mean` (their traits are measured with `rootshape_jax.traits`). Not needed
          when `traits` is empty.
        - `traits`: trait names (keys of `rootshape_jax.traits`); default the paper's three.
        - `covariates`: optional ``(n, c)`` user covariates (e.g. treatment, soil humidity),
          with `covariate_names`.
        - `n_components`: PCA components regressed (default `pca.n_components`).
        """
        traits = tuple(traits)
        n = pca.scores.shape[0]
        m = pca.n_components if n_components is None else int(n_components)
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
        P = np.concatenate([p, np.ones((n, 1))], axis=1).T  # (l+1, n)
        B = np.asarray(pca.scores[:, :m], dtype=np.float64).T  # (m, n)
        M = jnp.asarray(B @ np.linalg.pinv(P), pca.mean.q0.dtype)
        return cls(
            pca=pca,
            matrix=M,
            linear=_compose(M, pca.components, pca.eigenvalues),
            names=tuple(names),
            trait_names=traits,
            n_components=m,
        )

    def coefficients(self, values) -> Float[Array, "*N m"]:
        """PCA coefficients ``M [p; 1]`` for trait values ``(..., l)`` in the order of `names`."""
        v = jnp.asarray(values, self.matrix.dtype)
        if v.ndim == 0 or v.shape[-1] != len(self.names):
            raise ValueError(
                f"values must have shape (..., {len(self.names)}) in the order {self.names}, "
                f"got {v.shape}."
            )
        ones = jnp.ones(v.shape[:-1] + (1,), v.dtype)
        return jnp.concatenate([v, ones], axis=-1) @ self.matrix.T

    def synthesize(self, values, *, srvf: bool = False) -> RootTree | SRVFTree:
        """Roots with the requested trait values (``(l,)`` for one root, ``(N, l)`` for a
        batch), in the order of `names`."""
        v = jnp.asarray(values, self.matrix.dtype)
        if v.ndim == 0 or v.shape[-1] != len(self.names):
            raise ValueError(
                f"values must have shape (..., {len(self.names)}) in the order {self.names}, "
                f"got {v.shape}."
            )
        pc = self.pca
        return _synthesize(pc.mean, pc.scales, pc.min_lateral_length, self.linear, v, curves=not srvf)

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
                raise ValueError(f"report needs the covariates {self.names[len(self.trait_names):]}.")
            values.append(_as_matrix(covariates, n, "covariates"))
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
