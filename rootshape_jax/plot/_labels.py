"""Colour strips for labels (condition, genotype, ...) beside a heat map or a dendrogram."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib
import matplotlib.colors as mcolors
import numpy as np

# Unknown values (None, NaN, "") get a neutral light grey; known values a qualitative colour.
MISSING_COLOR = "#d9d9d9"
MISSING_TEXT = "(missing)"


def _is_missing(v: Any) -> bool:
    if v is None:
        return True
    if isinstance(v, float) and np.isnan(v):
        return True
    return isinstance(v, str) and not v.strip()


# One qualitative palette per label, so that two strips never share a colour by accident.
_PALETTES = ("tab10", "Dark2", "Set2", "Accent", "Pastel1")


def label_colors(values: Sequence[Any], *, palette: int = 0) -> dict[str, str]:
    """``{value: colour}`` for one label column: values sorted as text, colours from the
    `palette`-th qualitative matplotlib palette (``tab10``, ``Dark2``, ``Set2``, ...; ``tab20``
    beyond 10 values); missing values map to `MISSING_COLOR` under `MISSING_TEXT`."""
    known = sorted({str(v) for v in values if not _is_missing(v)})
    cmap = matplotlib.colormaps[_PALETTES[palette % len(_PALETTES)] if len(known) <= 8 else "tab20"]
    colors = {v: mcolors.to_hex(cmap(i % cmap.N)) for i, v in enumerate(known)}
    if any(_is_missing(v) for v in values):
        colors[MISSING_TEXT] = MISSING_COLOR
    return colors


def check_groups(groups: Any, n: int, *, what: str) -> dict[str, list[Any]]:
    """``groups`` as ``{label name: N values}``, or a ValueError naming the bad column."""
    if groups is None:
        return {}
    if not isinstance(groups, Mapping):
        raise ValueError(
            f"{what}: groups must be a mapping from a label name to one value per root, e.g. "
            f"{{'condition': [...]}}; got {type(groups).__name__}."
        )
    out = {}
    for name, values in groups.items():
        values = list(values)
        if len(values) != n:
            raise ValueError(f"{what}: groups[{name!r}] has {len(values)} values for {n} roots.")
        out[str(name)] = values
    return out


def legend_handles(colors: Mapping[str, Mapping[str, str]]) -> list:
    """Legend patches ``"name: value"``, one row per label when drawn with
    ``ncol = max(len(c) for c in colors.values())`` (matplotlib fills legends column by
    column, so the rows are padded with invisible entries)."""
    from matplotlib.patches import Patch

    rows = [[Patch(facecolor=c, label=f"{name}: {v}") for v, c in cs.items()] for name, cs in colors.items()]
    ncol = max((len(r) for r in rows), default=0)
    blank = lambda: Patch(visible=False, label="")  # noqa: E731
    grid = [r + [blank() for _ in range(ncol - len(r))] for r in rows]
    return [grid[r][c] for c in range(ncol) for r in range(len(grid))]


def value_key(v: Any) -> str:
    return MISSING_TEXT if _is_missing(v) else str(v)


def draw_label_strip(ax, values: Sequence[Any], colors: Mapping[str, str], *, name: str) -> None:
    """One row of cells, cell i coloured by ``values[i]`` (already in display order), with the
    label's name on the left."""
    rgb = np.array([[mcolors.to_rgb(colors[value_key(v)]) for v in values]])
    n = len(values)
    ax.imshow(rgb, aspect="auto", interpolation="nearest", extent=(-0.5, n - 0.5, 0.5, -0.5))
    ax.set_xticks([])
    ax.set_yticks([0], [name], fontsize=8)
    ax.tick_params(length=0)
    for spine in ax.spines.values():
        spine.set_visible(False)
