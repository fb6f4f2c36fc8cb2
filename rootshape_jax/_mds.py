"""Classical (Torgerson) multidimensional scaling: points in a plane whose distances
approximate a distance matrix.

With ``D²`` the squared distances and ``J = I − 11ᵀ/n`` the centring matrix,
``B = −½ J D² J`` is the Gram matrix of centred points when ``D`` is Euclidean. Its top
eigenpairs ``(λ_k, v_k)`` give the embedding ``X_k = √λ_k v_k``; for a Euclidean ``D`` in
``k`` dimensions the distances of ``X`` equal ``D`` (the configuration is recovered up to a
rotation, reflection and translation). A non-Euclidean ``D`` (as elastic distances are) gives
negative eigenvalues; the proportion explained uses the positive ones only.

This is an analysis of a small ``n × n`` matrix at the I/O boundary, so it runs in numpy.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Float

from ._cluster import check_distances


class MDS(eqx.Module):
    """Result of `mds`.

    - `embedding`: ``(n, n_components)`` coordinates, one row per root (centred; the sign of
      each axis is fixed so its largest coordinate is positive).
    - `eigenvalues`: ``(n,)`` every eigenvalue of ``B``, largest first (negative ones show how
      far ``D`` is from Euclidean).
    - `proportion_explained`: ``(n_components,)`` each kept axis's eigenvalue over the sum of
      the positive eigenvalues.
    """

    embedding: Float[np.ndarray, "n k"]
    eigenvalues: Float[np.ndarray, " n"]
    proportion_explained: Float[np.ndarray, " k"]

    def __check_init__(self):
        if self.embedding.shape[1] != self.proportion_explained.shape[0]:
            raise ValueError("MDS: embedding and proportion_explained disagree on the number of axes.")

    @property
    def n_components(self) -> int:
        return int(self.embedding.shape[1])


def mds(D, n_components: int = 2) -> MDS:
    """Classical (Torgerson) MDS of a distance matrix `D` (``(n, n)``, symmetric, zero
    diagonal, finite, non-negative) into `n_components` dimensions (``1 ≤ n_components < n``).

    Axes whose eigenvalue is not positive (a ``D`` with fewer real dimensions, or a
    non-Euclidean one) get zero coordinates. Raises `ValueError` for a non-square, asymmetric,
    negative or NaN `D`, or a bad `n_components`.
    """
    D = check_distances(D)
    n = D.shape[0]
    if isinstance(n_components, bool) or not isinstance(n_components, (int, np.integer)):
        raise ValueError(f"n_components must be a whole number, got {n_components!r}.")
    if not 1 <= int(n_components) < max(n, 2):
        raise ValueError(f"n_components must be between 1 and n - 1 = {n - 1} for {n} roots, got {n_components}.")
    k = int(n_components)
    D2 = D**2
    # Double centring without forming J: subtract row and column means, add the grand mean.
    B = -0.5 * (D2 - D2.mean(axis=0, keepdims=True) - D2.mean(axis=1, keepdims=True) + D2.mean())
    vals, vecs = np.linalg.eigh(B)
    order = np.argsort(vals)[::-1]
    vals, vecs = vals[order], vecs[:, order]
    top = np.clip(vals[:k], 0.0, None)
    X = vecs[:, :k] * np.sqrt(top)[None, :]
    # A deterministic sign: eigenvectors are defined up to ±1.
    flip = np.sign(X[np.argmax(np.abs(X), axis=0), np.arange(k)])
    X = X * np.where(flip == 0, 1.0, flip)[None, :]
    positive = float(np.sum(vals[vals > 0]))
    ratio = top / positive if positive > 0 else np.zeros(k)
    return MDS(embedding=X, eigenvalues=vals, proportion_explained=ratio)
