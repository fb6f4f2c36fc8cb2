"""QED tree-shape baseline (Feragen et al.): a re-implementation from the published description.

References: A. Feragen, F. Lauze, P. Lo, M. de Bruijne, M. Nielsen, "Geometries on spaces of
treelike shapes", ACCV 2010; A. Feragen, P. Lo, M. de Bruijne, M. Nielsen, F. Lauze,
"Toward a theory of statistical tree-shape analysis", IEEE TPAMI 35(8), 2013 — the method the
paper compares against in its geodesic and mean figures (Wang, Laga et al., Section 1, 5).

Representation (father–child branching, `_fatherchild`): the main root is cut at the
attachment points into main-root edges; every edge (main segments and laterals) is described
by ``n_landmarks`` points uniform in arc length, relative to the edge's start point (its
father's node), so an edge is a vector in ``R^(n_landmarks·d)``; collapsed or absent edges are
the zero vector. Trees with different lateral counts are padded at the tip with collapsed edges.

Metric: the *quotient* Euclidean distance minimises the Euclidean distance between the stacked
edge vectors over the tree's alternative representations. Here the correspondence is FIXED
(laterals matched by order along the main root, padding at the tip), so the QED reduces to the
Euclidean distance of the stacked vectors — a true metric on the padded representations. Its
geodesic is the straight line between the edge vectors, mapped back to curves by re-attaching
each edge at the end of its father; the mean is the Euclidean average. There is no rotation or
scale alignment: align the roots first (the paper's "alignment" step) if needed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from .._root import Root
from ._fatherchild import (
    assemble,
    check_count,
    check_root,
    check_roots,
    check_same_dim,
    edge_slots,
    result_dtype,
)


def _representations(roots: list[Root], n_landmarks: int):
    """``(X (N, 2C+1, n_landmarks + 1, d), origins (N, d))`` at the common capacity C."""
    capacity = max(r.n_laterals for r in roots)
    reps = [edge_slots(r, capacity, n_landmarks + 1) for r in roots]
    return np.stack([e for e, _ in reps]), np.stack([o for _, o in reps])


def qed_vectors(roots, *, n_landmarks: int = 20) -> np.ndarray:
    """The QED edge vectors of a population, shape ``(N, 2C + 1, n_landmarks, d)`` with
    ``C`` = the most laterals of any root (slot layout of `_fatherchild`; the edge's start
    point, always 0, is not stored)."""
    roots = check_roots(roots, "qed_vectors")
    n_landmarks = check_count(n_landmarks, "n_landmarks", 1)
    X, _ = _representations(roots, n_landmarks)
    return X[:, :, 1:]


def qed_distance(a: Root, b: Root, *, n_landmarks: int = 20) -> float:
    """QED between two roots for the fixed correspondence (laterals by order along the main
    root, the tree with fewer laterals padded with collapsed edges): the Euclidean distance
    ``sqrt(Σ_edges Σ_landmarks |x_a − x_b|²)`` of their edge-landmark vectors. `n_landmarks`:
    points per edge, uniform in arc length (the edge's start, its father's node, excluded)."""
    X = qed_vectors(_pair(a, b, "qed_distance"), n_landmarks=n_landmarks)
    return float(np.sqrt(np.sum((X[0] - X[1]) ** 2)))


def qed_distance_matrix(roots, *, n_landmarks: int = 20) -> np.ndarray:
    """``(N, N)`` matrix of `qed_distance` between every pair (exactly symmetric, zero diagonal)."""
    X = qed_vectors(roots, n_landmarks=n_landmarks)
    flat = X.reshape(X.shape[0], -1)
    D = cdist(flat, flat)
    D = 0.5 * (D + D.T)
    np.fill_diagonal(D, 0.0)
    return D


def qed_geodesic(a: Root, b: Root, *, n_steps: int = 9, n_landmarks: int = 20) -> list[Root]:
    """The straight line ``(1 − τ) x_a + τ x_b`` between the edge vectors, mapped back to roots.

    Each step re-attaches every edge at the end of its father (main edges end to end from the
    interpolated base ``(1 − τ) o_a + τ o_b``; lateral k at the end of main edge k). Every step
    has the same lateral slots (slot k = the k-th lateral along the main root, padded laterals
    grow from zero length), so slot index is the correspondence colour. The first step is `a`
    and the last `b`, each resampled to its landmarks.
    """
    pair = _pair(a, b, "qed_geodesic")
    n_steps = check_count(n_steps, "n_steps", 2)
    n_landmarks = check_count(n_landmarks, "n_landmarks", 1)
    X, origins = _representations(pair, n_landmarks)
    dtype = result_dtype(pair)
    out = []
    for i, tau in enumerate(np.linspace(0.0, 1.0, n_steps)):
        edges = (1 - tau) * X[0] + tau * X[1]
        origin = (1 - tau) * origins[0] + tau * origins[1]
        out.append(
            assemble(
                origin,
                edges,
                dtype=dtype,
                name=f"qed_geodesic_{i}",
                metadata={"method": "qed", "tau": float(tau)},
            )
        )
    return out


def qed_mean(roots, *, n_landmarks: int = 20) -> Root:
    """Euclidean mean of the edge vectors under the fixed correspondence, mapped back to a root
    (base at the mean of the bases). It has as many lateral slots as the root with the most."""
    roots = check_roots(roots, "qed_mean")
    n_landmarks = check_count(n_landmarks, "n_landmarks", 1)
    X, origins = _representations(roots, n_landmarks)
    return assemble(
        origins.mean(0),
        X.mean(0),
        dtype=result_dtype(roots),
        name="qed_mean",
        metadata={"method": "qed", "n_roots": len(roots)},
    )


def _pair(a, b, what: str) -> list[Root]:
    pair = [check_root(a, f"{what}: a"), check_root(b, f"{what}: b")]
    check_same_dim(pair, what)
    return pair
