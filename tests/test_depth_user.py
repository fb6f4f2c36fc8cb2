"""Whole root systems for the user (issue 15): plots, command line, simulated plants and RSML
writing at depth 3.

The plots are checked against a plain walk over `Root.children` (how many branches of each
order there are) and against the registration: along a geodesic from a root to a copy with
its branches shuffled at every level, one colour is one branch from start to end.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import sys
from pathlib import Path

import matplotlib.colors as mcolors
import numpy as np
import pytest
from helpers import run_cli

import rootshape_jax as rs
from rootshape_jax import plot as P
from rootshape_jax.datasets import synthetic_roots
from rootshape_jax.io import read_rsml, write_rsml

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(autouse=True)
def _close_pyplot_figures():
    yield
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")


def _line(p0, p1, n=9):
    return np.linspace(np.asarray(p0, float), np.asarray(p1, float), n)


def small_system(flip: bool = False) -> rs.Root:
    """A main root with three laterals holding 2, 0 and 1 second-order laterals (distinct
    shapes, so the matching is unique). `flip` lists laterals and sub-laterals in reverse."""
    main = _line([0, 0], [0, 10], 11)
    spec = [  # (attach, tip of the lateral, [(fraction along it, tip of its child)])
        (0.2, [4.0, 3.5], [(0.4, [2.6, 1.0]), (0.75, [4.5, 5.2])]),
        (0.5, [-5.0, 7.0], []),
        (0.8, [3.0, 9.5], [(0.5, [0.8, 9.9])]),
    ]
    lats, kids = [], []
    for s, tip, subs in spec:
        start = main[0] + s * (main[-1] - main[0])
        lat = _line(start, tip)
        sub_lats = [_line(lat[0] + f * (lat[-1] - lat[0]), t, 7) for f, t in subs]
        order = slice(None, None, -1) if flip else slice(None)
        kids.append(rs.Root(main=lat, laterals=tuple(sub_lats[order]), attach=np.array([f for f, _ in subs])[order]))
        lats.append(lat)
    order = slice(None, None, -1) if flip else slice(None)
    return rs.Root(
        main=main,
        laterals=tuple(lats[order]),
        attach=np.array([s for s, _, _ in spec])[order],
        children=tuple(kids[order]),
    )


def count_by_order(root: rs.Root) -> dict[int, int]:
    """Reference: branches of each order, by walking `Root.children`."""
    counts = {0: 1}

    def walk(node, order):
        counts[order] = counts.get(order, 0) + len(node.laterals)
        for c in node.children:
            walk(c, order + 1)

    walk(root, 1)
    return {k: v for k, v in counts.items() if v}


def drawn(ax) -> dict[int, list[tuple[str, np.ndarray]]]:
    """{order: [(colour, vertices)]} of the line collections `draw` put on ``ax``."""
    out: dict[int, list] = {}
    for c in ax.collections:
        gid = c.get_gid() or ""
        if not gid.startswith("order "):
            continue
        colors = [mcolors.to_hex(x) for x in c.get_colors()]
        if len(colors) == 1:
            colors = colors * len(c.get_paths())
        out[int(gid.split()[1])] = [(col, p.vertices) for col, p in zip(colors, c.get_paths())]
    return out


def test_plot_root_draws_every_order():
    root = synthetic_roots(1, depth=3, seed=3)[0]
    expected = count_by_order(root)
    assert expected.get(2, 0) > 0, "the synthetic root should have second-order laterals"
    _, ax = P.plot_root(root)
    got = {k: len(v) for k, v in drawn(ax).items()}
    assert got == expected
    # The same root as a padded depth-3 tree draws the same branches.
    tree = rs.batch([root], depth=3, n_points=20)
    _, ax = P.plot_root(rs.unstack(tree)[0])
    assert {k: len(v) for k, v in drawn(ax).items()} == expected
    # At depth 2 the second-order laterals are gone.
    _, ax = P.plot_root(rs.unstack(rs.batch([root], n_points=20))[0])
    assert {k: len(v) for k, v in drawn(ax).items()} == {0: 1, 1: expected[1]}


def test_deeper_branches_are_thinner_and_shades_of_their_parent():
    root = small_system()
    _, ax = P.plot_root(root, linewidth=2.0)
    widths = {int(c.get_gid().split()[1]): float(np.max(c.get_linewidths())) for c in ax.collections}
    assert widths[2] < widths[1] < widths[0]
    d = drawn(ax)
    parent_of = {0: 0, 1: 0, 2: 2}  # second-order branch i -> its lateral's slot
    for i, (col, _) in enumerate(d[2]):
        k = parent_of[i]
        assert col == P.branch_color((k, i if k == 0 else 0))
        # Lighter than its parent in every channel, and not the parent's colour.
        assert all(c >= p - 1e-9 for c, p in zip(mcolors.to_rgb(col), mcolors.to_rgb(P.slot_color(k))))
        assert col != P.slot_color(k)
    assert [c for c, _ in d[1]] == [P.slot_color(k) for k in range(3)]
    # One colour for the whole root is one colour at every order.
    _, ax = P.plot_root(root, colors="#123456")
    assert {c for v in drawn(ax).values() for c, _ in v} == {"#123456"}


def test_a_plant_draws_its_axes_dark_and_their_laterals_in_slot_colours():
    # A plant (axes around a zero-length main root): with the usual rule every lateral of an
    # axis would be a shade of the axis's one colour, so matched laterals (a geodesic between
    # plants) could not be told apart.
    from rootshape_jax.plot._draw import MAIN_COLOR, as_drawing, plant_stride

    axes = synthetic_roots(2, seed=7)
    plant = rs.io.plant_system(axes, name="p")
    _, ax = P.plot_root(plant)
    d = drawn(ax)
    assert {c for c, _ in d[1]} == {MAIN_COLOR}  # the axes
    n0, n1 = (len(a.laterals) for a in axes)
    stride = max(n0, n1)
    expected = [P.slot_color(k) for k in range(n0)] + [P.slot_color(stride + k) for k in range(n1)]
    assert sorted(c for c, _ in d[2]) == sorted(expected)
    # A padded tree of the plant (every frame of a geodesic) steps by its slot capacity, the
    # same in every frame, so a lateral keeps its colour along the deformation.
    padded = rs.unstack(rs.batch([plant], depth=3, n_points=20))[0]
    cap = plant_stride(as_drawing(padded, what="t"))
    assert cap >= stride
    _, ax = P.plot_root(padded)
    expected = [P.slot_color(k) for k in range(n0)] + [P.slot_color(cap + k) for k in range(n1)]
    assert sorted(c for c, _ in drawn(ax)[2]) == sorted(expected)
    # Without the axes' laterals (depth 2) the axes themselves correspond: slot colours.
    flat = rs.unstack(rs.batch([plant], depth=2, n_points=20))[0]
    assert plant_stride(as_drawing(flat, what="t")) is None
    _, ax = P.plot_root(flat)
    assert [c for c, _ in drawn(ax)[1]] == [P.slot_color(k) for k in range(2)]
    # An ordinary root keeps the usual rule; one colour stays one colour.
    assert plant_stride(as_drawing(axes[0], what="t")) is None
    _, ax = P.plot_root(plant, colors="#123456")
    assert {c for v in drawn(ax).values() for c, _ in v} == {"#123456"}


def test_branch_color_is_a_shade_of_the_parents():
    for slot in [(0,), (3, 1), (5, 2, 4)]:
        parent = P.branch_color(slot[:-1]) if len(slot) > 1 else None
        child = np.array(mcolors.to_rgb(P.branch_color(slot)))
        if parent is None:
            assert P.branch_color(slot) == P.slot_color(slot[0])
            continue
        t = 0.3 + 0.1 * (slot[-1] % 3)
        # Reference: mixing with white, by hand.
        np.testing.assert_allclose(child, (1 - t) * np.array(mcolors.to_rgb(parent)) + t, atol=1 / 255)


def test_geodesic_colours_follow_matched_branches_at_every_level():
    """b is a with laterals and second-order laterals listed in reverse: the registration must
    undo both, so along the geodesic (a to b, in place) each colour keeps its branch."""
    a, b = small_system(), small_system(flip=True)
    ta, tb = rs.unstack(rs.batch([a, b], depth=3, n_points=16, normalise_scale=False))
    reg = rs.register(ta, tb)
    assert float(reg.distance) < 1e-6
    perm1 = np.asarray(reg.permutation)
    assert list(perm1[:3]) == [2, 1, 0]  # slots of a matched to b's (reversed) laterals
    perm2 = np.asarray(reg.child_permutations[0])
    assert list(perm2[0, :2]) == [1, 0]  # a's first lateral's children, reversed in b
    path = rs.geodesic(ta, tb, n_steps=3, registration=reg)
    fig, axes = P.plot_geodesic(path)
    first, last = drawn(axes[0]), drawn(axes[-1])
    assert {k: len(v) for k, v in first.items()} == {0: 1, 1: 3, 2: 3}
    for order in (1, 2):
        by_colour = {c: v for c, v in first[order]}
        assert len(by_colour) == len(first[order])  # matched branches: one colour each
        for c, v in last[order]:
            np.testing.assert_allclose(v, by_colour[c], atol=1e-6)
    # Drawn as given (not registered), b's colours sit on other branches: the test can fail.
    _, ax = P.plot_root(rs.to_roots(rs.stack([tb]))[0])
    moved = {c: v for c, v in drawn(ax)[2]}
    assert any(not np.allclose(moved[c], v, atol=1e-3) for c, v in first[2] if c in moved)


# --------------------------------------------------------------------------------------------
# Command line: --depth and --per


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_matrix(path: Path) -> np.ndarray:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return np.array([[float(x) for x in r[1:]] for r in rows[1:]])


READING = ["distances", "geodesic", "mean", "pca", "sample", "regress", "cluster", "compare", "learn-weights", "traits"]


@pytest.mark.parametrize("cmd", READING)
def test_every_reading_command_takes_depth_and_per(cmd, capsys):
    from rootshape_jax._cli import main

    assert main([cmd, "--help"]) == 0
    text = capsys.readouterr().out
    assert "--depth {2,3,4}" in text and "--per {root,plant}" in text


def test_bad_depth_is_a_usage_error(capsys):
    from rootshape_jax._cli import main

    assert main(["distances", "--synthetic", "2", "--depth", "5"]) == 2
    assert "--depth" in capsys.readouterr().err


@pytest.fixture(scope="module")
def plant_file(tmp_path_factory) -> Path:
    """One RSML file with two plants: plant A has two axes (each with second-order laterals),
    plant B one axis."""
    roots = synthetic_roots(3, depth=3, seed=4)
    a = rs.io.plant_system(roots[:2], name="A", metadata={"plant_id": "A"})
    b = dataclasses.replace(roots[2], name="B", metadata={"plant_id": "B"})
    path = tmp_path_factory.mktemp("plants") / "plants.rsml"
    write_rsml([a, b], path, unit="mm")
    return path


def test_traits_per_plant_and_per_root(plant_file, tmp_path):
    by_root = read_rsml(plant_file)
    by_plant = read_rsml(plant_file, by="plant")
    assert (len(by_root), len(by_plant)) == (3, 2)
    # --depth 4 on plants keeps the axes' laterals and theirs: lateral orders 1 … 2 of the axes.
    proc = run_cli("traits", plant_file, "--per", "plant", "--depth", "4", "--out", tmp_path / "p")
    assert proc.returncode == 0, proc.stderr
    rows = read_csv(tmp_path / "p" / "traits.csv")
    assert len(rows) == 2 and "n_laterals_order3" not in rows[0]
    # Reference: count by walking Root.children (level 1 of a plant's system is its axes, so
    # the axes' laterals are order 1 of the plant's traits).
    for row, plant in zip(rows, by_plant):
        counts = count_by_order(plant)
        assert int(row["n_axes"]) == counts[1]
        assert int(row["n_laterals"]) == int(row["n_laterals_order1"]) == counts[2]
        assert int(row["n_laterals_order2"]) == counts.get(3, 0)
    assert [int(r["n_axes"]) for r in rows] == [2, 1]
    # Plant B has one axis: its traits are those of that axis read as a single root.
    proc = run_cli("traits", plant_file, "--depth", "3", "--out", tmp_path / "b")
    one = read_csv(tmp_path / "b" / "traits.csv")[2]
    assert {k: v for k, v in rows[1].items() if k not in ("name", "n_axes")} == {
        k: v for k, v in one.items() if k != "name"
    }
    proc = run_cli("traits", plant_file, "--depth", "4", "--out", tmp_path / "r")
    assert proc.returncode == 0, proc.stderr
    rows = read_csv(tmp_path / "r" / "traits.csv")
    assert len(rows) == 3 and "n_laterals_order3" in rows[0]  # --depth 4: orders 1 … 3
    for row, root in zip(rows, by_root):
        assert int(row["n_laterals_order2"]) == count_by_order(root).get(2, 0)


def test_mean_refused_at_depth_gives_one_clear_line(monkeypatch, capsys, tmp_path):
    """Whatever analysis refuses a deep tree (NotImplementedError) ends in one line naming
    --depth 2; at depth 2 the same exception is a bug and is reported as one."""
    from rootshape_jax._cli import main

    def refuse(*a, **k):
        raise NotImplementedError("depth 2 only")

    monkeypatch.setattr(rs, "karcher_mean", refuse)
    args = ["mean", "--synthetic", "2", "--points", "8", "--laterals", "2", "--quiet", "--out"]
    assert (
        main(["mean", "--synthetic", "2", "--points", "8", "--quiet", "--depth", "3", "--out", str(tmp_path / "a")])
        == 1
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--depth 3" in err[0] and "--depth 2" in err[0], err
    assert main(args + [str(tmp_path / "b")]) == 1
    err = capsys.readouterr().err
    assert "NotImplementedError" in err and "bug" in err


@pytest.mark.slow
def test_mean_at_depth_3_fails_clearly_or_works(tmp_path):
    """Against the library as it is: a clear refusal while the mean needs depth 2, a mean
    (with its second-order laterals written) once it handles depth 3."""
    out = tmp_path / "m"
    proc = run_cli("mean", "--synthetic", 3, "--depth", 3, "--points", 12, "--max-steps", 2, "--quiet", "--out", out)
    if proc.returncode == 0:
        assert (out / "mean.rsml").is_file()
        return
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert "--depth 2" in lines[0] and "bug" not in lines[0]


@pytest.mark.slow
def test_distances_at_depth_3_match_the_library(tmp_path):
    roots = synthetic_roots(3, depth=3, seed=0)
    out = tmp_path / "d"
    proc = run_cli("distances", "--synthetic", 3, "--depth", 3, "--points", 16, "--float64", "--quiet", "--out", out)
    assert proc.returncode == 0, proc.stderr
    D = read_matrix(out / "distances.csv")
    tree3 = rs.batch(roots, depth=3, n_points=16, normalise_scale=True, dtype=np.float64)
    ref = np.asarray(rs.pairwise_distances(tree3))
    np.testing.assert_allclose(D, ref, rtol=1e-6, atol=1e-9)
    # The second-order laterals count: depth 2 on the same roots gives other distances.
    tree2 = rs.batch(roots, n_points=16, normalise_scale=True, dtype=np.float64)
    D2 = np.asarray(rs.pairwise_distances(tree2))
    assert not np.allclose(D, D2, rtol=1e-3)


# --------------------------------------------------------------------------------------------
# Simulated plants (CPlantBox, the `sim` extra)


def test_simulated_roots_keep_every_axis_and_order():
    pytest.importorskip("plantbox")
    from rootshape_jax.datasets import simulated_roots

    taproots = simulated_roots("wheat", 2, days=12, seed=3)
    plants = simulated_roots("wheat", 2, days=12, seed=3, by="plant")
    for tap, plant in zip(taproots, plants):
        assert rs.io.is_plant_system(plant)
        assert plant.metadata["n_axes"] == plant.n_laterals > 1  # wheat: several seminal axes
        # The first axis is the by="root" root, bit for bit, with its own laterals.
        first = plant.children[0]
        np.testing.assert_array_equal(first.main, tap.main)
        np.testing.assert_array_equal(first.attach, tap.attach)
        assert len(first.laterals) == tap.n_laterals
        for x, y in zip(first.laterals, tap.laterals):
            np.testing.assert_array_equal(x, y)
        # Every axis starts at the collar, and deeper orders are there for batch(depth=3).
        for axis in plant.laterals:
            np.testing.assert_allclose(axis[0], plant.main[0], atol=1e-9)
    counts = count_by_order(plants[0])
    assert counts.get(2, 0) > 0
    with pytest.warns(UserWarning, match="left out"):  # wheat's third order, at depth 3
        tree = rs.batch(plants, depth=3, n_points=12)
    assert int(np.sum(np.asarray(tree.deeper[0].mask[0]))) == counts[2]
    with pytest.raises(ValueError, match="by"):
        simulated_roots("pea", 1, by="plants")


# --------------------------------------------------------------------------------------------
# write_rsml at depth: hierarchy and diameters at every order


def with_radii(root: rs.Root, rng, scale: float = 0.5) -> rs.Root:
    """The root with a radius varying along every branch, at every order (thinner by order)."""

    def radius(line, s):
        return s * (1.0 + 0.3 * rng.random(len(line)))

    kids = tuple(with_radii(c, rng, 0.5 * scale) for c in root.children)
    return dataclasses.replace(
        root,
        main_radius=radius(root.main, scale),
        children=kids,
        lateral_radii=tuple(k.main_radius for k in kids) if kids else None,
    )


def branches(root: rs.Root, path=()):
    """(slot path, Root) of every branch that has a `Root` record, depth first."""
    yield path, root
    for k, c in enumerate(root.children):
        yield from branches(c, path + (k,))


def assert_same_system(a: rs.Root, b: rs.Root, atol: float) -> int:
    """Same branches at every order (geometry, attachment, radii); returns the branches compared.
    A leaf lateral may or may not have its own `Root` record: the lateral and its radius are
    compared on the parent either way."""
    pa, pb = dict(branches(a)), dict(branches(b))
    assert all((pa.get(k) or pb.get(k)).n_laterals == 0 for k in set(pa) ^ set(pb))
    for k in set(pa) & set(pb):
        x, y = pa[k], pb[k]
        np.testing.assert_allclose(y.main, x.main, atol=atol, err_msg=str(k))
        assert y.n_laterals == x.n_laterals, k
        np.testing.assert_allclose(y.attach, x.attach, atol=atol, err_msg=str(k))
        for u, v in zip(x.laterals, y.laterals):
            np.testing.assert_allclose(v, u, atol=atol, err_msg=str(k))
        assert (x.main_radius is None) == (y.main_radius is None), k
        if x.main_radius is not None:
            np.testing.assert_allclose(y.main_radius, x.main_radius, atol=atol, err_msg=str(k))
        if x.n_laterals and x.lateral_radii is not None:
            for u, v in zip(x.lateral_radii, y.lateral_radii):
                np.testing.assert_allclose(v, u, atol=atol, err_msg=str(k))
    return len(pa)


def deepest(root: rs.Root) -> int:
    return max((len(p) for p, r in branches(root) if r.n_laterals), default=0) + 1


def test_write_rsml_round_trip_at_depth_3_with_diameters(tmp_path):
    rng = np.random.default_rng(7)
    roots = [with_radii(r, rng) for r in synthetic_roots(3, depth=3, seed=2)]
    assert all(deepest(r) == 2 for r in roots)  # laterals of laterals: order 2
    path = tmp_path / "deep.rsml"
    write_rsml(roots, path, unit="mm")
    back = read_rsml(path)
    assert len(back) == 3
    for a, b in zip(roots, back):
        assert assert_same_system(a, b, atol=1e-9) > a.n_laterals
        # The reader's per-order records agree with the file's own diameters.
        assert count_by_order(a) == count_by_order(b)
    # Roots rebuilt from a padded depth-3 tree (means, geodesics) round-trip the same way.
    out = rs.to_roots(rs.batch(roots, depth=3, n_points=16, dtype=np.float64), unit="mm")
    write_rsml(out, tmp_path / "tree.rsml")
    for a, b in zip(out, read_rsml(tmp_path / "tree.rsml")):
        assert_same_system(a, b, atol=1e-9)


def test_write_rsml_keeps_radii_given_on_the_parent_only(tmp_path):
    rng = np.random.default_rng(3)
    root = with_radii(synthetic_roots(1, depth=3, seed=5)[0], rng)
    # A user's Root: radii on the parent's `lateral_radii`, none on the children themselves.
    bare = dataclasses.replace(root, children=tuple(dataclasses.replace(c, main_radius=None) for c in root.children))
    write_rsml(bare, tmp_path / "r.rsml", unit="mm")
    back = read_rsml(tmp_path / "r.rsml")[0]
    for u, v in zip(root.lateral_radii, back.lateral_radii):
        np.testing.assert_allclose(v, u, atol=1e-9)


def test_write_rsml_round_trip_of_simulated_plants(tmp_path):
    pytest.importorskip("plantbox")
    from rootshape_jax.datasets import simulated_roots

    plants = simulated_roots("wheat", 1, days=12, seed=1, dim=2, by="plant")
    write_rsml(plants, tmp_path / "w.rsml")
    back = read_rsml(tmp_path / "w.rsml", by="plant")
    assert len(back) == 1 and back[0].metadata["n_axes"] == plants[0].metadata["n_axes"]
    assert deepest(plants[0]) >= 3  # axes, their laterals, and theirs
    assert_same_system(plants[0], back[0], atol=1e-9)


# --------------------------------------------------------------------------------------------
# The demo's whole-root-systems section (run in-process, nothing registered)


def _section_output(tmp_path, monkeypatch, folder):
    from rootshape_jax._cli import _systems
    from rootshape_jax._cli._parser import build_parser
    from rootshape_jax._cli._report import Output

    def no_cplantbox(n, args):
        raise rs.MissingDependencyError("no CPlantBox here")

    monkeypatch.setattr(_systems, "pea_population", no_cplantbox)
    monkeypatch.setattr(_systems, "shared_rsml_folder", lambda: folder)
    args = build_parser().parse_args(["demo", "--quiet", "--out", str(tmp_path / "out")])
    out = Output(args.out, args)
    _systems.run_whole_systems(out, args)
    (section,) = out.sections
    return out, section


def test_demo_section_without_cplantbox_and_without_multi_order_files(tmp_path, monkeypatch):
    folder = tmp_path / "real"
    folder.mkdir()
    write_rsml(synthetic_roots(2, seed=1), folder / "flat.rsml", unit="mm")
    out, sec = _section_output(tmp_path, monkeypatch, folder)
    assert any("CPlantBox" in n and "skipped" in n for n in sec.notes)
    assert any("none of the 1 RSML files" in n and "second-order" in n for n in sec.notes)
    assert not sec.items


def test_demo_section_draws_a_real_multi_order_file(tmp_path, monkeypatch):
    folder = tmp_path / "real"
    folder.mkdir()
    write_rsml(synthetic_roots(2, seed=1), folder / "a_flat.rsml", unit="mm")
    write_rsml(synthetic_roots(1, depth=3, seed=2), folder / "b_deep.rsml", unit="mm")
    out, sec = _section_output(tmp_path, monkeypatch, folder)
    assert [i.path for i in sec.items] == ["systems_real.png"]
    assert (out.folder / "systems_real.png").stat().st_size > 0
    assert any("1 of 2 RSML files" in n and "b_deep.rsml" in n for n in sec.notes)


@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")
def test_no_shared_rsml_file_holds_second_order_laterals():
    """What the demo says about the real files, checked on the XML itself: no `<root>` with
    geometry nested three deep (plant's root > lateral > lateral of the lateral)."""
    import xml.etree.ElementTree as ET

    from rootshape_jax._cli._systems import real_multi_order_files

    found, seen = real_multi_order_files(SHARED / "rsml")
    assert not found and len(seen) >= 10

    def nesting(el, d=0):
        best = d
        for c in el:
            tag = c.tag.split("}")[-1].lower()
            has_geometry = tag == "root" and any(g.tag.split("}")[-1].lower() == "geometry" for g in c)
            best = max(best, nesting(c, d + 1 if has_geometry else d))
        return best

    for path in sorted((SHARED / "rsml").rglob("*.rsml")):
        if path.name == "root_ramifie.rsml":  # topology without geometry (NOTICE.md)
            continue
        assert nesting(ET.parse(path).getroot()) <= 2, path


def _orders_drawn(fig) -> dict[int, int]:
    """Branches drawn per order over every Axes of a figure."""
    total: dict[int, int] = {}
    for ax in fig.axes:
        for k, v in drawn(ax).items():
            total[k] = total.get(k, 0) + len(v)
    return total


@pytest.mark.parametrize("which", ["mean", "modes", "samples", "regression", "dendrogram", "3d"])
def test_every_root_plot_draws_second_order_laterals(which):
    roots = synthetic_roots(4, depth=3, seed=8)
    tree = rs.batch(roots, depth=3, n_points=12)
    per_root = [count_by_order(r) for r in roots]
    n2 = sum(c.get(2, 0) for c in per_root)
    assert n2 > 0
    D = np.array([[abs(i - j) + (i != j) for j in range(4)] for i in range(4)], float)
    if which == "mean":
        fig, _ = P.plot_mean(tree, rs.unstack(tree)[0])
        want = n2 + per_root[0].get(2, 0)  # the samples and the "mean"
    elif which == "modes":
        grid = rs.stack([rs.stack(rs.unstack(tree)[:2]), rs.stack(rs.unstack(tree)[2:])])
        fig, _ = P.plot_modes(grid, [-1.0, 1.0])
        want = n2
    elif which == "samples":
        fig, _ = P.plot_samples_by_distance(tree, np.arange(4.0), n_groups=2)
        want = n2
    elif which == "regression":
        fig, _ = P.plot_regression_sweep(tree, [1.0, 2.0, 3.0, 4.0], trait_name="t")
        want = n2
    elif which == "dendrogram":
        fig, _ = P.plot_dendrogram(D, roots=tree, n_clusters=2)
        want = n2
    else:
        root3 = synthetic_roots(1, depth=3, seed=8, dim=3)[0]
        fig, ax = P.plot_root(root3, projection="3d")
        fig.savefig(io.BytesIO(), format="png")  # 3D lines get their (projected) paths when drawn
        assert {k: len(v) for k, v in drawn(ax).items()} == count_by_order(root3)
        return
    assert _orders_drawn(fig).get(2, 0) == want


def test_output_roots_drop_zero_length_branches_at_every_order():
    """A geodesic's end steps hold branches of zero length (present on the other side only):
    the CLI's RSML output leaves them out, at every order, so reading it back warns of nothing."""
    import warnings

    import equinox as eqx
    import jax.numpy as jnp

    from rootshape_jax._cli._inputs import Population, to_output_roots

    root = small_system()
    tree = rs.batch([root], depth=3, n_points=9, dtype=np.float64)
    # Collapse lateral 1 (no children) and the second child of lateral 0 to their first point,
    # as a geodesic's end step holds them.
    lats = np.asarray(tree.laterals).copy()
    lats[0, 1] = lats[0, 1, :1]
    curves = np.asarray(tree.deeper[0].curves).copy()
    curves[0, 0, 1] = curves[0, 0, 1, :1]
    tree = eqx.tree_at(lambda t: t.laterals, tree, jnp.asarray(lats))
    tree = eqx.tree_at(lambda t: t.deeper[0].curves, tree, jnp.asarray(curves))
    pop = Population(
        roots=[root],
        tree=tree,
        names=["r"],
        normalised=False,
        unit="mm",
        mean_length=1.0,
        mean_seed=root.main[0],
        conditions=None,
    )
    (out,) = to_output_roots(tree, pop, ["r"])
    assert count_by_order(root) == {0: 1, 1: 3, 2: 3}
    assert count_by_order(out) == {0: 1, 1: 2, 2: 2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        buf = io.BytesIO()
        write_rsml(out, buf)
        buf.seek(0)
        back = read_rsml(buf)[0]
    assert count_by_order(back) == {0: 1, 1: 2, 2: 2}


def test_mean_per_plant_writes_a_plant_system_and_regress_per_plant_is_refused(plant_file, tmp_path, capsys):
    from rootshape_jax._cli import main

    out = tmp_path / "m"
    args = ["mean", str(plant_file), "--per", "plant", "--depth", "3", "--points", "12", "--quiet"]
    assert main(args + ["--out", str(out)]) == 0
    mean = read_rsml(out / "mean.rsml", by="plant")
    # One system: a virtual main root (length 0) and its axes, in the input's units.
    assert len(mean) == 1 and mean[0].metadata["virtual_main"] and mean[0].main_length == 0
    assert 1 <= mean[0].n_laterals <= 2
    longest = max(max(r.lateral_lengths) for r in read_rsml(plant_file, by="plant"))
    assert 0.2 * longest < max(mean[0].lateral_lengths) < 2 * longest
    capsys.readouterr()
    assert main(["regress", str(plant_file), "--per", "plant", "--depth", "3", "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert "--per root" in err and "Traceback" not in err
    assert not (tmp_path / "r" / "mean.rsml").exists()


def test_level_weights_option_builds_per_order_weights_and_reaches_the_matrix(tmp_path, capsys):
    from rootshape_jax._cli import main
    from rootshape_jax._cli._common import CLIError, make_weights
    from rootshape_jax._cli._parser import build_parser

    parse = build_parser().parse_args
    args = parse(["distances", "--synthetic", "3", "--depth", "3", "--level-weights", "2,0.5;1,0"])
    w = make_weights(args)
    assert [tuple(float(x) for x in p) for p in w.deeper] == [(2.0, 0.5), (1.0, 0.0)]
    with pytest.raises(CLIError, match="--depth 3"):
        make_weights(parse(["distances", "--synthetic", "3", "--level-weights", "2,0.5"]))
    # A plant's axes are level 1, so its second-order laterals first appear at depth 4.
    plant = ["distances", "x.rsml", "--per", "plant", "--level-weights", "2,0.5", "--depth"]
    with pytest.raises(CLIError, match="--depth 4"):
        make_weights(parse(plant + ["3"]))
    assert [tuple(float(x) for x in p) for p in make_weights(parse(plant + ["4"])).deeper] == [(2.0, 0.5)]
    capsys.readouterr()
    # Refused before any file is read (x.rsml does not exist) or any folder made.
    assert main(plant + ["3", "--out", str(tmp_path / "o")]) == 1
    assert "add --depth 4" in capsys.readouterr().err and not (tmp_path / "o").exists()
    for bad in ("2", "2,1,1", "a,b", "-1,1", "1,1;"):
        assert main(["distances", "--synthetic", "3", "--depth", "3", "--level-weights", bad]) == 2
        assert "--level-weights" in capsys.readouterr().err
    # The first-order laterals' own weights give the default matrix; other weights another.
    base = ["distances", "--synthetic", "3", "--depth", "3", "--points", "12", "--laterals", "3", "--quiet"]
    mats = {}
    for name, extra in (("default", []), ("same", ["--level-weights", "1,1"]), ("heavy", ["--level-weights", "25,0"])):
        assert main(base + extra + ["--out", str(tmp_path / name)]) == 0
        mats[name] = read_matrix(tmp_path / name / "distances.csv")
    np.testing.assert_allclose(mats["same"], mats["default"], rtol=1e-6)
    assert np.all(mats["heavy"][np.triu_indices(3, 1)] > mats["default"][np.triu_indices(3, 1)] * (1 + 1e-3))
