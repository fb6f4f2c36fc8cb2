"""Shrinkage of a geodesic: how far a path's total root length falls below the straight
interpolation of its endpoints' lengths (the paper's criticism of father–child methods,
Section 1: "a significant shrinkage along the geodesics"). Usable with every method's path.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import numpy as np

from .._root import Root
from .._tree import RootTree, to_roots
from ._fatherchild import check_root, total_length


class Shrinkage(eqx.Module):
    """Total lengths along a path compared with the straight interpolation of the ends.

    **Fields**

    - `lengths`: ``(n_steps,)`` total length (main root + every lateral) of each step.
    - `interpolated`: ``(n_steps,)`` ``(1 − τ) L_0 + τ L_1`` with ``τ = linspace(0, 1, n_steps)``.
    - `min_ratio`: smallest ``lengths / interpolated`` over the path (1 = no shrinkage).
    - `mean_shortfall`: mean over the interior steps of ``1 − lengths / interpolated``
      (signed: negative when the path is longer than the interpolation; 0 with two steps).
    """

    lengths: np.ndarray
    interpolated: np.ndarray
    min_ratio: float
    mean_shortfall: float


def geodesic_shrinkage(path: Sequence[Root] | RootTree) -> Shrinkage:
    """Shrinkage of a path of roots at equally spaced ``τ``: a list of `Root` (the baselines'
    geodesics) or a batched `RootTree` (`rootshape_jax.geodesic`; null slots are dropped)."""
    if isinstance(path, RootTree):
        if path.main.ndim != 3:
            raise ValueError(
                "geodesic_shrinkage: expected a batched RootTree (leading axis = steps), got "
                f"main of shape {path.main.shape}."
            )
        roots = to_roots(path)
    elif isinstance(path, Root):
        raise TypeError("geodesic_shrinkage: expected a path (list of Root), got a single Root.")
    else:
        roots = list(path)
    if len(roots) < 2:
        raise ValueError(f"geodesic_shrinkage: a path needs at least 2 steps, got {len(roots)}.")
    lengths = np.array([total_length(check_root(r, f"geodesic_shrinkage: step {i}")) for i, r in enumerate(roots)])
    taus = np.linspace(0.0, 1.0, len(roots))
    interpolated = (1 - taus) * lengths[0] + taus * lengths[-1]
    positive = interpolated > 0
    ratio = np.where(positive, lengths / np.where(positive, interpolated, 1.0), 1.0)
    interior = ratio[1:-1]
    return Shrinkage(
        lengths=lengths,
        interpolated=interpolated,
        min_ratio=float(ratio.min()),
        mean_shortfall=float(np.mean(1.0 - interior)) if interior.size else 0.0,
    )
