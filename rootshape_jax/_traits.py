"""Classical root-architecture traits of a `Root` (numpy), and a CSV writer for trait tables.

The trait regression of the paper (§5.2) uses ``main_length``, ``mean_lateral_length`` and
``std_lateral_length``; those names are stable.
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import scipy.spatial

from ._errors import InvalidRootError
from ._root import Root, is_plant_system, plant_axes, polyline_length

TRAIT_NAMES: tuple[str, ...] = (
    "main_length",
    "n_laterals",
    "lateral_density",
    "mean_lateral_length",
    "std_lateral_length",
    "total_lateral_length",
    "total_length",
    "main_tortuosity",
    "mean_insertion_angle",
    "depth",
    "width",
    "convex_hull_area",
    "convex_hull_volume",
)


def _point_at(points: np.ndarray, cum: np.ndarray, s: float) -> np.ndarray:
    """Point of the polyline at arc length ``s`` (clipped to the polyline)."""
    s = min(max(s, 0.0), float(cum[-1]))
    return np.array([np.interp(s, cum, points[:, j]) for j in range(points.shape[1])])


def _cumlen(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else None


def _stub(cum: np.ndarray) -> float:
    """Segments shorter than this are a tracer's stubs, not a direction: half the polyline's
    median nonzero segment length (RhizoScan starts each lateral with a 1-2 px segment from
    the parent node, at any angle, before segments of 5-7 px)."""
    seg = np.diff(cum)
    seg = seg[seg > 0]
    return 0.5 * float(np.median(seg)) if seg.size else 0.0


def _main_direction(main: np.ndarray, cum: np.ndarray, s: float, window: float | None):
    if window is None:
        # The segment containing arc length s (a vertex belongs to the segment that starts
        # there; the tip to the last segment); if it is a stub, a chord of one typical segment
        # centred at s.
        seg = min(int(np.searchsorted(cum, s, side="right")) - 1, len(main) - 2)
        seg = max(seg, 0)
        stub = _stub(cum)
        if cum[seg + 1] - cum[seg] >= stub > 0:
            return _unit(main[seg + 1] - main[seg])
        window = 2.0 * stub
    return _unit(_point_at(main, cum, s + window / 2) - _point_at(main, cum, s - window / 2))


def _lateral_direction(lat: np.ndarray, window: float | None):
    cum = _cumlen(lat)
    if window is None:
        # To the first vertex past the stubs (the first segment on a regular polyline).
        far = np.flatnonzero(cum >= _stub(cum))
        far = far[far > 0]
        return _unit(lat[far[0]] - lat[0]) if far.size else None
    return _unit(_point_at(lat, cum, window) - lat[0])


def insertion_angles(root: Root, *, window: float | None = None) -> np.ndarray:
    """Insertion angle of every lateral, in degrees (NaN where a direction is undefined).

    The angle between the lateral's initial direction and the main root's local direction at
    the lateral's attachment point (arc-length fraction ``root.attach``), in [0, 180].
    With ``window=None`` the directions are those of the lateral's first segment and of the
    main root's segment containing the attachment point. A segment shorter than half the
    polyline's median segment is a tracer's stub, not a direction (RhizoScan starts every
    lateral with a 1-2 px segment from the parent node, which made every plate lateral 90°):
    the lateral's direction then reaches past its stubs, and the main root's is a chord of
    one median segment centred at the attachment point.
    With a ``window`` (arc length, in the root's units) they are chords: the lateral from its
    base to the point ``window`` along it; the main root from ``window/2`` before to
    ``window/2`` after the attachment point — smoother on noisy tracings.
    """
    if window is not None and not window > 0:
        raise ValueError(f"`window` must be a positive arc length or None, got {window!r}.")
    main = np.asarray(root.main, dtype=float)
    cum = _cumlen(main)
    angles = np.full(root.n_laterals, np.nan)
    for k, (lat, a) in enumerate(zip(root.laterals, root.attach)):
        t = _main_direction(main, cum, float(a) * cum[-1], window)
        u = _lateral_direction(np.asarray(lat, dtype=float), window)
        if t is not None and u is not None:
            angles[k] = math.degrees(math.acos(float(np.clip(t @ u, -1.0, 1.0))))
    return angles


def _hull_measure(points: np.ndarray) -> float:
    """Area (2D) or volume (3D) of the convex hull; 0 for degenerate (flat) point sets."""
    pts = np.unique(points, axis=0)
    if len(pts) <= pts.shape[1]:
        return 0.0
    centred = pts - pts.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-12 * max(1.0, float(np.abs(centred).max()))) < pts.shape[1]:
        return 0.0
    try:
        return float(scipy.spatial.ConvexHull(pts).volume)
    except scipy.spatial.QhullError:
        return 0.0


def _diameter(points: np.ndarray) -> float:
    """Largest distance between two points (on the convex hull's vertices when 2D)."""
    if points.shape[1] == 1:
        return float(points.max() - points.min())
    pts = np.unique(points, axis=0)
    if _hull_measure(pts) > 0:
        pts = pts[scipy.spatial.ConvexHull(pts).vertices]
    else:
        # Collinear (or a single point): the extent along the principal direction.
        centred = pts - pts.mean(axis=0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        proj = centred @ axis
        return float(proj.max() - proj.min())
    diff = pts[:, None, :] - pts[None, :, :]
    return float(np.sqrt(np.max(np.sum(diff * diff, axis=-1))))


def deepest_order(root: Root) -> int:
    """Highest lateral order present in `root` (0: no laterals, 1: first-order laterals only,
    2: laterals of laterals in `Root.children`, ...)."""
    best, stack = 0, [(root, 0)]
    while stack:  # iterative: deep files nest deeply
        node, order = stack.pop()
        if node.n_laterals:
            best = max(best, order + 1)
        stack.extend((c, order + 1) for c in node.children)
    return best


def _axes(root: Root) -> tuple[Root, ...]:
    """The top-level branches a root's traits describe: its own main root, or a plant's
    axes (`is_plant_system`; an axis known only as a polyline has no laterals)."""
    if not is_plant_system(root) or not root.n_laterals:
        return (root,)  # a plant without axes: its (virtual) main root alone
    return plant_axes(root)


def order_traits(root: Root, orders: int) -> dict:
    """Per-order counts and lengths for lateral orders 1 … `orders` (0 where an order is
    absent): ``n_laterals_order{k}``, ``length_order{k}`` (total length of the order-k
    laterals) and ``mean_length_order{k}``. Order k+1 comes from `Root.children`. For a
    plant's system the orders count from its axes (order 1: the axes' laterals)."""
    lengths: list[list[float]] = [[] for _ in range(orders)]
    stack = [(axis, 1) for axis in _axes(root)]
    while stack:
        node, order = stack.pop()
        if order > orders:
            continue
        lengths[order - 1].extend(polyline_length(np.asarray(lat, dtype=float)) for lat in node.laterals)
        stack.extend((c, order + 1) for c in node.children)
    out = {}
    for k, ls in enumerate(lengths, start=1):
        out[f"n_laterals_order{k}"] = len(ls)
        out[f"length_order{k}"] = float(np.sum(ls)) if ls else 0.0
        out[f"mean_length_order{k}"] = float(np.mean(ls)) if ls else 0.0
    return out


def _lateral_order(root: Root) -> int:
    """Deepest lateral order of `root`, counted from its axes for a plant's system."""
    return max(deepest_order(axis) for axis in _axes(root))


def _root_traits(root: Root, window: float | None) -> dict:
    if not isinstance(root, Root):
        raise InvalidRootError(
            f"traits() expects a rootshape_jax.Root or a sequence of them, got {type(root).__name__}."
        )
    axes = _axes(root)
    # A plant's main root is its longest axis; its laterals are those of every axis.
    axis_len = np.array([polyline_length(np.asarray(a.main, dtype=float)) for a in axes])
    main = np.asarray(axes[int(np.argmax(axis_len))].main, dtype=float)
    d = main.shape[1]
    lats = [np.asarray(lat, dtype=float) for a in axes for lat in a.laterals]
    lat_len = np.array([polyline_length(lat) for lat in lats])
    main_len = polyline_length(main)
    n = len(lat_len)
    pts = np.concatenate([np.asarray(a.main, dtype=float) for a in axes] + lats, axis=0)
    chord = float(np.linalg.norm(main[-1] - main[0]))
    angles = np.concatenate([insertion_angles(a, window=window) for a in axes])
    horizontal = pts[:, :-1]
    total_axis_len = float(axis_len.sum())
    return {
        "name": root.name,
        "main_length": main_len,
        "n_laterals": n,
        "lateral_density": n / total_axis_len if total_axis_len > 0 else math.nan,
        "mean_lateral_length": float(lat_len.mean()) if n else 0.0,
        "std_lateral_length": float(lat_len.std()) if n else 0.0,
        "total_lateral_length": float(lat_len.sum()),
        "total_length": total_axis_len + float(lat_len.sum()),
        "main_tortuosity": main_len / chord if chord > 0 else math.nan,
        "mean_insertion_angle": float(np.nanmean(angles)) if np.any(np.isfinite(angles)) else math.nan,
        "depth": float(pts[:, -1].max() - pts[:, -1].min()),
        "width": _diameter(horizontal),
        "convex_hull_area": _hull_measure(pts) if d == 2 else _hull_measure(horizontal),
        "convex_hull_volume": _hull_measure(pts) if d == 3 else math.nan,
    }


def traits(
    root_or_roots: Root | Sequence[Root], *, window: float | None = None, orders: int | None = None
) -> dict | list[dict]:
    """Architecture traits of one root (a dict) or of each root of a sequence (a list of dicts).

    Lengths are in the root's own units (see ``root.metadata.get("unit")``), angles in degrees.
    Gravity is along the last axis (y in 2D, z in 3D; up or down does not matter here), the
    other axes are horizontal. Points are those of the main root and of every lateral.

    - ``name``: ``root.name``.
    - ``unit``: the unit of the lengths, ``root.metadata.get("unit")`` (None when unknown);
      `traits_to_csv` puts it into the column names.
    - ``main_length``: polyline length of the main root.
    - ``n_laterals``: number of first-order laterals.
    - ``lateral_density``: ``n_laterals / main_length`` (laterals per unit main length).
    - ``mean_lateral_length``, ``std_lateral_length``: mean and population standard deviation
      (ddof = 0) of the lateral lengths; 0 when there are no laterals, so the regression traits
      stay finite.
    - ``total_lateral_length``: sum of the lateral lengths; ``total_length`` adds the main root.
    - ``main_tortuosity``: main length / straight distance from base to tip (≥ 1; NaN if closed).
    - ``mean_insertion_angle``: mean over laterals of `insertion_angles` (angle between the
      lateral's initial direction and the main root's local direction, degrees, in [0, 180];
      ``window`` as there); NaN without laterals. With the default ``window=None`` the
      directions are the tracing's first segments (past a tracer's stub), which on pixel
      tracings are a few pixels long and take few values (e.g. 45°, 90°): pass a ``window``
      (an arc length in the roots' unit, e.g. 20 px) for angles over a chord.
    - ``depth``: extent along the gravity axis (max − min of the last coordinate).
    - ``width``: horizontal extent, the largest distance between two points projected on the
      horizontal line (2D: max x − min x) or plane (3D).
    - ``convex_hull_area``: 2D — area of the convex hull of all points; 3D — area of the convex
      hull of the points projected on the horizontal plane (the root system's footprint, which
      does not depend on how the plant is turned about the vertical). 0 for degenerate hulls.
    - ``convex_hull_volume``: 3D — volume of the convex hull; NaN in 2D (a 2D tracing has no
      volume).

    The traits above use the main root and the first-order laterals. Higher orders (whole root
    systems, `Root.children`) add per-order columns for lateral orders k = 1 … `orders`
    (`order_traits`): ``n_laterals_order{k}``, ``length_order{k}`` (their total length) and
    ``mean_length_order{k}``. By default `orders` is the deepest order present in the root (in
    any root of a sequence, so the table is rectangular) when that is 2 or more; roots with
    first-order laterals only get no extra columns. ``orders=N`` always gives orders 1 … N
    (0 where absent).

    **A plant's system** (``read_rsml(by="plant")``, `rootshape_jax.io.plant_system`: axes
    under a virtual main root of zero length) is described as a plant: its main root is its
    longest axis (``main_length``, ``main_tortuosity``); its laterals are the first-order
    laterals of every axis (counts, lengths, insertion angles on their own axis);
    ``lateral_density`` divides by the summed length of the axes; ``total_length`` is every
    axis plus those laterals; the extents and hulls cover the axes and their laterals; orders
    count from the axes (order 1: the axes' laterals). A column ``n_axes`` (1 for single
    roots) is added when any root is a plant's system. A plant of one axis therefore has the
    traits of that axis read as a single root.
    """
    if orders is not None and (isinstance(orders, bool) or not isinstance(orders, (int, np.integer)) or orders < 0):
        raise ValueError(f"`orders` must be a whole number >= 0 or None, got {orders!r}.")
    single = isinstance(root_or_roots, Root)
    if not single and (isinstance(root_or_roots, (str, bytes, Mapping)) or not isinstance(root_or_roots, Iterable)):
        raise InvalidRootError(
            f"traits() expects a rootshape_jax.Root or a sequence of them, got {type(root_or_roots).__name__}."
        )
    roots = [root_or_roots] if single else list(root_or_roots)
    # Each row names its roots' length unit (None when unknown), so `traits_to_csv` labels the
    # columns with it (main_length_mm, ...).
    rows = [_root_traits(r, window) for r in roots]
    rows = [{"name": row.pop("name"), "unit": r.metadata.get("unit"), **row} for row, r in zip(rows, roots)]
    if any(is_plant_system(r) for r in roots):
        rows = [
            {"name": row.pop("name"), "n_axes": r.n_laterals if is_plant_system(r) else 1, **row}
            for row, r in zip(rows, roots)
        ]
    n = max((_lateral_order(r) for r in roots), default=0) if orders is None else orders
    if orders is not None or n >= 2:
        for row, r in zip(rows, roots):
            row.update(order_traits(r, n))
    return rows[0] if single else rows


# Power of length in each trait's unit (None: no unit); the insertion angle is in degrees.
TRAIT_LENGTH_POWER: dict[str, int | None] = {
    "main_length": 1,
    "n_laterals": None,
    "lateral_density": -1,
    "mean_lateral_length": 1,
    "std_lateral_length": 1,
    "total_lateral_length": 1,
    "total_length": 1,
    "main_tortuosity": None,
    "depth": 1,
    "width": 1,
    "convex_hull_area": 2,
    "convex_hull_volume": 3,
}


def trait_column(name: str, unit: str | None) -> str:
    """The column name of trait `name` with its unit: ``main_length_mm``,
    ``convex_hull_area_mm2``, ``lateral_density_per_mm``, ``mean_insertion_angle_deg``,
    ``length_order2_mm``
    (pixels: ``px``). Names of other columns, and every name when `unit` is None, are kept."""
    if name == "mean_insertion_angle":
        return f"{name}_deg"
    power = TRAIT_LENGTH_POWER.get(name)
    if re.fullmatch(r"(mean_)?length_order\d+", name):
        power = 1
    if power is None or unit is None:
        return name
    u = "px" if unit.lower() in ("pixel", "pixels", "px") else unit.replace(" ", "_")
    if power == -1:
        return f"{name}_per_{u}"
    return f"{name}_{u}" + (str(power) if power > 1 else "")


def traits_to_csv(rows: dict | Sequence[Mapping], path: str | os.PathLike, *, unit: str | None = None) -> None:
    """Write trait rows (from `traits`, possibly with extra keys) to a CSV file with a header.

    Columns are the union of the rows' keys in order of first appearance; missing cells are
    empty. Floats are written with full precision (``repr``), so reading back is exact.
    Trait columns carry their unit (`trait_column`): `unit`, or by default the rows' common
    ``"unit"`` value when they have one (the command line adds it); angles are in degrees.
    """
    if isinstance(rows, Mapping):
        rows = [rows]
    rows = list(rows)
    if not all(isinstance(r, Mapping) for r in rows):
        raise ValueError("traits_to_csv expects a dict or a sequence of dicts (from traits()).")
    if unit is None:
        units = {r.get("unit") for r in rows}
        unit = units.pop() if len(units) == 1 else None
    rows = [{trait_column(k, unit): v for k, v in r.items()} for r in rows]
    columns: list[str] = []
    for r in rows:
        for key in r:
            if key not in columns:
                columns.append(key)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="", lineterminator="\n")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})
