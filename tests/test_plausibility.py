"""Plausibility of synthesised roots: each criterion on hand-made cases."""

import numpy as np
import pytest
import scipy.stats

import rootshape_jax as rs
from rootshape_jax._plausibility import self_crossing


def _line(a, b, n=20):
    return np.linspace(a, b, n)


def test_self_crossing_cases():
    assert not self_crossing(_line([0, 0], [1, 2]))
    # A loop: a branch that runs on, turns round and crosses its earlier part.
    t = np.linspace(np.pi, 3 * np.pi, 60)
    curl = np.stack([t - 1.5 * np.sin(t), 1.5 * (1 - np.cos(t))], axis=1)
    assert self_crossing(curl)
    # The same curve stopped before it closes does not cross.
    assert not self_crossing(curl[:30])
    # A cusp: the branch turns back on itself.
    cusp = np.concatenate([_line([0, 0], [1, 0], 10), _line([1, 0], [0.5, 0.01], 10)[1:]])
    assert self_crossing(cusp)
    # 3D: a helix never comes near itself; a curve through its own earlier point does.
    s = np.linspace(0, 4 * np.pi, 80)
    helix = np.stack([np.cos(s), np.sin(s), 0.5 * s], axis=1)
    assert not self_crossing(helix)
    flat = helix.copy()
    flat[:, 2] = 0.0
    assert self_crossing(flat)


def _root(lat_lengths, bend=False):
    main = _line([0.0, 0.0], [0.0, 10.0], 30)
    lats, attach = [], []
    for k, L in enumerate(lat_lengths):
        y = 2.0 + 2 * k
        if bend:
            t = np.linspace(np.pi, 3 * np.pi, 60)
            lat = np.stack([t - 1.5 * np.sin(t), 1.5 * (1 - np.cos(t))], axis=1) * L / 8 + [0.0, y]
        else:
            lat = _line([0.0, y], [L, y + 0.2 * L])
        lats.append(lat)
        attach.append(y / 10)
    return rs.Root(main=main, laterals=lats, attach=np.array(attach))


def test_plausibility_of_a_batch():
    ref = rs.batch([_root([1.0, 2.0]), _root([3.0, 1.5, 2.5])], n_points=40, max_laterals=4)
    good = _root([1.2, 2.9])
    too_long = _root([1.2, 5.0])
    tangled = _root([2.0], bend=True)
    trees = rs.batch([good, too_long, tangled], n_points=40, max_laterals=4)
    p = rs.plausibility(trees, ref)

    # Lengths of the resampled polylines, slowly: one lateral at a time.
    def lengths(t):
        out = []
        for r in range(t.mask.shape[0]):
            for k in np.flatnonzero(np.asarray(t.mask[r])):
                lat = np.asarray(t.laterals[r, k])
                out.append(sum(np.linalg.norm(lat[i + 1] - lat[i]) for i in range(len(lat) - 1)))
        return np.array(out)

    ref_lengths = lengths(ref)
    lo, hi = p.length_range
    np.testing.assert_allclose([lo, hi], [ref_lengths.min(), ref_lengths.max()], rtol=1e-6)
    tangled_len = lengths(rs.batch([tangled], n_points=40, max_laterals=4))
    np.testing.assert_array_equal(p.lengths_in_range, [True, False, _in(tangled_len, lo, hi)])
    np.testing.assert_array_equal(p.no_self_crossing, [True, True, False])
    assert p.plausible[0] and not p.plausible[1] and not p.plausible[2]
    assert p.rate == pytest.approx(1 / 3)
    pooled = lengths(trees)
    ks = scipy.stats.ks_2samp(pooled, ref_lengths)
    assert p.ks_statistic == pytest.approx(ks.statistic, rel=1e-6)
    assert p.ks_pvalue == pytest.approx(ks.pvalue, rel=1e-4)
    # Widening the range by 70 % admits the long lateral (5.0 <= 3.0 × 1.7).
    assert rs.plausibility(trees, ref, tolerance=0.7).lengths_in_range[1]


def _in(lengths, lo, hi):
    return all(lo <= x <= hi for x in lengths)


def test_bad_input():
    ref = rs.batch([_root([1.0, 2.0])], n_points=20)
    with pytest.raises(TypeError, match="RootTree"):
        rs.plausibility([1, 2], ref)
    with pytest.raises(ValueError, match="tolerance"):
        rs.plausibility(ref, ref, tolerance=-1.0)
    with pytest.raises(ValueError, match="no real lateral"):
        rs.plausibility(ref, rs.batch([_root([])], n_points=20))
