"""`rootshape compare` and label colour strips: what the tables say is what the figures show."""

from __future__ import annotations

import argparse
import csv
import dataclasses
from pathlib import Path

import matplotlib.colors as mcolors
import numpy as np
import pytest
from helpers import run_cli, spy_on
from scipy.cluster import hierarchy

import rootshape_jax as rs
import rootshape_jax.plot as rplot
from rootshape_jax import io
from rootshape_jax.datasets import synthetic_roots

DATA = Path(__file__).parent / "data" / "rsml"


def hexes(colors) -> list[str]:
    return [mcolors.to_hex(c) for c in colors]


def labelled_roots():
    """12 synthetic roots in 3 files, labelled through a metadata table (condition, batch)."""
    roots, rows = [], []
    for f, c in enumerate(("control", "drought", "high_nitrate")):
        for r in synthetic_roots(4, condition=c, seed=5):
            roots.append(dataclasses.replace(r, metadata=dict(r.metadata, source_file=f"/x/f{f}.rsml")))
        rows.append({"file": f"f{f}", "treatment": c, "batch": "b1" if f < 2 else "b2"})
    roots = [dataclasses.replace(r, name=f"r{i:02d}") for i, r in enumerate(roots)]
    return io.attach_metadata(roots, rows)


def grouped_distances(n_per=4, shift=9.0, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(3 * n_per, 3)) + np.repeat(np.array([[0, 0, 0], [shift, 0, 0], [0, shift, 0]]), n_per, axis=0)
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def test_heat_map_strips_show_the_labels_in_the_matrix_order():
    D = grouped_distances()
    cond = ["c"] * 4 + ["d"] * 4 + ["h"] * 4
    geno = ["wt", "mut"] * 6
    fig, axes = rplot.plot_distance_matrix(
        D, labels=[f"r{i}" for i in range(12)], strips={"condition": cond, "genotype": geno}
    )
    order = hierarchy.leaves_list(hierarchy.linkage(D[np.triu_indices(12, 1)], "average", optimal_ordering=True))
    names = [t.get_text() for t in axes["matrix"].get_xticklabels()]
    assert names == [f"r{i}" for i in order]
    for key, values in (("condition", cond), ("genotype", geno)):
        ax = axes["strips"][key]
        bars = [p for p in ax.patches]
        assert [b.get_gid() for b in bars] == [values[i] for i in order]
        leg = axes["legends"][key].get_legend()
        legend = {t.get_text(): mcolors.to_hex(h.get_facecolor()) for t, h in zip(leg.texts, leg.legend_handles)}
        assert hexes(b.get_facecolor() for b in bars) == [legend[values[i]] for i in order]
        assert set(legend) == set(values) and len(set(legend.values())) == len(legend)
        assert ax.get_ylabel() == key


def test_strip_errors():
    D = grouped_distances()
    with pytest.raises(ValueError, match="strip 'c' has 3 values for 12 roots"):
        rplot.plot_distance_matrix(D, strips={"c": ["a", "b", "c"]})
    with pytest.raises(ValueError, match="own figure"):
        fig, _ = rplot.plot_distance_matrix(D)
        rplot.plot_dendrogram(D, strips={"c": ["a"] * 12}, ax=fig.axes[0])


def run_steps(tmp_path, monkeypatch, by="treatment"):
    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._report import Output
    from rootshape_jax._cli._steps import Context, run_cluster, run_compare

    roots = labelled_roots()
    args = argparse.Namespace(
        laterals=4,
        points=12,
        normalise_scale=True,
        clusters=3,
        linkage="average",
        by=by,
        command="compare",
        permutations=199,
        seed=3,
        quiet=True,
    )
    ctx = Context(prepare(roots, args))
    ctx.distances = grouped_distances()
    drawn = {}
    for name in ("plot_dendrogram", "plot_mds"):
        original = getattr(rplot, name)

        def spy(*a, _original=original, _name=name, **kw):
            drawn[_name] = _original(*a, **kw)
            return drawn[_name]

        monkeypatch.setattr(rplot, name, spy)
    out = Output(tmp_path / "o", args)
    run_compare(ctx, out, args)
    run_cluster(ctx, out, args)
    return ctx, drawn, tmp_path / "o"


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_compare_tables_agree_with_the_library_and_the_figures(tmp_path, monkeypatch, capsys):
    ctx, drawn, out = run_steps(tmp_path, monkeypatch)
    D, labels = ctx.distances, [r.metadata["treatment"] for r in ctx.pop.roots]
    rows = read_csv(out / "permanova.csv")
    overall = rs.permanova(D, labels, permutations=199, seed=3)
    assert float(rows[0]["pseudo_F"]) == pytest.approx(overall.pseudo_f, rel=1e-12)
    assert float(rows[0]["p_value"]) == overall.p_value and float(rows[0]["R2"]) == pytest.approx(overall.r2)
    pairs = rs.pairwise_permanova(D, labels, permutations=199, seed=4)
    assert [r["test"] for r in rows[1:]] == [f"{t.group_a} vs {t.group_b}" for t in pairs]
    assert [float(r["p_holm"]) for r in rows[1:]] == [t.p_adjusted for t in pairs]
    assert overall.p_value == 1 / 200  # three well separated groups
    printed = capsys.readouterr().out
    assert "| test (treatment) |" in printed and (out / "permanova.md").read_text().strip() == printed.strip()
    # mds.csv: coordinates are rs.mds's; each group's points in the figure carry its colour.
    mrows = read_csv(out / "mds.csv")
    emb = rs.mds(D, n_components=2).embedding
    np.testing.assert_allclose([[float(r["mds_1"]), float(r["mds_2"])] for r in mrows], emb)
    fig, ax = drawn["plot_mds"]
    colors = rplot.label_colors(labels)
    for coll in ax.collections:
        group = coll.get_label().split(" (n = ")[0]
        pts = coll.get_offsets()
        expect = np.array([[float(r["mds_1"]), float(r["mds_2"])] for r in mrows if r["treatment"] == group])
        np.testing.assert_allclose(np.asarray(pts), expect)
        assert hexes(coll.get_facecolor()) == [colors[group]]
    # Dendrogram strips: one per metadata label, values and colours as in the CSV of clusters' roots.
    _, axes = drawn["plot_dendrogram"]
    assert list(axes["strips"]) == ["treatment", "batch"]
    order = [t.get_text() for t in axes["strips"]["batch"].get_xticklabels()]
    meta = {r.name: r.metadata for r in ctx.pop.roots}
    for key, ax in axes["strips"].items():
        bars = list(ax.patches)
        assert [b.get_gid() for b in bars] == [meta[n][key] for n in order]
        col = rplot.label_colors([m[key] for m in meta.values()])
        assert hexes(b.get_facecolor() for b in bars) == [col[meta[n][key]] for n in order]
    crow = read_csv(out / "clusters.csv")
    assert {r["root"]: r["treatment"] for r in crow} == {n: m["treatment"] for n, m in meta.items()}


def test_compare_needs_two_groups(tmp_path, monkeypatch):
    from rootshape_jax._cli._common import CLIError

    with pytest.raises(CLIError, match="--by batch"):
        roots = labelled_roots()
        roots = [dataclasses.replace(r, metadata=dict(r.metadata, batch="b1")) for r in roots]
        from rootshape_jax._cli._inputs import prepare
        from rootshape_jax._cli._steps import group_labels

        args = argparse.Namespace(laterals=4, points=12, normalise_scale=True, by="batch", command="compare")
        group_labels(prepare(roots, args))


def test_compare_warns_about_one_root_groups(capsys):
    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._steps import group_labels

    roots = labelled_roots()
    batches = ["b1"] * (len(roots) - 1) + ["b2"]
    roots = [dataclasses.replace(r, metadata=dict(r.metadata, batch=b)) for r, b in zip(roots, batches)]
    args = argparse.Namespace(laterals=4, points=12, normalise_scale=True, by="batch", command="compare")
    capsys.readouterr()
    assert group_labels(prepare(roots, args)) == batches
    err = capsys.readouterr().err
    assert "group(s) 'b2' have one root" in err and "'b1'" not in err


# --------------------------------------------------------------------------------------------
# End to end, on a folder with a bad file (compiles registrations: slow)


@pytest.fixture
def labelled_folder(tmp_path):
    d = tmp_path / "roots"
    d.mkdir()
    for i, c in enumerate(("control", "control", "drought", "drought")):
        io.write_rsml(synthetic_roots(1, condition=c, seed=10 + i), d / f"p{i}.rsml")
    (d / "zz_bad.rsml").write_text("not xml")
    table = tmp_path / "m.csv"
    table.write_text("file,condition,tray\np0,control,1\np1.rsml,control,2\np2,drought,1\np3,drought,2\n")
    return d, table


def test_compare_missing_row_fails_before_computing(labelled_folder, tmp_path):
    d, _ = labelled_folder
    table = tmp_path / "short.csv"
    table.write_text("file,condition\np0,control\np1,control\np2,drought\n")
    proc = run_cli("compare", d, "--metadata", table, "--by", "condition", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    err = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert len(err) == 1 and "no row for 1 root(s): " in err[0] and "(p3.rsml)" in err[0], proc.stderr
    assert not (tmp_path / "o" / "distances.csv").exists()


def test_compare_unknown_label_is_one_line(labelled_folder, tmp_path):
    d, table = labelled_folder
    proc = run_cli("compare", d, "--metadata", table, "--by", "genotype", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "label 'genotype' is missing for 4 root(s)" in proc.stderr
    assert "labels seen: condition, tray" in proc.stderr


@pytest.mark.slow
def test_compare_end_to_end(labelled_folder, tmp_path):
    d, table = labelled_folder
    out = tmp_path / "o"
    proc = run_cli(
        "compare",
        d,
        "--metadata",
        table,
        "--by",
        "condition",
        "--out",
        out,
        "--points",
        "12",
        "--laterals",
        "3",
        "--permutations",
        "99",
        "--quiet",
    )
    assert proc.returncode == 0, proc.stderr
    assert (
        "zz_bad.rsml: not well-formed XML" in proc.stderr
        and "skipped 1: zz_bad.rsml (not well-formed XML)" in proc.stdout
    )
    assert "| test (condition) | roots | pseudo-F | R² | p | p (Holm) |" in proc.stdout
    rows = read_csv(out / "permanova.csv")
    assert rows[0]["test"] == "all groups (control n=2, drought n=2)" and len(rows) == 2
    names, D = None, None
    with open(out / "distances.csv", newline="") as f:
        r = list(csv.reader(f))
        names, D = r[0][1:], np.array([[float(x) for x in row[1:]] for row in r[1:]])
    labels = {m["root"]: m["condition"] for m in read_csv(out / "mds.csv")}
    ref = rs.permanova(D, [labels[n] for n in names], permutations=99, seed=0)
    assert float(rows[0]["pseudo_F"]) == pytest.approx(ref.pseudo_f, rel=1e-9)
    for f in ("mds.png", "permanova.md", "distances.png"):
        assert (out / f).is_file()


def test_cluster_by_classifies_the_chosen_label(tmp_path, monkeypatch):
    ctx, _, out = run_steps(tmp_path, monkeypatch, by="batch")
    rows = read_csv(out / "clusters.csv")
    assert list(rows[0]) == ["root", "cluster", "batch"]  # the --by label
    assert {r["root"]: r["batch"] for r in rows} == {r.name: r.metadata["batch"] for r in ctx.pop.roots}
    acc = read_csv(out / "classification.csv")
    labels = np.array([r.metadata["batch"] for r in ctx.pop.roots])
    ref = rs.loo_accuracy(ctx.distances, labels, rule="nearest_neighbour")
    assert float(acc[0]["accuracy"]) == pytest.approx(ref["accuracy"])


def test_pca_scores_table_agrees_with_the_library_and_the_figure(tmp_path, monkeypatch):
    """pca_scores.csv: each root's row holds its labels and its scores on the kept components
    (standardised: mean 0, variance 1 over the roots); pca_scores.png plots the CSV's first two
    columns, one colour per --by group."""
    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._report import Output
    from rootshape_jax._cli._steps import Context, run_pca

    roots = labelled_roots()
    args = argparse.Namespace(laterals=4, points=12, normalise_scale=True, by="treatment", modes=2, quiet=True)
    ctx = Context(prepare(roots, args))
    ctx.mean = rs.karcher_mean(ctx.pop.tree, progress=False)
    drawn = spy_on(monkeypatch, rplot, "plot_pca_scores")
    run_pca(ctx, Output(tmp_path / "o", args), args)
    rows = read_csv(tmp_path / "o" / "pca_scores.csv")
    kept = int(ctx.pca.n_components)
    assert kept >= 2
    assert list(rows[0]) == ["root", "treatment", "batch"] + [f"PC{k + 1}" for k in range(kept)]
    meta = {r.name: r.metadata for r in ctx.pop.roots}
    assert [r["root"] for r in rows] == ctx.pop.names
    assert all(r[key] == meta[r["root"]][key] for r in rows for key in ("treatment", "batch"))
    S = np.array([[float(r[f"PC{k + 1}"]) for k in range(kept)] for r in rows])
    np.testing.assert_allclose(S, np.asarray(ctx.pca.scores)[:, :kept], rtol=1e-6, atol=1e-6)
    # Standardised scores of the kept components: centred (the Karcher mean is the tangent
    # vectors' centre up to its tolerance) with unit sample variance.
    np.testing.assert_allclose(S.mean(axis=0), 0.0, atol=0.05)
    np.testing.assert_allclose(S.var(axis=0, ddof=1), 1.0, rtol=1e-4)
    _, ax = drawn["out"]
    colors = rplot.label_colors([m["treatment"] for m in meta.values()])
    groups = set()
    for coll in ax.collections:
        group = coll.get_label().split(" (n = ")[0]
        groups.add(group)
        expect = np.array([[float(r["PC1"]), float(r["PC2"])] for r in rows if r["treatment"] == group])
        np.testing.assert_allclose(np.asarray(coll.get_offsets()), expect, rtol=1e-6, atol=1e-6)
        assert hexes(coll.get_facecolor()) == [colors[group]]
    assert groups == {"control", "drought", "high_nitrate"}
    ratio = np.asarray(ctx.pca.explained_variance_ratio)
    assert ax.get_xlabel().startswith(f"PC1 score ({100 * ratio[0]:.0f} % of the variance")


def test_regress_by_reads_numeric_covariates_and_names_bad_values(tmp_path):
    from rootshape_jax._cli._common import CLIError
    from rootshape_jax._cli._inputs import covariate_columns, covariate_matrix, read_requested

    roots = io.attach_metadata(
        [
            dataclasses.replace(r, metadata=dict(r.metadata, source_file=f"f{i}.rsml"))
            for i, r in enumerate(synthetic_roots(3, seed=1))
        ],
        [
            {"file": "f0", "dose": "1.5", "g": "x"},
            {"file": "f1", "dose": "2", "g": "y"},
            {"file": "f2", "dose": "0", "g": "x"},
        ],
    )
    args = argparse.Namespace(command="regress", by="dose, g")
    assert covariate_columns(args) == ["dose", "g"]
    np.testing.assert_array_equal(covariate_matrix(roots, ["dose"]), [[1.5], [2.0], [0.0]])
    with pytest.raises(CLIError, match="--by g: covariates must be numbers, but root .* has 'x'"):
        covariate_matrix(roots, ["g"])
    req = tmp_path / "req.csv"
    req.write_text("main_length,mean_lateral_length,std_lateral_length,dose\n100,20,5,1\n")
    np.testing.assert_array_equal(
        read_requested(str(req), ["main_length", "mean_lateral_length", "std_lateral_length", "dose"]),
        [[100, 20, 5, 1]],
    )
    with pytest.raises(CLIError, match="missing dose2"):
        read_requested(
            str(req), ["main_length", "mean_lateral_length", "std_lateral_length", "dose", "g"][:3] + ["dose2"]
        )


@pytest.mark.parametrize("kind", ["matrix", "dendrogram", "dendrogram with roots"])
def test_strip_legends_lie_inside_the_figure_and_its_tight_box(kind, tmp_path):
    """Issue 17: the legends were outside the layout, so a figure saved with
    bbox_inches="tight" (notebooks' default) cut them off. Now the layout holds them."""
    import matplotlib.pyplot as plt
    from matplotlib.transforms import Bbox

    from rootshape_jax.datasets import synthetic_roots

    D = grouped_distances()
    strips = {"condition": ["control"] * 4 + ["drought"] * 4 + ["high_nitrate"] * 4, "genotype": ["wt", "mutant"] * 6}
    if kind == "matrix":
        fig, axes = rplot.plot_distance_matrix(D, labels=[f"r{i}" for i in range(12)], strips=strips)
    elif kind == "dendrogram":
        fig, axes = rplot.plot_dendrogram(D, labels=[f"r{i}" for i in range(12)], strips=strips)
    else:
        fig, axes = rplot.plot_dendrogram(D, roots=synthetic_roots(12, seed=3), n_clusters=3, strips=strips)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    whole = fig.bbox
    tight = fig.get_tightbbox(renderer)  # inches: what bbox_inches="tight" saves
    for name in strips:
        leg = axes["legends"][name].get_legend()
        box = leg.get_window_extent(renderer)
        assert Bbox.intersection(box, whole).width == pytest.approx(box.width), (name, box, whole)
        assert box.x1 <= whole.x1 + 0.5 and box.y0 >= whole.y0 - 0.5 and box.y1 <= whole.y1 + 0.5
        inches = box.transformed(fig.dpi_scale_trans.inverted())
        assert tight.x0 - 1e-6 <= inches.x0 and inches.x1 <= tight.x1 + 1e-6, (name, inches, tight)
        # The legend does not cover the strip or the heat map it explains.
        strip = axes["strips"][name].get_window_extent(renderer)
        assert box.x0 >= strip.x1 - 0.5
    if kind == "matrix":
        assert box.x0 >= axes["colorbar"].get_window_extent(renderer).x1 - 0.5
    plt.close(fig)
