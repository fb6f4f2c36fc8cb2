"""Roots far from the coordinate origin stay in place: geodesics start at a and end at b,
with and without scale normalisation (`geodesic(in_place=True, sizes=...)`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import rootshape_jax as rs
from rootshape_jax import io
from rootshape_jax.datasets import synthetic_roots

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rsml"
T = 24


def hausdorff(P, Q) -> float:
    D = np.linalg.norm(np.asarray(P)[:, None] - np.asarray(Q)[None], axis=-1)
    return float(max(D.min(0).max(), D.min(1).max()))


def moved(root: rs.Root, shift, angle: float) -> rs.Root:
    """The root turned by `angle` about its base, then shifted."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])
    o = root.main[0]
    f = lambda x: (x - o) @ R.T + o + shift  # noqa: E731
    return dataclasses.replace(root, main=f(root.main), laterals=tuple(f(x) for x in root.laterals))


def check_in_place(a: rs.Root, b: rs.Root, *, normalise: bool, n_points: int = T, tol: float = 0.03):
    tree = rs.batch([a, b], n_points=n_points)
    ta, tb = rs.unstack(rs.batch([a, b], n_points=n_points, normalise_scale=normalise, max_laterals=tree.capacity))
    sizes = tuple(float(x) for x in np.asarray(rs.curve_length(tree.main))) if normalise else None
    path = rs.geodesic(ta, tb, n_steps=4, in_place=True, sizes=sizes)
    ra, rb = rs.unstack(tree)
    m = np.asarray(path.main)
    # Bases: exactly a's and b's, and on the straight line between them.
    np.testing.assert_allclose(m[0, 0], a.main[0], atol=1e-9)
    np.testing.assert_allclose(m[-1, 0], b.main[0], atol=1e-9)
    np.testing.assert_allclose(m[1, 0], a.main[0] + (b.main[0] - a.main[0]) / 3, atol=1e-9)
    # Whole main roots: a at the start, b as given (not rotated) at the end, real sizes.
    assert hausdorff(m[0], ra.main) < tol * a.main_length
    assert hausdorff(m[-1], rb.main) < tol * b.main_length
    # Lengths: rebuilding a curve from its SRVF changes it by ~0.05 % at this T.
    la, lb = (float(x) for x in np.asarray(rs.curve_length(path.main))[[0, -1]])
    assert la == pytest.approx(float(rs.curve_length(ra.main)), rel=5e-3)
    assert lb == pytest.approx(float(rs.curve_length(rb.main)), rel=5e-3)
    return path


@pytest.mark.slow  # registration compiles (about a minute on a loaded 2-core machine)
@pytest.mark.parametrize("normalise", [False, True])
def test_geodesic_between_far_roots_starts_at_a_and_ends_at_b(normalise):
    a0, b0 = (rs.limit_laterals(r, 3) for r in synthetic_roots(2, seed=11))
    a = moved(a0, np.array([5000.0, 3000.0]), 0.0)
    b = moved(b0.scaled(1.7), np.array([5040.0, 2980.0]), 0.5)  # turned 29°, larger
    check_in_place(a, b, normalise=normalise)


@pytest.mark.slow
def test_without_in_place_the_end_is_b_registered_and_sizes_are_checked():
    a0, b0 = (rs.limit_laterals(r, 3) for r in synthetic_roots(2, seed=12))
    a, b = moved(a0, np.array([100.0, 50.0]), 0.0), moved(b0, np.array([100.0, 50.0]), 0.6)
    ta, tb = rs.unstack(rs.batch([a, b], n_points=T))
    reg = rs.register(ta, tb)
    path = rs.geodesic(ta, tb, n_steps=3, registration=reg)
    np.testing.assert_allclose(np.asarray(path.main[-1]), np.asarray(rs.to_curves(reg.registered).main), atol=1e-9)
    placed = rs.geodesic(ta, tb, n_steps=3, registration=reg, in_place=True)
    np.testing.assert_allclose(np.asarray(placed.main[0]), np.asarray(path.main[0]), atol=1e-9)
    assert hausdorff(placed.main[-1], tb.main) < hausdorff(path.main[-1], tb.main)
    with pytest.raises(ValueError, match="sizes must be two positive"):
        rs.geodesic(ta, tb, n_steps=3, registration=reg, sizes=(1.0, -2.0))


def test_fractional_rotation_3d_composes():
    from scipy.spatial.transform import Rotation

    from rootshape_jax._geodesic import fractional_rotation

    for seed in range(4):
        R = Rotation.random(random_state=seed)
        half = np.asarray(fractional_rotation(np.asarray(R.as_matrix()), 0.5))
        np.testing.assert_allclose(half @ half, R.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(half, (R**0.5).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(np.asarray(fractional_rotation(np.eye(3), 0.3)), np.eye(3), atol=1e-12)


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "rootnav_osr" / "B_osr_0101.rsml").is_file(), reason="shared data absent")
@pytest.mark.parametrize("normalise", [False, True])
def test_real_rootnav_pair_stays_in_place(normalise):
    a = rs.limit_laterals(io.read_rsml(SHARED / "rootnav_osr" / "B_osr_0101.rsml")[0], 4)
    b = rs.limit_laterals(io.read_rsml(SHARED / "rootnav_osr" / "B_osr_0107.rsml")[0], 4)
    assert np.linalg.norm(a.main[0]) > 500  # seeds far from the origin (pixels)
    check_in_place(a, b, normalise=normalise, n_points=40, tol=0.05)
