"""Clustering and classification from a distance matrix (docs/design.md §6, paper §6.6).

Everything here works on an ``(n, n)`` matrix of elastic distances (`pairwise_distances`), on
the host with numpy / scipy: the expensive part, the registrations, is done already.

- `cluster`: agglomerative clustering (`scipy.cluster.hierarchy.linkage`, method selectable)
  and flat clusters cut at a number of clusters or a height.
- `loo_accuracy`: leave-one-out classification with labels by the nearest neighbour or by
  the nearest class mean. The distance to a class mean is computed from distances alone:
  for points of a Euclidean space ``|x − m_C|² = mean_j d²(x, x_j) − mean_{j,k} d²(x_j, x_k)/2``
  over the class members j, k (exact there). In the shape space it approximates the distance
  to the class's Karcher mean without registering anything again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import scipy.cluster.hierarchy as sch
import scipy.spatial.distance as ssd

from ._errors import LabelError, is_real_scalar, require_labels_present
from ._tree import RootTree, SRVFTree

LINKAGE_METHODS = ("single", "complete", "average", "weighted", "ward", "centroid", "median")


def check_distances(distances) -> np.ndarray:
    if isinstance(distances, (RootTree, SRVFTree)):
        raise TypeError(
            f"distances must be an (n, n) matrix of distances, got {type(distances).__name__}; for roots, "
            "compute it first: rootshape_jax.pairwise_distances(trees)."
        )
    try:
        D = np.asarray(distances, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"distances must be an (n, n) matrix of numbers, got {type(distances).__name__} that is not one."
        ) from None
    if D.ndim != 2 or D.shape[0] != D.shape[1] or D.shape[0] == 0:
        raise ValueError(f"distances must be a square (n, n) matrix with n >= 1, got shape {D.shape}.")
    if not np.all(np.isfinite(D)):
        raise ValueError("distances contains NaN or inf.")
    if np.any(D < 0):
        raise ValueError("distances must be non-negative.")
    scale = max(float(np.abs(D).max()), 1e-300)
    if not np.allclose(D, D.T, rtol=1e-6, atol=1e-9 * scale):
        raise ValueError("distances must be symmetric (use pairwise_distances, or (D + D.T) / 2).")
    # A root's distance to itself is 0 up to the registration's discretisation; a diagonal
    # of the distances' own size means another kind of matrix (similarities, features).
    i = int(np.argmax(np.abs(np.diag(D))))
    if D[i, i] > 1e-3 * scale:
        raise ValueError(
            f"distances has a non-zero diagonal ({D[i, i]:.3g} at row {i}, the largest distance being "
            f"{scale:.3g}): a root's distance to itself is 0. Pass a distance matrix (pairwise_distances), "
            "not similarities or features."
        )
    D = 0.5 * (D + D.T)
    np.fill_diagonal(D, 0.0)
    return D


@dataclasses.dataclass(frozen=True)
class Clustering:
    """Result of `cluster`.

    - `linkage`: scipy linkage matrix ``(n − 1, 4)`` (for `scipy.cluster.hierarchy.dendrogram`).
    - `labels`: ``(n,)`` flat cluster of each root, 0-based, numbered in order of first
      appearance along the dendrogram's leaf order.
    - `order`: dendrogram leaf order (indices of the roots).
    - `method`: the linkage method used.
    """

    linkage: np.ndarray
    labels: np.ndarray
    order: np.ndarray
    method: str

    @property
    def n_clusters(self) -> int:
        return int(self.labels.max()) + 1 if self.labels.size else 0


#: Roots up to which the leaves are put in optimal order (adjacent leaves as close as possible);
#: it costs O(N³). The heat maps (`plot.plot_distance_matrix`) order by the same linkage.
MAX_OPTIMAL_ORDERING = 300


def linkage_matrix(D: np.ndarray, method: str) -> np.ndarray:
    """The scipy linkage of a distance matrix, leaves in optimal order up to
    `MAX_OPTIMAL_ORDERING` roots (the order changes no merge, so no flat cluster)."""
    return sch.linkage(
        ssd.squareform(D, checks=False), method=method, optimal_ordering=D.shape[0] <= MAX_OPTIMAL_ORDERING
    )


def cluster(
    distances,
    *,
    n_clusters: int | None = 2,
    height: float | None = None,
    method: str = "average",
) -> Clustering:
    """Hierarchical clustering of roots from their distance matrix.

    - `method`: a `scipy.cluster.hierarchy.linkage` method: "single", "complete", "average"
      (default), "weighted", or — for distances that behave like Euclidean ones — "ward",
      "centroid", "median".
    - Flat clusters: cut the tree into `n_clusters` (default 2), or at `height` (pass
      ``n_clusters=None``).
    """
    if method not in LINKAGE_METHODS:
        raise ValueError(f"method must be one of {LINKAGE_METHODS}, got {method!r}.")
    D = check_distances(distances)
    n = D.shape[0]
    if n < 2:
        raise ValueError("cluster needs at least two roots.")
    if (n_clusters is None) == (height is None):
        raise ValueError("give exactly one of n_clusters or height.")
    Z = linkage_matrix(D, method)
    if n_clusters is not None:
        if not isinstance(n_clusters, (int, np.integer)) or not 1 <= n_clusters <= n:
            raise ValueError(f"n_clusters must be an integer in [1, {n}], got {n_clusters!r}.")
        raw = sch.fcluster(Z, t=int(n_clusters), criterion="maxclust")
    else:
        if not (is_real_scalar(height) and 0 <= float(height) < np.inf):  # numbers, numpy and JAX scalars
            raise ValueError(f"height must be a finite distance >= 0, got {height!r}.")
        raw = sch.fcluster(Z, t=float(height), criterion="distance")
    order = sch.leaves_list(Z)
    # Renumber 0, 1, ... in dendrogram order, so labels do not depend on scipy's numbering.
    mapping: dict[int, int] = {}
    for i in order:
        mapping.setdefault(int(raw[i]), len(mapping))
    labels = np.array([mapping[int(c)] for c in raw], dtype=np.int64)
    return Clustering(linkage=Z, labels=labels, order=np.asarray(order), method=method)


def check_labels(labels, n: int) -> np.ndarray:
    """The labels as an ``(n,)`` array; `LabelError` for a missing label (NaN or None), which
    would otherwise be a class of its own."""
    y = np.asarray(labels)
    if y.shape != (n,):
        raise LabelError(f"labels must have shape ({n},), got {y.shape}.")
    require_labels_present(y.tolist())
    return y


def class_mean_distances(distances, labels, *, leave_out: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance of every root to every class mean, from distances alone (module
    docstring). With `leave_out`, root i is removed from its own class first (NaN if that
    empties the class). Returns ``(d2 of shape (n, n_classes), classes)``."""
    D = check_distances(distances)
    n = D.shape[0]
    y = check_labels(labels, n)
    classes = np.unique(y)
    D2 = D**2
    out = np.full((n, len(classes)), np.nan)
    for c, cls in enumerate(classes):
        members = np.flatnonzero(y == cls)
        for i in range(n):
            idx = members[members != i] if leave_out else members
            if idx.size == 0:
                continue
            spread = D2[np.ix_(idx, idx)].sum() / (2 * idx.size**2)
            out[i, c] = max(D2[i, idx].mean() - spread, 0.0)
    return out, classes


def loo_accuracy(distances, labels, *, rule: str = "nearest_neighbour") -> dict:
    """Leave-one-out classification accuracy.

    - ``rule="nearest_neighbour"``: each root takes the label of its nearest other root.
    - ``rule="nearest_mean"``: each root takes the label of the nearest class mean, the
      means computed without the root (see `class_mean_distances`).

    Ties go to the first candidate (smallest index / first class in sorted order). Returns
    ``{"accuracy", "predicted", "correct"}``.
    """
    D = check_distances(distances)
    n = D.shape[0]
    y = check_labels(labels, n)
    if n < 2:
        raise ValueError("leave-one-out needs at least two roots.")
    if rule == "nearest_neighbour":
        masked = D + np.diag(np.full(n, np.inf))
        predicted = y[np.argmin(masked, axis=1)]
    elif rule == "nearest_mean":
        d2, classes = class_mean_distances(D, y, leave_out=True)
        d2 = np.where(np.isnan(d2), np.inf, d2)
        predicted = classes[np.argmin(d2, axis=1)]
    else:
        raise ValueError(f"rule must be 'nearest_neighbour' or 'nearest_mean', got {rule!r}.")
    correct = predicted == y
    return {"accuracy": float(correct.mean()), "predicted": predicted, "correct": correct}


def _check_pair(labels, other, what: str, other_name: str) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(labels)
    p = np.asarray(other)
    if y.shape != p.shape or y.ndim != 1:
        raise ValueError(
            f"{what}: labels and {other_name} must be two 1-D sequences of one length, got "
            f"shapes {y.shape} and {p.shape}."
        )
    return y, p


def _is_text(x: np.ndarray) -> bool:
    return x.dtype.kind in "USO"


def confusion_matrix(labels, predicted, classes: Sequence | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Counts ``C[i, j]`` of roots of class i predicted as class j, with the class order.

    `predicted` names classes of `labels` (e.g. `loo_accuracy`'s "predicted"). To set
    clusters against labels (cluster numbers are not classes), use `contingency_table`.
    """
    y, p = _check_pair(labels, predicted, "confusion_matrix", "predicted")
    if classes is None:
        if _is_text(y) != _is_text(p) and not set(p.tolist()) <= set(y.tolist()):
            raise ValueError(
                f"confusion_matrix: predicted holds {sorted(set(p.tolist()), key=str)[:6]} but the labels' "
                f"classes are {sorted(set(y.tolist()), key=str)[:6]}: predictions must name the labels' classes. "
                "To compare "
                "clusters with labels use rootshape_jax.contingency_table(labels, clustering.labels)."
            )
        classes = np.unique(np.concatenate([y, p]))
    else:
        classes = np.asarray(classes)
    index = {c: k for k, c in enumerate(classes.tolist())}
    unknown = sorted({v for v in y.tolist() + p.tolist() if v not in index}, key=str)
    if unknown:
        raise ValueError(f"confusion_matrix: {unknown[:6]} are not among classes {classes.tolist()[:6]}.")
    C = np.zeros((len(classes), len(classes)), dtype=np.int64)
    for a, b in zip(y.tolist(), p.tolist()):
        C[index[a], index[b]] += 1
    return C, classes


def contingency_table(labels, groups) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts ``T[i, j]`` of roots of class i (`labels`) in group j (`groups`, e.g. the flat
    clusters ``cluster(D).labels``): how clusters split known classes. Returns ``(T, classes,
    group ids)``, both sorted; rows and columns need not match in number or kind."""
    y, g = _check_pair(labels, groups, "contingency_table", "groups")
    classes, rows = np.unique(y, return_inverse=True)
    ids, cols = np.unique(g, return_inverse=True)
    T = np.zeros((len(classes), len(ids)), dtype=np.int64)
    np.add.at(T, (rows.reshape(-1), cols.reshape(-1)), 1)
    return T, classes, ids
