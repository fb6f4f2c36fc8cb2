"""Optimal rotation (weighted Kabsch / orthogonal Procrustes) between SRVFs, d = 2 and 3."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._curves import trapezoid_weights
from ._errors import require_finite_values


def optimal_rotation(
    A: Float[ArrayLike, "*branches T d"],
    B: Float[ArrayLike, "*branches T d"],
    weights: Float[ArrayLike, " *branches"] | None = None,
) -> Float[Array, "d d"]:
    """Rotation ``O ∈ SO(d)`` maximising ``Σ_k w_k <A_k, O B_k>`` (so ``O·B ≈ A``).

    ``A`` and ``B`` hold SRVFs (or any functions) on the grid; the L2 inner products use the
    trapezoid rule, and every leading axis is summed with ``weights`` (default 1). The
    determinant is corrected so the result is a proper rotation, never a reflection.
    NaN or inf in the input is an `InputError` (under jit: an error when the program runs),
    not a NaN rotation.
    """
    A, B = _check_pair(A, B)
    A = require_finite_values(A, "optimal_rotation: A")
    B = require_finite_values(B, "optimal_rotation: B")
    if weights is not None:
        weights = require_finite_values(jnp.asarray(weights, A.dtype), "optimal_rotation: weights")
    return kabsch(A, B, weights)


def _check_pair(A, B) -> tuple[Array, Array]:
    A = jnp.asarray(A)
    B = jnp.asarray(B)
    if A.shape != B.shape or A.ndim < 2 or A.shape[-1] not in (2, 3):
        raise ValueError(
            f"optimal_rotation needs A and B of the same shape (..., T, d), d in (2, 3); got {A.shape} and {B.shape}."
        )
    return A, B


def kabsch(
    A: Float[ArrayLike, "*branches T d"],
    B: Float[ArrayLike, "*branches T d"],
    weights: Float[ArrayLike, " *branches"] | None = None,
) -> Float[Array, "d d"]:
    """`optimal_rotation` without its value checks, for the engine's and the elastic distance's
    inner loops (their inputs are checked where they enter the library)."""
    A, B = _check_pair(A, B)
    tw = trapezoid_weights(A.shape[-2], A.dtype)
    if weights is None:
        w = tw
        lead = A.shape[:-2]
        w = jnp.broadcast_to(w, lead + tw.shape)
    else:
        w = jnp.asarray(weights, A.dtype)[..., None] * tw
    # K = Σ w B Aᵀ (d×d); maximise tr(O K).
    K = jnp.einsum("...t,...ti,...tj->ij", w, B, A)
    return rotation_maximising(K)


def rotation_maximising(K: Float[Array, "d d"]) -> Float[Array, "d d"]:
    """The rotation ``O ∈ SO(d)`` maximising ``tr(O K)`` (``K = Σ w B Aᵀ``, see
    `optimal_rotation`); determinant corrected, never a reflection."""
    if K.shape[-1] == 2:
        return _rotation_2d(K)
    U, _, Vt = jnp.linalg.svd(K)
    V = Vt.T
    det = jnp.linalg.det(V @ U.T)
    d = K.shape[-1]
    D = jnp.ones((d,), K.dtype).at[-1].set(jnp.sign(det) + (det == 0))
    return (V * D) @ U.T


def _rotation_2d(K: Array) -> Array:
    # In 2-D, tr(O K) = c (K00 + K11) + s (K01 − K10) for O = [[c, −s], [s, c]]: the maximiser
    # is (c, s) ∝ (K00 + K11, K01 − K10), no SVD needed (LAPACK's batched SVD costs more than
    # the rest of a rotation step). K = 0 (nothing to align) gives the identity.
    x = K[0, 0] + K[1, 1]
    y = K[0, 1] - K[1, 0]
    ok = (x != 0) | (y != 0)
    x, y = jnp.where(ok, x, 1), jnp.where(ok, y, 0)  # safe values, and safe gradients
    r = jnp.hypot(x, y)  # no underflow for tiny K (float32 x² underflows below ~1e-19)
    c = jnp.where(ok, x / r, 1)
    s = jnp.where(ok, y / r, 0)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def axis_angle_rotation(axis: Float[ArrayLike, " 3"], angle) -> Float[Array, "3 3"]:
    """The 3D rotation by `angle` about the unit vector `axis` (Rodrigues:
    ``I + sin θ K + (1 − cos θ) K²``, K the cross-product matrix of the axis); a zero axis gives
    the identity. In the dtype of `axis`."""
    k = jnp.asarray(axis)
    zero = jnp.zeros((), k.dtype)
    K = jnp.stack([jnp.stack([zero, -k[2], k[1]]), jnp.stack([k[2], zero, -k[0]]), jnp.stack([-k[1], k[0], zero])])
    return jnp.eye(3, dtype=k.dtype) + jnp.sin(angle) * K + (1 - jnp.cos(angle)) * (K @ K)


def rotate(x: Float[ArrayLike, "*batch d"], O: Float[ArrayLike, "d d"]) -> Float[Array, "*batch d"]:
    """Apply the rotation ``O`` to points or SRVF values stored as rows."""
    return jnp.asarray(x) @ jnp.asarray(O).T
