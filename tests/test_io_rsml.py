"""RSML reader and writer on small hand-written fixtures (tests/data/rsml) and round trips."""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from rootshape_jax._errors import RSMLError, RSMLWarning, UnitError
from rootshape_jax._root import Root
from rootshape_jax.io import convert_units, read_rsml, write_rsml
from rootshape_jax.io._rsml import attachment_fraction

DATA = Path(__file__).parent / "data" / "rsml"


def _read_quiet(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean file must not warn
        return read_rsml(path, **kw)


def _brute_fraction(poly: np.ndarray, p: np.ndarray, n: int = 200_001) -> float:
    """Slow reference: arc-length fraction of the nearest of n dense samples of ``poly``."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(0.0, cum[-1], n)
    dense = np.stack([np.interp(s, cum, poly[:, k]) for k in range(poly.shape[1])], axis=1)
    return float(s[np.argmin(np.linalg.norm(dense - p, axis=1))] / cum[-1])


# ------------------------------------------------------------------------------------------
# Variants


def test_basic_plants_roots_laterals_children():
    roots = _read_quiet(DATA / "basic_2d.rsml")
    assert [r.metadata["plant_id"] for r in roots] == ["p1", "p1", "p2"]  # 2 top-level roots in p1
    assert [r.metadata["root_id"] for r in roots] == ["r1", "r2", "r3"]
    assert [r.name for r in roots] == ["primary-a", "primary-b", "basic_2d/p2/r3"]
    a = roots[0]
    assert a.dim == 2 and a.n_laterals == 2
    np.testing.assert_array_equal(a.main, [[10, 0], [10, 10], [10, 20], [10, 30], [10, 40]])
    np.testing.assert_allclose(a.attach, [0.25, 0.75], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(a.laterals[1], [[10, 30], [0, 35]])
    # Order 3 is kept in children, not dropped.
    assert len(a.children) == 2
    c0 = a.children[0]
    assert c0.metadata["root_id"] == "r1.1" and c0.metadata["order"] == 2
    np.testing.assert_array_equal(c0.main, a.laterals[0])
    assert c0.n_laterals == 1 and c0.children[0].metadata["order"] == 3
    np.testing.assert_array_equal(c0.laterals[0], [[20, 15], [20, 25]])
    np.testing.assert_allclose(c0.attach, [0.5], atol=1e-15)  # node 1 of 2 equal segments
    assert c0.children[0].metadata["attach_method"] == "parent-node"
    m = a.metadata
    assert m["unit"] == "pixel" and m["resolution"] == 1.0 and m["software"] == "hand"
    assert m["accession"] == "PO:0020127" and m["plant_label"] == "seedling"
    assert m["file"].endswith("basic_2d.rsml")
    assert roots[1].n_laterals == 0 and roots[1].children == ()


def test_namespace_prefix_caps_no_metadata_z0():
    roots = _read_quiet(DATA / "variants_namespace_caps.rsml")
    assert len(roots) == 1
    r = roots[0]
    assert r.dim == 2  # z = 0 everywhere: returned 2D
    assert r.metadata["plant_id"] == "A" and r.metadata["root_id"] == "main"
    assert r.metadata["unit"] == "pixel"  # no metadata: RSML coordinates are pixels
    np.testing.assert_array_equal(r.laterals[0], [[0, 5], [4, 8]])
    np.testing.assert_allclose(r.attach, [0.5])
    assert r.children[0].metadata["root_id"] == "lat"
    assert r.children[0].metadata["attach_method"] == "parent-node"
    # Empty label: the name falls back to file/plant/id.
    assert r.name == "variants_namespace_caps/A/main"


def test_smartroot_like_units_functions_metadata():
    (r,) = _read_quiet(DATA / "smartroot_like.rsml")
    # inch + 100 dpi: coordinates / 100 are inches.
    assert r.metadata["unit"] == "inch" and r.metadata["resolution"] == 100.0
    np.testing.assert_allclose(r.main[:, 1], [0, 1, 2, 3, 4])
    np.testing.assert_allclose(r.main[:, 0], 1.0)
    assert r.main_length == pytest.approx(4.0)  # matches the file's <length> property
    assert r.metadata["properties"]["length"] == 4.0
    # No parent-node: laterals are attached by projection (they start 0.2 inch away).
    fr = [_brute_fraction(r.main, lat[0]) for lat in r.laterals]
    np.testing.assert_allclose(r.attach, fr, atol=1e-4)
    np.testing.assert_allclose(r.attach, [1.5 / 4, 2.5 / 4], atol=1e-12)
    assert {c.metadata["attach_method"] for c in r.children} == {"projection"}
    assert [c.name for c in r.children] == ["lat_1", "lat_2"]
    # Functions: text samples and value= samples, three domains; never rescaled.
    f = r.metadata["functions"]
    np.testing.assert_array_equal(f["diameter"]["values"], [10.5, 9.0, 8.0, 7.5, 0.0])
    assert f["diameter"]["domain"] == "polyline"
    np.testing.assert_array_equal(f["hairs"]["values"], [1, 2, 3])
    assert f["hairs"]["domain"] == "uniform" and f["hairs"]["origin"] == "base"
    np.testing.assert_array_equal(f["colour"]["positions"], [0, 250])
    np.testing.assert_array_equal(f["colour"]["values"], [0.1, 0.7])
    assert r.metadata["time_index"] == 3 and r.metadata["time_sequence"] == "series-1"
    assert r.metadata["time_unified"] is False
    assert r.metadata["species"] == "Lupinus albus"
    assert r.metadata["accession"] == "PO:0009005"
    assert r.metadata["image"]["label"] == "scan-7"
    # The <rootnavspline> point (999, 999) was ignored.
    assert np.all(r.main < 5)


def test_physical_units_off_keeps_pixels():
    (r,) = _read_quiet(DATA / "smartroot_like.rsml", physical_units=False)
    assert r.metadata["unit"] == "pixel" and r.metadata["file_unit"] == "inch"
    np.testing.assert_allclose(r.main[:, 1], [0, 100, 200, 300, 400])


def test_three_d():
    roots = _read_quiet(DATA / "three_d.rsml")
    assert [r.dim for r in roots] == [3, 3]
    m = roots[0]
    np.testing.assert_array_equal(m.main[-1], [1, 1, 30])  # <x>/<y>/<z> child elements
    np.testing.assert_array_equal(m.laterals[0], [[0, 0, 10], [5, 5, 12]])
    assert m.attach[0] == pytest.approx(10 / m.main_length)
    np.testing.assert_array_equal(roots[1].main, [[10, 0, 0], [10, 5, 0]])  # no z: z = 0
    assert m.metadata["unit"] == "mm"


def test_attachment_parent_node_and_projection():
    (u,) = _read_quiet(DATA / "attach.rsml")
    ids = [c.metadata["root_id"] for c in u.children]
    assert ids == ["far-branch", "off-by-one", "inconsistent", "out-of-range", "none"]
    methods = [c.metadata["attach_method"] for c in u.children]
    assert methods == ["parent-node", "parent-node", "projection", "projection", "projection"]
    total = 60 + 2 * math.hypot(2, 5)
    # far-branch: parent-node 7 says the x = 4 branch although x = 0 is nearer.
    assert u.attach[0] == pytest.approx((30 + 2 * math.hypot(2, 5) + 20) / total, abs=1e-12)
    assert u.attach[0] != pytest.approx(_brute_fraction(u.main, u.laterals[0][0]), abs=1e-2)
    # off-by-one: node 4 given, the lateral starts at node 3.
    assert u.attach[1] == pytest.approx(30 / total, abs=1e-12)
    # inconsistent / out of range / absent: projection, checked against a dense brute force.
    for k in (2, 3, 4):
        assert u.attach[k] == pytest.approx(_brute_fraction(u.main, u.laterals[k][0]), abs=1e-4)
    assert u.attach[2] == pytest.approx(25 / total, abs=1e-12)


def test_attachment_fraction_random_against_bruteforce():
    rng = np.random.default_rng(0)
    for _ in range(20):
        parent = np.cumsum(rng.normal(size=(12, 2)), axis=0)
        lateral = np.stack([rng.normal(size=2) * 3, rng.normal(size=2)])
        frac, method = attachment_fraction(parent, lateral, None)
        assert method == "projection"
        assert frac == pytest.approx(_brute_fraction(parent, lateral[0]), abs=2e-4)
        # A lateral starting exactly on node k with parent-node k: exact node fraction.
        k = int(rng.integers(1, 11))
        seg = np.linalg.norm(np.diff(parent, axis=0), axis=1)
        frac, method = attachment_fraction(parent, np.stack([parent[k], parent[k] + 1]), k)
        assert method == "parent-node"
        assert frac == pytest.approx(np.sum(seg[:k]) / np.sum(seg), abs=1e-12)


# ------------------------------------------------------------------------------------------
# Bad files


def test_bad_roots_non_strict_keeps_the_rest():
    with pytest.warns(RSMLWarning) as rec:
        roots = read_rsml(DATA / "bad_roots.rsml")
    assert [r.metadata["root_id"] for r in roots] == ["ok1", "ok2"]
    ok1 = roots[0]
    assert ok1.n_laterals == 1 and ok1.children[0].metadata["root_id"] == "goodlat"
    assert ok1.attach[0] == pytest.approx(0.5)
    (w,) = rec
    msg = str(w.message)
    assert "bad_roots.rsml" in msg
    for rid in ("badlat", "nogeom", "empty", "onept", "nan", "text", "onlyspline"):
        assert f"root id='{rid}'" in msg
    assert "sub-root" in msg  # the bad lateral's own child is named as skipped with it


_TEMPLATE = """<?xml version="1.0"?>
<rsml><scene><plant id="P">
  <root id="good"><geometry><polyline><point x="0" y="0"/><point x="0" y="9"/></polyline></geometry></root>
  {bad}
</plant></scene></rsml>
"""

_BAD = {
    "no geometry": ('<root id="bad"><properties><a>1</a></properties></root>', "no <geometry>"),
    "empty root": ('<root id="bad"/>', "empty"),
    "one point": ('<root id="bad"><geometry><polyline><point x="1" y="2"/></polyline></geometry></root>', "1 point"),
    "nan": (
        '<root id="bad"><geometry><polyline><point x="1" y="nan"/><point x="1" y="2"/></polyline></geometry></root>',
        "not finite",
    ),
    "nan text": (
        '<root id="bad"><geometry><polyline><point><x>NaN</x><y>1</y></point><point x="1" y="2"/></polyline></geometry></root>',
        "not finite",
    ),
    "not a number": (
        '<root id="bad"><geometry><polyline><point x="one" y="1"/><point x="1" y="2"/></polyline></geometry></root>',
        "not a number",
    ),
    "no y": (
        '<root id="bad"><geometry><polyline><point x="1"/><point x="1" y="2"/></polyline></geometry></root>',
        "no y",
    ),
    "no polyline": ('<root id="bad"><geometry><rootnavspline/></geometry></root>', "no <polyline>"),
    "zero length": (
        '<root id="bad"><geometry><polyline><point x="1" y="1"/><point x="1" y="1"/></polyline></geometry></root>',
        "coincide",
    ),
    "bad lateral": (
        '<root id="main2"><geometry><polyline><point x="5" y="0"/><point x="5" y="9"/></polyline></geometry>'
        '<root id="bad"><geometry><polyline><point x="5" y="3"/></polyline></geometry></root></root>',
        "1 point",
    ),
}


@pytest.mark.parametrize("case", sorted(_BAD))
def test_bad_root_strict_and_non_strict(tmp_path, case):
    bad, expected = _BAD[case]
    path = tmp_path / "one_bad.rsml"
    path.write_text(_TEMPLATE.format(bad=bad))
    with pytest.raises(RSMLError) as err:
        read_rsml(path, strict=True)
    msg = str(err.value)
    assert "one_bad.rsml" in msg and "root id='bad'" in msg and expected in msg
    with pytest.warns(RSMLWarning, match="root id='bad'"):
        roots = read_rsml(path)
    ids = [r.metadata["root_id"] for r in roots]
    if case == "bad lateral":  # only the lateral goes, not its parent
        assert ids == ["good", "main2"] and roots[1].n_laterals == 0
    else:
        assert ids == ["good"]


@pytest.mark.parametrize(
    "name, expected",
    [
        ("malformed.rsml", "not well-formed XML"),
        ("no_scene.rsml", "no <scene>"),
        ("no_geometry.rsml", "nothing readable"),
    ],
)
def test_unreadable_files(name, expected):
    with pytest.raises(RSMLError, match=expected) as err:
        read_rsml(DATA / name, strict=True)
    assert name in str(err.value)
    with pytest.warns(RSMLWarning, match=expected):
        assert read_rsml(DATA / name) == []


def test_missing_file():
    with pytest.raises(FileNotFoundError):
        read_rsml(DATA / "does_not_exist.rsml")


def test_unit_without_resolution(tmp_path):
    path = tmp_path / "u.rsml"
    path.write_text(
        '<rsml><metadata><unit>cm</unit></metadata><scene><plant><root id="a"><geometry><polyline>'
        '<point x="0" y="0"/><point x="0" y="7"/></polyline></geometry></root></plant></scene></rsml>'
    )
    with pytest.raises(RSMLError, match="without <resolution>"):
        read_rsml(path, strict=True)
    with pytest.warns(RSMLWarning, match="without <resolution>"):
        (r,) = read_rsml(path)
    assert r.metadata["unit"] == "pixel" and r.main_length == 7.0


def test_rsml_error_is_value_error():
    assert issubclass(RSMLError, ValueError) and issubclass(RSMLWarning, UserWarning)


# ------------------------------------------------------------------------------------------
# Writing and round trips


def _compare_roots(a: Root, b: Root, *, children: bool = True):
    assert a.name == b.name
    assert a.dim == b.dim
    np.testing.assert_allclose(b.main, a.main, rtol=1e-9, atol=0)
    assert a.n_laterals == b.n_laterals
    for la, lb in zip(a.laterals, b.laterals):
        np.testing.assert_allclose(lb, la, rtol=1e-9, atol=0)
    np.testing.assert_allclose(b.attach, a.attach, rtol=1e-9, atol=1e-12)
    if children and a.children:
        assert len(b.children) == len(a.children)
        for ca, cb in zip(a.children, b.children):
            _compare_roots(ca, cb)


def _random_root(rng, *, d=2, n_lat=3, name="r", plant=None, scale=1.0):
    t = np.linspace(0, 1, 25)[:, None]
    main = np.zeros((25, d))
    main[:, 1] = 100 * t[:, 0] * scale
    main[:, 0] = 5 * np.sin(3 * t[:, 0]) * scale
    if d == 3:
        main[:, 2] = 3 * t[:, 0] ** 2 * scale
    main += rng.normal(scale=0.3 * scale, size=main.shape)
    lats = []
    for _ in range(n_lat):
        i = int(rng.integers(2, 23))
        direction = rng.normal(size=d)
        direction /= np.linalg.norm(direction)
        wobble = rng.normal(scale=0.1, size=(8, d))
        wobble[0] = 0.0  # each lateral starts on the main root
        lats.append(main[i] + np.linspace(0, 20 * scale, 8)[:, None] * direction + wobble)
    meta = {} if plant is None else {"plant_id": plant}
    return Root(main=main, laterals=tuple(lats), name=name, metadata=meta)


@pytest.mark.parametrize("d", [2, 3])
def test_round_trip_random_roots(tmp_path, d):
    rng = np.random.default_rng(1)
    roots = [
        _random_root(rng, d=d, name="alpha", plant="P1"),
        _random_root(rng, d=d, name="beta", plant="P1"),
        _random_root(rng, d=d, n_lat=0, name="gamma"),
        _random_root(rng, d=d, n_lat=5, name="delta", plant="P2"),
    ]
    path = tmp_path / "out.rsml"
    write_rsml(roots, path)
    back = _read_quiet(path)
    assert len(back) == 4
    for a, b in zip(roots, back):
        _compare_roots(a, b, children=False)
        assert b.metadata["unit"] == "pixel"
    assert [b.metadata["plant_id"] for b in back] == ["P1", "P1", "1", "P2"]
    # Laterals written without children get names derived from their root's.
    assert [c.name for c in back[0].children] == ["alpha/1", "alpha/2", "alpha/3"]

    # Plain xml.etree sees the RSML 1.0 structure.
    top = ET.parse(path).getroot()
    assert top.tag == "rsml"
    meta = top.find("metadata")
    assert meta.findtext("version") == "1.0"
    assert meta.findtext("unit") == "pixel" and meta.findtext("resolution") == "1.0"
    assert meta.findtext("software") == "rootshape_jax"
    assert meta.findtext("last-modified")
    plants = top.find("scene").findall("plant")
    assert [p.get("id") for p in plants] == ["P1", "1", "P2"]
    assert [len(p.findall("root")) for p in plants] == [2, 1, 1]
    first = plants[0].find("root")
    assert first.get("label") == "alpha" and first.get("id")
    pts = first.find("geometry/polyline").findall("point")
    assert len(pts) == 25 and (pts[0].get("z") is not None) == (d == 3)
    lats = first.findall("root")
    assert len(lats) == 3
    for lat in lats:
        node = int(lat.find("properties/parent-node").get("value"))
        assert 0 <= node < 25
    ids = [r.get("id") for r in top.iter("root")]
    assert len(ids) == len(set(ids))  # unique ids


def test_write_keeps_plants_of_different_files_apart(tmp_path):
    """Found on the Arabidopsis plate: three dates' files each number their seedlings 1-5, and
    writing the 15 together made 5 plants of 3 axes, each mixing the dates, in a new order."""
    import dataclasses

    rng = np.random.default_rng(4)

    def from_file(name, plant, file):
        r = _random_root(rng, name=name, plant=plant)
        return dataclasses.replace(r, metadata={**r.metadata, "file": file})

    roots = [
        from_file("a1", "1", "day1.rsml"),
        from_file("a2", "2", "day1.rsml"),
        from_file("b1", "1", "day2.rsml"),
        from_file("a1-axis2", "1", "day1.rsml"),  # a second axis of day 1's plant 1
        from_file("b2", "2", "day2.rsml"),
        _random_root(rng, name="loose"),
    ]
    path = tmp_path / "combined.rsml"
    write_rsml(roots, path)
    plants = ET.parse(path).getroot().find("scene").findall("plant")
    assert [p.get("id") for p in plants] == ["1", "2", "1-2", "2-2", "3"]
    assert [[r.get("label") for r in p.findall("root")] for p in plants] == [
        ["a1", "a1-axis2"],
        ["a2"],
        ["b1"],
        ["b2"],
        ["loose"],
    ]
    back = _read_quiet(path)
    assert [b.name for b in back] == ["a1", "a1-axis2", "a2", "b1", "b2", "loose"]
    by_name = {r.name: r for r in roots}
    for b in back:
        _compare_roots(by_name[b.name], b, children=False)
    # No file, an empty one and a stream are one unknown file: their plant 1 is one plant.
    unknown = [from_file(f"u{k}", "1", f) for k, f in enumerate((None, "", "<stream>"))]
    write_rsml(unknown, path)
    plants = ET.parse(path).getroot().find("scene").findall("plant")
    assert [p.get("id") for p in plants] == ["1"] and len(plants[0].findall("root")) == 3


def test_round_trip_units_and_resolution(tmp_path):
    (r,) = _read_quiet(DATA / "smartroot_like.rsml")
    path = tmp_path / "inch.rsml"
    write_rsml(r, path)  # unit and resolution taken from metadata
    top = ET.parse(path).getroot()
    assert top.findtext("metadata/unit") == "inch"
    assert float(top.findtext("metadata/resolution")) == 100.0
    # Stored as pixels, as RSML requires.
    assert float(top.find("scene/plant/root/geometry/polyline/point[2]").get("y")) == pytest.approx(100.0)
    assert top.findtext("metadata/time-sequence/index") == "3"
    (b,) = _read_quiet(path)
    _compare_roots(r, b)
    assert b.metadata["unit"] == "inch"
    assert b.metadata["accession"] == "PO:0009005"
    for name in ("diameter", "hairs", "colour"):
        np.testing.assert_array_equal(b.metadata["functions"][name]["values"], r.metadata["functions"][name]["values"])
    np.testing.assert_array_equal(b.metadata["functions"]["colour"]["positions"], [0, 250])
    # unit= labels, it does not convert: another unit than the roots' own is refused (inch
    # coordinates were written as mm, 25.4 times too small, without a word) ...
    path2 = tmp_path / "mm.rsml"
    with pytest.raises(UnitError, match=r"unit='mm', but the roots' coordinates are in inch.*convert_units"):
        write_rsml(r, path2, unit="mm", resolution=4.0)
    assert not path2.exists()
    # ... converted first, they are written in mm; a resolution may still be chosen.
    write_rsml(convert_units([r], "mm"), path2, unit="mm", resolution=4.0)
    (c,) = _read_quiet(path2)
    assert c.metadata["unit"] == "mm" and float(ET.parse(path2).getroot().findtext("metadata/resolution")) == 4.0
    np.testing.assert_allclose(c.main, 25.4 * r.main, rtol=1e-12)
    # Another spelling of the roots' own unit is that unit: its resolution is kept.
    for spelling in ("inches", "Inch"):
        write_rsml(r, tmp_path / "inches.rsml", unit=spelling)
        assert float(ET.parse(tmp_path / "inches.rsml").getroot().findtext("metadata/resolution")) == 100.0
    # Roots in two spellings of one unit are in one unit.
    mm = Root(main=np.array([[0.0, 0.0], [0.0, 1.0]]), metadata={"unit": "mm"})
    mm2 = Root(main=np.array([[1.0, 0.0], [1.0, 1.0]]), metadata={"unit": "millimetre"})
    write_rsml([mm, mm2], tmp_path / "mm2.rsml")
    assert ET.parse(tmp_path / "mm2.rsml").getroot().findtext("metadata/unit") == "mm"


def test_round_trip_fixtures_with_children(tmp_path):
    for name in ("basic_2d.rsml", "three_d.rsml", "attach.rsml", "variants_namespace_caps.rsml"):
        roots = _read_quiet(DATA / name)
        path = tmp_path / name
        write_rsml(roots, path)
        back = _read_quiet(path)
        assert len(back) == len(roots)
        for a, b in zip(roots, back):
            # Names made of the file stem survive as labels; children recursively.
            _compare_roots(a, b)
            assert b.metadata["plant_id"] == a.metadata["plant_id"]
            assert b.metadata["root_id"] == a.metadata["root_id"]
    # Order-3 root written as a grandchild <root>.
    top = ET.parse(tmp_path / "basic_2d.rsml").getroot()
    r1 = top.find("scene/plant/root")
    assert r1.find("root/root") is not None
    assert r1.find("root/root/properties/parent-node").get("value") == "1"


def test_float32_roots_are_written_with_float32_digits(tmp_path):
    main = np.array([[921.4, 10.1], [921.4, 30.7]], dtype=np.float32)
    lat = np.array([[921.4, 20.3], [930.2, 25.9]], dtype=np.float32)
    r = Root(
        main=main,
        laterals=[lat],
        main_radius=np.full(2, 0.3, np.float32),
        lateral_radii=[np.full(2, 0.1, np.float32)],
        metadata={"unit": "mm"},
    )
    path = tmp_path / "single.rsml"
    write_rsml(r, path)
    text = path.read_text()
    assert 'x="921.4"' in text and 'y="30.7"' in text and 'value="0.6"' in text
    assert "921.40002" not in text
    (back,) = _read_quiet(path)
    # The shortest float32 text reads back as the same float32.
    np.testing.assert_array_equal(np.asarray(back.main, np.float32), main)
    np.testing.assert_array_equal(np.asarray(back.laterals[0], np.float32), lat)


def test_write_errors(tmp_path):
    r = Root(main=np.array([[0.0, 0.0], [0.0, 1.0]]), metadata={"unit": "mm"})
    s = Root(main=np.array([[0.0, 0.0], [0.0, 1.0]]), metadata={"unit": "inch"})
    with pytest.raises(RSMLError, match="different units"):
        write_rsml([r, s], tmp_path / "x.rsml")
    with pytest.raises(RSMLError, match="resolution must be 1"):
        write_rsml([Root(main=r.main)], tmp_path / "x.rsml", unit="pixel", resolution=3)
    with pytest.raises(UnitError, match="does not convert"):
        write_rsml([r], tmp_path / "x.rsml", unit="pixel")
    with pytest.raises(RSMLError, match="positive"):
        write_rsml([r], tmp_path / "x.rsml", resolution=-1)
    with pytest.raises(RSMLError, match="no roots"):
        write_rsml([], tmp_path / "x.rsml")
    with pytest.raises(TypeError, match="expected a Root"):
        write_rsml([np.zeros((3, 2))], tmp_path / "x.rsml")
    bad_child = Root(
        main=np.array([[0.0, 0.0], [0.0, 2.0]]),
        laterals=(np.array([[0.0, 1.0], [1.0, 1.0]]),),
        children=(Root(main=np.array([[0.0, 1.0], [2.0, 1.0]])),),
    )
    with pytest.raises(RSMLError, match="children\\[0\\].main differs"):
        write_rsml(bad_child, tmp_path / "x.rsml")


def test_mixed_dimensions_written_as_3d(tmp_path):
    a = Root(main=np.array([[0.0, 0.0], [0.0, 5.0]]), name="flat")
    b = Root(main=np.array([[0.0, 0.0, 1.0], [0.0, 5.0, 2.0]]), name="deep")
    write_rsml([a, b], tmp_path / "m.rsml")
    back = _read_quiet(tmp_path / "m.rsml")
    assert [x.dim for x in back] == [3, 3]
    np.testing.assert_array_equal(back[0].main, [[0, 0, 0], [0, 5, 0]])
