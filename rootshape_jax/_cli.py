"""The ``rootshape`` command line (also ``python -m rootshape_jax``).

Every subcommand reads roots (RSML files, folders of them, scanned images, or built-in
synthetic roots), runs one analysis and writes CSV tables, PNG figures and RSML files into an
output folder. Mistakes in the input (a missing path, an unreadable file, a bad option value)
end with one line on stderr and a non-zero exit code, never a Python traceback (``--debug``
shows it).

This is the only module allowed to change JAX's global configuration (DESIGN.md §8, §10): it
asks for one XLA CPU device per core before JAX starts and turns on float64 on request.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import html
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

PROG = "rootshape"
RSML_SUFFIXES = (".rsml",)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
PAPER_TRAITS = ("main_length", "mean_lateral_length", "std_lateral_length")
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class CLIError(Exception):
    """A problem the user can fix; its message is printed as one line."""


# --------------------------------------------------------------------------------------------
# JAX configuration (the only place in the package that touches it)


def configure_jax(*, devices: int | None, float64: bool) -> None:
    """One XLA CPU device per core (so batches run on every core) and optional float64.

    The device count can only be set before JAX has started; when it has already started
    (e.g. `main` called from a running Python session) the current devices are kept.
    """
    import jax

    n = (os.cpu_count() or 1) if devices is None else devices
    with contextlib.suppress(RuntimeError):
        jax.config.update("jax_num_cpu_devices", int(n))
    if float64:
        jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------------------------
# Small helpers


def _say(args, message: str) -> None:
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr, flush=True)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, got {value}")
    return value


def _points(text: str) -> int:
    value = _positive_int(text)
    if value < 5:
        raise argparse.ArgumentTypeError(f"need at least 5 points per root, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _weights(text: str):
    parts = text.replace(";", ",").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values) or sum(values) == 0:
        raise argparse.ArgumentTypeError(
            f"expected three non-negative numbers main,lateral,position (e.g. 0.02,1,1), got {text!r}"
        )
    return tuple(values)


def _make_weights(args):
    from ._metric import Weights

    main, lateral, position = args.weights
    return Weights(main=main, lateral=lateral, position=position)


def _fmt(x: float, digits: int = 4) -> str:
    return f"{float(x):.{digits}g}"


# --------------------------------------------------------------------------------------------
# Reading roots


def _files_in(folder: Path) -> list[Path]:
    return sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in RSML_SUFFIXES + IMAGE_SUFFIXES
    )


def _read_file(path: Path, args) -> list:
    from . import io

    suffix = path.suffix.lower()
    if suffix in RSML_SUFFIXES:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            roots = io.read_rsml(path)
        if not roots:
            io.read_rsml(path, strict=True)  # raises the precise reason as one RSMLError
        for w in caught:  # parts skipped in a file that is otherwise readable
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
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


def _expand(paths: Sequence[str]) -> list[Path]:
    files: list[Path] = []
    for text in paths:
        p = Path(text)
        if not p.exists():
            raise CLIError(f"{text}: no such file or folder.")
        if p.is_dir():
            found = _files_in(p)
            if not found:
                raise CLIError(
                    f"{text}: the folder contains no RSML files (.rsml) or images "
                    f"({', '.join(IMAGE_SUFFIXES)})."
                )
            files.extend(found)
        else:
            files.append(p)
    return files


def _unique_names(roots: list) -> list:
    """Names that tell roots apart: a name shared by several roots gets its file name in front,
    and a number behind if that is not enough."""
    counts: dict[str, int] = {}
    for r in roots:
        counts[r.name] = counts.get(r.name, 0) + 1
    names = [
        f"{Path(r.metadata.get('source_file', '')).stem}/{r.name}" if counts[r.name] > 1 else r.name
        for r in roots
    ]
    seen: dict[str, int] = {}
    out = []
    for r, name in zip(roots, names):
        seen[name] = seen.get(name, 0) + 1
        if names.count(name) > 1:
            name = f"{name}_{seen[name]}"
        out.append(dataclasses.replace(r, name=name))
    return out


def load_roots(args, *, paths: Sequence[str] | None = None) -> list:
    """The roots named on the command line: files, folders, images, or --synthetic."""
    paths = list(args.inputs if paths is None else paths)
    synthetic = getattr(args, "synthetic", None)
    if paths and synthetic:
        raise CLIError("give either input files/folders or --synthetic N, not both.")
    if synthetic:
        from .datasets import synthetic_roots

        conditions = args.condition or ["control"]
        roots = []
        for c in conditions:
            roots.extend(synthetic_roots(synthetic, condition=c, seed=args.seed))
        return roots
    if not paths:
        raise CLIError(
            "no input: give RSML files, folders or images, or --synthetic N for example roots."
        )
    roots = []
    for f in _expand(paths):
        roots.extend(_read_file(f, args))
    return _unique_names(roots)


def subsample(roots: list, n: int | None) -> list:
    """At most `n` roots, evenly spaced through the input order (every group keeps members)."""
    if n is None or n >= len(roots):
        return list(roots)
    idx = np.unique(np.round(np.linspace(0, len(roots) - 1, n)).astype(int))
    return [roots[i] for i in idx]


def limit_laterals(root, n: int | None):
    """The root with only its `n` longest laterals (in their original order)."""
    if n is None or root.n_laterals <= n:
        return root
    keep = np.sort(np.argsort(-root.lateral_lengths, kind="stable")[:n])
    children = tuple(root.children[i] for i in keep) if root.children else ()
    return dataclasses.replace(
        root,
        laterals=tuple(root.laterals[i] for i in keep),
        attach=root.attach[keep],
        children=children,
    )


def _common_unit(roots) -> str | None:
    units = {r.metadata.get("unit") for r in roots}
    return units.pop() if len(units) == 1 else None


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
    from ._tree import batch

    roots = subsample(roots, samples)
    roots = [limit_laterals(r, args.laterals) for r in roots]
    if len(roots) < min_roots:
        raise CLIError(f"this analysis needs at least {min_roots} roots, got {len(roots)}.")
    normalised = args.normalise_scale
    tree = batch(roots, n_points=args.points, normalise_scale=normalised)
    conditions = [r.metadata.get("condition") for r in roots]
    return Population(
        roots=roots,
        tree=tree,
        names=[r.name for r in roots],
        normalised=normalised,
        unit=_common_unit(roots),
        mean_length=float(np.mean([r.main_length for r in roots])),
        conditions=conditions if all(c is not None for c in conditions) else None,
    )


def scale_tree(tree, scales):
    """A batched `RootTree` with root i scaled by ``scales[i]`` about its base (slots kept)."""
    import jax.numpy as jnp

    from ._tree import RootTree

    s = jnp.asarray(np.asarray(scales, dtype=np.float64), tree.main.dtype)
    o = tree.main[:, :1, :]
    main = o + (tree.main - o) * s[:, None, None]
    lats = o[:, None] + (tree.laterals - o[:, None]) * s[:, None, None, None]
    return RootTree(main=main, laterals=lats, attach=tree.attach, mask=tree.mask)


def _to_output_roots(tree, pop: Population, names: Sequence[str]) -> list:
    """Unpadded roots (null slots dropped) labelled with the input's unit."""
    from ._tree import to_roots

    meta = {"unit": pop.unit} if pop.unit else {}
    return [dataclasses.replace(r, metadata=dict(meta)) for r in to_roots(tree, names=list(names))]


def _in_input_units(tree, pop: Population):
    """Analysis coordinates back in the input's units: scale-normalised roots are scaled by
    the inputs' mean main-root length."""
    n = tree.batch_shape[0]
    return scale_tree(tree, [pop.output_scale()] * n) if pop.normalised else tree


def _write_rsml(roots, path: Path, pop: Population) -> None:
    from .io import write_rsml

    unit = pop.unit if pop.unit not in (None, "pixel") else None
    resolution = 1.0 if unit else None
    write_rsml(roots, path, unit=unit, resolution=resolution)


# --------------------------------------------------------------------------------------------
# Output folder and report


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

    def figure(self, section: Section, fig, name: str, caption: str) -> None:
        fig.savefig(self.path(name), dpi=110)
        _close(fig)
        section.items.append(Item("figure", name, caption))

    def file(self, section: Section, name: str, caption: str, kind: str = "file", table_html: str = "") -> None:
        section.items.append(Item(kind, name, caption, table_html))

    def files(self) -> list[Item]:
        return [i for s in self.sections for i in s.items]

    def print_summary(self) -> None:
        for s in self.sections:
            for note in s.notes:
                print(f"{s.title}: {note}")
        for item in self.files():
            print(f"  {self.folder / item.path}  ({item.caption})")
        print(f"Results are in {self.folder.resolve()}")


def _close(fig) -> None:
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close(fig)


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow([_cell(v) for v in row])


def _cell(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


def _html_table(header: Sequence[str], rows: Sequence[Sequence], max_rows: int = 20) -> str:
    def fmt(v):
        if isinstance(v, (float, np.floating)):
            return html.escape(_fmt(v))
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{fmt(v)}</td>" for v in row) + "</tr>" for row in rows[:max_rows]
    )
    more = f"<p class='more'>… {len(rows) - max_rows} more rows in the CSV file.</p>" if len(rows) > max_rows else ""
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>{more}"


# --------------------------------------------------------------------------------------------
# The analyses (shared by the subcommands and the demo)


@dataclasses.dataclass
class Context:
    """Results carried from one step to the next (the demo reuses them)."""

    pop: Population
    distances: np.ndarray | None = None
    mean: object = None  # KarcherMean
    pca: object = None  # TangentPCA


def run_distances(ctx: Context, out: Output, args) -> None:
    from ._pairwise import pairwise_distances
    from .plot import plot_distance_matrix

    pop = ctx.pop
    with out.step("Distance matrix") as sec:
        _say(args, f"Registering every pair of {len(pop.names)} roots "
                   f"({len(pop.names) * (len(pop.names) - 1) // 2} pairs)...")
        D, stats = pairwise_distances(
            pop.tree, weights=_make_weights(args), progress=not args.quiet, return_stats=True
        )
        D = np.asarray(D, dtype=np.float64)
        ctx.distances = D
        _write_csv(out.path("distances.csv"), ["root"] + pop.names, [[n] + list(row) for n, row in zip(pop.names, D)])
        out.file(sec, "distances.csv", f"elastic distance between every pair of roots ({len(D)} × {len(D)})", "table")
        fig, _ = plot_distance_matrix(D, labels=pop.names)
        out.figure(sec, fig, "distances.png", "heat map of the distance matrix, rows ordered by hierarchical clustering")
        done = stats.get("lateral_dp")
        skipped = stats.get("lateral_skipped", stats.get("lateral_pruned"))
        note = f"{len(D) * (len(D) - 1) // 2} pairs registered"
        if done is not None and skipped is not None:
            note += (f"; {done} lateral-pair alignments computed, {skipped} skipped by an exact "
                     "bound (they could not change the result)")
        sec.notes.append(note + ".")


def run_mean(ctx: Context, out: Output, args) -> None:
    import optimistix as optx

    from ._mean import karcher_mean
    from ._tree import stack
    from .plot import plot_energy_trace, plot_mean

    pop = ctx.pop
    with out.step("Mean root (Karcher mean)") as sec:
        _say(args, f"Fitting the mean root of {len(pop.names)} roots (each step registers every root "
                   "onto the current mean)...")
        km = karcher_mean(
            pop.tree, weights=_make_weights(args), distances=ctx.distances, max_steps=args.max_steps,
            throw=False,
        )
        ctx.mean = km
        trace = np.asarray(km.energy_trace, dtype=np.float64)
        mean_roots = _to_output_roots(_in_input_units(stack([km.mean]), pop), pop, ["mean"])
        _write_rsml(mean_roots, out.path("mean.rsml"), pop)
        out.file(sec, "mean.rsml", "the mean root (RSML)")
        _write_csv(out.path("mean_energy.csv"), ["step", "energy"], list(enumerate(trace)))
        out.file(sec, "mean_energy.csv", "Karcher energy F(μ) after each step", "table")
        fig, _ = plot_mean(pop.tree, km.mean, title=f"Mean of {len(pop.names)} roots")
        out.figure(sec, fig, "mean.png", "input roots (left) and their mean root (right)")
        fig, _ = plot_energy_trace(trace)
        out.figure(sec, fig, "mean_energy.png", "mean squared distance to the mean at each solver step (must fall)")
        n_drop = int(np.sum(np.asarray(km.dropped)))
        sec.notes.append(
            f"{int(km.steps)} steps, final energy {_fmt(trace[-1])} (start {_fmt(trace[0])}); "
            f"started from root {pop.names[km.init_index]!r} (the medoid); {n_drop} near-empty "
            f"lateral slots dropped; mean has {int(np.sum(np.asarray(km.mean.mask)))} laterals."
        )
        if not bool(np.asarray(km.result == optx.RESULTS.successful)):
            sec.notes.append(f"the solver stopped at the step limit ({args.max_steps}) before converging.")


def run_pca(ctx: Context, out: Output, args) -> None:
    from ._pca import modes, tangent_pca
    from .plot import plot_explained_variance, plot_modes

    pop = ctx.pop
    with out.step("Modes of variation (tangent PCA)") as sec:
        pc = tangent_pca(ctx.mean)
        ctx.pca = pc
        eig = np.asarray(pc.eigenvalues, dtype=np.float64)
        ratio = np.asarray(pc.explained_variance_ratio, dtype=np.float64)
        rows = [[i + 1, eig[i], ratio[i], float(np.sum(ratio[: i + 1]))] for i in range(len(eig))]
        header = ["component", "variance", "explained_ratio", "cumulative_ratio"]
        _write_csv(out.path("explained_variance.csv"), header, rows)
        out.file(sec, "explained_variance.csv", "variance explained by each principal component", "table",
                 _html_table(header, rows, max_rows=8))
        fig, _ = plot_explained_variance(eig)
        out.figure(sec, fig, "explained_variance.png", "variance explained per component and cumulated")
        n_modes = max(1, min(args.modes, len(eig)))
        alphas = [-2.0, -1.0, 0.0, 1.0, 2.0]
        trees = modes(pc, alphas, component=list(range(n_modes)))
        fig, _ = plot_modes(trees, alphas, explained=ratio[:n_modes])
        out.figure(sec, fig, "modes.png",
                   f"first {n_modes} modes: mean ± 1 and 2 standard deviations along each component")
        sec.notes.append(
            f"{pc.n_components} components explain {100 * pc.variance:.0f} % of the variance "
            f"(first: {100 * ratio[0]:.1f} %)."
        )


def run_sample(ctx: Context, out: Output, args) -> None:
    import jax

    from ._pca import reconstruct
    from .plot import plot_samples_by_distance

    pop = ctx.pop
    pc = ctx.pca
    with out.step("Random roots from the fitted model") as sec:
        n = args.n
        m = pc.n_components
        # Random coefficients b ~ N(0, I) (as `rootshape_jax.sample`), kept so that each root's
        # distance to the mean in the model, sqrt(sum_i sigma_i b_i^2), needs no registration.
        key = jax.random.key(args.seed)
        if args.truncate is None:
            b = jax.random.normal(key, (n, m), pc.mean.q0.dtype)
        else:
            b = jax.random.truncated_normal(key, -args.truncate, args.truncate, (n, m), pc.mean.q0.dtype)
        trees = reconstruct(pc, b)
        sigma = np.asarray(pc.eigenvalues, np.float64)[:m]
        d = np.sqrt(np.sum(np.asarray(b, np.float64) ** 2 * sigma, axis=1))
        names = [f"random_{i:03d}" for i in range(n)]
        roots = _to_output_roots(_in_input_units(trees, pop), pop, names)
        _write_rsml(roots, out.path("random_roots.rsml"), pop)
        out.file(sec, "random_roots.rsml", f"{n} random roots (RSML)")
        _write_csv(out.path("random_roots.csv"), ["root", "model_distance_to_mean"], list(zip(names, d)))
        out.file(sec, "random_roots.csv", "distance of each random root to the mean in the PCA model", "table")
        fig, _ = plot_samples_by_distance(trees, d, n_groups=min(3, n))
        out.figure(sec, fig, "random_roots.png",
                   "random roots, in rows of increasing distance to the mean (in the PCA model)")
        sec.notes.append(
            f"coefficients drawn from N(0, 1) on the {m} kept components"
            + (f", truncated to ±{args.truncate}" if args.truncate else "") + f", seed {args.seed}; "
            "the distance to the mean is measured in the model, sqrt(Σ σ_i b_i²)."
        )


def _trait_matrix(roots, names=PAPER_TRAITS) -> np.ndarray:
    from ._traits import traits

    rows = traits(roots)
    return np.array([[float(r[k]) for k in names] for r in rows], dtype=np.float64)


def _read_requested(path: str) -> np.ndarray:
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


def run_regress(ctx: Context, out: Output, args) -> None:
    from ._regression import TraitRegression
    from .plot import plot_regression_sweep

    pop = ctx.pop
    with out.step("Roots predicted from traits (regression)") as sec:
        # Traits in the input's units, measured on the roots as read. With scale normalisation
        # the model predicts the shape, and each predicted root is scaled to its requested
        # main-root length (so that trait is matched exactly by construction).
        P = _trait_matrix(pop.roots)
        reg = TraitRegression.fit(ctx.pca, None, traits=(), covariates=P, covariate_names=PAPER_TRAITS)

        def predict(values: np.ndarray, names: list[str]):
            trees = reg.synthesize(values)
            if pop.normalised:
                lengths = np.linalg.norm(np.diff(np.asarray(trees.main, np.float64), axis=1), axis=-1).sum(-1)
                trees = scale_tree(trees, values[:, 0] / np.maximum(lengths, 1e-12))
            return trees, _to_output_roots(trees, pop, names)

        # How well the model reproduces the training roots' own traits.
        _, fitted = predict(P, [f"fit_{i}" for i in range(len(P))])
        got = _trait_matrix(fitted)
        report = []
        for j, name in enumerate(PAPER_TRAITS):
            y, yhat = P[:, j], got[:, j]
            ss = float(np.sum((y - y.mean()) ** 2))
            r2 = 1.0 - float(np.sum((yhat - y) ** 2)) / ss if ss > 0 else float("nan")
            rel = float(np.mean(np.abs(yhat - y) / np.maximum(np.abs(y), 1e-12)))
            report.append([name, r2, rel])
        header = ["trait", "r2_requested_vs_measured", "mean_relative_error"]
        _write_csv(out.path("regression_report.csv"), header, report)
        out.file(sec, "regression_report.csv",
                 "traits requested (those of the input roots) vs traits measured on the predicted roots",
                 "table", _html_table(header, report))

        if getattr(args, "requested_values", None) is not None:
            values = args.requested_values
            vary = None
        else:
            # Sweep one trait from its 10th to its 90th percentile, the others at their median.
            vary = PAPER_TRAITS.index(args.vary)
            values = np.tile(np.median(P, axis=0), (5, 1))
            values[:, vary] = np.percentile(P[:, vary], [10, 30, 50, 70, 90])
        names = [f"predicted_{i:03d}" for i in range(len(values))]
        trees, roots = predict(values, names)
        _write_rsml(roots, out.path("predicted_roots.rsml"), pop)
        out.file(sec, "predicted_roots.rsml", f"{len(roots)} roots predicted from requested traits (RSML)")
        measured = _trait_matrix(roots)
        rows = [[n] + list(v) + list(m) for n, v, m in zip(names, values, measured)]
        header = ["root"] + [f"requested_{k}" for k in PAPER_TRAITS] + [f"measured_{k}" for k in PAPER_TRAITS]
        _write_csv(out.path("predicted_roots.csv"), header, rows)
        out.file(sec, "predicted_roots.csv", "requested and measured traits of each predicted root", "table")
        k = 0 if vary is None else vary
        fig, _ = plot_regression_sweep(
            trees, values[:, k], trait_name=PAPER_TRAITS[k].replace("_", " "), unit=pop.unit,
            measured=measured[:, k],
        )
        what = "requested" if vary is None else f"{PAPER_TRAITS[k].replace('_', ' ')} varied, other traits at their median"
        out.figure(sec, fig, "predicted_roots.png", f"roots predicted from traits ({what}); measured value below")
        if pop.normalised:
            sec.notes.append(
                "shapes were compared at equal main-root length; each predicted root is scaled to its "
                "requested main-root length, so that trait matches by construction."
            )


def run_cluster(ctx: Context, out: Output, args) -> None:
    from ._cluster import cluster, loo_accuracy
    from .plot import plot_dendrogram

    pop = ctx.pop
    with out.step("Clusters and classification") as sec:
        D = ctx.distances
        known = sorted(set(pop.conditions)) if pop.conditions else []
        k = args.clusters or (len(known) if len(known) >= 2 else 2)
        k = min(k, len(pop.names))
        cl = cluster(D, n_clusters=k, method=args.linkage)
        header = ["root", "cluster"] + (["condition"] if pop.conditions else [])
        rows = [[n, int(c)] + ([pop.conditions[i]] if pop.conditions else []) for i, (n, c) in enumerate(zip(pop.names, cl.labels))]
        _write_csv(out.path("clusters.csv"), header, rows)
        out.file(sec, "clusters.csv", f"cluster of each root ({k} clusters, {args.linkage} linkage)", "table")
        clusters_item = sec.items[-1]
        fig, _ = plot_dendrogram(D, labels=pop.names, n_clusters=k, method=args.linkage, roots=pop.tree)
        out.figure(sec, fig, "dendrogram.png", "dendrogram of the distance matrix, coloured by cluster, with members of each cluster")
        if len(known) >= 2:
            # Which conditions ended up in which cluster (the CSV has the same per root).
            cond = np.asarray(pop.conditions)
            table = [[c] + [int(np.sum((cond == c) & (cl.labels == g))) for g in range(k)] for c in known]
            clusters_item.html = _html_table(["condition"] + [f"cluster {g}" for g in range(k)], table)
            acc_rows = []
            for rule, label in (("nearest_neighbour", "nearest neighbour"), ("nearest_mean", "nearest class mean")):
                res = loo_accuracy(D, np.asarray(pop.conditions), rule=rule)
                acc_rows.append([label, res["accuracy"], int(np.sum(res["correct"])), len(pop.names)])
            header = ["rule", "accuracy", "correct", "roots"]
            _write_csv(out.path("classification.csv"), header, acc_rows)
            out.file(sec, "classification.csv",
                     f"leave-one-out classification of the conditions ({', '.join(known)}) from distances alone",
                     "table", _html_table(header, acc_rows))
            sec.notes.append(
                "classification accuracy (leave-one-out): "
                + "; ".join(f"{r[0]} {100 * r[1]:.0f} %" for r in acc_rows)
                + f" (chance ≈ {100 / len(known):.0f} %)."
            )


def run_traits(roots: list, out: Output, args) -> None:
    from ._traits import traits, traits_to_csv

    with out.step("Root traits") as sec:
        rows = traits(roots)
        for r, root in zip(rows, roots):
            for key in ("condition", "unit", "source_file"):
                if key in root.metadata:
                    r[key] = root.metadata[key]
        traits_to_csv(rows, out.path("traits.csv"))
        show = ["name", "main_length", "n_laterals", "mean_lateral_length", "total_length", "depth", "width"]
        out.file(sec, "traits.csv", f"architecture traits of the {len(rows)} input roots (lengths in "
                 f"{_common_unit(roots) or 'input units'})", "table",
                 _html_table(show, [[r[k] for k in show] for r in rows], max_rows=10))


def run_geodesic(a_root, b_root, out: Output, args) -> None:
    from ._geodesic import geodesic
    from ._registration import register
    from ._tree import unstack
    from .plot import plot_geodesic

    pop = prepare([a_root, b_root], args, min_roots=2)
    pair = pop.roots
    with out.step("Geodesic (optimal deformation)") as sec:
        a, b = unstack(pop.tree)
        reg = register(a, b, weights=_make_weights(args))
        path = geodesic(a, b, n_steps=args.steps, weights=_make_weights(args), registration=reg)
        taus = np.linspace(0.0, 1.0, args.steps)
        la, lb = (r.main_length for r in pair)
        if pop.normalised:  # back to the input's units, the size changing along the path
            path_out = scale_tree(path, [(1 - t) * la + t * lb for t in taus])
        else:
            path_out = path
        names = [f"step_{i:02d}" for i in range(args.steps)]
        roots = _to_output_roots(path_out, pop, names)
        for i, r in enumerate(roots):
            _write_rsml([r], out.path(f"geodesic_step_{i:02d}.rsml"), pop)
        out.file(sec, "geodesic_step_00.rsml",
                 f"each step of the deformation as RSML: geodesic_step_00.rsml … geodesic_step_{args.steps - 1:02d}.rsml")
        fig, _ = plot_geodesic(path, title=f"{pair[0].name} → {pair[1].name}: optimal deformation "
                                           "(colour = corresponding lateral)")
        out.figure(sec, fig, "geodesic.png", f"optimal deformation of {pair[0].name} into {pair[1].name}, "
                   "one colour per matched lateral")
        sec.notes.append(f"elastic distance {pair[0].name} → {pair[1].name}: {_fmt(float(reg.distance))}.")


# --------------------------------------------------------------------------------------------
# index.html


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
    parts.append(_html_table(["setting", "value"], rows, max_rows=len(rows)))
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


def _settings(args, pop: Population) -> list[tuple[str, str]]:
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
        ("rootshape_jax / jax", f"{_version()} / {jax.__version__}"),
    ]


def _version() -> str:
    from . import __version__

    return __version__


# --------------------------------------------------------------------------------------------
# Subcommands


def _pipeline(args, steps, *, min_roots: int = 2) -> None:
    """Load and prepare the roots, run `steps` (each ``step(ctx, out, args)``) in order."""
    out = Output(args.out, args)
    ctx = Context(prepare(load_roots(args), args, min_roots=min_roots, samples=args.samples))
    for step in steps:
        step(ctx, out, args)
    out.print_summary()


def cmd_distances(args) -> None:
    _pipeline(args, [run_distances])


def cmd_mean(args) -> None:
    _pipeline(args, [run_mean], min_roots=1)


def cmd_pca(args) -> None:
    _pipeline(args, [run_mean, run_pca])


def cmd_sample(args) -> None:
    _pipeline(args, [run_mean, run_pca, run_sample])


def cmd_regress(args) -> None:
    # Check the requested traits before the long computation.
    args.requested_values = _read_requested(args.requested) if args.requested else None
    _pipeline(args, [run_mean, run_pca, run_regress], min_roots=len(PAPER_TRAITS) + 2)


def cmd_cluster(args) -> None:
    _pipeline(args, [run_distances, run_cluster])


def cmd_traits(args) -> None:
    out = Output(args.out, args)
    roots = subsample(load_roots(args), args.samples)
    run_traits(roots, out, args)
    out.print_summary()


def _pick(roots: list, index: int, path: str):
    if not -len(roots) <= index < len(roots):
        raise CLIError(f"{path}: has {len(roots)} root(s); root number {index} does not exist.")
    return roots[index]


def cmd_geodesic(args) -> None:
    out = Output(args.out, args)
    a = _pick(load_roots(args, paths=[args.a]), args.root_a, args.a)
    b = _pick(load_roots(args, paths=[args.b]), args.root_b, args.b)
    run_geodesic(a, b, out, args)
    out.print_summary()


def cmd_demo(args) -> None:
    from .datasets import default_dataset

    out = Output(args.out, args)
    start = time.perf_counter()
    all_roots = default_dataset()
    ctx = Context(prepare(all_roots, args, min_roots=len(PAPER_TRAITS) + 2, samples=args.samples))
    pop = ctx.pop
    steps: list[tuple[str, Callable[[], None]]] = [
        ("traits", lambda: run_traits(pop.roots, out, args)),
        ("distances", lambda: run_distances(ctx, out, args)),
        ("geodesic", lambda: run_geodesic(*_demo_pair(ctx), out, args)),
        ("mean", lambda: run_mean(ctx, out, args)),
        ("modes", lambda: run_pca(ctx, out, args)),
        ("random roots", lambda: run_sample(ctx, out, args)),
        ("regression", lambda: run_regress(ctx, out, args)),
        ("clusters", lambda: run_cluster(ctx, out, args)),
    ]
    for i, (name, fn) in enumerate(steps, 1):
        _say(args, f"[{i}/{len(steps)}] {name}")
        fn()
    counts = {}
    for c in pop.conditions or []:
        counts[c] = counts.get(c, 0) + 1
    intro = [
        f"{len(pop.names)} synthetic root systems from the bundled data set "
        f"({', '.join(f'{v} {k}' for k, v in counts.items())}), analysed with the elastic "
        "shape metric of Wang et al. (main root, laterals and their positions; rotation, "
        "re-parameterisation and lateral correspondence optimised for every pair).",
        f"Each branch is resampled to T = {args.points} points"
        + (" (the demo's reduced resolution, chosen so it runs in a few minutes on a 2-core "
           "machine; use --points 100 for the library's usual resolution)" if args.points < 100 else "")
        + (f"; {len(pop.names)} of the {len(all_roots)} roots used (--samples)" if len(pop.names) < len(all_roots) else "")
        + ".",
        f"Total time {time.perf_counter() - start:.0f} s, including compilation (see the timings).",
    ]
    write_index(out, title="rootshape demo", intro=intro, settings=_settings(args, pop))
    print(f"Open {out.path('index.html').resolve()} in a web browser.")
    print(f"Results are in {out.folder.resolve()}")


def _demo_pair(ctx: Context):
    """The medoids (smallest sum of squared distances) of the first two conditions, or the
    two farthest roots when there are no conditions."""
    pop, D = ctx.pop, ctx.distances
    groups = list(dict.fromkeys(pop.conditions or []))
    if len(groups) >= 2:
        pair = []
        for g in groups[:2]:
            idx = [i for i, c in enumerate(pop.conditions) if c == g]
            pair.append(idx[int(np.argmin(np.sum(D[np.ix_(idx, idx)] ** 2, axis=1)))])
    else:
        pair = list(np.unravel_index(int(np.argmax(D)), D.shape))
    return pop.roots[pair[0]], pop.roots[pair[1]]


# --------------------------------------------------------------------------------------------
# Parser


_DESCRIPTION = """\
Compare the shapes of plant root systems: distances between roots, the optimal deformation of
one root into another, the mean root and its main modes of variation, random and trait-driven
new roots, and clusters. Roots are read from RSML files (SmartRoot, RootNav, RhizoVision,
CPlantBox, ...), folders of RSML files, or scanned images; each root is a main root with its
first-order laterals.

Results (CSV tables, PNG figures, RSML files) go into the folder given by --out.
Try:  rootshape demo          (everything on a bundled set of 53 roots)
      rootshape distances my_rsml_folder/ --out results
"""

_EPILOG = "Run 'rootshape COMMAND --help' for the options of one command."


def _add_common(p: argparse.ArgumentParser, *, inputs: bool = True, default_out: str = "rootshape_output") -> None:
    if inputs:
        p.add_argument(
            "inputs", nargs="*", metavar="INPUT",
            help="RSML files (.rsml), folders (every .rsml file and image inside), or scanned "
                 "images (.png, .jpg, .tif) of roots on a contrasting background",
        )
        g = p.add_argument_group("example roots instead of files")
        g.add_argument("--synthetic", type=_positive_int, metavar="N",
                       help="use N built-in synthetic roots per condition instead of files")
        g.add_argument("--condition", action="append", metavar="NAME",
                       help="condition of the synthetic roots: control, drought, high_nitrate, "
                            "low_phosphate (repeat for several; default control)")
        img = p.add_argument_group("images")
        img.add_argument("--pixel-size", type=_positive_float, metavar="SIZE",
                         help="length of one image pixel (e.g. 0.0423 for 600 dpi in mm); default: "
                              "keep pixels")
        img.add_argument("--unit", metavar="UNIT", help="unit of --pixel-size (default mm)")
    g = p.add_argument_group("analysis")
    g.add_argument("--out", default=default_out, metavar="DIR",
                   help=f"folder for the results (created if needed; default {default_out})")
    if inputs:
        g.add_argument("--samples", type=_positive_int, metavar="N",
                       help="use only N of the roots, evenly spread through the input order (faster)")
    g.add_argument("--laterals", type=_positive_int, metavar="N",
                   help="keep at most the N longest laterals of each root (faster; default: all)")
    g.add_argument("--points", type=_points, default=100, metavar="T",
                   help="points per root branch after resampling (default 100; 50 is faster)")
    g.add_argument("--weights", type=_weights, default=(0.02, 1.0, 1.0), metavar="M,L,P",
                   help="importance of main-root shape, lateral shape and lateral positions in "
                        "the distance (default 0.02,1,1 as in the paper)")
    g.add_argument("--normalise-scale", dest="normalise_scale", action=argparse.BooleanOptionalAction,
                   default=True,
                   help="scale every root to the same main-root length, so only shape counts "
                        "(default on; use --no-normalise-scale for growth studies where size matters)")
    g.add_argument("--seed", type=int, default=0, help="random seed (synthetic and random roots; default 0)")
    r = p.add_argument_group("computation")
    r.add_argument("--float64", action="store_true", help="compute in double precision (slower)")
    r.add_argument("--devices", type=_positive_int, metavar="N",
                   help="number of CPU devices to split the work over (default: one per core)")
    r.add_argument("--quiet", action="store_true", help="no progress messages or bars")
    r.add_argument("--debug", action="store_true", help="show the full Python traceback on errors")


def _add_mean_options(p):
    g = p.add_argument_group("mean root")
    g.add_argument("--max-steps", type=_positive_int, default=30, metavar="N",
                   help="maximum number of solver steps of the mean (default 30)")


def _add_pca_options(p):
    g = p.add_argument_group("modes of variation")
    g.add_argument("--modes", type=_positive_int, default=3, metavar="N",
                   help="number of principal modes to draw (default 3)")


def _add_sample_options(p, *, n_default=12):
    g = p.add_argument_group("random roots")
    g.add_argument("-n", "--n", type=_positive_int, default=n_default, metavar="N",
                   help=f"number of random roots (default {n_default})")
    g.add_argument("--truncate", type=_positive_float, default=None, metavar="C",
                   help="keep each random coefficient within ±C standard deviations (e.g. 2)")


def _add_regress_options(p):
    g = p.add_argument_group("trait regression")
    g.add_argument("--requested", metavar="CSV",
                   help="CSV with columns main_length, mean_lateral_length, std_lateral_length "
                        "(input units): one predicted root per row. Default: vary one trait (--vary)")
    g.add_argument("--vary", choices=PAPER_TRAITS, default="mean_lateral_length",
                   help="trait varied from its 10th to 90th percentile when --requested is not "
                        "given, the others at their median (default mean_lateral_length)")


def _add_cluster_options(p):
    g = p.add_argument_group("clusters")
    g.add_argument("--clusters", type=_positive_int, metavar="K",
                   help="number of clusters (default: the number of conditions of synthetic "
                        "roots, otherwise 2)")
    g.add_argument("--linkage", choices=("average", "complete", "single", "weighted", "ward"),
                   default="average", help="how cluster distances are measured (default average)")


def _add_geodesic_options(p):
    g = p.add_argument_group("geodesic")
    g.add_argument("--steps", type=_positive_int, default=7, metavar="N",
                   help="number of intermediate roots drawn, including both ends (default 7)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description=_DESCRIPTION, epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name, help_, description, func, **kw):
        p = sub.add_parser(name, help=help_, description=description, **kw)
        p.set_defaults(func=func)
        return p

    p = add("distances", "distance between every pair of roots (CSV matrix + heat map)",
            "Elastic shape distance between every pair of roots: 0 for identical shapes, larger "
            "the more bending, stretching, growing and moving of laterals it takes to turn one "
            "root into the other. Writes distances.csv and a heat map distances.png.", cmd_distances)
    _add_common(p)

    p = add("geodesic", "optimal deformation of one root into another (PNG strip + RSML per step)",
            "The optimal (shortest) deformation of root A into root B: a strip of intermediate "
            "roots in geodesic.png, each step as RSML, and the distance. Each of A and B is an "
            "RSML file or an image; --root-a/--root-b choose a root in a file with several.",
            cmd_geodesic)
    p.add_argument("a", metavar="A", help="file with the first root (RSML or image)")
    p.add_argument("b", metavar="B", help="file with the second root (RSML or image)")
    p.add_argument("--root-a", type=int, default=0, metavar="I", help="which root of file A (0 = first)")
    p.add_argument("--root-b", type=int, default=0, metavar="I", help="which root of file B (0 = first)")
    _add_geodesic_options(p)
    _add_common(p, inputs=False)
    img = p.add_argument_group("images")
    img.add_argument("--pixel-size", type=_positive_float, metavar="SIZE", help="length of one image pixel")
    img.add_argument("--unit", metavar="UNIT", help="unit of --pixel-size (default mm)")

    p = add("mean", "the mean root (RSML + PNG + energy trace)",
            "The mean root of a population (Karcher mean): the root closest on average to all "
            "inputs. Writes mean.rsml, mean.png (inputs and mean) and the solver's energy per "
            "step (mean_energy.csv/png).", cmd_mean)
    _add_common(p)
    _add_mean_options(p)

    p = add("pca", "main modes of shape variation (modes PNG + explained-variance CSV)",
            "Principal modes of variation around the mean root: modes.png shows the mean pushed "
            "±1 and ±2 standard deviations along each mode; explained_variance.csv says how much "
            "of the variation each mode explains. Also writes the mean.", cmd_pca)
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)

    p = add("sample", "random new roots from the population's variation (RSML + PNG)",
            "Random new roots drawn from the population's modes of variation (a Gaussian model "
            "around the mean). Writes random_roots.rsml, a figure grouped by distance to the "
            "mean, and the mean and modes it is based on.", cmd_sample)
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)
    _add_sample_options(p)

    p = add("regress", "roots predicted from traits (main and lateral lengths)",
            "Learn how root shape depends on three traits (main-root length, mean and standard "
            "deviation of lateral length) and predict roots with requested traits. Writes "
            "predicted_roots.rsml/png/csv and regression_report.csv (how well the predicted roots "
            "have the requested traits).", cmd_regress)
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)
    _add_regress_options(p)

    p = add("cluster", "group similar roots (dendrogram PNG + CSV labels)",
            "Hierarchical clustering of the roots from their distances: dendrogram.png and "
            "clusters.csv (cluster of each root). Synthetic roots also get a leave-one-out "
            "classification of their condition (classification.csv).", cmd_cluster)
    _add_common(p)
    _add_cluster_options(p)

    p = add("traits", "classical root traits (CSV)",
            "Classical architecture traits of each root (main-root length, number and density "
            "of laterals, lateral lengths, insertion angles, depth, width, convex hull) in "
            "traits.csv, in the input's units.", cmd_traits)
    _add_common(p)

    p = add("demo", "everything on the bundled 53-root data set, with an index.html",
            "Run every analysis on the bundled data set of 53 synthetic roots (control, drought, "
            "high nitrate) and write one folder with all figures, tables and an index.html that "
            "shows them.", cmd_demo)
    _add_common(p, inputs=False, default_out="demo_output")
    p.add_argument("--samples", type=_positive_int, metavar="N",
                   help="use only N of the 53 roots, evenly spread over the conditions (faster)")
    _add_mean_options(p)
    _add_pca_options(p)
    _add_sample_options(p)
    _add_regress_options(p)
    _add_cluster_options(p)
    _add_geodesic_options(p)
    p.set_defaults(points=50)  # measured: keeps the demo within a few minutes on 2 cores
    return parser


# --------------------------------------------------------------------------------------------
# Entry point


def _one_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    first = text.splitlines()[0]
    return first


@contextlib.contextmanager
def _plain_warnings():
    """Library warnings (e.g. skipped parts of an RSML file) as one line each, no source."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{PROG}: warning: {_one_line(message) if isinstance(message, Warning) else message}",
              file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        old = warnings.showwarning
        warnings.showwarning = show
        try:
            yield
        finally:
            warnings.showwarning = old


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with `argv` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (already printed)
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    configure_jax(devices=args.devices, float64=args.float64)
    try:
        with _plain_warnings():
            args.func(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted.", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - every failure becomes one line unless --debug
        if args.debug:
            raise
        from ._errors import RootShapeError

        known = (CLIError, RootShapeError, ValueError, TypeError, OSError)
        if isinstance(e, known):
            print(f"{PROG}: error: {_one_line(e)}", file=sys.stderr)
        else:
            print(f"{PROG}: error: {type(e).__name__}: {_one_line(e)} (this looks like a bug; "
                  "run again with --debug and report the traceback)", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK
