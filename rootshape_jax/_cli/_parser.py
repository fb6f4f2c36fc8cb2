"""The argument parser of ``rootshape`` (argparse): subcommands, options and their checks."""

from __future__ import annotations

import argparse
import csv
import math
import os
import re

from ._commands import (
    cmd_cluster,
    cmd_compare,
    cmd_demo,
    cmd_distances,
    cmd_extract,
    cmd_geodesic,
    cmd_learn_weights,
    cmd_mean,
    cmd_pca,
    cmd_regress,
    cmd_sample,
    cmd_traits,
)
from ._common import PAPER_TRAITS, PROG, version


def _whole_number(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected a number >= {minimum}, got {value}")
    return value


def _positive_int(text: str) -> int:
    return _whole_number(text, 1)


def _count(text: str) -> int:
    return _whole_number(text, 0)


def _length_unit(text: str) -> str:
    from rootshape_jax.io._units import check_length_unit

    try:
        check_length_unit(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).split(" (or ")[0]) from None
    return text.strip()


def _steps(text: str) -> int:
    value = _positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"a path needs at least 2 roots (its two ends), got {value}")
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


def _penalties(text: str) -> tuple[float, ...]:
    """One or more non-negative numbers, comma-separated (several: inner cross-validation picks one)."""
    try:
        values = tuple(float(p) for p in text.split(","))
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(
            f"expected one or more non-negative numbers separated by commas (e.g. 1e-3 or 0,1e-3,1e-1), got {text!r}"
        )
    return values


class WeightValues(tuple):
    """The terms' weights (in the order of `rootshape_jax.TERMS`) and, from a weights file,
    ``deeper``: (λs, λp) per order from the second (`rootshape_jax.Weights.deeper`)."""

    deeper: tuple = ()


def _weights(text: str):
    """One non-negative number per metric term, in the order of `rootshape_jax.TERMS`; terms left
    out keep their default (so the paper's three values still work). Or the weights.csv that
    learn-weights writes (its "learned" column)."""
    import rootshape_jax as rs

    names = [t.name for t in rs.TERMS]
    if text.lower().endswith(".csv") or os.path.isfile(text):
        return _weights_file(text, names)
    parts = text.replace(";", ",").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    ok = 3 <= len(values) <= len(names) and all(math.isfinite(v) and v >= 0 for v in values) and sum(values) > 0
    if not ok:
        raise argparse.ArgumentTypeError(
            f"expected {len(names) - 1} or {len(names)} non-negative numbers {','.join(names)}, not all "
            f"zero (e.g. 0.02,1,1 or 0.02,1,1,0.5), got {text!r}"
        )
    return tuple(values) + tuple(t.default_weight for t in rs.TERMS[len(values) :])


def _weights_file(path: str, names: list[str]) -> WeightValues:
    """The "learned" column of learn-weights' weights.csv (rows: term, start, learned), terms
    by name; ``lateral_order{ℓ}``/``position_order{ℓ}`` rows give the deeper orders' weights."""
    import rootshape_jax as rs

    def bad(why: str):
        return argparse.ArgumentTypeError(
            f"{path}: {why}. Expected the weights.csv that 'rootshape learn-weights' writes (columns "
            "term and learned; rows main, lateral, position[, thickness]), or numbers M,L,P[,R]"
        )

    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise bad(f"cannot be read ({e.strerror or e})") from None
    except (csv.Error, UnicodeDecodeError) as e:
        raise bad(f"is not a CSV table ({e})") from None
    if not rows or not {"term", "learned"} <= set(rows[0]):
        raise bad("has no columns 'term' and 'learned'")
    values = {}
    for row in rows:
        term, text = (row.get("term") or "").strip(), (row.get("learned") or "").strip()
        if not term and not text:
            continue  # an empty row (a spreadsheet's trailing ",,")
        try:
            v = float(text)
        except ValueError:
            raise bad(f"term {term!r} has the weight {text!r}, not a number") from None
        if not (math.isfinite(v) and v >= 0):
            raise bad(f"term {term!r} has the weight {text}; weights are non-negative numbers")
        if term in values:
            raise bad(f"term {term!r} appears twice")
        values[term] = v
    orders = {}
    for term in values:
        m = re.fullmatch(r"(lateral|position)_order(\d+)", term)
        if term not in names and not (m and int(m.group(2)) >= 2):
            raise bad(f"unknown term {term!r} (the terms are {', '.join(names)}, then lateral_orderN/position_orderN)")
        if m:
            orders.setdefault(int(m.group(2)), {})[m.group(1)] = values[term]
    missing = [n for n in names[:3] if n not in values]
    if missing:
        raise bad(f"no row for {', '.join(missing)}")
    if sum(values.get(n, 0.0) for n in names) <= 0:
        raise bad("every weight is 0")
    levels = sorted(orders)
    if levels != list(range(2, 2 + len(levels))) or any(len(orders[k]) != 2 for k in levels):
        raise bad("the deeper orders need lateral_orderN and position_orderN rows for N = 2, 3, … without gaps")
    out = WeightValues(values.get(n, t.default_weight) for n, t in zip(names, rs.TERMS))
    out.deeper = tuple((orders[k]["lateral"], orders[k]["position"]) for k in levels)
    return out


def _level_weights(text: str) -> tuple[tuple[float, float], ...]:
    """Pairs ``LS,LP`` (lateral shape, lateral position) separated by ``;``, one pair per order
    from the second down."""
    try:
        pairs = tuple(tuple(float(v) for v in part.split(",")) for part in text.split(";"))
    except ValueError:
        pairs = ()
    if not pairs or not all(len(p) == 2 and all(math.isfinite(v) and v >= 0 for v in p) for p in pairs):
        raise argparse.ArgumentTypeError(
            "expected pairs of non-negative numbers LS,LP (shape, position) separated by ';', "
            f"one per order from the second (e.g. 1,1 or 2,0.5;1,1), got {text!r}"
        )
    return pairs


PIXEL_SIZE_HELP = (
    "length of one pixel, for images and for RSML tracings stored in pixels without a resolution "
    "(RootNav, RhizoScan, ...), e.g. 0.0423 for 600 dpi in mm; their lengths are then in --unit "
    "(default mm). Files with their own <unit> and <resolution> keep them. Default: keep pixels"
)


def _add_system_options(p: argparse.ArgumentParser, *, metric: bool = True) -> None:
    """What one root system is and how many orders of laterals the analysis keeps (and, for
    commands that compare roots, how much each order weighs)."""
    g = p.add_argument_group("whole root systems")
    g.add_argument(
        "--depth",
        type=int,
        choices=(2, 3, 4),
        default=None,
        help="levels of the root system compared: 2 = main root + laterals (default, the "
        "paper's), 3 adds the laterals' own laterals (second order), 4 the third order; deeper "
        "branches than that are left out with a warning",
    )
    g.add_argument(
        "--per",
        choices=("root", "plant"),
        default="root",
        help="one root system per top-level root of an RSML file (root, default) or per plant "
        "(plant: all its axes, seminal and nodal roots or several seedlings, as one system "
        "around a zero-length main root at the collar; use with --depth 3 to keep the axes' "
        "laterals)",
    )
    if not metric:
        return
    g.add_argument(
        "--level-weights",
        type=_level_weights,
        default=(),
        metavar="LS,LP[;LS,LP...]",
        help="weights of the lateral shape and position terms for second-order laterals, then "
        "third-order (the last pair repeats below; needs --depth 3 or 4, with --per plant --depth 4). "
        "Default: every order "
        "takes the first-order laterals' weights (L,P of --weights)",
    )


_DESCRIPTION = """\
Compare the shapes of plant root systems: distances between roots, the optimal deformation of
one root into another, the mean root and its main modes of variation, random and trait-driven
new roots, and clusters. Roots are read from RSML files (SmartRoot, RootNav, RhizoVision,
CPlantBox, ...), folders of RSML files, or scanned images; each root is a main root with its
first-order laterals (--depth 3 adds second-order laterals, --per plant joins a plant's axes).

Results (CSV tables, PNG figures, RSML files) go into the folder given by --out.
Try:  rootshape demo          (everything on a bundled set of 53 roots)
      rootshape distances my_rsml_folder/ --out results
"""

_EPILOG = "Run 'rootshape COMMAND --help' for the options of one command."


def _add_common(
    p: argparse.ArgumentParser, *, inputs: bool = True, metric: bool = True, default_out: str = "rootshape_output"
) -> None:
    """The options every command shares; `metric=False` leaves out those of the distance (points,
    weights, scale, precision, devices) for commands that measure roots without comparing them."""
    if inputs:
        p.add_argument(
            "inputs",
            nargs="*",
            metavar="INPUT",
            help="RSML files (.rsml), folders (every .rsml file and image inside), or scanned "
            "images (.png, .jpg, .tif) of roots on a contrasting background",
        )
        g = p.add_argument_group("example roots instead of files")
        g.add_argument(
            "--synthetic",
            type=_positive_int,
            metavar="N",
            help="use N built-in synthetic roots per condition instead of files",
        )
        g.add_argument(
            "--condition",
            action="append",
            metavar="NAME",
            help="condition of the synthetic roots: control, drought, high_nitrate, "
            "low_phosphate (repeat for several; default control)",
        )
        img = p.add_argument_group("units")
        img.add_argument(
            "--pixel-size",
            type=_positive_float,
            metavar="SIZE",
            help=PIXEL_SIZE_HELP,
        )
        img.add_argument(
            "--unit",
            type=_length_unit,
            metavar="UNIT",
            help="convert every length to UNIT (mm, cm, m, um, inch): RSML files in inch + dpi, "
            "cm, or pixels with a <resolution>; also the unit of --pixel-size (default mm). "
            "Default: keep each file's unit",
        )
        g.add_argument(
            "--metadata",
            "--labels",
            metavar="CSV",
            help="table of labels joined to the roots by file name: a 'file' column (base name, "
            "extension optional), optional 'plant' and 'root' columns, and any label columns "
            "(condition, genotype, date, ...); see docs/metadata.md",
        )
        g.add_argument(
            "--strict",
            action="store_true",
            help="stop at the first unreadable file of a folder (default: skip it, name it, and go on with the others)",
        )
        _add_system_options(p, metric=metric)
    g = p.add_argument_group("analysis")
    g.add_argument(
        "--out",
        default=default_out,
        metavar="DIR",
        help=f"folder for the results (created if needed; default {default_out}); a "
        "folder holding earlier results is refused unless --overwrite",
    )
    g.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in the --out folder (earlier results this "
        "run does not write again are kept, and named at the end)",
    )
    if inputs:
        g.add_argument(
            "--samples",
            type=_positive_int,
            metavar="N",
            help="use only N of the roots, evenly spread through the input order (faster)",
        )
    g.add_argument("--seed", type=int, default=0, help="random seed (synthetic and random roots; default 0)")
    r = p.add_argument_group("computation")
    r.add_argument("--quiet", action="store_true", help="no progress messages or bars")
    r.add_argument("--debug", action="store_true", help="show the full Python traceback on errors")
    if not metric:
        return
    g.add_argument(
        "--laterals",
        type=_positive_int,
        metavar="N",
        help="keep at most the N longest laterals of each root (with --per plant: of each axis; faster; default: all)",
    )
    g.add_argument(
        "--points",
        type=_points,
        default=100,
        metavar="T",
        help="points per root branch after resampling (default 100; 50 is faster)",
    )
    g.add_argument(
        "--weights",
        type=_weights,
        default=(0.02, 1.0, 1.0, 0.0),
        metavar="M,L,P[,R]|CSV",
        help="importance of main-root shape, lateral shape, lateral positions and (R) "
        "radius along the roots, where the files give diameters, in the distance "
        "(default 0.02,1,1,0: the paper's; R > 0 compares thickness too), or the weights.csv "
        "that learn-weights wrote (its deeper orders' weights too, unless --level-weights)",
    )
    g.add_argument(
        "--normalise-scale",
        dest="normalise_scale",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="scale every root to the same main-root length, so only shape counts "
        "(default on; use --no-normalise-scale for growth studies where size matters: the shape "
        "terms then grow with the length unit and the lateral-position term does not, so keep one "
        "unit, --unit, for everything you compare)",
    )
    r.add_argument("--float64", action="store_true", help="compute in double precision (slower)")
    r.add_argument(
        "--devices",
        type=_positive_int,
        metavar="N",
        help="split each computation over N XLA CPU devices (default: one device, with the work's "
        "blocks on one worker thread per core, which is faster on a busy machine)",
    )


def _add_store_option(p):
    p.add_argument(
        "--store",
        metavar="DIR",
        help="keep every finished block of distances in DIR; after an interruption, the "
        "same command with the same --store computes only the missing ones",
    )


def _add_mean_options(p):
    g = p.add_argument_group("mean root")
    g.add_argument(
        "--max-steps",
        type=_positive_int,
        default=30,
        metavar="N",
        help="maximum number of solver steps of the mean (default 30)",
    )


def _add_pca_options(p):
    g = p.add_argument_group("modes of variation")
    g.add_argument(
        "--modes", type=_positive_int, default=3, metavar="N", help="number of principal modes to draw (default 3)"
    )


def _add_sample_options(p, *, n_default=12):
    g = p.add_argument_group("random roots")
    g.add_argument(
        "-n",
        "--n",
        type=_positive_int,
        default=n_default,
        metavar="N",
        help=f"number of random roots (default {n_default})",
    )
    g.add_argument(
        "--truncate",
        type=_positive_float,
        default=None,
        metavar="C",
        help="keep each random coefficient within ±C standard deviations (e.g. 2)",
    )


def _add_regress_options(p):
    g = p.add_argument_group("trait regression")
    g.add_argument(
        "--requested",
        metavar="CSV",
        help="CSV with columns main_length, mean_lateral_length, std_lateral_length "
        "(input units): one predicted root per row. Default: vary one trait (--vary)",
    )
    g.add_argument(
        "--vary",
        choices=PAPER_TRAITS,
        default="mean_lateral_length",
        help="trait varied from its 10th to 90th percentile when --requested is not "
        "given, the others at their median (default mean_lateral_length)",
    )


def _add_cluster_options(p):
    g = p.add_argument_group("clusters")
    g.add_argument(
        "--clusters",
        type=_positive_int,
        metavar="K",
        help="number of clusters (default: the number of conditions of synthetic roots, otherwise 2)",
    )
    g.add_argument(
        "--linkage",
        choices=("average", "complete", "single", "weighted", "ward"),
        default="average",
        help="how cluster distances are measured (default average)",
    )


def _add_by_option(p, what: str):
    p.add_argument(
        "--by",
        metavar="COLUMN",
        help=f"label column of --metadata to use for {what} (default: 'condition' when the roots have it)",
    )


def _add_geodesic_options(p):
    g = p.add_argument_group("geodesic")
    g.add_argument(
        "--steps",
        type=_steps,
        default=7,
        metavar="N",
        help="number of intermediate roots drawn, including both ends (default 7)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=_DESCRIPTION,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name, help_, description, func, **kw):
        p = sub.add_parser(name, help=help_, description=description, **kw)
        p.set_defaults(func=func)
        return p

    p = add(
        "distances",
        "distance between every pair of roots (CSV matrix + heat map)",
        "Elastic shape distance between every pair of roots: 0 for identical shapes, larger "
        "the more bending, stretching, growing and moving of laterals it takes to turn one "
        "root into the other. Writes distances.csv and a heat map distances.png.",
        cmd_distances,
    )
    _add_common(p)
    _add_store_option(p)

    p = add(
        "geodesic",
        "optimal deformation of one root into another (PNG strip + RSML per step)",
        "The optimal (shortest) deformation of root A into root B: a strip of intermediate "
        "roots in geodesic.png, each step as RSML, and the distance. Each of A and B is an "
        "RSML file or an image; --root-a/--root-b choose a root in a file with several.",
        cmd_geodesic,
    )
    p.add_argument("a", metavar="A", help="file with the first root (RSML or image)")
    p.add_argument("b", metavar="B", help="file with the second root (RSML or image)")
    p.add_argument("--root-a", type=int, default=0, metavar="I", help="which root of file A (0 = first)")
    p.add_argument("--root-b", type=int, default=0, metavar="I", help="which root of file B (0 = first)")
    _add_geodesic_options(p)
    _add_common(p, inputs=False)
    img = p.add_argument_group("units")
    img.add_argument("--pixel-size", type=_positive_float, metavar="SIZE", help=PIXEL_SIZE_HELP)
    img.add_argument(
        "--unit",
        type=_length_unit,
        metavar="UNIT",
        help="convert both roots to UNIT (mm, cm, m, um, inch); also the unit of --pixel-size (default mm)",
    )
    _add_system_options(p)

    p = add(
        "mean",
        "the mean root (RSML + PNG + energy trace)",
        "The mean root of a population (Karcher mean): the root closest on average to all "
        "inputs. Writes mean.rsml, mean.png (inputs and mean) and the solver's energy per "
        "step (mean_energy.csv/png).",
        cmd_mean,
    )
    _add_common(p)
    _add_mean_options(p)

    p = add(
        "pca",
        "main modes of shape variation (modes PNG + explained-variance and scores CSV)",
        "Principal modes of variation around the mean root: modes.png shows the mean pushed "
        "±1 and ±2 standard deviations along each mode; explained_variance.csv says how much "
        "of the variation each mode explains; pca_scores.csv gives each root's score on every "
        "kept mode, and pca_scores.png the first two (coloured by --by). Also writes the mean.",
        cmd_pca,
    )
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)
    _add_by_option(p, "the colours of the score plot (pca_scores.png)")

    p = add(
        "sample",
        "random new roots from the population's variation (RSML + PNG)",
        "Random new roots drawn from the population's modes of variation (a Gaussian model "
        "around the mean). Writes random_roots.rsml, a figure grouped by distance to the "
        "mean, and the mean and modes it is based on.",
        cmd_sample,
    )
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)
    _add_sample_options(p)
    _add_by_option(p, "the colours of the score plot (pca_scores.png)")

    p = add(
        "regress",
        "roots predicted from traits (main and lateral lengths)",
        "Learn how root shape depends on three traits (main-root length, mean and standard "
        "deviation of lateral length) and predict roots with requested traits. Writes "
        "predicted_roots.rsml/png/csv and regression_report.csv (how well the predicted roots "
        "have the requested traits).",
        cmd_regress,
    )
    _add_common(p)
    _add_mean_options(p)
    _add_pca_options(p)
    _add_regress_options(p)
    _add_by_option(p, "extra covariates (numeric columns; repeat or comma-separate for several)")

    p = add(
        "cluster",
        "group similar roots (dendrogram PNG + CSV labels)",
        "Hierarchical clustering of the roots from their distances: dendrogram.png and "
        "clusters.csv (cluster of each root). Synthetic roots also get a leave-one-out "
        "classification of their condition (classification.csv).",
        cmd_cluster,
    )
    _add_common(p)
    _add_store_option(p)
    _add_cluster_options(p)
    _add_by_option(p, "the leave-one-out classification")

    p = add(
        "compare",
        "group differences: MDS plot, PERMANOVA and pairwise tests (PNG + CSV + markdown)",
        "Do the groups of a label (condition, genotype, ...) differ in shape? Computes the "
        "distance matrix, draws the roots in two dimensions (classical MDS) coloured by group, "
        "and tests the groups with PERMANOVA (pseudo-F, p-value, R²), overall and for every "
        "pair of groups (p-values corrected with Holm's method). Writes mds.png, "
        "permanova.csv/.md, distances.csv and a heat map with a strip per label.",
        cmd_compare,
    )
    _add_common(p)
    _add_store_option(p)
    _add_by_option(p, "the groups")
    g = p.add_argument_group("tests")
    g.add_argument(
        "--permutations",
        type=_positive_int,
        default=999,
        metavar="N",
        help="permutations of each PERMANOVA (default 999; the smallest p-value is 1/(N+1))",
    )

    p = add(
        "learn-weights",
        "learn the metric weights from labelled roots (CSV + loss plot + cross-validation)",
        "Learn how much main-root shape, lateral shape and lateral positions (and thickness, "
        "where the files give diameters) should count so that roots of the same class (--by "
        "COLUMN of --labels/--metadata) are nearest each other. Writes weights.csv (give it to "
        "the other commands: --weights weights.csv), loss_trace.png, and cross_validation.csv: accuracy and log-loss on "
        "held-out roots with the weights learned on the other folds only, against the starting weights.",
        cmd_learn_weights,
    )
    _add_common(p)
    _add_by_option(p, "the classes")
    g = p.add_argument_group("learning")
    g.add_argument(
        "--folds",
        type=int,
        default=5,
        metavar="N",
        help="outer cross-validation folds (default 5; every class needs N members; 0 skips it)",
    )
    g.add_argument(
        "--repeats",
        type=_positive_int,
        default=1,
        metavar="R",
        help="repeat the cross-validation on R different splits (seeds --seed … --seed + R − 1; "
        "default 1): on small sets one split decides by a root or two",
    )
    g.add_argument(
        "--reregistrations",
        type=_positive_int,
        default=2,
        metavar="N",
        help="at most N re-registrations of every pair at the new weights (default 2)",
    )
    g.add_argument(
        "--regularisation",
        type=_penalties,
        default=(1e-3,),
        metavar="R[,R...]",
        help="penalty on log λ moving away from the starting weights (default 1e-3); several "
        "values: an inner cross-validation on the training roots picks one",
    )

    p = add(
        "traits",
        "classical root traits (CSV)",
        "Classical architecture traits of each root (main-root length, number and density "
        "of laterals, lateral lengths, insertion angles, depth, width, convex hull) in "
        "traits.csv, in the input's units.",
        cmd_traits,
    )
    _add_common(p, metric=False)
    p.add_argument(
        "--angle-window",
        dest="angle_window",
        type=_positive_float,
        metavar="LENGTH",
        help="insertion angles from chords of this arc length (in the roots' unit): the lateral "
        "from its base to LENGTH along it, the parent over LENGTH around the branching point. "
        "Default: each lateral's first segment, coarse on pixel tracings (steps of a few pixels)",
    )

    p = add(
        "extract",
        "roots from photographs or scans (one RSML + overlay PNG per image)",
        "Find the root systems in each image (plates with several seedlings, seedlings on "
        "germination paper, dark-on-light or light-on-dark): one RSML and an overlay PNG "
        "(the extraction drawn on the photo, one colour per root) per image, and "
        "summary.json. With --tracing, the hand tracing is drawn too and compared (lengths, "
        "lateral counts; the elastic distance with --elastic). A bad image is named and skipped. "
        "An --out folder holding an earlier run's results is refused unless --overwrite.",
        cmd_extract,
    )
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files or folders of images")
    p.add_argument("--out", default="rootshape_output", metavar="DIR", help="output folder")
    p.add_argument(
        "--tracing",
        nargs="+",
        metavar="RSML",
        help="hand tracings: an RSML file, a folder of <image name>.rsml, or several files",
    )
    p.add_argument(
        "--pixels-per-mm",
        dest="pixels_per_mm",
        type=_positive_float,
        metavar="X",
        help="image scale; the RSML is then written in mm",
    )
    p.add_argument(
        "--pixel-size",
        dest="pixel_size",
        type=_positive_float,
        metavar="SIZE",
        help="length of one image pixel in --unit (instead of --pixels-per-mm, as in the other commands); "
        "the RSML is then written in that unit",
    )
    p.add_argument("--unit", type=_length_unit, metavar="UNIT", default=None, help="unit of --pixel-size (default mm)")
    p.add_argument(
        "--root-width",
        dest="root_width",
        type=_positive_float,
        metavar="PX",
        help="typical root width in pixels (default 6; set it for thick roots)",
    )
    shoot = p.add_mutually_exclusive_group()
    shoot.add_argument(
        "--shoot-green",
        dest="shoot_green",
        type=_positive_float,
        metavar="G",
        help="colour photographs: how much greener than its background (CIELAB units) a "
        "seedling's shoot (cotyledons, hypocotyl) is, to be left out so the main root starts "
        "where the root starts (default 6; higher keeps pale shoots)",
    )
    shoot.add_argument(
        "--keep-shoot",
        dest="keep_shoot",
        action="store_true",
        help="keep green parts in the extraction (roots that are green themselves)",
    )
    p.add_argument(
        "--elastic",
        action="store_true",
        help="with --tracing, also compute the elastic distance of each extracted plant to its "
        "tracing (one registration per plant; compiles once, ~10-20 s)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in the --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show the full Python traceback on errors")

    p = add(
        "demo",
        "everything on the bundled 53-root data set, with an index.html",
        "Run every analysis on the bundled data set of 53 synthetic roots (control, drought, "
        "high nitrate) and write one folder with all figures, tables and an index.html that "
        "shows them.",
        cmd_demo,
    )
    _add_common(p, inputs=False, default_out="demo_output")
    p.add_argument(
        "--samples",
        type=_positive_int,
        metavar="N",
        help="use only N of the 53 roots, evenly spread over the conditions (faster)",
    )
    _add_mean_options(p)
    _add_pca_options(p)
    _add_sample_options(p)
    _add_regress_options(p)
    _add_cluster_options(p)
    _add_geodesic_options(p)
    g = p.add_argument_group("whole root systems")
    g.add_argument(
        "--plants",
        type=_count,
        default=10,
        metavar="N",
        help="CPlantBox pea plants of the whole-root-systems section (second-order laterals, "
        "depth 3 against depth 2; needs the 'sim' extra; default 10, 0 skips it)",
    )
    p.set_defaults(points=50)  # measured: keeps the demo within a few minutes on 2 cores
    return parser
