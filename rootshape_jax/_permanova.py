"""PERMANOVA (Anderson 2001): do groups of roots differ, from their distance matrix alone.

With ``n`` roots in ``a`` groups and squared distances ``d²_ij``, the total and within-group
sums of squares are ``SS_T = (1/n) Σ_{i<j} d²_ij`` and ``SS_W = Σ_g (1/n_g) Σ_{i<j in g} d²_ij``;
``SS_A = SS_T − SS_W``. The pseudo-F is ``(SS_A / (a − 1)) / (SS_W / (n − a))`` and
``R² = SS_A / SS_T``. The p-value is that of a permutation test: the labels are shuffled
`permutations` times and ``p = (1 + #{F_perm ≥ F}) / (1 + permutations)``. With Euclidean
distances of points the pseudo-F is the classical one-way ANOVA F statistic.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._cluster import check_distances, check_labels
from ._errors import as_count


@dataclasses.dataclass(frozen=True)
class Permanova:
    """Result of `permanova`: `pseudo_f`, `p_value`, `r2` (the fraction of the total sum of
    squares between groups), `permutations` and `n_groups`."""

    pseudo_f: float
    p_value: float
    r2: float
    permutations: int
    n_groups: int


def _pseudo_f(D2: np.ndarray, codes: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-F and R² for each row of `codes` (``(m, n)`` integer labels 0..a−1)."""
    n = D2.shape[0]
    ss_t = D2.sum() / (2 * n)
    onehot = np.eye(n_groups)[codes]  # (m, n, a)
    sizes = onehot.sum(axis=1)  # (m, a)
    within = np.einsum("mia,ij,mja->ma", onehot, D2, onehot) / 2
    ss_w = np.sum(within / sizes, axis=1)
    ss_a = ss_t - ss_w
    f = (ss_a / (n_groups - 1)) / (ss_w / (n - n_groups))
    return f, ss_a / ss_t


def permanova(D, labels, permutations: int = 999, seed: int = 0) -> Permanova:
    """One-way PERMANOVA of a distance matrix `D` (``(n, n)``) against group `labels` (``(n,)``,
    at least two groups, at least one group with two members): pseudo-F, permutation p-value
    (`permutations` label shuffles from `seed`) and R²."""
    D = check_distances(D)
    n = D.shape[0]
    y = check_labels(labels, n)
    _, codes = np.unique(y, return_inverse=True)
    a = int(codes.max()) + 1
    if a < 2 or a >= n:
        raise ValueError(
            f"permanova needs at least 2 groups and fewer groups than roots; got {a} group(s) for {n} roots."
        )
    as_count(permutations, "permutations")
    D2 = D**2
    f, r2 = _pseudo_f(D2, codes[None], a)
    rng = np.random.default_rng(as_count(seed, "seed", minimum=0))
    count = 0
    for start in range(0, int(permutations), 256):
        m = min(256, int(permutations) - start)
        perm = np.stack([rng.permutation(codes) for _ in range(m)])
        fp, _ = _pseudo_f(D2, perm, a)
        count += int(np.sum(fp >= f[0] * (1 - 1e-12)))
    return Permanova(
        pseudo_f=float(f[0]),
        p_value=(1 + count) / (1 + int(permutations)),
        r2=float(r2[0]),
        permutations=int(permutations),
        n_groups=a,
    )
