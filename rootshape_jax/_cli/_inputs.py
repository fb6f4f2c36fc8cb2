"""Reading roots (files, folders, images, synthetic) and preparing them for the analyses."""

from __future__ import annotations

import csv
import dataclasses
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import rootshape_jax as rs

from ._common import IMAGE_SUFFIXES, PAPER_TRAITS, RSML_SUFFIXES, CLIError, warn


def files_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RSML_SUFFIXES + IMAGE_SUFFIXES)


@dataclasses.dataclass
class Reading:
    """What reading the input files found: the terminal gets one line per problem file and a
    summary; `log` keeps the full messages (written to the output folder's log file)."""

    log_path: str = ""
    files: int = 0
    roots: int = 0
    skipped: list[tuple[str, str]] = dataclasses.field(default_factory=list)  # (file, reason)
    log: list[str] = dataclasses.field(default_factory=list)

    def summary(self) -> str:
        text = f"read {self.roots} root system(s) from {self.files} file(s)"
        if self.skipped:
            text += f"; skipped {len(self.skipped)}: " + ", ".join(f"{f} ({why})" for f, why in self.skipped)
        return text + "."


def short_reason(message: str, path: Path) -> str:
    """The gist of an error or warning about `path`: its first clause, without the path."""
    text = message.strip().splitlines()[0] if message.strip() else "unreadable"
    for prefix in (f"{path}: ", f"{path.name}: "):
        if text.startswith(prefix):
            text = text[len(prefix) :]
    cut = min((i for i in (text.find(" ("), text.find(": "), text.find("; ")) if i > 0), default=len(text))
    text = text[:cut].rstrip(".")
    return text if len(text) <= 70 else text[:69] + "…"


def _about(path: Path, message: str) -> str:
    return message if message.startswith(str(path)) else f"{path}: {message}"


def read_file(path: Path, args, reading: Reading | None = None) -> list:
    from rootshape_jax import io

    suffix = path.suffix.lower()
    if suffix in RSML_SUFFIXES:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            roots = io.read_rsml(path)
        if not roots:
            io.read_rsml(path, strict=True)  # raises the precise reason as one RSMLError
        # Parts skipped in a file that is otherwise readable: one line here, all in the log.
        others = [w for w in caught if not issubclass(w.category, rs.RSMLWarning)]
        caught = [w for w in caught if issubclass(w.category, rs.RSMLWarning)]
        for w in others:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        for w in caught:
            if reading is not None:
                reading.log.append(f"warning: {_about(path, str(w.message))}")
        if caught:
            where = f" (details in {reading.log_path})" if reading is not None and reading.log_path else ""
            warn(
                f"{path}: {short_reason(str(caught[0].message), path)}"
                + (f" and {len(caught) - 1} more warning(s)" if len(caught) > 1 else "")
                + where
            )
    elif suffix in IMAGE_SUFFIXES:
        pixel_size = getattr(args, "pixel_size", None)
        unit = getattr(args, "unit", None) or ("mm" if pixel_size else "pixel")
        roots = io.roots_from_image(path, pixel_size=pixel_size, unit=unit)
    else:
        raise CLIError(
            f"{path}: unsupported file type {path.suffix or '(no extension)'!r}; give .rsml files, "
            f"images ({', '.join(IMAGE_SUFFIXES)}) or folders of them."
        )
    if not roots:
        raise CLIError(f"{path}: no roots found in this file.")
    out = []
    for i, r in enumerate(roots):
        name = r.name or (path.stem if len(roots) == 1 else f"{path.stem}_{i}")
        meta = dict(r.metadata, source_file=str(path))
        out.append(dataclasses.replace(r, name=name, metadata=meta))
    return out


def expand(paths: Sequence[str]) -> list[tuple[Path, bool]]:
    """Every file to read, and whether it was found in a folder (then it may be skipped)."""
    files: list[tuple[Path, bool]] = []
    for text in paths:
        p = Path(text)
        if not p.exists():
            raise CLIError(f"{text}: no such file or folder.")
        if p.is_dir():
            found = files_in(p)
            if not found:
                raise CLIError(
                    f"{text}: the folder contains no RSML files (.rsml) or images ({', '.join(IMAGE_SUFFIXES)})."
                )
            files.extend((f, True) for f in found)
        else:
            files.append((p, False))
    return files


def unique_names(roots: list) -> list:
    """Names that tell roots apart: a name shared by several roots gets its file name in front,
    and a number behind if that is not enough."""
    counts: dict[str, int] = {}
    for r in roots:
        counts[r.name] = counts.get(r.name, 0) + 1
    names = [
        f"{Path(r.metadata.get('source_file', '')).stem}/{r.name}" if counts[r.name] > 1 else r.name for r in roots
    ]
    seen: dict[str, int] = {}
    out = []
    for r, name in zip(roots, names):
        seen[name] = seen.get(name, 0) + 1
        if names.count(name) > 1:
            name = f"{name}_{seen[name]}"
        out.append(dataclasses.replace(r, name=name))
    return out


def load_roots(args, *, paths: Sequence[str] | None = None, reading: Reading | None = None) -> list:
    """The roots named on the command line: files, folders, images, or --synthetic.

    A file named on the command line must be readable. A file found in a folder that cannot be
    read is skipped with one line on stderr (its full reason in `reading.log`), unless
    ``args.strict``; the run fails only when nothing at all is readable.
    """
    paths = list(args.inputs if paths is None else paths)
    synthetic = getattr(args, "synthetic", None)
    if paths and synthetic:
        raise CLIError("give either input files/folders or --synthetic N, not both.")
    if synthetic:
        from rootshape_jax.datasets import synthetic_roots

        conditions = args.condition or ["control"]
        roots = []
        for c in conditions:
            roots.extend(synthetic_roots(synthetic, condition=c, seed=args.seed))
        return roots
    if not paths:
        raise CLIError("no input: give RSML files, folders or images, or --synthetic N for example roots.")
    reading = Reading() if reading is None else reading
    roots = []
    for f, in_folder in expand(paths):
        try:
            got = read_file(f, args, reading)
        except (CLIError, rs.RootShapeError, OSError, ValueError) as e:
            if not in_folder or getattr(args, "strict", False):
                raise
            why = short_reason(str(e), f)
            reading.skipped.append((f.name, why))
            reading.log.append(f"skipped: {_about(f, str(e))}")
            warn(f"skipped {f}: {why}")
            continue
        reading.files += 1
        reading.roots += len(got)
        roots.extend(got)
    if not roots:
        skipped = ", ".join(f"{f} ({why})" for f, why in reading.skipped)
        raise CLIError(f"no readable roots: every file was skipped: {skipped}. Fix or remove these files.")
    return unique_names(roots)


def pick(roots: list, index: int, path: str):
    if not -len(roots) <= index < len(roots):
        raise CLIError(f"{path}: has {len(roots)} root(s); root number {index} does not exist.")
    return roots[index]


def subsample(roots: list, n: int | None) -> list:
    """At most `n` roots, evenly spaced through the input order (every group keeps members)."""
    if n is None or n >= len(roots):
        return list(roots)
    idx = np.unique(np.round(np.linspace(0, len(roots) - 1, n)).astype(int))
    return [roots[i] for i in idx]


def common_unit(roots) -> str | None:
    units = {r.metadata.get("unit") for r in roots}
    return units.pop() if len(units) == 1 else None


def read_requested(path: str) -> np.ndarray:
    """The requested traits of `regress --requested` (checked before any computation)."""
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"--requested {path}: no such file.")
    try:
        with open(p, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise CLIError(f"--requested {path}: cannot read the CSV file ({e}).") from None
    missing = [k for k in PAPER_TRAITS if not rows or k not in rows[0]]
    if missing:
        raise CLIError(f"--requested {path}: needs columns {', '.join(PAPER_TRAITS)}; missing {', '.join(missing)}.")
    try:
        values = np.array([[float(r[k]) for k in PAPER_TRAITS] for r in rows])
    except ValueError:
        raise CLIError(f"--requested {path}: every trait value must be a number.") from None
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise CLIError(f"--requested {path}: trait values must be finite and non-negative.")
    return values


@dataclasses.dataclass
class Population:
    """Roots prepared for the shape analysis: as read, and resampled/padded into a batch."""

    roots: list  # as read (after --samples and --laterals), original units
    tree: object  # batched RootTree
    names: list[str]
    normalised: bool
    unit: str | None
    mean_length: float  # mean main-root length, in `unit`
    conditions: list | None

    def output_scale(self) -> float:
        """Factor that takes analysis coordinates back to the input's units."""
        return self.mean_length if self.normalised else 1.0


def prepare(roots: list, args, *, min_roots: int = 1, samples: int | None = None) -> Population:
    """Subsample (--samples), keep the longest laterals (--laterals), resample and pad."""
    roots = subsample(roots, samples)
    roots = [rs.limit_laterals(r, args.laterals) for r in roots]
    if len(roots) < min_roots:
        raise CLIError(f"this analysis needs at least {min_roots} roots, got {len(roots)}.")
    normalised = args.normalise_scale
    tree = rs.batch(roots, n_points=args.points, normalise_scale=normalised)
    conditions = [r.metadata.get("condition") for r in roots]
    return Population(
        roots=roots,
        tree=tree,
        names=[r.name for r in roots],
        normalised=normalised,
        unit=common_unit(roots),
        mean_length=float(np.mean([r.main_length for r in roots])),
        conditions=conditions if all(c is not None for c in conditions) else None,
    )


def to_output_roots(tree, pop: Population, names: Sequence[str]) -> list:
    """Unpadded roots (null slots dropped) labelled with the input's unit."""
    meta = {"unit": pop.unit} if pop.unit else {}
    return [dataclasses.replace(r, metadata=dict(meta)) for r in rs.to_roots(tree, names=list(names))]


def in_input_units(tree, pop: Population):
    """Analysis coordinates back in the input's units: scale-normalised roots are scaled by
    the inputs' mean main-root length."""
    return rs.scale_tree(tree, pop.output_scale()) if pop.normalised else tree
