"""Optimal rotation (weighted Kabsch / orthogonal Procrustes) between SRVFs, d = 2 and 3."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._curves import trapezoid_weights


def optimal_rotation(
    A: Float[ArrayLike, "*branches T d"],
    B: Float[ArrayLike, "*branches T d"],
    weights: Float[ArrayLike, " *branches"] | None = None,
) -> Float[Array, "d d"]:
    """Rotation ``O ∈ SO(d)`` maximising ``Σ_k w_k <A_k, O B_k>`` (so ``O·B ≈ A``).

    ``A`` and ``B`` hold SRVFs (or any functions) on the grid; the L2 inner products use the
    trapezoid rule, and every leading axis is summed with ``weights`` (default 1). The
    determinant is corrected so the result is a proper rotation, never a reflection.
    """
    A = jnp.asarray(A)
    B = jnp.asarray(B)
    if A.shape != B.shape or A.ndim < 2 or A.shape[-1] not in (2, 3):
        raise ValueError(
            f"optimal_rotation needs A and B of the same shape (..., T, d), d in (2, 3); "
            f"got {A.shape} and {B.shape}."
        )
    tw = trapezoid_weights(A.shape[-2], A.dtype)
    if weights is None:
        w = tw
        lead = A.shape[:-2]
        w = jnp.broadcast_to(w, lead + tw.shape)
    else:
        w = jnp.asarray(weights, A.dtype)[..., None] * tw
    # K = Σ w B Aᵀ (d×d); maximise tr(O K).
    K = jnp.einsum("...t,...ti,...tj->ij", w, B, A)
    U, _, Vt = jnp.linalg.svd(K)
    V = Vt.T
    det = jnp.linalg.det(V @ U.T)
    d = A.shape[-1]
    D = jnp.ones((d,), A.dtype).at[-1].set(jnp.sign(det) + (det == 0))
    return (V * D) @ U.T


def rotate(x: Float[ArrayLike, "*batch d"], O: Float[ArrayLike, "d d"]) -> Float[Array, "*batch d"]:
    """Apply the rotation ``O`` to points or SRVF values stored as rows."""
    return jnp.asarray(x) @ jnp.asarray(O).T
