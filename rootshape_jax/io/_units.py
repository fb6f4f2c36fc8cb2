"""Converting roots between length units (pixel + resolution, inch + dpi, cm, mm, ...)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .._errors import UnitError
from .._root import Root
from .._units import MM_PER_UNIT as MM_PER_UNIT, NORMALISED_UNIT as NORMALISED_UNIT, PIXEL_UNITS as PIXEL_UNITS


def unit_label(unit: str | None) -> str:
    """The unit as written in column names and axis labels: ``"px"`` for pixels, the
    normalised wording as is, ``"input units"`` when unknown."""
    if unit is None:
        return "input units"
    return "px" if unit.lower() in PIXEL_UNITS else unit


def check_length_unit(unit: str) -> str:
    """The unit's key in `MM_PER_UNIT` (lower case), or `UnitError` naming the known units."""
    key = unit.strip().lower()
    if key not in MM_PER_UNIT:
        raise UnitError(
            f"unknown length unit {unit!r}; use one of mm, cm, m, um, inch (or convert the "
            "coordinates yourself and set metadata['unit'])."
        )
    return key


def convert_units(roots: Root | Sequence[Root], unit: str) -> list[Root]:
    """The roots with every coordinate and radius expressed in `unit` (e.g. ``"mm"``).

    Each root's source unit is its ``metadata["unit"]`` (as `read_rsml` and `roots_from_image`
    set it): a physical unit (``inch``, ``cm``, ``mm``, ``m``, ``um``) converts directly; a
    ``pixel`` root converts through ``metadata["resolution"]`` (pixels per
    ``metadata["file_unit"]``, the RSML file's ``<resolution>`` and ``<unit>``; for images read
    with ``pixel_size``, pixels per ``metadata["unit"]``). Coordinates are scaled about the
    origin, so positions convert too; attachment fractions are unitless and unchanged.
    ``metadata["resolution"]`` becomes pixels per `unit`, so `write_rsml` still writes the
    file's pixel coordinates.

    Raises `UnitError` for an unknown unit, a root without ``metadata["unit"]``, or a pixel
    root without a resolution (give the image's pixel size or the file's ``<resolution>``).
    """
    if isinstance(roots, Root):
        roots = [roots]
    target = check_length_unit(unit)
    out = []
    for r in roots:
        src = r.metadata.get("unit")
        label = f"root {r.name!r}" if r.name else "a root"
        if src is None:
            raise UnitError(
                f"{label} has no metadata['unit'], so it cannot be converted to {unit}; set "
                "metadata['unit'] to the unit of its coordinates first."
            )
        resolution = r.metadata.get("resolution")
        if str(src).lower() in PIXEL_UNITS:
            file_unit = r.metadata.get("file_unit")
            if resolution is None or file_unit is None or str(file_unit).lower() not in MM_PER_UNIT:
                where = r.metadata.get("source_file") or r.metadata.get("file") or label
                raise UnitError(
                    f"{where}: coordinates are in pixels with no physical resolution, so they cannot "
                    f"be converted to {unit}. Add <unit> and <resolution> (pixels per unit) to the "
                    "file's <metadata>, give the pixel size (--pixel-size, or pixel_size= when "
                    "reading), or leave out the unit option to keep pixels."
                )
            factor = MM_PER_UNIT[check_length_unit(str(file_unit))] / float(resolution) / MM_PER_UNIT[target]
        else:
            factor = MM_PER_UNIT[check_length_unit(str(src))] / MM_PER_UNIT[target]
        if str(src).lower() == target:
            out.append(r)
            continue
        meta = dict(r.metadata, unit=unit)
        if str(src).lower() in PIXEL_UNITS:
            meta["resolution"] = 1.0 / factor  # pixels per `unit`
        elif resolution is not None:
            meta["resolution"] = float(resolution) / factor
        zero = np.zeros(r.dim, dtype=r.main.dtype)
        out.append(dataclasses.replace(_scaled_meta(r.scaled_about(zero, factor), unit, factor), metadata=meta))
    return out


def _scaled_meta(root: Root, unit: str, factor: float) -> Root:
    """Children carry their own metadata unit: keep it in step with the coordinates."""
    if not root.children:
        return root
    kids = []
    for c in root.children:
        meta = dict(c.metadata)
        if "unit" in meta:
            meta["unit"] = unit
        if meta.get("resolution") is not None:
            meta["resolution"] = float(meta["resolution"]) / factor
        kids.append(dataclasses.replace(_scaled_meta(c, unit, factor), metadata=meta))
    return dataclasses.replace(root, children=tuple(kids))
