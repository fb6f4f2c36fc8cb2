"""TMD baseline (Kanari et al. 2018) through the `tmd` package: tree conversion and barcode."""

from __future__ import annotations

import numpy as np
import pytest

from rootshape_jax import Root

pytest.importorskip("tmd")
from rootshape_jax import baselines as bl  # noqa: E402


def t_root(lateral_length=3.0, frac=0.5):
    main = np.stack([np.zeros(41), np.linspace(0.0, 10.0, 41)], axis=1)
    base = np.array([0.0, 10.0 * frac])
    lat = base + np.linspace(0.0, lateral_length, 13)[:, None] * np.array([[1.0, 0.0]])
    return Root(main=main, laterals=(lat,), attach=np.array([frac]))


def test_barcode_of_a_t_shaped_root_by_hand():
    # Radial distance from the base: the lateral's tip is at √(5² + 3²); it dies where it
    # joins the main root (radial distance 5); the main root is born at its tip (10), dies at 0.
    bars = bl.tmd_barcode(t_root())
    expected = np.array([[np.hypot(5.0, 3.0), 5.0], [10.0, 0.0]])
    np.testing.assert_allclose(bars[np.argsort(-bars[:, 1])], expected, rtol=1e-5)


def test_tree_conversion_keeps_points_and_parents():
    r = t_root()
    tree = bl.to_tmd_tree(r)
    assert len(tree.x) == 41 + 13
    assert tree.p[0] == -1 and tree.p[41] == 20  # the lateral hangs from main point 20 (fraction 0.5)
    np.testing.assert_allclose(tree.x[41:], r.laterals[0][:, 0], rtol=1e-6)


def test_distance_matrix_is_a_symmetric_dissimilarity():
    roots = [t_root(3.0), t_root(3.0), t_root(1.0, 0.3), t_root(6.0, 0.8)]
    D = bl.tmd_distance_matrix(roots, resolution=40)
    assert D.shape == (4, 4)
    np.testing.assert_allclose(D, D.T)
    assert D[0, 1] == 0.0 and np.all(np.diag(D) == 0.0)
    assert D[0, 2] > 0 and D[0, 3] > 0


def test_laterals_at_the_base_or_tip_still_branch():
    r = t_root(2.0, 1.0)
    bars = bl.tmd_barcode(r)
    assert bars.shape == (2, 2)
    r0 = t_root(2.0, 0.0)
    assert bl.tmd_barcode(r0).shape == (2, 2)
