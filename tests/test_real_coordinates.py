"""Roots far from the coordinate origin stay in place (issue 17, item 5): geodesics start at a
and end at b, with and without scale normalisation (`geodesic` is in place by default; `sizes=`
after normalisation); Karcher means (Python and `rootshape mean`) and plots stay where the data
are."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import tree_allclose

import rootshape_jax as rs
from rootshape_jax import io
from rootshape_jax._tree import normalising_length
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
    path = rs.geodesic(ta, tb, n_steps=4, sizes=sizes)  # in place is the default
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
    path = rs.geodesic(ta, tb, n_steps=3, registration=reg, in_place=False)
    np.testing.assert_allclose(np.asarray(path.main[-1]), np.asarray(rs.to_curves(reg.registered).main), atol=1e-9)
    placed = rs.geodesic(ta, tb, n_steps=3, registration=reg)  # in place: the default
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


# ------------------------------------------------------------------------------------------
# Means and plots stay where the data are

SHIFT = np.array([5000.0, -3000.0])


def far_roots(n: int = 4, seed: int = 21) -> list[rs.Root]:
    """Synthetic roots (mm) moved far from the coordinate origin, each by a slightly different shift."""
    rng = np.random.default_rng(seed)
    return [moved(rs.limit_laterals(r, 3), SHIFT + rng.uniform(-20, 20, 2), 0.0) for r in synthetic_roots(n, seed=seed)]


def check_mean_in_place(roots: list[rs.Root], main: np.ndarray, *, real_size: bool) -> None:
    """`main`: the mean's main root ([T, d]) in the data's frame."""
    seeds = np.array([r.main[0] for r in roots])
    lengths = np.array([r.main_length for r in roots])
    # Its base is the mean of the seeds (inside their range).
    np.testing.assert_allclose(main[0], seeds.mean(0), atol=1e-6 * np.abs(seeds).max())
    assert np.all(main[0] >= seeds.min(0) - 1e-9) and np.all(main[0] <= seeds.max(0) + 1e-9)
    pts = np.concatenate([r.main for r in roots])
    lo, hi = pts.min(0), pts.max(0)
    margin = 0.5 * lengths.max()
    assert np.all(main >= lo - margin) and np.all(main <= hi + margin), (main.min(0), main.max(0), lo, hi)
    length = float(np.sum(np.linalg.norm(np.diff(main, axis=0), axis=-1)))
    if real_size:  # at the data's size, not in main-root lengths
        assert lengths.min() * 0.8 < length < lengths.max() * 1.2, (length, lengths)


@pytest.mark.slow  # a Karcher mean compiles (a minute or two on a loaded 2-core machine)
@pytest.mark.parametrize("normalise", [False, True])
def test_python_karcher_mean_of_far_roots_stays_in_place(normalise):
    roots = far_roots()
    tree = rs.batch(roots, n_points=T, normalise_scale=normalise)
    km = rs.karcher_mean(tree, max_steps=3, throw=False, progress=False)
    main = np.asarray(km.mean.main)
    if normalise:
        # Normalisation divides each root by its length about (0, 0): the mean is at main-root
        # length 1; scaled back by the mean length and put at the mean seed, it is in place.
        assert float(rs.curve_length(km.mean.main)) == pytest.approx(1.0, rel=0.1)
        size = float(np.mean([r.main_length for r in roots]))
        main = np.asarray(rs.scale_tree(km.mean, size, base=np.mean([r.main[0] for r in roots], axis=0)).main)
    check_mean_in_place(roots, main, real_size=True)


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "rootnav_osr").is_dir(), reason="shared data absent")
def test_python_karcher_mean_of_rootnav_files_stays_in_place():
    files = sorted((SHARED / "rootnav_osr").glob("*.rsml"))[:4]
    roots = [rs.limit_laterals(io.read_rsml(f)[0], 3) for f in files]
    assert min(np.linalg.norm(r.main[0]) for r in roots) > 500  # pixels, far from (0, 0)
    km = rs.karcher_mean(rs.batch(roots, n_points=30), max_steps=3, throw=False, progress=False)
    check_mean_in_place(roots, np.asarray(km.mean.main), real_size=True)


@pytest.mark.slow
@pytest.mark.parametrize("normalise", ["--normalise-scale", "--no-normalise-scale"])
def test_cli_mean_rsml_is_in_the_data_frame_and_unit(tmp_path, normalise):
    roots = far_roots()
    folder = tmp_path / "in"
    folder.mkdir()
    io.write_rsml(roots, folder / "far.rsml")
    back = io.read_rsml(folder / "far.rsml")
    assert back[0].metadata["unit"] == "mm"
    out = tmp_path / "out"
    proc = run_cli("mean", folder, "--points", T, "--laterals", 3, "--max-steps", 3, normalise, "--quiet", "--out", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (mean,) = io.read_rsml(out / "mean.rsml")
    assert mean.metadata["unit"] == "mm"
    check_mean_in_place(back, mean.main, real_size=True)
    # Upright like the inputs: its main root points their mean direction (the metric ignores
    # rotation, so the fit alone leaves it at the starting root's tilt, moved by the fit).
    chords = np.array([r.main[-1] - r.main[0] for r in back])
    target = np.sum(chords / np.linalg.norm(chords, axis=1, keepdims=True), axis=0)
    m = mean.main[-1] - mean.main[0]
    cos = float(m @ target / np.linalg.norm(m) / np.linalg.norm(target))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.5
    if normalise == "--normalise-scale":
        # The normalised mean (shorter than 1: averaging shrinks) gets the inputs' mean length.
        from rootshape_jax._tree import normalising_length

        size = np.mean([normalising_length(r, T) for r in back])
        assert mean.main_length == pytest.approx(size, rel=1e-4)


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rootshape_jax", *map(str, args)], capture_output=True, text=True, timeout=1800
    )


def test_plots_draw_far_roots_where_they_are():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rootshape_jax import plot as rplot

    roots = far_roots(2)
    tree = rs.batch(roots, n_points=T)
    for fig, ax, root in [
        (*rplot.plot_root(roots[0]), roots[0]),
        (*rplot.plot_root(rs.unstack(tree)[1]), roots[1]),
    ]:
        xy = np.concatenate([np.asarray(seg) for c in ax.collections for seg in c.get_segments()])
        # The drawn lines are the root's own coordinates, and the view holds them.
        assert hausdorff(xy, np.concatenate([root.main, *root.laterals])) < 0.03 * root.main_length
        (x0, x1), (y0, y1) = ax.get_xlim(), sorted(ax.get_ylim())
        assert x0 <= xy[:, 0].min() and xy[:, 0].max() <= x1 and y0 <= xy[:, 1].min() and xy[:, 1].max() <= y1
        assert x0 > 4000 and y1 < -2000
        plt.close(fig)
    # A geodesic strip: every panel shows the same region, holding every step where it is.
    fig, axes = rplot.plot_geodesic(tree, title=None)
    main = np.asarray(tree.main)
    for ax in np.ravel(axes):
        (x0, x1), (y0, y1) = ax.get_xlim(), sorted(ax.get_ylim())
        assert x0 <= main[..., 0].min() and main[..., 0].max() <= x1
        assert y0 <= main[..., 1].min() and main[..., 1].max() <= y1
    plt.close(fig)


def test_normalised_roots_far_from_the_origin_keep_float32_precision():
    # Normalisation divides each root by its length about (0, 0), so a root 1e5 mm from (0, 0)
    # keeps the digits its coordinates had. (Scaled about its base, as before, a length-1 root
    # at 1e5 lost most of a segment to float32 rounding; the SRVFs came out wrong.)
    roots = [rs.limit_laterals(r, 2) for r in synthetic_roots(2, seed=4)]
    far = [moved(r, np.array([1e5, -7e4]), 0.3) for r in roots]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t32 = rs.batch(far, n_points=50, normalise_scale=True, dtype=np.float32)
    t64 = rs.batch(far, n_points=50, normalise_scale=True, dtype=np.float64)
    near = rs.batch([moved(r, np.zeros(2), 0.3) for r in roots], n_points=50, normalise_scale=True, dtype=np.float64)
    # The same length-1 shapes with their bases left at the seeds (scaled about the base).
    lengths = [normalising_length(r, 50) for r in far]
    seeds = np.array([r.main[0] for r in far])
    at_seeds = jax.tree_util.tree_map(
        lambda x: x.astype(np.float32) if x.dtype == np.float64 else x, rs.scale_tree(t64, 1.0, base=seeds)
    )
    q32, q64, q_near, q_seeds = (np.asarray(rs.to_srvf(t).q0, np.float64) for t in (t32, t64, near, at_seeds))
    np.testing.assert_allclose(q64, q_near, atol=1e-9)  # the shape does not depend on the place
    # float32 keeps what the data's own coordinates hold (1e5 against segments of ~2 mm: a few
    # 1e-3 of a unit SRVF); at the seeds it lost a large part of every segment.
    assert np.abs(q32 - q64).max() < 5e-3
    assert np.abs(q_seeds - q64).max() > 0.1
    lat32, lat64 = (np.asarray(rs.to_srvf(t).q, np.float64) for t in (t32, t64))
    assert np.abs(lat32 - lat64).max() < 5e-3
    # The seeds went to seed / length; scale_tree(base=...) puts the roots back.
    back = rs.scale_tree(t64, lengths, base=seeds)
    assert tree_allclose(back, rs.batch(far, n_points=50, dtype=np.float64), atol=1e-8)


def test_batch_warns_when_float32_cannot_hold_roots_far_from_the_origin():
    # 1e8 mm from (0, 0), float32 rounds every point by a large fraction of a segment: the
    # data themselves cannot be held, normalised or not.
    root = rs.limit_laterals(synthetic_roots(1, seed=4)[0], 2)
    far = moved(root, np.array([1e8, 1e8]), 0.0)
    for normalise in (False, True):
        with pytest.warns(UserWarning, match=r"float32 rounds the coordinates of 1 root.*--float64"):
            rs.batch([far], n_points=50, normalise_scale=normalise, dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs.batch([root], n_points=50, normalise_scale=True, dtype=np.float32)  # near the origin
        rs.batch([moved(root, np.array([1e5, 1e5]), 0.0)], n_points=50, normalise_scale=True, dtype=np.float32)
        rs.batch([far], n_points=50, normalise_scale=True, dtype=np.float64)


def test_geodesic_strip_of_roots_far_apart_centres_each_panel_on_its_step():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rootshape_jax import plot as rplot

    a, b = far_roots(2)
    size = max(a.main_length, b.main_length)
    b = moved(b, np.array([10 * size, 0.0]), 0.0)  # another plant, ten root lengths away
    tree = rs.batch([a, b], n_points=T)
    main = np.asarray(tree.main)
    fig, axes = rplot.plot_geodesic(tree, title=None)  # auto: the bases travel far
    widths = []
    for ax, m in zip(np.ravel(axes), main):
        (x0, x1), (y0, y1) = ax.get_xlim(), sorted(ax.get_ylim())
        assert x0 <= m[:, 0].min() and m[:, 0].max() <= x1 and y0 <= m[:, 1].min() and m[:, 1].max() <= y1
        widths.append(x1 - x0)
    assert widths[0] == pytest.approx(widths[1]) and widths[0] < 3 * size  # same scale, each root large
    plt.close(fig)
    fig, axes = rplot.plot_geodesic(tree, title=None, align_bases=False)  # one region for all
    for ax in np.ravel(axes):
        x0, x1 = ax.get_xlim()
        assert x0 <= main[..., 0].min() and main[..., 0].max() <= x1
    plt.close(fig)


def test_precision_check_on_plants_collapsed_roots_and_no_lateral_slots():
    from rootshape_jax.io import plant_system

    root = rs.limit_laterals(synthetic_roots(1, seed=5)[0], 2)
    far = moved(root, np.array([1e8, 1e8]), 0.0)
    # A plant's system (zero-length main root) is measured against its axis.
    with pytest.warns(UserWarning, match="float32 rounds the coordinates of 1 root"):
        rs.batch([plant_system([far])], n_points=50, normalise_scale=True, dtype=np.float32, depth=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs.batch([plant_system([root])], n_points=50, normalise_scale=True, dtype=np.float32, depth=3)
        # No lateral slots at all: nothing to reduce over, no crash.
        bare = dataclasses.replace(root, laterals=(), attach=np.zeros(0), children=())
        rs.batch([bare], n_points=50, max_laterals=0, dtype=np.float32)
    # So far away that float32 collapses the normalised root to a point: all of it is lost.
    with pytest.warns(UserWarning, match="by up to all of a main-root segment"):
        rs.batch([moved(root, np.array([1e13, 1e13]), 0.0)], n_points=50, normalise_scale=True, dtype=np.float32)
