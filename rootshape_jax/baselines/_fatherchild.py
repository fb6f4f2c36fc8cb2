"""Father–child edge decomposition of a `Root`, shared by the baselines (numpy).

Feragen et al. and Wang et al. describe a tree by its *edges*: the main root is cut at the
attachment points of its laterals, so a root with ``n`` laterals (sorted by attachment fraction)
has ``n + 1`` main-root edges ``e_0 .. e_n`` (base → first node → ... → tip) and ``n`` lateral
edges; lateral ``k`` (0-based) is a child of the node between ``e_k`` and ``e_{k+1}``.

Fixed correspondence between two roots: edges are matched by slot — main edge ``k`` with main
edge ``k``, lateral ``k`` (the k-th along the main root) with lateral ``k``. The tree with fewer
laterals is padded at its tip with collapsed edges (zero vectors), so the slot layout of a
root padded to capacity ``N`` is

    [e_0, ..., e_N, lateral_0, ..., lateral_{N-1}]        (2N + 1 slots)

with the slots after the root's own ``n`` laterals (main ``n+1..N``, lateral ``n..N-1``) zero.
Padding further never changes a pairwise comparison (zero against zero costs nothing), so one
global capacity serves every pair of a population.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .._errors import InvalidRootError
from .._root import Root, check_polyline, polyline_length
from .._tree import resample_polyline


def check_root(root, what: str) -> Root:
    """Re-validate a `Root` (its arrays are writable numpy, so they may have changed since)."""
    if not isinstance(root, Root):
        raise TypeError(f"{what}: expected a rootshape_jax.Root, got {type(root).__name__}.")
    main = check_polyline(root.main, what=f"{what}: main root")
    for i, lat in enumerate(root.laterals):
        check_polyline(lat, what=f"{what}: lateral {i}", dim=main.shape[1])
    attach = np.asarray(root.attach)
    if attach.shape != (root.n_laterals,) or not np.all(np.isfinite(attach)):
        raise InvalidRootError(
            f"{what}: attachment fractions must be {root.n_laterals} finite numbers in [0, 1], got {attach.tolist()}."
        )
    return root


def check_roots(roots, what: str) -> list[Root]:
    if isinstance(roots, Root):
        raise TypeError(f"{what}: expected a sequence of Root, got a single Root; wrap it in a list.")
    roots = list(roots)
    if not roots:
        raise ValueError(f"{what}: needs at least one root, got an empty sequence.")
    for i, r in enumerate(roots):
        check_root(r, f"{what}: root {i}")
    check_same_dim(roots, what)
    return roots


def check_same_dim(roots: Sequence[Root], what: str) -> int:
    dims = {r.dim for r in roots}
    if len(dims) != 1:
        raise InvalidRootError(f"{what}: roots mix dimensions {sorted(dims)}; convert 2D roots to 3D (z = 0) first.")
    return dims.pop()


def check_count(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return int(value)


def result_dtype(roots: Sequence[Root]):
    return np.result_type(*[r.main.dtype for r in roots])


def _cumulative(points: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def _point_at_length(points: np.ndarray, cum: np.ndarray, length: float) -> np.ndarray:
    return np.array([np.interp(length, cum, points[:, k]) for k in range(points.shape[1])])


def split_polyline(points: np.ndarray, fractions: np.ndarray) -> list[np.ndarray]:
    """Cut a polyline at sorted arc-length fractions: ``len(fractions) + 1`` pieces, each
    from its cut point to the next, keeping the original vertices in between."""
    points = np.asarray(points, dtype=np.float64)
    cum = _cumulative(points)
    total = cum[-1]
    cuts = np.concatenate([[0.0], np.clip(np.asarray(fractions, np.float64), 0, 1) * total, [total]])
    pieces = []
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        inner = points[(cum > lo) & (cum < hi)]
        start = points[0] if lo <= 0 else _point_at_length(points, cum, lo)
        stop = points[-1] if hi >= total else _point_at_length(points, cum, hi)
        pieces.append(np.vstack([start[None], inner, stop[None]]))
    return pieces


def decompose(root: Root) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """``(origin, main_edges, lateral_edges)`` of one root, as absolute float64 polylines.

    Laterals are ordered by attachment fraction (stable for ties). A lateral whose first point
    is not on the main root is joined to its attachment point first (as `batch` does), so every
    lateral edge starts at its father's node.
    """
    main = np.asarray(root.main, np.float64)
    order = np.argsort(np.asarray(root.attach), kind="stable")
    fractions = np.asarray(root.attach, np.float64)[order]
    main_edges = split_polyline(main, fractions)
    scale = max(1.0, float(np.abs(main).max()))
    lateral_edges = []
    for k, idx in enumerate(order):
        lat = np.asarray(root.laterals[idx], np.float64)
        node = main_edges[k][-1]
        if np.linalg.norm(lat[0] - node) > 1e-9 * scale:
            lat = np.vstack([node[None], lat])
        lateral_edges.append(lat)
    return main[0].copy(), main_edges, lateral_edges


def edge_slots(root: Root, capacity: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The root's ``2·capacity + 1`` edges resampled to ``n_points`` points uniform in arc length
    and translated to start at 0, in the slot layout of the module docstring.

    Returns ``(edges (2N+1, n_points, d), origin (d,))``; padded slots are exactly zero.
    """
    if root.n_laterals > capacity:
        raise ValueError(f"capacity {capacity} < {root.n_laterals} laterals (internal error).")
    origin, main_edges, lateral_edges = decompose(root)
    d = origin.shape[0]
    out = np.zeros((2 * capacity + 1, n_points, d))
    for k, edge in enumerate(main_edges):
        out[k] = resample_polyline(edge, n_points) - edge[0]
    for k, edge in enumerate(lateral_edges):
        out[capacity + 1 + k] = resample_polyline(edge, n_points) - edge[0]
    return out, origin


def assemble(origin: np.ndarray, edges: np.ndarray, *, dtype, name: str = "", metadata: dict | None = None) -> Root:
    """Rebuild a `Root` from relative edge curves in the slot layout (father to child).

    Main edge ``k`` starts where main edge ``k − 1`` ends (edge 0 at `origin`); lateral ``k``
    starts at the end of main edge ``k``. Every lateral slot is kept (a zero-length lateral is a
    repeated point), so slot ``k`` is the same lateral along a path; attachment fractions are
    the nodes' arc-length fractions along the rebuilt main root.
    """
    edges = np.asarray(edges, np.float64)
    capacity = (edges.shape[0] - 1) // 2
    start = np.asarray(origin, np.float64)
    pieces, nodes = [], []
    for k in range(capacity + 1):
        piece = start + (edges[k] - edges[k][0])
        pieces.append(piece if k == 0 else piece[1:])
        start = piece[-1]
        nodes.append(piece[-1])
    main = np.vstack(pieces)
    cum = _cumulative(main)
    total = cum[-1]
    # Node k (end of main edge k) is the last point of piece k in the concatenated polyline.
    ends = np.cumsum([len(p) for p in pieces]) - 1
    attach = np.array([cum[ends[k]] / total if total > 0 else 0.0 for k in range(capacity)])
    lats = [nodes[k] + (edges[capacity + 1 + k] - edges[capacity + 1 + k][0]) for k in range(capacity)]
    return Root(
        main=main.astype(dtype),
        laterals=tuple(lat.astype(dtype) for lat in lats),
        attach=np.clip(attach, 0.0, 1.0).astype(dtype),
        name=name,
        metadata=metadata or {},
    )


def total_length(root: Root) -> float:
    return polyline_length(root.main) + float(sum(polyline_length(lat) for lat in root.laterals))
