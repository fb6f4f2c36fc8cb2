"""Names of length units, and when two roots' units are the same (one place for the readers,
`batch` and the CLI)."""

from __future__ import annotations

from ._errors import UnitError

# Millimetres per unit; spellings seen in RSML files (SmartRoot writes "inch").
MM_PER_UNIT = {
    "mm": 1.0,
    "millimetre": 1.0,
    "millimeter": 1.0,
    "millimetres": 1.0,
    "millimeters": 1.0,
    "cm": 10.0,
    "centimetre": 10.0,
    "centimeter": 10.0,
    "centimetres": 10.0,
    "centimeters": 10.0,
    "m": 1000.0,
    "metre": 1000.0,
    "meter": 1000.0,
    "metres": 1000.0,
    "meters": 1000.0,
    "um": 1e-3,
    "µm": 1e-3,  # micro sign
    "μm": 1e-3,  # Greek mu
    "micron": 1e-3,
    "microns": 1e-3,
    "micrometre": 1e-3,
    "micrometer": 1e-3,
    "micrometres": 1e-3,
    "micrometers": 1e-3,
    "inch": 25.4,
    "inches": 25.4,
    "in": 25.4,
}
PIXEL_UNITS = ("pixel", "pixels", "px")
# What a scale-normalised output's coordinates are in (never "pixel", whatever the input was).
NORMALISED_UNIT = "normalised (main-root length = 1)"


def is_known_unit(unit: str) -> bool:
    """Pixels, a length unit of `MM_PER_UNIT` (any spelling there), or `NORMALISED_UNIT`."""
    key = str(unit).strip().lower()
    return key in PIXEL_UNITS or key in MM_PER_UNIT or key == NORMALISED_UNIT


def check_unit_name(unit: str, where: str) -> str:
    """`unit` if `is_known_unit`, else `UnitError` naming the known units: a unit stored under
    a name nothing can convert ("parsec", a typo) would only fail later, far from its cause."""
    if not isinstance(unit, str) or not is_known_unit(unit):
        raise UnitError(
            f"{where}: unknown unit {unit!r}; use pixel, a length unit (mm, cm, m, um, inch) or "
            f"{NORMALISED_UNIT!r} for scale-normalised coordinates."
        )
    return unit


def unit_key(unit: str | None) -> str | None:
    """One key per unit, whatever its spelling ("mm" and "millimetre", "px" and "pixel"); None
    for no unit (None or "")."""
    key = "" if unit is None else str(unit).strip().lower()
    if not key:
        return None
    if key in PIXEL_UNITS:
        return "pixel"
    return f"{MM_PER_UNIT[key]:g} mm" if key in MM_PER_UNIT else key


def units_of(roots) -> dict[str, str]:
    """The units `roots` carry (``metadata["unit"]``): ``{unit_key: the first spelling seen}``;
    roots without a unit add nothing."""
    found: dict[str, str] = {}
    for r in roots:
        key = unit_key(r.metadata.get("unit"))
        if key is not None:
            found.setdefault(key, str(r.metadata["unit"]))
    return found
