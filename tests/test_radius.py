"""Radii (root thickness) in the data model, `batch`/`to_roots`, RSML, CPlantBox and plots."""

from __future__ import annotations

import dataclasses
import io
import warnings
from pathlib import Path

import jax
import matplotlib
import numpy as np
import pytest
from helpers import random_root
from matplotlib.collections import LineCollection

from rootshape_jax._errors import InvalidRootError, MissingRadiusWarning, RSMLError, RSMLWarning
from rootshape_jax._root import Root
from rootshape_jax._tree import RootTree, batch, to_roots
from rootshape_jax.io import read_rsml, write_rsml

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LUPIN = DATA / "rsml" / "smartroot" / "lupin.rsml"
MAIZE = DATA / "rsml" / "smartroot" / "maize.rsml"


@pytest.fixture
def rng():
    return np.random.default_rng(20261201)


def with_radii(root: Root, rng) -> Root:
    """The root with random positive radii on every branch."""
    return dataclasses.replace(
        root,
        main_radius=rng.uniform(0.01, 0.05, size=root.main.shape[0]),
        lateral_radii=tuple(rng.uniform(0.001, 0.01, size=lat.shape[0]) for lat in root.laterals),
    )


# --------------------------------------------------------------------------------------------
# Root validation


def test_root_validates_radii():
    main = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 2.0]])
    lat = np.array([[0.0, 1.0], [1.0, 1.0]])
    r = Root(main=main, laterals=(lat,), main_radius=[1, 2, 3], lateral_radii=([0.5, 0.0],))
    assert r.main_radius.dtype == np.float64 and r.has_radius
    assert not Root(main=main).has_radius
    with pytest.raises(InvalidRootError, match=r"main root radius.*shape \(3,\)"):
        Root(main=main, main_radius=[1.0, 2.0])
    with pytest.raises(InvalidRootError, match="main root radius.*finite and >= 0"):
        Root(main=main, main_radius=[1.0, -2.0, 3.0])
    with pytest.raises(InvalidRootError, match="lateral 0 radius.*finite"):
        Root(main=main, laterals=(lat,), lateral_radii=([np.nan, 1.0],))
    with pytest.raises(InvalidRootError, match="1 lateral radius arrays for 0 laterals"):
        Root(main=main, lateral_radii=([1.0, 1.0],))
    with pytest.raises(InvalidRootError, match="radii must be numbers"):
        Root(main=main, main_radius=["a", "b", "c"])


def test_scaled_and_select_laterals_keep_radii(rng):
    r = with_radii(random_root(rng, n_laterals=4), rng)
    s = r.scaled(-2.0)
    np.testing.assert_array_equal(s.main_radius, 2.0 * r.main_radius)
    np.testing.assert_array_equal(s.lateral_radii[3], 2.0 * r.lateral_radii[3])
    sel = r.select_laterals([2, 0])
    assert sel.n_laterals == 2
    np.testing.assert_array_equal(sel.lateral_radii[0], r.lateral_radii[2])
    np.testing.assert_array_equal(sel.laterals[1], r.laterals[0])
    assert sel.attach.tolist() == [r.attach[2], r.attach[0]]


# --------------------------------------------------------------------------------------------
# batch / to_roots


def _reference_resample(points, values, n):
    """Plain numpy: arc length by explicit loops, then linear interpolation of the values."""
    cum = [0.0]
    for a, b in zip(points[:-1], points[1:]):
        cum.append(cum[-1] + float(np.sqrt(np.sum((b - a) ** 2))))
    cum = np.array(cum)
    out = []
    for t in np.linspace(0.0, cum[-1], n):
        j = min(int(np.searchsorted(cum, t, side="right")) - 1, len(cum) - 2)
        w = (t - cum[j]) / (cum[j + 1] - cum[j])
        out.append((1 - w) * values[j] + w * values[j + 1])
    return np.array(out)


@pytest.mark.parametrize("normalise", [False, True])
def test_batch_resamples_radii_like_coordinates(rng, normalise):
    roots = [with_radii(random_root(rng, n_laterals=k, d=d), rng) for k, d in ((3, 2), (1, 2), (5, 2))]
    T = 17
    tree = batch(roots, n_points=T, max_laterals=6, normalise_scale=normalise)
    assert tree.main_radius.shape == (3, T) and tree.lateral_radius.shape == (3, 6, T)
    for i, r in enumerate(roots):
        scale = 1.0
        if normalise:  # radii scale like the coordinates: by 1 / (resampled main length)
            pts = _resampled_points(r.main, T)
            scale = 1.0 / sum(np.linalg.norm(b - a) for a, b in zip(pts[:-1], pts[1:]))
        np.testing.assert_allclose(
            tree.main_radius[i], scale * _reference_resample(r.main, r.main_radius, T), rtol=1e-12
        )
        for k, (lat, rad) in enumerate(zip(r.laterals, r.lateral_radii)):
            # random_root laterals start on the main root: no joining segment is added.
            np.testing.assert_allclose(tree.lateral_radius[i, k], scale * _reference_resample(lat, rad, T), rtol=1e-10)
        assert np.all(np.asarray(tree.lateral_radius[i, r.n_laterals :]) == 0.0)  # null slots


def _resampled_points(points, n):
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    t = np.linspace(0, cum[-1], n)
    return np.stack([np.interp(t, cum, points[:, k]) for k in range(points.shape[1])], axis=1)


def test_batch_joining_segment_takes_lateral_base_radius():
    main = np.array([[0.0, 0.0], [0.0, 2.0]])
    lat = np.array([[1.0, 1.0], [3.0, 1.0]])  # starts 1 away from the main root at y = 1
    r = Root(main=main, laterals=(lat,), attach=[0.5], main_radius=[2.0, 1.0], lateral_radii=([0.4, 0.2],))
    tree = batch(r, n_points=4)
    # The lateral becomes (0,1)-(1,1)-(3,1) with radii 0.4, 0.4, 0.2, sampled at 0, 1, 2, 3.
    np.testing.assert_allclose(tree.lateral_radius[0], [0.4, 0.4, 0.3, 0.2], rtol=1e-12)
    np.testing.assert_allclose(tree.main_radius, [2.0, 5 / 3, 4 / 3, 1.0], rtol=1e-12)


def test_batch_without_radii_is_unchanged(rng):
    roots = [random_root(rng, n_laterals=3) for _ in range(4)]
    plain = batch(roots, n_points=20)
    assert plain.main_radius is None and plain.lateral_radius is None
    assert len(jax.tree.leaves(plain)) == 4  # the same pytree as before radii existed
    # Radii never perturb the geometry: coordinates are bit-identical with or without them.
    thick = batch([with_radii(r, rng) for r in roots], n_points=20)
    for name in ("main", "laterals", "attach", "mask"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(thick, name))
    assert len(jax.tree.leaves(thick)) == 6


def test_mixed_batch_warns_and_pads_with_zero(rng):
    a = with_radii(dataclasses.replace(random_root(rng, n_laterals=2), name="thick"), rng)
    b = dataclasses.replace(random_root(rng, n_laterals=2), name="thin")
    with pytest.warns(MissingRadiusWarning, match="root 'thin' has no radius data; its radius is taken as 0"):
        tree = batch([a, b], n_points=10)
    assert np.all(np.asarray(tree.main_radius[1]) == 0) and np.all(np.asarray(tree.lateral_radius[1]) == 0)
    assert np.all(np.asarray(tree.main_radius[0]) > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        batch([a, a], n_points=10)  # every root has radii: no warning


def test_to_roots_returns_radii(rng):
    roots = [with_radii(random_root(rng, n_laterals=k), rng) for k in (2, 3)]
    tree = batch(roots, n_points=12, max_laterals=6)
    back = to_roots(tree)
    for i, r in enumerate(back):
        np.testing.assert_array_equal(r.main_radius, np.asarray(tree.main_radius[i]))
        assert len(r.lateral_radii) == roots[i].n_laterals
        np.testing.assert_array_equal(r.lateral_radii[1], np.asarray(tree.lateral_radius[i, 1]))
    assert to_roots(batch(random_root(rng)))[0].main_radius is None


def test_roottree_checks_radius_shapes(rng):
    t = batch(with_radii(random_root(rng, n_laterals=2), rng), n_points=8)
    with pytest.raises(ValueError, match="main_radius has shape"):
        RootTree(t.main, t.laterals, t.attach, t.mask, t.main_radius[:-1], t.lateral_radius)
    with pytest.raises(ValueError, match="lateral_radius has shape"):
        RootTree(t.main, t.laterals, t.attach, t.mask, t.main_radius, t.lateral_radius[:1])
    with pytest.raises(ValueError, match="given together"):
        RootTree(t.main, t.laterals, t.attach, t.mask, t.main_radius, None)
    # vmap / jit see the radii as ordinary leaves.
    doubled = jax.jit(lambda x: x.main_radius * 2)(t)
    np.testing.assert_allclose(doubled, 2 * np.asarray(t.main_radius))


# --------------------------------------------------------------------------------------------
# RSML

_FIXTURE = """<?xml version="1.0" encoding="UTF-8"?>
<rsml>
  <metadata><version>1</version><unit>mm</unit><resolution>10</resolution></metadata>
  <scene><plant id="p">
    <root id="main" label="a">
      <geometry><polyline>
        <point x="0" y="0"/><point x="0" y="100"/><point x="0" y="300"/>
      </polyline></geometry>
      <functions>
        <function name="diameter" domain="polyline">
          <sample value="8"/><sample value="6"/><sample value="4"/>
        </function>
      </functions>
      <root id="l1">
        <properties><parent-node value="1"/></properties>
        <geometry><polyline><point x="0" y="100"/><point x="40" y="100"/><point x="100" y="100"/></polyline></geometry>
        <functions><function name="radius" domain="uniform"><sample>2</sample><sample>1</sample></function></functions>
      </root>
      <root id="l2">
        <geometry><polyline><point x="0" y="200"/><point x="-50" y="200"/></polyline></geometry>
        <functions><function name="Diameter" domain="length">
          <sample position="50">2</sample><sample position="0">4</sample>
        </function></functions>
      </root>
      <root id="l3">
        <geometry><polyline><point x="0" y="250"/><point x="-20" y="250"/></polyline></geometry>
      </root>
    </root>
  </plant>
  <plant id="q">
    <root id="bare"><geometry><polyline><point x="5" y="0"/><point x="5" y="50"/></polyline></geometry></root>
  </plant></scene>
</rsml>
"""


def _read(text: str, **kw):
    return read_rsml(io.BytesIO(text.encode()), **kw)


def test_read_rsml_diameter_radius_domains_and_units():
    with pytest.warns(RSMLWarning, match=r"1 lateral\(s\) have no diameter/radius.*'l3'"):
        a, bare = _read(_FIXTURE)
    assert a.metadata["unit"] == "mm" and bare.main_radius is None and bare.lateral_radii is None
    # diameter / 2, then pixels / resolution (10 px per mm), like the coordinates.
    np.testing.assert_allclose(a.main_radius, [0.4, 0.3, 0.2])
    # uniform: samples at arc lengths 0 and 100 px; points at 0, 40, 100 px.
    np.testing.assert_allclose(a.lateral_radii[0], np.array([2.0, 1.6, 1.0]) / 10)
    # length domain (unsorted positions): radius 2 at 0 px, 1 at 50 px.
    np.testing.assert_allclose(a.lateral_radii[1], np.array([2.0, 1.0]) / 10)
    np.testing.assert_array_equal(a.lateral_radii[2], [0.0, 0.0])  # no data beside siblings
    assert a.children[2].main_radius is None
    np.testing.assert_array_equal(a.children[0].main_radius, a.lateral_radii[0])
    # Pixels kept: radii stay in pixels too.
    with pytest.warns(RSMLWarning):
        px = _read(_FIXTURE, physical_units=False)[0]
    np.testing.assert_allclose(px.main_radius, [4.0, 3.0, 2.0])


def test_read_rsml_bad_diameter_is_reported():
    bad = _FIXTURE.replace('<sample value="4"/>', "").replace(
        '<sample value="6"/>', '<sample value="-6"/><sample value="4"/>'
    )
    with pytest.warns(RSMLWarning) as record:
        a = _read(bad)[0]
    assert any("negative" in str(w.message) and "radius dropped" in str(w.message) for w in record)
    assert a.main_radius is None and a.lateral_radii is not None
    short = _FIXTURE.replace('<sample value="4"/>', "")
    with pytest.raises(RSMLError, match="2 samples for 3 points"):
        _read(short, strict=True)


def test_read_rsml_diameter_property_is_constant():
    text = _FIXTURE.replace('<root id="l3">', '<root id="l3"><properties><diameter value="3"/></properties>')
    a = _read(text)[0]
    np.testing.assert_allclose(a.lateral_radii[2], [0.15, 0.15])


def test_write_rsml_round_trips_radii(tmp_path):
    with pytest.warns(RSMLWarning):
        roots = _read(_FIXTURE)
    path = tmp_path / "out.rsml"
    write_rsml(roots, path)
    text = path.read_text()
    # main, l1, l2; none for l3 (unknown, padded with 0 on reading) nor for 'bare'.
    assert text.count('name="diameter"') == 3 and 'name="radius"' not in text
    with pytest.warns(RSMLWarning, match="'l3'"):
        back = read_rsml(path)
    for r, b in zip(roots, back):
        if r.main_radius is None:
            assert b.main_radius is None
            continue
        np.testing.assert_allclose(b.main_radius, r.main_radius, rtol=1e-15)
        for x, y in zip(r.lateral_radii, b.lateral_radii):
            np.testing.assert_allclose(y, x, rtol=1e-15)
    # Radii made in memory (no functions in the metadata) are written too.
    rng = np.random.default_rng(0)
    r = with_radii(random_root(rng, n_laterals=2), rng)
    write_rsml(r, tmp_path / "mem.rsml", unit="mm", resolution=100.0)
    b = read_rsml(tmp_path / "mem.rsml")[0]
    np.testing.assert_allclose(b.main_radius, r.main_radius, rtol=1e-14)
    np.testing.assert_allclose(b.lateral_radii[1], r.lateral_radii[1], rtol=1e-14)


@pytest.mark.skipif(not LUPIN.is_file(), reason="real data folder ../shared not present")
def test_real_smartroot_diameters():
    lupin = read_rsml(LUPIN)[0]
    assert lupin.metadata["unit"] == "inch"
    # Independent reading: the first diameter sample of the taproot is 38.5 px at 179 dpi.
    assert lupin.main_radius[0] * 25.4 == pytest.approx(38.5 / 2 / 179 * 25.4)
    # In mm: a lupin taproot is a few mm thick at the collar, laterals well under 1 mm.
    mm = lupin.main_radius * 25.4
    assert 1.0 < mm[:5].mean() < 5.0 and mm.min() > 0.1
    lat_mm = np.concatenate(lupin.lateral_radii) * 25.4
    assert 0.1 < np.median(lat_mm) < 1.0
    assert len(lupin.lateral_radii) == lupin.n_laterals > 50
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RSMLWarning)  # maize has one-point laterals
        maize = read_rsml(MAIZE)[0]
    assert maize.main_radius is not None and maize.n_laterals > 400
    tree = batch([lupin, maize.scaled(1.0)], n_points=50)
    assert np.all(np.asarray(tree.main_radius) > 0)


# --------------------------------------------------------------------------------------------
# Plots


def _widths(ax):
    out = []
    for c in ax.collections:
        if isinstance(c, LineCollection):
            out.extend(np.atleast_1d(c.get_linewidths()).tolist())
    return np.array(out)


def test_plot_line_width_follows_radius(rng):
    matplotlib.use("Agg")
    from rootshape_jax import plot as P
    from rootshape_jax.plot._draw import MIN_WIDTH, RADIUS_WIDTH

    plain = random_root(rng, n_laterals=2)
    _, ax = P.plot_root(plain, linewidth=2.0)
    assert sorted(set(_widths(ax))) == [2.0, 3.2]  # unknown radius: unchanged drawing
    main_r = np.linspace(1.0, 0.5, plain.main.shape[0])
    thick = dataclasses.replace(
        plain,
        main_radius=main_r,
        lateral_radii=tuple(np.full(lat.shape[0], 0.001) for lat in plain.laterals),
    )
    _, ax = P.plot_root(thick, linewidth=2.0)
    w = _widths(ax)
    n_main = plain.main.shape[0] - 1
    main_w = w[-n_main:]  # the main root is drawn last, one width per segment
    expected = RADIUS_WIDTH * 2.0 * 0.5 * (main_r[:-1] + main_r[1:]) / 1.0
    np.testing.assert_allclose(main_w, expected)
    assert np.all(np.diff(main_w) < 0)  # thinner towards the tip
    lat_w = w[:-n_main]
    np.testing.assert_allclose(lat_w, MIN_WIDTH * 2.0)  # clipped: still visible
    # The same through a RootTree; a batch member without radius data draws as before.
    with pytest.warns(UserWarning, match="no radius data"):
        tree = batch([thick, plain], n_points=10, max_laterals=4)
    from rootshape_jax._tree import unstack

    _, ax = P.plot_root(unstack(tree)[0], linewidth=1.0)
    assert len(set(np.round(_widths(ax), 9))) > 3
    _, ax = P.plot_root(unstack(tree)[1], linewidth=1.0)
    assert sorted(set(_widths(ax))) == [1.0, 1.6]


# --------------------------------------------------------------------------------------------
# CPlantBox

try:
    import plantbox as pb
except ImportError:
    pb = None


@pytest.mark.skipif(pb is None, reason="CPlantBox is not installed (extra `sim`)")
def test_simulated_roots_keep_cplantbox_radii():
    from rootshape_jax.datasets import simulated_roots

    root = simulated_roots("lupin", 1, days=12, seed=4)[0]
    rs = pb.RootSystem()
    rs.readParameters(str(pb.data_path()) + "/structural/rootsystem/Lupinus_albus_Leitner_2014.xml")
    rs.setSeed(root.metadata["cplantbox_seed"])
    rs.initialize(False)
    rs.simulate(12.0, False)
    tap = rs.getBaseRoots()[0]
    # CPlantBox: one radius per root, in cm; ours: per point, in mm.
    np.testing.assert_allclose(root.main_radius, 10.0 * tap.getParameter("radius"), rtol=1e-6)
    kids = [tap.getChild(k) for k in range(tap.getNumberOfChildren())]
    kids = [c for c in kids if c.getNumberOfNodes() >= 3]
    assert root.n_laterals == len(kids) > 0
    for lat, rad, c, child in zip(root.laterals, root.lateral_radii, kids, root.children):
        assert rad.shape == (lat.shape[0],)
        np.testing.assert_allclose(rad, 10.0 * c.getParameter("radius"), rtol=1e-6)
        np.testing.assert_array_equal(child.main_radius, rad)
    tree = batch(root, n_points=30)
    assert float(tree.main_radius[0]) == pytest.approx(10.0 * tap.getParameter("radius"), rel=1e-6)


def test_cli_speaks_of_radii_only_when_the_metric_weighs_them(rng, tmp_path):
    """A folder mixing files with and without diameters: at the default weights (no thickness
    term) the missing radii do not matter and are not reported; with a thickness weight they
    are. A thickness weight on files without any diameter says it has no effect."""
    from helpers import run_cli

    folder = tmp_path / "mixed"
    folder.mkdir()
    write_rsml([with_radii(random_root(rng, n_laterals=2), rng)], folder / "thick.rsml", unit="mm")
    write_rsml([random_root(rng, n_laterals=2)], folder / "thin.rsml", unit="mm")
    common = ("distances", folder, "--points", 12, "--quiet")
    proc = run_cli(*common, "--out", tmp_path / "a")
    assert proc.returncode == 0, proc.stderr
    assert "radius" not in proc.stderr and "radii" not in proc.stderr, proc.stderr
    proc = run_cli(*common, "--weights", "0.02,1,1,1", "--out", tmp_path / "b")
    assert proc.returncode == 0, proc.stderr
    assert "has no radius data; its radius is taken as 0" in proc.stderr, proc.stderr
    write_rsml([random_root(rng, n_laterals=2)], folder / "thick.rsml", unit="mm")  # now without
    proc = run_cli(*common, "--weights", "0.02,1,1,1", "--out", tmp_path / "c")
    assert proc.returncode == 0, proc.stderr
    assert "no root has radius data" in proc.stderr and "the thickness term is 0" in proc.stderr, proc.stderr
    assert "radius is taken as 0" not in proc.stderr, proc.stderr  # said once, not also per root


def test_learn_weights_keeps_the_radius_warning(rng, capsys):
    """learn-weights learns the thickness weight whenever radii exist (from 1), so roots
    without radii matter there even at the default weights: the warning stays."""
    import argparse

    from rootshape_jax._cli._inputs import prepare

    roots = [with_radii(random_root(rng, n_laterals=2), rng), dataclasses.replace(random_root(rng), name="thin")]
    base = dict(laterals=None, points=10, normalise_scale=True, weights=(0.02, 1.0, 1.0, 0.0))
    with pytest.warns(UserWarning, match="root 'thin' has no radius data"):
        prepare(roots, argparse.Namespace(command="learn-weights", **base))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepare(roots, argparse.Namespace(command="distances", **base))
