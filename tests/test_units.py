"""Length units: `io.convert_units` (inch + dpi, pixel + resolution, cm), `--unit`, unit-named
trait columns, and normalised outputs that say so."""

from __future__ import annotations

import csv
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rootshape_jax as rs
from rootshape_jax import io
from rootshape_jax.datasets import synthetic_roots

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rsml"


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rootshape_jax", *map(str, args)], capture_output=True, text=True, timeout=900
    )


def in_unit(roots, unit):
    return [dataclasses.replace(r, metadata=dict(r.metadata, unit=unit)) for r in roots]


def test_inch_with_dpi_to_mm_round_trips_through_rsml(tmp_path):
    roots = in_unit(synthetic_roots(2, seed=3), "inch")
    io.write_rsml(roots, tmp_path / "a.rsml", unit="inch", resolution=300.0)
    back = io.read_rsml(tmp_path / "a.rsml")
    assert back[0].metadata["unit"] == "inch" and back[0].metadata["resolution"] == 300.0
    mm = io.convert_units(back, "mm")
    for r, m in zip(back, mm):
        np.testing.assert_allclose(m.main, 25.4 * r.main, rtol=1e-12)
        for la, lb in zip(r.laterals, m.laterals):
            np.testing.assert_allclose(lb, 25.4 * la, rtol=1e-12)
        np.testing.assert_allclose(m.attach, r.attach)
        assert m.metadata["unit"] == "mm" and m.metadata["resolution"] == pytest.approx(300 / 25.4)
        assert m.main_length == pytest.approx(25.4 * r.main_length)
    # Written in mm, the file keeps the same pixel coordinates (resolution now per mm).
    io.write_rsml(mm, tmp_path / "b.rsml")
    again = io.read_rsml(tmp_path / "b.rsml")
    np.testing.assert_allclose(again[0].main, mm[0].main, rtol=1e-9)
    assert again[0].metadata["unit"] == "mm"


def test_pixel_with_resolution_and_cm(tmp_path):
    roots = in_unit(synthetic_roots(1, seed=4), "cm")
    io.write_rsml(roots, tmp_path / "c.rsml", unit="cm", resolution=50.0)
    px = io.read_rsml(tmp_path / "c.rsml", physical_units=False)
    assert px[0].metadata["unit"] == "pixel" and px[0].metadata["file_unit"] == "cm"
    mm = io.convert_units(px, "mm")
    np.testing.assert_allclose(mm[0].main, px[0].main / 50.0 * 10.0, rtol=1e-12)
    cm = io.read_rsml(tmp_path / "c.rsml")
    np.testing.assert_allclose(io.convert_units(cm, "mm")[0].main, mm[0].main, rtol=1e-12)
    assert io.convert_units(cm, "cm")[0] is cm[0]  # already in that unit: unchanged


def test_radii_and_children_convert_too():
    r = synthetic_roots(1, seed=5)[0]
    r = dataclasses.replace(
        r,
        metadata=dict(r.metadata, unit="cm"),
        main_radius=np.full(r.main.shape[0], 0.1),
        lateral_radii=tuple(np.full(lat.shape[0], 0.05) for lat in r.laterals),
    )
    m = io.convert_units(r, "mm")[0]
    np.testing.assert_allclose(m.main_radius, 1.0)
    np.testing.assert_allclose(m.lateral_radii[0], 0.5)


def test_pixels_without_resolution_and_unknown_units_fail_clearly(tmp_path):
    roots = in_unit(synthetic_roots(1, seed=6), "pixel")
    io.write_rsml(roots, tmp_path / "p.rsml")
    px = io.read_rsml(tmp_path / "p.rsml")
    with pytest.raises(rs.UnitError, match=r"p.rsml: coordinates are in pixels with no physical resolution"):
        io.convert_units(px, "mm")
    with pytest.raises(rs.UnitError, match="unknown length unit 'furlong'"):
        io.convert_units(in_unit(synthetic_roots(1), "mm"), "furlong")
    with pytest.raises(rs.UnitError, match="has no metadata\\['unit'\\]"):
        io.convert_units([rs.Root(main=np.array([[0.0, 0.0], [0.0, 1.0]]))], "mm")


def test_read_folder_unit(tmp_path):
    io.write_rsml(in_unit(synthetic_roots(1, seed=7), "inch"), tmp_path / "x.rsml", unit="inch", resolution=100.0)
    raw = io.read_folder(tmp_path)
    mm = io.read_folder(tmp_path, unit="mm")
    np.testing.assert_allclose(mm[0].main, 25.4 * raw[0].main)


@pytest.mark.parametrize(
    ("name", "unit", "expected"),
    [
        ("main_length", "mm", "main_length_mm"),
        ("main_length", "pixel", "main_length_px"),
        ("convex_hull_area", "mm", "convex_hull_area_mm2"),
        ("convex_hull_volume", "inch", "convex_hull_volume_inch3"),
        ("lateral_density", "cm", "lateral_density_per_cm"),
        ("mean_insertion_angle", "mm", "mean_insertion_angle_deg"),
        ("n_laterals", "mm", "n_laterals"),
        ("main_tortuosity", "mm", "main_tortuosity"),
        ("main_length", None, "main_length"),
        ("name", "mm", "name"),
    ],
)
def test_trait_columns_name_their_unit(name, unit, expected):
    assert rs.trait_column(name, unit) == expected


def test_every_length_trait_has_a_dimension():
    from rootshape_jax._traits import TRAIT_LENGTH_POWER, TRAIT_NAMES

    assert set(TRAIT_NAMES) - {"mean_insertion_angle"} == set(TRAIT_LENGTH_POWER)


def test_normalised_unit_round_trips_and_is_never_pixel(tmp_path):
    tree = rs.batch(synthetic_roots(2, seed=8), n_points=20, normalise_scale=True)
    roots = rs.to_roots(tree, unit=io.NORMALISED_UNIT)
    io.write_rsml(roots, tmp_path / "mean.rsml")
    text = (tmp_path / "mean.rsml").read_text()
    assert "<unit>normalised (main-root length = 1)</unit>" in text and "pixel" not in text
    back = io.read_rsml(tmp_path / "mean.rsml")
    assert back[0].metadata["unit"] == io.NORMALISED_UNIT
    np.testing.assert_allclose(back[0].main, roots[0].main, atol=1e-9)
    assert io.unit_label("pixel") == "px" and io.unit_label(None) == "input units"


def test_figure_unit_of_the_command_line():
    import argparse

    from rootshape_jax._cli._inputs import prepare
    from rootshape_jax._cli._steps import figure_note, figure_unit

    roots = in_unit(synthetic_roots(2, seed=9), "pixel")
    for norm, bar, note in (
        (True, "× main-root length", "(coordinates normalised (main-root length = 1))"),
        (False, "px", "(coordinates in px)"),
    ):
        pop = prepare(roots, argparse.Namespace(laterals=None, points=12, normalise_scale=norm))
        assert figure_unit(pop) == bar and figure_note(pop).strip() == note
        assert "pixel" not in figure_unit(pop) + figure_note(pop)


# --------------------------------------------------------------------------------------------
# Command line


def test_cli_unit_mm_converts_inch_traits(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    io.write_rsml(in_unit(synthetic_roots(2, seed=1), "inch"), d / "a.rsml", unit="inch", resolution=200.0)
    (d / "bad.rsml").write_text("<rsml>")
    proc = run_cli("traits", d, "--out", tmp_path / "o1")
    assert proc.returncode == 0, proc.stderr
    proc = run_cli("traits", d, "--unit", "mm", "--out", tmp_path / "o2")
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "o1" / "traits.csv", newline="") as f:
        inch = list(csv.DictReader(f))
    with open(tmp_path / "o2" / "traits.csv", newline="") as f:
        mm = list(csv.DictReader(f))
    assert "main_length_inch" in inch[0] and "main_length_mm" in mm[0] and "convex_hull_area_mm2" in mm[0]
    assert "lateral_density_per_mm" in mm[0] and "mean_insertion_angle_deg" in mm[0]
    for a, b in zip(inch, mm):
        assert float(b["main_length_mm"]) == pytest.approx(25.4 * float(a["main_length_inch"]), rel=1e-9)
        assert float(b["convex_hull_area_mm2"]) == pytest.approx(25.4**2 * float(a["convex_hull_area_inch2"]), rel=1e-9)
        assert b["unit"] == "mm"


def test_cli_unit_mm_on_pixels_without_resolution_is_one_line(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    io.write_rsml(in_unit(synthetic_roots(1, seed=1), "pixel"), d / "a.rsml")
    proc = run_cli("traits", d, "--unit", "mm", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "coordinates are in pixels with no physical resolution" in lines[0], proc.stderr


def test_pixel_size_puts_pixel_tracings_in_a_unit(tmp_path):
    """RSML tracings in pixels without a resolution (RootNav, RhizoScan) take the pixel size
    given, as images do; files with their own unit and resolution keep them."""
    roots = in_unit(synthetic_roots(2, seed=2), "pixel")
    io.write_rsml(roots, tmp_path / "px.rsml")
    io.write_rsml(in_unit(synthetic_roots(1, seed=3), "inch"), tmp_path / "own.rsml", unit="inch", resolution=100.0)
    raw = io.read_folder(tmp_path)
    mm = io.read_folder(tmp_path, pixel_size=0.05)
    cm = io.read_folder(tmp_path, pixel_size=0.005, unit="cm")
    by = {r.metadata["source_file"]: i for i, r in enumerate(raw)}
    own = by[str(tmp_path / "own.rsml")]
    pixel = [i for i in range(len(raw)) if raw[i].metadata["unit"] == "pixel"]
    assert len(pixel) == 2
    for i in pixel:
        assert mm[i].metadata["unit"] == "mm" and cm[i].metadata["unit"] == "cm"
        np.testing.assert_allclose(mm[i].main, 0.05 * raw[i].main, rtol=1e-12)
        np.testing.assert_allclose(cm[i].main, 0.005 * raw[i].main, rtol=1e-12)
        np.testing.assert_allclose(mm[i].lateral_lengths, 0.05 * raw[i].lateral_lengths, rtol=1e-12)
        # Written back, the file's pixels and its new resolution give the same coordinates.
        io.write_rsml([mm[i]], tmp_path / "back.out")
        (again,) = io.read_rsml(tmp_path / "back.out")
        np.testing.assert_allclose(again.main, mm[i].main, rtol=1e-6)
    assert mm[own].metadata["unit"] == "inch"  # its own <unit> and <resolution>
    np.testing.assert_allclose(mm[own].main, raw[own].main)
    np.testing.assert_allclose(cm[own].main, 2.54 * raw[own].main, rtol=1e-12)  # --unit still converts
    # From the command line: trait columns in mm, lengths scaled.
    d = tmp_path / "only_px"
    d.mkdir()
    io.write_rsml(roots, d / "px.rsml")
    proc = run_cli("traits", d, "--pixel-size", "0.05", "--out", tmp_path / "o")
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "o" / "traits.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["main_length_mm"]) for r in rows] == pytest.approx([0.05 * r.main_length for r in roots], rel=1e-9)


@pytest.mark.skipif(not (SHARED / "smartroot" / "lupin.rsml").is_file(), reason="shared data absent")
def test_real_smartroot_inches_to_mm():
    lupin = io.read_rsml(SHARED / "smartroot" / "lupin.rsml")
    assert lupin[0].metadata["unit"] == "inch"
    mm = io.convert_units(lupin, "mm")
    assert mm[0].main_length == pytest.approx(25.4 * lupin[0].main_length, rel=1e-12)
    px = io.read_rsml(SHARED / "smartroot" / "lupin.rsml", physical_units=False)
    np.testing.assert_allclose(io.convert_units(px, "mm")[0].main, mm[0].main, rtol=1e-9)


def test_cli_refuses_to_compare_sizes_across_units(tmp_path, capsys):
    # An inch file and a pixel file in one folder: their sizes cannot be compared.
    d = tmp_path / "mixed"
    d.mkdir()
    io.write_rsml(in_unit(synthetic_roots(2, seed=1), "inch"), d / "a.rsml", unit="inch", resolution=200.0)
    io.write_rsml(in_unit(synthetic_roots(2, seed=2), "pixel"), d / "b.rsml")
    proc = run_cli("distances", d, "--no-normalise-scale", "--points", "12", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert len(lines) == 1 and "different units (inch: a.rsml; pixel: b.rsml)" in lines[0] and "--unit" in lines[0], (
        proc.stderr
    )
    assert not (tmp_path / "o" / "distances.csv").exists()
    # Scale-normalised, the shapes are compared, with a warning that made roots stay normalised.
    from rootshape_jax._cli._inputs import _check_units

    roots = io.read_folder(d)
    assert _check_units(roots, normalised=True) is True
    assert "stay at the normalised scale" in capsys.readouterr().err
    # regress works from lengths: refused before any computation.
    io.write_rsml(in_unit(synthetic_roots(2, seed=3), "pixel"), d / "c.rsml")
    proc = run_cli("regress", d, "--points", "12", "--out", tmp_path / "r")
    assert proc.returncode == 1 and "traits (lengths) cannot be regressed" in proc.stderr, proc.stderr
    assert not (tmp_path / "r" / "mean.rsml").exists()
    # A geodesic between an inch root and a pixel root is written at the normalised scale, and
    # says so: it starts at a of main-root length 1.
    proc = run_cli(
        "geodesic", d / "a.rsml", d / "b.rsml", "--points", "12", "--steps", "3", "--quiet", "--out", tmp_path / "g"
    )
    assert proc.returncode == 0, proc.stderr
    (start,) = io.read_rsml(tmp_path / "g" / "geodesic_step_00.rsml")
    assert start.metadata["unit"] == io.NORMALISED_UNIT
    # (up to the SRVF-to-curve round trip of a T = 12 polyline; the inputs are ~100 units long)
    assert start.main_length == pytest.approx(1.0, rel=1e-2)


def test_spellings_of_one_unit_are_one_unit(capsys):
    from rootshape_jax._cli._inputs import _check_units

    roots = in_unit(synthetic_roots(1, seed=1), "mm") + in_unit(synthetic_roots(1, seed=2), "millimetre")
    _check_units(roots, normalised=False)  # the same unit: no error, no warning
    assert "different units" not in capsys.readouterr().err


def test_many_laterals_hint(capsys):
    from types import SimpleNamespace

    from rootshape_jax._cli._inputs import MANY_LATERALS, _hint_many_laterals

    root = synthetic_roots(1, seed=1)[0]
    big = dataclasses.replace(
        root,
        laterals=tuple(root.laterals[0] for _ in range(MANY_LATERALS + 1)),
        attach=np.full(MANY_LATERALS + 1, root.attach[0]),
        children=(),
        lateral_radii=None,
        name="big",
    )
    _hint_many_laterals([root, big], SimpleNamespace(laterals=None))
    assert f"big has {MANY_LATERALS + 1} laterals" in capsys.readouterr().err
    _hint_many_laterals([root, big], SimpleNamespace(laterals=20))  # --laterals given: quiet
    _hint_many_laterals([root], SimpleNamespace(laterals=None))
    assert capsys.readouterr().err == ""
    # --per plant: the laterals that cost are an axis's (the plant's own "laterals" are its
    # axes); --laterals N keeps N per axis and every axis (from a tour: lupin + maize plants
    # kept all 421 maize laterals and got no hint).
    from rootshape_jax._cli._inputs import _limit_laterals

    plant = io.plant_system([big, root], name="plant")
    _hint_many_laterals([plant], SimpleNamespace(laterals=None))
    assert f"an axis of plant has {MANY_LATERALS + 1} laterals" in capsys.readouterr().err
    limited = _limit_laterals(plant, 3)
    assert limited.n_laterals == 2 and [a.n_laterals for a in limited.children] == [3, min(3, root.n_laterals)]
    assert _limit_laterals(big, 3).n_laterals == 3
    assert rs.batch([limited], depth=3).deeper[0].mask.sum() == 3 + min(3, root.n_laterals)


def test_batch_refuses_roots_in_different_units_unless_normalised():
    """Found on the real files: lupin (inch) batched with its own pixel copy gave d = 94.8 and
    no word. Now batch names the units and the two ways out; spellings of one unit, roots
    without a unit, and scale-normalised batches (shapes only) pass."""
    a, b = synthetic_roots(2, seed=3)
    with pytest.raises(rs.UnitError, match=r"different units .*inch.*pixel.*convert_units.*normalise_scale=True"):
        rs.batch(in_unit([a], "inch") + in_unit([b], "pixel"))
    assert rs.batch(in_unit([a], "inch") + in_unit([b], "pixel"), normalise_scale=True).main.shape[0] == 2
    assert rs.batch(in_unit([a], "mm") + in_unit([b], "millimetre")).main.shape[0] == 2
    assert rs.batch(in_unit([a], "\u00b5m") + in_unit([b], "\u03bcm")).main.shape[0] == 2  # micro sign, Greek mu
    assert rs.batch(in_unit([a], "Micrometers") + in_unit([b], "um")).main.shape[0] == 2
    assert rs.batch(in_unit([a], "") + in_unit([b], "inch")).main.shape[0] == 2  # "" is no unit
    no_unit = dataclasses.replace(b, metadata={k: v for k, v in b.metadata.items() if k != "unit"})
    assert rs.batch(in_unit([a], "px") + [no_unit]).main.shape[0] == 2  # no unit: not checked
    lupin = SHARED / "smartroot" / "lupin.rsml"
    if lupin.exists():
        inch = io.read_rsml(lupin)
        pixel = io.read_rsml(lupin, physical_units=False)
        with pytest.raises(rs.UnitError):
            rs.batch(inch + pixel)
        # In one unit the copies are the same root.
        assert float(rs.distance(*rs.unstack(rs.batch(inch + io.convert_units(pixel, "inch"), n_points=32)))) < 1e-6


def test_batch_float64_without_x64_is_an_error_not_float32():
    """With JAX's 64-bit mode off, dtype=float64 used to give a float32 tree (and skip the
    precision warning, which looked at the float64 values)."""
    import jax

    (a,) = synthetic_roots(1, seed=4)
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="jax_enable_x64"):
            rs.batch([a], dtype=np.float64)
        assert rs.batch([a]).main.dtype == np.float32
    assert rs.batch([a], dtype=np.float64).main.dtype == np.float64


def test_compare_to_tracing_refuses_two_units():
    """Found on RootNav: an image read in mm against its tracing in px matched no plant
    (recall 0, length ratio 0.093) and said nothing."""
    a, b = synthetic_roots(2, seed=6)
    with pytest.raises(rs.UnitError, match=r"extracted roots are in mm and the traced roots in pixel.*convert_units"):
        io.compare_to_tracing(in_unit([a], "mm"), in_unit([b], "pixel"), elastic=False)
    # One unit (any spelling), or no unit on one side, is compared as before.
    same = io.compare_to_tracing(in_unit([a], "mm"), in_unit([a], "millimetre"), elastic=False)
    assert len(same.plants) == 1 and same.recall == 1.0
    no_unit = dataclasses.replace(a, metadata={k: v for k, v in a.metadata.items() if k != "unit"})
    assert len(io.compare_to_tracing([no_unit], in_unit([a], "pixel"), elastic=False).plants) == 1


def test_unit_names_nothing_can_convert_are_refused_where_they_enter(tmp_path):
    # "parsec" (or a typo) was stored as the roots' unit by every door in, and failed only
    # later (convert_units, --unit) or never (figures labelled in parsecs).
    roots = in_unit(synthetic_roots(1, seed=9), "mm")
    io.write_rsml(roots, tmp_path / "mm.rsml")
    text = (tmp_path / "mm.rsml").read_text()
    assert "<unit>mm</unit>" in text
    bad = tmp_path / "parsec.rsml"
    bad.write_text(
        text.replace("<unit>mm</unit>", "<unit>parsec</unit>").replace(
            "<resolution>1.0</resolution>", "<resolution>2</resolution>"
        )
    )
    assert "<resolution>2</resolution>" in bad.read_text()
    # Read: kept in pixels (the stored coordinates, not divided by the resolution), with a
    # warning naming the unit; strict raises.
    with pytest.warns(rs.RSMLWarning, match="<unit> 'parsec' is not a unit rootshape_jax knows"):
        (back,) = io.read_rsml(bad)
    assert back.metadata["unit"] == "pixel"
    np.testing.assert_allclose(back.main, io.read_rsml(tmp_path / "mm.rsml")[0].main, rtol=1e-6)
    with pytest.raises(rs.RSMLError, match="parsec"):
        io.read_rsml(bad, strict=True)
    # physical_units=False asks for pixels anyway: nothing to warn about.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert io.read_rsml(bad, physical_units=False)[0].metadata["unit"] == "pixel"
    # Written, stated or carried, and given to to_roots: refused, naming the known units.
    with pytest.raises(rs.UnitError, match="write_rsml: unknown unit 'parsec'; use pixel, a length unit"):
        io.write_rsml(in_unit(roots, "parsec"), tmp_path / "x.rsml")
    with pytest.raises(rs.UnitError, match="unknown unit 'furlong'"):
        io.write_rsml(in_unit(roots, "furlong"), tmp_path / "x.rsml", unit="furlong")
    tree = rs.batch(roots, n_points=12)
    with pytest.raises(rs.UnitError, match="to_roots: unknown unit 'parsec'"):
        rs.to_roots(tree, unit="parsec")
    for unit in ("mm", "Inches", "px", io.NORMALISED_UNIT):
        assert rs.to_roots(tree, unit=unit)[0].metadata["unit"] == unit
    assert not (tmp_path / "x.rsml").exists()


def test_an_images_unit_needs_its_scale_and_a_length_unit():
    from rootshape_jax.io._image import image_scale

    assert image_scale(None, 0.05, "mm") == (0.05, "mm")
    assert image_scale(None, None, "pixel") == (None, "pixel")
    assert image_scale(20.0, None, "pixel") == (0.05, "mm")
    with pytest.raises(rs.UnitError, match="unknown length unit 'parsec'"):
        image_scale(None, 0.05, "parsec")
    with pytest.raises(ValueError, match="unit='mm' without pixel_size"):
        image_scale(None, None, "mm")
    with pytest.raises(TypeError, match="unit must be a string"):
        image_scale(None, 0.05, None)
    image = np.zeros((40, 40))
    image[5:35, 19:21] = 1.0
    with pytest.raises(rs.UnitError, match="parsec"):
        io.roots_from_image(image, pixel_size=0.1, unit="parsec")
