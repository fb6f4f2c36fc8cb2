"""Metadata tables: your labels (condition, genotype, date, ...) joined onto roots by file.

Table format (CSV, comma-, semicolon- or tab-separated, UTF-8 with or without BOM)::

    file,plant,root,condition,genotype
    plate1.rsml,,,control,Col-0            <- every root of plate1.rsml
    plate2,1,,drought,Col-0                <- plant 1 of plate2.rsml (extension optional)
    plate2,2,,drought,ler                  <- plant 2 of plate2.rsml

- ``file`` (required): the file's base name, with or without its extension (no folder).
- ``plant`` (optional): the RSML plant id or plant label (``metadata["plant_id"]`` /
  ``["plant_label"]``). Blank: the row is about every plant of the file.
- ``root`` (optional): the root id, root label or root name (``metadata["root_id"]`` /
  ``["root_label"]``, `Root.name`). Blank: every root (of the plant).
- Every other column is a label. Values are kept as strings, numbers included ("7" stays
  "7"): convert them where you need numbers.

A root takes the most specific row that matches it (file + plant + root over file + plant
over file alone). A root with no row, and a root matched by two rows of the same kind, raise
`MetadataError` naming them.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .._errors import MetadataError, user_stacklevel
from .._root import Root

KEY_COLUMNS = ("file", "plant", "root")
# Metadata the readers set and the analyses rely on: a label must not overwrite them.
RESERVED_COLUMNS = (
    "unit",
    "resolution",
    "file_unit",
    "source_file",
    "plant_id",
    "plant_label",
    "root_id",
    "root_label",
    "order",
    "functions",
    "properties",
    "parent_node",
    "attach_method",
    "name",
    "label_columns",
)


@dataclasses.dataclass(frozen=True)
class MetadataTable:
    """A validated metadata table: its label columns and one dict of strings per row."""

    labels: tuple[str, ...]
    rows: tuple[dict[str, str], ...]
    source: str = "metadata"


def _stem(name: str) -> str:
    p = Path(name.strip())
    return p.stem if p.suffix else p.name


def _sniff(text: str) -> str:
    first = text.splitlines()[0] if text.strip() else ""
    counts = {d: first.count(d) for d in (",", ";", "\t")}
    best = max(counts, key=lambda d: counts[d])
    return best if counts[best] else ","


def read_metadata(path: str | os.PathLike) -> MetadataTable:
    """Read and check a metadata CSV file (format: see `attach_metadata`). Raises
    `MetadataError` naming the problem and how to fix it."""
    p = Path(path)
    if not p.is_file():
        raise MetadataError(f"metadata table {path}: no such file; give the path of a CSV file.")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise MetadataError(
            f"metadata table {path}: cannot read it as UTF-8 text ({e}); save it as CSV UTF-8."
        ) from None
    try:
        reader = csv.DictReader(io.StringIO(text), delimiter=_sniff(text))
        rows = list(reader)
    except csv.Error as e:
        raise MetadataError(f"metadata table {path}: not a readable CSV file ({e}).") from None
    return _table(rows, source=str(path), header=[str(c).strip() for c in reader.fieldnames or []])


def as_table(rows: Any, *, source: str = "metadata") -> MetadataTable:
    """A `MetadataTable` from a CSV path, a list of dicts, or a `MetadataTable`."""
    if isinstance(rows, MetadataTable):
        return rows
    if isinstance(rows, (str, os.PathLike)):
        return read_metadata(rows)
    if isinstance(rows, Mapping) or not isinstance(rows, Sequence):
        raise MetadataError(
            f"{source}: expected a CSV path or a list of dicts (one per row), got {type(rows).__name__}."
        )
    return _table(rows, source=source, header=[])


def _table(rows: Sequence, *, source: str, header: list[str]) -> MetadataTable:
    clean: list[dict[str, str]] = []
    columns: list[str] = list(header)
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise MetadataError(f"{source}: row {i + 1} is a {type(row).__name__}, expected a dict of column: value.")
        if None in row:  # csv.DictReader puts extra cells under None
            raise MetadataError(
                f"{source}: row {i + 2} has more cells than the header has columns; "
                "remove the extra cells or quote values that contain the separator."
            )
        d = {str(k).strip(): "" if v is None else str(v).strip() for k, v in row.items()}
        for k in d:
            if k not in columns:
                columns.append(k)
        if any(d.values()):  # blank lines in a spreadsheet export are not rows
            clean.append(d)
    if "file" not in columns:
        raise MetadataError(
            f"{source}: no 'file' column (columns: {', '.join(columns) or 'none'}); the table needs "
            "a column named 'file' with each RSML file's name, e.g. file,condition."
        )
    reserved = [c for c in columns if c in RESERVED_COLUMNS or c == ""]
    if reserved:
        raise MetadataError(
            f"{source}: column(s) {', '.join(repr(c) for c in reserved)} would overwrite what the "
            "readers set; rename them (e.g. 'unit' -> 'unit_label')."
        )
    if not clean:
        raise MetadataError(f"{source}: the table has no rows.")
    # Each row has every column (a missing cell is blank).
    clean = [{c: d.get(c, "") for c in columns} for d in clean]
    blank = [i + 2 for i, d in enumerate(clean) if not d["file"]]
    if blank:
        raise MetadataError(f"{source}: row(s) {_rows(blank)} have no file name; fill in the 'file' column.")
    seen: dict[tuple[str, str, str], int] = {}
    dups = []
    for i, d in enumerate(clean):
        key = (_stem(d["file"]), d.get("plant", ""), d.get("root", ""))
        if key in seen:
            dups.append(f"rows {seen[key]} and {i + 2} ({_describe(key)})")
        else:
            seen[key] = i + 2
    if dups:
        raise MetadataError(
            f"{source}: duplicate rows: {'; '.join(dups)}. Keep one row per file (or per file and "
            "plant / root); add a 'plant' or 'root' column to tell them apart."
        )
    labels = tuple(c for c in columns if c not in KEY_COLUMNS)
    return MetadataTable(labels=labels, rows=tuple(clean), source=source)


def _rows(numbers: list[int]) -> str:
    return ", ".join(map(str, numbers[:10])) + (f" and {len(numbers) - 10} more" if len(numbers) > 10 else "")


def _describe(key: tuple[str, str, str]) -> str:
    text = f"file {key[0]!r}"
    if key[1]:
        text += f", plant {key[1]!r}"
    if key[2]:
        text += f", root {key[2]!r}"
    return text


def _file_of(root: Root) -> str | None:
    where = root.metadata.get("source_file") or root.metadata.get("file")
    return None if where is None else Path(str(where)).name


def _matches(value: str, *candidates: Any) -> bool:
    return any(c is not None and str(c) == value for c in candidates)


def attach_metadata(roots: Sequence[Root], table: Any) -> list[Root]:
    """The roots with the labels of `table` in their ``metadata``.

    `table`: a CSV path, a list of dicts (one per row) or a `MetadataTable`. The format and the
    matching rules are described in this module's docstring: a ``file`` column (base name,
    extension optional), optional ``plant`` and ``root`` columns, every other column a label
    (kept as a string). A root is found by ``metadata["source_file"]`` (set by `read_folder`)
    or ``metadata["file"]`` (set by `read_rsml`).

    Raises `MetadataError` listing every root with no row, every root matched by two rows,
    and roots that have no file name. Rows that match no root (e.g. a file skipped as
    unreadable) give one warning.
    """
    table = as_table(table)
    by_file: dict[str, list[tuple[int, dict[str, str]]]] = {}
    for i, row in enumerate(table.rows):
        by_file.setdefault(_stem(row["file"]), []).append((i, row))
    used: set[int] = set()
    missing, ambiguous, nameless = [], [], []
    out = []
    for r in roots:
        fname = _file_of(r)
        if fname is None:
            nameless.append(r.name or "?")
            continue
        rows = by_file.get(_stem(fname), [])
        meta = r.metadata
        best: list[tuple[int, dict[str, str]]] = []
        best_rank = -1
        for i, row in rows:
            plant, rid = row.get("plant", ""), row.get("root", "")
            if plant and not _matches(plant, meta.get("plant_id"), meta.get("plant_label")):
                continue
            if rid and not _matches(rid, meta.get("root_id"), meta.get("root_label"), r.name):
                continue
            rank = bool(plant) + 2 * bool(rid)
            if rank > best_rank:
                best, best_rank = [(i, row)], rank
            elif rank == best_rank:
                best.append((i, row))
        who = f"{r.name} ({fname})" if r.name else fname
        if not best:
            missing.append(who)
            continue
        if len(best) > 1:
            ambiguous.append(f"{who}: rows {', '.join(str(i + 2) for i, _ in best)}")
            continue
        i, row = best[0]
        used.add(i)
        labels = {k: row[k] for k in table.labels}
        # `label_columns` names the table's columns, so the figures know which to draw.
        out.append(dataclasses.replace(r, metadata=dict(meta, **labels, label_columns=table.labels)))
    if nameless:
        raise MetadataError(
            f"{table.source}: root(s) {', '.join(nameless[:10])} have no file name to match; read them "
            "with read_folder, or set metadata['source_file']."
        )
    problems = []
    if missing:
        more = f" and {len(missing) - 10} more" if len(missing) > 10 else ""
        problems.append(
            f"no row for {len(missing)} root(s): {', '.join(missing[:10])}{more}. Add a row for each "
            "(file name, and plant / root where a file holds several differently labelled roots)"
        )
    if ambiguous:
        problems.append(
            f"several rows match {len(ambiguous)} root(s): {'; '.join(ambiguous[:10])}. Keep one, "
            "or tell them apart with the 'plant' / 'root' columns"
        )
    if problems:
        raise MetadataError(f"{table.source}: " + "; ".join(problems) + ".")
    unused = [table.rows[i]["file"] for i in range(len(table.rows)) if i not in used]
    if unused:
        warnings.warn(
            f"{table.source}: {len(unused)} row(s) match no root read: {', '.join(unused[:10])}"
            + (" ..." if len(unused) > 10 else "")
            + ".",
            stacklevel=user_stacklevel(),
        )
    return out


def labels_of(roots: Sequence[Root], column: str) -> list[str]:
    """Each root's value of the label `column`; `MetadataError` naming the roots without one
    and the labels that exist."""
    missing = [r.name for r in roots if r.metadata.get(column) in (None, "")]
    if missing:
        have = sorted({k for r in roots for k in r.metadata.get("label_columns", ())})
        more = f" and {len(missing) - 10} more" if len(missing) > 10 else ""
        raise MetadataError(
            f"label {column!r} is missing for {len(missing)} root(s): {', '.join(missing[:10])}{more}. "
            f"Give every root a value in that column of the metadata table (labels seen: "
            f"{', '.join(have) or 'none'})."
        )
    return [str(r.metadata[column]) for r in roots]
