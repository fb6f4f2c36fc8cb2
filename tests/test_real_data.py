"""The io readers on real public data in ../shared/data (skipped in a clone without it).

See shared/data/NOTICE.md for the sources: RhizoScan Arabidopsis plate (3 dates + photograph),
SmartRoot lupin / maize / root_ramifie (no geometry), RootNav oilseed rape.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from rootshape_jax._errors import RSMLError, RSMLWarning
from rootshape_jax.io import read_rsml, roots_from_image, write_rsml

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RSML_FILES = sorted((DATA / "rsml").glob("*/*.rsml")) if DATA.is_dir() else []
PLATE_IMAGE = DATA / "images" / "arabidopsis_plate" / "2012_11_19_18h00_chl110_1_1.jpg"
PLATE_RSML = DATA / "rsml" / "arabidopsis_plate" / "2012_11_19_18h00_chl110_1_1.rsml"

pytestmark = pytest.mark.skipif(
    not RSML_FILES, reason=f"real data folder {DATA} not present (only in the team workspace)"
)


def _usable(root_el) -> bool:
    poly = root_el.find("geometry/polyline")
    return poly is not None and len([p for p in poly if p.tag.lower() == "point"]) >= 2


def _raw_counts(path):
    """Independent plain-ElementTree counts: per plant, per usable top-level root, the number
    of usable direct child roots."""
    top = ET.parse(path).getroot()
    out = []
    for plant in top.find("scene").findall("plant"):
        out.append([sum(_usable(c) for c in r.findall("root")) for r in plant.findall("root") if _usable(r)])
    return out


def _count(root) -> int:
    return 1 + sum(_count(c) for c in root.children)


@pytest.mark.parametrize("path", RSML_FILES, ids=lambda p: p.name)
def test_counts_match_raw_xml(path):
    raw = _raw_counts(path)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        roots = read_rsml(path)
    n_plants_raw = sum(1 for p in raw if p)
    assert len({r.metadata["plant_id"] for r in roots}) == n_plants_raw
    assert [r.n_laterals for r in roots] == [n for plant in raw for n in plant]
    # Every <root> element is either returned (as a Root or a child, recursively) or skipped,
    # and a warning is issued if and only if something was skipped.
    n_elements = len(list(ET.parse(path).getroot().iter("root")))
    n_read = sum(_count(r) for r in roots)
    assert n_read <= n_elements
    assert (n_read < n_elements) == any(issubclass(w.category, RSMLWarning) for w in rec)
    for r in roots:
        assert r.metadata["file"] == str(path)
        assert len(r.children) == r.n_laterals
        assert np.all((r.attach >= 0) & (r.attach <= 1))


def test_expected_structure_of_known_files():
    by_name = {p.name: p for p in RSML_FILES}
    plate = read_rsml(by_name["2012_11_19_18h00_chl110_1_1.rsml"], strict=True)
    assert len(plate) == 5 and [r.n_laterals for r in plate] == [4, 5, 4, 3, 4]
    # RhizoScan gives exact parent-node indices: every lateral attached through them.
    assert {c.metadata["attach_method"] for r in plate for c in r.children} == {"parent-node"}
    (lupin,) = read_rsml(by_name["lupin.rsml"], strict=True)
    assert lupin.n_laterals == 60 and lupin.metadata["unit"] == "inch"
    # SmartRoot writes each root's length (cm) as a property: our inch lengths agree.
    ratios = [lupin.main_length * 2.54 / lupin.metadata["properties"]["length"]]
    ratios += [c.main_length * 2.54 / c.metadata["properties"]["length"] for c in lupin.children]
    np.testing.assert_allclose(ratios, 1.0, atol=1e-4)
    with pytest.raises(RSMLError, match="root id="):
        read_rsml(by_name["maize.rsml"], strict=True)  # 17 one-point laterals
    with pytest.warns(RSMLWarning, match="skipped 17"):
        (maize,) = read_rsml(by_name["maize.rsml"])
    assert maize.n_laterals == 438 - 17
    with pytest.raises(RSMLError, match="nothing readable"):
        read_rsml(by_name["root_ramifie.rsml"], strict=True)
    with pytest.warns(RSMLWarning, match="nothing readable"):
        assert read_rsml(by_name["root_ramifie.rsml"]) == []
    (osr,) = read_rsml(by_name["B_osr_0099.rsml"], strict=True)  # empty ID attributes
    assert osr.n_laterals == 61 and osr.name == "B_osr_0099/1/1"


@pytest.mark.parametrize("path", [p for p in RSML_FILES if p.name != "root_ramifie.rsml"], ids=lambda p: p.name)
def test_real_round_trip(tmp_path, path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RSMLWarning)
        roots = read_rsml(path)
    out = tmp_path / path.name
    write_rsml(roots, out)
    back = read_rsml(out, strict=True)
    assert [b.name for b in back] == [r.name for r in roots]
    for a, b in zip(roots, back):
        np.testing.assert_allclose(b.main, a.main, rtol=1e-9)
        assert b.n_laterals == a.n_laterals
        for la, lb in zip(a.laterals, b.laterals):
            np.testing.assert_allclose(lb, la, rtol=1e-9)
        np.testing.assert_allclose(b.attach, a.attach, atol=1e-9)
        assert b.metadata["unit"] == a.metadata["unit"]


def test_plate_dates_written_together_stay_fifteen_plants(tmp_path):
    """The three dates' files each number their seedlings 1-5: written together they were 5
    plants of 3 axes mixing the dates. Now 15 plants, in the input order."""
    files = sorted((DATA / "rsml" / "arabidopsis_plate").glob("*.rsml"))
    roots = [r for f in files for r in read_rsml(f)]
    assert len(roots) == 15 and len({r.metadata["plant_id"] for r in roots}) == 5
    out = tmp_path / "plate.rsml"
    write_rsml(roots, out)
    assert len(read_rsml(out, by="plant")) == 15
    back = read_rsml(out, strict=True)
    assert len(back) == 15
    for a, b in zip(roots, back):
        np.testing.assert_allclose(b.main, a.main, rtol=1e-9)
        assert b.n_laterals == a.n_laterals


# The seedling region of the plate (rows, then columns), inside the plate's rim and above its
# hand-written labels; thin roots on a photographed plate need background flattening.
_PLATE_OPTS = dict(roi=(450, 1200, 1450, 2950), background=15, threshold="triangle", min_root_length=150, close_gaps=7)


@pytest.mark.slow
@pytest.mark.skipif(not PLATE_IMAGE.is_file(), reason="plate photograph not present")
def test_plate_photograph_against_rsml():
    ref = read_rsml(PLATE_RSML, strict=True)
    roots = roots_from_image(PLATE_IMAGE, **_PLATE_OPTS)
    assert len(roots) == 5  # the plate's five seedlings, sorted left to right like the plants
    for r, t in zip(roots, ref):
        # Tips agree with the hand tracing within a few pixels (measured <= 5 px).
        assert np.linalg.norm(r.main[-1] - t.main[-1]) < 8
        # From the top-most pixel, the main path includes the cotyledons and hypocotyl above
        # the traced root base: measured ratios 1.078-1.145.
        assert 1.0 < r.main_length / t.main_length < 1.2
    # Starting each root at the traced base (base points in image x, y): measured 0.7-1.2 %.
    bases = np.array([t.main[0] for t in ref])
    from_bases = roots_from_image(PLATE_IMAGE, base=bases, **_PLATE_OPTS)
    rel = [r.main_length / t.main_length - 1 for r, t in zip(from_bases, ref)]
    assert max(abs(x) for x in rel) < 0.03


PLATE_2111 = DATA / "rsml" / "arabidopsis_plate" / "2012_11_21_09h00_chl110_1_1.rsml"


@pytest.mark.skipif(not PLATE_2111.is_file(), reason="plate tracing not present")
def test_distances_of_real_tracings_do_not_depend_on_place_or_dtype():
    # RhizoScan tracings step back along pixel rows (exact 180° turns), where an SRVF node's
    # direction was rounding noise, and every normalised main root has length 1, where the
    # pair's registration order was: moving the roots or computing in float32 changed
    # distances by up to 1.5 % (measured on these pairs before the fix).
    import dataclasses

    import rootshape_jax as rs

    roots = [rs.limit_laterals(r, 8) for r in read_rsml(PLATE_2111)[:4]]

    def at_origin(r):
        o = r.main[0]
        return dataclasses.replace(r, main=r.main - o, laterals=tuple(x - o for x in r.laterals))

    pairs = ([0, 0, 0, 1, 1, 2], [1, 2, 3, 2, 3, 3])

    def distances(rr, dtype):
        t = rs.batch(rr, n_points=100, normalise_scale=True, dtype=dtype)
        a, b = (rs.stack([rs.unstack(t)[i] for i in idx]) for idx in pairs)
        return np.asarray(rs.distance(a, b), np.float64)

    far = distances(roots, np.float64)
    np.testing.assert_allclose(distances([at_origin(r) for r in roots], np.float64), far, rtol=1e-5)
    np.testing.assert_allclose(distances(roots, np.float32), far, rtol=1e-4)


ROOTNAV = sorted((DATA / "rsml" / "rootnav_osr").glob("*.rsml")) if DATA.is_dir() else []


@pytest.mark.slow
@pytest.mark.skipif(len(ROOTNAV) < 6, reason="RootNav tracings not present")
def test_rootnav_geodesic_ends_at_b_and_zero_coefficients_give_the_mean():
    """An audit on these tracings found the geodesic's last step a lateral 8 % short of b's
    (rebuilt from b's warped SRVF) and ``reconstruct(pc, 0)`` with 3 of the mean's 8 laterals
    (the data's 10th percentile of lateral lengths is above a mean's shrunken laterals)."""
    import jax

    import rootshape_jax as rs

    roots = [rs.limit_laterals(read_rsml(f)[0], 6) for f in ROOTNAV]
    trees = rs.batch(roots, n_points=40, max_laterals=12, normalise_scale=True, dtype=np.float64)
    a, b = rs.unstack(trees)[0], rs.unstack(trees)[5]
    path = rs.geodesic(a, b, n_steps=2)
    own = rs.to_curves(rs.to_srvf(b))  # b's own round trip: as close as the end can be
    d_end = float(rs.distance(rs.unstack(path)[1], b))
    assert d_end == pytest.approx(float(rs.distance(own, b)), abs=1e-9)
    assert d_end < 0.1 * float(rs.distance(a, b))
    km = rs.karcher_mean(jax.tree.map(lambda x: x[:8], trees), progress=False)
    pc = rs.tangent_pca(km)
    zero = rs.reconstruct(pc, np.zeros(pc.components.shape[0]), srvf=True)
    np.testing.assert_array_equal(np.asarray(zero.mask), np.asarray(km.mean_srvf.mask))
    np.testing.assert_allclose(np.asarray(zero.q), np.asarray(km.mean_srvf.q), atol=1e-12)
    assert int(np.asarray(km.mean_srvf.mask).sum()) >= 6  # the case of the audit: a mean with short laterals
