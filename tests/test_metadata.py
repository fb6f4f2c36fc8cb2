"""Metadata tables joined onto roots (`rootshape_jax.io.read_folder(metadata=...)`), folder
reading shared with the command line, and `--metadata` end to end."""

from __future__ import annotations

import csv
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rootshape_jax as rs
from rootshape_jax import io
from rootshape_jax.datasets import synthetic_roots

DATA = Path(__file__).parent / "data" / "rsml"


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rootshape_jax", *map(str, args)], capture_output=True, text=True, timeout=900
    )


def write_table(path: Path, rows: list[list[str]], sep: str = ",") -> Path:
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f, delimiter=sep).writerows(rows)
    return path


@pytest.fixture
def folder(tmp_path) -> Path:
    """a.rsml (2 plants), b.rsml (1 plant), a file that is not XML, a file without geometry."""
    d = tmp_path / "roots"
    d.mkdir()
    a = synthetic_roots(2, condition="control", seed=1)
    a = [r.__class__(**{**r.__dict__, "metadata": dict(r.metadata, plant_id=str(i + 1))}) for i, r in enumerate(a)]
    io.write_rsml(a, d / "a.rsml")
    io.write_rsml(synthetic_roots(1, condition="drought", seed=2), d / "b.rsml")
    (d / "c_notxml.rsml").write_text("this is not xml")
    (d / "d_nogeom.rsml").write_text((DATA / "no_geometry.rsml").read_text())
    return d


def test_read_folder_skips_bad_files_with_a_report(folder):
    report = io.ReadReport()
    with pytest.warns(rs.RSMLWarning) as caught:
        roots = io.read_folder(folder, report=report)
    assert len(roots) == 3
    assert report.files == 2 and report.roots == 3
    assert [f for f, _ in report.skipped] == ["c_notxml.rsml", "d_nogeom.rsml"]
    assert report.summary().startswith("read 3 root system(s) from 2 file(s); skipped 2: c_notxml.rsml (not well")
    # One warning per skipped file, each one line.
    assert len([w for w in caught if "skipped" in str(w.message)]) == 2
    assert all("\n" not in str(w.message) for w in caught)
    assert {Path(r.metadata["source_file"]).name for r in roots} == {"a.rsml", "b.rsml"}
    with pytest.raises(rs.RSMLError, match="c_notxml.rsml"):
        io.read_folder(folder, strict=True)


def test_file_level_labels_with_and_without_extension(folder, tmp_path):
    table = write_table(
        tmp_path / "m.csv", [["file", "condition", "dose"], ["a.rsml", "control", "7"], ["b", "drought", "0.5"]]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.read_folder(folder, metadata=table)
    got = {(Path(r.metadata["source_file"]).name, r.metadata["condition"], r.metadata["dose"]) for r in roots}
    assert got == {("a.rsml", "control", "7"), ("b.rsml", "drought", "0.5")}
    assert all(isinstance(r.metadata["dose"], str) for r in roots)  # numbers stay strings
    assert io.labels_of(roots, "condition") == [r.metadata["condition"] for r in roots]


# A file row and a plant row that overrides it for plant 2 of a.rsml.
GENOTYPE_ROWS = [
    {"file": "a", "plant": "", "genotype": "wt"},
    {"file": "a", "plant": "2", "genotype": "mutant"},
    {"file": "b.rsml", "plant": "", "genotype": "wt"},
]


def read_quietly(folder, **kwargs):
    """`read_folder` of the `folder` fixture, whose bad files' warnings are tested elsewhere."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        return io.read_folder(folder, **kwargs)


def test_plant_rows_override_the_file_row(folder, tmp_path):
    roots = read_quietly(folder, metadata=GENOTYPE_ROWS)
    by_plant = {(Path(r.metadata["source_file"]).stem, r.metadata["plant_id"]): r.metadata["genotype"] for r in roots}
    assert by_plant[("a", "1")] == "wt" and by_plant[("a", "2")] == "mutant" and by_plant[("b", "1")] == "wt"


def test_read_folder_by_plant_gives_labelled_systems_as_the_command_line_does(folder):
    # read_folder had no `by`: from Python, plants' systems with labels needed read_paths and
    # attach_metadata, which no page names.
    plants = read_quietly(folder, metadata=GENOTYPE_ROWS, by="plant")
    singles = read_quietly(folder, metadata=GENOTYPE_ROWS)
    assert all(p.metadata["virtual_main"] for p in plants) and len(plants) == 3
    key = lambda r: (Path(r.metadata["source_file"]).stem, r.metadata["plant_id"], r.metadata["genotype"])  # noqa: E731
    assert sorted(map(key, plants)) == sorted(map(key, singles))
    with pytest.raises(ValueError, match="by must be 'root' or 'plant', got 'plants'"):
        io.read_folder(folder, by="plants")


def test_root_column_matches_root_name(folder):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.read_folder(folder)
    rows = [{"file": Path(r.metadata["source_file"]).name, "root": r.name, "k": str(i)} for i, r in enumerate(roots)]
    out = io.attach_metadata(roots, rows)
    assert [r.metadata["k"] for r in out] == [str(i) for i in range(len(roots))]


def test_missing_rows_are_named(folder, tmp_path):
    table = write_table(tmp_path / "m.csv", [["file", "condition"], ["a.rsml", "control"]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.read_folder(folder)
    with pytest.raises(rs.MetadataError, match=r"no row for 1 root\(s\): .*\(b.rsml\).*Add a row"):
        io.attach_metadata(roots, table)


def test_duplicate_rows_are_named(tmp_path):
    table = write_table(tmp_path / "m.csv", [["file", "c"], ["a.rsml", "x"], ["b", "y"], ["a", "z"]])
    with pytest.raises(rs.MetadataError, match=r"duplicate rows: rows 2 and 4 \(file 'a'\)"):
        io.read_metadata(table)


def test_two_matching_rows_of_equal_rank_are_ambiguous(folder):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.read_folder(folder)
    b = [r for r in roots if Path(r.metadata["source_file"]).stem == "b"]
    rows = [
        {"file": "b", "plant": "1", "c": "x"},
        {"file": "b", "plant": b[0].metadata["plant_label"] or "1 ", "c": "y"},
    ]
    # The second row's plant is the same id after stripping: a duplicate in the table itself.
    with pytest.raises(rs.MetadataError, match="duplicate rows"):
        io.attach_metadata(b, rows)


@pytest.mark.parametrize(
    ("rows", "fragment"),
    [
        ([["name", "condition"], ["a", "x"]], "no 'file' column"),
        ([["file", "unit"], ["a", "mm"]], "'unit' would overwrite"),
        ([["file", "c"], ["", "x"]], "have no file name"),
        ([["file", "c"]], "no rows"),
        ([["file", "c"], ["a", "x", "extra"]], "more cells than the header"),
    ],
)
def test_bad_tables_say_what_to_fix(tmp_path, rows, fragment):
    with pytest.raises(rs.MetadataError, match=fragment):
        io.read_metadata(write_table(tmp_path / "m.csv", rows))


def test_semicolon_tables_and_bom(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("\ufefffile;condition\na.rsml;control\n", encoding="utf-8")
    t = io.read_metadata(p)
    assert t.labels == ("condition",) and t.rows[0] == {"file": "a.rsml", "condition": "control"}


def test_unused_rows_warn(folder, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.read_folder(folder)
    rows = [{"file": "a", "c": "1"}, {"file": "b", "c": "2"}, {"file": "c_notxml", "c": "3"}]
    with pytest.warns(UserWarning, match="1 row\\(s\\) match no root read: c_notxml"):
        io.attach_metadata(roots, rows)


def test_labels_of_names_roots_without_the_label(folder):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.RSMLWarning)
        roots = io.attach_metadata(io.read_folder(folder), [{"file": "a", "c": "1"}, {"file": "b", "c": "2"}])
    with pytest.raises(rs.MetadataError, match=r"label 'genotype' is missing for 3 root\(s\).*labels seen: c"):
        io.labels_of(roots, "genotype")


# --------------------------------------------------------------------------------------------
# Command line


def test_cli_metadata_labels_reach_the_traits_table(folder, tmp_path):
    table = write_table(tmp_path / "m.csv", [["file", "condition"], ["a", "control"], ["b", "drought"]])
    out = tmp_path / "o"
    proc = run_cli("traits", folder, "--metadata", table, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "skipped 2: c_notxml.rsml" in proc.stdout
    with open(out / "traits.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["condition"] for r in rows) == ["control", "control", "drought"]


def test_cli_metadata_missing_row_is_one_line_error(folder, tmp_path):
    table = write_table(tmp_path / "m.csv", [["file", "condition"], ["a", "control"]])
    proc = run_cli("traits", folder, "--metadata", table, "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("rootshape: error:")]
    assert len(errors) == 1 and "no row for 1 root(s)" in errors[0] and "b.rsml" in errors[0], proc.stderr


def test_cli_metadata_with_synthetic_is_refused(tmp_path):
    proc = run_cli("traits", "--synthetic", "2", "--metadata", tmp_path / "m.csv", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "--metadata labels files" in proc.stderr


def test_labels_written_in_every_file_get_their_file_name(tmp_path):
    # SmartRoot labels its roots root_1, root_2, ... in every file: read from several files the
    # names carry the file (lupin/root_1, maize/root_1); one file keeps the plain labels, and a
    # table's root column still matches the label.
    from rootshape_jax._root import Root

    main = np.array([[0.0, 0.0], [0.0, 5.0]])
    for stem in ("lupin", "maize"):
        io.write_rsml(
            [Root(main=main, name="root_1"), Root(main=main + 1.0, name="root_2")], tmp_path / f"{stem}.rsml", unit="mm"
        )
    roots = io.read_folder(tmp_path)
    assert sorted(r.name for r in roots) == ["lupin/root_1", "lupin/root_2", "maize/root_1", "maize/root_2"]
    # A short file name inside a label is not the file's name: "1.rsml" still prefixes root_10.
    io.write_rsml([Root(main=main, name="root_10")], tmp_path / "1.rsml", unit="mm")
    assert "1/root_10" in {r.name for r in io.read_folder(tmp_path)}
    assert [r.name for r in io.read_folder(tmp_path / "lupin.rsml")] == ["root_1", "root_2"]
    table = [
        {"file": "maize", "root": "root_2", "genotype": "B73"},
        {"file": "lupin", "root": "", "genotype": "x"},
        {"file": "maize", "root": "root_1", "genotype": "B73"},
    ]
    out = io.attach_metadata(roots, table)
    assert {r.name: r.metadata["genotype"] for r in out}["maize/root_2"] == "B73"
