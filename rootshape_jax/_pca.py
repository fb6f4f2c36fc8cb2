"""Tangent PCA at the Karcher mean, modes of variation and random synthesis (docs/design.md §6,
paper §4–5.1).

The shape space is flat in SRVF-tree coordinates (the pre-shape metric is a weighted L2
norm), so the tangent vector of sample i at the mean μ is ``registered_i − μ`` and the
exponential map is addition. Vectors are whitened by the metric, ``v = W^{1/2}(x − μ)``: √λm
and the trapezoid weights on the main root, √λs and the trapezoid weights on the laterals,
√λp on the attachment fractions. Euclidean geometry of the flattened ``v`` is then the
metric's own, ``|v_i|² = d²(μ, x_i)``. A null lateral of a sample sits at the mean's position,
so it adds no position difference, exactly as in the metric.
At depth D > 2 every deeper level's branches and attachments are blocks of their own, whitened
with that level's weights, and the length limits below are taken level by level.

Following the paper, the covariance is ``(1/(n−1)) Σ v_i v_iᵀ`` (tangent vectors at the
Karcher mean average to zero, so no further centring), computed by an SVD of the ``n × p``
data matrix (through its ``n × n`` Gram matrix). A root is synthesised as
``μ + Σ_i b_i √σ_i Λ_i`` and mapped back to curves;
its laterals shorter than a threshold are nulls, laterals longer than the data's longest are
scaled down to it, attachment fractions are clipped to [0, 1].

Plausibility (`rootshape_jax.plausibility`): by default the synthesised laterals keep within
the data's lateral-length range: shorter than the data's 10th percentile of lateral lengths,
a lateral is dropped (the mean's slots that few samples reach are short, and their variation
makes many short laterals that the data does not have); longer than the data's longest, it is
scaled down to that length. Measured on the bundled 53 roots (T = 50): random roots with every
lateral in range 84 % → 100 %, ±2σ along modes 1–5 90 % → 100 %; KS statistic of the pooled
lateral lengths against the data 0.29 → 0.16 (random roots; 0.18 with the exception below).
See BENCHMARKS.md. The Karcher mean's own laterals are the exception: averaging shrinks them,
and below the percentile they would vanish from the mean itself (zero coefficients), so each
stays real down to its length in the mean (which can be below the data's shortest lateral).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._curves import l2_norm_squared
from ._engine import RegistrationOptions, registration_options
from ._errors import InputError, as_count, is_real_scalar, require_finite_values
from ._executor import LocalExecutor
from ._mean import KarcherMean, register_onto
from ._metric import Weights, system_weights
from ._tangent import TreeParams, exp_map, flatten, level_value, log_map, params_of, whiten, whitening
from ._tree import RootTree, SRVFTree, check_compatible, to_curves, to_srvf


class TangentPCA(eqx.Module):
    """Principal modes of variation in the tangent space at the Karcher mean.

    **Fields**

    - `mean`: the point of tangency, an `SRVFTree` with every slot real (as fitted).
    - `components`: ``[m, p]`` orthonormal principal directions ``Λ_i`` in whitened,
      flattened coordinates (``m = min(n, p)``), by decreasing eigenvalue.
    - `eigenvalues`: ``[m]`` variances ``σ_i`` (covariance ``VᵀV / (n − 1)``).
    - `explained_variance_ratio`: ``[m]`` ``σ_i / Σσ``.
    - `scores`: ``[n, m]`` standardised coefficients ``b_i = <v, Λ_i> / √σ_i`` of the samples
      (0 where ``σ_i = 0``). The tangent vectors are not re-centred (the Karcher mean is their
      centre up to its tolerance), so the last component, of variance near 0, is their small
      average left by that tolerance: every sample scores about √((n − 1)/n) on it.
    - `n_components`: leading components explaining at least `variance` of the total
      (static; 0 when the samples do not vary beyond rounding: total variance below
      ``(10⁴ ε)² |W^{1/2} μ|²``).
    - `scales`: whitening factors per block (main, laterals, positions; per deeper level).
    - `weights`: the metric weights. `min_lateral_length`: synthesised laterals shorter than
      this are nulls; `max_lateral_length`: longer ones are scaled down to it (inf: never).
      At depth D > 2 both hold one value per branch level ``[D − 1]`` (first-order laterals
      first), or one value for every level.
    - `slot_min_lengths`: with the default `min_lateral_length`, the thresholds applied, one
      array per level with one value per slot: `min_lateral_length`, lowered in the Karcher
      mean's own laterals to their length in the mean and raised in the laterals it dropped
      above their length in the fitted mean, so that zero coefficients give the mean
      (`KarcherMean.mean_srvf`) exactly. ``()`` when `min_lateral_length` was given.
    """

    mean: SRVFTree
    components: Float[Array, "m p"]
    eigenvalues: Float[Array, " m"]
    explained_variance_ratio: Float[Array, " m"]
    scores: Float[Array, "n m"]
    scales: TreeParams
    weights: Weights
    registration: RegistrationOptions
    min_lateral_length: Float[Array, "*L"]
    max_lateral_length: Float[Array, "*L"]
    n_components: int = eqx.field(static=True)
    variance: float = eqx.field(static=True)
    slot_min_lengths: tuple[Array, ...] = ()


def min_lengths(pc: TangentPCA) -> Array | tuple[Array, ...]:
    """The lateral-length thresholds `reconstruct` applies: per slot (`slot_min_lengths`)
    with the default `min_lateral_length`, else the value given."""
    return pc.slot_min_lengths or pc.min_lateral_length


@eqx.filter_jit
def _fit(registered: SRVFTree, mean: SRVFTree, weights: Weights):
    T = mean.q0.shape[0]
    # A plant's axes are whitened as main roots, as the engine weighs them (§11).
    c = whitening(system_weights(weights, mean), T, mean.q0.dtype, depth=mean.depth)
    V = log_map(registered, mean, c)
    n = V.shape[0]
    # SVD through the n × n Gram matrix: n (roots) is far smaller than p (coordinates), and
    # XLA:CPU's SVD of a wide matrix is slow (seconds at 53 × 12,260; the Gram route takes ms).
    w, U = jnp.linalg.eigh(V @ V.T)
    w, U = w[::-1], U[:, ::-1]
    S2 = jnp.maximum(w, 0.0)
    S = jnp.sqrt(S2)
    Vt = (U.T @ V) / jnp.where(S > 0, S, 1.0)[:, None]
    eig = S2 / max(n - 1, 1)
    total = jnp.sum(eig)
    ratio = jnp.where(total > 0, eig / jnp.where(total > 0, total, 1.0), 0.0)
    scores = _scores(V, Vt, eig)
    mean_norm2 = jnp.sum(flatten(whiten(params_of(mean), c)) ** 2)
    # The data's branch lengths, level by level (registration keeps every branch's length).
    limits = [_length_limits(registered.q, registered.mask, mean)]
    limits += [_length_limits(lv.q, lv.mask, mean) for lv in registered.deeper]
    if registered.deeper:
        threshold, longest = (jnp.stack(x) for x in zip(*limits))
    else:
        threshold, longest = limits[0]
    return c, Vt, eig, ratio, scores, mean_norm2, threshold, longest


def _length_limits(q, mask, mean):
    """The 10th percentile and the largest of the real branches' lengths; without any,
    2 % of the mean's main-root length and inf."""
    lengths = l2_norm_squared(q)
    any_real = jnp.any(mask)
    low = jnp.nanquantile(jnp.where(mask, lengths, jnp.nan), 0.1)
    high = jnp.max(jnp.where(mask, lengths, -jnp.inf))
    threshold = jnp.where(any_real, low, 0.02 * l2_norm_squared(mean.q0))
    longest = jnp.where(any_real, high, jnp.inf)
    return threshold, longest


def _scores(V, Vt, eig):
    proj = V @ Vt.T
    ok = eig > 0
    return jnp.where(ok, proj / jnp.sqrt(jnp.where(ok, eig, 1.0)), 0.0)


def _count(ratio, eigenvalues, scale: float, eps: float, variance: float) -> int:
    ratio = np.asarray(ratio, dtype=np.float64)
    # Variance at rounding level (identical roots) is no variation at all.
    if float(np.sum(eigenvalues)) <= (1e4 * eps) ** 2 * scale or ratio.sum() <= 0:
        return 0
    cum = np.cumsum(ratio)
    # Smallest m with cumulative ratio >= variance (tolerant of rounding at 100 %).
    return int(min(np.searchsorted(cum, variance - 1e-12) + 1, len(ratio)))


def tangent_pca(
    mean: KarcherMean,
    *,
    variance: float = 0.99,
    min_lateral_length: float | None = None,
    max_lateral_length: float | None = None,
) -> TangentPCA:
    """Tangent PCA of the samples of a `karcher_mean` result.

    - `variance`: keep the leading components whose cumulative explained variance reaches
      this fraction (the paper's 99 %); `n_components` reports how many.
    - `min_lateral_length`: laterals of synthesised roots shorter than this are nulls;
      default the 10th percentile of the samples' lateral lengths (module docstring; 2 % of
      the mean's main-root length when no sample has a lateral), except in the Karcher mean's
      own laterals, which stay real down to their length in the mean (and its dropped ones
      null up to theirs), so that zero coefficients give the mean (`slot_min_lengths`).
    - `max_lateral_length`: laterals of synthesised roots longer than this are scaled down to
      it; default the samples' longest lateral (``float("inf")`` turns it off).

    At depth D > 2 the defaults are taken level by level (second-order laterals against the
    samples' second-order laterals, ...); a value given applies to every level, and a
    synthesised branch that becomes a null drops its children.
    """
    if not isinstance(mean, KarcherMean):
        raise TypeError(f"tangent_pca expects the result of karcher_mean, got {type(mean).__name__}.")
    if not 0 < variance <= 1:
        raise ValueError(f"variance must be in (0, 1], got {variance!r}.")
    # The tangent point is the fitted mean (every slot real), where the samples were registered.
    mu = mean.fitted
    dtype = mu.q0.dtype
    c, Vt, eig, ratio, scores, mean_norm2, default_threshold, default_longest = _fit(mean.registered, mu, mean.weights)
    if min_lateral_length is None:
        threshold = default_threshold
        slots = _keep_the_means_laterals(mean, threshold)
    else:
        if not np.all(np.asarray(min_lateral_length, dtype=np.float64) >= 0):  # NaN fails too
            raise ValueError(f"min_lateral_length must be >= 0, got {min_lateral_length!r}.")
        threshold = jnp.asarray(min_lateral_length, dtype)
        slots = ()
    if max_lateral_length is None:
        longest = default_longest
    else:
        if not np.all(np.asarray(max_lateral_length, dtype=np.float64) > 0):
            raise ValueError(f"max_lateral_length must be positive, got {max_lateral_length!r}.")
        longest = jnp.asarray(max_lateral_length, dtype)
    if (
        min_lateral_length is not None
        and max_lateral_length is not None
        and np.any(np.asarray(min_lateral_length, dtype=np.float64) > np.asarray(max_lateral_length, dtype=np.float64))
    ):
        raise ValueError(
            f"min_lateral_length ({min_lateral_length!r}) is above max_lateral_length ({max_lateral_length!r}): "
            "every synthesised lateral would be dropped or cut."
        )
    ratio_np, eig_np = jax.device_get((ratio, eig))
    return TangentPCA(
        mean=mu,
        components=Vt,
        eigenvalues=eig,
        explained_variance_ratio=ratio,
        scores=scores,
        scales=c,
        weights=mean.weights,
        registration=mean.registration,
        min_lateral_length=threshold,
        max_lateral_length=longest,
        n_components=_count(ratio_np, eig_np, float(mean_norm2), float(jnp.finfo(dtype).eps), variance),
        variance=float(variance),
        slot_min_lengths=slots,
    )


# Relative margin of the per-slot thresholds around the mean's own lateral lengths.
_LENGTH_MARGIN = 1e-4


def _keep_the_means_laterals(mean: KarcherMean, threshold: Array) -> tuple[Array, ...]:
    """Per-slot thresholds from the level thresholds: a lateral the Karcher mean kept stays
    real down to its own length in the mean, one it dropped stays a null up to its length in
    the fitted mean, so that ``reconstruct(pc, 0)`` is the mean itself. (The data's 10th
    percentile can exceed a mean's laterals: averaging shrinks them, and RootNav's mean kept 8
    laterals where the percentile alone left 3.)"""
    out = []
    # From the trees themselves (every level, however the result was built): the fitted mean's
    # lengths and the slots `mean_srvf` dropped.
    fitted = (mean.fitted.q, *(lv.q for lv in mean.fitted.deeper))
    kept = (mean.mean_srvf.mask, *(lv.mask for lv in mean.mean_srvf.deeper))
    for level, (q, mask) in enumerate(zip(fitted, kept), start=1):
        lengths, dropped = l2_norm_squared(q), ~mask
        thr = level_value(threshold, level)
        # A relative margin: `reconstruct` measures the lengths again inside its compiled
        # program, which can round them a step the other way (10-15 % of slots, measured).
        # (A kept slot of zero length, as in a hand-built mean, is no lateral: the level's value.)
        kept_below = jnp.where(lengths > 0, jnp.minimum(thr, lengths * (1 - _LENGTH_MARGIN)), thr)
        out.append(jnp.where(dropped, jnp.maximum(thr, lengths * (1 + _LENGTH_MARGIN)), kept_below))
    return tuple(out)


# --------------------------------------------------------------------------------------------
# Back to roots


def _to_tree(pc: TangentPCA, v: Array) -> SRVFTree:
    """SRVF trees ``μ + W^{-1/2} v`` for flattened whitened tangent vectors v (batched)."""
    return exp_map(pc.mean, pc.scales, min_lengths(pc), v, pc.max_lateral_length)


@eqx.filter_jit
def _reconstruct(pc: TangentPCA, coefficients: Array) -> tuple[SRVFTree, RootTree]:
    m = coefficients.shape[-1]
    # Scale the coefficients, not the (m, p) basis: one small product per root.
    t = _to_tree(pc, (coefficients * jnp.sqrt(pc.eigenvalues[:m])) @ pc.components[:m])
    return t, to_curves(t)


def reconstruct(pc: TangentPCA, coefficients, *, srvf: bool = False) -> RootTree | SRVFTree:
    """Roots ``μ + Σ_i b_i √σ_i Λ_i`` from standardised coefficients ``b`` (``[..., m]``, the
    first m components; m <= number of components). Returns a (batched) `RootTree`, or the
    `SRVFTree` with ``srvf=True``."""
    dtype = pc.mean.q0.dtype
    if np.iscomplexobj(coefficients):
        raise TypeError("reconstruct: coefficients must be real numbers, got complex ones.")
    b = require_finite_values(jnp.asarray(coefficients, dtype), "reconstruct: coefficients")
    if b.ndim == 0 or b.shape[-1] > pc.components.shape[0]:
        raise ValueError(f"coefficients must have shape (..., m) with m <= {pc.components.shape[0]}, got {b.shape}.")
    t, curves = _reconstruct(pc, b)
    if not isinstance(b, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(curves.main))):
        # Finite coefficients so large that the roots' coordinates overflow the dtype.
        raise InputError(
            f"reconstruct: coefficients up to {float(jnp.max(jnp.abs(b))):.3g} standard deviations give "
            f"roots whose coordinates overflow {dtype}; the data span a few standard deviations."
        )
    return t if srvf else curves


def modes(pc: TangentPCA, alphas: Sequence[float] | Array, *, component: int | Sequence[int] = 0) -> RootTree:
    """Roots along principal mode(s): ``μ + α √σ_i Λ_i`` for each α in `alphas`.

    One `component` gives a batched `RootTree` of shape ``(len(alphas),)``; a sequence of
    components gives shape ``(len(components), len(alphas))``.
    """
    alphas = jnp.asarray(alphas, pc.mean.q0.dtype).reshape(-1)
    single = np.ndim(component) == 0
    given = [component] if single else list(component) if np.ndim(component) == 1 else []
    if not given or not all(is_real_scalar(c, "iu") for c in given):  # numpy and JAX integers too
        raise ValueError(f"modes: component must be an integer or a sequence of integers, got {component!r}.")
    comps = [int(c) for c in given]
    m = pc.components.shape[0]
    for c in comps:
        if not 0 <= c < m:
            raise ValueError(f"component {c} is out of range: the PCA has {m} components.")
    top = max(comps) + 1
    b = jnp.zeros((len(comps), alphas.shape[0], top), alphas.dtype)
    for i, c in enumerate(comps):
        b = b.at[i, :, c].set(alphas)
    out = reconstruct(pc, b)
    return jax.tree.map(lambda x: x[0], out) if single else out


def sample(
    pc: TangentPCA,
    key: PRNGKeyArray,
    n: int,
    *,
    truncate: float | None = None,
    n_components: int | None = None,
    srvf: bool = False,
) -> RootTree | SRVFTree:
    """`n` random roots: ``b ~ N(0, I)`` on the kept components (`pc.n_components`, or
    `n_components`), optionally truncated to ``[−truncate, truncate]`` (a truncated normal),
    mapped through `reconstruct`. Laterals shorter than their threshold are nulls
    (`pc.slot_min_lengths` by default, else `pc.min_lateral_length`; see `tangent_pca`)."""
    n = as_count(n, "n")
    _check_key(key)
    m = pc.n_components if n_components is None else as_count(n_components, "n_components", minimum=0)
    if not 0 <= m <= pc.components.shape[0]:
        raise ValueError(f"n_components must be in [0, {pc.components.shape[0]}], got {m}.")
    if truncate is not None and not truncate > 0:
        raise ValueError(f"truncate must be positive, got {truncate!r}.")
    t, curves = _sample(pc, key, n, m, None if truncate is None else float(truncate))
    return t if srvf else curves


def _check_key(key) -> None:
    """`TypeError` unless `key` is a JAX random key: a typed key (`jax.random.key`) or a legacy
    uint32 key (`jax.random.PRNGKey`: 2 words, 4 with the "rbg" generator)."""
    if isinstance(key, jax.core.Tracer):
        return
    dtype, shape = getattr(key, "dtype", None), getattr(key, "shape", None)
    typed = dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key) and shape == ()
    legacy = dtype == np.uint32 and shape in ((2,), (4,))  # threefry, rbg
    if not (typed or legacy):
        raise TypeError(f"key must be one JAX random key, e.g. jax.random.key(0), got {key!r}.")


@eqx.filter_jit
def _sample(pc: TangentPCA, key, n: int, m: int, truncate: float | None):
    dtype = pc.mean.q0.dtype
    if truncate is None:
        b = jax.random.normal(key, (n, m), dtype)
    else:
        b = jax.random.truncated_normal(key, -truncate, truncate, (n, m), dtype)
    return _reconstruct(pc, b)


@eqx.filter_jit
def _project(pc: TangentPCA, x: SRVFTree, opts):
    registered, energies, _ = register_onto(pc.mean, x, pc.weights, opts)
    V = log_map(registered, pc.mean, pc.scales)
    return _scores(V, pc.components, pc.eigenvalues), energies


# Roots per block of `project`: a block of large roots (pea, K = 54) registers in seconds, so
# the progress bar moves at least every few seconds; blocks run on worker threads.
PROJECT_BLOCK = 4


def project_block(idx, n_valid: int, pc: TangentPCA, x: SRVFTree, opts) -> dict:
    """Coefficients of the rows `idx` of `x` (padded to one block size, so one compilation
    serves every block); the first `n_valid` rows are real."""
    b, _ = _project(pc, jax.tree.map(lambda a: a[idx], x), opts)
    return {"b": np.asarray(b)[:n_valid]}


def project(
    pc: TangentPCA,
    trees: RootTree | SRVFTree,
    *,
    n_components: int | None = None,
    registration: RegistrationOptions | dict | None = None,
    progress: bool = True,
    block_size: int = PROJECT_BLOCK,
) -> Float[Array, "n m"]:
    """Standardised coefficients ``b`` of roots: each is registered onto the mean (options of
    `register` in `registration`) and its tangent vector projected on the first
    `n_components` (default `pc.n_components`) directions, divided by ``√σ_i``. A single tree
    gives shape ``(m,)``. Registration options default to those the mean used.

    More than `block_size` roots are registered in blocks of that many, on worker threads
    (every core), with a progress bar (`progress`) that moves after every block.

    The tangent space is at the fitted mean (`KarcherMean.fitted`: every lateral slot real),
    while `reconstruct`, `modes` and `sample` turn laterals shorter than their threshold into
    nulls (`TangentPCA.slot_min_lengths`). So a synthesised root projects back onto its
    coefficients only approximately, and ``project(pc, km.mean_srvf)`` (short laterals
    dropped) is not exactly 0; with ``tangent_pca(..., min_lateral_length=0,
    max_lateral_length=float("inf"))`` nothing is dropped or shortened and the round trip
    holds to the registration's accuracy."""
    x = to_srvf(trees, weights=pc.weights)
    single = x.batch_shape == ()
    if single:
        x = jax.tree.map(lambda a: a[None], x)
    if len(x.batch_shape) != 1:
        raise ValueError(f"project: expected one tree or a batch, got batch shape {x.batch_shape}.")
    check_compatible(pc.mean, x, "project: the PCA's mean and trees")
    opts = registration_options(registration, base=pc.registration)
    block_size = as_count(block_size, "project: block_size")
    n = x.batch_shape[0]
    if n <= block_size or isinstance(x.q0, jax.core.Tracer):
        b, _ = _project(pc, x, opts)
    else:
        starts = range(0, n, block_size)
        blocks = [(np.minimum(np.arange(a, a + block_size), n - 1), min(block_size, n - a)) for a in starts]
        results, _ = LocalExecutor().map_blocks(
            project_block,
            blocks,
            shared=(pc, x, opts),
            sizes=[v for _, v in blocks],
            progress=progress,
            desc="projecting onto the modes",
            unit="root",
        )
        b = jnp.asarray(np.concatenate([r["b"] for r in results]))
    m = pc.n_components if n_components is None else as_count(n_components, "project: n_components", minimum=0)
    if m > pc.components.shape[0]:
        raise ValueError(f"project: n_components must be in [0, {pc.components.shape[0]}], got {m}.")
    b = b[:, :m]
    return b[0] if single else b
