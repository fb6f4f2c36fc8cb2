"""Reading roots (files, folders, images, synthetic) and preparing them for the analyses."""

from __future__ import annotations

import csv
import dataclasses
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import rootshape_jax as rs
from rootshape_jax import io

from ._common import PAPER_TRAITS, CLIError, warn


class Reading(io.ReadReport):
    """What reading the input files found (`rootshape_jax.io.ReadReport`), and the log file
    the terminal lines point to."""

    def __init__(self, log_path: str = ""):
        super().__init__()
        self.log_path = log_path


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

        if getattr(args, "metadata", None):
            raise CLIError("--metadata labels files read from disk; synthetic roots already carry their condition.")

        conditions = args.condition or ["control"]
        # Synthetic roots grow second-order laterals when the analysis keeps them.
        depth = min(getattr(args, "depth", None) or 2, 3)
        roots = []
        for c in conditions:
            roots.extend(synthetic_roots(synthetic, condition=c, seed=args.seed, depth=depth))
        return roots
    if not paths:
        raise CLIError("no input: give RSML files, folders or images, or --synthetic N for example roots.")
    reading = Reading() if reading is None else reading

    def notice(kind: str, text: str) -> None:
        if kind == "warning" and reading.log_path:
            text += f" (details in {reading.log_path})"
        warn(text)

    # Tables are checked before the files are read: a bad table fails at once.
    table = io.read_metadata(args.metadata) if getattr(args, "metadata", None) else None
    pixel_size = getattr(args, "pixel_size", None)
    unit = getattr(args, "unit", None)
    roots = io.read_paths(
        paths,
        strict=getattr(args, "strict", False),
        pixel_size=pixel_size,
        unit=unit,
        report=reading,
        notice=notice,
        by=getattr(args, "per", "root"),
    )
    if unit:
        roots = io.convert_units(roots, unit)
    if table is not None:
        roots = io.attach_metadata(roots, table)
    return roots


def pick(roots: list, index: int, path: str):
    if not -len(roots) <= index < len(roots):
        raise CLIError(
            f"{path}: has {len(roots)} root(s); root number {index} does not exist (give 0 to {len(roots) - 1}, "
            "counted from 0 in the file's order)."
        )
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


def covariate_columns(args) -> list[str]:
    """The extra regression covariates named by ``regress --by`` (repeatable, comma-separated)."""
    if getattr(args, "command", None) != "regress" or not getattr(args, "by", None):
        return []
    return [c.strip() for c in args.by.split(",") if c.strip()]


def covariate_matrix(roots: list, columns: Sequence[str]) -> np.ndarray:
    """The numeric label columns as an (n, c) matrix; `CLIError` names a non-numeric value."""
    out = np.zeros((len(roots), len(columns)))
    for j, c in enumerate(columns):
        for i, v in enumerate(io.labels_of(roots, c)):
            try:
                out[i, j] = float(v)
            except ValueError:
                raise CLIError(
                    f"--by {c}: covariates must be numbers, but root {roots[i].name!r} has {v!r}; "
                    "use a numeric column (or code the groups as numbers)."
                ) from None
    if not np.all(np.isfinite(out)):
        raise CLIError("--by: covariate values must be finite numbers.")
    return out


def read_requested(path: str, names: Sequence[str] = PAPER_TRAITS) -> np.ndarray:
    """The requested traits (and covariates) of `regress --requested`, checked before any computation."""
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"--requested {path}: no such file.")
    try:
        with open(p, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise CLIError(f"--requested {path}: cannot read the CSV file ({e}).") from None
    missing = [k for k in names if not rows or k not in rows[0]]
    if missing:
        raise CLIError(f"--requested {path}: needs columns {', '.join(names)}; missing {', '.join(missing)}.")
    try:
        values = np.array([[float(r[k]) for k in names] for r in rows])
    except ValueError:
        raise CLIError(f"--requested {path}: every value must be a number.") from None
    if not np.all(np.isfinite(values)) or np.any(values[:, : len(PAPER_TRAITS)] < 0):
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
    mean_seed: np.ndarray  # mean main-root base (a plant's: its collar), in the input's frame
    conditions: list | None  # the group label of each root (--by, default "condition")
    label_name: str = "condition"
    labels: dict = dataclasses.field(default_factory=dict)  # every label column: {name: [value per root]}
    mixed_units: bool = False  # inputs in several units (then only normalised shapes are compared)

    @property
    def output_unit(self) -> str | None:
        """The unit of the roots a run makes: the inputs' own, or with mixed units (no common
        one) the normalised scale."""
        return io.NORMALISED_UNIT if self.normalised and self.mixed_units else self.unit


def prepare(roots: list, args, *, min_roots: int = 1, samples: int | None = None) -> Population:
    """Subsample (--samples), keep the longest laterals (--laterals), resample and pad."""
    roots = subsample(roots, samples)
    roots = [_limit_laterals(r, args.laterals) for r in roots]
    if len(roots) < min_roots:
        raise CLIError(f"this analysis needs at least {min_roots} roots, got {len(roots)}.")
    normalised = args.normalise_scale
    mixed = _check_units(roots, normalised, getattr(args, "command", None))
    by = group_column(args)
    conditions = io.labels_of(roots, by) if by else [r.metadata.get("condition") for r in roots]
    thickness = dict(zip((t.name for t in rs.TERMS), getattr(args, "weights", ()))).get("thickness", 0.0)
    no_radius = not any(r.has_radius for r in roots)
    with warnings.catch_warnings():
        # learn-weights learns the thickness weight whenever radii exist: missing ones matter there.
        if (not thickness and getattr(args, "command", None) != "learn-weights") or (thickness and no_radius):
            # Radii taken as 0 where a file has none matter only when the metric weighs them; with
            # none at all, the warning below says so once.
            warnings.simplefilter("ignore", rs.MissingRadiusWarning)
        # depth None (no --depth) is batch's default: depth 2, deeper orders ignored silently.
        tree = rs.batch(roots, n_points=args.points, normalise_scale=normalised, depth=getattr(args, "depth", None))
    if thickness and no_radius:
        warn(
            f"--weights gives thickness the weight {thickness:g}, but no root has radius data (diameters): "
            "the thickness term is 0 and the distances are the paper's metric. Use files with diameters "
            "(SmartRoot, CPlantBox, ...) or leave the fourth weight out."
        )
    _hint_many_laterals(roots, args)
    return Population(
        roots=roots,
        tree=tree,
        names=[r.name for r in roots],
        normalised=normalised,
        unit=common_unit(roots),
        mean_length=float(np.mean([rs.normalising_length(r, args.points) for r in roots])),
        mean_seed=np.mean([np.asarray(r.main[0], np.float64) for r in roots], axis=0),
        conditions=conditions if all(c is not None for c in conditions) else None,
        label_name=by or "condition",
        labels=label_columns(roots),
        mixed_units=mixed,
    )


#: Laterals on one root above which the CLI suggests --laterals: a pair's registration weighs
#: every lateral of one root against every lateral of the other (lupin's 60 against maize's 421
#: took 145 s and 6.7 GB at --points 50).
MANY_LATERALS = 150


def _axes(root) -> tuple:
    """The roots whose laterals --laterals limits: a plant's axes (--per plant), else the root."""
    return tuple(root.children) if io.is_plant_system(root) and root.children else (root,)


def _limit_laterals(root, n: int | None):
    """`rs.limit_laterals` on each axis of a plant's system (its laterals are its axes, which
    --laterals does not drop), else on the root."""
    if n is None or not (io.is_plant_system(root) and root.children):
        return rs.limit_laterals(root, n)
    return dataclasses.replace(root, children=tuple(rs.limit_laterals(axis, n) for axis in root.children))


def _hint_many_laterals(roots: list, args) -> None:
    if getattr(args, "laterals", None):
        return
    most, n = max(((r, axis.n_laterals) for r in roots for axis in _axes(r)), key=lambda rn: rn[1])
    if n > MANY_LATERALS:
        where = "an axis of " if io.is_plant_system(most) else ""
        warn(
            f"{where}{most.name or 'a root'} has {n} laterals: every pair with it compares each of its "
            "laterals with each of the other root's, which can take minutes and gigabytes. --laterals N keeps "
            "each root's (with --per plant: each axis's) N longest laterals (e.g. --laterals 60)."
        )


def _check_units(roots: list, normalised: bool, command: str | None = None) -> bool:
    """Whether the roots are in different units (inch and pixel, say). They have no common
    size: refused unless scale-normalised, where only the shapes are compared (then a warning:
    the roots a run makes stay normalised), and refused by regress, whose traits are lengths."""
    from rootshape_jax._units import unit_key

    by_unit: dict[str, list[str]] = {}
    names: dict[str, str] = {}
    for r in roots:
        unit = r.metadata.get("unit")
        key = unit_key(unit)
        if key is not None:
            unit = names.setdefault(key, str(unit))
            source = r.metadata.get("source_file")
            by_unit.setdefault(str(unit), []).append(Path(source).name if source else str(r.name))
    if len(by_unit) < 2:
        return False
    listed = "; ".join(
        f"{u}: {', '.join(sorted(set(f))[:2])}{' ...' if len(set(f)) > 2 else ''}" for u, f in by_unit.items()
    )
    fix = (
        "convert them to one unit with --unit (files in pixels also need --pixel-size), or analyse "
        "each unit's files separately"
    )
    if not normalised:
        raise CLIError(f"the roots are in different units ({listed}), so their sizes cannot be compared; {fix}.")
    if command == "regress":
        raise CLIError(
            f"the roots are in different units ({listed}), so their traits (lengths) cannot be regressed "
            f"together; {fix}."
        )
    warn(
        f"the roots are in different units ({listed}); their shapes are compared (scale-normalised), and "
        "any roots this run writes (mean, random roots, geodesics) stay at the normalised scale (main-root "
        f"length 1), as the inputs share no unit. To keep sizes, {fix}."
    )
    return True


def group_column(args) -> str | None:
    """The label column that defines the groups (--by; regress uses --by for covariates)."""
    by = getattr(args, "by", None)
    return None if getattr(args, "command", None) == "regress" else by


def label_columns(roots: list) -> dict[str, list[str]]:
    """Every label every root has: the metadata table's columns, or the synthetic condition."""
    names: list[str] = []
    for r in roots:
        for k in r.metadata.get("label_columns", ()):
            if k not in names:
                names.append(k)
    if not names and all(r.metadata.get("condition") is not None for r in roots):
        names = ["condition"]
    return {k: [str(r.metadata.get(k, "")) for r in roots] for k in names}


def length(polyline) -> float:
    return float(np.sum(np.linalg.norm(np.diff(np.asarray(polyline), axis=0), axis=1)))


def without_empty_branches(root, tol: float):
    """`root` without the branches of length <= `tol` (at every order, with their own
    laterals): a branch present on one side of a geodesic only has zero length at the other
    end, and an RSML reader skips a zero-length root with a warning."""
    keep = [k for k, lat in enumerate(root.laterals) if length(lat) > tol]
    if len(keep) < root.n_laterals:
        root = root.select_laterals(keep)
    if root.children:
        kids = tuple(without_empty_branches(c, tol) for c in root.children)
        root = dataclasses.replace(root, children=kids)
    return root


def to_output_roots(tree, pop: Population, names: Sequence[str]) -> list:
    """Unpadded roots (null slots and zero-length branches dropped) labelled with the input's unit."""
    meta = {"unit": pop.output_unit} if pop.output_unit else {}
    out = []
    for r in rs.to_roots(tree, names=list(names)):
        tol = 1e-9 * max(length(r.main), *(length(x) for x in r.laterals), 1e-300)
        out.append(dataclasses.replace(without_empty_branches(r, tol), metadata=dict(meta)))
    return out


def in_input_units(tree, pop: Population, lengths=None):
    """Analysis coordinates back in the input's units and frame. Scale-normalised roots (a
    mean, modes, synthesised roots) are scaled about their base by `lengths` (default the
    inputs' mean main-root length; see `mean_size`) and put at the inputs' mean seed:
    normalisation divided each root by its length about (0, 0), so their bases moved too."""
    if not pop.normalised or pop.mixed_units:
        return tree  # mixed units: no common size to restore
    return rs.scale_tree(tree, pop.mean_length if lengths is None else lengths, base=pop.mean_seed)


def turn(tree, rotation: np.ndarray | None):
    """`tree` (a `RootTree` or `SRVFTree`, batched or not) as curves, every root turned by
    `rotation` about its main-root base (None: unchanged)."""
    if rotation is None:
        return tree
    return rs.turn_about_base(rs.to_curves(tree), rotation)


def mean_size(mean, pop: Population) -> float:
    """The factor that gives the scale-normalised mean root (one `SRVFTree`/`RootTree`) the
    inputs' mean main-root length (for plants: longest axis). The Karcher mean of roots of
    length 1 is shorter than 1 (averaging the SRVFs of different shapes shrinks them), so
    scaling it by the mean length alone drew it 3–9 % shorter than the inputs on real tracings.
    The roots synthesised around it take the same factor."""
    tree = rs.to_curves(mean)
    (root,) = rs.to_roots(rs.stack([tree]))
    own = rs.normalising_length(root, int(tree.main.shape[-2]))
    return pop.mean_length / own if own > 0 else pop.mean_length
