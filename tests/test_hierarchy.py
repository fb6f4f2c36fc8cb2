"""Whole root systems (issue 15, docs/design.md §11), data side: trees of depth D with padded
deeper levels, plants with several axes, higher-order data, per-order traits, RSML round trips,
and the slow reference distance that the nested registration must equal."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_root, reference_tree_distance, tree_allclose

import rootshape_jax as rs
from rootshape_jax._curves import interpolate_at_fraction
from rootshape_jax._root import polyline_length
from rootshape_jax.datasets import synthetic_roots
from rootshape_jax.io import is_plant_system, plant_system, read_rsml, write_rsml

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _arc(start, direction, length, n=12, bend=0.0):
    """A gently bending polyline of exactly `length` from `start` along `direction`."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    normal = np.array([-d[1], d[0]])
    t = np.linspace(0.0, 1.0, n)
    pts = t[:, None] * d + bend * (t**2)[:, None] * normal
    return np.asarray(start, float) + pts * (length / polyline_length(pts))


def _point(poly, frac):
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    return np.array([np.interp(frac * cum[-1], cum, poly[:, k]) for k in range(poly.shape[1])])


def deep_root(rng, *, n_laterals=3, max_sub=2, sub_sub=0, radius=False) -> rs.Root:
    """A random 2D root with second-order laterals (and third-order ones when `sub_sub`)."""
    base = random_root(rng, n_laterals=n_laterals)
    kids = []
    for lat in base.laterals:
        n_sub = int(rng.integers(0, max_sub + 1))
        att = np.sort(rng.uniform(0.15, 0.85, n_sub))
        subs, grand = [], []
        for a in att:
            start = _point(lat, a)
            sub = _arc(start, rng.normal(size=2), rng.uniform(0.03, 0.08), bend=rng.normal() * 0.3)
            subs.append(sub)
            g_att = np.sort(rng.uniform(0.2, 0.8, sub_sub))
            g = [_arc(_point(sub, b), rng.normal(size=2), 0.02, n=6) for b in g_att]
            grand.append(
                rs.Root(main=sub, laterals=g, attach=g_att, main_radius=np.full(len(sub), 0.005) if radius else None)
            )
        kids.append(
            rs.Root(
                main=lat,
                laterals=subs,
                attach=att,
                children=tuple(grand) if sub_sub else (),
                main_radius=np.linspace(0.02, 0.01, len(lat)) if radius else None,
                lateral_radii=tuple(np.full(len(s), 0.005) for s in subs) if radius else None,
            )
        )
    return dataclasses.replace(
        base,
        children=tuple(kids),
        main_radius=np.linspace(0.05, 0.02, len(base.main)) if radius else None,
        lateral_radii=tuple(np.linspace(0.02, 0.01, len(lat)) for lat in base.laterals) if radius else None,
    )


def _max_abs(x, y):
    return max(float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float)))) for a, b in zip(x, y))


# --------------------------------------------------------------------------------------------
# Data model


def test_depth_two_is_todays_tree_bit_for_bit():
    rng = np.random.default_rng(0)
    roots = [deep_root(rng) for _ in range(3)]
    plain = [dataclasses.replace(r, children=()) for r in roots]
    today = rs.batch(plain, n_points=15)
    assert today.deeper == () and today.depth == 2 and today.capacities == (today.capacity,)
    default = rs.batch(roots, n_points=15)  # children ignored silently, as before
    with pytest.warns(UserWarning, match=r"batch\(depth=2\): \d+ laterals of order 2"):
        explicit = rs.batch(roots, n_points=15, depth=2)
    for t in (default, explicit):
        assert jax.tree.structure(t) == jax.tree.structure(today)
        assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(t), jax.tree.leaves(today)))
    s = rs.to_srvf(today)
    assert s.deeper == () and s.depth == 2


def test_depth_three_shapes_capacities_padding_and_attachment():
    rng = np.random.default_rng(1)
    roots = [deep_root(rng, n_laterals=n, max_sub=3) for n in (0, 2, 4)]
    t = rs.batch(roots, n_points=20, depth=3)
    n1 = max(r.n_laterals for r in roots)
    n2 = max(c.n_laterals for r in roots for c in r.children)
    assert t.depth == 3 and t.capacities == (2 * n1, max(2, 2 * n2))
    lv = t.deeper[0]
    K1, K2 = t.capacities
    assert lv.curves.shape == (3, K1, K2, 20, 2) and lv.mask.shape == (3, K1, K2) and lv.radius is None
    for i, r in enumerate(roots):
        for k in range(K1):
            expected = r.children[k].n_laterals if k < r.n_laterals else 0
            assert int(lv.mask[i, k].sum()) == expected
            # Real children first, in order, at their attachment points on the padded parent.
            assert np.all(np.asarray(lv.mask[i, k, :expected]))
            for j in range(expected):
                base = interpolate_at_fraction(t.laterals[i, k], lv.attach[i, k, j])
                np.testing.assert_allclose(lv.curves[i, k, j, 0], base, atol=1e-9)
                length = polyline_length(np.asarray(lv.curves[i, k, j]))
                assert length == pytest.approx(polyline_length(r.children[k].laterals[j]), rel=0.05)
            # Null slots: collapsed to the parent's first point, finite, SRVF exactly 0.
            for j in range(expected, K2):
                np.testing.assert_array_equal(lv.curves[i, k, j], np.repeat(t.laterals[i, k, :1], 20, axis=0))
    s = rs.to_srvf(t)
    q = np.asarray(s.deeper[0].q)
    assert np.all(q[~np.asarray(lv.mask)] == 0) and np.all(np.isfinite(q))
    # Lengths: ||q||² of each real child equals its padded polyline length.
    L = np.asarray(rs.l2_norm_squared(s.deeper[0].q))
    np.testing.assert_allclose(L, np.asarray(rs.curve_length(lv.curves)) * np.asarray(lv.mask), atol=1e-12)


def test_attachment_fraction_moves_with_the_joining_segment():
    # A lateral that starts 0.1 away from the main root is joined to it; its child must stay
    # at the same physical point, so its fraction along the joined lateral changes.
    main = np.stack([np.zeros(11), np.linspace(0, 1, 11)], 1)
    lat = np.array([[0.1, 0.5], [0.5, 0.5]])  # 0.4 long, 0.1 from the main root
    sub = np.array([[0.3, 0.5], [0.3, 0.7]])  # at fraction 0.5 of the lateral (x = 0.3)
    child = rs.Root(main=lat, laterals=[sub], attach=[0.5])
    r = rs.Root(main=main, laterals=[lat], attach=[0.5], children=(child,))
    t = rs.batch(r, n_points=41, depth=3, dtype=np.float64)
    assert float(t.deeper[0].attach[0, 0]) == pytest.approx((0.1 + 0.2) / 0.5, abs=1e-12)
    np.testing.assert_allclose(t.deeper[0].curves[0, 0, 0], [0.3, 0.5], atol=1e-12)
    np.testing.assert_allclose(t.deeper[0].curves[0, 0, -1], [0.3, 0.7], atol=1e-12)


def test_capacity_errors_name_the_level_and_the_capacity_needed():
    rng = np.random.default_rng(2)
    r = deep_root(rng, n_laterals=3, max_sub=3)
    most = max(c.n_laterals for c in r.children)
    assert most >= 2
    with pytest.raises(rs.CapacityError, match=rf"level 2 is K2 = 1; level 2 needs K2 >= {most}"):
        rs.batch(r, depth=3, max_children=(6, 1))
    with pytest.raises(rs.CapacityError, match="capacity is K = 2"):
        rs.batch(r, depth=3, max_children=(2, 8))
    with pytest.raises(ValueError, match="max_children must hold 2"):
        rs.batch(r, depth=3, max_children=(6,))
    with pytest.raises(ValueError, match=r"max_children must hold 2 .*got 12"):  # was 'int' is not iterable
        rs.batch(r, depth=3, max_children=12)
    with pytest.raises(ValueError, match="disagrees"):
        rs.batch(r, depth=3, max_laterals=8, max_children=(6, 8))
    with pytest.raises(ValueError, match="depth must be an integer >= 2"):
        rs.batch(r, depth=1)
    t = rs.batch(r, depth=3, max_children=(7, most), n_points=10)
    assert t.capacities == (7, most)


def test_truncation_warns_once_with_the_number_left_out():
    rng = np.random.default_rng(3)
    roots = [deep_root(rng, n_laterals=3, max_sub=2, sub_sub=2) for _ in range(2)]
    n3 = sum(g.n_laterals for r in roots for c in r.children for g in c.children)
    assert n3 > 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rs.batch(roots, depth=3, n_points=10)
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and f"{n3} laterals of order 3" in msgs[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t4 = rs.batch(roots, depth=4, n_points=10)
    assert t4.depth == 4 and int(t4.deeper[1].mask.sum()) == n3


@pytest.mark.parametrize("depth", [3, 4])
def test_batch_to_roots_batch_round_trip(depth):
    rng = np.random.default_rng(4 + depth)
    roots = [deep_root(rng, n_laterals=3, max_sub=2, sub_sub=2, radius=True) for _ in range(2)]
    if depth == 3:  # the third-order laterals are left out, with a warning
        with pytest.warns(UserWarning, match="laterals of order 3"):
            t = rs.batch(roots, n_points=60, depth=depth, dtype=np.float64)
    else:
        t = rs.batch(roots, n_points=60, depth=depth, dtype=np.float64)
    back = rs.to_roots(t)

    def shape(r, level):
        if level == 0:
            return r.n_laterals
        return (r.n_laterals, tuple(shape(c, level - 1) for c in r.children))

    assert [shape(r, depth - 2) for r in back] == [shape(r, depth - 2) for r in roots]
    again = rs.batch(back, n_points=60, depth=depth, max_children=t.capacities, dtype=np.float64)
    assert jax.tree.structure(again) == jax.tree.structure(t)
    for a, b in zip(jax.tree.leaves(t), jax.tree.leaves(again)):
        if a.dtype == bool:
            np.testing.assert_array_equal(a, b)
    for lv_a, lv_b in zip(t.deeper, again.deeper):
        np.testing.assert_allclose(lv_a.attach, lv_b.attach, atol=1e-12)
    # Re-resampling a resampled polyline moves points by its chord error only (corners of the
    # input polylines): small against the unit main root.
    assert _max_abs(jax.tree.leaves(t), jax.tree.leaves(again)) < 1e-2


def test_srvf_round_trip_at_depth_three_and_normalise_scale():
    rng = np.random.default_rng(6)
    roots = [deep_root(rng, n_laterals=3, max_sub=2, radius=True) for _ in range(2)]
    t = rs.batch(roots, n_points=200, depth=3, dtype=np.float64)
    back = rs.to_curves(rs.to_srvf(t))
    assert back.depth == 3 and back.capacities == t.capacities
    m = np.asarray(t.deeper[0].mask)
    # As at depth 2 (test_tree): the corners of the inputs cost a few tenths of a percent.
    assert np.abs(np.asarray(back.deeper[0].curves - t.deeper[0].curves))[m].max() < 3e-3
    np.testing.assert_array_equal(back.deeper[0].attach, t.deeper[0].attach)
    # With a thickness channel, radii come back too.
    w = rs.Weights(thickness=0.5)
    st = rs.to_srvf(t, weights=w)
    assert st.deeper[0].q.shape[-1] == 3 and st.deeper[0].base_radius.shape == m.shape
    thick = rs.to_curves(st)
    assert np.abs(np.asarray(thick.deeper[0].radius - t.deeper[0].radius))[m].max() < 1e-3
    assert np.abs(np.asarray(thick.deeper[0].curves - t.deeper[0].curves))[m].max() < 3e-3
    # normalise_scale divides every level by the main-root length.
    r = roots[0]
    unit = rs.batch(r, n_points=40, depth=3, normalise_scale=True, dtype=np.float64)
    big = rs.batch(r.scaled(7.0), n_points=40, depth=3, normalise_scale=True, dtype=np.float64)
    assert tree_allclose(unit, big, atol=1e-12)


def test_batch_operations_and_checks_carry_the_deeper_levels():
    rng = np.random.default_rng(7)
    roots = [deep_root(rng, n_laterals=2, max_sub=2) for _ in range(3)]
    t = rs.batch(roots, n_points=12, depth=3, max_children=(4, 3))
    sub = jax.tree.map(lambda x: x[np.array([2, 0])], t)
    assert sub.batch_shape == (2,) and sub.deeper[0].curves.shape[:3] == (2, 4, 3)
    np.testing.assert_array_equal(sub.deeper[0].mask[0], t.deeper[0].mask[2])
    assert tree_allclose(rs.stack(rs.unstack(t)), t)
    from rootshape_jax._tree import batch_size, check_compatible

    assert batch_size(t) == 3
    other = rs.batch(roots, n_points=12, depth=3, max_children=(4, 5))
    with pytest.raises(ValueError, match="capacities per level"):
        check_compatible(t, other)
    with pytest.raises(ValueError, match="capacities per level"):
        check_compatible(t, rs.batch(roots, n_points=12, max_laterals=4))
    scaled = rs.scale_tree(t, jnp.array([2.0, 1.0, 0.5]))
    o = np.asarray(t.main[:, 0])[:, None, None, None, :]
    expect = o + (np.asarray(t.deeper[0].curves) - o) * np.array([2.0, 1.0, 0.5])[:, None, None, None, None]
    np.testing.assert_allclose(scaled.deeper[0].curves, expect, rtol=1e-6, atol=1e-6)


def test_level_modules_refuse_bad_shapes_and_orphans():
    main, lats = jnp.zeros((5, 2)), jnp.zeros((2, 5, 2))
    attach, mask = jnp.zeros(2), jnp.array([True, False])
    good = rs.BranchLevel(jnp.zeros((2, 3, 5, 2)), jnp.zeros((2, 3)), jnp.zeros((2, 3), bool))
    rs.RootTree(main, lats, attach, mask, deeper=(good,))
    with pytest.raises(ValueError, match="slots"):
        bad = rs.BranchLevel(jnp.zeros((3, 3, 5, 2)), jnp.zeros((3, 3)), jnp.zeros((3, 3), bool))
        rs.RootTree(main, lats, attach, mask, deeper=(bad,))
    with pytest.raises(ValueError, match="attach has shape"):
        rs.BranchLevel(jnp.zeros((2, 3, 5, 2)), jnp.zeros((2,)), jnp.zeros((2, 3), bool))
    orphan = rs.BranchLevel(jnp.zeros((2, 3, 5, 2)), jnp.zeros((2, 3)), jnp.zeros((2, 3), bool).at[1, 0].set(True))
    with pytest.raises(ValueError, match="under null parent"):
        rs.RootTree(main, lats, attach, mask, deeper=(orphan,))
    with pytest.raises(ValueError, match="radii exactly when"):
        rs.RootTree(
            main, lats, attach, mask, main_radius=jnp.zeros(5), lateral_radius=jnp.zeros((2, 5)), deeper=(good,)
        )


def test_virtual_main_root_is_finite_everywhere():
    rng = np.random.default_rng(8)
    axes = [deep_root(rng, n_laterals=2, max_sub=1) for _ in range(2)]
    axes = [dataclasses.replace(a, main=a.main - a.main[0]) for a in axes]  # same collar
    plant = plant_system(axes, name="p")
    assert is_plant_system(plant) and plant.main_length == 0 and np.all(plant.attach == 0)
    t = rs.batch([plant, plant_system(axes[:1])], n_points=16, depth=4, normalise_scale=True, dtype=np.float64)
    # Scaled by the longest axis, as a taproot system is by its main root.
    longest = max(polyline_length(rs.batch(a, n_points=16, dtype=np.float64).main) for a in axes)
    np.testing.assert_allclose(
        float(rs.curve_length(t.laterals[0, 0])), polyline_length(axes[0].main) / longest, rtol=2e-2
    )
    s = rs.to_srvf(t)
    assert np.all(np.asarray(s.q0) == 0)
    c = rs.to_curves(s)
    for leaf in jax.tree.leaves((s, c)):
        assert np.all(np.isfinite(np.asarray(leaf, float)))

    def energy(main):
        ta = rs.RootTree(main, t.laterals[0], t.attach[0], t.mask[0])
        from rootshape_jax._metric import preshape_distance_squared

        return preshape_distance_squared(rs.to_srvf(ta), rs.to_srvf(rs.unstack(t)[1]))

    g = jax.grad(energy)(t.main[0])
    assert np.all(np.isfinite(np.asarray(g)))


# --------------------------------------------------------------------------------------------
# Several axes per plant (RSML)

_PLANTS_RSML = """<?xml version="1.0" encoding="UTF-8"?>
<rsml>
  <metadata><version>1</version><unit>mm</unit><resolution>1</resolution></metadata>
  <scene>
    <plant id="A" label="maize-like">
      <root id="A1">
        <geometry><polyline><point x="0" y="0"/><point x="0" y="10"/><point x="1" y="20"/></polyline></geometry>
        <functions><function name="diameter" domain="polyline">
          <sample value="2"/><sample value="1.5"/><sample value="1"/></function></functions>
        <root id="A1a">
          <geometry><polyline><point x="0" y="5"/><point x="4" y="6"/><point x="8" y="8"/></polyline></geometry>
          <root id="A1a1">
            <geometry><polyline><point x="4" y="6"/><point x="4" y="9"/></polyline></geometry>
          </root>
        </root>
      </root>
      <root id="A2">
        <geometry><polyline><point x="0" y="0"/><point x="-5" y="8"/><point x="-9" y="15"/></polyline></geometry>
        <root id="A2a">
          <geometry><polyline><point x="-5" y="8"/><point x="-2" y="12"/></polyline></geometry>
        </root>
      </root>
    </plant>
    <plant id="B">
      <root id="B1">
        <geometry><polyline><point x="30" y="0"/><point x="30" y="12"/></polyline></geometry>
      </root>
    </plant>
  </scene>
</rsml>
"""


def test_read_rsml_by_plant_on_a_hand_built_file(tmp_path):
    path = tmp_path / "plants.rsml"
    path.write_text(_PLANTS_RSML)
    by_root = read_rsml(path)
    plants = read_rsml(path, by="plant")
    assert [r.metadata["root_id"] for r in by_root] == ["A1", "A2", "B1"]
    assert [p.name for p in plants] == ["maize-like", "plants/B"]
    a, b = plants
    assert (a.n_laterals, b.n_laterals) == (2, 1) and a.metadata["n_axes"] == 2 and a.metadata["virtual_main"]
    np.testing.assert_array_equal(a.main, [[0, 0], [0, 0]])
    np.testing.assert_array_equal(b.main, [[30, 0], [30, 0]])
    np.testing.assert_array_equal(a.attach, [0, 0])
    for axis, child, lat in zip(by_root[:2], a.children, a.laterals):
        np.testing.assert_array_equal(child.main, axis.main)
        np.testing.assert_array_equal(lat, axis.main)
        assert child.n_laterals == axis.n_laterals and child.metadata["root_id"] == axis.metadata["root_id"]
    # Radii: the diameter function of A1 (radius = diameter / 2); A2 has none (0); main 0.
    np.testing.assert_allclose(a.lateral_radii[0], [1.0, 0.75, 0.5])
    np.testing.assert_array_equal(a.lateral_radii[1], 0.0)
    np.testing.assert_array_equal(a.main_radius, [0.0, 0.0])
    assert b.main_radius is None
    # Orders: axes are level 1, their laterals level 2, the order-3 root of A1a is level 3.
    with pytest.warns(UserWarning, match="'plants/B' has no radius data"):
        t = rs.batch(plants, n_points=10, depth=4, dtype=np.float64)
    assert [int(x) for x in t.mask.sum(1)] == [2, 1]
    assert int(t.deeper[0].mask.sum()) == 2 and int(t.deeper[1].mask.sum()) == 1
    # Traits count orders from the axes: the order-3 root of the file is their order 2.
    row = rs.traits(a)
    assert (row["n_axes"], row["n_laterals_order1"], row["n_laterals_order2"]) == (2, 2, 1)
    assert "n_laterals_order3" not in row
    with pytest.raises(ValueError, match="by must be"):
        read_rsml(path, by="axis")
    # Written back as the axes of one plant, read back identically either way.
    out = tmp_path / "again.rsml"
    write_rsml(plants, out)
    again_roots = read_rsml(out)
    assert [r.metadata["root_id"] for r in again_roots] == ["A1", "A2", "B1"]
    again = read_rsml(out, by="plant")
    assert [p.n_laterals for p in again] == [2, 1]
    for p, q in zip(plants, again):
        for x, y in zip(p.laterals, q.laterals):
            np.testing.assert_allclose(x, y, atol=1e-9)
        for c, e in zip(p.children, q.children):
            assert c.n_laterals == e.n_laterals
            np.testing.assert_allclose(c.attach, e.attach, atol=1e-9)


@pytest.mark.skipif(not (SHARED / "rsml" / "arabidopsis_plate").is_dir(), reason="shared data absent")
def test_read_rsml_by_plant_on_a_plate_of_seedlings():
    path = sorted((SHARED / "rsml" / "arabidopsis_plate").glob("*.rsml"))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        roots = read_rsml(path)
        plants = read_rsml(path, by="plant")
    assert len(plants) == len({r.metadata["plant_id"] for r in roots}) == 5
    axes = [c for p in plants for c in p.children]
    assert len(axes) == len(roots)
    owners = [p for p in plants for _ in p.children]
    for r, c, owner in zip(roots, axes, owners):
        np.testing.assert_array_equal(c.main, r.main)
        np.testing.assert_array_equal(owner.main[0], owner.laterals[0][0])
        assert c.n_laterals == r.n_laterals
    t = rs.batch(plants, n_points=20, depth=3, normalise_scale=True, dtype=np.float64)
    for leaf in jax.tree.leaves(rs.to_srvf(t)):
        assert np.all(np.isfinite(np.asarray(leaf, float)))


# --------------------------------------------------------------------------------------------
# RSML writing keeps the hierarchy and the diameters


@pytest.mark.skipif(not (SHARED / "rsml" / "smartroot" / "lupin.rsml").is_file(), reason="shared data absent")
def test_write_rsml_round_trip_on_smartroot_lupin(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (lupin,) = read_rsml(SHARED / "rsml" / "smartroot" / "lupin.rsml")
        write_rsml(lupin, tmp_path / "lupin.rsml")
        (back,) = read_rsml(tmp_path / "lupin.rsml")
    assert back.n_laterals == lupin.n_laterals == 60
    np.testing.assert_allclose(back.main, lupin.main, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.main_radius, lupin.main_radius, rtol=1e-9)
    np.testing.assert_allclose(back.attach, lupin.attach, atol=1e-9)
    for x, y, rx, ry in zip(back.laterals, lupin.laterals, back.lateral_radii, lupin.lateral_radii):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rx, ry, rtol=1e-9)
    assert len(back.children) == 60 and all(c.n_laterals == 0 for c in back.children)


def test_write_rsml_round_trip_keeps_three_orders_and_radii(tmp_path):
    rng = np.random.default_rng(9)
    root = deep_root(rng, n_laterals=3, max_sub=2, sub_sub=1, radius=True)
    write_rsml(root, tmp_path / "deep.rsml", unit="mm")
    (back,) = read_rsml(tmp_path / "deep.rsml")
    assert back.n_laterals == root.n_laterals
    assert sum(c.n_laterals for c in back.children) == sum(c.n_laterals for c in root.children) > 0
    for c, e in zip(root.children, back.children):
        assert c.n_laterals == e.n_laterals
        np.testing.assert_allclose(e.main_radius, c.main_radius, rtol=1e-9)
        for x, y, rx, ry in zip(c.laterals, e.laterals, c.lateral_radii, e.lateral_radii or ()):
            np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(ry, rx, rtol=1e-9)
        for g, h in zip(c.children, e.children):
            assert g.n_laterals == h.n_laterals == 1
            np.testing.assert_allclose(h.laterals[0], g.laterals[0], rtol=1e-9, atol=1e-12)
    t, u = (rs.batch(r, n_points=30, depth=4, max_children=(6, 4, 2), dtype=np.float64) for r in (root, back))
    # Attachments read back by projection/parent node: equal to the fractions within 1e-6.
    assert _max_abs(jax.tree.leaves(t), jax.tree.leaves(u)) < 1e-6


# --------------------------------------------------------------------------------------------
# Data


def test_synthetic_roots_grow_higher_orders_and_keep_depth_two_bit_for_bit():
    flat = synthetic_roots(4, seed=3)
    deep = synthetic_roots(4, seed=3, depth=3)
    again = synthetic_roots(4, seed=3, depth=3)
    assert all(r.children == () for r in flat)
    for a, b, c in zip(flat, deep, again):
        np.testing.assert_array_equal(a.main, b.main)
        np.testing.assert_array_equal(a.attach, b.attach)
        assert all(np.array_equal(x, y) for x, y in zip(a.laterals, b.laterals))
        assert len(b.children) == b.n_laterals
        for child, lat, child2 in zip(b.children, b.laterals, c.children):
            np.testing.assert_array_equal(child.main, lat)
            assert child.n_laterals == child2.n_laterals
            for sub, s in zip(child.laterals, child.attach):
                np.testing.assert_allclose(sub[0], _point(lat, s), atol=1e-9)
                assert polyline_length(sub) < polyline_length(lat)
    assert sum(c.n_laterals for r in deep for c in r.children) > 10
    four = synthetic_roots(2, seed=3, depth=4)
    assert sum(g.n_laterals for r in four for c in r.children for g in c.children) > 0
    with pytest.raises(ValueError, match="depth"):
        synthetic_roots(1, depth=1)


try:
    import plantbox  # noqa: F401

    _HAVE_PB = True
except ImportError:
    _HAVE_PB = False


@pytest.mark.slow
@pytest.mark.skipif(not _HAVE_PB, reason="CPlantBox is not installed (the `sim` extra)")
def test_simulated_roots_keep_higher_orders():
    from rootshape_jax.datasets import simulated_roots

    (root,) = simulated_roots("lupin", 1, days=25, seed=1, dim=2)
    n2 = sum(c.n_laterals for c in root.children)
    n3 = sum(g.n_laterals for c in root.children for g in c.children)

    def below(r):  # every lateral of r's laterals, at any depth
        return sum(c.n_laterals + below(c) for c in r.children)

    n_deep = sum(below(c) for c in root.children)
    assert len(root.children) == root.n_laterals and n2 > 0 and n3 > 0 and n_deep >= n3
    with pytest.warns(UserWarning, match=f"{n_deep} laterals of order 3"):
        t = rs.batch(root, n_points=20, depth=3)
    assert int(t.deeper[0].mask.sum()) == n2
    with pytest.warns(UserWarning, match=f"{n_deep - n3} laterals of order 4"):
        t4 = rs.batch(root, n_points=20, depth=4)
    assert int(t4.deeper[1].mask.sum()) == n3


# --------------------------------------------------------------------------------------------
# Traits


def test_per_order_traits_and_their_columns(tmp_path):
    main = np.stack([np.zeros(5), np.linspace(0, 4, 5)], 1)
    lat1 = np.array([[0.0, 1.0], [2.0, 1.0]])
    lat2 = np.array([[0.0, 2.0], [-3.0, 2.0]])
    sub = np.array([[1.0, 1.0], [1.0, 1.5]])
    child1 = rs.Root(main=lat1, laterals=[sub], attach=[0.5])
    r = rs.Root(main=main, laterals=[lat1, lat2], attach=[0.25, 0.5], children=(child1, rs.Root(main=lat2)))
    row = rs.traits(r)
    assert row["n_laterals_order1"] == 2 and row["length_order1"] == pytest.approx(5.0)
    assert row["mean_length_order1"] == pytest.approx(2.5)
    assert row["n_laterals_order2"] == 1 and row["length_order2"] == pytest.approx(0.5)
    assert "n_laterals_order3" not in row
    plain = dataclasses.replace(r, children=())
    assert not any("order" in k for k in rs.traits(plain))  # depth-2 tables unchanged
    rows = rs.traits([plain, r], orders=3)
    assert rows[0]["n_laterals_order2"] == 0 and rows[1]["n_laterals_order3"] == 0
    assert set(rs.traits([plain, r])[0]) == set(rs.traits([plain, r])[1])
    rs.traits_to_csv(rows, tmp_path / "t.csv", unit="mm")
    header = (tmp_path / "t.csv").read_text().splitlines()[0].split(",")
    assert {"n_laterals_order2", "length_order2_mm", "mean_length_order1_mm"} <= set(header)


# --------------------------------------------------------------------------------------------
# The slow reference distance (tests/helpers.reference_tree_distance)


@pytest.mark.slow
@pytest.mark.parametrize("seed, d", [(5, 2), (11, 3)])
def test_reference_equals_todays_registration_at_depth_two(seed, d):
    rng = np.random.default_rng(seed)
    a, b = random_root(rng, n_laterals=2, d=d), random_root(rng, n_laterals=3, d=d)
    w = rs.Weights(main=0.3, lateral=1.0, position=0.7)
    opts = dict(n_points=10, neighbourhood=4)
    ta, tb = rs.unstack(rs.batch([a, b], n_points=10, dtype=np.float64))
    e_ab, info = reference_tree_distance(a, b, w, 2, **opts)
    e_ba, _ = reference_tree_distance(b, a, w, 2, **opts)
    assert abs(float(rs.register(ta, tb, weights=w, neighbourhood=4).energy) - e_ab) < 1e-9
    assert abs(float(rs.register(tb, ta, weights=w, neighbourhood=4).energy) - e_ba) < 1e-9
    from rootshape_jax._engine import canonical_pairs

    first, _ = canonical_pairs(*(rs.stack([x]) for x in rs.unstack(rs.to_srvf(rs.stack([ta, tb])))))
    swapped = bool(np.array_equal(np.asarray(first.q0[0]), np.asarray(rs.to_srvf(tb).q0)))
    dist = float(rs.distance(ta, tb, weights=w, neighbourhood=4))
    assert abs(dist**2 - (e_ba if swapped else e_ab)) < 1e-9
    assert info["n_dp"][1] > 0 and info["n_dp"][1] % 6 == 0  # every real-real pair, every round
    # Without rotation search: one round from the identity.
    e_fixed, _ = reference_tree_distance(a, b, w, 2, rotation=False, **opts)
    assert abs(float(rs.register(ta, tb, weights=w, neighbourhood=4, rotation=False).energy) - e_fixed) < 1e-9


@pytest.mark.slow
def test_reference_at_depth_three_properties():
    rng = np.random.default_rng(12)
    a = deep_root(rng, n_laterals=2, max_sub=2)
    b = deep_root(rng, n_laterals=2, max_sub=2)
    w = rs.Weights(main=0.3, lateral=1.0, position=0.7)
    levels = [(1.0, 0.7), (0.5, 0.2)]
    opts = dict(n_points=8, neighbourhood=3, level_weights=levels)
    assert reference_tree_distance(a, a, w, 3, **opts)[0] == pytest.approx(0.0, abs=1e-12)
    e_ab, info = reference_tree_distance(a, b, w, 3, **opts)
    assert e_ab > 0 and info["n_dp"][2] > 0
    # The order of the children at every level does not matter.
    perm = rs.Root(
        main=b.main,
        laterals=b.laterals[::-1],
        attach=b.attach[::-1],
        children=tuple(c.select_laterals(list(range(c.n_laterals))[::-1]) for c in b.children[::-1]),
    )
    assert reference_tree_distance(a, perm, w, 3, **opts)[0] == pytest.approx(e_ab, abs=1e-12)
    # Without second-order laterals, depth 3 is depth 2.
    flat_a, flat_b = (dataclasses.replace(r, children=()) for r in (a, b))
    e3 = reference_tree_distance(flat_a, flat_b, w, 3, n_points=8, neighbourhood=3, max_children=(4, 2))[0]
    e2 = reference_tree_distance(flat_a, flat_b, w, 2, n_points=8, neighbourhood=3)[0]
    assert e3 == pytest.approx(e2, abs=1e-12)
    # A lateral subtree removed from a, at a fixed pose: matching it to a null costs its whole
    # λ-weighted norm (λs of each level times ||q||² of each branch), an upper bound that the
    # optimum reaches here (every other branch matches itself at cost 0).
    k = int(np.argmax([c.n_laterals for c in a.children]))
    keep = [j for j in range(a.n_laterals) if j != k]
    cut = a.select_laterals(keep)
    e_cut, _ = reference_tree_distance(a, cut, w, 3, rotation=False, max_children=(4, 4), **opts)
    t = rs.to_srvf(rs.batch(a, n_points=8, depth=3, max_children=(4, 4), dtype=np.float64))
    subtree = levels[0][0] * float(rs.l2_norm_squared(t.q[k])) + levels[1][0] * float(
        jnp.sum(rs.l2_norm_squared(t.deeper[0].q[k]))
    )
    assert e_cut == pytest.approx(subtree, rel=1e-9)


@pytest.mark.slow
def test_plant_systems_register_today_without_nan():
    # The engine (depth 2 today) on systems with a virtual zero-length main root: the main
    # term vanishes and the axes are matched as laterals; nothing is NaN.
    rng = np.random.default_rng(13)
    axes = [random_root(rng, n_laterals=2) for _ in range(3)]
    plants = [plant_system(axes[:2]), plant_system(axes[2:])]
    ta, tb = rs.unstack(rs.batch(plants, n_points=12, normalise_scale=True, dtype=np.float64))
    reg = rs.register(ta, tb, neighbourhood=3)
    assert float(reg.terms.main) == 0.0
    assert np.isfinite(float(reg.energy)) and float(reg.energy) > 0
    g = jax.grad(lambda x: rs.distance(eqx.tree_at(lambda t: t.laterals, ta, x), tb, neighbourhood=3))(ta.laterals)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


def test_per_order_weights_that_weigh_no_branch_are_named():
    """From a tour: Weights(deeper=...) on trees without second-order laterals (depth 2, or
    plants' systems at depth 3, whose axes' laterals take `lateral`/`position`) changed
    nothing, silently. Now a warning says so; where they weigh a level, nothing is said."""
    rng = np.random.default_rng(5)
    roots = [random_root(rng, n_laterals=2) for _ in range(2)]
    w = rs.Weights(deeper=((2.0, 0.5),))
    flat = rs.batch(roots, n_points=16, dtype=np.float64)
    with pytest.warns(UserWarning, match=r"weights.deeper has no effect.*depth 2.*depth=3"):
        rs.to_srvf(flat, weights=w)
    plants = rs.batch([plant_system(roots[:1]), plant_system(roots[1:])], depth=3, n_points=16, dtype=np.float64)
    with pytest.warns(UserWarning, match=r"weights.deeper has no effect.*plants' systems.*depth=4"):
        rs.to_srvf(rs.to_srvf(plants), weights=w)  # also for an SRVF tree
    deep = rs.batch(roots, depth=3, n_points=16, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs.to_srvf(deep, weights=w)
        rs.to_srvf(flat, weights=rs.Weights())
