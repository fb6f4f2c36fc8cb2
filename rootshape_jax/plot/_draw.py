"""Shared drawing machinery: slot colours, input conversion, one root on one Axes, layout.

Nothing here touches matplotlib's global state: figures are `matplotlib.figure.Figure`
objects (no GUI, no backend choice) unless the user already imported `matplotlib.pyplot`, in
which case they are made through pyplot so that notebooks and `plt.show()` display them.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Sequence
from typing import Any

import matplotlib
import matplotlib.colors as mcolors
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from .._mean import KarcherMean
from .._root import Root
from .._tree import RootTree, SRVFTree, to_curves

MAIN_COLOR = "#1a1a1a"
LATERAL_COLOR = "#a0622d"  # every lateral, when slot colours are off
NEUTRAL_COLOR = "#6e6e6e"


def _palette() -> tuple[str, ...]:
    tab10 = matplotlib.colormaps["tab10"].colors
    tab20 = matplotlib.colormaps["tab20"].colors
    # Grey is dropped: it reads as the (dark) main root or as a null.
    dark = [c for i, c in enumerate(tab10) if i != 7]
    light = [c for i, c in enumerate(tab20) if i % 2 == 1 and i != 15]
    tab20b = matplotlib.colormaps["tab20b"].colors
    extra = [tab20b[i] for i in (0, 4, 8, 12, 16, 2, 6, 10, 14, 18)]
    return tuple(mcolors.to_hex(c) for c in dark + light + extra)


SLOT_PALETTE = _palette()


def slot_color(k: int) -> str:
    """Colour of lateral slot ``k``: fixed, so one slot has one colour in every plot.

    The palette is matplotlib's qualitative ``tab10`` (without grey), the light half of
    ``tab20``, then ten colours of ``tab20b``: 28 colours, then it repeats.
    """
    return SLOT_PALETTE[int(k) % len(SLOT_PALETTE)]


def shade(color: Any, k: int) -> str:
    """The colour of child slot ``k`` of a branch drawn in ``color``: the parent's colour mixed
    with white (30, 40 or 50 %, by ``k``), so a branch's children read as its family and
    siblings stay apart. Deeper orders are shades of shades, lighter at every level."""
    rgb = np.asarray(mcolors.to_rgb(color))
    t = 0.3 + 0.1 * (int(k) % 3)
    return mcolors.to_hex((1 - t) * rgb + t)


def branch_color(slot: Sequence[int]) -> str:
    """Colour of the branch at ``slot = (k1, k2, …)``: `slot_color(k1)` for a first-order
    lateral, and for a deeper branch a `shade` of its parent's colour. It depends on the slot
    only, so matched branches (same slot after registration, or along a geodesic) share it
    at every level."""
    return deeper_color(tuple(slot), None, True)


# --------------------------------------------------------------------------------------------
# Inputs -> plain numpy drawings


@dataclasses.dataclass(frozen=True)
class Drawing:
    """One root as numpy polylines: what the plotting code draws."""

    main: np.ndarray  # (n, d)
    laterals: tuple[tuple[int, np.ndarray], ...]  # (slot, (m, d)) for real laterals
    nulls: tuple[tuple[int, np.ndarray], ...]  # (slot, (d,)) position of padding slots
    unit: str | None = None
    name: str = ""
    main_radius: np.ndarray | None = None  # (n,) when known
    lateral_radii: tuple[tuple[int, np.ndarray], ...] = ()  # (slot, (m,)) where known
    # Second-order laterals and below: (slot (k1, …, kℓ), (m, d) polyline, (m,) radius or None).
    deeper: tuple[tuple[tuple[int, ...], np.ndarray, np.ndarray | None], ...] = ()
    # Padding slots below the first order whose parent is real: (slot (k1, …, kℓ), (d,) position).
    deeper_nulls: tuple[tuple[tuple[int, ...], np.ndarray], ...] = ()

    @property
    def dim(self) -> int:
        return int(self.main.shape[1])

    def shifted(self, shift: np.ndarray) -> "Drawing":
        """The same drawing translated by ``shift`` (radii, names and units kept)."""
        return self._moved(lambda x: x + shift)

    def turned(self, rotation: np.ndarray) -> "Drawing":
        """The same drawing turned by ``rotation`` ``[d, d]`` about its main root's base."""
        o = self.main[0]
        return self._moved(lambda x: o + (x - o) @ rotation.T)

    def _moved(self, f) -> "Drawing":
        """Every point of the drawing mapped by ``f`` (radii, names and units kept)."""
        return dataclasses.replace(
            self,
            main=f(self.main),
            laterals=tuple((k, f(lat)) for k, lat in self.laterals),
            nulls=tuple((k, f(p)) for k, p in self.nulls),
            deeper=tuple((slot, f(b), r) for slot, b, r in self.deeper),
            deeper_nulls=tuple((slot, f(p)) for slot, p in self.deeper_nulls),
        )


def turned_drawings(drawings: list, rotation: Any, *, what: str) -> list:
    """`drawings` turned about their bases by `rotation` (``[d, d]``), or as they are for None."""
    if rotation is None:
        return drawings
    R = np.asarray(rotation, dtype=float)
    d = drawings[0].dim
    if R.shape != (d, d) or not np.all(np.isfinite(R)):
        raise ValueError(
            f"{what}: rotation must be a finite [{d}, {d}] matrix (rootshape_jax.upright_rotation(mean, "
            f"trees)), got shape {R.shape}."
        )
    return [x.turned(R) for x in drawings]


def _root_deeper(root: Root) -> tuple:
    """Every branch below the first-order laterals of ``root``, keyed by its slot path."""
    out = []
    stack = [((k,), c) for k, c in enumerate(root.children)][::-1]
    while stack:
        slot, node = stack.pop()
        for k, lat in enumerate(node.laterals):
            r = None if node.lateral_radii is None else np.asarray(node.lateral_radii[k], dtype=float)
            if node.children and node.children[k].main_radius is not None:
                r = np.asarray(node.children[k].main_radius, dtype=float)
            out.append((slot + (k,), np.asarray(lat, dtype=float), r))
        stack.extend([(slot + (k,), c) for k, c in enumerate(node.children)][::-1])
    return tuple(out)


def _from_root(root: Root) -> Drawing:
    unit = root.metadata.get("unit")
    main_radius = None if root.main_radius is None else np.asarray(root.main_radius, dtype=float)
    lateral_radii = ()
    if root.lateral_radii is not None:
        lateral_radii = tuple((k, np.asarray(r, dtype=float)) for k, r in enumerate(root.lateral_radii))
    return Drawing(
        main=np.asarray(root.main, dtype=float),
        laterals=tuple((k, np.asarray(lat, dtype=float)) for k, lat in enumerate(root.laterals)),
        nulls=(),
        unit=str(unit) if unit is not None else None,
        name=root.name,
        main_radius=main_radius,
        lateral_radii=lateral_radii,
        deeper=_root_deeper(root),
    )


def _from_arrays(main, lats, mask, main_r=None, lat_r=None, deeper=()) -> Drawing:
    """``deeper``: one ``(curves [K1..Kℓ, T, d], mask [K1..Kℓ], radius or None)`` per level."""
    # In a batch, a root without radius data is padded with radius 0: draw it as unknown.
    known = main_r is not None and (np.any(main_r > 0) or np.any(lat_r[mask] > 0))
    branches, null_slots, parent = [], [], np.asarray(mask, bool)
    for curves, m, r in deeper:
        for slot in zip(*np.nonzero(m)):
            slot = tuple(int(k) for k in slot)
            branches.append((slot, curves[slot], r[slot] if known and r is not None else None))
        # A null under a null parent is no slot the root uses: only a real parent's nulls.
        for slot in zip(*np.nonzero(~m & parent[..., None])):
            slot = tuple(int(k) for k in slot)
            null_slots.append((slot, curves[slot][0]))
        parent = np.asarray(m, bool)
    return Drawing(
        main=main,
        laterals=tuple((k, lats[k]) for k in range(lats.shape[0]) if mask[k]),
        nulls=tuple((k, lats[k, 0]) for k in range(lats.shape[0]) if not mask[k]),
        main_radius=main_r if known else None,
        lateral_radii=tuple((k, lat_r[k]) for k in range(lats.shape[0]) if mask[k]) if known else (),
        deeper=tuple(branches),
        deeper_nulls=tuple(null_slots),
    )


def _curves(x: Any, what: str) -> RootTree:
    if isinstance(x, KarcherMean):  # the result of karcher_mean draws as its mean root
        x = x.mean
    if isinstance(x, SRVFTree):
        return to_curves(x)
    if isinstance(x, RootTree):
        return x
    raise TypeError(
        f"{what}: expected a rootshape_jax.Root or RootTree, got {type(x).__name__}. "
        "Build a RootTree with rootshape_jax.batch(roots)."
    )


def _tree_drawings(tree: RootTree) -> np.ndarray:
    """Object array of Drawings with the tree's batch shape (one host transfer per field)."""
    main = np.asarray(tree.main, dtype=float)
    lats = np.asarray(tree.laterals, dtype=float)
    mask = np.asarray(tree.mask, dtype=bool)
    main_r = getattr(tree, "main_radius", None)
    lat_r = getattr(tree, "lateral_radius", None)
    if main_r is not None and lat_r is not None:
        main_r = np.asarray(main_r, dtype=float)
        lat_r = np.asarray(lat_r, dtype=float)
    else:
        main_r = lat_r = None
    levels = [
        (
            np.asarray(lv.curves, dtype=float),
            np.asarray(lv.mask, dtype=bool),
            None if lv.radius is None or main_r is None else np.asarray(lv.radius, dtype=float),
        )
        for lv in tree.deeper
    ]
    batch = main.shape[:-2]
    out = np.empty(batch, dtype=object)
    for idx in np.ndindex(*batch):
        radii = (main_r[idx], lat_r[idx]) if main_r is not None else (None, None)
        deeper = [(c[idx], m[idx], None if r is None else r[idx]) for c, m, r in levels]
        out[idx] = _from_arrays(main[idx], lats[idx], mask[idx], *radii, deeper=deeper)
    return out


def as_drawing(x: Any, *, what: str) -> Drawing:
    """One root: a `Root`, or an unbatched `RootTree` / `SRVFTree`."""
    if isinstance(x, Root):
        return _from_root(x)
    tree = _curves(x, what)
    if tree.batch_shape != ():
        raise ValueError(
            f"{what}: expected one root, got a batched RootTree with batch shape "
            f"{tree.batch_shape}. Pick one with rootshape_jax.unstack(tree)[i], or use a plot "
            "made for several roots (plot_geodesic, plot_mean, ...)."
        )
    return _tree_drawings(tree)[()]


def as_drawing_list(xs: Any, *, what: str) -> list[Drawing]:
    """Several roots: a batched `RootTree` (one leading axis) or a sequence of single roots."""
    if isinstance(xs, (RootTree, SRVFTree)):
        tree = _curves(xs, what)
        if len(tree.batch_shape) != 1:
            raise ValueError(
                f"{what}: expected a RootTree with one leading batch axis, got batch shape "
                f"{tree.batch_shape}. Use rootshape_jax.batch(roots) or stack(trees)."
            )
        out = list(_tree_drawings(tree))
    elif isinstance(xs, Root):
        raise TypeError(f"{what}: expected several roots, got one Root; wrap it in a list.")
    elif isinstance(xs, Sequence) or isinstance(xs, np.ndarray):
        out = [as_drawing(x, what=f"{what}[{i}]") for i, x in enumerate(xs)]
    else:
        raise TypeError(f"{what}: expected a batched RootTree or a list of roots, got {type(xs).__name__}.")
    if not out:
        raise ValueError(f"{what}: no roots to draw.")
    dims = {d.dim for d in out}
    if len(dims) != 1:
        raise ValueError(f"{what}: roots mix dimensions {sorted(dims)}; draw 2D and 3D roots apart.")
    return out


def as_drawing_grid(xs: Any, *, what: str) -> list[list[Drawing]]:
    """Rows of roots: a RootTree with two batch axes, one batch axis (a single row), or a
    sequence of rows."""
    if isinstance(xs, (RootTree, SRVFTree)):
        tree = _curves(xs, what)
        if len(tree.batch_shape) not in (1, 2):
            raise ValueError(
                f"{what}: expected a RootTree with batch shape (rows, columns), or (columns,) for "
                f"one row, got {tree.batch_shape}."
            )
        grid = _tree_drawings(tree)
        # One batch axis is one row: what modes(pc, alphas, component=i) returns.
        return [list(grid)] if grid.ndim == 1 else [list(row) for row in grid]
    if isinstance(xs, Root) or not isinstance(xs, Sequence):
        raise TypeError(
            f"{what}: expected a RootTree of batch shape (rows, columns) or (columns,), or a list of rows, got "
            f"{type(xs).__name__}."
        )
    rows = [as_drawing_list(row, what=f"{what}[{i}]") for i, row in enumerate(xs)]
    if not rows:
        raise ValueError(f"{what}: no roots to draw.")
    return rows


def common_unit(drawings: Sequence[Drawing]) -> str | None:
    units = {d.unit for d in drawings}
    return units.pop() if len(units) == 1 else None


# --------------------------------------------------------------------------------------------
# Projections and colours

COLUMNS = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2), "3d": (0, 1, 2)}
_LABELS = {
    (2, "xy"): ("x", "y (depth)"),
    (3, "xz"): ("x", "z (depth)"),
    (3, "yz"): ("y", "z (depth)"),
    (3, "xy"): ("x", "y"),
    (3, "3d"): ("x", "y", "z (depth)"),
}


def resolve_projection(dim: int, projection: str | None) -> str:
    """``None`` means ``"xy"`` for 2D roots and the side view ``"xz"`` (x, depth) for 3D."""
    if projection is None:
        return "xy" if dim == 2 else "xz"
    allowed = ("xy",) if dim == 2 else ("xz", "yz", "xy", "3d")
    if projection not in allowed:
        raise ValueError(
            f"projection={projection!r} is not available for {dim}D roots; choose one of "
            f"{allowed} (None picks {allowed[0]!r})."
        )
    return projection


def axis_labels(dim: int, projection: str, unit: str | None) -> tuple[str, ...]:
    suffix = f" [{unit}]" if unit else ""
    return tuple(lab + suffix for lab in _LABELS[(dim, projection)])


def _is_single_color(colors: Any) -> bool:
    if isinstance(colors, str):
        return True
    return isinstance(colors, tuple) and len(colors) in (3, 4) and all(isinstance(c, (int, float)) for c in colors)


def check_colors(colors: Any) -> None:
    if colors is None:
        return
    if _is_single_color(colors):
        if not mcolors.is_color_like(colors):
            raise ValueError(f"colors={colors!r} is not a matplotlib colour.")
        return
    if not isinstance(colors, Sequence) or not all(mcolors.is_color_like(c) for c in colors):
        raise ValueError(
            "colors must be None (slot colours), one matplotlib colour (the whole root), or a "
            f"sequence of colours indexed by lateral slot; got {colors!r}."
        )


def _lateral_color(k: int, colors: Any, slot_colors: bool) -> Any:
    if colors is None:
        return slot_color(k) if slot_colors else LATERAL_COLOR
    if _is_single_color(colors):
        return colors
    if k >= len(colors):
        raise ValueError(
            f"colors has {len(colors)} entries but the root uses lateral slot {k}; give one "
            "colour per slot (the capacity K), or None for the default slot colours."
        )
    return colors[k]


# Line widths from radii: the thickest point of a root is drawn RADIUS_WIDTH x `linewidth`
# points wide, thinner points in proportion, never thinner than MIN_WIDTH x `linewidth`.
RADIUS_WIDTH = 2.4
MIN_WIDTH = 0.25


def segment_widths(radius: np.ndarray, reference: float, linewidth: float) -> np.ndarray:
    """Line width (points) of each segment of a branch with ``radius`` at its points: the mean
    radius of the segment relative to ``reference`` (the root's largest radius), clipped to
    ``[MIN_WIDTH, RADIUS_WIDTH] x linewidth`` so that thin laterals stay visible."""
    r = 0.5 * (radius[:-1] + radius[1:])
    return np.clip(RADIUS_WIDTH * linewidth * r / reference, MIN_WIDTH * linewidth, RADIUS_WIDTH * linewidth)


def _radius_reference(drawing: Drawing) -> float:
    rs = ([drawing.main_radius] if drawing.main_radius is not None else []) + [r for _, r in drawing.lateral_radii]
    rs += [r for _, _, r in drawing.deeper if r is not None]
    ref = max((float(np.max(r)) for r in rs if r.size), default=0.0)
    return ref if np.isfinite(ref) and ref > 0 else 0.0


def _split(line: np.ndarray) -> list[np.ndarray]:
    return [line[i : i + 2] for i in range(line.shape[0] - 1)]


def draw(
    ax,
    drawing: Drawing,
    *,
    projection: str,
    colors: Any = None,
    slot_colors: bool = True,
    linewidth: float = 1.5,
    show_nulls: bool = False,
    alpha: float = 1.0,
    zorder: float = 2.0,
) -> None:
    """Draw one root on ``ax``: laterals first, main root on top, nulls as hollow circles.

    Every order is drawn: second-order laterals and below (`Drawing.deeper`) under their
    parents, thinner, each in a `shade` of its parent's colour. A plant's system (axes around
    a zero-length main root) has its axes dark and their laterals in slot colours
    (`plant_stride`). Each order is one line
    collection whose ``gid`` is ``"order ℓ"`` (0 main root, 1 laterals, 2 their laterals, ...).

    Where the radius is known, each segment's width follows it (`segment_widths`: relative to
    the root's largest radius, clipped to a readable range); elsewhere laterals are
    ``linewidth`` wide and the main root 1.6 times that."""
    cols = list(COLUMNS[projection])
    main_color = colors if _is_single_color(colors) else MAIN_COLOR
    stride = plant_stride(drawing) if colors is None and slot_colors else None
    reference = _radius_reference(drawing)
    lat_radius = dict(drawing.lateral_radii) if reference > 0 else {}
    segs, lat_colors, lat_widths = [], [], []
    for k, lat in drawing.laterals:
        c = MAIN_COLOR if stride is not None else _lateral_color(k, colors, slot_colors)
        if k in lat_radius and lat.shape[0] >= 2:
            pieces = _split(lat[:, cols])
            segs += pieces
            lat_colors += [c] * len(pieces)
            lat_widths += list(segment_widths(lat_radius[k], reference, linewidth))
        else:
            segs.append(lat[:, cols])
            lat_colors.append(c)
            lat_widths.append(linewidth)
    if projection == "3d":
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        def add(lines, cs, lw, z, level=0):
            lc = Line3DCollection(lines, colors=cs, linewidths=lw, alpha=alpha, zorder=z)
            lc.set_gid(f"order {level}")
            ax.add_collection3d(lc)

    else:

        def add(lines, cs, lw, z, level=0):
            lc = LineCollection(
                lines,
                colors=cs,
                linewidths=lw,
                alpha=alpha,
                zorder=z,
                capstyle="round",
                joinstyle="round",
            )
            lc.set_gid(f"order {level}")  # the branch order it draws: 0 main root, 1 laterals, ...
            ax.add_collection(lc, autolim=True)

    if segs:
        add(segs, lat_colors, lat_widths, zorder, 1)
    # Second-order laterals and below: one collection per level, under their parents, each
    # level thinner and (by its shade of the parent's colour) lighter.
    for level, (segs, cs, widths) in sorted(
        _deeper_segments(drawing, cols, colors, slot_colors, linewidth, reference, stride).items()
    ):
        add(segs, cs, widths, zorder - 0.01 * level, level)
    if reference > 0 and drawing.main_radius is not None:
        pieces = _split(drawing.main[:, cols])
        widths = segment_widths(drawing.main_radius, reference, linewidth)
        add(pieces, [main_color] * len(pieces), list(widths), zorder + 0.1, 0)
    else:
        # The main root is drawn thicker, as it is in the plant.
        add([drawing.main[:, cols]], [main_color], 1.6 * linewidth, zorder + 0.1, 0)
    if show_nulls and (drawing.nulls or drawing.deeper_nulls):
        pts = np.stack([p[cols] for _, p in drawing.nulls] + [p[cols] for _, p in drawing.deeper_nulls])
        ncol = [MAIN_COLOR if stride is not None else _lateral_color(k, colors, slot_colors) for k, _ in drawing.nulls]
        ncol += [deeper_color(slot, colors, slot_colors, stride) for slot, _ in drawing.deeper_nulls]
        ax.scatter(
            *pts.T,
            s=(3.5 * linewidth) ** 2,
            facecolors="none",
            edgecolors=ncol,
            linewidths=0.8 * linewidth,
            alpha=alpha,
            zorder=zorder + 0.2,
        )


# Width of an order-ℓ branch (ℓ >= 2) without radius data: DEEPER_WIDTH^(ℓ-1) x `linewidth`.
DEEPER_WIDTH = 0.6


def plant_stride(drawing: Drawing) -> int | None:
    """For a plant's whole system (`rootshape_jax.io.plant_system`: a zero-length main root at
    the collar, the plant's axes as its laterals) drawn with the axes' laterals, the number of
    lateral slots per axis; None for any other root.

    A plant is drawn with its axes dark, like main roots, and each axis's laterals in slot
    colours of their own (`deeper_color`), so matched laterals can be told apart: with the
    usual rule every lateral of an axis would be a shade of one colour."""
    if not drawing.laterals or np.ptp(drawing.main, axis=0).max() > 0:
        return None
    second = [s[1] for s, _, _ in drawing.deeper if len(s) >= 2] + [
        s[1] for s, _ in drawing.deeper_nulls if len(s) >= 2
    ]
    # Without the axes' laterals (depth 2) the axes are what corresponds: slot colours, as usual.
    return max(second) + 1 if second else None


def deeper_color(slot: Sequence[int], colors: Any, slot_colors: bool, stride: int | None = None) -> Any:
    """Colour of the deeper branch at ``slot``: one colour for the whole root when `colors` is
    one colour, otherwise a `shade` of its parent's colour at every level (`branch_color`).
    In a plant (`stride` from `plant_stride`) an axis's lateral ``(a, k)`` takes slot colour
    ``a * stride + k`` and its own branches shades of it."""
    if stride is not None:
        color, below = slot_color(slot[0] * stride + slot[1]), slot[2:]
    else:
        color, below = _lateral_color(slot[0], colors, slot_colors), slot[1:]
        if _is_single_color(colors):
            return color
    for k in below:
        color = shade(color, k)
    return color


def _deeper_segments(drawing: Drawing, cols, colors, slot_colors, linewidth, reference, stride=None) -> dict:
    """{order ℓ: (segments, colours, widths)} of the branches below the first-order laterals."""
    out: dict[int, tuple[list, list, list]] = {}
    for slot, line, radius in drawing.deeper:
        segs, cs, widths = out.setdefault(len(slot), ([], [], []))
        c = deeper_color(slot, colors, slot_colors, stride)
        if radius is not None and reference > 0 and line.shape[0] >= 2:
            pieces = _split(line[:, cols])
            segs += pieces
            cs += [c] * len(pieces)
            widths += list(segment_widths(radius, reference, linewidth))
        else:
            segs.append(line[:, cols])
            cs.append(c)
            widths.append(linewidth * DEEPER_WIDTH ** (len(slot) - 1))
    return out


def points_of(drawing: Drawing, projection: str, show_nulls: bool) -> np.ndarray:
    cols = list(COLUMNS[projection])
    parts = [drawing.main[:, cols]] + [lat[:, cols] for _, lat in drawing.laterals]
    parts += [b[:, cols] for _, b, _ in drawing.deeper]
    if show_nulls and (drawing.nulls or drawing.deeper_nulls):
        parts.append(np.stack([p[cols] for _, p in drawing.nulls] + [p[cols] for _, p in drawing.deeper_nulls]))
    return np.concatenate(parts, axis=0)


# --------------------------------------------------------------------------------------------
# Limits, figures, panels


@dataclasses.dataclass(frozen=True)
class Frame:
    """Axis limits: ``lo``/``hi`` per projected axis (plus an offset per panel, see below)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def span(self) -> np.ndarray:
        return self.hi - self.lo

    @property
    def aspect(self) -> float:
        """Width / height of the 2D picture."""
        return float(self.span[0] / self.span[-1])


def _pad(lo: np.ndarray, hi: np.ndarray, frac: float = 0.06) -> Frame:
    span = hi - lo
    size = float(span.max()) if np.all(np.isfinite(span)) and span.max() > 0 else 1.0
    # Keep a thin root from becoming a sliver: every axis spans at least 15 % of the largest.
    grow = np.maximum(span, 0.15 * size) - span
    lo, hi = lo - grow / 2, hi + grow / 2
    return Frame(lo - frac * size, hi + frac * size)


def absolute_frame(drawings: Sequence[Drawing], projection: str, show_nulls: bool) -> Frame:
    """One set of limits holding every drawing where it is (geodesics: nothing moves)."""
    pts = np.concatenate([points_of(d, projection, show_nulls) for d in drawings])
    return _pad(pts.min(axis=0), pts.max(axis=0))


def base_frame(drawings: Sequence[Drawing], projection: str, show_nulls: bool) -> Frame:
    """Limits relative to each root's base: panels share one scale with the bases aligned."""
    cols = list(COLUMNS[projection])
    rel = [points_of(d, projection, show_nulls) - d.main[0, cols] for d in drawings]
    pts = np.concatenate(rel)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    # Horizontal axes symmetric about the base: every main root sits on the panel's centre line.
    half = np.maximum(-lo[:-1], hi[:-1])
    lo[:-1], hi[:-1] = -half, half
    return _pad(lo, hi)


def apply_frame(ax, frame: Frame, *, projection: str, invert_y: bool, offset=None) -> None:
    """Set limits (shifted by ``offset``), equal aspect, and the depth axis pointing down."""
    off = np.zeros_like(frame.lo) if offset is None else np.asarray(offset, dtype=float)
    lo, hi = frame.lo + off, frame.hi + off
    ax.set_xlim(lo[0], hi[0])
    if projection == "3d":
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(*((hi[2], lo[2]) if invert_y else (lo[2], hi[2])))
        ax.set_box_aspect(tuple(frame.span), zoom=0.85)  # room for the axis labels
    else:
        ax.set_ylim(*((hi[1], lo[1]) if invert_y else (lo[1], hi[1])))
        ax.set_aspect("equal", adjustable="box")


def panel_offset(drawing: Drawing, projection: str):
    return drawing.main[0, list(COLUMNS[projection])]


def new_figure(figsize: tuple[float, float], *, layout: str | None = "constrained"):
    """A figure without GUI: pyplot's when the user imported pyplot (so notebooks show it),
    otherwise a bare `matplotlib.figure.Figure`, which never needs a backend or display."""
    if "matplotlib.pyplot" in sys.modules:
        plt = sys.modules["matplotlib.pyplot"]
        return plt.figure(figsize=figsize, layout=layout)
    return Figure(figsize=figsize, layout=layout)


def subplot_kw(projection: str) -> dict:
    return {"projection": "3d"} if projection == "3d" else {}


def clean_panel(ax, projection: str) -> None:
    """No ticks or frame: root drawings are read by shape; a scale bar gives the size."""
    if projection == "3d":
        ax.set_xticklabels([])
        ax.set_yticklabels([])
        ax.set_zticklabels([])
        return
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)


def nice_length(span: float) -> float:
    """A 1-2-5 round number close to a fifth of ``span``."""
    if not np.isfinite(span) or span <= 0:
        return 1.0
    target = span / 5
    base = 10 ** math.floor(math.log10(target))
    for m in (5, 2, 1):
        if m * base <= target * 1.0001:
            return m * base
    return base


def add_scale_bar(ax, frame: Frame, unit: str | None, *, projection: str) -> None:
    if projection == "3d":
        return
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    length = nice_length(float(frame.span[0]))
    label = f"{length:g} {unit}" if unit else f"{length:g}"
    bar = AnchoredSizeBar(
        ax.transData,
        length,
        label,
        loc="lower right",
        frameon=False,
        pad=0.1,
        sep=2,
        size_vertical=0,
        color="#333333",
        fontproperties={"size": 8},
    )
    ax.add_artist(bar)


def wrap_name(text: str, width: int) -> str:
    """`text` on at most two lines of about `width` characters, broken after a separator
    (``/ _ - .`` or a space) where there is one; a second line still too long loses its middle
    to "…". Long file-derived root names (``2012_11_21_09h00_chl110_1_1/3/415``) then fit a
    narrow panel instead of running into their neighbours' titles."""
    text = str(text)
    width = max(int(width), 4)
    if len(text) <= width:
        return text
    cut = max(text.rfind(sep, 0, width) for sep in "/_-. ")
    cut = cut + 1 if cut > 0 else width
    first, rest = text[:cut].rstrip(), text[cut:].lstrip()
    if len(rest) > width:
        keep = width - 1
        rest = rest[: keep // 2] + "\u2026" + rest[len(rest) - (keep - keep // 2) :]
    return first + "\n" + rest


def panel_size(frame: Frame, height: float) -> tuple[float, float]:
    """Inches (width, height) of one panel holding ``frame`` at equal aspect."""
    width = float(np.clip(height * frame.aspect, 0.35 * height, 2.5 * height))
    return width, height


def grid_shape(n: int, ncols: int | None, *, max_cols: int = 8) -> tuple[int, int]:
    if ncols is None:
        ncols = min(n, max_cols)
    if not isinstance(ncols, int) or ncols < 1:
        raise ValueError(f"ncols must be a positive integer, got {ncols!r}.")
    return math.ceil(n / ncols), ncols


def as_float_array(x: Any, *, what: str, expected: str) -> np.ndarray:
    """`x` as a float array, or a TypeError naming what `what` accepts (`expected`)."""
    try:
        return np.asarray(x, dtype=float)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{what}: expected {expected}, got {type(x).__name__}.") from e


def check_positive(name: str, value: Any) -> None:
    if not isinstance(value, (int, float)) or not value > 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}.")
