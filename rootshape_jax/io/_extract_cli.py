"""The `rootshape extract` command: photographs → one RSML and one overlay PNG per image.

The command-line parser lives with the other subcommands; this module holds the logic,
`extract_images`, so it can be called and tested directly.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._atomic import atomic_write, atomic_write_all, last_words
from .._errors import ImageError, RSMLError, user_stacklevel
from .._root import Root
from ._folder import FIGURE_SOFTWARE

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
_COLOURS = ("#e41a1c", "#ff7f00", "#ffff33", "#4daf4a", "#f781bf", "#a65628", "#984ea3", "#00e5ff")


#: Seconds between rewrites of summary.json while images are extracted.
_SUMMARY_EVERY = 10.0


def expand_images(images: Sequence[str | os.PathLike]) -> list[Path]:
    """Files as given; a folder gives its image files (sorted, by suffix)."""
    out: list[Path] = []
    for item in images:
        p = Path(item)
        if p.is_dir():
            out.extend(sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file()))
        else:
            out.append(p)
    return out


def _tracing_for(image: Path, tracing, n_images: int) -> Path | None:
    """The RSML tracing of `image`: a folder holds <stem>.rsml; a file is used for a single
    image or when its stem matches; a list of files is matched by stem."""
    if tracing is None:
        return None
    items = [tracing] if isinstance(tracing, (str, os.PathLike)) else list(tracing)
    for item in items:
        p = Path(item)
        if p.is_dir():
            cand = p / f"{image.stem}.rsml"
            if cand.is_file():
                return cand
        elif p.stem == image.stem or (len(items) == 1 and n_images == 1):
            return p
    return None


def draw_overlay(
    image_path: Path,
    roots: Sequence[Root],
    out_png: Path,
    *,
    tracing: Sequence[Root] = (),
    scale: float = 1.0,
    max_side: int = 2000,
) -> None:
    """The photograph with the extraction on top (one colour per root system; laterals thinner)
    and, when given, the tracing as white dashed lines. `scale` converts root coordinates to
    pixels (pixels per unit). The photograph is shown subsampled to at most `max_side` px."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from ._image import intensity_scale, load_image

    img, _ = load_image(image_path)
    H, W = img.shape[:2]
    step = max(1, int(np.ceil(max(H, W) / max_side)))
    shown = img[::step, ::step]
    if shown.ndim == 3:  # imshow takes colour as 0-255 integers or 0-1 floats: 12-bit data too
        shown = np.clip(shown[..., :3].astype(np.float32) * np.float32(intensity_scale(shown[..., :3])), 0.0, 1.0)
    fig = plt.figure(figsize=(10, 10 * H / W), dpi=max(100, int(max_side / 10)) if max(H, W) >= max_side else 100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.imshow(shown, extent=(-0.5, W - 0.5, H - 0.5, -0.5), cmap="gray" if shown.ndim == 2 else None)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.axis("off")
    for k, r in enumerate(roots):
        c = _COLOURS[k % len(_COLOURS)]
        ax.plot(r.main[:, 0] * scale, r.main[:, 1] * scale, "-", color=c, lw=0.7)
        for lat in r.laterals:
            ax.plot(lat[:, 0] * scale, lat[:, 1] * scale, "-", color=c, lw=0.45)
        ax.plot(r.main[0, 0] * scale, r.main[0, 1] * scale, "o", color=c, ms=2.5)
    for r in tracing:  # on top, dashed, so both stay visible
        for br in (r.main, *r.laterals):
            ax.plot(br[:, 0], br[:, 1], "--", color="white", lw=0.5, alpha=0.9)
    fig.savefig(out_png, format="png", metadata={"Software": FIGURE_SOFTWARE})
    plt.close(fig)


def extract_images(
    images: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    tracing: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    pixels_per_mm: float | None = None,
    pixel_size: float | None = None,
    unit: str = "mm",
    progress: bool = True,
    elastic: bool = False,
    **options,
) -> list[dict]:
    """Extract roots from each image; write ``OUT/<stem>.rsml`` and ``OUT/<stem>_overlay.png``.

    **Arguments**

    - `images`: image files and/or folders (a folder gives its .jpg/.png/.tif/.bmp files).
    - `out`: output folder (created).
    - `tracing`: hand tracings to draw and score against: an RSML file, a folder of
      ``<stem>.rsml`` files, or a list of RSML files matched by stem.
    - `pixels_per_mm`: image scale; the RSML is then written in mm. Or `pixel_size`: the length
      of one pixel in `unit` (default mm), the RSML then written in `unit`. Default: pixels.
    - `progress`: show a progress bar.
    - `elastic`: with a tracing, also compute each matched plant's elastic distance to it
      (`compare_to_tracing(elastic=True)`); otherwise that field is null in summary.json.
    - `**options`: passed to `roots_from_image`.

    A bad image (unreadable, truncated, unsupported, no root found) is named in a warning and
    skipped; the others are still processed. Writes ``OUT/summary.json`` (rewritten as images
    finish, at most every 10 s, so an interrupted run leaves the summary of the images it
    finished up to then) and returns its rows:
    one dict per image with ``status`` ("ok" or "skipped"), ``reason``, ``plants``,
    ``laterals``, ``rsml``, ``overlay`` and, with a tracing, ``comparison``.
    """
    from tqdm.auto import tqdm

    from ._compare import compare_to_tracing
    from ._image import image_scale, roots_from_image
    from ._rsml import read_rsml, write_rsml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = expand_images(images)
    if not files:
        raise FileNotFoundError(f"no image files in {list(map(str, images))} (looked for {', '.join(IMAGE_SUFFIXES)}).")
    # Checked here, not once per image (where a ValueError would only skip that image).
    pixel_size, unit = image_scale(pixels_per_mm, pixel_size, unit if pixel_size is not None else "pixel")
    # Pixels per output unit: the overlay and the tracing comparison work in pixels.
    scale = 1.0 if pixel_size is None else 1.0 / pixel_size
    rows: list[dict] = []
    written = [-math.inf]  # when summary.json was last written

    def write_summary(final: bool = False):
        # At most every _SUMMARY_EVERY seconds, and at the end: rewritten whole after every
        # image, a summary of 20,000 images would write ~200 GB over the run.
        now = time.monotonic()
        if not final and now - written[0] < _SUMMARY_EVERY:
            return
        written[0] = now
        # Strict JSON: a value not computed (NaN) is written as null.
        text = json.dumps(_json_safe(rows), indent=2, allow_nan=False, default=float)
        atomic_write(out / "summary.json", lambda p: p.write_text(text))

    bar = tqdm(files, desc="extract", unit="image", disable=not progress)
    # Interrupted, summary.json is brought up to the images finished (while the run goes on
    # it is rewritten at most every _SUMMARY_EVERY seconds).
    with last_words(lambda: write_summary(final=True)):
        for path in bar:
            bar.set_postfix_str(path.name)
            row: dict = {"image": str(path), "status": "ok", "reason": None}
            try:
                roots = roots_from_image(path, pixel_size=pixel_size, unit=unit, **options)
            except (ImageError, OSError, ValueError) as e:
                reason = str(e) if str(path) in str(e) else f"{path}: {e}"
                warnings.warn(f"skipped {path.name}: {reason}", stacklevel=user_stacklevel())
                row.update(status="skipped", reason=reason)
                rows.append(row)
                write_summary()
                continue
            rsml_path = out / f"{path.stem}.rsml"
            traced: list[Root] = []
            tpath = _tracing_for(path, tracing, len(files))
            if tpath is not None:
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        traced = read_rsml(tpath, physical_units=False)
                except (RSMLError, OSError) as e:
                    warnings.warn(
                        f"{path.name}: tracing {tpath} not read ({e}); overlay without it.",
                        stacklevel=user_stacklevel(),
                    )
            png = out / f"{path.stem}_overlay.png"
            row.update(
                plants=len(roots),
                laterals=[r.n_laterals for r in roots],
                rsml=str(rsml_path),
                overlay=str(png),
            )
            if traced:
                # Compare in pixels: the tracing is read in pixels.
                px = [r.scaled_about(np.zeros(r.dim), scale) for r in roots] if scale != 1.0 else roots
                cmp = compare_to_tracing(px, traced, elastic=elastic)
                row.update(tracing=str(tpath), comparison=cmp.as_dict())
            # An image's RSML and overlay are written together, whole or not at all: a Ctrl-C
            # leaves every image done complete and no image half done. Its row joins the
            # summary's with the renames, before a Ctrl-C held back during them ends the run.
            atomic_write_all(
                [
                    (rsml_path, lambda p: write_rsml(roots, p)),
                    (png, lambda p: draw_overlay(path, roots, p, tracing=traced, scale=scale)),
                ],
                then=lambda: rows.append(row),
            )
            write_summary()
        write_summary(final=True)  # inside: a Ctrl-C during it still leaves the whole summary
    return rows


def _json_safe(x):
    """`x` with NaN and infinite floats as None and numpy scalars as Python numbers."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
