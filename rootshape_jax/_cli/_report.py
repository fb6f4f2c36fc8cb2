"""The output folder: every file written (CSV, PNG, RSML), its caption, and index.html."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import fnmatch
import html
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rootshape_jax._atomic import atomic_write
from rootshape_jax.io._folder import FIGURE_SOFTWARE, OUTPUT_LOG

from ._common import CLIError, fmt, make_weights, version


@dataclasses.dataclass
class Item:
    kind: str  # "figure", "table", "file"
    path: str
    caption: str
    html: str = ""


@dataclasses.dataclass
class Section:
    title: str
    seconds: float = 0.0
    items: list[Item] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)


# Every name the command line writes (a folder holding any of them holds earlier results).
OUTPUT_NAMES = (
    "index.html",
    OUTPUT_LOG,
    "traits.csv",
    "distances.csv",
    "distances.png",
    "geodesic.png",
    "geodesic_step_*.rsml",
    "mean.rsml",
    "mean.png",
    "mean_energy.csv",
    "mean_energy.png",
    "explained_variance.csv",
    "explained_variance.png",
    "modes.png",
    "pca_scores.csv",
    "pca_scores.png",
    "random_roots.rsml",
    "random_roots.csv",
    "random_roots.png",
    "regression_report.csv",
    "predicted_roots.rsml",
    "predicted_roots.csv",
    "predicted_roots.png",
    "clusters.csv",
    "dendrogram.png",
    "classification.csv",
    "permanova.csv",
    "permanova.md",
    "mds.csv",
    "mds.png",
    "systems_*.csv",  # the demo's whole-root-systems section
    "systems_*.png",
)
LOG_NAME = OUTPUT_LOG


def is_output_name(name: str) -> bool:
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in OUTPUT_NAMES)


def refuse_earlier_results(folder, earlier: list[str]) -> None:
    """`CLIError` when the --out `folder` holds files of an earlier run (`earlier`, their names).
    A log alone is no result (a run stopped, e.g. by SIGTERM, before writing any): not refused."""
    if set(earlier) - {LOG_NAME}:
        earlier = sorted(earlier)
        shown = ", ".join(earlier[:6]) + (f" and {len(earlier) - 6} more" if len(earlier) > 6 else "")
        raise CLIError(
            f"--out {folder}: holds results of an earlier run ({shown}); give --overwrite "
            "to replace them, or choose another folder."
        )


class Output:
    """The output folder: writes files, remembers them with captions, times each step.

    Files are written atomically (a temporary file in the folder, then `os.replace`), so an
    interrupted or failed write leaves the earlier file intact and a symlink at the target is
    replaced, never written through. A folder holding results of an earlier run is refused
    unless `args.overwrite`.
    """

    def __init__(self, folder: str | os.PathLike, args):
        self.folder = Path(folder)
        self.overwrite = bool(getattr(args, "overwrite", False))
        if self.folder.exists() and not self.folder.is_dir():
            raise CLIError(f"--out {folder}: exists and is not a folder.")
        # Results of an earlier run in the folder: refused, or (--overwrite) those this run does
        # not write again are named at its end (`stale`).
        self.earlier = (
            {p.name for p in self.folder.iterdir() if is_output_name(p.name)} if self.folder.is_dir() else set()
        )
        if not self.overwrite:
            refuse_earlier_results(folder, list(self.earlier))
        if self.earlier == {LOG_NAME}:
            # The log of a run stopped before its first result: not this run's, so it goes.
            (self.folder / LOG_NAME).unlink(missing_ok=True)
            self.earlier = set()
        # A folder this run creates is removed again if the run stops before writing into it,
        # with the parents it created for it (`created_top`; None: the folder was there).
        self.created_top = _first_missing(self.folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise CLIError(f"--out {folder}: cannot create the output folder ({e.strerror}).") from None
        self.args = args
        OPENED.append(self)
        self.sections: list[Section] = []
        self.written: set[str] = set()
        self.failed: set[str] = set()  # names whose write failed (the error said so)
        self.log: list[str] = []

    @contextlib.contextmanager
    def step(self, title: str):
        section = Section(title)
        self.sections.append(section)
        start = time.perf_counter()
        try:
            yield section
        finally:
            section.seconds = time.perf_counter() - start

    def path(self, name: str) -> Path:
        return self.folder / name

    def write(self, name: str, write_to: Callable[[Path], object]) -> Path:
        """Write file `name` atomically: ``write_to(temporary_path)``, then rename it."""
        path = self.path(name)
        existed = os.path.lexists(path)
        if existed and not self.overwrite and name not in self.written:
            raise CLIError(f"{path}: exists already (an earlier result); give --overwrite to replace it.")
        try:
            atomic_write(path, write_to)
        except OSError as e:
            self.failed.add(name)  # its error names it: the note of what is left does not
            kept = f"the earlier {name} is unchanged" if existed else "nothing was written"
            raise CLIError(f"cannot write {path}: {os_reason(e)} ({kept}).") from None
        self.written.add(name)
        return path

    # Writers: each writes one file and lists it (with its caption) in `section`.

    def csv(
        self,
        section: Section,
        name: str,
        header: Sequence[str],
        rows: Sequence[Sequence],
        caption: str,
        *,
        table_html: str = "",
    ) -> Item:
        self.write(name, lambda p: write_csv(p, header, rows))
        return self.file(section, name, caption, "table", table_html)

    def figure(self, section: Section, fig, name: str, caption: str) -> Item:
        try:
            # Marked, so a results folder read again does not take its figures for photographs.
            self.write(name, lambda p: fig.savefig(p, dpi=110, format="png", metadata={"Software": FIGURE_SOFTWARE}))
        finally:
            close(fig)
        return self.file(section, name, caption, "figure")

    def rsml(self, section: Section | None, roots, name: str, caption: str, *, unit: str | None) -> Item | None:
        from rootshape_jax.io import write_rsml

        unit = unit if unit not in (None, "pixel") else None
        self.write(name, lambda p: write_rsml(roots, p, unit=unit, resolution=1.0 if unit else None))
        return None if section is None else self.file(section, name, caption)

    def write_log(self) -> Path | None:
        """Full details of skipped files and parts (the terminal shows one line per file)."""
        if not self.log:
            return None
        text = "\n".join(self.log) + "\n"
        return self.write(LOG_NAME, lambda p: p.write_text(text, encoding="utf-8"))

    def file(self, section: Section, name: str, caption: str, kind: str = "file", table_html: str = "") -> Item:
        item = Item(kind, name, caption, table_html)
        section.items.append(item)
        return item

    def stale(self) -> list[str]:
        """Earlier results still in the folder that this run did not replace (with --overwrite,
        e.g. a cluster run's dendrogram.png beside new distances, or geodesic steps beyond
        this run's last): still there after this run ends, though not made from its inputs."""
        return sorted(n for n in self.earlier - self.written if os.path.lexists(self.path(n)))

    def files(self) -> list[Item]:
        return [i for s in self.sections for i in s.items]

    def print_summary(self) -> None:
        for s in self.sections:
            for note in s.notes:
                print(f"{s.title}: {note}")
        for item in self.files():
            print(f"  {self.folder / item.path}  ({item.caption})")
        print(f"Results are in {self.folder.resolve()}")


def _first_missing(folder: Path) -> Path | None:
    """The outermost of `folder` and its parents that does not exist yet (None if it exists):
    what ``mkdir(parents=True)`` creates."""
    top = None
    for p in [folder, *folder.parents]:
        if p.exists():
            break
        top = p
    return top


class WrittenFolder:
    """The --out folder of a command that writes its files itself (`extract`, through
    `atomic_write`): what it wrote, for the message when it stops early (`unfinished_note`)."""

    def __init__(self, folder: str | os.PathLike, paths: list[Path]):
        self.folder = Path(folder)
        self.created_top = _first_missing(self.folder)
        self.paths = paths  # filled by `recording_writes`
        OPENED.append(self)

    @property
    def written(self) -> set[str]:
        return {p.name for p in self.paths if p.parent == self.folder}


# The output folders of the running command, for the message when it stops early.
OPENED: list[Output | WrittenFolder] = []


def unfinished_note() -> str | None:
    """What a command that stopped early (error, Ctrl-C) leaves in its output folders: the
    files it wrote are complete (atomic writes), the rest is missing, and a plain rerun into
    the same folder is refused (`Output`), so say so."""

    def listed(names: list[str]) -> str:
        return ", ".join(names[:6]) + (f" and {len(names) - 6} more" if len(names) > 6 else "")

    notes = []
    for out in OPENED:
        # The log of skipped files is not a result: it explains the error, so it is kept.
        names = sorted(n for n in out.written if n != LOG_NAME)
        # With --overwrite, the earlier run's files this run had not yet replaced are still
        # there, beside the new ones they no longer match (an old index.html, mean.png, ...).
        stale = [n for n in out.stale() if n != LOG_NAME and n not in out.failed] if isinstance(out, Output) else []
        store = getattr(getattr(out, "args", None), "store", None)
        kept = len(list(Path(store).glob("block_*.npz"))) if store and Path(store).is_dir() else 0
        if kept:  # the blocks finished so far are kept
            notes.append(
                f"--store {store} keeps the {kept} block{'s' if kept > 1 else ''} of distances finished so "
                "far: the same command with the same --store"
                + (" and --overwrite" if names else "")
                + " computes only the missing ones"
            )
        log = LOG_NAME in out.written
        if not names and not stale:
            if log:  # a folder that holds only the log is not refused by a plain rerun
                notes.append(
                    f"the run stopped before its end: {out.folder} holds only {LOG_NAME}, the full reasons "
                    "for the inputs skipped (a rerun into that folder needs no --overwrite)"
                )
            continue
        if names:
            what = (
                f"{out.folder} holds only the {len(names)} file{'s' if len(names) > 1 else ''} written "
                f"before ({listed(names)})"
            )
        else:
            what = f"{out.folder} holds no file of this run"
        if log:
            what += f" (and {LOG_NAME}, the inputs skipped so far)"
        if stale:
            what += (
                f", and {len(stale)} file{'s' if len(stale) > 1 else ''} of an earlier run that this run "
                f"had not replaced ({listed(stale)}), which may not match the new ones"
            )
        notes.append(
            f"the run stopped before its end: {what}; run again with --overwrite to replace "
            + ("them (files it does not write again stay: delete them, or use a new --out)" if stale else "them")
        )
    return "; ".join(notes) or None


def remove_empty_outputs() -> None:
    """Remove the output folders this run created and left empty (an input error, Ctrl-C
    before the first file): no empty folder stays behind."""
    for out in OPENED:
        if out.created_top is not None:
            # The folder, then each parent the run created for it, while they are empty.
            for p in [out.folder, *out.folder.parents]:
                try:
                    p.rmdir()  # only succeeds when empty
                except OSError:
                    break
                if p == out.created_top:
                    break


def os_reason(e: OSError) -> str:
    """`OSError.strerror`, also for an error built as ``OSError(errno.ENOSPC)``."""
    code = e.errno if e.errno is not None else (e.args[0] if len(e.args) == 1 and isinstance(e.args[0], int) else None)
    return e.strerror or (os.strerror(code) if code is not None else str(e) or type(e).__name__)


def close(fig) -> None:
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close(fig)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow([cell(h) for h in header])
        for row in rows:
            w.writerow([cell(v) for v in row])


def write_dict_csv(path: Path, rows: Sequence[dict]) -> None:
    """Rows of dicts (e.g. `rootshape_jax.traits`): columns in order of first appearance."""
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    write_csv(path, columns, [[r.get(k, "") for k in columns] for r in rows])


# A text cell starting like a formula is run by spreadsheets (CSV injection); OWASP: prefix
# it with a quote. Plain numbers such as -1.5 stay numbers.
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
_PLAIN_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def safe_text(text: str) -> str:
    if text.startswith(_FORMULA_START) and not _PLAIN_NUMBER.fullmatch(text):
        return "'" + text
    return text


def cell(v):
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, np.floating) and v.dtype.itemsize < 8:
        return str(v)  # the shortest text that reads back as this float32 (0.02, not 0.0199999995...)
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (int, np.integer)):
        return int(v)
    return safe_text(str(v))


def html_table(header: Sequence[str], rows: Sequence[Sequence], max_rows: int = 20) -> str:
    def show(v):
        if isinstance(v, (float, np.floating)):
            return html.escape(fmt(v))
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{show(v)}</td>" for v in row) + "</tr>" for row in rows[:max_rows])
    more = f"<p class='more'>… {len(rows) - max_rows} more rows in the CSV file.</p>" if len(rows) > max_rows else ""
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>{more}"


_CSS = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; padding: 0 1em; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 2em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption, .caption { color: #555; font-size: 0.95em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: right; }
th { background: #f3f3f3; } td:first-child, th:first-child { text-align: left; }
.time { color: #777; font-size: 0.85em; font-weight: normal; } .more { color: #777; font-size: 0.85em; }
"""


def write_index(out: Output, *, title: str, intro: Sequence[str], settings: Sequence[tuple[str, str]]) -> Path:
    parts = [
        "<!DOCTYPE html>",
        "<html lang='en'><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    parts += [f"<p>{html.escape(p)}</p>" for p in intro]
    rows = list(settings) + [(f"time: {s.title}", f"{s.seconds:.1f} s") for s in out.sections]
    rows.append(("time: total", f"{sum(s.seconds for s in out.sections):.1f} s"))
    parts.append("<h2>Settings and timings</h2>")
    parts.append(html_table(["setting", "value"], rows, max_rows=len(rows)))
    for s in out.sections:
        parts.append(f"<h2>{html.escape(s.title)} <span class='time'>({s.seconds:.1f} s)</span></h2>")
        parts += [f"<p class='caption'>{html.escape(n)}</p>" for n in s.notes]
        for item in s.items:
            src = html.escape(item.path, quote=True)
            cap = html.escape(item.caption)
            if item.kind == "figure":
                parts.append(
                    f"<figure><a href='{src}'><img src='{src}' alt='{cap}'></a><figcaption>{cap}</figcaption></figure>"
                )
            else:
                parts.append(f"<p><a href='{src}'>{html.escape(item.path)}</a> — {cap}</p>")
                if item.html:
                    parts.append(item.html)
    parts.append("</body></html>")
    text = "\n".join(parts)
    return out.write("index.html", lambda p: p.write_text(text, encoding="utf-8"))


def settings(args, pop) -> list[tuple[str, str]]:
    """The settings table of index.html."""
    import jax

    import rootshape_jax as rs

    w = args.weights
    deeper = make_weights(args).deeper  # --level-weights, or a weights file's deeper orders
    return [
        ("roots", str(len(pop.names))),
        ("points per root (T)", str(args.points)),
        ("lateral slots (K)", str(int(pop.tree.capacity))),
        ("depth (levels; child slots per level)", f"{pop.tree.depth}; {', '.join(map(str, pop.tree.capacities))}"),
        ("one system per", getattr(args, "per", "root")),
        ("most laterals of a root", str(max(r.n_laterals for r in pop.roots))),
        ("scale normalised", "yes (every main root scaled to length 1)" if pop.normalised else "no"),
        ("weights " + ", ".join(t.name for t in rs.TERMS), ", ".join(f"{v:g}" for v in w)),
        (
            "weights of deeper orders (lateral, position)",
            "; ".join(f"order {k}: {float(a):g}, {float(b):g}" for k, (a, b) in enumerate(deeper, start=2))
            if deeper
            else "as the first-order laterals'",
        ),
        ("precision", jax.numpy.zeros(()).dtype.name),
        ("devices", f"{len(jax.devices())} × {jax.devices()[0].platform.upper()}"),
        ("worker threads", str(rs.LocalExecutor().n_workers())),
        ("rootshape_jax / jax", f"{version()} / {jax.__version__}"),
    ]
