"""Root systems from a scanned image: threshold → clean → skeleton → graph → longest paths.

Coordinates: the image is indexed ``(row, col)``; every returned `Root` is in ``(x, y)`` with
``x = col`` and ``y = row`` — so **y points down**, as in the image (a root growing down the
plate has increasing y). This is the one place where ``(row, col)`` becomes ``(x, y)``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.sparse import csgraph

from .._errors import ImageError
from .._root import Root, project_onto_polyline

_METHODS = ("otsu", "li", "triangle", "yen", "isodata", "mean")


# --------------------------------------------------------------------------------------------
# Image → binary mask.


def _load(image: Any) -> tuple[np.ndarray, str]:
    if isinstance(image, (str, os.PathLike)):
        p = Path(image)
        if not p.is_file():
            raise FileNotFoundError(f"image file not found: {p}")
        import skimage.io

        try:
            arr = skimage.io.imread(p)
        except Exception as e:  # the reader's own errors vary by plugin
            raise ImageError(f"{p}: cannot be read as an image ({e}).") from e
        return np.asarray(arr), p.stem
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
            f"{source}: expected a 2D grayscale/binary image or an (H, W, 3|4) colour image, "
            f"got shape {arr.shape}."
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


def _close(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disk = xx * xx + yy * yy <= radius * radius
    padded = np.pad(mask, radius + 1)
    closed = ndi.binary_closing(padded, structure=disk)
    return closed[radius + 1 : -radius - 1, radius + 1 : -radius - 1]


# --------------------------------------------------------------------------------------------
# Skeleton → graph → paths.

_OFFSETS = ((0, 1, 1.0), (1, -1, math.sqrt(2.0)), (1, 0, 1.0), (1, 1, math.sqrt(2.0)))


def skeleton_graph(skeleton: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
    """Pixels of a boolean skeleton and their 8-adjacency graph.

    Returns ``(rc, graph)``: ``rc`` the (n, 2) ``(row, col)`` of the skeleton pixels and
    ``graph`` a symmetric sparse (n, n) matrix with weight 1 between 4-neighbours and √2
    between diagonal neighbours.
    """
    rc = np.argwhere(skeleton)
    n = rc.shape[0]
    index = np.full(skeleton.shape, -1, dtype=np.int64)
    index[rc[:, 0], rc[:, 1]] = np.arange(n)
    rows, cols, vals = [], [], []
    H, W = skeleton.shape
    for dr, dc, w in _OFFSETS:
        r2, c2 = rc[:, 0] + dr, rc[:, 1] + dc
        ok = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
        j = np.full(n, -1, dtype=np.int64)
        j[ok] = index[r2[ok], c2[ok]]
        has = j >= 0
        i = np.nonzero(has)[0]
        rows.append(i)
        cols.append(j[has])
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


def roots_from_image(
    image: Any,
    *,
    threshold: float | str | None = None,
    invert: bool | None = None,
    base: str | Sequence[float] | np.ndarray = "top",
    roi: tuple[int, int, int, int] | None = None,
    background: float | None = None,
    close_gaps: int = 2,
    min_object_size: int = 64,
    max_hole_size: int = 16,
    min_root_length: float = 20.0,
    min_lateral_length: float = 10.0,
    smooth: float = 2.0,
    spacing: float | None = 2.0,
    refine_junctions: bool = True,
    pixel_size: float | None = None,
    unit: str = "pixel",
) -> list[Root]:
    """Extract root systems (main root + first-order laterals) from a scanned image.

    **Arguments**

    - `image`: a path, or an array: 2D grayscale, 2D binary (bool, or two values), or
      (H, W, 3|4) colour (converted to gray; alpha ignored).
    - `threshold`: None or ``"otsu"`` (default), ``"li"``, ``"triangle"``, ``"yen"``,
      ``"isodata"``, ``"mean"`` (scikit-image's methods), or a number in the gray scale
      (integer images are scaled to [0, 1]; after `background` subtraction the scale is
      centred on 0). Ignored for binary images.
    - `invert`: True if roots are darker than the background, False if brighter, None (default)
      to decide automatically: roots are the minority class (fewer pixels) after thresholding.
    - `base`: where each root starts: ``"top"`` (default; the top-most skeleton pixel of each
      connected root), ``"bottom"``, ``"left"``, ``"right"``, or an ``(x, y)`` point / an
      ``(n, 2)`` array of points in image ``(x = col, y = row)`` coordinates — then one root per
      point, from the skeleton pixel nearest to it.
    - `roi`: ``(top, bottom, left, right)`` pixel bounds of the region to analyse (rows
      ``top:bottom``, columns ``left:right``); coordinates stay in the full image's frame.
    - `background`: None (default) or a Gaussian sigma in pixels: the smoothed image is
      subtracted first, which flattens uneven lighting (useful for thin roots on photographed
      plates; combine with ``threshold="triangle"``).
    - `close_gaps`: radius (px) of a morphological closing that bridges small gaps (≈ up to
      2 × radius px) in a root; 0 disables.
    - `min_object_size`: connected foreground objects smaller than this (px) are removed.
    - `max_hole_size`: background holes up to this size (px) inside roots are filled.
    - `min_root_length`: roots whose main path is shorter (px) are dropped.
    - `min_lateral_length`: side branches shorter than this (px, measured from the edge of the
      main root, i.e. path length minus the main root's local half-width) are spurs, ignored.
    - `smooth`: Gaussian sigma (in path pixels) that smooths the pixel staircase of each path
      (end points are kept fixed); 0 disables.
    - `spacing`: resample every branch uniformly at this arc-length spacing (px); None keeps
      one point per skeleton pixel.
    - `refine_junctions`: where a thick lateral meets the main root, the skeleton junction
      slides downstream (a few px, more at acute angles); if True (default) each lateral's
      direction beyond the junction zone is extended back to the main root, which becomes its
      attachment point, and its start is made straight. False keeps the raw skeleton junction.
    - `pixel_size`, `unit`: multiply coordinates by `pixel_size` and record `unit` (e.g.
      ``pixel_size=0.05, unit="mm"``); default pixels.

    **Pipeline**: gray → optional background subtraction → threshold → closing → fill small
    holes → remove small objects → skeletonize (scikit-image) → 8-connected pixel graph
    (weights 1 and √2) → per connected component: main root = longest shortest path from the
    base; every subtree hanging off the main path gives one lateral = its longest path from
    the main path (only first-order laterals; a lateral crossing another merges with it).
    Attachment fractions come from where each lateral leaves the main path, and each lateral
    starts exactly on the main root.

    **Returns** one `Root` per connected root sorted by base position (x, then y) — or one
    per base point, in the points' order — in ``(x, y)`` coordinates with **x = column, y = row (y points down)**.
    ``metadata`` holds ``source``, ``unit``, ``threshold``, ``roots_dark``, ``base_xy``,
    ``component_pixels``, ``y_axis = "down"`` (and ``resolution`` = 1 / pixel_size).

    Raises `ImageError` when the image is unusable or contains no root.
    """
    if isinstance(base, str) and base.lower() not in ("top", "bottom", "left", "right"):
        raise ValueError(f"base must be 'top', 'bottom', 'left', 'right' or (x, y) point(s), got {base!r}.")
    arr, stem = _load(image)
    source = str(image) if isinstance(image, (str, os.PathLike)) else "array"
    if arr.size == 0:
        raise ImageError(f"{source}: the image is empty (shape {arr.shape}).")
    if pixel_size is not None and not (math.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number, got {pixel_size!r}.")
    if pixel_size is not None and unit.lower() in ("pixel", "pixels", "px"):
        raise ValueError("pixel_size given: pass the physical unit too, e.g. unit='mm'.")
    for opt, val in (("close_gaps", close_gaps), ("min_object_size", min_object_size), ("max_hole_size", max_hole_size)):
        if int(val) != val or val < 0:
            raise ValueError(f"{opt} must be a non-negative integer, got {val!r}.")

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
    gray = _to_gray(arr, source)

    # Binary input (bool, or only two grey values): no thresholding.
    step = max(1, gray.shape[0] // 256)
    is_binary = gray.dtype == bool or (
        np.unique(gray[::step]).size <= 2 and np.unique(gray).size <= 2
    )
    if is_binary:
        values = np.unique(gray)
        if values.size < 2:
            raise ImageError(f"{source}: the image is uniform (single value); it contains no root.")
        bright = gray > values[0]
        t = float(values[0])
    else:
        if background is not None:
            if not (background > 0):
                raise ValueError(f"background must be a positive Gaussian sigma (px), got {background!r}.")
            gray = gray - ndi.gaussian_filter(gray, float(background), mode="nearest")
        if float(gray.max() - gray.min()) <= 1e-12 * max(1.0, float(np.abs(gray).max())):
            raise ImageError(f"{source}: the image is uniform; it contains no root.")
        t = _threshold(gray, threshold, source)
        bright = gray > t
    roots_dark = bool(bright.mean() > 0.5) if invert is None else bool(invert)
    mask = ~bright if roots_dark else bright

    mask = _close(mask, int(close_gaps))
    mask = _fill_small_holes(mask, int(max_hole_size))
    mask = _remove_small(mask, int(min_object_size))
    if not mask.any():
        raise ImageError(_no_root_message(source, threshold, t, roots_dark, "after thresholding and removing small objects the mask is empty"))

    from skimage.morphology import skeletonize

    skel = skeletonize(mask)
    halfwidth = ndi.distance_transform_edt(mask)
    rc, graph = skeleton_graph(skel)
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    sizes = np.bincount(comp, minlength=n_comp)
    # A path of length L has at least L / sqrt(2) + 1 pixels.
    eligible = np.nonzero(sizes >= max(2, min_root_length / math.sqrt(2.0)))[0]
    if eligible.size == 0:
        raise ImageError(_no_root_message(source, threshold, t, roots_dark, f"no skeleton reaches min_root_length={min_root_length} px"))

    scale = 1.0 if pixel_size is None else float(pixel_size)
    results = []
    for c, base_node in _base_nodes(base, rc, comp, eligible, (c0, r0)):
        nodes = np.nonzero(comp == c)[0]
        sub = graph[nodes][:, nodes]
        local = {int(g): k for k, g in enumerate(nodes)}
        b = local[base_node]
        dist, pred = csgraph.dijkstra(sub, directed=False, indices=b, return_predecessors=True)
        tip = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
        if dist[tip] < min_root_length:
            continue
        main_idx = _path_to(pred, tip)
        lat_paths = _lateral_paths(sub, main_idx, halfwidth, rc[nodes], min_lateral_length)
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
    if not results:
        raise ImageError(_no_root_message(source, threshold, t, roots_dark, f"no main path reaches min_root_length={min_root_length} px"))
    if isinstance(base, str):  # base points keep the caller's order
        results.sort(key=lambda item: item[0])
    return [Root(name=f"{stem}/{k + 1}", **kw) for k, (_, kw) in enumerate(results)]


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


def _lateral_paths(sub, main_idx, halfwidth, rc, min_lateral_length) -> list[np.ndarray]:
    """Longest path into every side subtree of the main path, as node paths from the main."""
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
    side = np.nonzero(~on_main)[0]
    only_side = side_graph[side][:, side]
    n_sub, lab = csgraph.connected_components(only_side, directed=False)
    paths = []
    for s in range(n_sub):
        members = side[lab == s]
        d = dist[members]
        if not np.any(np.isfinite(d)):
            continue
        far = int(members[np.argmax(np.where(np.isfinite(d), d, -1))])
        a = int(src[far])
        r, c = rc[a]
        if dist[far] - halfwidth[r, c] < min_lateral_length:
            continue
        paths.append(_path_to(pred, far))
    return paths


def _no_root_message(source, threshold, t, roots_dark, why) -> str:
    method = "otsu" if threshold is None else threshold
    polarity = "dark roots on a light background" if roots_dark else "light roots on a dark background"
    return (
        f"{source}: no root found: {why} (threshold {method!r} = {t:.4g}, assuming {polarity}). "
        "Try another threshold= (e.g. 'triangle'), invert=, background= for uneven lighting, "
        "or smaller min_object_size / min_root_length."
    )
