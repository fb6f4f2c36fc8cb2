"""Scoring an extraction against a hand tracing: match plants, compare lengths, counts, shape."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from .._errors import UnitError
from .._root import Root
from .._units import units_of


def total_length(root: Root) -> float:
    """Main-root length plus the lengths of all laterals."""
    return float(root.main_length + float(np.sum(root.lateral_lengths)))


@dataclasses.dataclass(frozen=True)
class PlantComparison:
    """One matched plant: extracted index, traced index, and the scores.

    Ratios are extracted / traced (1 is perfect). `elastic_distance` is the elastic tree
    distance (`rootshape_jax.distance`) between the two systems, each scaled to unit main-root
    length, so it scores shape only (lengths are in the ratios); nan when not computed.
    """

    extracted: int
    traced: int
    base_distance: float
    main_length_ratio: float
    total_length_ratio: float
    laterals_extracted: int
    laterals_traced: int
    elastic_distance: float


@dataclasses.dataclass(frozen=True)
class TracingComparison:
    """Result of `compare_to_tracing`: matched plants and the unmatched ones on either side."""

    plants: tuple[PlantComparison, ...]
    n_extracted: int
    n_traced: int
    unmatched_extracted: tuple[int, ...]
    unmatched_traced: tuple[int, ...]
    total_length_ratio: float  # all extracted plants' length / all traced plants' length
    recall: float  # fraction of the traced length within `tolerance` of the extraction
    precision: float  # fraction of the extracted length within `tolerance` of the tracing
    tolerance: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _base(root: Root) -> np.ndarray:
    return np.asarray(root.main[0, :2], dtype=np.float64)


def _check_same_unit(extracted: list[Root], traced: list[Root]) -> None:
    """`UnitError` when the two sets name different units: lengths, bases and `tolerance`
    would compare numbers in different units (an image read in mm against a tracing in px
    matched no plant and scored recall 0). Roots without a unit are not checked."""
    ext, tr = units_of(extracted), units_of(traced)
    if ext and tr and set(ext) != set(tr):
        raise UnitError(
            f"compare_to_tracing: the extracted roots are in {', '.join(ext.values())} and the traced "
            f"roots in {', '.join(tr.values())}; compare them in one unit: "
            "rootshape_jax.io.convert_units(roots, unit) on one side (pixels need a resolution), or "
            "read the image without pixels_per_mm / pixel_size to keep pixels."
        )


def compare_to_tracing(
    extracted: Sequence[Root],
    traced: Sequence[Root],
    *,
    elastic: bool = True,
    n_points: int = 64,
    max_base_distance: float | None = None,
    tolerance: float = 8.0,
) -> TracingComparison:
    """Match extracted plants to traced plants and score each pair.

    **Arguments**

    - `extracted`, `traced`: root systems in the same coordinates (e.g. `roots_from_image` and
      `read_rsml` of the same photograph, both in pixels); different ``metadata["unit"]`` on
      the two sides is a `UnitError`.
    - `elastic`: also compute the elastic distance of each matched pair (slower: one
      registration per pair).
    - `n_points`: points per branch for the elastic distance.
    - `max_base_distance`: plants are matched by their bases (the start of the main root) with
      an optimal assignment; a pair further apart than this is left unmatched. Default: half
      the traced main root's length.
    - `tolerance`: distance (same unit as the roots) for `recall` and `precision`: the
      fractions of traced (resp. extracted) length, sampled every ``tolerance / 4``, that lie
      within `tolerance` of the other set. Unlike length ratios they do not depend on
      whether touching roots are counted once or twice.

    **Returns** a `TracingComparison` whose plants are in traced order.
    """
    from scipy.optimize import linear_sum_assignment

    extracted, traced = list(extracted), list(traced)
    for name, roots in (("extracted", extracted), ("traced", traced)):
        if not all(isinstance(r, Root) for r in roots):
            raise TypeError(f"compare_to_tracing: {name} must be a sequence of Root.")
    _check_same_unit(extracted, traced)
    total_e = sum(total_length(r) for r in extracted)
    total_t = sum(total_length(r) for r in traced)
    overall = total_e / total_t if total_t > 0 else math.nan
    pairs: list[tuple[int, int, float]] = []
    if extracted and traced:
        cost = np.array([[np.linalg.norm(_base(e) - _base(t)) for t in traced] for e in extracted])
        rows, cols = linear_sum_assignment(cost)
        for i, j in zip(rows, cols):
            limit = 0.5 * traced[j].main_length if max_base_distance is None else float(max_base_distance)
            if cost[i, j] <= limit:
                pairs.append((int(i), int(j), float(cost[i, j])))
    pairs.sort(key=lambda p: p[1])
    plants = []
    for i, j, d in pairs:
        e, t = extracted[i], traced[j]
        plants.append(
            PlantComparison(
                extracted=i,
                traced=j,
                base_distance=d,
                main_length_ratio=float(e.main_length / t.main_length) if t.main_length > 0 else math.nan,
                total_length_ratio=total_length(e) / total_length(t) if total_length(t) > 0 else math.nan,
                laterals_extracted=int(e.n_laterals),
                laterals_traced=int(t.n_laterals),
                elastic_distance=_elastic(e, t, n_points) if elastic else math.nan,
            )
        )
    matched_e = {p.extracted for p in plants}
    matched_t = {p.traced for p in plants}
    recall, precision = _coverage(extracted, traced, float(tolerance))
    return TracingComparison(
        plants=tuple(plants),
        n_extracted=len(extracted),
        n_traced=len(traced),
        unmatched_extracted=tuple(i for i in range(len(extracted)) if i not in matched_e),
        unmatched_traced=tuple(j for j in range(len(traced)) if j not in matched_t),
        total_length_ratio=float(overall),
        recall=recall,
        precision=precision,
        tolerance=float(tolerance),
    )


def sample_branches(roots: Sequence[Root], step: float) -> np.ndarray:
    """Points every `step` along every branch (main and laterals) of `roots`, as (n, 2)."""
    out = [np.zeros((0, 2))]
    for r in roots:
        for b in (r.main, *r.laterals):
            b = np.asarray(b, dtype=np.float64)[:, :2]
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(b, axis=0), axis=1))])
            s = np.arange(0.0, cum[-1] + 1e-12, step)
            out.append(np.stack([np.interp(s, cum, b[:, 0]), np.interp(s, cum, b[:, 1])], axis=1))
    return np.concatenate(out)


def _coverage(extracted, traced, tol: float) -> tuple[float, float]:
    from scipy.spatial import cKDTree

    pe, pt = sample_branches(extracted, tol / 4), sample_branches(traced, tol / 4)
    if len(pe) == 0 or len(pt) == 0:
        return 0.0, 0.0
    recall = float(np.mean(cKDTree(pe).query(pt)[0] <= tol))
    precision = float(np.mean(cKDTree(pt).query(pe)[0] <= tol))
    return recall, precision


def _elastic(a: Root, b: Root, n_points: int) -> float:
    from .._registration import distance
    from .._tree import batch, unstack

    # 2-D: drop a z column (RSML tracings are often 2-D stored with z = 0).
    a2 = (
        dataclasses.replace(a, main=a.main[:, :2], laterals=tuple(l[:, :2] for l in a.laterals))
        if a.main.shape[1] > 2
        else a
    )
    b2 = (
        dataclasses.replace(b, main=b.main[:, :2], laterals=tuple(l[:, :2] for l in b.laterals))
        if b.main.shape[1] > 2
        else b
    )
    # The distance ignores translation: both bases at (0, 0), where float32 holds the most digits.
    a2, b2 = (
        dataclasses.replace(r, main=r.main - r.main[0], laterals=tuple(l - r.main[0] for l in r.laterals), children=())
        for r in (a2, b2)
    )
    ta, tb = unstack(batch([a2, b2], n_points=n_points, normalise_scale=True))
    return float(distance(ta, tb))
