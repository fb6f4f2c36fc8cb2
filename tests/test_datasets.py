import dataclasses

import numpy as np
import pytest

from rootshape_jax._root import Root, project_onto_polyline
from rootshape_jax._traits import insertion_angles, traits
from rootshape_jax.datasets import (
    CONDITIONS,
    DEFAULT_COMPOSITION,
    RootParameters,
    default_dataset,
    synthetic_roots,
)


def _same(a: Root, b: Root) -> bool:
    return (
        np.array_equal(a.main, b.main)
        and len(a.laterals) == len(b.laterals)
        and all(np.array_equal(x, y) for x, y in zip(a.laterals, b.laterals))
        and np.array_equal(a.attach, b.attach)
    )


def _point_at_fraction(main, frac):
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(main, axis=0), axis=1))])
    s = frac * cum[-1]
    return np.array([np.interp(s, cum, main[:, j]) for j in range(main.shape[1])])


@pytest.mark.parametrize("dim", [2, 3])
def test_deterministic(dim):
    a = synthetic_roots(4, seed=11, dim=dim)
    b = synthetic_roots(4, seed=11, dim=dim)
    assert all(_same(x, y) for x, y in zip(a, b))
    c = synthetic_roots(4, seed=12, dim=dim)
    assert not any(_same(x, y) for x, y in zip(a, c))
    # Root i depends only on (seed, condition, i), not on n.
    assert all(_same(x, y) for x, y in zip(synthetic_roots(2, seed=11, dim=dim), a))
    # Conditions use unrelated streams even with the same seed.
    d = synthetic_roots(4, seed=11, dim=dim, condition="drought")
    assert not any(np.allclose(x.main[:5], y.main[:5]) for x, y in zip(a, d))


@pytest.mark.parametrize("condition", sorted(CONDITIONS))
@pytest.mark.parametrize("dim", [2, 3])
def test_valid_and_consistent(condition, dim):
    p = CONDITIONS[condition]
    roots = synthetic_roots(8, condition=condition, seed=3, dim=dim)
    for i, r in enumerate(roots):
        assert isinstance(r, Root) and r.dim == dim
        assert r.metadata == {"condition": condition, "seed": 3, "index": i, "unit": "mm", "source": "synthetic"}
        assert r.name == f"{condition}_s3_{i:03d}"
        assert r.main.shape[0] >= 3 and np.all(np.isfinite(r.main))
        np.testing.assert_array_equal(r.main[0], np.zeros(dim))
        # Gravity along the last axis, pointing down (+): the tip is deep below the base.
        assert r.main[-1, -1] > 0.7 * r.main_length
        assert r.main_length >= 0.2 * p.main_length_mean
        assert r.n_laterals <= p.max_laterals
        L = r.main_length
        for lat, a, length in zip(r.laterals, r.attach, r.lateral_lengths):
            assert 0.0 <= a <= 1.0
            # Exactly on the main polyline, in the branched zone only.
            np.testing.assert_allclose(lat[0], _point_at_fraction(r.main, a), atol=1e-10)
            assert project_onto_polyline(r.main, lat[0]) == pytest.approx(a, abs=1e-9)
            assert p.basal_zone - 1e-9 <= a * L <= L - p.apical_zone + 1e-9
            assert length >= p.lateral_min_length - 1e-9
            assert lat.shape[0] >= 3
        # Attachment fractions are sorted from base to tip.
        assert np.all(np.diff(r.attach) >= 0)


@pytest.mark.parametrize("dim", [2, 3])
def test_insertion_angle_and_length_exact_without_noise(dim):
    roots = synthetic_roots(
        5,
        seed=0,
        dim=dim,
        insertion_angle_mean=37.0,
        insertion_angle_sd=0.0,
        lateral_length_cv=0.0,
        main_length_sd=0.0,
    )
    for r in roots:
        assert r.main_length == pytest.approx(120.0)
        np.testing.assert_allclose(insertion_angles(r), 37.0, atol=1e-9)
        # Without noise, lateral length is the documented linear profile of position.
        u = (r.attach * r.main_length - 5.0) / (120.0 - 5.0 - 20.0)
        np.testing.assert_allclose(r.lateral_lengths, np.maximum((1 - u) * 40.0 + u * 5.0, 1.0), rtol=1e-9)


def test_alternating_sides_2d():
    for r in synthetic_roots(5, seed=4, side_pattern="alternate"):
        sides = []
        for lat, a in zip(r.laterals, r.attach):
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(r.main, axis=0), axis=1))])
            seg = min(np.searchsorted(cum, a * cum[-1], side="right") - 1, len(r.main) - 2)
            t = r.main[seg + 1] - r.main[seg]
            d = lat[1] - lat[0]
            sides.append(np.sign(t[0] * d[1] - t[1] * d[0]))
        assert all(s1 == -s2 for s1, s2 in zip(sides, sides[1:]))
    rand = [r for r in synthetic_roots(10, seed=4, side_pattern="random")]
    assert any(r.n_laterals > 3 for r in rand)


def _mean_traits(condition, dim=2, n=30):
    rows = traits(synthetic_roots(n, condition=condition, seed=100, dim=dim))
    return {k: np.mean([r[k] for r in rows]) for k in ("main_length", "n_laterals", "mean_lateral_length", "depth")}


@pytest.mark.parametrize("dim", [2, 3])
def test_conditions_differ_in_documented_directions(dim):
    c = _mean_traits("control", dim)
    dr = _mean_traits("drought", dim)
    hn = _mean_traits("high_nitrate", dim)
    lp = _mean_traits("low_phosphate", dim)
    # Drought: longer (deeper) main root, fewer and shorter laterals.
    assert dr["main_length"] > 1.15 * c["main_length"]
    assert dr["depth"] > c["depth"]
    assert dr["n_laterals"] < 0.85 * c["n_laterals"]
    assert dr["mean_lateral_length"] < 0.8 * c["mean_lateral_length"]
    # High nitrate: more and longer laterals, shorter main root.
    assert hn["main_length"] < 0.9 * c["main_length"]
    assert hn["n_laterals"] > 1.15 * c["n_laterals"]
    assert hn["mean_lateral_length"] > 1.2 * c["mean_lateral_length"]
    # Low phosphate: short main root, more laterals.
    assert lp["main_length"] < 0.7 * c["main_length"]
    assert lp["n_laterals"] > 1.15 * c["n_laterals"]
    # Moderate numbers of laterals (the paper's roots have about 20).
    assert 10 <= c["n_laterals"] <= 25


def test_lateral_length_profile_longer_near_base():
    upper, lower = [], []
    for r in synthetic_roots(20, seed=9):
        for a, length in zip(r.attach, r.lateral_lengths):
            (upper if a < 0.4 else lower).append(length)
    assert np.mean(upper) > 1.5 * np.mean(lower)


def test_overrides_and_errors():
    r = synthetic_roots(3, seed=1, lateral_density=0.0)
    assert all(x.n_laterals == 0 for x in r)
    many = synthetic_roots(3, seed=1, lateral_density=5.0, max_laterals=7)
    assert all(x.n_laterals == 7 for x in many)
    custom = dataclasses.replace(CONDITIONS["control"], main_length_mean=50.0, main_length_sd=0.0)
    r = synthetic_roots(2, condition=custom)
    assert r[0].metadata["condition"] == "custom"
    assert r[0].main_length == pytest.approx(50.0)
    assert synthetic_roots(0) == []
    with pytest.raises(ValueError, match="Unknown condition"):
        synthetic_roots(1, condition="flood")
    with pytest.raises(ValueError, match="lateral_densty"):
        synthetic_roots(1, lateral_densty=1.0)
    with pytest.raises(ValueError, match="dim"):
        synthetic_roots(1, dim=4)
    with pytest.raises(ValueError, match="n"):
        synthetic_roots(-1)
    with pytest.raises(ValueError, match="side_pattern"):
        RootParameters(side_pattern="spiral")
    with pytest.raises(ValueError, match="segment_length"):
        RootParameters(segment_length=0.0)
    with pytest.raises(ValueError, match="lateral_density"):
        RootParameters(lateral_density=-1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        CONDITIONS["control"].lateral_density = 1.0


def test_default_dataset():
    roots = default_dataset()
    assert len(roots) == 53
    labels = [r.metadata["condition"] for r in roots]
    assert {c: labels.count(c) for c in set(labels)} == DEFAULT_COMPOSITION
    assert len({r.name for r in roots}) == 53
    again = default_dataset()
    assert all(_same(a, b) for a, b in zip(roots, again))
    # Cached arrays are shared but read-only; metadata dicts are per call.
    with pytest.raises(ValueError):
        roots[0].main[0, 0] = 1.0
    roots[0].metadata["condition"] = "edited"
    assert default_dataset()[0].metadata["condition"] == "control"
    # It is the documented generator's output, not a stored blob.
    assert _same(roots[0], synthetic_roots(1, condition="control", seed=roots[0].metadata["seed"])[0])
    r3 = default_dataset(dim=3)
    assert len(r3) == 53 and r3[0].dim == 3
