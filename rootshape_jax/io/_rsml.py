"""RSML (Root System Markup Language) reading and writing.

RSML stores a scene of plants; each plant holds roots (``<root>``), each root a
``<geometry><polyline>`` of ``<point x= y= [z=]/>`` and its child roots nested inside it.
This module maps every top-level root of every plant to one `Root`: its direct children are the
laterals, deeper orders go to `Root.children` (one `Root` per lateral, recursively).

Files are parsed with ``defusedxml`` (DTDs and entity declarations are refused, nothing is
fetched) and written as an ``xml.etree`` tree serialised by a small iterative writer. Tags and
attribute names are matched on their local name, case-insensitively, so ``point``/``Point``,
``id``/``ID`` and namespaced files all read. Nested ``<root>`` elements are walked with
explicit stacks (no recursion), so any nesting depth reads and writes.
"""

from __future__ import annotations

import datetime
import itertools
import math
import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape, quoteattr

import numpy as np
from defusedxml import DefusedXmlException, ElementTree as DET

from .._errors import InvalidRootError, RSMLError, RSMLWarning, UnitError, as_flag, user_stacklevel
from .._root import ROOT_COORDINATE_LIMIT, Root, check_range, is_plant_system, plant_axes
from .._tree import RootTree, SRVFTree
from .._units import PIXEL_UNITS, check_unit_name, is_known_unit, unit_key, units_of

_PO_NS = "http://www.plantontology.org/xml-dtd/po.dtd"


# --------------------------------------------------------------------------------------------
# Small XML helpers: local names, case-insensitive.


def _local(name: Any) -> str:
    if not isinstance(name, str):  # comments / processing instructions
        return ""
    return name.rsplit("}", 1)[-1].rsplit(":", 1)[-1].lower()


def _attr(elem: ET.Element, name: str) -> str | None:
    for key, value in elem.attrib.items():
        if _local(key) == name:
            return value
    return None


def _children(elem: ET.Element, name: str) -> list[ET.Element]:
    return [c for c in elem if _local(c.tag) == name]


def _child(elem: ET.Element | None, name: str) -> ET.Element | None:
    if elem is None:
        return None
    for c in elem:
        if _local(c.tag) == name:
            return c
    return None


def _text(elem: ET.Element | None) -> str | None:
    if elem is None or elem.text is None:
        return None
    text = elem.text.strip()
    return text or None


def _number(text: str | None) -> int | float | str | None:
    """Property values: int or float when they parse, else the stripped text."""
    if text is None:
        return None
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


# --------------------------------------------------------------------------------------------
# Reading.


@dataclass
class _Node:
    """One parsed ``<root>`` element, before the file's dimension is known."""

    where: str  # human-readable location, used in every message about this root
    rid: str | None
    label: str | None
    accession: str | None
    properties: dict
    functions: dict
    parent_node: int | None
    points: np.ndarray | None = None  # (n, 3), z = 0 where absent; None when unreadable
    has_z: bool = False
    problem: str | None = None
    radius: np.ndarray | None = None  # (n,) radius per point in stored (pixel) units
    radius_problem: str | None = None
    children: list["_Node"] = field(default_factory=list)
    position: str = ""  # "1", "1.3", ... (1-based position among sibling roots)

    def n_descendants(self) -> int:
        return sum(1 for _ in _walk(self.children))  # iterative: files can nest deeply


class _Problems:
    """Collects unreadable parts; raises at once when strict."""

    def __init__(self, source: str, strict: bool):
        self.source = source
        self.strict = strict
        self.items: list[str] = []

    def report(self, where: str, message: str) -> None:
        if self.strict:
            raise RSMLError(f"{self.source}: {where}: {message}")
        self.items.append(f"{where}: {message}")

    def warn(self) -> None:
        if not self.items:
            return
        shown = self.items[:20]
        more = f"; ... and {len(self.items) - 20} more" if len(self.items) > 20 else ""
        warnings.warn(
            RSMLWarning(
                f"{self.source}: skipped {len(self.items)} unreadable part(s) "
                f"(strict=True, or --strict on the command line, raises instead): " + "; ".join(shown) + more
            ),
            stacklevel=user_stacklevel(),
        )


def _parse_points(polyline: ET.Element) -> tuple[np.ndarray, bool]:
    """Points of a ``<polyline>`` as (n, 3) with z = 0 where absent; raises ValueError."""
    rows = []
    z_flags = []
    for k, pt in enumerate(_children(polyline, "point")):
        coords = {}
        for axis in ("x", "y", "z"):
            raw = _attr(pt, axis)
            if raw is None:  # older writers: <point><x>1</x><y>2</y></point>
                raw = _text(_child(pt, axis))
            coords[axis] = raw
        for axis in ("x", "y"):
            if coords[axis] is None:
                raise ValueError(f"point {k} has no {axis} coordinate")
        values = []
        for axis in ("x", "y", "z"):
            raw = coords[axis]
            if raw is None:
                values.append(0.0)
                continue
            try:
                v = float(raw)
            except ValueError:
                raise ValueError(f"point {k}: {axis}={raw!r} is not a number") from None
            if not math.isfinite(v):
                raise ValueError(f"point {k}: {axis}={raw!r} is not finite")
            if abs(v) > ROOT_COORDINATE_LIMIT:
                raise ValueError(
                    f"point {k}: {axis}={raw!r} is too large to compute lengths with (limit "
                    f"{ROOT_COORDINATE_LIMIT:.3g}); rescale the file's coordinates"
                )
            values.append(v)
        rows.append(values)
        z_flags.append(coords["z"] is not None)
    if len(rows) < 2:
        raise ValueError(f"polyline has {len(rows)} point(s); a root needs at least 2")
    if any(z_flags) and not all(z_flags):
        raise ValueError("some points have a z coordinate and others do not")
    pts = np.asarray(rows, dtype=np.float64)
    if not np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) > 0):
        raise ValueError("all points of the polyline coincide (zero length)")
    return pts, all(z_flags)


def _parse_functions(root_el: ET.Element) -> dict:
    out = {}
    for fns in _children(root_el, "functions"):
        for fn in _children(fns, "function"):
            name = _attr(fn, "name") or f"function{len(out)}"
            domain = (_attr(fn, "domain") or "polyline").strip().lower()
            values, positions = [], []
            for s in _children(fn, "sample"):
                raw = _attr(s, "value")
                if raw is None:
                    raw = _text(s)
                try:
                    values.append(float(raw) if raw is not None else math.nan)
                except ValueError:
                    values.append(math.nan)
                pos = _attr(s, "position")
                try:
                    positions.append(float(pos) if pos is not None else math.nan)
                except ValueError:
                    positions.append(math.nan)
            entry = {"domain": domain, "values": np.asarray(values, dtype=np.float64)}
            origin = _attr(fn, "origin")
            if origin is not None:
                entry["origin"] = origin
            if domain == "length" or not all(math.isnan(p) for p in positions):
                entry["positions"] = np.asarray(positions, dtype=np.float64)
            out[name] = entry
    return out


_RADIUS_NAMES = (("diameter", 0.5), ("radius", 1.0))


def _radius_of(node: _Node) -> tuple[np.ndarray | None, str | None]:
    """(radius at each polyline point in stored units, problem) from a ``diameter`` or ``radius``
    function (domains ``polyline``, ``uniform``, ``length``) or, failing that, a numeric
    ``diameter`` / ``radius`` property (one value for the whole branch, as CPlantBox writes)."""
    pts = node.points
    by_name = {str(k).strip().lower(): v for k, v in node.functions.items()}
    for name, factor in _RADIUS_NAMES:
        fn = by_name.get(name)
        if fn is None:
            continue
        what = f"<function name={name!r}>"
        values = fn["values"]
        domain = fn["domain"]
        if values.size == 0:
            return None, f"{what} has no samples; radius dropped"
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            return None, f"{what} has a missing, non-numeric or negative sample; radius dropped"
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        if domain == "polyline":
            if values.size != pts.shape[0]:
                return None, (
                    f"{what} (domain polyline) has {values.size} samples for {pts.shape[0]} points; radius dropped"
                )
            r = values
        elif domain == "uniform":
            # Samples evenly spaced in arc length from the base to the tip.
            where = np.linspace(0.0, cum[-1], values.size) if values.size > 1 else np.zeros(1)
            r = np.interp(cum, where, values)
        elif domain == "length":
            pos = fn.get("positions")
            if pos is None or pos.shape != values.shape or not np.all(np.isfinite(pos)):
                return None, f"{what} (domain length) needs a numeric position on every sample; radius dropped"
            order = np.argsort(pos, kind="stable")
            r = np.interp(cum, pos[order], values[order])
        else:
            return None, f"{what} has unknown domain {domain!r}; radius dropped"
        return np.asarray(r, dtype=np.float64) * factor, None
    for name, factor in _RADIUS_NAMES:
        value = node.properties.get(name)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not (math.isfinite(value) and value >= 0):
                return None, f"property {name}={value!r} is not a finite number >= 0; radius dropped"
            return np.full(pts.shape[0], float(value) * factor), None
    return None, None


def _parse_properties(elem: ET.Element) -> dict:
    out = {}
    for props in _children(elem, "properties"):
        for p in props:
            key = _local(p.tag)
            if not key:
                continue
            raw = _attr(p, "value")
            out[key] = _number(raw if raw is not None else _text(p))
    return out


def _parse_root(el: ET.Element, where_prefix: str, position: str) -> _Node:
    """The `_Node` tree of a ``<root>`` and every ``<root>`` nested in it.

    Iterative (an explicit stack, not recursion), so any nesting depth reads."""
    top = _parse_one_root(el, where_prefix, position)
    stack = [(el, top)]
    while stack:
        el, node = stack.pop()
        for k, c in enumerate(_children(el, "root")):
            child = _parse_one_root(c, where_prefix, f"{node.position}.{k + 1}")
            node.children.append(child)
            stack.append((c, child))
    return top


def _parse_one_root(el: ET.Element, where_prefix: str, position: str) -> _Node:
    """One ``<root>`` element without its nested roots."""
    rid = _attr(el, "id")
    rid = rid.strip() if rid and rid.strip() else None
    label = _attr(el, "label")
    label = label.strip() if label and label.strip() else None
    name_bit = f"root id={rid!r}" if rid else (f"root label={label!r}" if label else "root")
    where = f"{where_prefix}, {name_bit} (root #{position})"
    props = _parse_properties(el)
    pn = props.get("parent-node")
    if isinstance(pn, float) and pn.is_integer():  # "4.0" from some writers
        pn = int(pn)
    node = _Node(
        where=where,
        rid=rid,
        label=label,
        accession=_attr(el, "accession"),
        properties=props,
        functions=_parse_functions(el),
        parent_node=pn if isinstance(pn, int) else None,
        position=position,
    )
    geometry = _child(el, "geometry")
    polyline = _child(geometry, "polyline")
    if geometry is None:
        node.problem = "has no <geometry>" if len(el) else "is empty (no <geometry>)"
    elif polyline is None:
        node.problem = "<geometry> has no <polyline>"
    else:
        try:
            node.points, node.has_z = _parse_points(polyline)
        except ValueError as e:
            node.problem = str(e)
        else:
            node.radius, node.radius_problem = _radius_of(node)
    return node


def _closest(poly: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """(arc length along ``poly`` of its point closest to ``p``, distance to it)."""
    seg = np.diff(poly, axis=0)
    seg_len2 = np.sum(seg * seg, axis=1)
    rel = p[None, :] - poly[:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(seg_len2 > 0, np.sum(rel * seg, axis=1) / seg_len2, 0.0)
    u = np.clip(u, 0.0, 1.0)
    dist = np.linalg.norm(poly[:-1] + u[:, None] * seg - p[None, :], axis=1)
    best = int(np.argmin(dist))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(seg_len2))])
    return float(cum[best] + u[best] * np.sqrt(seg_len2[best])), float(dist[best])


def attachment_fraction(parent: np.ndarray, lateral: np.ndarray, parent_node: int | None) -> tuple[float, str]:
    """Arc-length fraction of a lateral's attachment on its parent, and how it was found.

    The RSML ``parent-node`` (index of a parent polyline point) is used when it agrees with the
    geometry: the lateral's first point must be no farther from the parent's polyline around
    that node (the two segments touching it, which tolerates an off-by-one index) than from the
    whole parent, plus half a local segment length. The fraction is then the projection of the
    lateral's first point onto those two segments. Otherwise — no ``parent-node``, an index out
    of range, or one that points elsewhere — the first point is projected onto the whole parent.
    Returns ``(fraction, "parent-node" | "projection")``.
    """
    base = lateral[0]
    seg_len = np.linalg.norm(np.diff(parent, axis=0), axis=1)
    total = float(np.sum(seg_len))
    s_all, d_all = _closest(parent, base)
    n = parent.shape[0]
    if parent_node is not None and 0 <= parent_node <= n:  # == n: a 1-based last index
        centre = min(parent_node, n - 1)
        lo, hi = max(centre - 1, 0), min(centre + 1, n - 1)
        window = parent[lo : hi + 1]
        s_win, d_win = _closest(window, base)
        tol = 0.5 * float(np.max(seg_len[lo:hi])) + 1e-9 * max(total, 1.0)
        if d_win <= d_all + tol:
            s = float(np.sum(seg_len[:lo])) + s_win
            return min(max(s / total, 0.0), 1.0), "parent-node"
    return min(max(s_all / total, 0.0), 1.0), "projection"


def _source_name(path: Any) -> tuple[str, str]:
    """(label used in messages and metadata, stem used in generated names)."""
    if isinstance(path, (str, os.PathLike)):
        p = Path(path)
        return str(p), p.stem
    name = getattr(path, "name", None)
    if isinstance(name, str):
        return name, Path(name).stem
    return "<stream>", "rsml"


def _file_metadata(meta_el: ET.Element | None, problems: _Problems, physical_units: bool):
    """Metadata shared by every root of the file, and the coordinate scale factor."""
    info: dict[str, Any] = {}
    unit_raw = _text(_child(meta_el, "unit"))
    res_raw = _text(_child(meta_el, "resolution"))
    resolution = None
    if res_raw is not None:
        try:
            resolution = float(res_raw)
        except ValueError:
            resolution = None
        if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
            resolution = None
        if resolution is None:
            problems.report("<metadata>", f"<resolution> {res_raw!r} is not a positive number")
    for tag in ("version", "software", "last-modified", "user", "file-key"):
        value = _text(_child(meta_el, tag))
        if value is not None:
            info[tag.replace("-", "_")] = value
    ts = _child(meta_el, "time-sequence")
    if ts is not None:
        label = _text(_child(ts, "label"))
        index = _number(_text(_child(ts, "index")))
        unified = _text(_child(ts, "unified"))
        if label is not None:
            info["time_sequence"] = label
        if index is not None:
            info["time_index"] = index
        if unified is not None:
            info["time_unified"] = unified.lower() == "true"
    image = _child(meta_el, "image")
    if image is not None:
        info["image"] = {_local(c.tag): _text(c) for c in image if _local(c.tag)}
    species = _text(_child(meta_el, "species"))
    if species is not None:
        info["species"] = species

    scale = 1.0
    is_pixel = unit_raw is None or unit_raw.lower() in PIXEL_UNITS
    info["file_unit"] = unit_raw
    info["resolution"] = resolution
    if not physical_units or is_pixel:
        info["unit"] = "pixel"
    elif not is_known_unit(unit_raw):
        problems.report(
            "<metadata>",
            f"<unit> {unit_raw!r} is not a unit rootshape_jax knows (pixel, mm, cm, m, um, inch); "
            "coordinates kept in pixels",
        )
        info["unit"] = "pixel"
    elif resolution is None:
        if res_raw is None:
            problems.report("<metadata>", f"unit {unit_raw!r} without <resolution>; coordinates kept in pixels")
        info["unit"] = "pixel"
    else:
        info["unit"] = unit_raw
        scale = 1.0 / resolution
    return info, scale


def read_rsml(
    path: str | os.PathLike, *, strict: bool = False, physical_units: bool = True, by: str = "root"
) -> list[Root]:
    """Read every root system of an RSML file.

    **Arguments**

    - `path`: the ``.rsml`` file (a path or an open binary file).
    - `strict`: if True, anything unreadable raises `RSMLError` (naming the file and the root).
      If False (default), unreadable roots are skipped with one `RSMLWarning` per file that
      lists them, and everything else is returned.
    - `physical_units`: convert coordinates to the file's unit (see below). If False, keep the
      stored pixel coordinates and report ``unit = "pixel"``.
    - `by`: ``"root"`` (default): one `Root` per top-level root, as described below.
      ``"plant"``: one `Root` per plant, the whole system (docs/design.md §11): a *virtual main
      root* of zero length (two copies of the collar, the mean of the bases of the plant's axes), its
      top-level roots (seminal, nodal axes, several seedlings' roots) as laterals at
      ``attach = 0`` in file order, and each axis's `Root` (with its own laterals, recursively)
      as the matching entry of `Root.children`. Its radius is 0 along the virtual main root
      when any axis has radii. ``metadata`` holds the plant's fields plus ``virtual_main =
      True`` and ``n_axes``; its name is the plant's label when set and unique, else
      ``"{file stem}/{plant id}"``. Use ``batch(..., depth=3)`` (or more) to keep the axes'
      laterals in the analysis.

    **Returns** a list of `Root`, one per top-level (order-1) root of every plant, in file
    order. A plant with several top-level roots (seminal / nodal axes, several seedlings) gives
    several `Root`s sharing ``metadata["plant_id"]``.

    - `Root.laterals` are the order-2 roots inside the top-level root; `Root.children` holds
      one `Root` per lateral (its `main` is that lateral, its laterals are the order-3 roots,
      and so on), so deeper orders are kept.
    - `Root.attach`: from the RSML ``parent-node`` property when it agrees with the geometry,
      otherwise by projecting the lateral's first point onto its parent (see
      `attachment_fraction`); each child records ``metadata["attach_method"]``.
    - Units: RSML stores pixel coordinates, ``<unit>`` names a physical unit and
      ``<resolution>`` the number of pixels per that unit (SmartRoot: ``inch`` and dpi). With
      ``physical_units=True`` the returned coordinates are ``stored / resolution`` in that
      unit. Files in ``pixel`` (or with no ``<unit>``) are returned as stored. A physical unit
      without a usable resolution keeps pixels (with a warning). ``metadata["unit"]`` always
      names the unit of the returned coordinates; ``metadata["resolution"]`` and
      ``metadata["file_unit"]`` are the file's values. Function samples kept in
      ``metadata["functions"]`` are never rescaled.
    - Radii: a ``diameter`` (radius = diameter / 2) or ``radius`` function gives
      `Root.main_radius` / `Root.lateral_radii` (and each child's `main_radius`), converted like
      the coordinates (``stored / resolution`` in physical units). Domains: ``polyline`` (one
      sample per point), ``uniform`` (samples evenly spaced in arc length from base to tip) and
      ``length`` (``position`` = arc length from the base, in stored units), interpolated
      linearly at the polyline points. Without a function, a numeric ``diameter`` / ``radius``
      property (CPlantBox) is a constant radius. A root without any has radius ``None``; a
      lateral without one beside siblings that have one gets radius 0 (with an
      `RSMLWarning`). An unusable function (wrong sample count, negative or non-numeric
      samples) drops that radius (reported like other unreadable parts).
    - Dimension: the file is 3D if any polyline point has a non-zero ``z``; otherwise roots are
      returned 2D (``z = 0`` is dropped). In a 3D file a root without ``z`` lies in ``z = 0``.
    - Names: the root's ``label`` when it is set and unique in the file, else
      ``"{file stem}/{plant id}/{root id or position}"``.
    - Metadata on every `Root`: ``file``, ``plant_id``, ``plant_label``, ``root_id``,
      ``root_label``, ``order``, ``unit``, ``resolution``, ``file_unit`` and, where present,
      ``accession`` (``po:accession``), ``species``, ``software``, ``time_index``,
      ``time_sequence``, ``properties``, ``functions`` (``{name: {"domain", "values",
      ["positions", "origin"]}}``), ``parent_node``.

    Unreadable (skipped or raising): malformed XML, no ``<scene>``, a root without geometry
    or with an empty ``<root/>``, a polyline with fewer than 2 points or coinciding points,
    a non-numeric / NaN / inf coordinate, or one too large to compute lengths with (above
    ~8e152, or a top-level root whose converted coordinates are; the other roots are kept). A
    bad lateral drops only that lateral (and its own sub-roots). A file with nothing readable
    raises with ``strict=True`` and warns and returns ``[]`` otherwise. Extra geometry
    (``<rootnavspline>``, ...) is ignored. Any nesting depth of ``<root>`` reads.

    Refused with `RSMLError` whatever `strict` says: a file declaring a DTD (``<!DOCTYPE``)
    or entities (billion laughs, quadratic blow-up, external entities); nothing is fetched.
    """
    if by not in ("root", "plant"):
        raise ValueError(f"read_rsml: by must be 'root' or 'plant', got {by!r}.")
    strict = as_flag(strict, "read_rsml: strict")
    physical_units = as_flag(physical_units, "read_rsml: physical_units")
    if not isinstance(path, (str, os.PathLike)) and not hasattr(path, "read"):
        # An int would be opened as a file descriptor, None fails inside ElementTree.
        raise TypeError(f"read_rsml: path must be a file name or an open file, got {path!r}.")
    source, stem = _source_name(path)
    problems = _Problems(source, strict)
    if isinstance(path, (str, os.PathLike)) and Path(path).is_dir():
        raise IsADirectoryError(
            f"read_rsml: {source} is a folder; read_rsml reads one file (rootshape_jax.io.read_folder reads "
            "every RSML file and image of a folder)."
        )
    if isinstance(path, (str, os.PathLike)) and not Path(path).is_file():
        raise FileNotFoundError(f"RSML file not found: {source}")

    try:
        # defusedxml: no DTD, no entity declarations, nothing fetched. RSML never needs them,
        # and they are how XML files blow up memory (billion laughs) or leak local files.
        doc = DET.parse(path, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except DefusedXmlException as e:
        raise RSMLError(
            f"{source}: refused to read: the file declares a DTD or entities ({type(e).__name__}: "
            f"{e}). RSML does not use them and they can exhaust memory or read/fetch other "
            "files; remove the <!DOCTYPE ...> / <!ENTITY ...> declarations if the file is trusted."
        ) from None
    except ET.ParseError as e:
        return _nothing(problems, f"not well-formed XML ({e})")
    except (LookupError, UnicodeError) as e:  # e.g. <?xml encoding="UTF-0"?>
        return _nothing(problems, f"unreadable XML encoding ({e})")
    top = doc.getroot()
    scene = top if _local(top.tag) == "scene" else _child(top, "scene")
    if scene is None:
        return _nothing(problems, f"no <scene> element (top element is <{_local(top.tag)}>)")

    info, scale = _file_metadata(_child(top, "metadata"), problems, physical_units)
    info["file"] = source

    # Pass 1: parse every root, geometry still (n, 3).
    plants = []
    for i, plant_el in enumerate(_children(scene, "plant")):
        pid = _attr(plant_el, "id")
        pid = pid.strip() if pid and pid.strip() else str(i + 1)
        plabel = _attr(plant_el, "label")
        prefix = f"plant {pid!r}"
        nodes = [_parse_root(r, prefix, str(k + 1)) for k, r in enumerate(_children(plant_el, "root"))]
        plant_info = {"plant_id": pid, "plant_label": plabel.strip() if plabel else None}
        pprops = _parse_properties(plant_el)
        species = pprops.get("species", _attr(plant_el, "species"))
        if species is not None:
            plant_info["species"] = str(species)
        accession = _attr(plant_el, "accession")
        if accession is not None:
            plant_info["plant_accession"] = accession
        plants.append((plant_info, nodes))
    # Roots directly under <scene> (seen in hand-made files): one anonymous plant.
    loose = _children(scene, "root")
    if loose:
        nodes = [_parse_root(r, "scene", str(k + 1)) for k, r in enumerate(loose)]
        plants.append(({"plant_id": str(len(plants) + 1), "plant_label": None}, nodes))

    all_nodes = [n for _, nodes in plants for n in _walk(nodes)]
    is_3d = any(n.points is not None and n.has_z and np.any(n.points[:, 2] != 0) for n in all_nodes)
    dim = 3 if is_3d else 2
    label_count: dict[str, int] = {}
    for n in all_nodes:
        if n.label:
            label_count[n.label] = label_count.get(n.label, 0) + 1

    def name_of(node: _Node, pid: str) -> str:
        if node.label and label_count[node.label] == 1:
            return node.label
        return f"{stem}/{pid}/{node.rid or node.position}"

    def build(top: _Node, plant_info: dict) -> Root:
        """The `Root` of a top-level node, children included, without recursion: a pre-order
        pass checks children and finds attachments, then roots are made leaves first."""
        pre: list[tuple[_Node, int, dict]] = []
        usable: dict[int, list[tuple[_Node, float]]] = {}
        stack = [(top, 1, {})]
        while stack:
            node, order, extra = stack.pop()
            pre.append((node, order, extra))
            if node.radius_problem is not None:
                problems.report(node.where, node.radius_problem)
            main = scaled(node)
            kids, pushed = [], []
            for child in node.children:
                if child.problem is not None:
                    problems.report(child.where, _problem_text(child))
                    continue
                lat = scaled(child)
                frac, method = attachment_fraction(main, lat, child.parent_node)
                kids.append((child, frac))
                pushed.append((child, order + 1, {"attach_method": method}))
            usable[id(node)] = kids
            stack.extend(reversed(pushed))  # file order
        built: dict[int, Root] = {}
        for node, order, extra in reversed(pre):  # children before their parent
            kids = [built.pop(id(c)) for c, _ in usable[id(node)]]
            attach = [f for _, f in usable[id(node)]]
            built[id(node)] = make_root(node, plant_info, order, extra, kids, attach)
        return built[id(top)]

    def scaled(node: _Node) -> np.ndarray:
        """The node's points in the returned unit; out of range -> CoordinateRangeError."""
        with np.errstate(over="ignore"):
            pts = node.points[:, :dim] * scale
        check_range(
            np.where(np.isfinite(pts), pts, np.inf),
            limit=ROOT_COORDINATE_LIMIT,
            what=f"{node.where}: in {info['unit']!r}",
            fix="The file's <resolution> is too small for its coordinates; fix it, or read with physical_units=False.",
        )
        return pts

    def make_root(node, plant_info, order, extra, kids, attach) -> Root:
        main = node.points[:, :dim] * scale
        # Radii are stored in pixels like the coordinates, so they take the same scale.
        main_radius = None
        if node.radius is not None:
            with np.errstate(over="ignore"):
                main_radius = node.radius * scale
            if not np.all(main_radius <= ROOT_COORDINATE_LIMIT):
                problems.report(node.where, "radius out of range once converted; radius dropped")
                main_radius = None
        lats = [k.main for k in kids]
        lateral_radii = None
        if any(k.main_radius is not None for k in kids):
            lateral_radii = []
            for k in kids:
                if k.main_radius is None:
                    no_radius.append(k.metadata.get("root_id") or k.name)
                    lateral_radii.append(np.zeros(k.main.shape[0]))
                else:
                    lateral_radii.append(k.main_radius)
            lateral_radii = tuple(lateral_radii)
        meta = dict(info)
        meta.update(plant_info)
        meta.update(root_id=node.rid, root_label=node.label, order=order)
        if "species" in node.properties:
            meta["species"] = str(node.properties["species"])
        if node.accession is not None:
            meta["accession"] = node.accession
        if node.properties:
            meta["properties"] = node.properties
        if node.functions:
            meta["functions"] = node.functions
        if node.parent_node is not None:
            meta["parent_node"] = node.parent_node
        meta.update(extra)
        return Root(
            main=main,
            laterals=tuple(lats),
            attach=np.asarray(attach, dtype=np.float64),
            name=name_of(node, plant_info["plant_id"]),
            metadata=meta,
            children=tuple(kids),
            main_radius=main_radius,
            lateral_radii=lateral_radii,
        )

    top_nodes = [n for _, nodes in plants for n in nodes]
    if strict and all(n.problem is not None for n in top_nodes):
        what = (
            "no root"
            if not top_nodes
            else (
                f"none of its {len(top_nodes)} top-level root(s) has usable geometry "
                f"(first: {top_nodes[0].where}: {top_nodes[0].problem})"
            )
        )
        raise RSMLError(f"{source}: nothing readable: {what}.")
    roots = []
    per_plant: list[tuple[dict, list[Root]]] = []
    no_radius: list[str] = []  # laterals without radius beside siblings that have one
    n_top = 0
    for plant_info, nodes in plants:
        axes: list[Root] = []
        for node in nodes:
            n_top += 1
            if node.problem is not None:
                problems.report(node.where, _problem_text(node))
                continue
            try:
                axes.append(build(node, plant_info))
            except InvalidRootError as e:  # e.g. coordinates out of range after unit scaling
                k = node.n_descendants()
                subs = f" (its {k} sub-root(s) are skipped with it)" if k else ""
                problems.report(node.where, f"{e}{subs}")
        roots.extend(axes)
        if axes:
            per_plant.append((plant_info, axes))
    if not roots:
        what = "no root" if n_top == 0 else f"none of its {n_top} top-level root(s) has usable geometry"
        if strict:
            raise RSMLError(f"{source}: nothing readable: {what}.")
        problems.items.insert(0, f"nothing readable: {what}")
    problems.warn()
    if no_radius:
        shown = ", ".join(repr(n) for n in no_radius[:10])
        more = f" and {len(no_radius) - 10} more" if len(no_radius) > 10 else ""
        warnings.warn(
            RSMLWarning(
                f"{source}: {len(no_radius)} lateral(s) have no diameter/radius while their "
                f"siblings have one; their radius is taken as 0: {shown}{more}."
            ),
            stacklevel=user_stacklevel(),
        )
    if by == "plant":
        plant_labels = [pi.get("plant_label") for pi, _ in per_plant]
        return [
            plant_system(
                axes,
                name=(
                    pi["plant_label"]
                    if pi.get("plant_label") and plant_labels.count(pi["plant_label"]) == 1
                    else f"{stem}/{pi['plant_id']}"
                ),
                metadata={**info, **pi},
            )
            for pi, axes in per_plant
        ]
    return roots


def plant_system(axes: Sequence[Root], *, name: str = "", metadata: dict | None = None) -> Root:
    """One plant as one `Root` (docs/design.md §11): a virtual main root of zero length at the
    collar (the mean of the axes' bases, so the order of the axes does not matter), the axes
    as laterals at ``attach = 0``, and the axes themselves (with their own laterals) as
    `Root.children`.

    `batch` marks such systems (`RootTree.virtual_main`) and registration weighs their axes as
    main roots and every deeper level as the level above it, so plants of one axis each give
    exactly the distances of the axes as taproot systems (at one more level of depth:
    ``batch(plants, depth=D + 1)`` matches ``batch(axes, depth=D)``).

    The plant's ``metadata["unit"]`` is its axes' unit (unless `metadata` gives one); axes in
    different units are a `UnitError`."""
    axes = list(axes)
    if not axes:
        raise InvalidRootError("plant_system: a plant needs at least one axis.")
    # The mean of the axes' bases: the same whatever the order of the axes (one axis: its base;
    # axes sharing a collar: that point); an axis starting elsewhere is joined to it by `batch`.
    collar = np.mean([np.asarray(a.main[0], dtype=np.float64) for a in axes], axis=0).astype(axes[0].main.dtype)
    has_radius = any(a.main_radius is not None for a in axes)
    meta = dict(metadata or {})
    own = units_of(axes)
    if len(own) > 1:
        raise UnitError(
            f"plant_system: the axes are in different units {sorted(own.values())}; convert them to one "
            "first (rootshape_jax.io.convert_units(axes, 'mm'))."
        )
    if own and meta.get("unit") is None:
        meta["unit"] = next(iter(own.values()))  # the plant's lengths are its axes'
    meta.update(virtual_main=True, n_axes=len(axes))
    return Root(
        main=np.stack([collar, collar]),
        laterals=tuple(a.main for a in axes),
        attach=np.zeros(len(axes)),
        name=name,
        metadata=meta,
        children=tuple(axes),
        main_radius=np.zeros(2) if has_radius else None,
        lateral_radii=(
            tuple(a.main_radius if a.main_radius is not None else np.zeros(len(a.main)) for a in axes)
            if has_radius
            else None
        ),
    )


def _axes_of(r: Root) -> list[tuple]:
    """(polyline, Root, radius) of each axis of a plant's system, to write as top-level roots."""
    out = []
    for k, (lat, child) in enumerate(zip(r.laterals, plant_axes(r))):
        radius = child.main_radius
        if radius is None and r.lateral_radii is not None:
            radius = r.lateral_radii[k]
        out.append((lat, child, radius))
    return out


def _problem_text(node: _Node) -> str:
    k = node.n_descendants()
    return node.problem + (f" (its {k} sub-root(s) are skipped with it)" if k else "")


def _walk(nodes: Iterable[_Node]):
    """Every node and its descendants, depth first, in file order (iterative)."""
    stack = list(nodes)[::-1]
    while stack:
        n = stack.pop()
        yield n
        stack.extend(n.children[::-1])


def _nothing(problems: _Problems, message: str) -> list[Root]:
    if problems.strict:
        raise RSMLError(f"{problems.source}: {message}.")
    problems.items.append(message)
    problems.warn()
    return []


# --------------------------------------------------------------------------------------------
# Writing.


def _fmt(v: float, single: bool = False) -> str:
    # The shortest text that reads back as the value, at the precision it was computed in: a
    # float32 921.4 is written "921.4", not its float64 expansion 921.4000244140625.
    return str(np.float32(v)) if single else repr(float(v))


def _is_single(a) -> bool:
    dtype = np.asarray(a).dtype
    return dtype.kind == "f" and dtype.itemsize < 8


def _common(roots: Sequence[Root], key: str):
    values = {repr(r.metadata.get(key)) for r in roots}
    return roots[0].metadata.get(key) if len(values) == 1 else None


def _nearest_node(poly: np.ndarray, fraction: float) -> int:
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    return int(np.argmin(np.abs(cum - fraction * cum[-1])))


def _free_id(taken: set[str], stem: str | None) -> str:
    """A plant id not in `taken`: the first free of 1, 2, ... without a stem (a root without a
    plant id), else stem-2, stem-3, ... (a plant id that another file's plant has already)."""
    names = (str(k) for k in itertools.count(1)) if stem is None else (f"{stem}-{k}" for k in itertools.count(2))
    return next(n for n in names if n not in taken)


def _source_file(root: Root) -> str:
    """The file a root was read from, "" when unknown (a stream's roots cannot be told apart)."""
    source = root.metadata.get("file")
    return "" if source in (None, "", "<stream>") else str(source)


def write_rsml(
    roots: Root | Sequence[Root],
    path: str | os.PathLike,
    *,
    unit: str | None = None,
    resolution: float | None = None,
    software: str = "rootshape_jax",
) -> None:
    """Write roots to an RSML 1.0 file that `read_rsml` (and other RSML tools) read back.

    **Arguments**

    - `roots`: a `Root` or a sequence of them.
    - `path`: the output file.
    - `unit`: unit of the roots' coordinates (a label: nothing is converted). Default: their
      common ``metadata["unit"]``, else ``"pixel"``. A unit other than the one the roots
      carry is a `UnitError` (use `convert_units` to convert).
    - `resolution`: pixels per `unit` written in the file. RSML stores pixel coordinates, so
      the coordinates are multiplied by it (and `read_rsml` divides them back). Default: the
      roots' common ``metadata["resolution"]`` for a physical unit, else 1. Must be 1 (or None)
      for pixel units.
    - `software`: written in ``<metadata><software>``.

    **Layout**: roots sharing ``metadata["plant_id"]`` and ``metadata["file"]`` (as read; roots
    read from streams count as one file) are written in one ``<plant>`` (in first-seen order);
    a root without a plant id gets its own plant. A plant id that roots of another file used
    already is written as ``id-2``, ``id-3``, .... Each root's ``name`` is its
    ``label``, its id is ``metadata["root_id"]`` when set and unused, else a generated unique
    id. Laterals are child ``<root>``s with a ``parent-node`` property (index of the main
    polyline point nearest to the attachment); `Root.children` are written recursively (a
    child's `main` must equal its lateral). 2D roots are written without ``z``; if any root is
    3D, 2D roots get ``z = 0``. Functions kept in ``metadata["functions"]`` are written back
    (polyline-domain ones only when their sample count still matches the polyline). Radii
    (`Root.main_radius`, `Root.lateral_radii`, or a child's `main_radius`) are written as a
    ``diameter`` function (domain ``polyline``, in pixels like the coordinates), replacing any
    ``diameter`` / ``radius`` function kept in the metadata.

    The attachment fractions read back equal `Root.attach` when each lateral starts on the main
    root (as from `read_rsml`, `roots_from_image` and `Root(attach=None)`); RSML stores only
    the parent node, so a lateral starting away from its attachment reads back projected.
    """
    if isinstance(roots, Root):
        roots = [roots]
    if isinstance(roots, (RootTree, SRVFTree)):
        raise TypeError(
            f"write_rsml writes Roots, got a {type(roots).__name__}: convert it with "
            "rootshape_jax.to_roots(tree, unit=...) (name the unit: a tree does not carry it; an SRVFTree "
            "first through rootshape_jax.to_curves)."
        )
    roots = list(roots)
    if not roots:
        raise RSMLError("write_rsml: no roots to write (got an empty sequence).")
    for i, r in enumerate(roots):
        if not isinstance(r, Root):
            raise TypeError(f"write_rsml: item {i} is a {type(r).__name__}, expected a Root.")

    own = units_of(roots)  # by `unit_key`: "mm" is "millimetre", "inch" is "Inches"
    if unit is None:
        if len(own) > 1:
            raise RSMLError(
                f"write_rsml: the roots carry different units {sorted(own.values())}; convert them to "
                "one unit first (or pass unit= to state the unit of all coordinates)."
            )
        unit = next(iter(own.values())) if own else "pixel"
    else:
        stated = sorted(v for k, v in own.items() if k != unit_key(unit))
        if stated:
            raise UnitError(
                f"write_rsml: unit={unit!r}, but the roots' coordinates are in {', '.join(stated)} "
                "(metadata['unit']): write_rsml labels coordinates, it does not convert them. Convert "
                f"first (rootshape_jax.io.convert_units(roots, {unit!r})), or leave unit= out."
            )
    # Written as the file's <unit>: one a reader can convert (read_rsml keeps pixels otherwise).
    check_unit_name(unit, "write_rsml")
    is_pixel = unit.lower() in PIXEL_UNITS
    if resolution is None:
        common = _common(roots, "resolution")
        same_unit = len(own) == 1 and unit_key(unit) in own and all(r.metadata.get("unit") is not None for r in roots)
        if is_pixel or common is None or not same_unit:
            resolution = 1.0
        else:
            resolution = float(common)
    resolution = float(resolution)
    if not (math.isfinite(resolution) and resolution > 0):
        raise RSMLError(f"write_rsml: resolution must be a positive number, got {resolution}.")
    if is_pixel and resolution != 1.0:
        raise RSMLError(
            f"write_rsml: unit {unit!r} is pixels, so resolution must be 1 (got {resolution}); "
            "pass a physical unit (e.g. unit='mm') to write a pixel density."
        )
    dim3 = any(r.dim == 3 for r in roots)

    top = ET.Element("rsml", {"xmlns:po": _PO_NS})
    meta = ET.SubElement(top, "metadata")
    for tag, text in (
        ("version", "1.0"),
        ("unit", unit),
        ("resolution", _fmt(resolution)),
        ("last-modified", datetime.datetime.now().replace(microsecond=0).isoformat()),
        ("software", software),
    ):
        ET.SubElement(meta, tag).text = text
    defs = ET.SubElement(meta, "property-definitions")
    pdef = ET.SubElement(defs, "property-definition")
    ET.SubElement(pdef, "label").text = "parent-node"
    ET.SubElement(pdef, "type").text = "integer"
    t_index, t_label = _common(roots, "time_index"), _common(roots, "time_sequence")
    if t_index is not None or t_label is not None:
        ts = ET.SubElement(meta, "time-sequence")
        if t_label is not None:
            ET.SubElement(ts, "label").text = str(t_label)
        if t_index is not None:
            ET.SubElement(ts, "index").text = str(t_index)
    scene = ET.SubElement(top, "scene")

    # Plants: group by (source file, plant id), keep first-seen order. Plant ids are only
    # unique within a file: seedling 1 of three dates' files are three plants.
    groups: dict[tuple, list[Root]] = {}
    plant_ids: dict[tuple, str] = {}
    used_pids = {str(r.metadata["plant_id"]) for r in roots if r.metadata.get("plant_id") is not None}
    written: set[str] = set()
    for i, r in enumerate(roots):
        pid = r.metadata.get("plant_id")
        key = ("", i) if pid is None else (_source_file(r), str(pid))
        if key not in groups:
            if pid is None:
                name = _free_id(used_pids | written, None)
            else:
                name = key[1] if key[1] not in written else _free_id(used_pids | written, key[1])
            written.add(name)
            plant_ids[key] = name
            groups[key] = []
        groups[key].append(r)

    used_ids: set[str] = set()

    for key, members in groups.items():
        pid = plant_ids[key]
        first = members[0]
        attrs = {"id": pid}
        if first.metadata.get("plant_label"):
            attrs["label"] = str(first.metadata["plant_label"])
        plant_el = ET.SubElement(scene, "plant", attrs)
        tops = []
        for r in members:
            # A plant's system (virtual main root of zero length) is written as its axes.
            tops.extend(_axes_of(r) if is_plant_system(r) and r.n_laterals else [(r.main, r, r.main_radius)])
        for k, (poly, r, radius) in enumerate(tops):
            _write_root(plant_el, poly, r, f"{pid}.{k + 1}", None, resolution, dim3, used_ids, radius)

    data = _serialise(top)
    if hasattr(path, "write"):
        path.write(data)
    else:
        with open(path, "wb") as f:
            f.write(data)


_ATTR_ENTITIES = {"\n": "&#10;", "\r": "&#13;", "\t": "&#9;"}


def _serialise(top: ET.Element) -> bytes:
    """UTF-8 XML of ``top``, indented by two spaces, written with an explicit stack:
    xml.etree's ``indent`` and ``write`` recurse once per level and fail on deep trees.
    (Elements written here have text or children, never both.)"""
    out = ["<?xml version='1.0' encoding='UTF-8'?>\n"]
    stack: list[tuple[ET.Element, int, bool]] = [(top, 0, False)]
    while stack:
        el, depth, closing = stack.pop()
        pad = "  " * depth
        if closing:
            out.append(f"{pad}</{el.tag}>\n")
            continue
        attrs = "".join(f" {k}={quoteattr(str(v), _ATTR_ENTITIES)}" for k, v in el.attrib.items())
        kids = list(el)
        if kids:
            out.append(f"{pad}<{el.tag}{attrs}>\n")
            stack.append((el, depth, True))
            stack.extend((c, depth + 1, False) for c in reversed(kids))
        elif el.text:
            out.append(f"{pad}<{el.tag}{attrs}>{escape(el.text)}</{el.tag}>\n")
        else:
            out.append(f"{pad}<{el.tag}{attrs} />\n")
    return "".join(out).encode("utf-8")


def _unique_id(wanted: Any, fallback: str, used: set[str]) -> str:
    if wanted is not None and str(wanted).strip() and str(wanted) not in used:
        rid = str(wanted)
    else:
        rid, n = fallback, 1
        while rid in used:
            n += 1
            rid = f"{fallback}-{n}"
    used.add(rid)
    return rid


def _write_root(parent_el, polyline, root, fallback_id, parent_node, resolution, dim3, used_ids, radius=None):
    """A ``<root>`` and all its nested laterals, depth first in order, with an explicit stack
    (any nesting depth)."""
    stack = [(parent_el, polyline, root, fallback_id, parent_node, radius)]
    while stack:
        el, poly, r, fid, pn, rad = stack.pop()
        jobs = _write_one_root(el, poly, r, fid, pn, resolution, dim3, used_ids, rad)
        stack.extend(reversed(jobs))


def _write_one_root(
    parent_el, polyline, root, fallback_id, parent_node, resolution, dim3, used_ids, radius
) -> list[tuple]:
    """One ``<root>``: ``polyline`` is its geometry; ``root`` (or None) gives names and laterals;
    ``radius`` (or None) its radius per point, written as a ``diameter`` function. Returns the
    laterals still to write, as `_write_root` stack entries."""
    meta = root.metadata if root is not None else {}
    attrs = {"id": _unique_id(meta.get("root_id"), fallback_id, used_ids)}
    if root is not None and root.name:
        attrs["label"] = root.name
    if meta.get("accession"):
        attrs["po:accession"] = str(meta["accession"])
    el = ET.SubElement(parent_el, "root", attrs)
    if parent_node is not None:
        props = ET.SubElement(el, "properties")
        ET.SubElement(props, "parent-node", {"value": str(parent_node)})
    geom = ET.SubElement(ET.SubElement(el, "geometry"), "polyline")
    single = _is_single(polyline)
    pts = np.asarray(polyline, dtype=np.float64) * resolution
    for p in pts:
        a = {"x": _fmt(p[0], single), "y": _fmt(p[1], single)}
        if dim3:
            a["z"] = _fmt(p[2], single) if p.shape[0] == 3 else "0.0"
        ET.SubElement(geom, "point", a)
    functions = dict(meta.get("functions") or {})
    if radius is not None:
        # The radii are the truth now: drop stale diameter/radius functions read from a file.
        functions = {n: f for n, f in functions.items() if str(n).strip().lower() not in ("diameter", "radius")}
        functions["diameter"] = {
            "domain": "polyline",
            "values": 2.0 * np.asarray(radius, dtype=np.float64) * resolution,
            "single": _is_single(radius),
        }
    written = {
        name: f
        for name, f in functions.items()
        if f.get("domain", "polyline") != "polyline" or len(f["values"]) == pts.shape[0]
    }
    if written:
        fns = ET.SubElement(el, "functions")
        for name, f in written.items():
            fa = {"name": str(name), "domain": f.get("domain", "polyline")}
            if f.get("origin") is not None:
                fa["origin"] = str(f["origin"])
            fn = ET.SubElement(fns, "function", fa)
            positions = f.get("positions")
            for j, v in enumerate(f["values"]):
                sa = {"value": _fmt(v, f.get("single", False))}
                if positions is not None and not math.isnan(positions[j]):
                    sa["position"] = _fmt(positions[j])
                ET.SubElement(fn, "sample", sa)
    if root is None:
        return []
    jobs = []
    for k, lat in enumerate(root.laterals):
        child = root.children[k] if root.children else None
        if child is not None and (
            child.main.shape != lat.shape or not np.allclose(child.main, lat, rtol=1e-12, atol=0)
        ):
            raise RSMLError(
                f"write_rsml: root {root.name!r}: children[{k}].main differs from laterals[{k}]; "
                "a child Root must describe the same polyline as its lateral."
            )
        lat_radius = root.lateral_radii[k] if root.lateral_radii is not None else None
        if child is None:
            # Named so that the lateral keeps an identity when read back.
            child = Root(main=lat, name=f"{root.name}/{k + 1}" if root.name else "")
        elif child.main_radius is not None or lat_radius is None or not np.any(lat_radius > 0):
            # The child is the branch's own record: no radius there means none was known
            # (read_rsml pads such a lateral with 0 in `lateral_radii`). Radii given only on
            # the parent (a user's Root) are kept: all-zero padding is the one thing dropped.
            lat_radius = child.main_radius
        node = _nearest_node(root.main, float(root.attach[k]))
        jobs.append((el, lat, child, f"{attrs['id']}.{k + 1}", node, lat_radius))
    return jobs
