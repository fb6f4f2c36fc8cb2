"""The subcommands: load the roots, run the analysis steps in order, report."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ._common import PAPER_TRAITS, CLIError, say, warn
from ._inputs import Reading, covariate_columns, load_roots, pick, prepare, read_requested, subsample
from ._report import LOG_NAME, OPENED, Output, WrittenFolder, refuse_earlier_results, settings, write_index
from ._steps import (
    Context,
    group_labels,
    run_cluster,
    run_compare,
    run_distances,
    run_geodesic,
    run_learn_weights,
    run_mean,
    run_pca,
    run_regress,
    run_sample,
    run_traits,
)
from ._systems import run_whole_systems


def _read(args, out: Output, reading: Reading, paths=None) -> list:
    """The input roots; the details of any skipped file or part go to the log file at once."""
    try:
        return load_roots(args, paths=paths, reading=reading)
    finally:  # also when a file stops the run: the warnings so far point to the log
        out.log[:] = reading.log
        out.write_log()


def _finish(out: Output, reading: Reading) -> None:
    out.print_summary()
    if reading.files or reading.skipped:
        print(reading.summary())
    _warn_stale(out)


def _warn_stale(out: Output) -> None:
    stale = out.stale()
    if stale:
        shown = ", ".join(stale[:6]) + (f" and {len(stale) - 6} more" if len(stale) > 6 else "")
        warn(
            f"--out {out.folder} also holds {len(stale)} file{'s' if len(stale) > 1 else ''} of an earlier run "
            f"that this run did not replace ({shown}); "
            + ("they were" if len(stale) > 1 else "it was")
            + " not made from this run's inputs: delete "
            + ("them" if len(stale) > 1 else "it")
            + ", or use a new --out folder."
        )


def _pipeline(args, steps, *, min_roots: int = 2) -> None:
    """Load and prepare the roots, run `steps` (each ``step(ctx, out, args)``) in order."""
    out = Output(args.out, args)
    reading = Reading(log_path=str(out.path(LOG_NAME)))
    ctx = Context(prepare(_read(args, out, reading), args, min_roots=min_roots, samples=args.samples))
    for step in steps:
        step(ctx, out, args)
    _finish(out, reading)


def cmd_distances(args) -> None:
    _pipeline(args, [run_distances])


def cmd_mean(args) -> None:
    _pipeline(args, [run_mean], min_roots=1)


def cmd_pca(args) -> None:
    _pipeline(args, [run_mean, run_pca])


def cmd_sample(args) -> None:
    _pipeline(args, [run_mean, run_pca, run_sample])


def cmd_regress(args) -> None:
    # Check the request before the long computation.
    if getattr(args, "per", "root") == "plant":
        raise CLIError(
            "regress scales each predicted root to its requested main-root length, and a plant's "
            "system (--per plant: several axes under a virtual main root of zero length) has none; "
            "run regress with --per root (one system per axis)."
        )
    names = list(PAPER_TRAITS) + covariate_columns(args)
    args.requested_values = read_requested(args.requested, names) if args.requested else None
    _pipeline(args, [run_mean, run_pca, run_regress], min_roots=len(PAPER_TRAITS) + 2)


def cmd_cluster(args) -> None:
    _pipeline(args, [run_distances, run_cluster])


def cmd_compare(args) -> None:
    # The groups are checked before the distances are computed.
    _pipeline(args, [lambda ctx, out, args: group_labels(ctx.pop), run_distances, run_compare], min_roots=3)


def cmd_learn_weights(args) -> None:
    # The classes are checked before anything is registered.
    _pipeline(args, [lambda ctx, out, args: group_labels(ctx.pop, "learn-weights"), run_learn_weights], min_roots=4)


def cmd_traits(args) -> None:
    out = Output(args.out, args)
    reading = Reading(log_path=str(out.path(LOG_NAME)))
    roots = subsample(_read(args, out, reading), args.samples)
    run_traits(roots, out, args)
    _finish(out, reading)


def cmd_geodesic(args) -> None:
    out = Output(args.out, args)
    reading = Reading(log_path=str(out.path(LOG_NAME)))
    a = pick(_read(args, out, reading, [args.a]), args.root_a, args.a)
    b = pick(_read(args, out, reading, [args.b]), args.root_b, args.b)
    run_geodesic(a, b, out, args)
    _finish(out, reading)


def cmd_extract(args) -> None:
    import warnings
    from pathlib import Path

    from rootshape_jax._atomic import recording_writes
    from rootshape_jax.io import extract_images
    from rootshape_jax.io._extract_cli import expand_images

    if args.pixel_size is not None and args.pixels_per_mm is not None:
        raise CLIError("give --pixels-per-mm or --pixel-size (with --unit), not both.")
    if args.unit is not None and args.pixel_size is None:
        raise CLIError(f"--unit {args.unit}: it is the unit of --pixel-size; give --pixel-size too.")
    out_dir = Path(args.out)
    stems = {p.stem for p in expand_images(args.images)}
    for t in map(Path, args.tracing or ()):
        # A tracing where extract writes its own <image name>.rsml would be replaced before it is read.
        if t.is_dir():
            clash = t.resolve() == out_dir.resolve() and any((t / f"{s}.rsml").exists() for s in stems)
        else:
            clash = t.parent.resolve() == out_dir.resolve() and t.stem in stems
        if clash:
            raise CLIError(
                f"--tracing {t}: the hand tracings are in --out {args.out}, where extract writes "
                "<image name>.rsml over them; give another --out."
            )
    if out_dir.is_dir() and not args.overwrite:
        refuse_earlier_results(
            args.out,
            [
                p.name
                for p in out_dir.iterdir()
                if p.name == "summary.json"
                or (p.suffix == ".rsml" and p.stem in stems)
                or (p.name.endswith("_overlay.png") and p.stem[: -len("_overlay")] in stems)
            ],
        )
    options = {} if args.root_width is None else {"root_width": args.root_width}
    if args.keep_shoot:
        options["shoot_green"] = None
    elif args.shoot_green is not None:
        options["shoot_green"] = args.shoot_green
    with warnings.catch_warnings(), recording_writes() as written:
        # Stopped early, the run names the files it finished (`unfinished_note`).
        folder = WrittenFolder(args.out, written)
        # A skipped image is named in its row and summarised below: one line each, no repeat.
        warnings.simplefilter("ignore", UserWarning)
        rows = extract_images(
            args.images,
            args.out,
            tracing=args.tracing,
            pixels_per_mm=args.pixels_per_mm,
            pixel_size=args.pixel_size,
            unit=args.unit or "mm",
            progress=not args.quiet,
            elastic=args.elastic,
            **options,
        )
    OPENED.remove(folder)  # every image done: an error below is not a run stopped early
    ok = [r for r in rows if r.get("status") == "ok"]
    skipped = [r for r in rows if r.get("status") != "ok"]
    for r in skipped:
        warn(f"skipped {r.get('image', '?')}: {r.get('reason', 'unreadable')}")
    if not ok:
        raise CLIError(f"no roots could be extracted from {len(rows)} image(s); see the lines above.")
    plants = sum(int(r.get("plants", 0)) for r in ok)
    say(
        args,
        f"extracted {plants} root system(s) from {len(ok)} image(s)"
        + (f"; skipped {len(skipped)}" if skipped else "")
        + f"; results in {args.out}",
    )


def cmd_demo(args) -> None:
    from rootshape_jax.datasets import default_dataset

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
    if args.plants:
        steps.append(("whole root systems (CPlantBox pea, depth 3)", lambda: run_whole_systems(out, args)))
    for i, (name, fn) in enumerate(steps, 1):
        say(args, f"[{i}/{len(steps)}] {name}")
        fn()
    counts: dict[str, int] = {}
    for c in pop.conditions or []:
        counts[c] = counts.get(c, 0) + 1
    intro = [
        f"{len(pop.names)} synthetic root systems from the bundled data set "
        f"({', '.join(f'{v} {k}' for k, v in counts.items())}), analysed with the elastic "
        "shape metric of Wang et al. (main root, laterals and their positions; rotation, "
        "re-parameterisation and lateral correspondence optimised for every pair).",
        f"Each branch is resampled to T = {args.points} points"
        + (
            " (the demo's reduced resolution, chosen so it runs in a few minutes on a 2-core "
            "machine; use --points 100 for the library's usual resolution)"
            if args.points < 100
            else ""
        )
        + (
            f"; {len(pop.names)} of the {len(all_roots)} roots used (--samples)"
            if len(pop.names) < len(all_roots)
            else ""
        )
        + ".",
        *(
            [
                f"The last section compares whole root systems: {args.plants} CPlantBox pea plants with "
                "second-order laterals, at depth 3 (every order matched under its parent's match) and at "
                "depth 2 (--plants 0 skips it)."
            ]
            if args.plants
            else []
        ),
        f"Total time {time.perf_counter() - start:.0f} s, including compilation (see the timings).",
    ]
    write_index(out, title="rootshape demo", intro=intro, settings=settings(args, pop))
    print(f"Open {out.path('index.html').resolve()} in a web browser.")
    print(f"Results are in {out.folder.resolve()}")
    _warn_stale(out)


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
