"""Pairwise group tests: a PERMANOVA for every pair of groups, with Holm's correction."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from ._cluster import check_distances, check_labels
from ._permanova import permanova


@dataclasses.dataclass(frozen=True)
class PairTest:
    """One pair of groups: sizes, pseudo-F, R², raw and Holm-adjusted p-values."""

    group_a: str
    group_b: str
    n_a: int
    n_b: int
    pseudo_f: float
    r2: float
    p_value: float
    p_adjusted: float


def holm(p_values) -> np.ndarray:
    """Holm's step-down adjustment (controls the family-wise error rate): the i-th smallest
    p-value is multiplied by ``m − i`` (i from 0), made non-decreasing, capped at 1."""
    p = np.asarray(p_values, dtype=np.float64)
    if p.ndim != 1 or not np.all((p >= 0) & (p <= 1)):  # NaN fails too
        raise ValueError(f"holm: p_values must be a 1-D sequence of probabilities in [0, 1], got {p_values!r}.")
    m = p.size
    order = np.argsort(p, kind="stable")
    adjusted = np.minimum(1.0, np.maximum.accumulate(p[order] * (m - np.arange(m))))
    out = np.empty(m)
    out[order] = adjusted
    return out


def pairwise_permanova(D, labels, *, permutations: int = 999, seed: int = 0) -> list[PairTest]:
    """A PERMANOVA (`rootshape_jax.permanova`) on the sub-matrix of every pair of groups, in
    the order the groups first appear, with Holm-adjusted p-values. Pairs where neither group
    has two members cannot be tested and are left out."""
    D = check_distances(D)
    y = np.asarray(check_labels(labels, D.shape[0])).astype(str)
    groups = list(dict.fromkeys(y.tolist()))
    if len(groups) < 2:
        raise ValueError(f"pairwise tests need at least 2 groups, got {len(groups)}.")
    raw = []
    for k, (a, b) in enumerate(itertools.combinations(groups, 2)):
        idx = np.flatnonzero((y == a) | (y == b))
        na, nb = int(np.sum(y == a)), int(np.sum(y == b))
        if max(na, nb) < 2:
            continue
        res = permanova(D[np.ix_(idx, idx)], y[idx], permutations=permutations, seed=seed + k)
        raw.append((a, b, na, nb, res))
    adj = holm([r.p_value for *_, r in raw]) if raw else []
    return [PairTest(a, b, na, nb, r.pseudo_f, r.r2, r.p_value, float(q)) for (a, b, na, nb, r), q in zip(raw, adj)]
