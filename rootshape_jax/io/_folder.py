"""Reading folders of root files: every RSML file and image, a bad file skipped and named."""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from .._errors import InputError, RootShapeError, RSMLError, RSMLWarning, user_stacklevel
from .._root import Root
from ._image import roots_from_image
from ._rsml import read_rsml
from ._units import PIXEL_UNITS, convert_units

RSML_SUFFIXES = (".rsml",)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: PNG "Software" text of the figures rootshape writes: a folder of results read again (e.g.
#: `rootshape traits out/`) must not read its figures as photographs of roots.
FIGURE_SOFTWARE = "rootshape_jax figure"
#: The command line's log, written into every --out folder: its PNGs are rootshape's figures
#: (also those written before the figures carried `FIGURE_SOFTWARE`).
OUTPUT_LOG = "rootshape.log"


@dataclasses.dataclass
class ReadReport:
    """What reading found: counts, skipped files with a short reason, and the full messages.

    Pass one to `read_folder(report=...)` to get these details (the command line prints
    `summary()` and writes `log` to its log file)."""

    files: int = 0
    roots: int = 0
    skipped: list[tuple[str, str]] = dataclasses.field(default_factory=list)  # (file name, reason)
    log: list[str] = dataclasses.field(default_factory=list)

    def summary(self) -> str:
        text = f"read {self.roots} root system(s) from {self.files} file(s)"
        if self.skipped:
            text += f"; skipped {len(self.skipped)}: " + ", ".join(f"{f} ({why})" for f, why in self.skipped)
        return text + "."


def root_files(folder: str | os.PathLike) -> list[Path]:
    """The RSML files and images directly inside `folder`, sorted by name; not the overlays
    that `rootshape extract` writes beside its RSML files (`extract_overlays`) nor the
    figures rootshape wrote (`rootshape_figures`)."""
    return _scan(Path(folder))[0]


def _scan(folder: Path) -> tuple[list[Path], list[Path], list[Path]]:
    """(`root_files` of `folder`, the `extract_overlays` and the `rootshape_figures` left out
    of them), from one listing."""
    found = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RSML_SUFFIXES + IMAGE_SUFFIXES]
    overlays = extract_overlays(found)
    figures = sorted(set(rootshape_figures(found, folder)) - set(overlays))
    return sorted(set(found) - set(overlays) - set(figures)), overlays, figures


def rootshape_figures(files: Sequence[Path], folder: Path) -> list[Path]:
    """The PNGs among `files` that rootshape drew (a results folder read again): those whose
    PNG "Software" text is `FIGURE_SOFTWARE`, and every PNG of a folder holding the command
    line's log (`OUTPUT_LOG`)."""
    pngs = [p for p in files if p.suffix.lower() == ".png"]
    if (folder / OUTPUT_LOG).is_file():
        return pngs
    return [p for p in pngs if _png_software(p) == FIGURE_SOFTWARE]


def _png_software(path: Path) -> str | None:
    """The PNG's "Software" text (read from its header chunks only), None if unreadable."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            return im.info.get("Software")
    except Exception:  # not our concern here: reading the file as an image reports it
        return None


def extract_overlays(files: Sequence[Path]) -> list[Path]:
    """The images among `files` that are `rootshape extract`'s drawings, not photographs:
    ``<stem>_overlay.png`` beside its ``<stem>.rsml``. Read as photographs they would add a
    second, wrong copy of every extracted root."""
    rsml = {p.with_suffix("").name for p in files if p.suffix.lower() in RSML_SUFFIXES}
    return [
        p
        for p in files
        if p.suffix.lower() == ".png" and p.stem.endswith("_overlay") and p.stem[: -len("_overlay")] in rsml
    ]


def short_reason(message: str, path: Path) -> str:
    """The gist of an error or warning about `path`: its first clause, without the path."""
    text = message.strip().splitlines()[0] if message.strip() else "unreadable"
    for prefix in (f"{path}: ", f"{path.name}: "):
        if text.startswith(prefix):
            text = text[len(prefix) :]
    cut = min((i for i in (text.find(" ("), text.find(": "), text.find("; ")) if i > 0), default=len(text))
    text = text[:cut].rstrip(".")
    return text if len(text) <= 70 else text[:69] + "…"


def about(path: Path, message: str) -> str:
    """`message` starting with the path it is about."""
    return message if message.startswith(str(path)) else f"{path}: {message}"


def _default_notice(kind: str, text: str) -> None:
    warnings.warn(RSMLWarning(text), stacklevel=user_stacklevel())


def read_root_file(
    path: str | os.PathLike,
    *,
    pixel_size: float | None = None,
    unit: str | None = None,
    report: ReadReport | None = None,
    notice: Callable[[str, str], None] | None = None,
    by: str = "root",
) -> list[Root]:
    """Every root of one RSML file or image, named and tagged with ``metadata["source_file"]``.

    `by`: as in `read_rsml` (``"plant"``: one system per plant of an RSML file); an image's
    roots are its seedlings, one system each, either way.

    Parts of an RSML file that cannot be read are summarised in one `notice` line (full text
    in ``report.log``); a file with nothing readable raises `RSMLError` with the precise reason.
    `pixel_size` (length of a pixel in `unit`, default mm), when given, puts images and RSML
    roots in pixels without a physical resolution (RootNav, RhizoScan, ...) in `unit`; RSML
    files with their own ``<unit>`` and ``<resolution>`` keep them.
    """
    path = Path(path)
    notice = _default_notice if notice is None else notice
    suffix = path.suffix.lower()
    if suffix in RSML_SUFFIXES:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            roots = read_rsml(path, by=by)
        if not roots:
            read_rsml(path, strict=True, by=by)  # raises the precise reason as one RSMLError
        # Parts skipped in a file that is otherwise readable: one line here, all in the log.
        for w in caught:
            if not issubclass(w.category, RSMLWarning):
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        caught = [w for w in caught if issubclass(w.category, RSMLWarning)]
        if report is not None:
            report.log.extend(f"warning: {about(path, str(w.message))}" for w in caught)
        if caught:
            notice(
                "warning",
                f"{path}: {short_reason(str(caught[0].message), path)}"
                + (f" and {len(caught) - 1} more warning(s)" if len(caught) > 1 else ""),
            )
        if pixel_size is not None:
            roots = [_with_pixel_size(r, pixel_size, unit or "mm") for r in roots]
    elif suffix in IMAGE_SUFFIXES:
        roots = roots_from_image(path, pixel_size=pixel_size, unit=(unit or "mm") if pixel_size else "pixel")
    else:
        raise InputError(
            f"{path}: unsupported file type {path.suffix or '(no extension)'!r}; give .rsml files, "
            f"images ({', '.join(IMAGE_SUFFIXES)}) or folders of them."
        )
    if not roots:
        raise RSMLError(f"{path}: no roots found in this file.")
    out = []
    for i, r in enumerate(roots):
        name = r.name or (path.stem if len(roots) == 1 else f"{path.stem}_{i}")
        out.append(dataclasses.replace(r, name=name, metadata=dict(r.metadata, source_file=str(path))))
    return out


def _with_pixel_size(root: Root, pixel_size: float, unit: str) -> Root:
    """A root in pixels with no physical resolution, in `unit` through the pixel size given
    (pixels per `unit` = 1 / `pixel_size`); any other root as it is."""
    if str(root.metadata.get("unit")).lower() not in PIXEL_UNITS:
        return root
    meta = dict(root.metadata, file_unit=unit, resolution=1.0 / float(pixel_size))
    (out,) = convert_units(dataclasses.replace(root, metadata=meta), unit)
    return out


def expand(paths: Sequence[str | os.PathLike]) -> list[tuple[Path, bool]]:
    """Every file to read, and whether it was found in a folder (then it may be skipped)."""
    files: list[tuple[Path, bool]] = []
    for text in paths:
        p = Path(text)
        if not p.exists():
            raise InputError(f"{text}: no such file or folder.")
        if p.is_dir():
            found, overlays, figures = _scan(p)
            if overlays:
                warnings.warn(
                    f"{text}: left out {len(overlays)} overlay image(s) that `rootshape extract` wrote "
                    "(<name>_overlay.png beside <name>.rsml): the roots are read from the RSML files.",
                    UserWarning,
                    stacklevel=user_stacklevel(),
                )
            if figures:
                names = ", ".join(f.name for f in figures[:4]) + (", ..." if len(figures) > 4 else "")
                warnings.warn(
                    f"{text}: left out {len(figures)} figure(s) that rootshape drew ({names}): they are "
                    "results, not photographs of roots.",
                    UserWarning,
                    stacklevel=user_stacklevel(),
                )
            if not found:
                subs = sorted(q.name for q in p.iterdir() if q.is_dir() and not q.name.startswith("."))
                hint = (
                    f" It has subfolders ({', '.join(subs[:4])}{', ...' if len(subs) > 4 else ''}), which are not "
                    "searched: name them instead (several folders may be given)."
                    if subs
                    else ""
                )
                raise InputError(
                    f"{text}: the folder contains no RSML files (.rsml) or images ({', '.join(IMAGE_SUFFIXES)})." + hint
                )
            files.extend((f, True) for f in found)
        else:
            files.append((p, False))
    return files


def _names_file(name: str, stem: str) -> bool:
    """True when `name` already starts with its file's name (``stem/plant/root``)."""
    return name == stem or name.startswith(stem + "/")


def unique_names(roots: list[Root]) -> list[Root]:
    """Names that tell roots apart: a name shared by several roots gets its file name in front,
    and a number behind if that is not enough. Roots read from several files all carry their
    file's name: a label a tracing tool writes in every file (SmartRoot's ``root_1``) says
    nothing about which file, so ``lupin/root_1`` and ``maize/root_1`` are kept apart."""
    counts: dict[str, int] = {}
    for r in roots:
        counts[r.name] = counts.get(r.name, 0) + 1
    stems = [Path(r.metadata.get("source_file", "")).stem for r in roots]
    several = len({s for s in stems if s}) > 1
    names = [
        f"{stem}/{r.name}" if stem and (counts[r.name] > 1 or (several and not _names_file(r.name, stem))) else r.name
        for r, stem in zip(roots, stems)
    ]
    seen: dict[str, int] = {}
    out = []
    for r, name in zip(roots, names):
        seen[name] = seen.get(name, 0) + 1
        if names.count(name) > 1:
            name = f"{name}_{seen[name]}"
        out.append(dataclasses.replace(r, name=name))
    return out


def read_paths(
    paths: Sequence[str | os.PathLike],
    *,
    strict: bool = False,
    pixel_size: float | None = None,
    unit: str | None = None,
    report: ReadReport | None = None,
    notice: Callable[[str, str], None] | None = None,
    by: str = "root",
) -> list[Root]:
    """The roots of files and folders. A file named in `paths` must be readable; a file found
    in a folder that cannot be read is skipped (one `notice` line, its reason in
    ``report.log``) unless `strict`. Raises `InputError` when nothing at all is readable.
    `by`: ``"root"`` or ``"plant"``, as in `read_rsml`."""
    if by not in ("root", "plant"):  # checked once, not as a reason to skip every file
        raise ValueError(f"by must be 'root' or 'plant', got {by!r}.")
    report = ReadReport() if report is None else report
    notice = _default_notice if notice is None else notice
    roots: list[Root] = []
    for f, in_folder in expand(paths):
        try:
            got = read_root_file(f, pixel_size=pixel_size, unit=unit, report=report, notice=notice, by=by)
        except (RootShapeError, OSError, ValueError) as e:
            if not in_folder or strict:
                raise
            why = short_reason(str(e), f)
            report.skipped.append((f.name, why))
            report.log.append(f"skipped: {about(f, str(e))}")
            notice("skipped", f"skipped {f}: {why}")
            continue
        report.files += 1
        report.roots += len(got)
        roots.extend(got)
    if not roots:
        skipped = ", ".join(f"{f} ({why})" for f, why in report.skipped)
        raise InputError(f"no readable roots: every file was skipped: {skipped}. Fix or remove these files.")
    return unique_names(roots)


def read_folder(
    path: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    metadata: Any = None,
    strict: bool = False,
    unit: str | None = None,
    pixel_size: float | None = None,
    report: ReadReport | None = None,
    by: str = "root",
) -> list[Root]:
    """Every root system in a folder of RSML files and images, with your labels attached.

    **Arguments**

    - `path`: a folder (every ``.rsml`` file and image directly inside, in name order), a
      file, or a list of them.
    - `metadata`: optional table of labels (conditions, genotypes, dates, ...): a CSV path or
      a list of dicts. See `attach_metadata` for the format; its label columns end up in each
      `Root.metadata` as strings.
    - `strict`: if True, the first unreadable file raises. If False (default), an unreadable
      file in a folder is skipped with one `RSMLWarning` naming it and its reason.
    - `unit`: convert every root to this length unit (``"mm"``, ``"cm"``, ``"inch"``, ...) with
      `convert_units`; default: keep each file's unit (``metadata["unit"]``).
    - `pixel_size`: the length of one pixel, in `unit` (mm by default), for images and for RSML
      roots in pixels without a physical resolution.
    - `report`: a `ReadReport` to fill with counts, skipped files and the full messages.
    - `by`: ``"root"`` (default): one `Root` per top-level root; ``"plant"``: one per plant,
      the whole system (as `read_rsml(by="plant")` and the command line's ``--per plant``;
      batch them with ``depth=3`` or more to keep the axes' laterals).

    **Returns** a list of `Root`: names made unique across files, ``metadata["source_file"]``
    set to the file read.
    """
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    roots = read_paths(paths, strict=strict, pixel_size=pixel_size, unit=unit, report=report, by=by)
    if unit is not None:
        roots = convert_units(roots, unit)
    if metadata is not None:
        from ._metadata import attach_metadata

        roots = attach_metadata(roots, metadata)
    return roots
