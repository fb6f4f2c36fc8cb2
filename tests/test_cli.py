"""The `rootshape` command line, run as a user runs it: in a subprocess, on tiny inputs.

Fast tests cover help, traits and every way bad input must fail (one line on stderr, non-zero
exit code, no traceback). Runs that register roots compile JAX programs (tens of seconds), so
they are marked slow.
"""

from __future__ import annotations

import csv
import dataclasses
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

import rootshape_jax as rs
from rootshape_jax.datasets import synthetic_roots
from rootshape_jax.io import read_rsml, write_rsml

DATA = Path(__file__).parent / "data" / "rsml"


def assert_one_line_error(proc: subprocess.CompletedProcess, *fragments: str) -> str:
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rootshape: error: "), lines[0]
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def read_matrix(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    names = rows[0][1:]
    assert [r[0] for r in rows[1:]] == names
    return names, np.array([[float(x) for x in r[1:]] for r in rows[1:]])


@pytest.fixture(scope="module")
def rsml_files(tmp_path_factory) -> Path:
    """A folder with two RSML files of two synthetic roots each (mm)."""
    folder = tmp_path_factory.mktemp("rsml")
    write_rsml(synthetic_roots(2, condition="control", seed=1), folder / "control.rsml")
    write_rsml(synthetic_roots(2, condition="drought", seed=1), folder / "drought.rsml")
    return folder


# --------------------------------------------------------------------------------------------
# Help and fast commands


def test_help_lists_every_command():
    proc = run_cli("--help")
    assert proc.returncode == 0, proc.stderr
    for cmd in ("distances", "geodesic", "mean", "pca", "sample", "regress", "cluster", "traits", "demo"):
        assert re.search(rf"^\s+{cmd}\b", proc.stdout, re.M), cmd


@pytest.mark.parametrize(
    "cmd", ["distances", "geodesic", "mean", "pca", "sample", "regress", "cluster", "traits", "demo"]
)
def test_subcommand_help(cmd, capsys):
    from rootshape_jax._cli import main

    assert main([cmd, "--help"]) == 0
    text = capsys.readouterr().out
    assert f"usage: rootshape {cmd}" in text
    assert "--out" in text


def test_entry_point_matches_module():
    # The installed `rootshape` script calls the same main(); check the declared target exists.
    import tomllib

    root = Path(__file__).resolve().parents[1]
    scripts = tomllib.loads((root / "pyproject.toml").read_text())["project"]["scripts"]
    module, func = scripts["rootshape"].split(":")
    assert (module, func) == ("rootshape_jax._cli", "main")


def test_traits_end_to_end(rsml_files, tmp_path):
    out = tmp_path / "out"
    proc = run_cli("traits", rsml_files, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert str(out.resolve()) in proc.stdout
    with open(out / "traits.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    roots = read_rsml(rsml_files / "control.rsml") + read_rsml(rsml_files / "drought.rsml")
    assert len(rows) == len(roots) == 4
    # Same values as the library (files are read in sorted order: control, then drought).
    for row, root in zip(rows, roots):
        assert float(row["main_length_mm"]) == pytest.approx(root.main_length, rel=1e-12)
        assert int(row["n_laterals"]) == root.n_laterals
    # 2D tracings have no volume: no column of NaN for it.
    assert {r.dim for r in roots} == {2} and "convex_hull_area_mm2" in rows[0]
    assert not any(k.startswith("convex_hull_volume") for k in rows[0])


def test_distances_say_their_unit_when_not_normalised(rsml_files, tmp_path):
    """Unnormalised distances depend on the length unit (shape terms are lengths, positions are
    fractions): the run says so, and the heat map names the unit."""
    out = tmp_path / "o"
    proc = run_cli("distances", rsml_files, "--no-normalise-scale", "--points", 12, "--quiet", "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "depend on the unit" in proc.stdout and "(mm here)" in proc.stdout, proc.stdout
    proc = run_cli("distances", rsml_files, "--points", 12, "--quiet", "--out", tmp_path / "n")
    assert proc.returncode == 0 and "depend on the unit" not in proc.stdout


def test_traits_angle_window_on_pixel_tracings(tmp_path):
    """Pixel tracings: the first-segment insertion angles are coarse, and the run says how to
    measure them over a chord; --angle-window gives the library's chord angles."""
    roots = [dataclasses.replace(r, metadata={"unit": "pixel"}) for r in synthetic_roots(2, seed=4)]
    roots = [r.scaled(200.0) for r in roots]  # a main root of ~200 px
    folder = tmp_path / "px"
    folder.mkdir()
    write_rsml(roots, folder / "px.rsml")
    back = read_rsml(folder / "px.rsml")
    proc = run_cli("traits", folder, "--out", tmp_path / "a")
    assert proc.returncode == 0, proc.stderr
    assert "--angle-window" in proc.stdout
    proc = run_cli("traits", folder, "--angle-window", 20, "--out", tmp_path / "b")
    assert proc.returncode == 0, proc.stderr
    assert "--angle-window" not in proc.stdout, proc.stdout
    with open(tmp_path / "b" / "traits.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    want = [t["mean_insertion_angle"] for t in rs.traits(back, window=20.0)]
    first = [t["mean_insertion_angle"] for t in rs.traits(back)]
    assert [float(r["mean_insertion_angle_deg"]) for r in rows] == pytest.approx(want, rel=1e-12)
    assert want != pytest.approx(first, rel=1e-6)  # the option changes what is measured


def test_angle_window_needs_one_unit(tmp_path):
    d = tmp_path / "mixed"
    d.mkdir()
    write_rsml(synthetic_roots(1, seed=1), d / "mm.rsml", unit="mm")
    px = [dataclasses.replace(r, metadata={"unit": "pixel"}) for r in synthetic_roots(1, seed=2)]
    write_rsml(px, d / "px.rsml")
    proc = run_cli("traits", d, "--angle-window", 5, "--out", tmp_path / "o")
    assert_one_line_error(proc, "--angle-window 5", "different units", "--unit")


def test_traits_samples_subsamples_evenly(tmp_path):
    out = tmp_path / "out"
    proc = run_cli(
        "traits", "--synthetic", 5, "--condition", "control", "--condition", "drought", "--samples", 3, "--out", out
    )
    assert proc.returncode == 0, proc.stderr
    with open(out / "traits.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # 10 roots (5 control, then 5 drought); the evenly spread ones are numbers 0, 4 and 9.
    assert [r["name"] for r in rows] == ["control_s0_000", "control_s0_004", "drought_s0_004"]
    assert {r["condition"] for r in rows} == {"control", "drought"}


@pytest.mark.parametrize("option", [["--weights", "1,1,1"], ["--points", "50"], ["--laterals", "3"], ["--float64"]])
def test_traits_refuses_options_of_the_distance(option, tmp_path, capsys):
    # traits measures roots without comparing them: a metric option would be silently ignored.
    from rootshape_jax._cli import main

    assert main(["traits", "--synthetic", "2", *option, "--out", str(tmp_path / "o")]) == 2
    assert f"unrecognized arguments: {option[0]}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------------------------
# Bad input: one clear line, non-zero exit code, no traceback


def test_missing_path(tmp_path):
    proc = run_cli("distances", tmp_path / "nope.rsml", "--out", tmp_path / "o")
    assert_one_line_error(proc, "nope.rsml", "no such file")


@pytest.mark.parametrize(
    "content, fragment",
    [("this is not xml", "not well-formed XML"), ("<rsml><metadata/></rsml>", "no <scene>")],
)
def test_bad_rsml_file(tmp_path, content, fragment):
    bad = tmp_path / "bad.rsml"
    bad.write_text(content)
    proc = run_cli("distances", bad, "--out", tmp_path / "o")
    assert_one_line_error(proc, "bad.rsml", fragment)


@pytest.mark.parametrize("fixture", ["malformed.rsml", "no_geometry.rsml"])
def test_unreadable_fixture_files(tmp_path, fixture):
    proc = run_cli("mean", DATA / fixture, "--out", tmp_path / "o")
    assert_one_line_error(proc, fixture)


def test_partly_bad_file_warns_in_one_line_and_goes_on(tmp_path):
    proc = run_cli("traits", DATA / "bad_roots.rsml", "--out", tmp_path / "o")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    warn = [ln for ln in proc.stderr.splitlines() if ln.startswith("rootshape: warning:")]
    assert len(warn) == 1 and "bad_roots.rsml" in warn[0]
    assert (tmp_path / "o" / "traits.csv").exists()


def test_unsupported_file_type(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("hello")
    assert_one_line_error(run_cli("cluster", f, "--out", tmp_path / "o"), "notes.txt", "unsupported file type")


def test_blank_image(tmp_path):
    from skimage.io import imsave

    img = tmp_path / "blank.png"
    imsave(img, np.full((40, 40), 255, np.uint8), check_contrast=False)
    assert_one_line_error(run_cli("distances", img, "--out", tmp_path / "o"), "blank.png")


def test_empty_folder_and_no_input(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_one_line_error(run_cli("pca", empty, "--out", tmp_path / "o"), "empty", "no RSML files")
    assert_one_line_error(run_cli("distances", "--out", tmp_path / "o"), "no input")
    # A folder of folders: they are named, with what to do.
    (empty / "plate_a").mkdir()
    assert_one_line_error(run_cli("traits", empty, "--out", tmp_path / "o"), "subfolders (plate_a)", "name them")


def test_too_few_roots(rsml_files, tmp_path):
    proc = run_cli("distances", rsml_files / "control.rsml", "--samples", 1, "--out", tmp_path / "o")
    assert_one_line_error(proc, "at least 2 roots")


def test_geodesic_root_index_out_of_range(rsml_files, tmp_path):
    f = rsml_files / "control.rsml"
    proc = run_cli("geodesic", f, f, "--root-b", 5, "--out", tmp_path / "o")
    assert_one_line_error(proc, "control.rsml", "root number 5", "give 0 to")


def test_out_is_a_file(rsml_files, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    assert_one_line_error(run_cli("traits", rsml_files, "--out", f), "not a folder")


def test_unknown_condition(tmp_path):
    proc = run_cli("traits", "--synthetic", 2, "--condition", "flooded", "--out", tmp_path / "o")
    assert_one_line_error(proc, "flooded")
    # The run created its output folder and wrote nothing: no empty folder stays behind; a
    # folder that was there before stays.
    assert not (tmp_path / "o").exists()
    (tmp_path / "mine").mkdir()
    proc = run_cli("traits", "--synthetic", 2, "--condition", "flooded", "--out", tmp_path / "mine")
    assert_one_line_error(proc, "flooded")
    assert (tmp_path / "mine").is_dir()
    # The parents it created for --out go too (an audit found nest/a left behind), not more.
    from rootshape_jax._cli import main

    for out, gone, kept in (
        (tmp_path / "n" / "a" / "b", tmp_path / "n", tmp_path),
        (tmp_path / "mine" / "x" / "y", tmp_path / "mine" / "x", tmp_path / "mine"),
    ):
        assert main(["traits", "--synthetic", "2", "--condition", "flooded", "--quiet", "--out", str(out)]) == 1
        assert not gone.exists() and kept.is_dir()


def test_bad_requested_csv_fails_before_computing(rsml_files, tmp_path):
    req = tmp_path / "req.csv"
    req.write_text("main_length,foo\n1,2\n")
    proc = run_cli("regress", rsml_files, "--requested", req, "--out", tmp_path / "o")
    assert_one_line_error(proc, "req.csv", "mean_lateral_length")


@pytest.mark.slow
def test_regress_says_when_requested_traits_are_out_of_range_or_missed(tmp_path):
    """Requested traits outside the inputs' range are named; a trait the predicted roots miss by
    more than REGRESSION_MISS on average is reported, and only then (checked against the CSV)."""
    from rootshape_jax._cli._steps import REGRESSION_MISS

    req = tmp_path / "req.csv"
    # The 6 synthetic roots' ranges: main 95-131 mm, mean lateral 26-41 mm, std 2.2-6.2 mm.
    req.write_text("main_length,mean_lateral_length,std_lateral_length\n110,30,4\n110,900,4\n")
    out = tmp_path / "o"
    proc = run_cli(
        "regress", "--synthetic", 6, "--points", 20, "--laterals", 4, "--max-steps", 3, "--requested", req,
        "--quiet", "--out", out,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "outside the inputs' range: mean_lateral_length 900" in proc.stderr, proc.stderr
    assert "mean_lateral_length 30 " not in proc.stderr and "main_length 110" not in proc.stderr
    with open(out / "predicted_roots.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for name in ("main_length", "mean_lateral_length", "std_lateral_length"):
        asked = np.array([float(r[f"requested_{name}_mm"]) for r in rows])
        got = np.array([float(r[f"measured_{name}_mm"]) for r in rows])
        missed = np.mean(np.abs(got - asked) / asked) > REGRESSION_MISS
        assert (f"miss the requested {name.replace('_', ' ')}" in proc.stderr) == missed, (name, proc.stderr)


def test_geodesic_steps_below_two_is_a_usage_error(rsml_files, capsys):
    from rootshape_jax._cli import main

    f = str(rsml_files / "control.rsml")
    assert main(["geodesic", f, f, "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert "--steps" in err and "at least 2 roots" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "option",
    [
        ["--weights", "1,2"],
        ["--weights", "a,b,c"],
        ["--weights", "-1,1,1"],
        ["--weights", "0,0,0"],
        ["--unit", "furlong"],
        ["--points", "1"],
        ["--samples", "0"],
    ],
)
def test_bad_option_values_are_usage_errors(rsml_files, option, capsys):
    # argparse rejects these before anything runs; in-process keeps the test fast.
    from rootshape_jax._cli import main

    assert main(["distances", str(rsml_files), *option]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error: argument" in err


def test_unknown_command(capsys):
    from rootshape_jax._cli import main

    assert main(["frobnicate"]) == 2
    assert "invalid choice" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Helpers of the command line (in-process)


def test_limit_laterals_keeps_the_longest_in_order():
    from rootshape_jax import limit_laterals

    root = synthetic_roots(1, seed=3)[0]
    kept = limit_laterals(root, 3)
    lengths = root.lateral_lengths
    top = np.sort(np.argsort(-lengths)[:3])
    assert kept.n_laterals == 3
    for k, i in enumerate(top):
        np.testing.assert_array_equal(kept.laterals[k], root.laterals[i])
        assert kept.attach[k] == root.attach[i]
    assert limit_laterals(root, 100) is root


def test_subsample_is_even_and_ordered():
    from rootshape_jax._cli._inputs import subsample

    items = list(range(53))
    assert subsample(items, 6) == [0, 10, 21, 31, 42, 52]
    assert subsample(items, 100) == items
    assert subsample(items, None) == items


def test_scale_tree_scales_about_the_base():
    from rootshape_jax import scale_tree

    tree = rs.batch(synthetic_roots(2, seed=0), n_points=20)
    scaled = scale_tree(tree, [2.0, 0.5])
    o = np.asarray(tree.main)[:, :1]
    np.testing.assert_allclose(np.asarray(scaled.main)[0], o[0] + 2.0 * (np.asarray(tree.main)[0] - o[0]))
    np.testing.assert_allclose(np.asarray(scaled.laterals)[1], o[1] + 0.5 * (np.asarray(tree.laterals)[1] - o[1]))
    np.testing.assert_array_equal(np.asarray(scaled.mask), np.asarray(tree.mask))


def test_cluster_numbers_agree_in_csv_figure_and_table(tmp_path, monkeypatch):
    """clusters.csv, the dendrogram's cluster rows (label, size, colour) and the HTML table all
    number the clusters the same way (one `Clustering`)."""
    import argparse

    import matplotlib.colors as mcolors

    import rootshape_jax.plot as rplot
    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._report import Output
    from rootshape_jax._cli._steps import Context, run_cluster

    roots = [r for c in ("control", "drought", "high_nitrate") for r in synthetic_roots(4, condition=c, seed=5)]
    args = argparse.Namespace(laterals=4, points=12, normalise_scale=True, clusters=3, linkage="average")
    ctx = Context(prepare(roots, args))
    # Distances between random points with three well-separated groups (no registration).
    rng = np.random.default_rng(0)
    x = rng.normal(size=(12, 3)) + np.repeat(np.array([[0, 0, 0], [9, 0, 0], [0, 9, 0]]), 4, axis=0)
    x = x[rng.permutation(12)]
    ctx.distances = np.linalg.norm(x[:, None] - x[None], axis=-1)

    drawn = {}
    original = rplot.plot_dendrogram

    def spy(*a, **kw):
        drawn["fig"], drawn["axes"] = original(*a, **kw)
        return drawn["fig"], drawn["axes"]

    monkeypatch.setattr(rplot, "plot_dendrogram", spy)
    out = Output(tmp_path / "o", args)
    run_cluster(ctx, out, args)

    with open(tmp_path / "o" / "clusters.csv", newline="") as f:
        csv_number = {r["root"]: int(r["cluster"]) for r in csv.DictReader(f)}
    assert set(csv_number.values()) == {1, 2, 3}
    seen = set()
    for row in drawn["axes"]["roots"]:
        label = row[0].get_ylabel()
        m = re.fullmatch(r"cluster (\d+)\nn = (\d+)", label)
        assert m, label
        number, size = int(m.group(1)), int(m.group(2))
        seen.add(number)
        assert size == sum(v == number for v in csv_number.values())
        for ax in row:  # every root drawn in this row is in this cluster in the CSV
            assert csv_number[ax.get_title()] == number, (ax.get_title(), number)
        assert mcolors.to_hex(row[0].yaxis.label.get_color()) == drawn["axes"]["cluster_colors"][number - 1]
    assert seen == {1, 2, 3}
    assert len(set(drawn["axes"]["cluster_colors"])) == 3
    # The condition-by-cluster table on the page uses the same numbers.
    table = out.sections[0].items[0].html
    assert all(f"<th>cluster {g}</th>" in table for g in (1, 2, 3)) and "cluster 0" not in table
    cond = {r.name: r.metadata["condition"] for r in ctx.pop.roots}
    cells = re.findall(r"<tr><td>(\w+)</td>((?:<td>\d+</td>)+)</tr>", table)
    for condition, counts in cells:
        counts = [int(c) for c in re.findall(r"\d+", counts)]
        assert counts == [sum(cond[n] == condition and csv_number[n] == g for n in csv_number) for g in (1, 2, 3)]
    assert len(cells) == 3


# --------------------------------------------------------------------------------------------
# End to end (compiles registrations: slow)


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.images: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "a" and "href" in a:
            self.links.append(a["href"])
        if tag == "img":
            self.images.append(a["src"])


@pytest.mark.slow
def test_demo_tiny_index_links_exist(tmp_path):
    out = tmp_path / "demo"
    proc = run_cli(
        "demo",
        "--samples",
        6,
        "--points",
        30,
        "--laterals",
        4,
        "-n",
        4,
        "--max-steps",
        5,
        "--plants",
        3,
        "--out",
        out,
        timeout=900,  # ~150 s on a quiet 2-core machine; a hang fails with its stacks
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert str(out.resolve()) in proc.stdout
    index = out / "index.html"
    parser = _Links()
    parser.feed(index.read_text(encoding="utf-8"))
    assert len(parser.images) >= 9  # every analysis has at least one figure
    for ref in parser.links + parser.images:
        assert (out / ref).is_file(), ref
        assert (out / ref).stat().st_size > 0, ref
    for img in parser.images:
        assert (out / img).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", img
    # Every file written is shown or linked.
    written = {p.name for p in out.iterdir()} - {"index.html"}
    linked = set(parser.links) | set(parser.images)
    steps = {n for n in written if n.startswith("geodesic_step_")}
    assert written - steps <= linked, written - linked
    # Every file is one the overwrite check knows (a rerun into this folder is refused).
    from rootshape_jax._cli._report import is_output_name

    assert all(is_output_name(n) for n in written | {"index.html"}), written
    # Timings of every step are on the page.
    text = index.read_text(encoding="utf-8")
    for step in ("Distance matrix", "Mean root", "Modes of variation", "Clusters"):
        assert re.search(rf"{step}[^<]*<span class='time'>\(\d+\.\d s\)", text), step
    # The outputs are what they claim.
    names, D = read_matrix(out / "distances.csv")
    assert len(names) == 6
    np.testing.assert_allclose(D, D.T)
    assert np.all(np.diag(D) == 0) and np.all(D[~np.eye(6, dtype=bool)] > 0)
    assert len(read_rsml(out / "mean.rsml")) == 1
    assert len(read_rsml(out / "random_roots.rsml")) == 4
    with open(out / "clusters.csv", newline="") as f:
        clusters = list(csv.DictReader(f))
    assert [c["root"] for c in clusters] == names
    assert {c["condition"] for c in clusters} == {"control", "drought", "high_nitrate"}


@pytest.mark.slow
def test_distances_match_the_library(rsml_files, tmp_path):
    """The CSV matrix is the library's pairwise_distances of the same roots, same settings."""
    out = tmp_path / "o"
    proc = run_cli(
        "distances",
        rsml_files,
        "--points",
        24,
        "--laterals",
        3,
        "--weights",
        "0.1,1,0.5",
        "--float64",
        "--quiet",
        "--out",
        out,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "distances.png").read_bytes()[:4] == b"\x89PNG"
    names, D = read_matrix(out / "distances.csv")
    from rootshape_jax import limit_laterals

    roots = read_rsml(rsml_files / "control.rsml") + read_rsml(rsml_files / "drought.rsml")
    roots = [limit_laterals(r, 3) for r in roots]
    tree = rs.batch(roots, n_points=24, normalise_scale=True)
    ref = np.asarray(rs.pairwise_distances(tree, weights=rs.Weights(0.1, 1.0, 0.5), progress=False))
    np.testing.assert_allclose(D, ref, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_geodesic_end_to_end(rsml_files, tmp_path):
    out = tmp_path / "o"
    a, b = rsml_files / "control.rsml", rsml_files / "drought.rsml"
    proc = run_cli(
        "geodesic", a, b, "--root-b", 1, "--steps", 5, "--points", 30, "--laterals", 3, "--quiet", "--out", out
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "geodesic.png").read_bytes()[:4] == b"\x89PNG"
    steps = [read_rsml(out / f"geodesic_step_{i:02d}.rsml") for i in range(5)]
    assert all(len(s) == 1 for s in steps)
    ra, rb = read_rsml(a)[0], read_rsml(b)[1]
    # Scale-normalised shapes are scaled back: the ends have the inputs' main-root lengths
    # (up to resampling to 30 points), and the unit is kept.
    assert steps[0][0].main_length == pytest.approx(ra.main_length, rel=0.02)
    assert steps[-1][0].main_length == pytest.approx(rb.main_length, rel=0.02)
    assert steps[0][0].metadata["unit"] == ra.metadata["unit"] == "mm"
    assert "elastic distance" in proc.stdout


# --------------------------------------------------------------------------------------------
# Reliability (issues 17 and 18): folders with bad files, earlier results, atomic writes,
# CSV injection, Ctrl-C

SHARED_RSML = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rsml"


@pytest.fixture
def folder_with_bad_files(tmp_path) -> Path:
    """Two good RSML files, one that is not XML, one without geometry, one partly bad."""
    folder = tmp_path / "mixed"
    folder.mkdir()
    write_rsml(synthetic_roots(2, condition="control", seed=1), folder / "a_good.rsml")
    (folder / "b_notxml.rsml").write_text("this is not xml")
    (folder / "c_nogeom.rsml").write_text((DATA / "no_geometry.rsml").read_text())
    (folder / "d_partly.rsml").write_text((DATA / "bad_roots.rsml").read_text())
    write_rsml(synthetic_roots(1, condition="drought", seed=2), folder / "e_good.rsml")
    return folder


def test_folder_skips_unreadable_files_and_summarises(folder_with_bad_files, tmp_path):
    out = tmp_path / "o"
    proc = run_cli("traits", folder_with_bad_files, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    # One line per problem file, naming it with its reason.
    assert len([ln for ln in lines if "b_notxml.rsml" in ln]) == 1
    assert len([ln for ln in lines if "c_nogeom.rsml" in ln]) == 1
    assert len([ln for ln in lines if "d_partly.rsml" in ln]) == 1
    # ... and one line saying the files mix units (the synthetic files are in mm, the others in pixels).
    assert len(lines) == 4 and "different units (mm, pixel)" in lines[3], proc.stderr
    assert any("skipped" in ln and "b_notxml.rsml" in ln and "not well-formed XML" in ln for ln in lines)
    # The summary ends the run: 2 + 2 (partly bad: ok1, ok2) + 1 roots from 3 files.
    summary = proc.stdout.strip().splitlines()[-1]
    assert summary == (
        "read 5 root system(s) from 3 file(s); skipped 2: b_notxml.rsml (not well-formed XML), "
        "c_nogeom.rsml (nothing readable)."
    ), summary
    with open(out / "traits.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 5
    # Full detail goes to the log: every skipped part of the partly bad file, each skip reason.
    log = (out / "rootshape.log").read_text()
    assert "root id='nan'" in log and "root id='onlyspline'" in log
    assert "b_notxml.rsml" in log and "c_nogeom.rsml" in log


def test_a_run_stopped_after_logging_skipped_files_names_the_log(folder_with_bad_files, tmp_path, monkeypatch, capsys):
    # The log of skipped files is written as soon as the files are read: a run stopped before
    # its first result leaves a folder holding only rootshape.log, and says so (it said
    # nothing). A plain rerun is not refused by a folder holding only a log.
    from rootshape_jax._cli import _commands, main

    def fail(*args, **kwargs):
        raise ValueError("simulated failure before the first result")

    monkeypatch.setattr(_commands, "run_traits", fail)
    out = tmp_path / "o"
    assert main(["traits", str(folder_with_bad_files), "--quiet", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["rootshape.log"]
    assert f"{out} holds only rootshape.log, the full reasons for the inputs skipped (a rerun" in err, err
    monkeypatch.undo()
    assert main(["traits", str(folder_with_bad_files), "--quiet", "--out", str(out)]) == 0
    assert (out / "traits.csv").exists()


def test_strict_stops_at_first_bad_file(folder_with_bad_files, tmp_path):
    proc = run_cli("traits", folder_with_bad_files, "--strict", "--out", tmp_path / "o")
    assert_one_line_error(proc, "b_notxml.rsml", "not well-formed XML")


def test_folder_of_only_bad_files_fails_naming_them(tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "x.rsml").write_text("nope")
    (folder / "y.rsml").write_text("<rsml><metadata/></rsml>")
    proc = run_cli("traits", folder, "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 4 and lines[0].startswith("rootshape: warning: skipped") and "x.rsml" in lines[0]
    assert lines[2] == (
        "rootshape: error: no readable roots: every file was skipped: x.rsml (not well-formed "
        "XML), y.rsml (no <scene> element). Fix or remove these files."
    )
    # The log of the skipped files is the one file left, and is named with what it holds.
    assert "o holds only rootshape.log, the full reasons for the inputs skipped" in lines[3], lines


@pytest.mark.skipif(not SHARED_RSML.is_dir(), reason="shared RSML data not present")
def test_real_folder_with_a_file_without_geometry(tmp_path):
    import shutil

    folder = tmp_path / "smartroot"
    shutil.copytree(SHARED_RSML / "smartroot", folder)
    proc = run_cli("traits", folder, "--out", tmp_path / "o")
    assert proc.returncode == 0, proc.stderr
    warn = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    # maize.rsml (17 parts skipped) and root_ramifie.rsml, each summarised (no per-root detail).
    assert len(warn) == 2 and not any("root id=" in ln for ln in warn), warn
    assert any("root_ramifie.rsml" in ln and "skipped" in ln for ln in warn)
    assert "skipped 1: root_ramifie.rsml (nothing readable)" in proc.stdout


def test_earlier_results_are_not_overwritten(rsml_files, tmp_path):
    out = tmp_path / "o"
    assert run_cli("traits", rsml_files / "control.rsml", "--out", out).returncode == 0
    before = (out / "traits.csv").read_bytes()
    proc = run_cli("traits", rsml_files, "--out", out)
    assert_one_line_error(proc, str(out), "traits.csv", "--overwrite")
    assert (out / "traits.csv").read_bytes() == before
    proc = run_cli("traits", rsml_files, "--out", out, "--overwrite")
    assert proc.returncode == 0, proc.stderr
    with open(out / "traits.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 4
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def _output(folder, *, overwrite):
    import argparse

    from rootshape_jax._cli._report import Output

    return Output(folder, argparse.Namespace(overwrite=overwrite))


def test_writes_replace_a_symlink_never_write_through_it(tmp_path):
    from rootshape_jax._cli._common import CLIError

    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    folder = tmp_path / "o"
    folder.mkdir()
    (folder / "notes.txt").write_text("not a result")  # unrelated files do not block a run
    (folder / "x.csv").symlink_to(target)
    out = _output(folder, overwrite=False)
    with pytest.raises(CLIError, match="x.csv"):
        out.write("x.csv", lambda p: p.write_text("new"))
    out = _output(folder, overwrite=True)
    out.write("x.csv", lambda p: p.write_text("new"))
    assert target.read_text() == "keep me"
    assert not (folder / "x.csv").is_symlink() and (folder / "x.csv").read_text() == "new"
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "x.csv"]


def test_full_disk_names_the_file_and_keeps_the_earlier_one(rsml_files, tmp_path, monkeypatch, capsys):
    import errno

    import rootshape_jax._cli._report as report
    from rootshape_jax._cli import main

    out = tmp_path / "o"
    out.mkdir()
    (out / "traits.csv").write_text("earlier results\n")

    class FullDisk:
        def __init__(self, f, **kw):
            pass

        def writerow(self, row):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report.csv, "writer", FullDisk)
    assert main(["traits", str(rsml_files), "--out", str(out), "--overwrite", "--quiet"]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("rootshape: error: "), err
    assert str(out / "traits.csv") in err[0] and "No space left on device" in err[0]
    assert "earlier traits.csv is unchanged" in err[0]
    assert (out / "traits.csv").read_text() == "earlier results\n"
    assert sorted(p.name for p in out.iterdir()) == ["traits.csv"]  # no temporary file left
    # The bare form OSError(errno.ENOSPC) is explained too.
    monkeypatch.setattr(FullDisk, "writerow", lambda self, row: (_ for _ in ()).throw(OSError(errno.ENOSPC)))
    assert main(["traits", str(rsml_files), "--out", str(out), "--overwrite", "--quiet"]) == 1
    assert "No space left on device" in capsys.readouterr().err


@pytest.mark.parametrize(
    "text, expected",
    [
        ('=HYPERLINK("http://x","y")', '\'=HYPERLINK("http://x","y")'),
        ("+1+2", "'+1+2"),
        ("-2+3", "'-2+3"),
        ("@SUM(A1)", "'@SUM(A1)"),
        ("\tx", "'\tx"),
        ("\rx", "'\rx"),
        ("-1.5", "-1.5"),
        ("-3", "-3"),
        ("+2e-3", "+2e-3"),
        ("plain", "plain"),
        ("a=b", "a=b"),
    ],
)
def test_csv_cells_are_escaped_like_owasp(text, expected):
    from rootshape_jax._cli._report import cell

    assert cell(text) == expected
    assert cell(-1.5) == "-1.5" and cell(np.int64(-3)) == -3


def test_formula_root_labels_are_escaped_in_csv(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    roots = synthetic_roots(2, seed=0)
    import dataclasses

    roots = [
        dataclasses.replace(roots[0], name='=HYPERLINK("http://evil","x")'),
        dataclasses.replace(roots[1], name="-7"),
    ]
    write_rsml(roots, folder / "f.rsml")
    out = tmp_path / "o"
    proc = run_cli("traits", folder, "--out", out)
    assert proc.returncode == 0, proc.stderr
    with open(out / "traits.csv", newline="") as f:
        names = [r["name"] for r in csv.DictReader(f)]
    assert names == ['\'=HYPERLINK("http://evil","x")', "-7"]


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="watches /proc/PID/maps for JAX loading")
def test_ctrl_c_while_the_program_starts_ends_it(tmp_path):
    """From an audit: Ctrl-C in the first ~2 s (while the package imports JAX, before `main`
    installs its handler) printed a traceback, or was swallowed by a JAX garbage-collection
    callback and the run went on to write traits.csv. Now it ends with 130 and one line."""
    import signal
    import time

    write_rsml(synthetic_roots(2, seed=1), tmp_path / "r.rsml")
    for delay in (0.0, 0.3):
        out = tmp_path / f"o{delay}"
        p = subprocess.Popen(
            [sys.executable, "-m", "rootshape_jax", "traits", str(tmp_path / "r.rsml"), "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        # The handler is in place before the package imports JAX: wait until jaxlib is mapped.
        deadline = time.monotonic() + 60
        maps = Path(f"/proc/{p.pid}/maps")
        while time.monotonic() < deadline and p.poll() is None and "jaxlib" not in maps.read_text(errors="replace"):
            time.sleep(0.005)
        time.sleep(delay)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
        err = err.decode(errors="replace")
        assert p.returncode == 130, (delay, p.returncode, err[-2000:])
        assert "Traceback" not in err and "Exception ignored" not in err and "rootshape: interrupted" in err
        assert not (out / "traits.csv").exists()


@pytest.mark.slow
def test_ctrl_c_during_distances_exits_cleanly(tmp_path):
    """SIGINT while the distance matrix compiles or runs: exit code 130 every time, never a
    death by signal (the old code died by SIGSEGV when interrupted during compilation)."""
    import os
    import random
    import select
    import signal
    import time

    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}  # compile for real
    env["PYTHONFAULTHANDLER"] = "1"  # SIGABRT dumps every thread's stack: where a stuck run waits
    rng = random.Random(18)
    for attempt in range(3):
        out = tmp_path / f"o{attempt}"
        p = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "rootshape_jax",
                "distances",
                "--synthetic",
                "4",
                "--condition",
                "control",
                "--condition",
                "drought",
                "--points",
                "20",
                "--laterals",
                "3",
                "--out",
                str(out),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
        )
        # The bar shows after ~5 s here; in CI once it did not (stuck for 120 s, or the run died
        # without a word), so wait longer and, if it never shows, report how the run ended or,
        # with faulthandler's dump, where it was stuck.
        seen, started = b"", time.monotonic()
        deadline = started + 300
        while b"/28 " not in seen and time.monotonic() < deadline:  # the progress bar is shown
            if select.select([p.stderr], [], [], 1.0)[0]:
                chunk = os.read(p.stderr.fileno(), 4096)
                if not chunk:
                    break
                seen += chunk
        if b"/28 " not in seen:
            p.send_signal(signal.SIGABRT)
            _, err = p.communicate(timeout=60)
            waited = time.monotonic() - started
            pytest.fail(
                f"attempt {attempt}: no progress bar after {waited:.0f} s (exit code {p.returncode})\n"
                + (seen + err).decode(errors="replace")
            )
        time.sleep(rng.uniform(1.0, 8.0))
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
        err = (seen + err).decode(errors="replace")
        assert p.returncode == 130, (attempt, p.returncode, err[-2000:])
        assert "Traceback" not in err and "rootshape: interrupted" in err
        assert not (out / "distances.csv").exists()
        # Nothing half-written; a folder the run made and left empty is removed.
        assert not out.exists() or not [q for q in out.iterdir() if q.name.endswith(".tmp")]


@pytest.mark.slow
def test_store_resumes_after_ctrl_c(tmp_path):
    """--store keeps the finished blocks of an interrupted run; the rerun computes only the
    missing ones and the matrix equals the library's."""
    pytest.importorskip("dask.distributed")
    import signal
    import time

    store, out = tmp_path / "store", tmp_path / "o"
    cmd = [
        sys.executable,
        "-m",
        "rootshape_jax",
        "distances",
        "--synthetic",
        "10",
        "--condition",
        "control",
        "--condition",
        "drought",
        "--points",
        "16",
        "--laterals",
        "3",
        "--float64",
        "--quiet",
        "--store",
        str(store),
        "--out",
        str(out),
    ]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 600
    while not list(store.glob("block_*.npz")) and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err.decode(errors="replace")[-2000:]  # 190 pairs: 3 blocks of 64
    kept = sorted(q.name for q in store.glob("block_*.npz"))
    assert 1 <= len(kept) < 3, kept
    # The message says that the same command resumes (an audit found only the generic line).
    block = f"{len(kept)} block{'s' if len(kept) > 1 else ''}"
    assert f"--store {store} keeps the {block} of distances finished so far" in err.decode(errors="replace")
    assert not out.exists() or not (out / "distances.csv").exists()

    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"{len(kept)} of 3 blocks of 64 pairs read from earlier runs, {3 - len(kept)} computed" in proc.stdout
    names, D = read_matrix(out / "distances.csv")
    roots = [r for c in ("control", "drought") for r in synthetic_roots(10, condition=c, seed=0)]
    roots = [rs.limit_laterals(r, 3) for r in roots]
    assert names == [r.name for r in roots]
    ref = np.asarray(rs.pairwise_distances(rs.batch(roots, n_points=16, normalise_scale=True), progress=False))
    np.testing.assert_allclose(D, ref, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_thickness_weight_from_the_command_line(tmp_path):
    """--weights takes a fourth value, the thickness weight: with diameters in the files the CSV
    matrix is the library's with Weights(..., thickness=λr), and it differs from λr = 0."""
    rng = np.random.default_rng(4)
    roots = []
    for i, r in enumerate(synthetic_roots(3, condition="control", seed=2)):
        taper = lambda pts, r0: r0 * (1.2 - np.linspace(0, 1, len(pts)))  # noqa: E731
        roots.append(
            dataclasses.replace(
                r,
                main_radius=taper(r.main, 0.5 + 0.2 * i),
                lateral_radii=tuple(taper(lat, 0.2 + 0.1 * rng.random()) for lat in r.laterals),
            )
        )
    write_rsml(roots, tmp_path / "thick.rsml")
    mats = {}
    for w in ("0.02,1,1,0.5", "0.02,1,1"):
        out = tmp_path / w.replace(",", "_")
        proc = run_cli(
            "distances",
            tmp_path / "thick.rsml",
            "--points",
            24,
            "--laterals",
            3,
            "--weights",
            w,
            "--float64",
            "--quiet",
            "--out",
            out,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        mats[w] = read_matrix(out / "distances.csv")[1]
    from rootshape_jax import limit_laterals

    back = [limit_laterals(r, 3) for r in read_rsml(tmp_path / "thick.rsml")]
    tree = rs.batch(back, n_points=24, normalise_scale=True)
    assert tree.main_radius is not None
    ref = np.asarray(rs.pairwise_distances(tree, weights=rs.Weights(0.02, 1, 1, 0.5), progress=False))
    np.testing.assert_allclose(mats["0.02,1,1,0.5"], ref, rtol=1e-6, atol=1e-9)
    assert not np.allclose(mats["0.02,1,1,0.5"], mats["0.02,1,1"])


# --------------------------------------------------------------------------------------------
# Progress (issue 17, item 6): bars redrawn at least every few seconds


def test_heartbeat_redraws_a_bar_that_gets_no_update():
    """A bar waiting for a long block (or a compilation) is still redrawn, so its elapsed time
    moves; a step without a bar of its own gets one (`ticking`), silent with --quiet."""
    import io
    import time
    from types import SimpleNamespace

    from tqdm import tqdm

    from rootshape_jax._cli._common import heartbeat, ticking

    def redraws(text: str) -> int:
        return text.count("\r")

    sink = io.StringIO()
    with heartbeat(0.05):
        bar = tqdm(total=3, desc="blocks", file=sink, mininterval=0)
        time.sleep(0.2)
        quiet_redraws = redraws(sink.getvalue())
        time.sleep(0.6)
        bar.close()
    # Drawn once when made; then about every 0.05 s although update() was never called.
    assert redraws(sink.getvalue()) - quiet_redraws >= 4, sink.getvalue()
    with heartbeat(0.05):
        with ticking(SimpleNamespace(quiet=True), "silent") as bar:
            assert bar.disable
        with ticking(SimpleNamespace(quiet=False), "working") as bar:
            assert not bar.disable and bar.total is None


def test_a_run_that_fails_midway_says_what_it_left_in_out(tmp_path, monkeypatch, capsys):
    # A step failing after traits.csv was written: the error line, then which complete files
    # the folder holds and that a rerun needs --overwrite (a plain rerun is refused).
    from rootshape_jax._cli import _commands, main

    def fail(*args, **kwargs):
        raise ValueError("simulated failure after the traits were written")

    monkeypatch.setattr(_commands, "_finish", fail)
    out = tmp_path / "o"
    assert main(["traits", "--synthetic", "2", "--quiet", "--out", str(out)]) == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines[0] == "rootshape: error: simulated failure after the traits were written", lines
    assert len(lines) == 2 and str(out) in lines[1] and "traits.csv" in lines[1], lines
    assert "--overwrite" in lines[1] and "stopped before its end" in lines[1], lines
    assert (out / "traits.csv").exists()
    monkeypatch.undo()
    assert main(["traits", "--synthetic", "2", "--quiet", "--out", str(out)]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert main(["traits", "--synthetic", "2", "--quiet", "--overwrite", "--out", str(out)]) == 0
    # An --overwrite run stopped midway: the earlier run's files it had not yet replaced are
    # named too, not only the new ones (an audit found an old index.html beside new results,
    # with "holds only the 1 file written before").
    (out / "distances.csv").write_text("x\n")  # as left by another command's earlier run
    earlier = sorted(p.name for p in out.iterdir() if p.name not in ("traits.csv", "rootshape.log"))
    capsys.readouterr()
    monkeypatch.setattr(_commands, "_finish", fail)
    assert main(["traits", "--synthetic", "3", "--quiet", "--overwrite", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "holds only the 1 file written before (traits.csv)" in err, err
    assert f"of an earlier run that this run had not replaced ({', '.join(earlier[:6])}" in err, err


def test_a_folder_holding_only_a_log_is_not_refused(tmp_path, capsys):
    # A run killed (SIGTERM) before its first result leaves only rootshape.log: no result to
    # protect, so the next run into that folder goes ahead (it was refused).
    from rootshape_jax._cli import main

    out = tmp_path / "o"
    out.mkdir()
    (out / "rootshape.log").write_text("killed\n")
    assert main(["traits", "--synthetic", "2", "--quiet", "--out", str(out)]) == 0
    log = out / "rootshape.log"  # the stale log went; this run writes its own only if it logs
    assert (out / "traits.csv").exists() and (not log.exists() or "killed" not in log.read_text())


def test_overwrite_names_earlier_results_it_did_not_replace(tmp_path, capsys):
    # --overwrite into a folder of another command's results: the files this run does not write
    # stay, so the run says which, instead of leaving them to pass for its own.
    from rootshape_jax._cli import main

    out = str(tmp_path / "o")
    assert main(["traits", "--synthetic", "3", "--out", out, "--quiet"]) == 0
    assert main(["traits", "--synthetic", "2", "--out", out, "--quiet", "--overwrite"]) == 0
    assert "earlier run" not in capsys.readouterr().err  # everything rewritten
    (tmp_path / "o" / "notes.txt").write_text("mine")  # not a result: never named
    assert main(["distances", "--synthetic", "2", "--points", "12", "--out", out, "--quiet", "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert "also holds 1 file of an earlier run that this run did not replace (traits.csv)" in err
    assert "notes.txt" not in err and (tmp_path / "o" / "traits.csv").exists()


@pytest.mark.parametrize("dim", [2, 3])
def test_generated_roots_are_turned_upright_like_the_inputs(dim):
    # The mean's orientation is the solver's starting root's, moved by the fit; the CLI turns
    # the mean (and the roots built on it) about their bases so the main root points the
    # inputs' mean direction. Shapes, bases and attachments are unchanged.
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from rootshape_jax._cli._inputs import turn

    rng = np.random.default_rng(dim)

    def rot(deg):
        if dim == 2:
            t = np.radians(deg)
            return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        return Rotation.from_rotvec(np.radians(deg) * np.array([0.6, 0.0, 0.8])).as_matrix()

    def turned_root(r, deg, shift):
        R = rot(deg)
        f = lambda x: (np.asarray(x) - r.main[0]) @ R.T + shift  # noqa: E731
        return dataclasses.replace(r, main=f(r.main), laterals=tuple(f(x) for x in r.laterals))

    base = synthetic_roots(5, seed=2, dim=dim)
    inputs = [turned_root(r, a, rng.normal(size=dim) * 50) for r, a in zip(base, [10, 15, 20, 25, 30])]
    tree = rs.batch(inputs, n_points=20)
    pop = SimpleNamespace(tree=tree)
    mean = rs.unstack(rs.batch([turned_root(base[0], -40, np.zeros(dim))], n_points=20))[0]
    R = rs.upright_rotation(mean, pop.tree)
    out = turn(mean, R)
    chords = np.asarray(tree.main)[:, -1] - np.asarray(tree.main)[:, 0]
    target = np.sum(chords / np.linalg.norm(chords, axis=1, keepdims=True), axis=0)
    m = np.asarray(out.main)[-1] - np.asarray(out.main)[0]
    assert np.dot(m, target) / np.linalg.norm(m) / np.linalg.norm(target) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(R @ R.T, np.eye(dim), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # About the base: base kept, every distance from it kept, lateral bases stay on the main root.
    np.testing.assert_allclose(np.asarray(out.main)[0], np.asarray(mean.main)[0], atol=1e-12)
    for a, b in [(out.main, mean.main), (out.laterals, mean.laterals)]:
        da = np.linalg.norm(np.asarray(a) - np.asarray(mean.main)[0], axis=-1)
        np.testing.assert_allclose(da, np.linalg.norm(np.asarray(b) - np.asarray(mean.main)[0], axis=-1), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(out.attach), np.asarray(mean.attach))
    # A batch turns root by root, each about its own base; None leaves the tree unchanged.
    both = turn(rs.stack([mean, mean]), R)
    np.testing.assert_allclose(np.asarray(both.main)[1], np.asarray(out.main), atol=1e-12)
    assert turn(mean, None) is mean
    # A plant (axes around a zero-length main root) has no main direction: not turned.
    from rootshape_jax.io import plant_system

    plant = rs.batch([plant_system(inputs[:2])], n_points=20, depth=3)
    assert rs.upright_rotation(rs.unstack(plant)[0], plant) is None


def test_progress_bars_in_a_log_are_whole_lines():
    # stderr redirected to a file: no carriage returns or cursor codes, one line per bar unless
    # it runs long, and the text around the bars keeps its own lines.
    import io

    from tqdm import tqdm

    from rootshape_jax._cli._common import LogStream

    sink = io.StringIO()
    log = LogStream(sink, interval=3600.0)
    print("Registering...", file=log)
    with tqdm(total=5, desc="distances", file=log, mininterval=0) as bar:
        for _ in range(5):
            bar.update()
    log.write("\x1b[A")  # a nested bar's cursor move
    with tqdm(total=2, desc="mean", file=log, mininterval=0, leave=False) as bar:
        bar.update()
        print("rootshape: warning: something", file=log)
        bar.update()
    print("done", file=log)
    log.close_line()
    text = sink.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = [line.split("|")[0] for line in text.splitlines()]
    # Each bar's first state at once (the step has started), its latest before other text (the
    # warning: the bar's state so far, then the warning on its own line) and when it ends.
    assert lines == [
        "Registering...",
        "distances:   0%",
        "distances: 100%",
        "mean:   0%",
        "mean:  50%",
        "rootshape: warning: something",
        "done",  # the mean bar (leave=False) cleared itself: its last state is not written
    ]

    # With no interval every redraw is kept, as a line of its own (tqdm redraws its last state
    # when it closes).
    sink = io.StringIO()
    log = LogStream(sink, interval=0.0)
    with tqdm(total=3, desc="d", file=log, mininterval=0) as bar:
        for _ in range(3):
            bar.update()
    lines = sink.getvalue().splitlines()
    assert [line.split("|")[0] for line in lines] == ["d:   0%", "d:  33%", "d:  67%", "d: 100%", "d: 100%"]


def test_log_bars_come_before_stdout_and_a_second_bar_of_one_name_starts_at_once():
    import io

    from tqdm import tqdm

    from rootshape_jax._cli._common import BarsFirst, LogStream

    # `> log 2>&1`: one file for both streams. A finished bar's last state is written before
    # the stdout line that reports the step's result, not after it at the end of the run.
    sink = io.StringIO()
    log = LogStream(sink, interval=3600.0)
    out = BarsFirst(sink, log)
    for depth in (3, 2):  # two bars named alike, one after the other (as in the demo)
        with tqdm(total=4, desc="distances", file=log, mininterval=0) as bar:
            for _ in range(4):
                bar.update()
        print(f"wrote depth {depth}", file=out)
    log.close_line()
    lines = [line.split("|")[0] for line in sink.getvalue().splitlines()]
    assert lines == [
        "distances:   0%",
        "distances: 100%",
        "wrote depth 3",
        "distances:   0%",  # the second bar's first state at once, although its name was seen
        "distances: 100%",
        "wrote depth 2",
    ]


def test_log_bar_counts_with_unit_scale_and_cut_short():
    from rootshape_jax._cli._common import _progress, _went_back

    # unit_scale: 999 -> 1.00k is not a count going back; a bar cut short shows no count.
    assert _progress("d:  10%|#  | 1.50k/10.0k [00:05<00:20, 300it/s]") == (1500.0, 5.0)
    assert not _went_back(_progress("d: 1.00kit [00:06, 300it/s]"), _progress("d: 999it [00:05, 300it/s]"))
    assert _progress("distances:  3") == (None, None)
    assert not _went_back(_progress("distances:  3"), _progress("distances:  50%|##  | 5/10 [00:09<00:09]"))
    assert _went_back(
        _progress("distances:   0%|  | 0/10 [00:00<?]"), _progress("distances: 100%|##| 10/10 [00:09<00:00]")
    )
    assert _progress("mean: 01:00:12") == (None, 3612.0)


def test_log_stream_keeps_text_and_throttles_nested_bars():
    import io

    from tqdm import tqdm

    from rootshape_jax._cli._common import LogStream

    # Text still waiting for its newline when a bar redraws (print writes text and "\n"
    # separately; the heartbeat thread redraws in between) is kept, and so is "text\r\n".
    sink = io.StringIO()
    log = LogStream(sink, interval=3600.0)
    log.write("rootshape: warning: something important")
    log.write("\rbar:  10%|#")
    log.write("\n")
    log.write("windows line\r\n")
    log.close_line()
    assert sink.getvalue().splitlines() == ["rootshape: warning: something important", "bar:  10%|#", "windows line"]

    # An outer bar with a nested (leave=False) inner bar per step, as the Karcher mean draws:
    # tqdm moves the cursor with newlines and escape codes, which must not make every redraw
    # a line. Each bar's first state, then only its latest state before other text.
    sink = io.StringIO()
    log = LogStream(sink, interval=3600.0)
    with tqdm(total=3, desc="mean (fixed point)", file=log, mininterval=0) as outer:
        for _ in range(3):
            with tqdm(total=50, desc="registering", file=log, mininterval=0, leave=False, position=1) as inner:
                for _ in range(50):
                    inner.update()
            outer.update()
    print("done", file=log)
    log.close_line()
    lines = [line.split("|")[0] for line in sink.getvalue().splitlines()]
    assert lines[0] == "mean (fixed point):   0%" and lines[1] == "registering:   0%"
    assert lines[-2] == "mean (fixed point): 100%" and lines[-1] == "done"
    assert len(lines) <= 5, lines


def test_cli_log_has_no_carriage_returns(tmp_path):
    proc = run_cli("distances", "--synthetic", 3, "--points", 20, "--out", tmp_path / "o")
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "distances: 100%" in proc.stderr
