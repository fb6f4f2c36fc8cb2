"""`rootshape learn-weights FOLDER --labels CSV --by COLUMN`: weights, loss plot, CV table."""

from __future__ import annotations

import csv
import re

import numpy as np
import pytest
from helpers import run_cli

import rootshape_jax as rs
from rootshape_jax import io
from rootshape_jax._cli._common import make_weights
from rootshape_jax._cli._parser import build_parser
from rootshape_jax.datasets import synthetic_roots


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture
def labelled_folder(tmp_path):
    d = tmp_path / "roots"
    d.mkdir()
    conds = ["control"] * 3 + ["drought"] * 3
    for i, c in enumerate(conds):
        io.write_rsml(synthetic_roots(1, condition=c, seed=20 + i), d / f"p{i}.rsml")
    table = tmp_path / "labels.csv"
    table.write_text("file,condition\n" + "".join(f"p{i},{c}\n" for i, c in enumerate(conds)))
    return d, table


def test_single_class_fails_before_registering(labelled_folder, tmp_path):
    d, _ = labelled_folder
    table = tmp_path / "one.csv"
    table.write_text("file,condition\n" + "".join(f"p{i},control\n" for i in range(6)))
    proc = run_cli("learn-weights", d, "--labels", table, "--by", "condition", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "same value" in proc.stderr or "same label" in proc.stderr, proc.stderr
    assert not (tmp_path / "o" / "weights.csv").exists()


@pytest.mark.slow
def test_learn_weights_end_to_end(labelled_folder, tmp_path):
    d, table = labelled_folder
    out = tmp_path / "o"
    proc = run_cli(
        "learn-weights", d, "--labels", table, "--by", "condition", "--out", out, "--points", "12",
        "--laterals", "3", "--folds", "3", "--repeats", "2", "--reregistrations", "1", "--quiet",
        "--regularisation", "1e-3,0.1",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    w = {r["term"]: r for r in read_csv(out / "weights.csv")}
    assert set(w) == {"main", "lateral", "position", "thickness"}
    assert float(w["lateral"]["learned"]) == 1.0 and w["main"]["start"] == "0.02"  # float32, shortest text
    cv = read_csv(out / "cross_validation.csv")
    # Two repeats of 3 folds, then the mean and sd over all six.
    assert [(r["repeat"], r["fold"]) for r in cv] == [
        ("1", "1"), ("1", "2"), ("1", "3"), ("2", "1"), ("2", "2"), ("2", "3"), ("", "mean"), ("", "sd")
    ]  # fmt: skip
    # Each repeat holds every root out once.
    assert sum(int(r["held_out"]) for r in cv[:3]) == sum(int(r["held_out"]) for r in cv[3:6]) == 6
    for r in cv[:6]:
        for k in ("learned_1nn", "learned_class_mean", "start_1nn", "start_class_mean"):
            assert 0.0 <= float(r[k]) <= 1.0
    # The held-out log-loss per fold, and the mean row is the mean of the folds'.
    for k in ("learned_log_loss", "start_log_loss"):
        folds = [float(r[k]) for r in cv[:6]]
        assert all(np.isfinite(v) and v > 0 for v in folds)
        assert float(cv[6][k]) == pytest.approx(np.mean(folds), rel=1e-6)
    # The note's fold counts are the table's (better / same / worse than the starting weights).
    for name, learned, start, sign in (
        ("1-NN", "learned_1nn", "start_1nn", 1),
        ("class mean", "learned_class_mean", "start_class_mean", 1),
        ("log-loss", "learned_log_loss", "start_log_loss", -1),
    ):
        a, b = np.array([float(r[learned]) for r in cv[:6]]), np.array([float(r[start]) for r in cv[:6]])
        same = np.isclose(a, b, rtol=1e-4, atol=1e-12)
        better, worse = np.sum((sign * (a - b) > 0) & ~same), np.sum((sign * (a - b) < 0) & ~same)
        assert f"{name} {better} / {np.sum(same)} / {worse}" in proc.stdout, proc.stdout
        # And its corrected paired t-test is the one of the table's fold scores (3 folds a repeat).
        expected = rs.fold_t_test(a, b, n_folds=3).p_value
        if np.isnan(expected):
            assert f"{name} p undefined" in proc.stdout, proc.stdout
        else:
            p = float(re.search(rf"{name} p = (\d+(?:\.\d+)?(?:e[+-]\d+)?)", proc.stdout).group(1))
            assert p == pytest.approx(expected, rel=1e-2)
    assert (out / "loss_trace.png").is_file()
    # --weights weights.csv: what the other commands weigh with is the learned column.
    args = build_parser().parse_args(["distances", str(d), "--weights", str(out / "weights.csv")])
    assert make_weights(args).to_dict() == pytest.approx({k: float(r["learned"]) for k, r in w.items()})
    # The inner cross-validation picked one of the two penalties given.
    assert "(regularisation 0.001)" in proc.stdout or "(regularisation 0.1)" in proc.stdout, proc.stdout


@pytest.mark.parametrize("bad", ["-1", "x", "1e-3,,2", "nan"])
def test_bad_regularisation_is_a_usage_error(labelled_folder, tmp_path, bad):
    d, table = labelled_folder
    proc = run_cli(
        "learn-weights", d, "--labels", table, "--by", "condition", "--out", tmp_path / "o", "--regularisation", bad
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "--regularisation" in proc.stderr and "non-negative numbers" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_learn_weights_per_order_at_depth_3(tmp_path):
    """--depth 3 --level-weights: the second order's (λs, λp) are learned and reported, in
    weights.csv and in each fold's row of the cross-validation table."""
    d = tmp_path / "roots"
    d.mkdir()
    conds = ["control"] * 3 + ["drought"] * 3
    for i, c in enumerate(conds):
        io.write_rsml(synthetic_roots(1, condition=c, seed=40 + i, depth=3), d / f"p{i}.rsml")
    table = tmp_path / "labels.csv"
    table.write_text("file,condition\n" + "".join(f"p{i},{c}\n" for i, c in enumerate(conds)))
    out = tmp_path / "o"
    proc = run_cli(
        "learn-weights", d, "--labels", table, "--by", "condition", "--out", out, "--points", "12",
        "--laterals", "3", "--depth", "3", "--level-weights", "2,0.5", "--folds", "3",
        "--reregistrations", "1", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    w = {r["term"]: r for r in read_csv(out / "weights.csv")}
    assert set(w) == {"main", "lateral", "position", "thickness", "lateral_order2", "position_order2"}
    assert float(w["lateral_order2"]["start"]) == 2.0 and float(w["position_order2"]["start"]) == 0.5
    assert float(w["lateral_order2"]["learned"]) > 0 and float(w["lateral"]["learned"]) == 1.0
    assert "--level-weights" in proc.stdout
    # --weights weights.csv at --depth 3 brings the second order's learned weights; at depth 2
    # they have nothing to weigh, and --level-weights given on the command line wins.
    learned = {k: float(r["learned"]) for k, r in w.items()}
    csv_path = str(out / "weights.csv")
    args = build_parser().parse_args(["distances", str(d), "--depth", "3", "--weights", csv_path])
    assert make_weights(args).to_dict() == pytest.approx(learned)
    args = build_parser().parse_args(["distances", str(d), "--weights", csv_path])
    assert make_weights(args).deeper == ()
    args = build_parser().parse_args(
        ["distances", str(d), "--depth", "3", "--weights", csv_path, "--level-weights", "3,4"]
    )
    assert make_weights(args).deeper == ((3.0, 4.0),)
    cv = read_csv(out / "cross_validation.csv")
    assert all(float(r["lambda_position_order2"]) > 0 for r in cv[:3])
    # Without --repeats, one split: every fold row is repeat 1.
    assert [(r["repeat"], r["fold"]) for r in cv] == [("1", "1"), ("1", "2"), ("1", "3"), ("", "mean"), ("", "sd")]


def write_table(path, text):
    path.write_text(text)
    return str(path)


def test_weights_file_is_read_by_term(tmp_path):
    """--weights FILE.csv takes the learned column by term name, in any row order; terms
    left out (thickness) keep their default."""
    # Saved again by a spreadsheet: a byte-order mark, CRLF line ends, a trailing empty row.
    text = "\ufeffterm,start,learned\r\nposition,1,0.25\r\nmain,0.02,0.0125\r\nlateral,1,1\r\n,,\r\n"
    f = write_table(tmp_path / "w.csv", text)
    args = build_parser().parse_args(["distances", str(tmp_path), "--weights", f])
    w = make_weights(args)
    assert w.to_dict() == pytest.approx({"main": 0.0125, "lateral": 1.0, "position": 0.25, "thickness": 0.0})
    assert isinstance(w, rs.Weights)


@pytest.mark.parametrize(
    "text, problem",
    [
        ("term,weight\nmain,1\n", "no columns 'term' and 'learned'"),
        ("term,learned\nmain,0.02\nlateral,1\n", "no row for position"),
        ("term,learned\nmain,x\nlateral,1\nposition,1\n", "'main' has the weight 'x', not a number"),
        ("term,learned\nmain,-1\nlateral,1\nposition,1\n", "weights are non-negative"),
        ("term,learned\nmain,nan\nlateral,1\nposition,1\n", "weights are non-negative"),
        ("term,learned\nmain,1\nmain,2\nlateral,1\nposition,1\n", "'main' appears twice"),
        ("term,learned\nmain,1\nlateral,1\nposition,1\nroots,2\n", "unknown term 'roots'"),
        ("term,learned\nmain,0\nlateral,0\nposition,0\n", "every weight is 0"),
        ("term,learned\nmain,1\nlateral,1\nposition,1\nlateral_order3,1\nposition_order3,1\n", "without gaps"),
    ],
)
def test_bad_weights_file_is_a_usage_error(tmp_path, capsys, text, problem):
    f = write_table(tmp_path / "w.csv", text)
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["distances", str(tmp_path), "--weights", f])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--weights" in err and problem in err and "learn-weights" in err, err


def test_missing_weights_file_is_a_usage_error(tmp_path):
    proc = run_cli("distances", tmp_path, "--weights", tmp_path / "nothing.csv", "--out", tmp_path / "o")
    assert proc.returncode == 2 and "cannot be read" in proc.stderr, proc.stderr
