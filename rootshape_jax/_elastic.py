"""Elastic shape distance between two open curves (SRVF framework; docs/design.md §3, §4).

``d(β1, β2) = min_{O ∈ SO(d), γ} ||q1 − O (q2∘γ)√γ'||``, minimised by alternating the two
exact partial problems: for a fixed rotation, the DP warp (`dp_warp`); for a fixed warp, weighted
Kabsch (`kabsch`) on the very quadrature that defines the energy (`warp_samples`).
Each step can only lower the energy, so the alternation is monotone. The problem is not
convex, so it is started twice — from the identity (the result is then never worse than
without rotation) and from the rotation aligning the unwarped SRVFs — and continued from the
better start until a rotation step lowers the energy by less than ``rtol`` (relative) or
``max_iterations`` alternation steps are done.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._curves import l2_norm_squared, real_coordinates, require_finite, resample_curve, srvf
from ._devices import split_over_devices
from ._errors import InvalidRootError, as_count, as_flag
from ._executor import LocalExecutor
from ._rotation import kabsch
from ._warp import check_neighbourhood, dp_warp_if, warp_samples, warp_samples_unchecked


class CurveRegistration(eqx.Module):
    """Result of `elastic_curve_distance` (β2 registered onto β1).

    - `distance`: ``sqrt(energy)``, the elastic (SRVF L2) distance.
    - `energy`: ``∫|q1 − O (q2∘γ)√γ'|²`` at the optimum (`warp_energy`'s discretisation).
    - `rotation`: ``O`` (d×d, det +1), applied to β2 (``β2 @ O.T``).
    - `gamma`: the warp of β2 on the grid ``linspace(0, 1, n_samples)``; the registered curve
      is ``apply_warp_curve(resample_curve(β2, n_samples) @ O.T, gamma)`` (divided by its
      length when ``scale=True``).
    - `n_iterations`: number of DP solves performed (with rotation: two starts + further
      alternation steps).

    With ``scale=True`` (unit-length curves) ``||q1|| = ||q2|| = 1`` and the geodesic distance
    on the pre-shape sphere is ``2·arcsin(distance / 2)``.
    """

    distance: Float[Array, ""]
    energy: Float[Array, ""]
    rotation: Float[Array, "d d"]
    gamma: Float[Array, " T"]
    n_iterations: Int[Array, ""]


def _check_curve(beta, name: str):
    beta = real_coordinates(beta, f"elastic_curve_distance: {name}")
    if beta.ndim != 2 or beta.shape[0] < 2:
        raise InvalidRootError(
            f"elastic_curve_distance: {name} must be an (n_points, d) polyline with n_points >= 2, "
            f"got shape {beta.shape}. Use jax.vmap for batches of curves."
        )
    return eqx.error_if(beta, ~jnp.all(jnp.isfinite(beta)), f"elastic_curve_distance: {name} contains NaN or inf.")


def _unit(q: Array) -> Array:
    n2 = l2_norm_squared(q)
    ok = n2 > 0
    return q / jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1)), 1)


def _register(q1, q2, *, rotation: bool, neighbourhood: int, max_iterations, rtol):
    """Alternating minimisation; returns (O, gamma, energy, n_iterations), no gradients.

    ``max_iterations`` and ``rtol`` may be traced (they do not trigger recompilation).
    """
    dtype = q1.dtype
    d = q1.shape[-1]
    eye = jnp.eye(d, dtype=dtype)

    def rotation_step(gamma, O_used):
        # The energy is Σ w·(|A − O·B|² at both interval ends)/2, a weighted Procrustes
        # problem in O: its Kabsch solution is exact for this γ. Also returns the energy at
        # the rotation the DP used, to measure what the rotation step gained.
        A, B, w = warp_samples_unchecked(q1, q2, gamma)  # γ comes from the DP: no checks needed
        O = kabsch(A, B, w) if rotation else eye

        def energy(R):
            diff = A - B @ R.T
            return jnp.sum(w * 0.5 * jnp.sum(diff * diff, axis=(1, 2)))

        return O, energy(O), energy(O_used)

    # Two starting points, each one DP + one rotation step: the identity (so the result is
    # never worse than without rotation) and the rotation aligning the unwarped SRVFs; the
    # alternation continues from the better. It stops when the rotation step of the best
    # state gained less than rtol (relative): γ is then DP-optimal for (nearly) the final
    # rotation, and another DP would gain about as little. Without rotation one DP is exact.
    O_kabsch = kabsch(q1, q2) if rotation else eye
    cap = max_iterations + 1 if rotation else 1
    forced = 2 if rotation else 1

    def cond(state):
        i, _, _, _, energy, gain = state
        return (i < forced) | ((i < cap) & (gain > rtol * energy))

    def body(state):
        i, O_next, O, gamma, energy, gain = state
        # Under vmap, lanes that have stopped are skipped by the DP's batching rule.
        gamma_new = dp_warp_if(q1, q2 @ O_next.T, cond(state), neighbourhood=neighbourhood)[0]
        O_new, energy_new, energy_at_dp = rotation_step(gamma_new, O_next)
        # Monotone in exact arithmetic after the starts; keep the best in any case.
        better = energy_new <= energy
        O = jnp.where(better, O_new, O)
        gamma = jnp.where(better, gamma_new, gamma)
        # A worse second start leaves the first one to continue; later, no gain means stop.
        gain = jnp.where(better, energy_at_dp - energy_new, jnp.where(i == 1, gain, 0))
        O_next = jnp.where(i == 0, O_kabsch, O)
        return i + 1, O_next, O, gamma, jnp.minimum(energy, energy_new), gain

    # Every DP runs inside the loop, so the DP kernel is compiled once.
    inf = jnp.asarray(jnp.inf, dtype)
    identity = jnp.linspace(0, 1, q1.shape[0], dtype=dtype)
    init = (jnp.asarray(0, jnp.int32), eye, eye, identity, inf, inf)
    n_it, _, O, gamma, energy, _ = jax.lax.while_loop(cond, body, init)
    return O, gamma, energy, n_it


def _check_options(n_samples, max_iterations, rtol, neighbourhood) -> tuple[int, int]:
    """The counts as Python ints (numpy integers would be traced as static options)."""
    n_samples = as_count(n_samples, "n_samples", minimum=2)
    max_iterations = as_count(max_iterations, "max_iterations")
    if not isinstance(rtol, (int, float)) or not rtol >= 0:
        raise ValueError(f"rtol must be a float >= 0, got {rtol!r}.")
    check_neighbourhood(neighbourhood)
    return n_samples, max_iterations


def elastic_curve_distance(
    beta1: Float[ArrayLike, "n1 d"],
    beta2: Float[ArrayLike, "n2 d"],
    *,
    rotation: bool = True,
    scale: bool = False,
    n_samples: int = 100,
    neighbourhood: int = 7,
    max_iterations: int = 10,
    rtol: float = 1e-4,
) -> CurveRegistration:
    """Elastic distance between two open curves, with the optimal rotation and warp.

    **Arguments**

    - `beta1`, `beta2`: polylines of shape ``(n_points, d)``, d = 2 or 3 (the point counts may
      differ). Translation never matters (SRVFs ignore it).
    - `rotation`: also minimise over rotations ``O ∈ SO(d)`` (alternating with the warp).
    - `scale`: rescale both curves to unit length first (a scale-invariant shape distance);
      off, curve size counts (growth studies).
    - `n_samples`: points of the arc-length resampling, ``T`` (static: one compile per value).
    - `neighbourhood`: DP move size (static; 7 by default, fdasrsf uses 10).
    - `max_iterations`: cap on the rotation/warp alternation steps (one DP solve each, plus
      one DP for the second starting point; not static).
    - `rtol`: stop once a rotation step lowers the energy by less than this fraction (not
      static).

    **Returns** a `CurveRegistration`. Gradients of `distance`/`energy` with respect to the
    curves follow the envelope theorem (the registration is held fixed). Works under
    `jax.vmap` for curves that share a shape; compiled once per shapes, dtype and static
    options.
    """
    n_samples, max_iterations = _check_options(n_samples, max_iterations, rtol, neighbourhood)
    beta1 = real_coordinates(beta1, "elastic_curve_distance: beta1")
    beta2 = real_coordinates(beta2, "elastic_curve_distance: beta2")
    require_finite(beta1, "elastic_curve_distance: beta1")  # concrete input; traced: eqx.error_if
    require_finite(beta2, "elastic_curve_distance: beta2")
    return _elastic_curve_distance(
        beta1,
        beta2,
        jnp.asarray(max_iterations, jnp.int32),
        jnp.asarray(rtol),
        rotation=as_flag(rotation, "rotation"),
        scale=as_flag(scale, "scale"),
        n_samples=n_samples,
        neighbourhood=int(neighbourhood),
    )


def _curve_distance(beta1, beta2, max_iterations, rtol, *, rotation, scale, n_samples, neighbourhood):
    beta1 = _check_curve(beta1, "beta1")
    beta2 = _check_curve(beta2, "beta2")
    if beta1.shape[1] != beta2.shape[1]:
        raise InvalidRootError(
            f"elastic_curve_distance: both curves need the same dimension d, got {beta1.shape[1]} and {beta2.shape[1]}."
        )
    d = beta1.shape[1]
    if rotation and d not in (2, 3):
        raise InvalidRootError(f"elastic_curve_distance: rotation=True needs curves in 2D or 3D, got d = {d}.")
    dtype = jnp.result_type(beta1, beta2)
    rtol = jnp.asarray(rtol, dtype)
    q1 = srvf(resample_curve(beta1.astype(dtype), n_samples))
    q2 = srvf(resample_curve(beta2.astype(dtype), n_samples))
    if scale:
        q1, q2 = _unit(q1), _unit(q2)
    O, gamma, _, n_it = _register(
        jax.lax.stop_gradient(q1),
        jax.lax.stop_gradient(q2),
        rotation=rotation,
        neighbourhood=neighbourhood,
        max_iterations=max_iterations,
        rtol=rtol,
    )
    O = jax.lax.stop_gradient(O)
    gamma = jax.lax.stop_gradient(gamma)
    # Recomputed outside the search so that gradients reach the curves (envelope theorem).
    A, B, w = warp_samples(q1, q2 @ O.T, gamma)
    diff = A - B
    energy = jnp.sum(w * 0.5 * jnp.sum(diff * diff, axis=(1, 2)))
    ok = energy > 0
    distance = jnp.where(ok, jnp.sqrt(jnp.where(ok, energy, 1)), 0)
    return CurveRegistration(distance, energy, O, gamma, n_it)


_elastic_curve_distance = eqx.filter_jit(_curve_distance)


@eqx.filter_jit
def _elastic_curve_distances(beta1, beta2, max_iterations, rtol, **static):
    def one(b1, b2):
        return _curve_distance(b1, b2, max_iterations, rtol, **static)

    return split_over_devices(jax.vmap(one), (beta1, beta2))


def elastic_curve_distances(
    A: Float[ArrayLike, "N n1 d"],
    B: Float[ArrayLike, "N n2 d"],
    *,
    rotation: bool = True,
    scale: bool = False,
    n_samples: int = 100,
    neighbourhood: int = 7,
    max_iterations: int = 10,
    rtol: float = 1e-4,
    workers: int | None = None,
) -> CurveRegistration:
    """`elastic_curve_distance` of every pair ``(A[k], B[k])``, on every core.

    The batch is cut into one equal chunk per worker thread (default: one per core left
    over by the XLA devices; XLA:CPU runs one call on about one core) and, with several
    devices (`use_all_cores`), each chunk is also split across them. Every chunk has the same
    shape, so it compiles once; the results equal ``jax.vmap(elastic_curve_distance)`` of the
    same pairs. Options as in `elastic_curve_distance`. Returns a `CurveRegistration` with a
    leading batch axis N. For all pairs between two sets, index them: ``A[I], B[J]``.
    `workers`: worker threads, one chunk each (default: one per usable core left over by the
    XLA devices).
    """
    A = real_coordinates(A, "elastic_curve_distances: A")
    B = real_coordinates(B, "elastic_curve_distances: B")
    if A.ndim != 3 or B.ndim != 3 or A.shape[0] != B.shape[0]:
        raise ValueError(
            f"elastic_curve_distances: A and B must be batches of curves (N, n_points, d) with the same N, "
            f"got shapes {A.shape} and {B.shape}. For one pair use elastic_curve_distance."
        )
    n = A.shape[0]
    if n == 0:
        raise ValueError("elastic_curve_distances: empty batch; give at least one pair of curves.")
    n_samples, max_iterations = _check_options(n_samples, max_iterations, rtol, neighbourhood)
    executor = LocalExecutor(workers)
    n_chunks = min(executor.n_workers(), n)
    size = -(-n // n_chunks)
    idx = np.minimum(np.arange(n_chunks * size), n - 1).reshape(n_chunks, size)  # pad with the last pair
    static = dict(
        rotation=as_flag(rotation, "rotation"),
        scale=as_flag(scale, "scale"),
        n_samples=n_samples,
        neighbourhood=int(neighbourhood),
    )
    cap, tol = jnp.asarray(max_iterations, jnp.int32), jnp.asarray(rtol)

    def chunk(rows):
        res = _elastic_curve_distances(A[rows], B[rows], cap, tol, **static)
        return {f: getattr(res, f) for f in _FIELDS}

    results, _ = executor.map_blocks(chunk, [(rows,) for rows in idx], progress=False)
    return CurveRegistration(*(jnp.asarray(np.concatenate([r[f] for r in results])[:n]) for f in _FIELDS))


_FIELDS = ("distance", "energy", "rotation", "gamma", "n_iterations")
