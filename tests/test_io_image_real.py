"""roots_from_image on real photographs with hand tracings (../shared/data; skipped without it).

Tolerances are the issue's per-image targets where this image meets them (measured figures in
BENCHMARKS.md, "Roots from photographs"): they guard against regressions, they are not tuned.
"""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

from rootshape_jax.io import compare_to_tracing, read_rsml, roots_from_image

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
pytestmark = pytest.mark.skipif(not (DATA / "images").is_dir(), reason="../shared/data not present")


@functools.cache
def _plate():
    stem = "2012_11_19_18h00_chl110_1_1"
    ex = roots_from_image(DATA / "images" / "arabidopsis_plate" / f"{stem}.jpg")
    tr = read_rsml(DATA / "rsml" / "arabidopsis_plate" / f"{stem}.rsml")
    return ex, tr


@pytest.mark.slow
def test_plate_one_root_system_per_seedling():
    ex, tr = _plate()
    assert len(ex) == len(tr) == 5
    xs = [r.metadata["base_xy"][0] for r in ex]
    assert xs == sorted(xs)
    cmp = compare_to_tracing(ex, tr, elastic=False)
    assert len(cmp.plants) == 5 and [p.traced for p in cmp.plants] == [p.extracted for p in cmp.plants]
    assert abs(cmp.total_length_ratio - 1) <= 0.2
    for p in cmp.plants:
        assert 0.85 <= p.main_length_ratio <= 1.25  # measured 0.98-1.02
        assert abs(p.laterals_extracted - p.laterals_traced) <= 3


@pytest.mark.slow
def test_plate_main_roots_start_below_the_shoot():
    # The tracing starts each main root where it leaves the shoot. The green shoot
    # (cotyledons, hypocotyl) is removed from the root mask, so the extraction does too:
    # bases measured 1-10 px from the traced ones, main-root ratios 0.98-1.02. With the shoot
    # kept (shoot_green=None, the behaviour before) the main roots started at a cotyledon's tip:
    # bases 38-61 px away, ratios 1.08-1.13.
    ex, tr = _plate()
    cmp = compare_to_tracing(ex, tr, elastic=False)
    assert len(cmp.plants) == 5
    for p in cmp.plants:
        assert p.base_distance <= 20
        assert p.main_length_ratio == pytest.approx(1.0, abs=0.05)


def test_rootnav_seedling_on_blue_paper():
    stem = "B_osr_0111"
    ex = roots_from_image(DATA / "images" / "rootnav_osr" / f"{stem}.jpg")
    tr = read_rsml(DATA / "rsml" / "rootnav_osr" / f"{stem}.rsml")
    assert len(ex) == 1
    assert ex[0].metadata["roots_dark"] is False  # white roots on blue paper
    cmp = compare_to_tracing(ex, tr, elastic=False)
    (p,) = cmp.plants
    assert p.main_length_ratio == pytest.approx(1.0, abs=0.1)
    assert abs(p.total_length_ratio - 1) <= 0.2
    assert abs(p.laterals_extracted - p.laterals_traced) <= 0.3 * p.laterals_traced + 1


def _pairs():
    stem = "2012_11_19_18h00_chl110_1_1"
    out = [
        (DATA / "images" / "arabidopsis_plate" / f"{stem}.jpg", DATA / "rsml" / "arabidopsis_plate" / f"{stem}.rsml")
    ]
    for img in sorted((DATA / "images" / "rootnav_osr").glob("*.jpg")):
        out.append((img, DATA / "rsml" / "rootnav_osr" / f"{img.stem}.rsml"))
    return out


@pytest.mark.slow
def test_issue_targets_over_all_photographs():
    # The issue's targets over every shared photograph (11 at the time of writing): total length
    # within 20 % on at least 80 % of them, first-order laterals within 30 % on at least 70 %.
    # Measured (BENCHMARKS.md): 9/11 and 10/11.
    rows = []
    for img, rsml in _pairs():
        ex = roots_from_image(img)
        tr = read_rsml(rsml)
        cmp = compare_to_tracing(ex, tr, elastic=False)
        lat_e, lat_t = sum(r.n_laterals for r in ex), sum(r.n_laterals for r in tr)
        rows.append((cmp.total_length_ratio, abs(lat_e - lat_t) / lat_t))
    n = len(rows)
    assert n >= 11
    assert sum(abs(t - 1) <= 0.2 for t, _ in rows) >= 0.8 * n
    assert sum(e <= 0.3 for _, e in rows) >= 0.7 * n
