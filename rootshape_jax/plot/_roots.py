"""Root drawings: one root, geodesic strips, mean, modes, samples, regression sweeps.

Conventions shared by every function here:

- **Depth points down** (`invert_y=True`, the image convention): 2D roots are ``(x, y)`` with
  y the depth, 3D roots ``(x, y, z)`` with z the depth; the base of the main root is at the top.
- **Colours**: the main root is near-black and drawn thicker; lateral slot ``k`` always has
  `slot_color(k)`, so after registration (or along a geodesic) one colour is one lateral in
  every panel. `colors` overrides this: one colour for the whole root, or one per slot.
- **Deeper orders** (trees of depth 3 or more, `Root.children`): second-order laterals and
  below are drawn under their parents, thinner, each in a lighter shade of its parent's colour
  (`branch_color`), so matched branches share a colour at every level.
- **3D roots** are drawn as the side view ``projection="xz"`` (x against depth) unless you ask
  for ``"yz"``, ``"xy"`` (top view) or ``"3d"`` (a 3D axis).
- Panels of a multi-root figure share one scale (equal aspect); a scale bar gives the length.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.ticker import MaxNLocator

from .._mean import KarcherMean
from .._pca import TangentPCA, modes
from .._tree import RootTree, SRVFTree, rotation_towards_chords, to_curves, turn_about_base
from ._draw import (
    COLUMNS,
    Frame,
    absolute_frame,
    add_scale_bar,
    apply_frame,
    as_drawing,
    as_drawing_grid,
    as_drawing_list,
    axis_labels,
    base_frame,
    check_colors,
    check_positive,
    clean_panel,
    common_unit,
    draw,
    grid_shape,
    new_figure,
    panel_offset,
    panel_size,
    resolve_projection,
    subplot_kw,
    turned_drawings,
)

_MINUS = "\u2212"


def _fmt(x: float, digits: int = 3) -> str:
    return f"{x:.{digits}g}".replace("-", _MINUS)


def plot_root(
    root: Any,
    *,
    ax=None,
    colors: Any = None,
    slot_colors: bool = True,
    linewidth: float = 1.5,
    show_nulls: bool = False,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    title: str | None = None,
):
    """Draw one root.

    **Arguments**

    - `root`: a `Root`, or an unbatched `RootTree` (null slots, ``mask = False``, are skipped).
    - `ax`: the matplotlib Axes to draw into (a 3D Axes for ``projection="3d"``); a new figure
      when None. Several roots can be drawn into one Axes by passing the same `ax`.
    - `colors`: None for the default colours (main root near-black, laterals by slot), one
      matplotlib colour for the whole root, or a sequence of colours indexed by lateral slot.
    - `slot_colors`: colour laterals by slot (True) or all in one brown (False).
    - `linewidth`: lateral line width in points; the main root is 1.6 times thicker.
    - `show_nulls`: mark the padding (null) slots of a `RootTree` as hollow circles, at every
      level (the unused child slots of each real branch, at their attachment points).
    - `invert_y`: depth axis pointing down, base of the root at the top (image convention).
    - `projection`: for 3D roots, ``"xz"`` (default: x against depth), ``"yz"``, ``"xy"`` or
      ``"3d"``; 2D roots only take ``"xy"``.
    - `unit`: length unit for the axis labels; default ``root.metadata["unit"]`` (a `Root`).
    - `title`: Axes title; default the root's name (if any).

    **Returns** ``(fig, ax)``.
    """
    drawing = as_drawing(root, what="plot_root: root")
    check_colors(colors)
    check_positive("linewidth", linewidth)
    if ax is not None and getattr(ax, "name", "") == "3d" and projection is None:
        projection = "3d"
    projection = resolve_projection(drawing.dim, projection)
    frame = absolute_frame([drawing], projection, show_nulls)
    if ax is None:
        fig = new_figure(_single_size(frame, projection))
        ax = fig.add_subplot(**subplot_kw(projection))
        own_axes = True
    else:
        fig = ax.figure
        own_axes = False
        if ax.has_data():
            frame = _extend_frame(ax, frame, projection)
        if (projection == "3d") != (getattr(ax, "name", "") == "3d"):
            raise ValueError(
                f"projection={projection!r} needs {'a 3D' if projection == '3d' else 'a 2D'} Axes; "
                "pass ax=None or an Axes made with the matching projection."
            )
    draw(
        ax,
        drawing,
        projection=projection,
        colors=colors,
        slot_colors=slot_colors,
        linewidth=linewidth,
        show_nulls=show_nulls,
    )
    apply_frame(ax, frame, projection=projection, invert_y=invert_y)
    if own_axes:
        labels = axis_labels(drawing.dim, projection, unit if unit is not None else drawing.unit)
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        if projection == "3d":
            ax.set_zlabel(labels[2])
            for axis in (ax.xaxis, ax.yaxis):
                axis.set_major_locator(MaxNLocator(4))
        else:
            ax.spines[["top", "right"]].set_visible(False)
    name = drawing.name if title is None else title
    if name:
        ax.set_title(name)
    return fig, ax


def _single_size(frame, projection) -> tuple[float, float]:
    if projection == "3d":
        return (6.0, 6.0)
    w, h = panel_size(frame, 5.0)
    return (max(w + 1.2, 3.5), h + 0.8)


def _extend_frame(ax, frame: Frame, projection: str) -> Frame:
    """Drawing into an Axes that already shows data: the union of its limits and ``frame``."""
    lims = [ax.get_xlim(), ax.get_ylim()] + ([ax.get_zlim()] if projection == "3d" else [])
    lo = np.minimum(frame.lo, [min(v) for v in lims])
    hi = np.maximum(frame.hi, [max(v) for v in lims])
    return Frame(lo, hi)


# --------------------------------------------------------------------------------------------
# Grids of roots


def _panel_grid(fig, nrows: int, ncols: int, n_used: int, projection: str, gridspec=None):
    """``n_used`` panels filled row by row; the unused cells of the last row are not created."""
    gs = gridspec if gridspec is not None else fig.add_gridspec(nrows, ncols)
    axes = []
    for i in range(n_used):
        r, c = divmod(i, ncols)
        axes.append(fig.add_subplot(gs[r, c], **subplot_kw(projection)))
    return axes


def _draw_panels(axes, drawings, frame, *, projection, invert_y, align_bases, style, unit, scale_bar=True):
    for ax, d in zip(axes, drawings):
        draw(ax, d, projection=projection, **style)
        offset = panel_offset(d, projection) if align_bases else None
        apply_frame(ax, frame, projection=projection, invert_y=invert_y, offset=offset)
        clean_panel(ax, projection)
    if scale_bar and axes:
        add_scale_bar(axes[-1], frame, unit, projection=projection)


def _style(colors, slot_colors, linewidth, show_nulls) -> dict:
    check_colors(colors)
    check_positive("linewidth", linewidth)
    return dict(colors=colors, slot_colors=slot_colors, linewidth=linewidth, show_nulls=show_nulls)


def _suptitle(fig, title, *, own_figure: bool = True):
    if title:
        fig.suptitle(title, fontsize=12)
        # A narrow strip of panels must not cut its title off (~0.09 inch per character).
        w, h = fig.get_size_inches()
        need = 0.09 * max(len(line) for line in title.split("\n")) + 0.3
        if own_figure and w < need:
            fig.set_size_inches(need, h)


def plot_geodesic(
    path: Any,
    *,
    axes=None,
    taus: Sequence[float] | None = None,
    ncols: int | None = None,
    colors: Any = None,
    linewidth: float = 1.3,
    show_nulls: bool = False,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    panel_height: float = 2.6,
    title: str | None = "Geodesic (optimal deformation); colour = corresponding lateral",
    align_bases: bool | None = None,
):
    """A strip of the steps of a geodesic, e.g. the output of `rootshape_jax.geodesic`.

    **Arguments**

    - `path`: a batched `RootTree` whose leading axis is the step (or a list of roots). Slot
      ``k`` has the same colour in every step, so you can follow each lateral along the path;
      at depth 3 or more each lateral's own laterals keep a shade of its colour the same way.
    - `axes`: one Axes per step to draw into; a new figure when None.
    - `taus`: the path parameter of each step, for the panel titles (default evenly spaced
      from 0 to 1).
    - `ncols`: wrap the strip after this many panels (default: one row).
    - `colors`, `linewidth`, `show_nulls`, `invert_y`, `projection`: as in `plot_root`.
    - `unit`: length unit of the scale bar (a `RootTree` does not carry one).
    - `panel_height`: inches per panel. `title`: figure title (None for none).

    - `align_bases`: False: every panel shows the same region at the same scale, so only the
      deformation moves. True: every panel has the same scale and size, centred on its step's
      base (the path's translation is left out of the picture). None (default): True when the
      bases travel further than the roots are large (roots at two places of a plate), where
      one shared region would draw each root as a speck; else False.

    **Returns** ``(fig, axes)`` with `axes` a list, one per step.
    """
    drawings = as_drawing_list(path, what="plot_geodesic: path")
    n = len(drawings)
    style = _style(colors, True, linewidth, show_nulls)
    projection = resolve_projection(drawings[0].dim, projection)
    if taus is None:
        taus = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    taus = np.asarray(taus, dtype=float).reshape(-1)
    if taus.shape[0] != n:
        raise ValueError(f"plot_geodesic: {taus.shape[0]} taus for {n} steps; give one per step.")
    frame = absolute_frame(drawings, projection, show_nulls)
    relative = base_frame(drawings, projection, show_nulls)
    if align_bases is None:
        align_bases = bool(np.max(frame.span) > 2.0 * np.max(relative.span))
    if align_bases:
        frame = relative
    nrows, ncols = grid_shape(n, ncols if ncols is not None else n, max_cols=n)
    if axes is None:
        w, h = panel_size(frame, panel_height)
        fig = new_figure((ncols * w + 0.3, nrows * (h + 0.35) + (0.45 if title else 0.1)))
        axes = _panel_grid(fig, nrows, ncols, n, projection)
        own_figure = True
    else:
        own_figure = False
        axes = list(np.ravel(axes))
        if len(axes) != n:
            raise ValueError(f"plot_geodesic: {len(axes)} axes for {n} steps; give one per step.")
        fig = axes[0].figure
    _draw_panels(
        axes,
        drawings,
        frame,
        projection=projection,
        invert_y=invert_y,
        align_bases=align_bases,
        style=style,
        unit=unit if unit is not None else common_unit(drawings),
    )
    for i, (ax, tau) in enumerate(zip(axes, taus)):
        label = f"\u03c4 = {_fmt(tau, 2)}"
        if n > 1 and i == 0:
            label = "start, " + label
        elif n > 1 and i == n - 1:
            label = "end, " + label
        ax.set_title(label, fontsize=9)
    _suptitle(fig, title, own_figure=own_figure)
    return fig, axes


def plot_mean(
    samples: Any,
    mean: Any,
    *,
    layout: str = "grid",
    names: Sequence[str] | None = None,
    max_samples: int = 64,
    ncols: int | None = None,
    colors: Any = None,
    slot_colors: bool = True,
    linewidth: float = 1.0,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    title: str | None = "Mean root",
    upright: bool = True,
):
    """Input roots beside their (Karcher) mean, as in the paper's "mean root" figure.

    **Arguments**

    - `samples`: the input roots (a batched `RootTree` or a list of `Root` / `RootTree`).
      Registered samples (in the mean's slot order) share the mean's lateral colours.
    - `mean`: the mean root (`Root` or unbatched `RootTree`), or the `KarcherMean` itself.
    - `layout`: ``"grid"`` (small panels of the first `max_samples` inputs, mean in a large
      panel on the right) or ``"overlay"`` (one panel: inputs in light grey, translated so
      their bases meet the mean's, with the mean drawn on top in colour).
    - `names`: one name per sample, written above its panel (default: the roots' own names
      when `samples` are `Root`s; none for a `RootTree`).
    - `max_samples`: draw at most this many samples in the grid.
    - `ncols`: columns of the sample grid (default about square).
    - `colors`, `slot_colors`, `linewidth`, `invert_y`, `projection`, `unit`: as in
      `plot_root` (`unit` labels the scale bars).
    - `upright`: a mean given as a `KarcherMean` or an `SRVFTree` (whose pose the metric
      ignores: it keeps the tilt of the root the solver started from) is drawn turned about its
      base so its main root points where the samples' main roots point on average
      (`rootshape_jax.upright_rotation`). A `Root` or `RootTree` mean is drawn as given.

    **Returns** ``(fig, axes)`` with ``axes = {"samples": [...], "mean": ax}`` (for the
    overlay layout ``"samples"`` is the same single Axes as ``"mean"``).
    """
    drawings = as_drawing_list(samples, what="plot_mean: samples")
    if upright and isinstance(mean, (KarcherMean, SRVFTree)):
        mean = _turned_upright(mean, drawings)
    mean_d = as_drawing(mean, what="plot_mean: mean")
    if mean_d.dim != drawings[0].dim:
        raise ValueError(f"plot_mean: the mean is {mean_d.dim}D but the samples are {drawings[0].dim}D.")
    style = _style(colors, slot_colors, linewidth, False)
    projection = resolve_projection(mean_d.dim, projection)
    if not isinstance(max_samples, int) or max_samples < 1:
        raise ValueError(f"max_samples must be a positive integer, got {max_samples!r}.")
    if unit is None:
        unit = common_unit(drawings + [mean_d])
    if layout == "overlay":
        return _mean_overlay(drawings, mean_d, projection, invert_y, style, unit, title)
    if layout != "grid":
        raise ValueError(f"layout must be 'grid' or 'overlay', got {layout!r}.")
    # A long unit ("normalised (main-root length = 1)") under a small panel's scale bar would
    # widen its column: the bars then show numbers and the unit is said once below the figure.
    long_unit = unit if unit is not None and len(unit) > 10 else None
    bar_unit = None if long_unit else unit

    if names is None:
        names = [d.name for d in drawings] if all(d.name for d in drawings) else None
    elif len(names) != len(drawings):
        raise ValueError(f"plot_mean: {len(names)} names for {len(drawings)} samples.")
    shown = drawings[:max_samples]
    n = len(shown)
    frame = base_frame(shown + [mean_d], projection, False)
    w, h = panel_size(frame, 1.35)
    # The mean at its own (larger) scale, filling its panel; each side has its scale bar.
    mean_frame = base_frame([mean_d], projection, False)
    mean_aspect = float(np.divide(*panel_size(mean_frame, 1.0)))
    if names is not None:
        # Room for the name above each panel (about 0.045 inch per character at 6 pt), so that
        # constrained layout does not widen single columns around a long title.
        w = max(w, 0.047 * max(len(str(x)) for x in names[:n]) + 0.05)
    if ncols is None:
        # About 1.3 times wider than tall, whatever the roots' own aspect; among the nearby
        # column counts prefer the one leaving fewest empty cells in the last row.
        c = float(np.sqrt(1.3 * n * h / w))
        candidates = [k for k in range(int(c) - 1, int(c) + 3) if 1 <= k <= n] or [1]
        ncols = min(candidates, key=lambda k: ((-n) % k, abs(k - c)))
    nrows, ncols = grid_shape(n, ncols, max_cols=ncols)
    mean_h = float(np.clip(nrows * h, 3.2, 5.5))  # beside a tall grid, not as tall as it
    mean_w = max(mean_h * mean_aspect, 2.0)  # room for its title beside a narrow root
    fig = new_figure((ncols * w + mean_w + 0.6, max(nrows * h, mean_h) + 0.9))
    outer = fig.add_gridspec(1, 2, width_ratios=[ncols * w, mean_w])
    inner = outer[0, 0].subgridspec(nrows, ncols)
    sample_axes = _panel_grid(fig, nrows, ncols, n, projection, gridspec=inner)
    _draw_panels(
        sample_axes,
        shown,
        frame,
        projection=projection,
        invert_y=invert_y,
        align_bases=True,
        style=style,
        unit=bar_unit,
    )
    if names is not None:
        for ax, name in zip(sample_axes, names):
            ax.set_title(str(name), fontsize=6, pad=1.5)
    mean_ax = fig.add_subplot(outer[0, 1], **subplot_kw(projection))
    mean_style = dict(style, linewidth=1.6 * linewidth)
    _draw_panels(
        [mean_ax],
        [mean_d],
        mean_frame,
        projection=projection,
        invert_y=invert_y,
        align_bases=True,
        style=mean_style,
        unit=bar_unit,
    )
    # Said in the mean's title: a header over the grid would widen its first column.
    more = f"\n({n} of them shown)" if n < len(drawings) else ""
    mean_ax.set_title(f"Mean of the\n{len(drawings)} roots{more}", fontsize=10)
    if long_unit:
        fig.supxlabel(f"scale bars in {long_unit}", fontsize=9)
    _suptitle(fig, title)
    return fig, {"samples": sample_axes, "mean": mean_ax}


def _mean_overlay(drawings, mean_d, projection, invert_y, style, unit, title):
    frame = base_frame(drawings + [mean_d], projection, False)
    w, h = panel_size(frame, 5.0)
    fig = new_figure((w + 0.6, h + 0.9))
    ax = fig.add_subplot(**subplot_kw(projection))
    base = panel_offset(mean_d, projection)
    cols = list(COLUMNS[projection])
    faint = dict(style, colors="#9a9a9a", linewidth=0.7 * style["linewidth"])
    alpha = float(np.clip(6.0 / len(drawings), 0.15, 0.6))
    for d in drawings:
        shift = np.zeros(d.dim)
        shift[cols] = base - panel_offset(d, projection)
        moved = dataclasses.replace(d.shifted(shift), nulls=())
        draw(ax, moved, projection=projection, alpha=alpha, zorder=1.0, **faint)
    bold = dict(style, linewidth=2 * style["linewidth"])
    draw(ax, mean_d, projection=projection, zorder=3.0, **bold)
    apply_frame(ax, frame, projection=projection, invert_y=invert_y, offset=base)
    clean_panel(ax, projection)
    add_scale_bar(ax, frame, unit, projection=projection)
    ax.set_title(f"{len(drawings)} input roots (grey, bases aligned) and their mean", fontsize=10)
    _suptitle(fig, title)
    return fig, {"samples": ax, "mean": ax}


def _turned_upright(mean, drawings: list) -> RootTree:
    """The mean as curves, turned about its base towards the samples' mean main-root direction
    (unchanged when they point every way, or for plants' systems)."""
    tree = to_curves(mean.mean if isinstance(mean, KarcherMean) else mean)
    if tree.batch_shape != () or tree.virtual_main:
        return tree  # as_drawing names a batched mean; a plant has no main root to point
    main = np.asarray(tree.main, np.float64)
    chords = np.array([d.main[-1] - d.main[0] for d in drawings if d.dim == main.shape[-1]])
    R = rotation_towards_chords(main[-1] - main[0], chords) if len(chords) else None
    return tree if R is None else turn_about_base(tree, R)


def plot_modes(
    mode_trees: Any,
    alphas: Sequence[float],
    *,
    explained: Sequence[float] | None = None,
    components: int | Sequence[int] | None = None,
    colors: Any = None,
    linewidth: float = 1.2,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    panel_height: float = 2.2,
    title: str | None = "Principal modes of variation",
    rotation: Any = None,
):
    """Grid of the roots along principal modes: rows = components, columns = α.

    **Arguments**

    - `mode_trees`: a `TangentPCA` (``rootshape_jax.tangent_pca``): its modes are computed
      for `components` (default: the first three, at most `n_components`), and `explained`
      defaults to its `explained_variance_ratio`. Or what `rootshape_jax.modes` returns: a
      `RootTree` with batch shape ``(n_components, n_alphas)`` (``component=[0, 1, ...]``) or
      ``(n_alphas,)``, one row (``component=i``; pass the same ``components=i`` here, the
      tree does not record it); or a list of rows (each a batched `RootTree` or a list of
      roots). Entry ``[i][j]`` is ``mean + alphas[j] √σ_i Λ_i``.
    - `alphas`: the multiples of the standard deviation, e.g. ``[-2, -1, 0, 1, 2]``; the
      ``α = 0`` column (the mean) is shaded.
    - `explained`: optional fraction of variance explained by each component, indexed by
      component (``pc.explained_variance_ratio``, or the `TangentPCA` itself), shown in the
      row labels.
    - `components`: the component of each row, as passed to `modes` (0-based; row ``i`` is
      labelled ``PC components[i] + 1``); default ``0, 1, ...``.
    - `colors`, `linewidth`, `invert_y`, `projection`, `unit`: as in `plot_root`.
    - `rotation`: a ``[d, d]`` rotation every root is turned by about its base before drawing.
      The metric ignores rotation, so a mean (and the modes around it) keeps the tilt of the
      root its solver started from; ``rotation=rs.upright_rotation(pc.mean, trees)`` draws
      the modes upright like the `trees` the PCA was fitted to, as the command line does.

    **Returns** ``(fig, axes)`` with `axes` a list of rows of Axes.
    """
    if isinstance(mode_trees, TangentPCA):
        if components is None:
            components = list(range(max(1, min(3, mode_trees.n_components))))
        if explained is None:
            explained = mode_trees.explained_variance_ratio
        one = not isinstance(components, (Sequence, np.ndarray))
        comps = _row_components(components, 1 if one else len(components))
        mode_trees = modes(mode_trees, alphas, component=comps)
    rows = as_drawing_grid(mode_trees, what="plot_modes: mode_trees")
    rows = [turned_drawings(row, rotation, what="plot_modes") for row in rows]
    alphas = np.asarray(alphas, dtype=float).reshape(-1)
    for i, row in enumerate(rows):
        if len(row) != alphas.shape[0]:
            raise ValueError(
                f"plot_modes: row {i} has {len(row)} roots but {alphas.shape[0]} alphas were "
                "given; every component needs one root per alpha."
            )
    comps = _row_components(components, len(rows))
    if isinstance(explained, TangentPCA):
        explained = explained.explained_variance_ratio
    if explained is not None:
        explained = np.asarray(explained, dtype=float).reshape(-1)
        if explained.shape[0] <= max(comps):
            raise ValueError(
                f"plot_modes: explained has {explained.shape[0]} values but component {max(comps)} is drawn; "
                "pass one value per component, e.g. explained=pc.explained_variance_ratio."
            )
    flat = [d for row in rows for d in row]
    style = _style(colors, True, linewidth, False)
    projection = resolve_projection(flat[0].dim, projection)
    frame = base_frame(flat, projection, False)
    unit = unit if unit is not None else common_unit(flat)
    nrows, ncols = len(rows), alphas.shape[0]
    w, h = panel_size(frame, panel_height)
    fig = new_figure((ncols * w + 0.7, nrows * (h + 0.1) + 0.4 + (0.45 if title else 0)))
    gs = fig.add_gridspec(nrows, ncols)
    grid = []
    for i, row in enumerate(rows):
        axes = [fig.add_subplot(gs[i, j], **subplot_kw(projection)) for j in range(ncols)]
        _draw_panels(
            axes,
            row,
            frame,
            projection=projection,
            invert_y=invert_y,
            align_bases=True,
            style=style,
            unit=unit,
            scale_bar=(i == nrows - 1),
        )
        label = f"PC {comps[i] + 1}"
        if explained is not None:
            label += f"\n{100 * explained[comps[i]]:.1f} % var."
        if projection != "3d":
            axes[0].set_ylabel(label, fontsize=10, rotation=0, ha="right", va="center")
        for j, ax in enumerate(axes):
            if np.isclose(alphas[j], 0.0) and projection != "3d":
                ax.set_facecolor("#f2f2f2")
        grid.append(axes)
    for j, a in enumerate(alphas):
        head = "mean" if np.isclose(a, 0.0) else f"{'+' if a > 0 else ''}{_fmt(a)}\u03c3"
        grid[0][j].set_title(head.replace("-", _MINUS), fontsize=10)
    _suptitle(fig, title)
    return fig, grid


def _row_components(components: Any, nrows: int) -> list[int]:
    """The component drawn in each row: `components` checked, or 0, 1, ... by default."""
    if components is None:
        return list(range(nrows))
    comps = [components] if isinstance(components, (int, np.integer)) else components
    if not isinstance(comps, (Sequence, np.ndarray)) or not all(
        isinstance(c, (int, np.integer)) and not isinstance(c, bool) for c in comps
    ):
        raise TypeError(
            f"plot_modes: components must be a component index or a list of them (one per row), got {components!r}."
        )
    if any(c < 0 for c in comps):
        raise ValueError(f"plot_modes: components are indices >= 0 (as passed to modes), got {components!r}.")
    if len(comps) != nrows:
        raise ValueError(f"plot_modes: {len(comps)} components for {nrows} rows of roots; pass one per row.")
    return [int(c) for c in comps]


def plot_samples_by_distance(
    samples: Any,
    distances_to_mean: Any,
    *,
    n_groups: int = 3,
    max_per_group: int = 8,
    colors: Any = None,
    linewidth: float = 1.1,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    panel_height: float = 1.9,
    title: str | None = "Random roots from the fitted model, grouped by distance to the mean",
    rotation: Any = None,
):
    """Sampled roots in rows of increasing distance to the mean (the paper's random-synthesis
    figure): samples are sorted by distance and cut into `n_groups` groups of equal size.

    **Arguments**

    - `samples`: the roots (batched `RootTree` or list); `distances_to_mean`: one distance each.
    - `n_groups`: number of rows, closest group first.
    - `max_per_group`: panels per row; larger groups show evenly spaced members (by distance).
    - `colors`, `linewidth`, `invert_y`, `projection`, `unit`: as in `plot_root`.
    - `rotation`: as in `plot_modes` (``rs.upright_rotation(pc.mean, trees)`` draws samples of
      a `TangentPCA` upright like the trees it was fitted to).

    **Returns** ``(fig, axes)`` with `axes` a list of rows of Axes.
    """
    drawings = as_drawing_list(samples, what="plot_samples_by_distance: samples")
    drawings = turned_drawings(drawings, rotation, what="plot_samples_by_distance")
    dist = np.asarray(distances_to_mean, dtype=float).reshape(-1)
    if dist.shape[0] != len(drawings):
        raise ValueError(f"plot_samples_by_distance: {dist.shape[0]} distances for {len(drawings)} samples.")
    if not np.all(np.isfinite(dist)):
        raise ValueError("plot_samples_by_distance: distances must be finite.")
    if not isinstance(n_groups, int) or not 1 <= n_groups <= len(drawings):
        raise ValueError(
            f"n_groups must be an integer between 1 and the number of samples ({len(drawings)}), got {n_groups!r}."
        )
    if not isinstance(max_per_group, int) or max_per_group < 1:
        raise ValueError(f"max_per_group must be a positive integer, got {max_per_group!r}.")
    style = _style(colors, True, linewidth, False)
    projection = resolve_projection(drawings[0].dim, projection)
    order = np.argsort(dist, kind="stable")
    groups = []
    for members in np.array_split(order, n_groups):
        if len(members) > max_per_group:
            members = members[np.round(np.linspace(0, len(members) - 1, max_per_group)).astype(int)]
        groups.append(members)
    frame = base_frame(drawings, projection, False)
    ncols = max(len(g) for g in groups)
    w, h = panel_size(frame, panel_height)
    fig = new_figure((ncols * w + 1.2, n_groups * (h + 0.3) + (0.45 if title else 0.1)))
    gs = fig.add_gridspec(n_groups, ncols)
    grid = []
    names = _group_names(n_groups)
    for g, members in enumerate(groups):
        axes = [fig.add_subplot(gs[g, j], **subplot_kw(projection)) for j in range(len(members))]
        _draw_panels(
            axes,
            [drawings[i] for i in members],
            frame,
            projection=projection,
            invert_y=invert_y,
            align_bases=True,
            style=style,
            unit=unit if unit is not None else common_unit(drawings),
            scale_bar=(g == n_groups - 1),
        )
        for ax, i in zip(axes, members):
            ax.set_title(f"d = {_fmt(dist[i])}", fontsize=8)
        lo, hi = dist[members].min(), dist[members].max()
        if projection != "3d":
            axes[0].set_ylabel(
                f"{names[g]}\nd {_fmt(lo)}\u2013{_fmt(hi)}",
                fontsize=9,
                rotation=0,
                ha="right",
                va="center",
            )
        grid.append(axes)
    _suptitle(fig, title)
    return fig, grid


def _group_names(n: int) -> list[str]:
    if n == 1:
        return ["all"]
    names = [f"group {g + 1}" for g in range(n)]
    names[0] += "\n(closest)"
    names[-1] += "\n(farthest)"
    return names


def plot_regression_sweep(
    trees: Any,
    values: Sequence[float],
    *,
    trait_name: str,
    trait_unit: str | None = None,
    measured: Sequence[float] | None = None,
    colors: Any = None,
    linewidth: float = 1.3,
    invert_y: bool = True,
    projection: str | None = None,
    unit: str | None = None,
    panel_height: float = 2.6,
    title: str | None = None,
):
    """Roots predicted by a trait regression while one trait varies and the others stay fixed.

    **Arguments**

    - `trees`: the predicted roots (batched `RootTree` or list), one per value.
    - `values`: the requested values of the varied trait.
    - `trait_name`: e.g. ``"main root length"``; `trait_unit`: its unit for the panel titles.
    - `measured`: optional trait values measured on the predicted roots, shown under the
      requested ones so you can judge how well the model honours the request.
    - `colors`, `linewidth`, `invert_y`, `projection`, `unit`: as in `plot_root`.
    - `title`: figure title; None names the trait, ``""`` gives none.

    **Returns** ``(fig, axes)`` with `axes` a list.
    """
    if not isinstance(trait_name, str) or not trait_name:
        raise ValueError("plot_regression_sweep: trait_name must be a non-empty string.")
    drawings = as_drawing_list(trees, what="plot_regression_sweep: trees")
    values = np.asarray(values, dtype=float).reshape(-1)
    if values.shape[0] != len(drawings):
        raise ValueError(f"plot_regression_sweep: {values.shape[0]} values for {len(drawings)} roots.")
    if measured is not None:
        measured = np.asarray(measured, dtype=float).reshape(-1)
        if measured.shape[0] != len(drawings):
            raise ValueError(f"plot_regression_sweep: {measured.shape[0]} measured values for {len(drawings)} roots.")
    style = _style(colors, True, linewidth, False)
    projection = resolve_projection(drawings[0].dim, projection)
    frame = base_frame(drawings, projection, False)
    n = len(drawings)
    w, h = panel_size(frame, panel_height)
    fig = new_figure((n * w + 0.3, h + 0.6 + (0.45 if title != "" else 0)))
    axes = _panel_grid(fig, 1, n, n, projection)
    _draw_panels(
        axes,
        drawings,
        frame,
        projection=projection,
        invert_y=invert_y,
        align_bases=True,
        style=style,
        unit=unit if unit is not None else common_unit(drawings),
    )
    u = f" {trait_unit}" if trait_unit else ""
    for i, ax in enumerate(axes):
        text = f"{_fmt(values[i])}{u}"
        if measured is not None:
            text += f"\n(measured {_fmt(measured[i])})"
        ax.set_title(text, fontsize=9)
    if title is None:
        title = f"Roots predicted from traits: {trait_name} varied, other traits fixed"
    _suptitle(fig, title)
    return fig, axes
