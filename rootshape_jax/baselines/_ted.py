"""Tree edit distance on the father–child topology: a re-implementation from the published
description of the Zhang–Shasha algorithm.

Reference: K. Zhang, D. Shasha, "Simple fast algorithms for the editing distance between trees
and related problems", SIAM Journal on Computing 18(6), 1989. A classic topology-only baseline
for the paper's classification comparison.

The tree (ORDERED, rooted, labelled): one node per father–child edge of `_fatherchild` — the
main-root segments between attachment points and the laterals — labelled with the edge's
length. Main segment ``e_k``'s children are, in this order, the next main segment ``e_{k+1}``
and the lateral attached at their common node; the tip segment is a leaf, the root of the tree
is the segment at the base. Putting the main continuation first keeps the main root on the
leftmost path, which Zhang–Shasha handles in ``O(n²)`` for these caterpillar trees.

Costs: relabel ``|ℓ_a − ℓ_b|``, insert / delete ``ℓ`` (a node's length). These form a metric on
labels (the empty label has length 0), so the edit distance is a metric on ordered trees.
Geometry other than edge lengths (directions, shapes, sides) is ignored.
"""

from __future__ import annotations

import numpy as np

from .._root import Root, polyline_length
from ._fatherchild import check_root, check_roots, decompose


def edit_tree(root: Root) -> tuple[list[float], list[list[int]]]:
    """``(lengths, children)`` of the root's father–child tree; node 0 is the base segment.

    Nodes ``0..n`` are the main segments ``e_0..e_n``, node ``n + 1 + k`` the k-th lateral
    along the main root; ``children[i]`` lists node i's children in order.
    """
    _, main_edges, lateral_edges = decompose(root)
    n = len(lateral_edges)
    lengths = [polyline_length(e) for e in main_edges] + [polyline_length(e) for e in lateral_edges]
    children: list[list[int]] = [[] for _ in range(2 * n + 1)]
    for k in range(n):
        children[k] = [k + 1, n + 1 + k]
    return lengths, children


class _Postorder:
    """A tree in postorder: node weights, leftmost-leaf descendants and keyroots."""

    def __init__(self, lengths: list[float], children: list[list[int]]):
        order: list[int] = []
        stack = [(0, False)]
        while stack:  # iterative postorder (main roots can have hundreds of segments)
            node, expanded = stack.pop()
            if expanded:
                order.append(node)
            else:
                stack.append((node, True))
                stack.extend((c, False) for c in reversed(children[node]))
        index = {node: i for i, node in enumerate(order)}
        self.weight = [float(lengths[node]) for node in order]
        lml = [0] * len(order)
        for i, node in enumerate(order):
            lml[i] = lml[index[children[node][0]]] if children[node] else i
        self.lml = lml
        # A keyroot is the highest node among those sharing its leftmost leaf.
        last: dict[int, int] = {}
        for i, leaf in enumerate(lml):
            last[leaf] = i
        self.keyroots = sorted(last.values())


def _zhang_shasha(t1: _Postorder, t2: _Postorder) -> float:
    w1, w2, l1, l2 = t1.weight, t2.weight, t1.lml, t2.lml
    td = [[0.0] * len(w2) for _ in range(len(w1))]
    for i in t1.keyroots:
        for j in t2.keyroots:
            li, lj = l1[i], l2[j]
            m, n = i - li + 2, j - lj + 2
            # fd[x][y]: distance between the forests l1[i]..li+x-1 and lj..lj+y-1.
            fd = [[0.0] * n for _ in range(m)]
            for x in range(1, m):
                fd[x][0] = fd[x - 1][0] + w1[li + x - 1]
            for y in range(1, n):
                fd[0][y] = fd[0][y - 1] + w2[lj + y - 1]
            for x in range(1, m):
                a = li + x - 1
                wa, la = w1[a], l1[a]
                row, prev = fd[x], fd[x - 1]
                for y in range(1, n):
                    b = lj + y - 1
                    delete = prev[y] + wa
                    insert = row[y - 1] + w2[b]
                    if la == li and l2[b] == lj:
                        v = min(delete, insert, prev[y - 1] + abs(wa - w2[b]))
                        td[a][b] = v
                    else:
                        v = min(delete, insert, fd[la - li][l2[b] - lj] + td[a][b])
                    row[y] = v
    return td[-1][-1]


def tree_edit_distance(a: Root, b: Root) -> float:
    """Zhang–Shasha edit distance between the ordered father–child trees of two roots
    (relabel ``|Δ length|``, insert / delete = length; see the module docstring)."""
    a = check_root(a, "tree_edit_distance: a")
    b = check_root(b, "tree_edit_distance: b")
    return _zhang_shasha(_Postorder(*edit_tree(a)), _Postorder(*edit_tree(b)))


def tree_edit_distance_matrix(roots) -> np.ndarray:
    """``(N, N)`` matrix of `tree_edit_distance` (computed for i < j and mirrored)."""
    roots = check_roots(roots, "tree_edit_distance_matrix")
    trees = [_Postorder(*edit_tree(r)) for r in roots]
    n = len(trees)
    D = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            D[i, j] = D[j, i] = _zhang_shasha(trees[i], trees[j])
    return D
