"""Measurable plausibility of synthesised roots against a reference population.

A synthesised root (a PCA mode, a random sample, a regressed root) is *plausible* here when

1. **lengths**: every real lateral's length lies within the reference's lateral-length range,
   widened by `tolerance` (relative) on both sides;
2. **no self-crossing**: no branch (main root or lateral) crosses itself. In 2D two
   non-adjacent segments of the polyline intersect; in 3D they come closer than
   `tolerance` × the branch's length. In both, a cusp (two consecutive segments turning by
   more than 150°: the branch retraces itself) counts as a crossing;

and a *set* of roots is plausible when, in addition,

3. **distribution**: the pooled lateral lengths of the set are close to the reference's: the
   two-sample Kolmogorov–Smirnov statistic, with its p-value (``scipy.stats.ks_2samp``).

Lengths are those of the `RootTree` polylines, in the trees' units: give `trees` and
`reference` in the same units (e.g. both scale-normalised). Checks run in numpy: this is
an I/O-side measurement, not part of any compiled computation.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.stats

from ._tree import RootTree, SRVFTree, to_curves

_CUSP_COS = float(np.cos(np.deg2rad(150.0)))


@dataclasses.dataclass(frozen=True)
class Plausibility:
    """Result of `plausibility` for ``n`` roots.

    - `plausible`: ``(n,)`` every real lateral's length in range and no branch crossing itself.
    - `lengths_in_range`: ``(n,)`` criterion 1. `no_self_crossing`: ``(n,)`` criterion 2.
    - `n_out_of_range`, `n_crossing`: ``(n,)`` laterals out of range; branches crossing
      themselves (the main root counts as one branch).
    - `length_range`: ``(lo, hi)`` the allowed lateral lengths (reference range with tolerance).
    - `ks_statistic`, `ks_pvalue`: criterion 3, pooled lateral lengths against the reference
      (NaN when either side has no lateral).
    - `rate`: fraction of plausible roots.
    """

    plausible: np.ndarray
    lengths_in_range: np.ndarray
    no_self_crossing: np.ndarray
    n_out_of_range: np.ndarray
    n_crossing: np.ndarray
    length_range: tuple[float, float]
    ks_statistic: float
    ks_pvalue: float

    @property
    def rate(self) -> float:
        return float(np.mean(self.plausible)) if self.plausible.size else float("nan")


def _as_curves(trees, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(trees, SRVFTree):
        trees = to_curves(trees)
    if not isinstance(trees, RootTree):
        raise TypeError(
            f"plausibility: {what} must be a RootTree or SRVFTree (rootshape_jax.batch, "
            f"sample, modes), got {type(trees).__name__}."
        )
    main = np.asarray(trees.main, dtype=np.float64)
    lats = np.asarray(trees.laterals, dtype=np.float64)
    mask = np.asarray(trees.mask, dtype=bool)
    if main.ndim == 2:  # one tree
        main, lats, mask = main[None], lats[None], mask[None]
    main = main.reshape((-1,) + main.shape[-2:])
    lats = lats.reshape((-1,) + lats.shape[-3:])
    mask = mask.reshape((-1, mask.shape[-1]))
    if not (np.all(np.isfinite(main)) and np.all(np.isfinite(lats))):
        raise ValueError(f"plausibility: {what} holds NaN or inf coordinates.")
    return main, lats, mask


def _lengths(curves: np.ndarray) -> np.ndarray:
    return np.sum(np.linalg.norm(np.diff(curves, axis=-2), axis=-1), axis=-1)


def _cross2(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _segment_distance(p1, p2, q1, q2):
    """Closest distance between segments [p1, p2] and [q1, q2] (broadcast; any dimension)."""
    d1, d2, r = p2 - p1, q2 - q1, p1 - q1
    a = np.sum(d1 * d1, -1)
    e = np.sum(d2 * d2, -1)
    f = np.sum(d2 * r, -1)
    c = np.sum(d1 * r, -1)
    b = np.sum(d1 * d2, -1)
    denom = a * e - b * b
    safe_a = np.where(a > 0, a, 1.0)
    safe_e = np.where(e > 0, e, 1.0)
    s = np.where(denom > 1e-300, np.clip((b * f - c * e) / np.where(denom > 1e-300, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / safe_e
    s = np.where(t < 0, np.clip(-c / safe_a, 0, 1), np.where(t > 1, np.clip((b - c) / safe_a, 0, 1), s))
    t = np.clip(t, 0, 1)
    diff = (p1 + d1 * s[..., None]) - (q1 + d2 * t[..., None])
    return np.linalg.norm(diff, axis=-1)


def self_crossing(curve: np.ndarray, tolerance: float = 1e-3) -> bool:
    """True when a polyline crosses itself (module docstring, criterion 2)."""
    seg = np.diff(curve, axis=0)
    seg_len = np.linalg.norm(seg, axis=-1)
    keep = seg_len > 1e-12 * max(float(seg_len.sum()), 1e-300)
    pts = np.concatenate([curve[:1], curve[1:][keep]])
    seg = np.diff(pts, axis=0)
    m = seg.shape[0]
    if m < 2:
        return False
    lens = np.linalg.norm(seg, axis=-1)
    cos = np.sum(seg[1:] * seg[:-1], -1) / (lens[1:] * lens[:-1])
    if np.any(cos < _CUSP_COS):
        return True
    if m < 3:
        return False
    i, j = np.triu_indices(m, k=2)
    a0, a1, b0, b1 = pts[i], pts[i + 1], pts[j], pts[j + 1]
    if curve.shape[-1] == 2:
        da, db = a1 - a0, b1 - b0
        o1 = _cross2(da, b0 - a0)
        o2 = _cross2(da, b1 - a0)
        o3 = _cross2(db, a0 - b0)
        o4 = _cross2(db, a1 - b0)
        return bool(np.any((o1 * o2 < 0) & (o3 * o4 < 0)))
    return bool(np.any(_segment_distance(a0, a1, b0, b1) < tolerance * lens.sum()))


def plausibility(trees: RootTree | SRVFTree, reference: RootTree | SRVFTree, *, tolerance: float = 0.0) -> Plausibility:
    """Plausibility of (synthesised) `trees` against a `reference` population (module
    docstring): lateral lengths within the reference's range, no branch crossing itself, and
    the KS two-sample statistic of the pooled lateral lengths.

    - `trees`, `reference`: batched (or single) `RootTree`s or `SRVFTree`s in the same units,
      e.g. `sample(pca, key, n)` and the `batch(...)` the PCA's mean was fitted to.
    - `tolerance`: relative widening of the reference range (``[lo (1 − tol), hi (1 + tol)]``);
      in 3D also the crossing distance, relative to the branch length (at least 1e-3).
    """
    if not tolerance >= 0:
        raise ValueError(f"plausibility: tolerance must be >= 0, got {tolerance!r}.")
    main, lats, mask = _as_curves(trees, "trees")
    _, ref_lats, ref_mask = _as_curves(reference, "reference")
    if main.shape[-1] != ref_lats.shape[-1]:
        raise ValueError(
            f"plausibility: trees are {main.shape[-1]}D and the reference {ref_lats.shape[-1]}D; "
            "compare roots of one dimension."
        )
    ref_len = _lengths(ref_lats)[ref_mask]
    if ref_len.size == 0:
        raise ValueError("plausibility: the reference has no real lateral; give a population with laterals.")
    lo, hi = float(ref_len.min()) * (1 - tolerance), float(ref_len.max()) * (1 + tolerance)
    lengths = _lengths(lats)
    out = mask & ((lengths < lo) | (lengths > hi))
    n_out = out.sum(axis=1)
    tol3 = max(float(tolerance), 1e-3)
    n_cross = np.zeros(main.shape[0], dtype=np.int64)
    for r in range(main.shape[0]):
        n_cross[r] = int(self_crossing(main[r], tol3))
        for k in np.flatnonzero(mask[r]):
            n_cross[r] += int(self_crossing(lats[r, k], tol3))
    pooled = lengths[mask]
    if pooled.size:
        ks = scipy.stats.ks_2samp(pooled, ref_len)
        stat, p = float(ks.statistic), float(ks.pvalue)
    else:
        stat, p = float("nan"), float("nan")
    in_range = n_out == 0
    no_cross = n_cross == 0
    return Plausibility(
        plausible=in_range & no_cross,
        lengths_in_range=in_range,
        no_self_crossing=no_cross,
        n_out_of_range=n_out,
        n_crossing=n_cross,
        length_range=(lo, hi),
        ks_statistic=stat,
        ks_pvalue=p,
    )
