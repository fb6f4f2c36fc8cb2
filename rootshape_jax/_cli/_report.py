"""The output folder: every file written (CSV, PNG, RSML), its caption, and index.html."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import html
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._common import CLIError, fmt, version


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


class Output:
    """The output folder: writes files, remembers them with captions, times each step."""

    def __init__(self, folder: str | os.PathLike, args):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise CLIError(f"--out {folder}: exists and is not a folder.")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise CLIError(f"--out {folder}: cannot create the output folder ({e.strerror}).") from None
        self.args = args
        self.sections: list[Section] = []

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

    # Writers: each writes one file and lists it (with its caption) in `section`.

    def csv(self, section: Section, name: str, header: Sequence[str], rows: Sequence[Sequence],
            caption: str, *, table_html: str = "") -> Item:
        write_csv(self.path(name), header, rows)
        return self.file(section, name, caption, "table", table_html)

    def figure(self, section: Section, fig, name: str, caption: str) -> Item:
        try:
            fig.savefig(self.path(name), dpi=110)
        finally:
            close(fig)
        return self.file(section, name, caption, "figure")

    def rsml(self, section: Section | None, roots, name: str, caption: str, *, unit: str | None) -> Item | None:
        from rootshape_jax.io import write_rsml

        unit = unit if unit not in (None, "pixel") else None
        write_rsml(roots, self.path(name), unit=unit, resolution=1.0 if unit else None)
        return None if section is None else self.file(section, name, caption)

    def file(self, section: Section, name: str, caption: str, kind: str = "file", table_html: str = "") -> Item:
        item = Item(kind, name, caption, table_html)
        section.items.append(item)
        return item

    def files(self) -> list[Item]:
        return [i for s in self.sections for i in s.items]

    def print_summary(self) -> None:
        for s in self.sections:
            for note in s.notes:
                print(f"{s.title}: {note}")
        for item in self.files():
            print(f"  {self.folder / item.path}  ({item.caption})")
        print(f"Results are in {self.folder.resolve()}")


def close(fig) -> None:
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close(fig)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow([cell(v) for v in row])


def cell(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


def html_table(header: Sequence[str], rows: Sequence[Sequence], max_rows: int = 20) -> str:
    def show(v):
        if isinstance(v, (float, np.floating)):
            return html.escape(fmt(v))
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{show(v)}</td>" for v in row) + "</tr>" for row in rows[:max_rows]
    )
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
                parts.append(f"<figure><a href='{src}'><img src='{src}' alt='{cap}'></a>"
                             f"<figcaption>{cap}</figcaption></figure>")
            else:
                parts.append(f"<p><a href='{src}'>{html.escape(item.path)}</a> — {cap}</p>")
                if item.html:
                    parts.append(item.html)
    parts.append("</body></html>")
    path = out.path("index.html")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def settings(args, pop) -> list[tuple[str, str]]:
    """The settings table of index.html."""
    import jax

    w = args.weights
    return [
        ("roots", str(len(pop.names))),
        ("points per root (T)", str(args.points)),
        ("lateral slots (K)", str(int(pop.tree.capacity))),
        ("most laterals of a root", str(max(r.n_laterals for r in pop.roots))),
        ("scale normalised", "yes (every main root scaled to length 1)" if pop.normalised else "no"),
        ("weights main, lateral, position", f"{w[0]:g}, {w[1]:g}, {w[2]:g}"),
        ("precision", jax.numpy.zeros(()).dtype.name),
        ("devices", f"{len(jax.devices())} × {jax.devices()[0].platform.upper()}"),
        ("rootshape_jax / jax", f"{version()} / {jax.__version__}"),
    ]
