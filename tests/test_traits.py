import csv
import dataclasses
import math

import numpy as np
import pytest

from rootshape_jax import trait_column as rs_trait_column
from rootshape_jax._errors import InvalidRootError, UnitError
from rootshape_jax._root import Root
from rootshape_jax._traits import TRAIT_NAMES, insertion_angles, traits, traits_to_csv
from rootshape_jax.datasets import synthetic_roots


def l_shaped_root():
    # Main: down 6, then right 4 (length 10). Lateral 1 at arc 3 going down-right at 45°;
    # lateral 2 at arc 8 (on the horizontal part) going straight down (90° to the main).
    return Root(
        main=np.array([[0.0, 0.0], [0.0, 6.0], [4.0, 6.0]]),
        laterals=(np.array([[0.0, 3.0], [2.0, 5.0]]), np.array([[2.0, 6.0], [2.0, 9.0]])),
        attach=np.array([0.3, 0.8]),
        name="L",
    )


def test_l_shaped_root_by_hand():
    t = traits(l_shaped_root())
    l1, l2 = 2 * math.sqrt(2), 3.0
    assert t["name"] == "L"
    assert t["main_length"] == pytest.approx(10.0)
    assert t["n_laterals"] == 2
    assert t["lateral_density"] == pytest.approx(0.2)
    assert t["mean_lateral_length"] == pytest.approx((l1 + l2) / 2)
    assert t["std_lateral_length"] == pytest.approx(abs(l2 - l1) / 2)
    assert t["total_lateral_length"] == pytest.approx(l1 + l2)
    assert t["total_length"] == pytest.approx(10 + l1 + l2)
    assert t["main_tortuosity"] == pytest.approx(10 / math.sqrt(52))
    assert t["mean_insertion_angle"] == pytest.approx((45 + 90) / 2)
    np.testing.assert_allclose(insertion_angles(l_shaped_root()), [45.0, 90.0])
    assert t["depth"] == pytest.approx(9.0)
    assert t["width"] == pytest.approx(4.0)
    # Hull vertices (0,0), (4,6), (2,9), (0,6): shoelace area 18.
    assert t["convex_hull_area"] == pytest.approx(18.0)
    assert math.isnan(t["convex_hull_volume"])
    assert set(TRAIT_NAMES) | {"name", "unit"} == set(t)
    assert t["unit"] is None  # the hand-made root names no unit


def test_traits_name_their_unit_and_the_csv_columns_carry_it(tmp_path):
    """Each row names its root's unit, so traits_to_csv labels the length columns without
    being told; roots of different units keep plain names and say their unit per row."""
    root = l_shaped_root()
    mm = dataclasses.replace(root, metadata={"unit": "mm"})
    rows = traits([mm, mm])
    assert [r["unit"] for r in rows] == ["mm", "mm"] and list(rows[0])[:2] == ["name", "unit"]
    traits_to_csv(rows, tmp_path / "t.csv")
    with open(tmp_path / "t.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert {"main_length_mm", "convex_hull_area_mm2", "lateral_density_per_mm"} <= set(table[0])
    assert table[0]["unit"] == "mm" and float(table[0]["main_length_mm"]) == pytest.approx(10.0)
    # A plant's system has its axes' unit; axes in different units make no plant.
    from rootshape_jax.io import plant_system

    assert traits(plant_system([mm, mm]))["unit"] == "mm"
    with pytest.raises(UnitError, match=r"different units \['cm', 'mm'\].*convert_units"):
        plant_system([mm, dataclasses.replace(root, metadata={"unit": "cm"})])
    cm = dataclasses.replace(root, metadata={"unit": "cm"})
    traits_to_csv(traits([mm, cm]), tmp_path / "mixed.csv")
    with open(tmp_path / "mixed.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert "main_length" in table[0] and [r["unit"] for r in table] == ["mm", "cm"]


@pytest.mark.parametrize("angle", [10.0, 45.0, 90.0, 120.0, 170.0])
@pytest.mark.parametrize("main_dir_deg", [0.0, 30.0, -75.0])
def test_insertion_angle_known_2d(angle, main_dir_deg):
    phi = math.radians(main_dir_deg)
    t = np.array([math.sin(phi), math.cos(phi)])  # main heading, tilted from straight down
    main = np.outer(np.linspace(0, 10, 6), t)
    a = math.radians(angle)
    for side in (1, -1):
        n = side * np.array([-t[1], t[0]])
        d = math.cos(a) * t + math.sin(a) * n
        base = 4.0 * t
        root = Root(main=main, laterals=(np.stack([base, base + 2.5 * d]),), attach=[0.4])
        assert traits(root)["mean_insertion_angle"] == pytest.approx(angle, abs=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_insertion_angle_known_3d(seed):
    rng = np.random.default_rng(seed)
    t = rng.normal(size=3)
    t /= np.linalg.norm(t)
    n = rng.normal(size=3)
    n -= (n @ t) * t
    n /= np.linalg.norm(n)
    angle = rng.uniform(5, 175)
    a = math.radians(angle)
    d = math.cos(a) * t + math.sin(a) * n
    main = np.outer(np.linspace(0, 10, 11), t)
    root = Root(main=main, laterals=(np.stack([5 * t, 5 * t + d, 5 * t + 3 * d]),), attach=[0.5])
    assert traits(root)["mean_insertion_angle"] == pytest.approx(angle, abs=1e-9)


def test_insertion_angle_window():
    main = np.array([[0.0, 0.0], [0.0, 10.0]])
    # First segment perpendicular, then a turn downward: the chord over 2 units is at 45°.
    lat = np.array([[0.0, 5.0], [1.0, 5.0], [1.0, 6.0], [1.0, 9.0]])
    root = Root(main=main, laterals=(lat,), attach=[0.5])
    assert insertion_angles(root)[0] == pytest.approx(90.0)
    assert insertion_angles(root, window=2.0)[0] == pytest.approx(45.0)
    with pytest.raises(ValueError, match="window"):
        insertion_angles(root, window=0.0)


def test_insertion_angle_skips_a_tracers_stub():
    # As in the RhizoScan plate files: each lateral starts with a 1 px segment from the parent
    # node, at right angles, then runs at 60° in 6 px segments. The stub is not the direction
    # (the first-segment rule gave 90° for every plate lateral); nor is a stub of the main root.
    main = np.array([[0.0, 0.0], [0.0, 6.0], [0.0, 6.5], [0.0, 12.0], [0.0, 18.0]])
    a = math.radians(60.0)
    d = np.array([math.sin(a), math.cos(a)])
    lat = np.concatenate([[[0.0, 6.25], [-1.0, 6.25]], [-1.0, 6.25] + 6.0 * np.arange(1, 5)[:, None] * d])
    root = Root(main=main, laterals=(lat,), attach=[6.25 / 18.0])
    got = insertion_angles(root)[0]
    # The chord from the base past the stub: 60° off by the stub's 1 px over 6 px.
    want = math.degrees(math.acos(float(np.clip((lat[2] - lat[0]) @ [0, 1] / np.linalg.norm(lat[2] - lat[0]), -1, 1))))
    assert got == pytest.approx(want) and abs(got - 60.0) < 6.0


def test_insertion_angle_at_a_vertex_and_zero_length_segments():
    # Attachment exactly at the main root's corner: the segment that starts there is used.
    main = np.array([[0.0, 0.0], [0.0, 5.0], [0.0, 5.0], [5.0, 5.0]])
    lat = np.array([[0.0, 5.0], [0.0, 5.0], [0.0, 8.0]])
    root = Root(main=main, laterals=(lat,), attach=[0.5])
    assert insertion_angles(root)[0] == pytest.approx(90.0)


def test_3d_root_by_hand():
    main = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
    lats = (np.array([[0.0, 0.0, 5.0], [3.0, 4.0, 5.0]]), np.array([[0.0, 0.0, 5.0], [-4.0, 3.0, 5.0]]))
    t = traits(Root(main=main, laterals=lats, attach=[0.5, 0.5]))
    assert t["main_length"] == pytest.approx(10.0)
    assert t["mean_lateral_length"] == pytest.approx(5.0)
    assert t["std_lateral_length"] == pytest.approx(0.0)
    assert t["mean_insertion_angle"] == pytest.approx(90.0)
    assert t["depth"] == pytest.approx(10.0)
    assert t["width"] == pytest.approx(math.sqrt(50.0))  # |(3,4) - (-4,3)|
    assert t["convex_hull_area"] == pytest.approx(12.5)  # footprint triangle
    # Tetrahedron (0,0,0), (0,0,10), (3,4,5), (-4,3,5): |det| / 6 = 250 / 6.
    assert t["convex_hull_volume"] == pytest.approx(250.0 / 6.0)


def test_degenerate_roots():
    straight = Root(main=np.array([[0.0, 0.0], [0.0, 3.0], [0.0, 7.0]]))
    t = traits(straight)
    assert t["n_laterals"] == 0
    assert t["mean_lateral_length"] == 0.0 and t["std_lateral_length"] == 0.0
    assert t["total_lateral_length"] == 0.0
    assert math.isnan(t["mean_insertion_angle"])
    assert t["depth"] == pytest.approx(7.0)
    assert t["width"] == 0.0
    assert t["convex_hull_area"] == 0.0
    # One lateral in 3D: everything lies in a plane, footprint is a segment.
    flat = Root(
        main=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 4.0]]),
        laterals=(np.array([[0.0, 0.0, 2.0], [3.0, 4.0, 6.0]]),),
        attach=[0.5],
    )
    t3 = traits(flat)
    assert t3["convex_hull_area"] == 0.0
    assert t3["convex_hull_volume"] == 0.0
    assert t3["width"] == pytest.approx(5.0)


def _brute_force(root):
    """Slow obvious reference for the geometric traits."""
    pts = np.concatenate([root.main, *root.laterals])
    lens = [sum(np.linalg.norm(b[i + 1] - b[i]) for i in range(len(b) - 1)) for b in root.laterals]
    horiz = pts[:, :-1]
    width = max(np.linalg.norm(p - q) for p in horiz for q in horiz)
    return {
        "mean_lateral_length": float(np.mean(lens)),
        "std_lateral_length": float(np.sqrt(np.mean((np.array(lens) - np.mean(lens)) ** 2))),
        "depth": float(pts[:, -1].max() - pts[:, -1].min()),
        "width": float(width),
    }


def _shoelace_hull_area(points):
    # Monotone chain hull + shoelace, independent of scipy.
    pts = sorted(map(tuple, np.unique(points, axis=0)))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    hull = np.array(lower[:-1] + upper[:-1])
    x, y = hull[:, 0], hull[:, 1]
    return 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


@pytest.mark.parametrize("dim", [2, 3])
def test_against_brute_force_on_synthetic(dim):
    for root in synthetic_roots(3, seed=5, dim=dim, segment_length=6.0):
        t = traits(root)
        ref = _brute_force(root)
        for k, v in ref.items():
            assert t[k] == pytest.approx(v, rel=1e-10, abs=1e-10), k
        pts = np.concatenate([root.main, *root.laterals])
        hull_pts = pts if dim == 2 else pts[:, :2]
        assert t["convex_hull_area"] == pytest.approx(_shoelace_hull_area(hull_pts), rel=1e-10)


def test_invariances():
    root = synthetic_roots(1, seed=3, dim=3)[0]
    t0 = traits(root)
    # Rotation about the vertical axis + translation: nothing changes.
    c, s = math.cos(0.7), math.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    shift = np.array([3.0, -2.0, 5.0])
    moved = Root(
        main=root.main @ R.T + shift,
        laterals=tuple(lat @ R.T + shift for lat in root.laterals),
        attach=root.attach,
    )
    t1 = traits(moved)
    for k in TRAIT_NAMES:
        assert t1[k] == pytest.approx(t0[k], rel=1e-9), k
    # Scaling by 2: lengths ×2, areas ×4, volume ×8, density ÷2, angles and counts unchanged.
    t2 = traits(root.scaled(2.0))
    power = {
        "n_laterals": 0,
        "lateral_density": -1,
        "main_tortuosity": 0,
        "mean_insertion_angle": 0,
        "convex_hull_area": 2,
        "convex_hull_volume": 3,
    }
    for k in TRAIT_NAMES:
        assert t2[k] == pytest.approx(t0[k] * 2.0 ** power.get(k, 1), rel=1e-9), k


def test_list_input_and_errors():
    roots = synthetic_roots(3, seed=1)
    rows = traits(roots)
    assert isinstance(rows, list) and len(rows) == 3
    assert rows[1] == traits(roots[1])
    assert traits([]) == []
    with pytest.raises(InvalidRootError, match="Root"):
        traits(np.zeros((3, 2)))
    with pytest.raises(InvalidRootError, match="Root"):
        traits("root.rsml")


def test_csv_round_trip(tmp_path):
    rows = traits(synthetic_roots(4, seed=2)) + [traits(Root(main=np.array([[0.0, 0.0], [0.0, 1.0]])))]
    rows[0]["condition"] = "control"  # extra column on one row only
    path = tmp_path / "traits.csv"
    traits_to_csv(rows, path)
    with open(path, newline="") as f:
        back = list(csv.DictReader(f))
    assert len(back) == len(rows)
    # Without a unit only the angle's column names its unit (degrees).
    columns = [rs_trait_column(k, None) for k in TRAIT_NAMES]
    assert "mean_insertion_angle_deg" in columns
    assert list(back[0])[: len(TRAIT_NAMES) + 2] == ["name", "unit", *columns]
    assert back[0]["condition"] == "control" and back[1]["condition"] == ""
    for r, b in zip(rows, back):
        assert b["name"] == r["name"]
        for k in TRAIT_NAMES:
            v = float(b[rs_trait_column(k, None)])
            assert (math.isnan(v) and math.isnan(r[k])) or v == r[k], k  # exact round trip
    traits_to_csv(rows[0], tmp_path / "one.csv")
    with open(tmp_path / "one.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 1


def test_plant_systems_are_described_as_plants():
    """A plant's system (axes under a zero-length virtual main root) is described by its axes:
    main = the longest axis, laterals = every axis's laterals, totals over the whole plant;
    a plant of one axis has exactly the traits of that axis (issue 21's review: they were 0,
    NaN and the axes counted as laterals)."""
    from rootshape_jax.io import plant_system

    axes = synthetic_roots(3, seed=7, dim=2, segment_length=6.0)
    plant = plant_system(axes, name="p")
    row = traits(plant)
    lens = [sum(np.linalg.norm(np.diff(a.main, axis=0), axis=1)) for a in axes]
    lat_lens = [sum(np.linalg.norm(np.diff(lat, axis=0), axis=1)) for a in axes for lat in a.laterals]
    primary = axes[int(np.argmax(lens))]
    pts = np.concatenate([p for a in axes for p in (a.main, *a.laterals)])
    assert row["n_axes"] == 3 and list(row)[:4] == ["name", "n_axes", "unit", "main_length"]
    assert row["main_length"] == pytest.approx(max(lens), rel=1e-12)
    assert row["main_tortuosity"] == pytest.approx(traits(primary)["main_tortuosity"], rel=1e-12)
    assert row["n_laterals"] == len(lat_lens) == sum(a.n_laterals for a in axes)
    assert row["lateral_density"] == pytest.approx(len(lat_lens) / sum(lens), rel=1e-12)
    assert row["mean_lateral_length"] == pytest.approx(np.mean(lat_lens), rel=1e-12)
    assert row["std_lateral_length"] == pytest.approx(np.std(lat_lens), rel=1e-12)
    assert row["total_length"] == pytest.approx(sum(lens) + sum(lat_lens), rel=1e-12)
    angles = np.concatenate([insertion_angles(a) for a in axes])
    assert row["mean_insertion_angle"] == pytest.approx(np.nanmean(angles), rel=1e-12)
    assert row["depth"] == pytest.approx(pts[:, 1].max() - pts[:, 1].min(), rel=1e-12)
    assert row["width"] == pytest.approx(pts[:, 0].max() - pts[:, 0].min(), rel=1e-12)
    assert row["convex_hull_area"] == pytest.approx(_shoelace_hull_area(pts), rel=1e-10)
    # One axis: the axis's own traits, plus n_axes = 1.
    one = traits(plant_system(axes[:1], name=axes[0].name))
    alone = traits(axes[0])
    assert math.isnan(one.pop("convex_hull_volume")) and math.isnan(alone.pop("convex_hull_volume"))  # 2D
    assert one.pop("n_axes") == 1 and one == alone
    # A plant without axes (all dropped) is its virtual main root alone, not an error.
    empty = traits(plant.select_laterals([]))
    assert empty["n_axes"] == 0 and empty["n_laterals"] == 0 and empty["main_length"] == 0.0
    # A table mixing plants and single roots stays rectangular; single roots have one axis.
    rows = traits([plant, axes[1]])
    assert list(rows[0]) == list(rows[1]) and rows[1]["n_axes"] == 1
    assert "n_axes" not in traits(axes)[0]
