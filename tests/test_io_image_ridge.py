"""Ridge-filter extraction (issue 19): synthetic roots at several widths, contrasts and
polarities, gaps, clutter that is not a plant, bad inputs, compare_to_tracing, extract_images."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import render_root_image

from rootshape_jax import Root
from rootshape_jax._errors import ImageError
from rootshape_jax._root import polyline_length
from rootshape_jax.io import compare_to_tracing, read_rsml, roots_from_image, total_length
from rootshape_jax.io._extract_cli import extract_images


def _seedling(seed, *, x0, y0=30.0, length=300.0, n_lat=3):
    """A wavy main root going down with straight laterals alternating left and right."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 300)
    main = np.stack([x0 + rng.uniform(4, 12) * np.sin(rng.uniform(1, 3) * t * math.pi), y0 + length * t], axis=1)
    cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(main, axis=0), axis=1))])
    fracs = np.linspace(0.2, 0.65, n_lat) + rng.uniform(-0.03, 0.03, n_lat)
    lats = []
    for k, f in enumerate(fracs):
        p = np.array([np.interp(f * cum[-1], cum, main[:, j]) for j in range(2)])
        side = 1 if k % 2 == 0 else -1
        ang = rng.uniform(0.4, 0.8)
        d = np.array([side * math.cos(ang), math.sin(ang)])
        lats.append(p + np.linspace(0, 1, 30)[:, None] * rng.uniform(45, 70) * d)
    return main, lats


def _draw(polylines, *, shape, width, contrast, noise, dark=True, seed=0, gaps=()):
    """render_root_image's mask, redrawn at a chosen contrast around a mid-grey background."""
    _, mask = render_root_image(polylines, shape=shape, width=width, noise=0.0, seed=seed, gaps=gaps)
    bg = 0.6
    fg = bg - contrast if dark else bg + contrast
    img = np.where(mask, fg, bg) + noise * np.random.default_rng(seed).standard_normal(shape)
    return np.clip(img, 0, 1)


# Measured over the grid below (seeds 0-1): main length within 3.5 %, lateral lengths within 6 px
# of the drawn ones; tolerances set with margin.
@pytest.mark.parametrize("width", [2.0, 4.0, 7.0])
@pytest.mark.parametrize("contrast, noise", [(0.4, 0.05), (0.15, 0.03)])
@pytest.mark.parametrize("dark", [True, False])
def test_widths_contrasts_polarities(width, contrast, noise, dark):
    main, lats = _seedling(int(width * 10 + 100 * contrast), x0=150)
    img = _draw([main, *lats], shape=(380, 300), width=width, contrast=contrast, noise=noise, dark=dark, seed=1)
    (r,) = roots_from_image(img)
    assert r.metadata["roots_dark"] is dark
    assert r.main_length == pytest.approx(polyline_length(main), rel=0.05)
    assert r.n_laterals == len(lats)
    np.testing.assert_allclose(r.lateral_lengths, [polyline_length(l) for l in lats], atol=10.0)
    assert np.linalg.norm(r.main[0] - main[0]) < 5


@pytest.mark.parametrize("width", [14.0, 20.0])
@pytest.mark.parametrize("dark", [True, False])
def test_wide_roots_with_root_width(width, dark):
    # Roots wider than the default scales (σ up to 3) need root_width: the large scales run
    # on a block-averaged image. Measured: main length within 1 %, laterals exact.
    main, lats = _seedling(3, x0=200, length=500)
    img = _draw([main, *lats], shape=(620, 400), width=width, contrast=0.4, noise=0.05, dark=dark, seed=1)
    (r,) = roots_from_image(img, root_width=24)
    assert r.metadata["roots_dark"] is dark
    assert r.main_length == pytest.approx(polyline_length(main), rel=0.03)
    assert r.n_laterals == len(lats)


def test_ridge_sigmas_and_block_helpers():
    from rootshape_jax.io._image import _block_mean, _repeat_to, _ridge_sigmas

    assert _ridge_sigmas(6) == (1.0, 2.0, 3.0)
    assert _ridge_sigmas(24) == (1.0, 2.0, 3.0, 4.0, 6.0, 9.0, 12.0)
    rng = np.random.default_rng(0)
    a = rng.random((2100, 37)).astype(np.float32)  # more rows than one band, odd sizes
    m = _block_mean(a, 4)
    ref = np.array(
        [
            [a[i : i + 4, j : j + 4].mean() if i + 4 <= 2100 and j + 4 <= 37 else np.nan for j in range(0, 37, 4)]
            for i in range(0, 2100, 4)
        ]
    )
    ok = np.isfinite(ref)
    np.testing.assert_allclose(m[ok], ref[ok], rtol=1e-5)
    back = _repeat_to(m, 4, a.shape)
    assert back.shape == a.shape and back[5, 9] == m[1, 2]


def test_colour_photo_light_roots_on_blue_paper():
    # White roots on blue paper (as in the RootNav photographs): colour is converted to
    # luminance, polarity found automatically.
    main, lats = _seedling(3, x0=150)
    _, mask = render_root_image([main, *lats], shape=(380, 300), width=4, noise=0.0)
    rng = np.random.default_rng(0)
    blue = np.array([50, 66, 190], float)
    white = np.array([225, 225, 215], float)
    rgb = np.where(mask[..., None], white, blue) + rng.normal(0, 8, (380, 300, 3))
    (r,) = roots_from_image(np.clip(rgb, 0, 255).astype(np.uint8))
    assert r.metadata["roots_dark"] is False
    assert r.main_length == pytest.approx(polyline_length(main), rel=0.05)
    assert r.n_laterals == 3


@pytest.mark.parametrize("gap", [8, 14])
def test_gaps_are_bridged(gap):
    main, lats = _seedling(5, x0=150)
    img = _draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.04, gaps=[(260, 260 + gap)])
    (r,) = roots_from_image(img)
    assert r.main_length == pytest.approx(polyline_length(main), rel=0.05)
    assert r.n_laterals == 3
    # Without bridging the main root stops at the gap.
    parts = roots_from_image(img, bridge_gaps=0, close_gaps=0, min_plant_fraction=0)
    assert parts[0].main_length < 0.85 * polyline_length(main)


_RIMS = {
    "closed": [[40, 40], [520, 40], [520, 560], [40, 560], [40, 40]],
    "open_bottom": [[40, 560], [40, 40], [520, 40], [520, 560]],  # a U upside down
    "corner": [[40, 560], [40, 40], [520, 40]],
    "one_side": [[40, 40], [40, 560]],  # a broken rim: one straight side left
}


@pytest.mark.parametrize("rim_shape", list(_RIMS))
def test_plate_with_rim_label_and_edge_gives_one_root_per_seedling(rim_shape):
    # Three seedlings on a "plate": a rim around them (whole or broken), a thick
    # handwritten-like label scribble at the bottom, a lighting step edge, and speckles.
    # Exactly three plants come back, left to right.
    H, W = 600, 560
    seedlings = [_seedling(s, x0=x, y0=80, length=330, n_lat=2) for s, x in zip((1, 2, 3), (140, 280, 420))]
    rim = np.array(_RIMS[rim_shape], float)
    rim = np.concatenate([np.linspace(p, q, 200) for p, q in zip(rim[:-1], rim[1:])])
    label = np.array([[200 + 8 * k, 520 + 10 * (k % 2)] for k in range(12)], float)
    polys = [p for m, ls in seedlings for p in (m, *ls)]
    img = _draw([*polys, rim], shape=(H, W), width=2.5, contrast=0.12, noise=0.03, seed=2)
    _, lab_mask = render_root_image([label], shape=(H, W), width=6, noise=0.0)
    img[lab_mask] = 0.3
    img[:, :20] -= 0.25  # a step edge along the left border (the sheet behind the plate)
    rng = np.random.default_rng(0)
    for r0, c0 in rng.integers(60, 500, size=(15, 2)):
        img[r0 : r0 + 3, c0 : c0 + 3] = 0.35
    roots = roots_from_image(np.clip(img, 0, 1))
    assert len(roots) == 3
    xs = [r.metadata["base_xy"][0] for r in roots]
    assert xs == sorted(xs)
    for r, (main, lats) in zip(roots, seedlings):
        assert abs(r.metadata["base_xy"][0] - main[0, 0]) < 15
        assert r.main_length == pytest.approx(polyline_length(main), rel=0.06)
        assert r.n_laterals == len(lats)


def test_pixels_per_mm():
    main, lats = _seedling(7, x0=150)
    img = _draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.03)
    (px,) = roots_from_image(img)
    (mm,) = roots_from_image(img, pixels_per_mm=10.0)
    np.testing.assert_allclose(mm.main, px.main / 10.0, rtol=1e-12)
    assert mm.metadata["unit"] == "mm" and mm.metadata["resolution"] == pytest.approx(10.0)
    with pytest.raises(ValueError, match="pixels_per_mm"):
        roots_from_image(img, pixels_per_mm=-1.0)


# ------------------------------------------------------------------------------------------
# Bad input (issue 18 item 7 and issue 19): ImageError naming the problem, or no root.


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_noise_gives_image_error(seed):
    rng = np.random.default_rng(seed)
    for img in (rng.random((300, 300)), (rng.random((200, 240, 3)) * 255).astype(np.uint8)):
        with pytest.raises(ImageError, match="no root"):
            roots_from_image(img)


def test_smoothed_noise_gives_image_error_or_nothing_rootlike():
    # Agar-like texture (noise smoothed at several scales): either an ImageError, or whatever
    # comes back is not a long root (never longer than a tenth of the image).
    import scipy.ndimage as ndi

    rng = np.random.default_rng(0)
    for sigma in (1.0, 2.0, 4.0):
        img = 0.6 + ndi.gaussian_filter(rng.standard_normal((300, 300)), sigma) * 0.05
        try:
            roots = roots_from_image(img)
        except ImageError:
            continue
        assert all(r.main_length < 30 for r in roots)


def test_blank_truncated_and_unsupported_files(tmp_path):
    import skimage.io

    with pytest.raises(ImageError, match="uniform"):
        roots_from_image(np.full((80, 80, 3), 200, np.uint8))
    good = tmp_path / "good.jpg"
    main, lats = _seedling(0, x0=150)
    skimage.io.imsave(
        good, (_draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.03) * 255).astype(np.uint8)
    )
    data = good.read_bytes()
    bad = tmp_path / "truncated.jpg"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(ImageError, match="truncated.jpg"):
        roots_from_image(bad)
    txt = tmp_path / "notes.png"
    txt.write_text("not an image")
    with pytest.raises(ImageError, match="notes.png"):
        roots_from_image(txt)
    with pytest.raises(ImageError, match="shape"):
        roots_from_image(np.zeros((50, 50, 2)))  # two-channel: unsupported mode
    with pytest.raises(ImageError, match="numbers"):
        roots_from_image(np.zeros((50, 50), complex))


# ------------------------------------------------------------------------------------------
# compare_to_tracing


def _root(x0, n_lat=2, scale=1.0):
    main, lats = _seedling(int(x0), x0=x0, n_lat=n_lat)
    attach = np.linspace(0.2, 0.6, n_lat)
    return Root(main=main * scale, laterals=tuple(l * scale for l in lats), attach=attach)


def test_compare_identical_matches_and_scores_one():
    traced = [_root(100), _root(300, 3), _root(500)]
    cmp = compare_to_tracing(list(reversed(traced)), traced)
    assert [(p.extracted, p.traced) for p in cmp.plants] == [(2, 0), (1, 1), (0, 2)]
    for p in cmp.plants:
        assert p.main_length_ratio == pytest.approx(1.0) and p.total_length_ratio == pytest.approx(1.0)
        assert p.laterals_extracted == p.laterals_traced
        assert p.elastic_distance == pytest.approx(0.0, abs=1e-3)
    assert cmp.total_length_ratio == pytest.approx(1.0)
    assert cmp.recall == cmp.precision == 1.0


def test_compare_coverage_against_bruteforce():
    # recall / precision against a double loop over the sampled points.
    from rootshape_jax.io._compare import sample_branches

    traced = [_root(100), _root(300)]
    ex = [Root(main=traced[0].main + [5.0, 0.0], laterals=traced[0].laterals[:1], attach=traced[0].attach[:1])]
    cmp = compare_to_tracing(ex, traced, elastic=False, tolerance=8.0)
    pe, pt = sample_branches(ex, 2.0), sample_branches(traced, 2.0)
    d = np.sqrt(((pt[:, None, :] - pe[None, :, :]) ** 2).sum(-1))
    assert cmp.recall == pytest.approx(np.mean(d.min(axis=1) <= 8.0))
    assert cmp.precision == pytest.approx(np.mean(d.min(axis=0) <= 8.0))
    assert 0.2 < cmp.recall < 0.6 and cmp.precision > 0.9


def test_compare_ratios_unmatched_and_distance_grows():
    traced = [_root(100), _root(300)]
    ex0 = traced[0]
    # Drop one lateral of the first plant: total-length ratio as computed by hand.
    ex1 = Root(main=ex0.main, laterals=ex0.laterals[:1], attach=ex0.attach[:1])
    far = _root(900)
    cmp = compare_to_tracing([ex1, far], traced)
    assert len(cmp.plants) == 1 and cmp.unmatched_extracted == (1,) and cmp.unmatched_traced == (1,)
    (p,) = cmp.plants
    want = (polyline_length(ex0.main) + polyline_length(ex0.laterals[0])) / total_length(ex0)
    assert p.total_length_ratio == pytest.approx(want)
    assert p.laterals_extracted == 1 and p.laterals_traced == 2
    assert p.elastic_distance > 0.05
    assert cmp.n_extracted == 2 and cmp.n_traced == 2


# ------------------------------------------------------------------------------------------
# extract_images (the `rootshape extract` command's logic)


def test_run_extract_writes_rsml_and_overlay_and_skips_bad(tmp_path):
    import skimage.io

    from rootshape_jax.io import write_rsml

    src = tmp_path / "photos"
    src.mkdir()
    mains = {}
    for k, x0 in enumerate((120, 180)):
        main, lats = _seedling(k, x0=x0)
        img = _draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.03, seed=k)
        skimage.io.imsave(src / f"p{k}.png", (img * 255).astype(np.uint8))
        mains[f"p{k}"] = (main, lats)
    (src / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    (src / "blank.png").write_bytes(b"")
    skimage.io.imsave(src / "blank.png", np.full((50, 50), 128, np.uint8), check_contrast=False)
    tr = tmp_path / "tracings"
    tr.mkdir()
    main, lats = mains["p0"]
    write_rsml([Root(main=main, laterals=tuple(lats), attach=np.linspace(0.2, 0.65, 3))], tr / "p0.rsml")
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = extract_images([src], out, tracing=tr, progress=False)
    by = {Path(r["image"]).stem: r for r in rows}
    assert by["p0"]["status"] == by["p1"]["status"] == "ok"
    assert by["broken"]["status"] == "skipped" and "broken.png" in by["broken"]["reason"]
    assert by["blank"]["status"] == "skipped" and "blank.png" in by["blank"]["reason"]
    msgs = " ".join(str(w.message) for w in caught)
    assert "broken.png" in msgs and "blank.png" in msgs
    for stem in ("p0", "p1"):
        assert (out / f"{stem}.rsml").is_file() and (out / f"{stem}_overlay.png").stat().st_size > 1000
        (r,) = read_rsml(out / f"{stem}.rsml")
        assert r.main_length == pytest.approx(polyline_length(mains[stem][0]), rel=0.05)
    comp = by["p0"]["comparison"]["plants"][0]
    assert comp["main_length_ratio"] == pytest.approx(1.0, abs=0.05)
    assert "comparison" not in by["p1"]
    # Strict JSON (no NaN): the elastic distance, not asked for, is null.
    import json

    summary = json.loads((out / "summary.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    (plant,) = [r for r in summary if Path(r["image"]).stem == "p0"][0]["comparison"]["plants"]
    assert plant["elastic_distance"] is None and plant["main_length_ratio"] == pytest.approx(1.0, abs=0.05)
    # The folder extract wrote reads as its RSML files: the overlays are left out, with a word.
    from rootshape_jax.io import read_folder

    with pytest.warns(UserWarning, match="left out 2 overlay image"):
        again = read_folder(out)
    assert len(again) == 2
    # pixels_per_mm: RSML in mm, overlay still in pixels.
    rows = extract_images([src / "p1.png"], tmp_path / "mm", pixels_per_mm=20.0, progress=False)
    (r,) = read_rsml(tmp_path / "mm" / "p1.rsml")
    assert r.metadata["unit"] == "mm"
    assert r.main_length == pytest.approx(polyline_length(mains["p1"][0]) / 20.0, rel=0.05)
    # pixel_size in a unit (as the other commands' --pixel-size): the same roots, in that unit.
    extract_images([src / "p1.png"], tmp_path / "cm", pixel_size=0.005, unit="cm", progress=False)
    (r_cm,) = read_rsml(tmp_path / "cm" / "p1.rsml")
    assert r_cm.metadata["unit"] == "cm"
    np.testing.assert_allclose(r_cm.main * 10.0, r.main, rtol=1e-6)
    # The overlay is drawn in pixels either way (the same lines, up to anti-aliasing of rounding).
    import skimage.io

    cm_png, mm_png = (skimage.io.imread(tmp_path / d / "p1_overlay.png").astype(float) for d in ("cm", "mm"))
    assert cm_png.shape == mm_png.shape and np.mean(np.abs(cm_png - mm_png)) < 0.01
    with pytest.raises(ValueError, match="not both"):
        extract_images([src / "p1.png"], tmp_path / "x", pixels_per_mm=20.0, pixel_size=0.05, progress=False)
    with pytest.raises(ValueError, match="unknown length unit 'furlong'"):
        extract_images([src / "p1.png"], tmp_path / "x", pixel_size=0.05, unit="furlong", progress=False)
    # A missing file is named and skipped like a bad one; an empty folder is an error.
    with pytest.warns(UserWarning, match="missing.png"):
        (row,) = extract_images([tmp_path / "missing.png"], tmp_path / "o2", progress=False)
    assert row["status"] == "skipped"
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no image files"):
        extract_images([tmp_path / "empty"], out, progress=False)


def test_bad_options_name_the_option():
    img = np.full((40, 40), 0.5)
    img[5:35, 20] = 0.1
    for kw, word in (
        (dict(sensitivity=(6.0, 2.0)), "sensitivity"),
        (dict(root_width=0), "root_width"),
        (dict(bridge_gaps=-1), "bridge_gaps"),
        (dict(spur_factor=float("nan")), "spur_factor"),
        (dict(min_plant_fraction=2.0), "min_plant_fraction"),
        (dict(pixels_per_mm=10.0, pixel_size=0.1, unit="mm"), "pixels_per_mm"),
    ):
        with pytest.raises(ValueError, match=word):
            roots_from_image(img, **kw)


def test_cli_extract_writes_rsml_overlay_and_names_a_bad_image(tmp_path):
    """`rootshape extract IMAGES --out DIR`: one RSML and overlay per good image, the bad one
    named on one line and skipped, exit 0."""
    import subprocess
    import sys

    import skimage.io

    src = tmp_path / "photos"
    src.mkdir()
    main, lats = _seedling(3, x0=150)
    img = _draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.03, seed=3)
    skimage.io.imsave(src / "good.png", (img * 255).astype(np.uint8))
    (src / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "rootshape_jax", "extract", str(src), "--out", str(out), "--quiet"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert len([ln for ln in proc.stderr.splitlines() if "broken.png" in ln]) == 1
    roots = read_rsml(out / "good.rsml")
    assert len(roots) == 1 and roots[0].n_laterals >= 2
    assert (out / "good_overlay.png").read_bytes()[:4] == b"\x89PNG"
    assert not (out / "broken.rsml").exists()
    # A second run into the same folder is refused (nothing rewritten), unless --overwrite.
    before = (out / "good.rsml").stat().st_mtime_ns
    cmd = [sys.executable, "-m", "rootshape_jax", "extract", str(src / "good.png"), "--out", str(out), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0 and "--overwrite" in proc.stderr and "Traceback" not in proc.stderr
    assert (out / "good.rsml").stat().st_mtime_ns == before
    proc = subprocess.run(cmd + ["--overwrite"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Hand tracings in the --out folder would be written over before being read: refused.
    proc = subprocess.run(cmd + ["--overwrite", "--tracing", str(out)], capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0 and "hand tracings are in --out" in proc.stderr and "Traceback" not in proc.stderr
    # --pixel-size with --unit, as in the other commands; clear errors for the wrong pairings.
    proc = subprocess.run(
        cmd + ["--overwrite", "--pixel-size", "0.1", "--unit", "cm"], capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    (cm,) = read_rsml(out / "good.rsml")
    assert cm.metadata["unit"] == "cm" and cm.main_length == pytest.approx(roots[0].main_length * 0.1, rel=1e-6)
    for extra, words in (
        (["--pixel-size", "0.1", "--pixels-per-mm", "10"], "not both"),
        (["--unit", "cm"], "give --pixel-size too"),
    ):
        proc = subprocess.run(cmd + ["--overwrite", *extra], capture_output=True, text=True, timeout=600)
        assert proc.returncode != 0 and words in proc.stderr and "Traceback" not in proc.stderr


def _photos_interrupted_at_the_last_overlay(tmp_path, monkeypatch, n=2):
    """A folder of `n` seedling photographs; `draw_overlay` writes part of the last overlay,
    then Ctrl-C (KeyboardInterrupt). Returns the folder."""
    import skimage.io

    from rootshape_jax.io import _extract_cli

    src = tmp_path / "photos"
    src.mkdir()
    for k, x0 in enumerate((120, 180, 150)[:n]):
        main, lats = _seedling(k, x0=x0)
        img = _draw([main, *lats], shape=(380, 300), width=3, contrast=0.3, noise=0.03, seed=k)
        skimage.io.imsave(src / f"p{k}.png", (img * 255).astype(np.uint8))
    draw = _extract_cli.draw_overlay
    calls = []

    def interrupted(image, roots, out_png, **kw):
        calls.append(out_png)
        if len(calls) == n:
            Path(out_png).write_bytes(b"\x89PNG half")  # part of the file, then Ctrl-C
            raise KeyboardInterrupt
        return draw(image, roots, out_png, **kw)

    monkeypatch.setattr(_extract_cli, "draw_overlay", interrupted)
    return src


def test_extract_interrupted_while_writing_leaves_no_half_written_file(tmp_path, monkeypatch):
    # Ctrl-C while the second image's overlay is being written: the first image's files are
    # complete, the second image's RSML and overlay are both absent (not half a PNG, not an
    # RSML without its overlay), no temporary file stays, and summary.json describes the one
    # finished image.
    import json

    import skimage.io

    src = _photos_interrupted_at_the_last_overlay(tmp_path, monkeypatch)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        extract_images([src], out, progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["p0.rsml", "p0_overlay.png", "summary.json"]
    assert skimage.io.imread(out / "p0_overlay.png").ndim == 3
    assert len(read_rsml(out / "p0.rsml")) == 1
    (row,) = json.loads((out / "summary.json").read_text())
    assert row["image"] == str(src / "p0.png") and row["status"] == "ok" and row["plants"] == 1


def test_an_interrupted_extract_brings_its_summary_up_to_the_images_finished(tmp_path, monkeypatch):
    # summary.json is rewritten at most every _SUMMARY_EVERY seconds: interrupted, it lagged
    # behind the images whose files were written (here: it listed p0 only, not p1).
    import json

    from rootshape_jax._atomic import last_words, run_last_words
    from rootshape_jax.io import _extract_cli

    monkeypatch.setattr(_extract_cli, "_SUMMARY_EVERY", 1e9)
    src = _photos_interrupted_at_the_last_overlay(tmp_path, monkeypatch, n=3)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        extract_images([src], out, progress=False)
    assert sorted(p.name for p in out.iterdir()) == [
        "p0.rsml",
        "p0_overlay.png",
        "p1.rsml",
        "p1_overlay.png",
        "summary.json",
    ]
    rows = json.loads((out / "summary.json").read_text())
    assert [Path(r["image"]).stem for r in rows] == ["p0", "p1"] and all(r["status"] == "ok" for r in rows)
    # The command line's Ctrl-C handler ends the process at once: it runs the last words
    # (once), then ends with 130.
    import signal

    from rootshape_jax._cli import _main

    said = []
    monkeypatch.setattr(_main, "_end_process", lambda code: said.append(code))
    monkeypatch.setattr(_main.signal, "signal", lambda *args: None)  # keep pytest's handler
    with last_words(lambda: said.append("summary")):
        _main._on_sigint(signal.SIGINT, None)
        run_last_words()  # nothing left to run
    assert said == ["summary", 130]


def test_extract_command_stopped_early_names_the_images_it_finished(tmp_path, monkeypatch, capsys):
    """From a tour: an interrupted `rootshape extract` printed no "stopped before its end" line
    (the other commands do), so the user did not know which images were done."""

    from rootshape_jax._cli._main import main
    from rootshape_jax._cli._report import OPENED

    src = _photos_interrupted_at_the_last_overlay(tmp_path, monkeypatch)
    out = tmp_path / "out"
    code = main(["extract", str(src), "--out", str(out), "--quiet"])
    OPENED.clear()
    err = capsys.readouterr().err
    assert code == 130 and "interrupted" in err
    assert "stopped before its end" in err and "p0.rsml" in err and "p0_overlay.png" in err and "p1" not in err
    assert sorted(p.name for p in out.iterdir()) == ["p0.rsml", "p0_overlay.png", "summary.json"]


def test_a_results_folder_read_again_leaves_rootshape_figures_out(tmp_path):
    """From a tour: `rootshape traits out/` on a `rootshape sample` folder read mean.png,
    modes.png and random_roots.png as photographs: 24 of 37 rows were roots 'found' in figures."""
    import shutil

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import skimage.io

    from rootshape_jax.io import read_folder, root_files
    from rootshape_jax.io._folder import FIGURE_SOFTWARE

    main = np.stack([np.full(200, 60.0), np.linspace(20, 220, 200)], 1)
    img, _ = render_root_image([main], shape=(240, 120), seed=3)
    folder = tmp_path / "mixed"
    folder.mkdir()
    skimage.io.imsave(folder / "photo.png", (img * 255).astype(np.uint8), check_contrast=False)
    fig = plt.figure()
    fig.add_subplot().plot([0, 1], [0, 1])
    fig.savefig(folder / "modes.png", metadata={"Software": FIGURE_SOFTWARE})
    plt.close(fig)
    assert [p.name for p in root_files(folder)] == ["photo.png"]
    with pytest.warns(UserWarning, match=r"left out 1 figure\(s\) that rootshape drew \(modes.png\)"):
        roots = read_folder(folder)
    assert len(roots) == 1
    # A folder with the command line's log is a results folder: its PNGs are figures, also
    # those written before the figures were marked.
    results = tmp_path / "results"
    shutil.copytree(folder, results)
    (results / "rootshape.log").write_text("log")
    assert root_files(results) == []
