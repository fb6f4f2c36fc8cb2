"""Root systems from a scanned image or photograph: ridge filter (or threshold) → clean →
skeleton → spur pruning (skan) → gap bridging → plants → graph → longest paths.

Coordinates: the image is indexed ``(row, col)``; every returned `Root` is in ``(x, y)`` with
``x = col`` and ``y = row`` — so **y points down**, as in the image (a root growing down the
plate has increasing y). This is the one place where ``(row, col)`` becomes ``(x, y)``.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.sparse import csgraph

from .._errors import ImageError, as_flag
from .._root import Root, project_onto_polyline
from .._units import PIXEL_UNITS
from ._units import check_length_unit

_METHODS = ("otsu", "li", "triangle", "yen", "isodata", "mean")


# --------------------------------------------------------------------------------------------
# Image → binary mask.


def load_image(image: Any) -> tuple[np.ndarray, str]:
    """``(pixels, stem)`` of an image file (or ``(array, "image")`` for an array); `ImageError`
    naming the file when it cannot be read as an image."""
    if isinstance(image, (str, os.PathLike)):
        p = Path(image)
        if not p.is_file():
            raise FileNotFoundError(f"image file not found: {p}")
        import imageio.v3 as iio

        # Opened here and handed over with the suffix as the format hint: given a path, imageio
        # left the file of an image it could not read open (closed only by a later garbage
        # collection, with a ResourceWarning wherever that happens to run).
        try:
            with open(p, "rb") as f:
                arr = iio.imread(f, extension=p.suffix.lower() or None)
        except Exception as e:  # the reader's own errors vary by plugin
            # imageio's message for a file that is not an image of its kind suggests plugins
            # to install (pyav, opencv): no plugin opens a broken or mislabelled file.
            why = str(e).split("\n")[0].strip()
            if "backend" in why.lower() or not why:
                why = f"its content is not a {p.suffix.lstrip('.').upper() or 'known'} image: broken, empty or misnamed"
            raise ImageError(f"{p}: cannot be read as an image ({why}).") from e
        arr = np.asarray(arr)
        if arr.ndim == 3 and arr.shape[-1] not in (3, 4) and arr.shape[0] in (3, 4):
            arr = np.moveaxis(arr, 0, -1)  # a TIFF of separate colour planes, (3|4, H, W)
        return arr, p.stem
    return np.asarray(image), "image"


def _to_gray(arr: np.ndarray, source: str) -> np.ndarray:
    """Float grayscale (integer images scaled to [0, 1]); bool images stay bool."""
    if arr.dtype == bool:
        if arr.ndim != 2:
            raise ImageError(f"{source}: a binary image must be 2D, got shape {arr.shape}.")
        return arr
    if arr.dtype.kind not in "fiu":
        raise ImageError(f"{source}: pixels must be numbers, got dtype {arr.dtype}.")
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        from skimage.color import rgb2gray
        from skimage.util import img_as_float

        arr = rgb2gray(img_as_float(arr[..., :3]))
    elif arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise ImageError(
            f"{source}: expected a 2D grayscale/binary image or an (H, W, 3|4) colour image, got shape {arr.shape}."
        )
    if min(arr.shape) < 3:
        raise ImageError(f"{source}: image of shape {arr.shape} is too small.")
    if arr.dtype.kind in "iu":
        from skimage.util import img_as_float

        arr = img_as_float(arr)
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ImageError(f"{source}: image contains NaN or inf pixels.")
    return arr


def _threshold(gray: np.ndarray, threshold: Any, source: str) -> float:
    if threshold is None:
        threshold = "otsu"
    if isinstance(threshold, str):
        method = threshold.lower()
        if method not in _METHODS:
            raise ValueError(f"threshold must be a number or one of {_METHODS}, got {threshold!r}.")
        import skimage.filters

        return float(getattr(skimage.filters, f"threshold_{method}")(gray))
    t = float(threshold)
    if not math.isfinite(t):
        raise ValueError(f"threshold must be finite, got {threshold!r}.")
    return t


def _banded(fn, mask: np.ndarray, size: int) -> np.ndarray:
    """Apply a size filter in row bands with a margin of `size` rows.

    Exact for `_remove_small` and `_fill_small_holes`: a connected set that reaches from a
    band's interior to its padded edge spans at least `size` rows, so it has at least `size`
    pixels in the padded band and is kept (resp. not filled), as it would be on the full image.
    Saves the full-size int32 label image of large scans.
    """
    H = mask.shape[0]
    if H <= 2 * _BAND:
        return fn(mask, size)
    out = np.empty_like(mask)
    for r0 in range(0, H, _BAND):
        r1 = min(r0 + _BAND, H)
        p0, p1 = max(r0 - size - 1, 0), min(r1 + size + 1, H)
        out[r0:r1] = fn(mask[p0:p1], size)[r0 - p0 : r1 - p0]
    return out


def _remove_small(mask: np.ndarray, min_size: int) -> np.ndarray:
    if min_size <= 1:
        return mask
    lab, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return mask
    sizes = np.bincount(lab.ravel())
    keep = sizes >= min_size
    keep[0] = False
    return keep[lab]


def _fill_small_holes(mask: np.ndarray, max_size: int) -> np.ndarray:
    if max_size <= 0:
        return mask
    lab, n = ndi.label(~mask)  # 4-connected background
    if n == 0:
        return mask
    sizes = np.bincount(lab.ravel())
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    fill = sizes <= max_size
    fill[0] = False
    fill[border] = False
    return mask | fill[lab]


def _disk(radius: int) -> np.ndarray:
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return xx * xx + yy * yy <= radius * radius


def _close(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    padded = np.pad(mask, radius + 1)
    closed = ndi.binary_closing(padded, structure=_disk(radius))
    return closed[radius + 1 : -radius - 1, radius + 1 : -radius - 1]


# --------------------------------------------------------------------------------------------
# Ridge (line) filter: multi-scale Hessian, tiled so that large scans stay within memory.


def intensity_scale(arr: np.ndarray) -> float:
    """Factor that brings a colour image's values to [0, 1] for colour measures (CIELAB).

    Integer images are scaled by their bit depth, the smallest of 8, 10, 12, 14, 16, 24 or 32
    bits that holds their largest value (uint8 always by 255): a camera's 12-bit data stored in
    uint16 peaks at 4095, and read as 16-bit it would be nearly black, which the colour test
    for green shoots cannot see. Float images up to 2 are kept (values a little above 1 come
    from flat-field or colour correction; colour conversions clip them); float images of
    larger values (8- or 16-bit data converted to float) are scaled as integers are.
    Grayscale conversion and numeric thresholds do not use this: they scale integer images by
    their dtype, so a threshold means the same on every image of a batch.
    """
    if arr.dtype == np.uint8:
        return 1.0 / 255.0
    if arr.dtype.kind not in "fiu" or arr.size == 0:
        return 1.0
    top = float(np.max(arr))
    if arr.dtype.kind == "f" and top <= 2.0:
        return 1.0
    for bits in (8, 10, 12, 14, 16, 24, 32):
        if top <= 2.0**bits - 1:
            return 1.0 / (2.0**bits - 1)
    return 1.0 / top


_LUMA = np.array([0.2125, 0.7154, 0.0721], dtype=np.float32)
_BAND = 1024  # rows per tile of the ridge filter and the distance transform


def gray_float32(arr: np.ndarray, source: str) -> np.ndarray:
    """Luminance in [0, 1] as float32, converted in row bands (no full float64 copy)."""
    if arr.dtype.kind not in "fiu" or arr.dtype == bool:
        raise ImageError(f"{source}: pixels must be numbers, got dtype {arr.dtype}.")
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] in (3, 4))):
        raise ImageError(
            f"{source}: expected a 2D grayscale/binary image or an (H, W, 3|4) colour image, got shape {arr.shape}."
        )
    if min(arr.shape[:2]) < 3:
        raise ImageError(f"{source}: image of shape {arr.shape} is too small.")
    scale = 1.0
    if arr.dtype.kind in "iu":
        info = np.iinfo(arr.dtype)
        scale = 1.0 / float(info.max) if info.min == 0 else 1.0 / float(info.max - info.min)
    out = np.empty(arr.shape[:2], dtype=np.float32)
    for r0 in range(0, arr.shape[0], _BAND):
        block = arr[r0 : r0 + _BAND]
        if block.ndim == 3:
            block = block[..., :3].astype(np.float32) @ _LUMA
        out[r0 : r0 + _BAND] = block.astype(np.float32) * np.float32(scale)
    if not np.all(np.isfinite(out)):
        raise ImageError(f"{source}: image contains NaN or inf pixels.")
    return out


def _ridge_measures(g: np.ndarray, sigma: float, edge_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale-normalised line measures (bright lines, dark lines) of a float32 patch.

    With Hessian eigenvalues l1 >= l2, a bright line has l2 << 0 and l1 ~ 0; a dark line
    l1 >> 0 and l2 ~ 0. The measure ``-l2 - max(l1, 0)`` (resp. ``l1 + min(l2, 0)``) is
    Sato's: curvature of the other sign (a saddle, a line of the other polarity) is
    penalised, curvature of the same sign is not, so junctions, where a lateral meets its
    parent and both directions curve, are kept. A step
    edge also has a one-sided second derivative; at its peak the σ-scaled gradient equals the
    σ²-scaled curvature, so subtracting ``edge_weight · σ |∇g|`` suppresses edges (the rim of a
    paper sheet, a shadow) while the centre of a line, where the gradient vanishes, keeps its value.
    """
    f = lambda order: ndi.gaussian_filter(g, sigma, order=order, mode="nearest")  # noqa: E731
    hrr, hcc, hrc = f((2, 0)), f((0, 2)), f((1, 1))
    half_tr = 0.5 * (hrr + hcc)
    d = np.sqrt((0.5 * (hrr - hcc)) ** 2 + hrc**2)
    del hrr, hcc, hrc
    l1, l2 = half_tr + d, half_tr - d
    del half_tr, d
    s2 = np.float32(sigma * sigma)
    grad = np.float32(edge_weight * sigma) * np.hypot(f((1, 0)), f((0, 1)))
    bright = s2 * (-l2 - np.maximum(l1, 0)) - grad
    dark = s2 * (l1 + np.minimum(l2, 0)) - grad
    return bright, dark


def _robust_stats(x: np.ndarray) -> tuple[float, float]:
    med = float(np.median(x))
    mad = 1.4826 * float(np.median(np.abs(x - med)))
    return med, max(mad, 1e-12)


def ridge_filter(
    gray: np.ndarray, sigmas: Sequence[float], *, edge_weight: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Line strength of bright and of dark lines, in units of the background's noise.

    Returns ``(bright, dark)`` float16 maps: the maximum over `sigmas` of the standardised
    line measure (see `_ridge_measures`). Scales up to 3 px are computed on the image itself;
    larger ones on a block-averaged copy (by 2 for σ up to 6, by 4 up to 12, ...), where they
    are 1.5–3 px again, and the result is repeated back to full size: wide roots cost no more
    than thin ones.
    """
    groups: dict[int, list[float]] = {}
    for s in sigmas:
        f = 1
        while s / f > 3.0 + 1e-9:
            f *= 2
        groups.setdefault(f, []).append(float(s) / f)
    H, W = gray.shape
    bright = dark = None
    for f in sorted(groups):
        if f == 1:
            zb, zd = _ridge_filter_direct(gray, groups[f], edge_weight=edge_weight)
        else:
            if min(H, W) // f < 8:
                continue
            small = _block_mean(gray, f)
            zb, zd = _ridge_filter_direct(small, groups[f], edge_weight=edge_weight)
            del small
            zb, zd = _repeat_to(zb, f, (H, W)), _repeat_to(zd, f, (H, W))
        if bright is None:
            bright, dark = zb, zd
        else:
            np.maximum(bright, zb, out=bright)
            np.maximum(dark, zd, out=dark)
        del zb, zd
    return bright, dark


def _block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over f × f blocks (the last partial row/column of blocks uses its own pixels)."""
    H, W = a.shape
    Hf, Wf = -(-H // f), -(-W // f)
    out = np.zeros((Hf, Wf), dtype=np.float32)
    band = max(f, _BAND // f * f)  # whole blocks per band, for any f
    for r0 in range(0, H, band):  # in bands: no full-size float copy
        block = a[r0 : r0 + band]
        h = block.shape[0]
        padded = np.pad(block, ((0, (-h) % f), (0, (-W) % f)), mode="edge")
        out[r0 // f : r0 // f + padded.shape[0] // f] = padded.reshape(padded.shape[0] // f, f, Wf, f).mean(axis=(1, 3))
    return out


def _repeat_to(a: np.ndarray, f: int, shape: tuple[int, int]) -> np.ndarray:
    H, W = shape
    out = np.empty(shape, dtype=a.dtype)
    for r0 in range(0, H, _BAND):
        r1 = min(r0 + _BAND, H)
        rows = a[np.arange(r0, r1) // f]
        out[r0:r1] = np.repeat(rows, f, axis=1)[:, :W]
    return out


def _ridge_filter_direct(
    gray: np.ndarray, sigmas: Sequence[float], *, edge_weight: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """`ridge_filter` at the image's own resolution.

    For each scale the measure of `_ridge_measures` is standardised by its median and MAD over
    the image (estimated on up to 16 sample tiles), and the maximum over scales is kept, so a
    value of 5 means "5 noise standard deviations above the typical background". Computed in
    row bands with a margin of 4σ, so memory stays at a few float32 copies of the image.
    """
    H, W = gray.shape
    pad = int(math.ceil(4 * max(sigmas))) + 2
    # Noise statistics per scale from sample tiles (the whole image when small).
    tiles = []
    if H * W <= 1024 * 1024:
        tiles.append((slice(0, H), slice(0, W)))
    else:
        for fr in np.linspace(0, 1, 4):
            for fc in np.linspace(0, 1, 4):
                r = int(fr * max(H - 256, 0))
                c = int(fc * max(W - 256, 0))
                tiles.append((slice(r, r + 256), slice(c, c + 256)))
    stats = []
    for s in sigmas:
        b_all, d_all = [], []
        for rs, cs in tiles:
            r0, r1 = max(rs.start - pad, 0), min(rs.stop + pad, H)
            c0, c1 = max(cs.start - pad, 0), min(cs.stop + pad, W)
            b, d = _ridge_measures(gray[r0:r1, c0:c1], s, edge_weight)
            inner = (slice(rs.start - r0, rs.stop - r0), slice(cs.start - c0, cs.stop - c0))
            b_all.append(b[inner].ravel())
            d_all.append(d[inner].ravel())
        stats.append((_robust_stats(np.concatenate(b_all)), _robust_stats(np.concatenate(d_all))))
    # float16 output: z-scores compared with thresholds of a few units; halves the memory.
    bright = np.empty((H, W), dtype=np.float16)
    dark = np.empty((H, W), dtype=np.float16)
    for r0 in range(0, H, _BAND):
        r1 = min(r0 + _BAND, H)
        p0, p1 = max(r0 - pad, 0), min(r1 + pad, H)
        block = gray[p0:p1]
        zb = np.full((r1 - r0, W), -np.inf, dtype=np.float32)
        zd = np.full((r1 - r0, W), -np.inf, dtype=np.float32)
        for s, ((mb, sb), (md, sd)) in zip(sigmas, stats):
            b, d = _ridge_measures(block, s, edge_weight)
            np.maximum(zb, (b[r0 - p0 : r1 - p0] - mb) / np.float32(sb), out=zb)
            np.maximum(zd, (d[r0 - p0 : r1 - p0] - md) / np.float32(sd), out=zd)
        bright[r0:r1] = np.clip(zb, -6e4, 6e4)
        dark[r0:r1] = np.clip(zd, -6e4, 6e4)
    return bright, dark


def _hysteresis(z: np.ndarray, low: float, high: float) -> np.ndarray:
    """Pixels above `low` connected (8-neighbours) to a pixel above `high`."""
    lab, n = ndi.label(z > low, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(z.shape, bool)
    strong = np.zeros(n + 1, bool)
    strong[np.unique(lab[z > high])] = True
    strong[0] = False
    return strong[lab]


def halfwidth_map(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance to the background (float16), computed in row bands with a margin."""
    H = mask.shape[0]
    out = np.empty(mask.shape, dtype=np.float16)  # widths of a few px: float16 halves the memory
    margin = 64  # roots wider than 128 px would be under-measured near band edges only
    for r0 in range(0, H, _BAND):
        r1 = min(r0 + _BAND, H)
        p0, p1 = max(r0 - margin, 0), min(r1 + margin, H)
        out[r0:r1] = ndi.distance_transform_edt(mask[p0:p1])[r0 - p0 : r1 - p0]
    return out


# Yellow-green, about the hue of leaves and other chlorophyll-bearing tissue (CIELAB hue angle 120°).
_FOLIAGE = np.array([math.cos(math.radians(120.0)), math.sin(math.radians(120.0))], dtype=np.float32)


def shoot_mask(rgb: np.ndarray, *, green: float, root_width: float) -> np.ndarray | None:
    """Green shoot (cotyledons, hypocotyl, leaves) of a colour photograph, or None if there is none.

    Seedlings on a plate are photographed with their shoot above the root; the shoot is dark
    and elongated too, so the line filter keeps it and the main root would start at the tip
    of a cotyledon. Roots carry no chlorophyll: on agar they take the background's colour, on
    paper they are white. A pixel is shoot when it is green (CIELAB ``a* <= -green``) *and*
    at least `green` units further along the yellow-green foliage hue than its background:
    the first test spares white roots on blue paper (which are "greener" than the paper), the
    second spares roots on green-tinted agar (as green as the agar). The background is local,
    a median over about 36 root widths, because a plate's tint drifts across a photograph by
    more than the shoot's contrast. Green regions count only where they are wider than the
    widest root somewhere (a thin green line may be a root in the light; a leaf is a blob),
    and are grown by the ridge filter's largest scale, ``root_width / 2``, which is how far
    the filter's response to their dark outline reaches beyond them.
    """
    from skimage.color import rgb2lab

    H, W = rgb.shape[:2]
    scale = intensity_scale(rgb[..., :3])
    # Chroma along the foliage hue (float16: differences of a few units matter, not their
    # decimals), and which pixels are green at all; in row bands, so no full-size Lab copy.
    foliage = np.empty((H, W), dtype=np.float16)
    is_green = np.empty((H, W), dtype=bool)
    for r0 in range(0, H, _BAND):
        block = rgb[r0 : r0 + _BAND, :, :3].astype(np.float32) * np.float32(scale)
        lab = rgb2lab(np.clip(block, 0.0, 1.0, out=block))
        foliage[r0 : r0 + _BAND] = lab[..., 1] * _FOLIAGE[0] + lab[..., 2] * _FOLIAGE[1]
        is_green[r0 : r0 + _BAND] = lab[..., 1] <= -green
    # Local background: median of 4-root-width block means over 9 × 9 blocks.
    f = max(1, int(round(4 * root_width)))
    bg = ndi.median_filter(_block_mean(foliage, f), size=9, mode="nearest")
    for r0 in range(0, H, _BAND):
        r1 = min(r0 + _BAND, H)
        local = np.repeat(bg[np.arange(r0, r1) // f], f, axis=1)[:, :W]
        is_green[r0:r1] &= foliage[r0:r1] - local >= green
    del foliage
    if not is_green.any():
        return None
    rows, cols = np.nonzero(is_green.any(axis=1))[0], np.nonzero(is_green.any(axis=0))[0]
    grow = int(math.ceil(root_width / 2.0))
    r0, r1 = max(rows[0] - grow - 1, 0), min(rows[-1] + grow + 2, H)
    c0, c1 = max(cols[0] - grow - 1, 0), min(cols[-1] + grow + 2, W)
    crop = is_green[r0:r1, c0:c1]
    del is_green
    lab, n = ndi.label(crop, structure=np.ones((3, 3), bool))
    wide = np.zeros(n + 1, dtype=bool)
    wide[np.unique(lab[ndi.binary_erosion(crop, structure=_disk(grow))])] = True
    wide[0] = False
    if not wide.any():
        return None
    out = np.zeros((H, W), dtype=bool)
    out[r0:r1, c0:c1] = ndi.binary_dilation(wide[lab], structure=_disk(grow))
    return out


# --------------------------------------------------------------------------------------------
# Skeleton clean-up: spur pruning (skan) and gap bridging.


def prune_spurs(skel: np.ndarray, halfwidth: np.ndarray, *, factor: float, min_length: float) -> np.ndarray:
    """Remove end branches shorter than ``max(min_length, factor × local half-width)``.

    The skeleton graph comes from `skan`; an end branch (junction to tip, or an isolated
    segment) is a spur when it is short compared with the width of the root it sticks out of:
    skeletonising a thick root leaves such whiskers at bumps and junctions.
    """
    from skan.csr import Skeleton, summarize

    if not skel.any():
        return skel
    sk = Skeleton(skel)
    with warnings.catch_warnings():
        # skan's summarize calls DataFrame.rename(inplace=True), which pandas >= 3.1 deprecates
        # (Pandas4Warning, a DeprecationWarning; a FutureWarning should pandas promote it): on
        # every image, and skan's to fix, not the user's. Only that message from skan is hidden.
        for category in (DeprecationWarning, FutureWarning):
            warnings.filterwarnings("ignore", message="The inplace keyword", category=category, module=r"skan\.")
        df = summarize(sk, separator="_")
    src = df[["image_coord_src_0", "image_coord_src_1"]].to_numpy().astype(np.int64)
    dst = df[["image_coord_dst_0", "image_coord_dst_1"]].to_numpy().astype(np.int64)
    hw = np.maximum(halfwidth[src[:, 0], src[:, 1]], halfwidth[dst[:, 0], dst[:, 1]])
    limit = np.maximum(min_length, factor * hw)
    spur = (df["branch_type"].to_numpy() <= 1) & (df["branch_distance"].to_numpy() < limit)
    if not spur.any():
        return skel
    out = skel.copy()
    for i in np.nonzero(spur)[0]:
        ids = sk.path(int(i))
        ids = ids[sk.degrees[ids] <= 2]  # keep the junction pixels
        rc = np.round(sk.coordinates[ids]).astype(np.int64)
        out[rc[:, 0], rc[:, 1]] = False
    from skimage.morphology import skeletonize

    return skeletonize(out)


def bridge_skeleton_gaps(skel: np.ndarray, *, max_gap: float, direction_length: float) -> tuple[np.ndarray, int]:
    """Join skeleton pieces across small gaps: each tip reaches forward to another piece.

    For every tip (a pixel with one neighbour) the direction of its last `direction_length`
    pixels is extended; the nearest pixel of a *different* piece within `max_gap` px and within
    45° of that direction is joined by a straight line. Gaps are closed shortest first and only
    between pieces not yet connected (a spanning forest), so no loops are made.
    Returns (skeleton, number of bridges).
    """
    from scipy.spatial import cKDTree
    from skimage.draw import line

    if max_gap <= 0 or not skel.any():
        return skel, 0
    # Pieces and tips from the pixel graph (no full-size label image).
    pts, graph = skeleton_graph(skel)
    n, lab = csgraph.connected_components(graph, directed=False)
    if n < 2:
        return skel, 0
    degree = np.diff(graph.indptr)
    tree = cKDTree(pts)
    cand = []
    for t in np.nonzero(degree == 1)[0]:
        tip = pts[t]
        own = lab[t]
        near = np.asarray(tree.query_ball_point(tip, direction_length), dtype=np.int64)
        near = near[lab[near] == own]
        v = tip - pts[near].mean(axis=0)
        nv = float(np.hypot(*v))
        if nv < 1e-9:
            continue
        v = v / nv
        idx = np.asarray(tree.query_ball_point(tip, max_gap), dtype=np.int64)
        idx = idx[lab[idx] != own]
        if idx.size == 0:
            continue
        w = pts[idx] - tip
        dist = np.hypot(w[:, 0], w[:, 1])
        cos = (w @ v) / np.maximum(dist, 1e-9)
        ok = cos >= math.cos(math.radians(45))
        if not ok.any():
            continue
        k = int(np.argmin(np.where(ok, dist, np.inf)))
        cand.append((float(dist[k]), int(own), int(lab[idx[k]]), tuple(tip), tuple(pts[idx[k]])))
    parent = list(range(n + 1))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    out = skel.copy()
    made = 0
    for _, a, b, p, q in sorted(cand):
        ra, rb = find(a), find(b)
        if ra == rb:
            continue
        parent[ra] = rb
        rr, cc = line(p[0], p[1], q[0], q[1])
        out[rr, cc] = True
        made += 1
    return out, made


# --------------------------------------------------------------------------------------------
# Skeleton → graph → paths.

_OFFSETS = ((0, 1, 1.0), (1, -1, math.sqrt(2.0)), (1, 0, 1.0), (1, 1, math.sqrt(2.0)))


def skeleton_graph(skeleton: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
    """Pixels of a boolean skeleton and their full 8-adjacency graph.

    (`skan`'s pixel graph drops the diagonal edges of 2 × 2 blocks; the full graph keeps
    every 8-neighbour, so path lengths match a plain Dijkstra on the pixel grid. `skan` builds
    the branch graph used for spur pruning, `prune_spurs`.)

    Returns ``(rc, graph)``: ``rc`` the (n, 2) ``(row, col)`` of the skeleton pixels and
    ``graph`` a symmetric sparse (n, n) matrix with weight 1 between 4-neighbours and √2
    between diagonal neighbours.
    """
    rc = np.argwhere(skeleton)
    n = rc.shape[0]
    H, W = skeleton.shape
    # Neighbours by binary search in the sorted linear indices (argwhere is in raster order):
    # no full-size index image, which would cost 8 bytes per pixel of a large scan.
    lin = rc[:, 0].astype(np.int64) * W + rc[:, 1]
    rows, cols, vals = [], [], []
    for dr, dc, w in _OFFSETS:
        r2, c2 = rc[:, 0] + dr, rc[:, 1] + dc
        ok = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
        target = r2.astype(np.int64) * W + c2
        pos = np.minimum(np.searchsorted(lin, target), max(n - 1, 0))
        has = ok & (lin[pos] == target) if n else ok
        i = np.nonzero(has)[0]
        rows.append(i)
        cols.append(pos[has])
        vals.append(np.full(i.shape[0], w))
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    v = np.concatenate(vals)
    g = sp.coo_matrix((np.concatenate([v, v]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))
    return rc, g.tocsr()


def _path_to(pred: np.ndarray, target: int) -> np.ndarray:
    path = [target]
    while pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    return np.asarray(path[::-1], dtype=np.int64)


def _smooth(points: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along a path that keeps both end points fixed.

    The path is extended by point reflection about each end (``2 p0 − p_k``), so a straight
    end stays straight and the end points do not move.
    """
    n = points.shape[0]
    if sigma <= 0 or n < 3:
        return points
    pad = min(n - 1, int(math.ceil(4 * sigma)))
    head = 2 * points[0] - points[1 : pad + 1][::-1]
    tail = 2 * points[-1] - points[-pad - 1 : -1][::-1]
    ext = np.concatenate([head, points, tail])
    out = ndi.gaussian_filter1d(ext, sigma, axis=0, mode="nearest")[pad : pad + n]
    out[0], out[-1] = points[0], points[-1]
    return out


def _cumlen(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _at(points: np.ndarray, cum: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, cum, points[:, k]) for k in range(points.shape[1])])


def _resample(points: np.ndarray, spacing: float | None) -> np.ndarray:
    if spacing is None:
        return points
    cum = _cumlen(points)
    n = max(2, int(math.ceil(cum[-1] / spacing)) + 1)
    s = np.linspace(0.0, cum[-1], n)
    return np.stack([np.interp(s, cum, points[:, k]) for k in range(points.shape[1])], axis=1)


def _base_nodes(base: Any, rc: np.ndarray, comp: np.ndarray, eligible: np.ndarray, offset_xy):
    """[(component, base node)] for the base option (points given in full-image x, y)."""
    out = []
    if isinstance(base, str):
        key = base.lower()
        if key not in ("top", "bottom", "left", "right"):
            raise ValueError(f"base must be 'top', 'bottom', 'left', 'right' or (x, y) point(s), got {base!r}.")
        # primary: row or column; ties broken by the other coordinate's median distance.
        axis, sign = {"top": (0, 1), "bottom": (0, -1), "left": (1, 1), "right": (1, -1)}[key]
        for c in eligible:
            nodes = np.nonzero(comp == c)[0]
            primary = sign * rc[nodes, axis]
            cand = nodes[primary == primary.min()]
            other = rc[cand, 1 - axis]
            out.append((int(c), int(cand[np.argmin(np.abs(other - np.median(other)))])))
        return out
    pts = np.asarray(base, dtype=np.float64)
    if pts.ndim == 1:
        pts = pts[None, :]
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isfinite(pts)):
        raise ValueError(f"base points must be (x, y) or an (n, 2) array of them, got {base!r}.")
    ok = np.isin(comp, eligible)
    cand = np.nonzero(ok)[0]
    for x, y in pts - np.asarray(offset_xy, dtype=np.float64):
        d2 = (rc[cand, 1] - x) ** 2 + (rc[cand, 0] - y) ** 2
        node = int(cand[np.argmin(d2)])
        out.append((int(comp[node]), node))
    return out


def _contrast_to_background(gray: np.ndarray, pix: np.ndarray, sigma: float) -> np.ndarray:
    """gray − (Gaussian-smoothed gray) at the pixels `pix`, smoothing only their bounding box."""
    m = int(math.ceil(4 * sigma))
    r0, c0 = np.maximum(pix.min(axis=0) - m, 0)
    r1, c1 = np.minimum(pix.max(axis=0) + m + 1, gray.shape)
    crop = gray[r0:r1, c0:c1]
    bg = ndi.gaussian_filter(crop, sigma, mode="nearest")
    rr, cc = pix[:, 0] - r0, pix[:, 1] - c0
    return crop[rr, cc] - bg[rr, cc]


def _unwound_base(nodes, rc, sub, base_local, axis_sign, *, band: float, root_width: float) -> int:
    """The base of a piece's main root: the extreme node (`base_local`, the top row's middle
    for ``base="top"``) unless the path from it to the tip winds far out of its way.

    The extreme node can be the end of a lateral that reaches the paper's edge beside the main
    root, which the main root then ran along (a RootNav seedling's started 133 px aside and
    zigzagged through the laterals crossing under the edge). Of the nodes within `band` px of
    the extreme, take the one whose path to the tip (the node farthest from the extreme)
    exceeds the straight line to the tip least (of those within ``band / 4`` px of that least
    excess, the one nearest the base side), but only when this saves more than
    ``8 · root_width`` px over the extreme node's excess and the path between the two nodes
    leaves the band (goes down and comes back up). Two nodes on the same root near the extreme
    differ in excess by about their distance along it (a few px; the plate's seedlings saved at
    most 5 px); a main root that starts sideways along the band before turning down saves its
    sideways run, but its path to that corner stays in the band, so it keeps its own end.
    """
    dist, pred = csgraph.dijkstra(sub, directed=False, indices=base_local, return_predecessors=True)
    tip = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
    from_tip = csgraph.dijkstra(sub, directed=False, indices=tip)
    axis, sign = axis_sign
    pix = rc[nodes].astype(np.float64)
    depth = sign * pix[:, axis]
    near_side = np.flatnonzero(depth <= depth[base_local] + band)  # one component: all reach the tip
    excess = from_tip[near_side] - np.hypot(*(pix[near_side] - pix[tip]).T)
    own = from_tip[base_local] - np.hypot(*(pix[base_local] - pix[tip]))
    if own - excess.min() <= 8.0 * root_width:
        return base_local
    direct = excess <= excess.min() + band / 4
    best = int(near_side[direct][np.lexsort((excess[direct], depth[near_side[direct]]))[0]])
    winds = depth[_path_to(pred, best)].max() > depth[base_local] + band
    return best if winds else base_local


def _plant_checks(nodes, rc, sub, base_local, gray, halfwidth, axis_sign):
    """Measures used to tell a plant from clutter: main path, frame, edge and direction."""
    dist, pred = csgraph.dijkstra(sub, directed=False, indices=base_local, return_predecessors=True)
    tip = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
    length = float(dist[tip])
    pix = rc[nodes]
    axis, sign = axis_sign
    # Growth direction: roots photographed upright grow away from the base side (gravitropism),
    # so most of a main root heads that way (measured ≥ 92 % on the real photographs), while a
    # plate rim, a ruler or a label stroke runs sideways for much of its length. Directions over
    # 10-px chords so the pixel staircase does not matter.
    path = pix[_path_to(pred, tip)].astype(np.float64)
    k = min(10, len(path) - 1)
    if k >= 1:
        chord = path[k:] - path[:-k]
        clen = np.hypot(chord[:, 0], chord[:, 1])
        heading = float(np.sum(clen[sign * chord[:, axis] >= 0.5 * clen]) / max(float(np.sum(clen)), 1e-12))
    else:
        heading = 0.0
    # Frame: a closed outline (plate rim, tray edge) encloses most of its bounding box.
    r0, c0 = pix.min(axis=0)
    r1, c1 = pix.max(axis=0) + 1
    crop = np.zeros((r1 - r0, c1 - c0), bool)
    crop[pix[:, 0] - r0, pix[:, 1] - c0] = True
    enclosed = int(ndi.binary_fill_holes(crop).sum() - nodes.size)
    frame = enclosed > 0.5 * crop.size and crop.size > 400
    # Edge: a ridge found along a step edge has one side bright and one dark, so the ring
    # around it is bimodal (wide interquartile range) compared with the line's own contrast.
    # The ring is sampled around up to 2,000 skeleton pixels at 16 angles and two radii (memory
    # bounded for any size of piece), keeping samples farther than the root's width from it.
    from scipy.spatial import cKDTree

    hw = float(np.median(halfwidth[pix[:, 0], pix[:, 1]]))
    step = max(1, nodes.size // 2000)
    centres = pix[::step].astype(np.float64)
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    offs = np.concatenate([r * np.stack([np.sin(ang), np.cos(ang)], axis=1) for r in (2 * hw + 4, 3 * hw + 6)])
    samples = np.round((centres[:, None, :] + offs[None, :, :]).reshape(-1, 2)).astype(np.int64)
    H, W = gray.shape
    inside = (samples[:, 0] >= 0) & (samples[:, 0] < H) & (samples[:, 1] >= 0) & (samples[:, 1] < W)
    samples = samples[inside]
    if samples.size:
        far = cKDTree(pix).query(samples)[0] > hw + 2
        samples = samples[far]
    ring_v = gray[samples[:, 0], samples[:, 1]].astype(np.float64)
    line_v = gray[pix[::step, 0], pix[::step, 1]]
    q25, q50, q75 = np.percentile(ring_v, [25, 50, 75]) if ring_v.size else (0.0, 0.0, 0.0)
    contrast = abs(float(np.median(line_v)) - float(q50))
    edge = float(q75 - q25) > 1.0 * contrast
    # Border: the edge of a sheet, tray or scanner bed runs along the image border; a plant
    # is photographed inside the frame.
    margin = max(10.0, 0.05 * min(H, W))
    d_border = np.minimum(np.minimum(pix[:, 0], H - 1 - pix[:, 0]), np.minimum(pix[:, 1], W - 1 - pix[:, 1]))
    border = bool(np.mean(d_border < margin) > 0.5)
    # Open frame: the sides of a plate rim or tray (an L, a U) run along the piece's bounding
    # box, whereas a root system's main root crosses the inside of its box. Only for pieces
    # wide and tall compared with a root.
    bh, bw = r1 - r0, c1 - c0
    if min(bh, bw) >= 20 * max(hw, 1.0):
        tol = max(3.0 * hw + 3.0, 0.05 * min(bh, bw))
        d_box = np.minimum(
            np.minimum(pix[:, 0] - r0, r1 - 1 - pix[:, 0]), np.minimum(pix[:, 1] - c0, c1 - 1 - pix[:, 1])
        )
        frame = frame or bool(np.mean(d_box <= tol) >= 0.9)
    # Ruler-straight: an unbranched line of 300 px or more that never leaves its chord by
    # more than a couple of pixels is an edge of the set-up (a rim side, a ruler), not a grown
    # root (roots wave: the plate's seedlings and the paper-grown taproots leave their chords
    # by 5 px and more).
    if length >= 300 and len(path) >= 2:
        a, b = path[0], path[-1]
        u = (b - a) / max(float(np.hypot(*(b - a))), 1e-12)
        dev = np.abs((path[:, 0] - a[0]) * u[1] - (path[:, 1] - a[1]) * u[0])
        frame = frame or bool(dev.max() <= max(2.0, 0.004 * length) and nodes.size <= 1.2 * len(path))
    return dict(length=length, heading=heading, frame=frame, edge=edge, border=border, tip=tip, dist=dist, pred=pred)


def _shoot(arr: np.ndarray, green: float | None, root_width: float) -> np.ndarray | None:
    """`shoot_mask` of a colour image; None for grayscale (no colour cue) or when disabled."""
    if green is None or arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        return None
    return shoot_mask(arr, green=float(green), root_width=float(root_width))


def image_scale(pixels_per_mm: float | None, pixel_size: float | None, unit: str) -> tuple[float | None, str]:
    """``(pixel_size, unit)`` from either way of giving an image's scale (`pixels_per_mm`, or
    `pixel_size` in `unit`); `ValueError` naming a bad or doubled value."""
    if pixels_per_mm is not None:
        if pixel_size is not None:
            raise ValueError("give pixels_per_mm or pixel_size, not both.")
        if not (math.isfinite(pixels_per_mm) and pixels_per_mm > 0):
            raise ValueError(f"pixels_per_mm must be a positive number, got {pixels_per_mm!r}.")
        return 1.0 / float(pixels_per_mm), "mm"
    if pixel_size is not None and not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, got {pixel_size!r}.")
    if not isinstance(unit, str):
        raise TypeError(f"unit must be a string such as 'mm' or 'pixel', got {type(unit).__name__}.")
    is_pixel = unit.strip().lower() in PIXEL_UNITS
    if pixel_size is not None and is_pixel:
        raise ValueError("pixel_size given: pass the physical unit too, e.g. unit='mm'.")
    if pixel_size is None and not is_pixel:
        raise ValueError(
            f"unit={unit!r} without pixel_size: an image's coordinates are pixels until its scale is "
            f"given; pass pixel_size (the size of one pixel in {unit}) or pixels_per_mm, or leave unit out."
        )
    if pixel_size is not None:
        check_length_unit(unit)
    return pixel_size, unit


def roots_from_image(
    image: Any,
    *,
    threshold: float | str | None = None,
    invert: bool | None = None,
    base: str | Sequence[float] | np.ndarray = "top",
    roi: tuple[int, int, int, int] | None = None,
    background: float | None = None,
    root_width: float = 6.0,
    sensitivity: tuple[float, float] = (2.0, 6.0),
    close_gaps: int = 2,
    bridge_gaps: float | None = None,
    min_object_size: int = 64,
    max_hole_size: int = 16,
    min_root_length: float = 20.0,
    min_lateral_length: float = 10.0,
    spur_factor: float = 4.0,
    min_plant_fraction: float = 0.2,
    smooth: float = 2.0,
    spacing: float | None = 2.0,
    refine_junctions: bool = True,
    split_touching: bool = True,
    shoot_green: float | None = 6.0,
    pixels_per_mm: float | None = None,
    pixel_size: float | None = None,
    unit: str = "pixel",
) -> list[Root]:
    """Extract root systems (main root + first-order laterals) from a scanned image or photograph.

    **Arguments**

    - `image`: a path, or an array: 2D grayscale, 2D binary (bool, or two values), or
      (H, W, 3|4) colour (converted to luminance; alpha ignored). Integer images are scaled
      to [0, 1] by their dtype (a numeric `threshold` is in those units); the shoot's colour
      test finds the bit depth from the largest value (`intensity_scale`: 12-bit camera data
      in uint16 by 4095; float images of 0-255 values by 255).
    - `threshold`: None (default) segments with a multi-scale ridge (line) filter, which keeps
      thin faint laterals and ignores smooth lighting changes and edges. A number or one of
      ``"otsu"``, ``"li"``, ``"triangle"``, ``"yen"``, ``"isodata"``, ``"mean"`` instead uses
      a global threshold of the gray values (the old behaviour, for clean flat-bed scans of
      thick roots). Ignored for binary images.
    - `invert`: True if roots are darker than the background, False if brighter, None (default)
      to decide automatically (ridge mode: the polarity with more strong line pixels; threshold
      mode: roots are the minority class).
    - `base`: where each root starts: ``"top"`` (default; roots grow down from the top-most
      pixel of each plant, unless the path from it winds far out of the main root's way, e.g.
      a lateral reaching the top edge beside it: then the node within two root widths of the
      top that goes most directly to the tip), ``"bottom"``, ``"left"``, ``"right"``, or an
      ``(x, y)`` point / an
      ``(n, 2)`` array of points in image ``(x = col, y = row)`` coordinates — then one root per
      point, from the skeleton pixel nearest to it (no plant selection).
    - `roi`: ``(top, bottom, left, right)`` pixel bounds of the region to analyse; coordinates
      stay in the full image's frame.
    - `background`: threshold mode only: Gaussian sigma (px) of a background subtracted first.
    - `root_width`: widest root expected, in px (default 6, for seedlings photographed at
      2–12 megapixels); sets the ridge filter's scales (σ from 1 to ``root_width / 2``; scales
      above 3 run on a block-averaged image, so wide roots are cheap). Raise it for scans of
      thick roots: on the real photographs, scales beyond the roots' width pick up clutter.
    - `sensitivity`: ``(low, high)`` hysteresis thresholds of the ridge strength in noise
      standard deviations: a pixel is root if it is above `low` and connected to a pixel above
      `high`. Lower values keep fainter roots and more clutter.
    - `close_gaps`: radius (px) of a morphological closing of the mask; 0 disables.
    - `bridge_gaps`: largest gap (px) bridged between skeleton pieces along a tip's direction;
      None (default) is ``max(20, 4 × root_width)``; 0 disables.
    - `min_object_size`: connected foreground objects smaller than this (px) are removed.
    - `max_hole_size`: background holes up to this size (px) inside roots are filled.
    - `min_root_length`: roots whose main path is shorter (px) are dropped.
    - `min_lateral_length`: side branches shorter than this (px, measured from the edge of the
      main root) are ignored.
    - `spur_factor`: ridge mode: skeleton end branches shorter than the larger of
      ``spur_factor ×`` the local half-width and `min_lateral_length` are pruned before the
      graph is analysed (a threshold or a binary mask keeps its skeleton unpruned).
    - `min_plant_fraction`: with a string `base`, a piece is a plant only if its main root is at
      least this fraction of the longest plant's; together with the frame test (a closed outline
      such as a plate rim, or an open one whose pieces run along their bounding box, or a
      ruler-straight unbranched line), the edge test (a line along a step edge such as the border of a
      paper sheet), the border test (most of it within 5 % of the image border) and the
      direction test (at least 60 % of the main root heads away from the base side, within
      60°), this drops labels, rims and debris; a shorter piece close to a longer plant and
      mostly inside its bounding box is a broken-off part of it and is dropped too.
    - `smooth`: Gaussian sigma (in path pixels) that smooths the pixel staircase of each path.
    - `spacing`: resample every branch uniformly at this arc-length spacing (px); None keeps
      one point per skeleton pixel.
    - `refine_junctions`: extend each lateral's direction back to the main root to place its
      attachment (the skeleton junction of a thick lateral slides downstream).
    - `split_touching`: laterals that touch in the crown run as one line in the photograph and
      the skeleton holds their shared stretch once; True (default) makes every tip of a side
      subtree one lateral, routed along the skeleton back to the main root (so the shared
      stretch counts once per root), when its own part beyond the junction is longer than a
      junction whisker and a minimum lateral (``min_lateral_length + spur_factor ×`` the
      half-width at the junction). This assumes the side branches are first-order laterals
      (seedlings): a true second-order lateral becomes a lateral of the main root that repeats
      its parent's stretch. False keeps one lateral per attachment (its longest path) and drops
      the other tips.
    - `shoot_green`: colour images: a seedling's green shoot (cotyledons, hypocotyl) is dark
      and elongated like a root, so without this the main root starts at a cotyledon's tip.
      Pixels that are green (CIELAB ``a* <= -shoot_green``) and at least `shoot_green` CIELAB
      units further along the yellow-green hue than their local background, in regions wider
      than `root_width` somewhere, are shoot and are removed from the root mask (grown by
      ``root_width / 2``), so each main root starts where it leaves the shoot (see
      `shoot_mask`). Default 6: a clearly visible difference (about 2.5 just-noticeable
      differences, 5 standard deviations of a JPEG photograph's chroma noise). Higher values
      keep pale shoots; None keeps the shoot. Grayscale and binary images are unaffected.
    - `pixels_per_mm`: the image's scale; coordinates are then in mm. Or `pixel_size` with
      `unit` (e.g. ``pixel_size=0.05, unit="mm"``). Default: pixels.

    **Pipeline** (ridge mode): luminance → multi-scale Hessian line filter for both polarities
    (`ridge_filter`) → polarity → hysteresis → minus the green shoot (colour images,
    `shoot_mask`) → closing, hole filling, small-object removal →
    skeleton (scikit-image) → spur pruning on the `skan` skeleton graph → gap bridging →
    8-connected pixel graph (`skan`) → plants (connected pieces passing the tests above) →
    main root = longest shortest path from the base; every side subtree gives one lateral =
    its longest path from the main root, plus, with `split_touching`, one per further tip.

    **Returns** one `Root` per plant sorted by base position (x, then y) — or one per base
    point, in the points' order — in ``(x, y)`` coordinates with **x = column, y = row (y points
    down)**. ``metadata`` holds ``source``, ``unit``, ``threshold``, ``roots_dark``,
    ``base_xy``, ``component_pixels``, ``y_axis = "down"`` (and ``resolution`` = 1 / pixel_size).

    Raises `ImageError` (naming the file) when the image is unreadable, uniform, pure noise or
    contains no elongated structure.
    """
    if isinstance(base, str) and base.lower() not in ("top", "bottom", "left", "right"):
        raise ValueError(f"base must be 'top', 'bottom', 'left', 'right' or (x, y) point(s), got {base!r}.")
    pixel_size, unit = image_scale(pixels_per_mm, pixel_size, unit)
    arr, stem = load_image(image)
    source = str(image) if isinstance(image, (str, os.PathLike)) else "array"
    if arr.size == 0:
        raise ImageError(f"{source}: the image is empty (shape {arr.shape}).")
    for opt, val in (
        ("close_gaps", close_gaps),
        ("min_object_size", min_object_size),
        ("max_hole_size", max_hole_size),
    ):
        if int(val) != val or val < 0:
            raise ValueError(f"{opt} must be a non-negative integer, got {val!r}.")
    if not (root_width > 0):
        raise ValueError(f"root_width must be a positive number of pixels, got {root_width!r}.")
    try:
        low, high = (float(v) for v in sensitivity)
    except (TypeError, ValueError):
        low = high = math.nan
    if not (0 < low <= high):
        raise ValueError(f"sensitivity must be (low, high) with 0 < low <= high, got {sensitivity!r}.")
    if isinstance(smooth, bool) or not isinstance(smooth, numbers.Real) or not 0 <= smooth < math.inf:
        raise ValueError(f"smooth must be a non-negative number of pixels (0: no smoothing), got {smooth!r}.")
    if spacing is not None and (
        isinstance(spacing, bool) or not isinstance(spacing, numbers.Real) or not 0 < spacing < math.inf
    ):
        raise ValueError(
            f"spacing must be a positive arc length in pixels, or None to keep every skeleton pixel; got {spacing!r}."
        )
    if roi is not None and (isinstance(roi, (str, bytes)) or np.size(roi) != 4):
        raise ValueError(f"roi must be (top, bottom, left, right) in pixels, got {roi!r}.")
    if invert is not None:
        as_flag(invert, "invert")
    as_flag(refine_junctions, "refine_junctions")
    as_flag(split_touching, "split_touching")
    if bridge_gaps is None:
        bridge_gaps = max(20.0, 4.0 * float(root_width))
    for opt, val in (("bridge_gaps", bridge_gaps), ("spur_factor", spur_factor)):
        if not (math.isfinite(val) and val >= 0):
            raise ValueError(f"{opt} must be a non-negative number, got {val!r}.")
    if not (0.0 <= min_plant_fraction <= 1.0):
        raise ValueError(f"min_plant_fraction must lie in [0, 1], got {min_plant_fraction!r}.")
    if shoot_green is not None and (
        isinstance(shoot_green, bool) or not isinstance(shoot_green, numbers.Real) or not 0 < shoot_green < math.inf
    ):
        raise ValueError(f"shoot_green must be a positive number (CIELAB units) or None, got {shoot_green!r}.")

    r0 = c0 = 0
    if roi is not None:  # crop first: a photograph's full-size float copy is large
        if arr.ndim not in (2, 3):
            raise ImageError(f"{source}: expected a 2D or colour image, got shape {arr.shape}.")
        top, bottom, left, right = (int(v) for v in roi)
        H, W = arr.shape[:2]
        top, left = max(top, 0), max(left, 0)
        bottom, right = min(bottom, H), min(right, W)
        if bottom - top < 3 or right - left < 3:
            raise ImageError(f"{source}: roi {roi} leaves no usable region of the {H}x{W} image.")
        arr = arr[top:bottom, left:right]
        r0, c0 = top, left

    # Binary input (bool, or only two grey values): no thresholding.
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise ImageError(f"{source}: image contains NaN or inf pixels.")
    is_binary = arr.dtype == bool
    if not is_binary and arr.ndim == 2 and arr.dtype.kind in "fiu":
        step = max(1, arr.shape[0] // 256)
        is_binary = np.unique(arr[::step]).size <= 2 and np.unique(arr).size <= 2
    if is_binary:
        if arr.ndim != 2:
            raise ImageError(f"{source}: a binary image must be 2D, got shape {arr.shape}.")
        if min(arr.shape) < 3:
            raise ImageError(f"{source}: image of shape {arr.shape} is too small.")
        values = np.unique(arr)
        if values.size < 2:
            raise ImageError(f"{source}: the image is uniform (single value); it contains no root.")
        bright = arr > values[0]
        t: float | str = float(values[0])
        roots_dark = bool(bright.mean() > 0.5) if invert is None else bool(invert)
        mask = ~bright if roots_dark else bright
        gray = (~mask).astype(np.float32)  # for the plant tests: roots 0 on background 1
        del bright
    elif threshold is not None:
        gray64 = _to_gray(arr, source)
        gray = gray64.astype(np.float32)
        if background is not None:
            if not (background > 0):
                raise ValueError(f"background must be a positive Gaussian sigma (px), got {background!r}.")
            gray64 = gray64 - ndi.gaussian_filter(gray64, float(background), mode="nearest")
        if float(gray64.max() - gray64.min()) <= 1e-12 * max(1.0, float(np.abs(gray64).max())):
            raise ImageError(f"{source}: the image is uniform; it contains no root.")
        t = _threshold(gray64, threshold, source)
        bright = gray64 > t
        del gray64
        roots_dark = bool(bright.mean() > 0.5) if invert is None else bool(invert)
        mask = ~bright if roots_dark else bright
        del bright
        shoot = _shoot(arr, shoot_green, root_width)
        if shoot is not None:
            mask &= ~shoot
    else:
        gray = gray_float32(arr, source)
        if float(gray.max() - gray.min()) <= 1e-6:
            raise ImageError(f"{source}: the image is uniform; it contains no root.")
        shoot = _shoot(arr, shoot_green, root_width)
        del arr
        sigmas = _ridge_sigmas(root_width)
        z_bright, z_dark = ridge_filter(gray, sigmas)
        masks = {True: _hysteresis(z_dark, low, high)}
        del z_dark
        masks[False] = _hysteresis(z_bright, low, high)
        del z_bright
        if shoot is not None:
            for m in masks.values():
                m &= ~shoot
        t = "ridge"

    opts = dict(
        close_gaps=int(close_gaps),
        max_hole_size=int(max_hole_size),
        min_object_size=int(min_object_size),
        spur_factor=float(spur_factor),
        min_lateral_length=float(min_lateral_length),
        bridge_gaps=float(bridge_gaps),
        root_width=float(root_width),
        min_root_length=float(min_root_length),
        min_plant_fraction=float(min_plant_fraction),
        base=base,
        offset=(c0, r0),
    )
    if t == "ridge":
        # Polarity: when not given, trace both and keep the one whose accepted plants carry
        # more contrast: the sum over their skeleton pixels of how much darker (or brighter)
        # than the local background they are. Counting line pixels alone does not decide it: a
        # dark root has bright flanks on both sides, and rims and labels have both polarities.
        choices = [bool(invert)] if invert is not None else [True, False]
        best = None
        for dark in choices:
            traced = _trace(masks.pop(dark), gray, **opts)
            score = 0.0
            if len(choices) > 1:
                for cand in traced[0]:
                    diff = _contrast_to_background(gray, traced[1][cand[0]], 2.0 * float(root_width))
                    score += float(np.sum(-diff if dark else diff))
            if best is None or score > best[0]:
                best = (score, dark, traced)
            del traced
        _, roots_dark, (candidates, rc, halfwidth, why) = best
    else:
        # A global threshold or a given binary mask keeps its skeleton as it is (the
        # behaviour before the ridge filter): no spur pruning.
        candidates, rc, halfwidth, why = _trace(mask, gray, **{**opts, "spur_factor": None})
        del mask
    if not candidates:
        raise ImageError(_no_root_message(source, threshold, t, roots_dark, why))

    scale = 1.0 if pixel_size is None else float(pixel_size)
    results = []
    for nodes, sub, _b, base_node, pred, tip, _ in candidates:
        main_idx = _path_to(pred, tip)
        lat_paths = _lateral_paths(
            sub,
            main_idx,
            halfwidth,
            rc[nodes],
            min_lateral_length,
            split_factor=float(spur_factor) if split_touching else None,
        )
        xy = rc[nodes][:, ::-1].astype(np.float64) + np.array([c0, r0], dtype=np.float64)
        main_s = _smooth(xy[main_idx], smooth)
        cum = _cumlen(main_s)
        main_out = _resample(main_s, spacing)
        cum_out = _cumlen(main_out)
        pos_on_main = {int(g): k for k, g in enumerate(main_idx)}
        lats, attach = [], []
        for path in lat_paths:
            k = pos_on_main[int(path[0])]
            lat = _smooth(xy[path], smooth)
            s_attach = cum[k]
            if refine_junctions:
                jr, jc = rc[nodes[path[0]]]
                s_attach, lat = _refine_junction(main_s, cum, k, lat, float(halfwidth[jr, jc]))
            p_attach = _at(main_s, cum, s_attach)
            frac = project_onto_polyline(main_out, p_attach)
            start = _at(main_out, cum_out, frac * cum_out[-1])
            lat[0] = start
            lat = _resample(lat, spacing)
            lat[0] = start
            lats.append(lat)
            attach.append(frac)
        order = np.argsort(attach, kind="stable")
        by, bx = rc[base_node]
        meta = {
            "source": source,
            "unit": "pixel" if pixel_size is None else unit,
            "threshold": t,
            "roots_dark": roots_dark,
            "base_xy": (float(bx + c0), float(by + r0)),
            "component_pixels": int(nodes.size),
            "y_axis": "down",
        }
        if pixel_size is not None:
            meta["resolution"] = 1.0 / float(pixel_size)
        results.append(
            (
                (float(bx + c0), float(by + r0)),
                dict(
                    main=main_out * scale,
                    laterals=tuple(lats[i] * scale for i in order),
                    attach=np.asarray(attach, dtype=np.float64)[order],
                    metadata=meta,
                ),
            )
        )
    if isinstance(base, str):  # base points keep the caller's order
        results.sort(key=lambda item: item[0])
    return [Root(name=f"{stem}/{k + 1}", **kw) for k, (_, kw) in enumerate(results)]


def _trace(
    mask,
    gray,
    *,
    close_gaps,
    max_hole_size,
    min_object_size,
    spur_factor,
    min_lateral_length,
    bridge_gaps,
    root_width,
    min_root_length,
    min_plant_fraction,
    base,
    offset,
):
    """Mask → cleaned skeleton → graph → accepted plants.

    Returns (candidates, rc, halfwidth, why): candidates are (nodes, subgraph, base index,
    base node, predecessors, tip, main length); `why` says what was missing when none is found.
    """
    from skimage.morphology import skeletonize

    c0, r0 = offset
    mask = _close(mask, int(close_gaps))
    mask = _banded(_fill_small_holes, mask, int(max_hole_size))
    mask = _banded(_remove_small, mask, int(min_object_size))
    if not mask.any():
        return [], None, None, "after segmentation and removing small objects the mask is empty"
    halfwidth = halfwidth_map(mask)
    skel = skeletonize(mask)
    del mask
    if spur_factor is not None:
        skel = prune_spurs(skel, halfwidth, factor=float(spur_factor), min_length=float(min_lateral_length))
    skel, _ = bridge_skeleton_gaps(skel, max_gap=float(bridge_gaps), direction_length=max(6.0, 2.0 * float(root_width)))
    rc, graph = skeleton_graph(skel)
    del skel
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    sizes = np.bincount(comp, minlength=n_comp)
    # A path of length L has at least L / sqrt(2) + 1 pixels.
    eligible = np.nonzero(sizes >= max(2, min_root_length / math.sqrt(2.0)))[0]
    if eligible.size == 0:
        return [], rc, halfwidth, f"no skeleton reaches min_root_length={min_root_length} px"

    auto_base = isinstance(base, str)
    axis_sign = (
        {"top": (0, 1), "bottom": (0, -1), "left": (1, 1), "right": (1, -1)}[base.lower()] if auto_base else None
    )
    candidates = []
    for c, base_node in _base_nodes(base, rc, comp, eligible, (c0, r0)):
        nodes = np.nonzero(comp == c)[0]
        sub = graph[nodes][:, nodes]
        local = {int(g): k for k, g in enumerate(nodes)}
        b = local[base_node]
        if auto_base:
            b = _unwound_base(
                nodes, rc, sub, b, axis_sign, band=max(10.0, 2.0 * float(root_width)), root_width=float(root_width)
            )
            base_node = int(nodes[b])
            chk = _plant_checks(nodes, rc, sub, b, gray, halfwidth, axis_sign)
            if chk["frame"] or chk["edge"] or chk["border"] or chk["heading"] < 0.6:
                continue
            dist, pred, tip = chk["dist"], chk["pred"], chk["tip"]
        else:
            dist, pred = csgraph.dijkstra(sub, directed=False, indices=b, return_predecessors=True)
            tip = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
        if dist[tip] < min_root_length:
            continue
        candidates.append((nodes, sub, b, base_node, pred, tip, float(dist[tip])))
    if auto_base and candidates:
        from scipy.spatial import cKDTree

        longest = max(cand[-1] for cand in candidates)
        candidates = [cand for cand in candidates if cand[-1] >= min_plant_fraction * longest]
        # A piece is a part of a longer plant broken off by a gap too wide to bridge (a
        # lateral, the rest of a main root), not a plant of its own, when its base lies close
        # to that plant, or when it is less than half as long, lies mostly inside the plant's
        # bounding box and comes close to it somewhere. (Neighbouring seedlings on a plate
        # have side-by-side bounding boxes and bases far apart.)
        near = 3.0 * bridge_gaps
        kept, trees = [], []
        for cand in sorted(candidates, key=lambda cand: -cand[-1]):
            pix = rc[cand[0]]
            lo, hi = pix.min(axis=0), pix.max(axis=0) + 1
            part_of = False
            for other, tree, (olo, ohi) in trees:
                if tree.query(rc[cand[3]])[0] <= near:
                    part_of = True
                elif cand[-1] < 0.5 * other[-1]:
                    inter = np.prod(np.clip(np.minimum(hi, ohi) - np.maximum(lo, olo), 0, None))
                    if inter >= 0.5 * np.prod(hi - lo) and tree.query(pix[:: max(1, len(pix) // 500)])[0].min() <= near:
                        part_of = True
                if part_of:
                    break
            if part_of:
                continue
            kept.append(cand)
            opix = rc[cand[0]]
            trees.append((cand, cKDTree(opix), (opix.min(axis=0), opix.max(axis=0) + 1)))
        candidates = kept
    why = f"no elongated root-like structure reaches min_root_length={min_root_length} px"
    return candidates, rc, halfwidth, why


def _ridge_sigmas(root_width: float) -> tuple[float, ...]:
    """Scales 1, 2, 3, then 4, 6, 8, 12, 16, ... up to root_width / 2 (a bar of width w gives
    its strongest centre response near σ ≈ w / 2√3, and still a single ridge up to σ ≈ w / 2)."""
    top = max(1.0, float(root_width) / 2.0)
    out = [s for s in (1.0, 2.0, 3.0) if s <= top + 1e-9]
    s = 4.0
    while s <= top + 1e-9:
        out.append(s)
        s = s * 1.5 if s * 1.5 == int(s * 1.5) else s * 4 / 3
    return tuple(out) if out else (1.0,)


def _refine_junction(main, cum, k, lat, hw):
    """Move a lateral's attachment from the skeleton junction to its true insertion.

    Where a thick lateral meets the main root at an acute angle, the skeleton's branch point
    slides downstream and the lateral's first pixels bend along the main root. The lateral's
    direction is measured beyond that junction zone (from arc length ``a = 2·hw + 2`` to
    ``b = a + max(6, 2·hw)``, ``hw`` the main root's half-width there) and extended back to the
    main root; the attachment becomes that crossing and the lateral starts with the straight
    segment to its point at ``a``. Laterals too short to measure, or whose extension does not
    cross the main root nearby, are left as they are. Returns (attachment arc length, lateral).
    """
    s = _cumlen(lat)
    a = 2.0 * hw + 2.0
    b = a + max(6.0, 2.0 * hw)
    if s[-1] < b + 2.0:
        return cum[k], lat
    A, B = _at(lat, s, a), _at(lat, s, b)
    u = A - B
    norm = float(np.linalg.norm(u))
    if norm == 0:
        return cum[k], lat
    u /= norm
    lo = max(int(np.searchsorted(cum, cum[k] - 3 * b)) - 1, 0)
    hi = min(int(np.searchsorted(cum, cum[k] + 3 * b)), main.shape[0] - 1)
    best = None
    for i in range(lo, hi):
        p, q = main[i], main[i + 1]
        m = np.column_stack([u, p - q])
        det = float(np.linalg.det(m))
        if abs(det) < 1e-12:
            continue
        t, v = np.linalg.solve(m, p - A)
        if 0 <= t <= a + 4 * hw + 5 and 0 <= v <= 1 and (best is None or t < best[0]):
            best = (t, cum[i] + v * (cum[i + 1] - cum[i]), A + t * u)
    if best is None:
        return cum[k], lat
    return best[1], np.concatenate([best[2][None], A[None], lat[s > a]])


def _lateral_paths(sub, main_idx, halfwidth, rc, min_lateral_length, *, split_factor=None) -> list[np.ndarray]:
    """Paths from the main path into its side subtrees, one per lateral.

    Node paths starting on the main path. Each attachment (junctions closer than about a root
    width along the main path count as one) gives its longest path. With `split_factor`, every
    further tip of that side subtree whose own part (beyond the node where its path joins the
    paths already taken) is at least ``min_lateral_length + split_factor × half-width`` there
    gives one more lateral, the whole path from the main root: roots touching in the crown are
    one skeleton line until they part, and each of them grew along it from the main root.
    Tips are taken farthest first, so the longest root keeps the shared stretch as its own.
    """
    n = sub.shape[0]
    on_main = np.zeros(n, dtype=bool)
    on_main[main_idx] = True
    if on_main.all():
        return []
    coo = sub.tocoo()
    keep = ~(on_main[coo.row] & on_main[coo.col])  # drop main–main edges
    side_graph = sp.csr_matrix((coo.data[keep], (coo.row[keep], coo.col[keep])), shape=(n, n))
    # Multi-source Dijkstra from the whole main path: each side pixel's distance from the main
    # path and the main pixel it is reached from (a shortest path never passes through another
    # main pixel, which is itself a source at distance 0).
    dist, pred, src = csgraph.dijkstra(
        side_graph, directed=False, indices=main_idx, min_only=True, return_predecessors=True
    )
    degree = np.diff(side_graph.indptr)
    side = np.nonzero(~on_main)[0]
    only_side = side_graph[side][:, side]
    n_sub, lab = csgraph.connected_components(only_side, directed=False)
    pos = np.full(n, -1, dtype=np.int64)
    pos[main_idx] = np.arange(main_idx.size)
    taken = np.zeros(n, dtype=bool)
    paths = []
    for s in range(n_sub):
        members = side[lab == s]
        members = members[np.isfinite(dist[members])]
        if members.size == 0:
            continue
        # Laterals that touch or cross (dense crowns) form one side subtree; split it by the
        # main-root pixel each side pixel is nearest to. Attachments a few pixels apart along
        # the main root are one junction smeared by the root's width.
        at = pos[src[members]]
        order = np.unique(at)
        hw_at = halfwidth[rc[main_idx[order], 0], rc[main_idx[order], 1]]
        new_group = np.concatenate([[True], np.diff(order) > 2 * hw_at[1:] + 3])
        group_of = dict(zip(order.tolist(), np.cumsum(new_group).tolist()))
        groups = np.array([group_of[int(a)] for a in at])
        for gidx in np.unique(groups):
            mem = members[groups == gidx]
            far = int(mem[np.argmax(dist[mem])])
            a = int(src[far])
            r, c = rc[a]
            if dist[far] - halfwidth[r, c] < min_lateral_length:
                continue
            path = _path_to(pred, far)
            paths.append(path)
            if split_factor is None:
                continue
            taken[path] = True
            tips = mem[degree[mem] == 1]
            for t in tips[np.argsort(-dist[tips], kind="stable")]:
                if taken[t]:
                    continue
                path = _path_to(pred, int(t))
                shared = np.nonzero(taken[path])[0]
                j = path[shared[-1]] if shared.size else path[0]
                jr, jc = rc[j]
                if dist[t] - dist[j] < min_lateral_length + split_factor * float(halfwidth[jr, jc]):
                    continue
                paths.append(path)
                taken[path] = True
    return paths


def _no_root_message(source, threshold, t, roots_dark, why) -> str:
    polarity = "dark roots on a light background" if roots_dark else "light roots on a dark background"
    if isinstance(t, str):  # ridge mode
        how = f"ridge filter, assuming {polarity}"
        fix = "Try a lower sensitivity=(low, high), root_width= for wide roots, invert=, or threshold='otsu' for a clean scan"
    else:
        how = f"threshold {threshold!r} = {t:.4g}, assuming {polarity}"
        fix = "Try another threshold= (e.g. 'triangle'), invert=, background= for uneven lighting"
    return f"{source}: no root found: {why} ({how}). {fix}, or smaller min_object_size / min_root_length."
