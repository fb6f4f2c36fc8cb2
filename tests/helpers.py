"""Shared test builders and comparisons."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rootshape_jax._root import Root


def tree_allclose(x, y, *, rtol=1e-7, atol=1e-9) -> bool:
    """True when two pytrees have the same structure and allclose leaves."""
    lx, tx = jax.tree.flatten(x)
    ly, ty = jax.tree.flatten(y)
    if tx != ty:
        return False
    return all(
        np.shape(a) == np.shape(b) and np.allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=atol)
        for a, b in zip(lx, ly)
    )


def smooth_curve(rng: np.random.Generator, *, n=60, d=2, length=1.0, bend=1.0, start=None) -> np.ndarray:
    """A random smooth open curve of roughly the given length, heading along +y (down)."""
    t = np.linspace(0, 1, n)
    heading = np.zeros(d)
    heading[1] = 1.0
    coeffs = rng.normal(size=(3, d)) * bend * 0.3
    pts = heading[None] * t[:, None]
    for k, c in enumerate(coeffs, start=1):
        pts = pts + c[None] * np.sin(np.pi * k * t)[:, None] / k
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
    pts = pts * (length / seg)
    if start is not None:
        pts = pts + np.asarray(start)[None]
    return pts


def random_root(rng: np.random.Generator, *, n_laterals=5, d=2, main_length=1.0) -> Root:
    """A random root: smooth main root plus laterals attached at random fractions."""
    main = smooth_curve(rng, d=d, length=main_length, n=80)
    attach = np.sort(rng.uniform(0.05, 0.9, size=n_laterals))
    lats = []
    cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(main, axis=0), axis=1))])
    for s in attach:
        base = np.array([np.interp(s * cum[-1], cum, main[:, k]) for k in range(d)])
        side = rng.choice([-1.0, 1.0])
        curve = smooth_curve(rng, d=d, length=rng.uniform(0.1, 0.35) * main_length, n=30, bend=0.6)
        # Turn the lateral sideways: swap the first two axes so it grows along ±x.
        curve = curve[:, [1, 0] + list(range(2, d))] * np.array([side, 1.0] + [1.0] * (d - 2))
        lats.append(curve - curve[0] + base)
    return Root(main=main, laterals=lats, attach=attach)


def rotation_matrix(rng: np.random.Generator, d: int) -> np.ndarray:
    """A random proper rotation in SO(d)."""
    q, r = np.linalg.qr(rng.normal(size=(d, d)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def reparameterise(points: np.ndarray, gamma) -> np.ndarray:
    """Resample a polyline at arc-length fractions gamma(t) (a reparameterisation)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0], np.cumsum(seg)]) / seg.sum()
    t = np.linspace(0, 1, len(points))
    g = gamma(t)
    return np.stack([np.interp(g, cum, points[:, k]) for k in range(points.shape[1])], axis=1)


def as_jnp(x):
    return jnp.asarray(x)


def transformed_copies(root: Root, rng: np.random.Generator, n: int, *, reparam=True) -> list[Root]:
    """Copies of `root`, each rotated (about the main root's base), with its lateral order
    permuted and (optionally) every branch reparameterised — all the same shape."""
    d = root.dim
    out = []
    for i in range(n):
        O = rotation_matrix(rng, d) if i else np.eye(d)
        o = root.main[0]
        rot = lambda p: (p - o) @ O.T + o  # noqa: E731
        a = rng.uniform(0.6, 1.6) if (reparam and i) else 1.0
        warp = lambda t, a=a: t**a
        main = reparameterise(rot(root.main), warp) if reparam else rot(root.main)
        order = rng.permutation(root.n_laterals)
        lats = [reparameterise(rot(root.laterals[k]), warp) if reparam else rot(root.laterals[k]) for k in order]
        out.append(Root(main=main, laterals=lats, attach=np.asarray(root.attach)[order]))
    return out


def linear_srvf_population(base, coefficients, *, lateral_scale=0.5, shift=0.2):
    """SRVF trees ``x_i = base + a_i Δ1 + b_i Δ2``, exactly linear in the coefficients (a_i, b_i):
    Δ1 scales every real lateral's SRVF (``q_k → (1 + lateral_scale·a) q_k``: longer or shorter
    laterals, which no rotation or reparameterisation can undo), Δ2 moves every attachment
    fraction by ``shift·b``. `base` is a single SRVFTree; returns a batched SRVFTree."""
    from rootshape_jax._tree import SRVFTree

    c = jnp.asarray(coefficients, base.q0.dtype)
    a, b = c[:, 0], c[:, 1]
    n = c.shape[0]
    q = base.q[None] * (1 + lateral_scale * a)[:, None, None, None]
    s = jnp.where(base.mask[None], base.s[None] + shift * b[:, None], base.s[None])
    rep = lambda x: jnp.broadcast_to(x, (n,) + x.shape)  # noqa: E731
    return SRVFTree(q0=rep(base.q0), q=q, s=s, mask=rep(base.mask), origin=rep(base.origin))


def render_root_image(polylines, *, shape, width=5.0, noise=0.05, dark=True, seed=0, gaps=()):
    """Draw (x = col, y = row) polylines as thick lines of `width` px on a noisy background.

    Returns (float image in [0, 1], boolean root mask). Dark roots (0.25) on light (0.85) by
    default. `gaps`: (row0, row1) bands erased from the mask to cut the roots there.
    """
    import scipy.ndimage as ndi

    centre = np.zeros(shape, bool)
    for poly in polylines:
        poly = np.asarray(poly, float)
        for p, q in zip(poly[:-1], poly[1:]):
            n = max(2, int(np.ceil(4 * np.linalg.norm(q - p))) + 1)
            pts = p + np.linspace(0, 1, n)[:, None] * (q - p)
            r = np.round(pts[:, 1]).astype(int)
            c = np.round(pts[:, 0]).astype(int)
            ok = (r >= 0) & (r < shape[0]) & (c >= 0) & (c < shape[1])
            centre[r[ok], c[ok]] = True
    mask = ndi.distance_transform_edt(~centre) <= width / 2
    for r0, r1 in gaps:
        mask[r0:r1] = False
    fg, bg = (0.25, 0.85) if dark else (0.85, 0.25)
    img = np.where(mask, fg, bg) + noise * np.random.default_rng(seed).standard_normal(shape)
    return np.clip(img, 0.0, 1.0), mask


# --- DP warp references (tests/test_warp.py, tests/test_elastic.py) -------------------------
# Slow, obvious numpy versions of the DP of rootshape_jax._warp, written from the definition
# (merged breakpoints, linear interpolation, trapezoid), sharing no code with the library.


def reference_moves(neighbourhood: int) -> list[tuple[int, int]]:
    import math

    n = neighbourhood
    return [(a, b) for a in range(1, n + 1) for b in range(1, n + 1) if math.gcd(a, b) == 1]


def _ref_lerp(v: np.ndarray, x: float) -> np.ndarray:
    i0 = min(int(np.floor(x)), len(v) - 2)
    f = x - i0
    return v[i0] * (1 - f) + v[i0 + 1] * f


def reference_warp_energy(q1: np.ndarray, q2: np.ndarray, gamma: np.ndarray) -> float:
    """∫|q1 − √γ' q2∘γ|² for γ piecewise linear on the grid: on each grid interval, trapezoid
    on its ends plus every point where γ crosses a node of q2's grid."""
    q1, q2 = np.asarray(q1, float), np.asarray(q2, float)
    T = len(q1)
    g = np.asarray(gamma, float) * (T - 1)
    total = 0.0
    for i in range(T - 1):
        s = g[i + 1] - g[i]
        xs = [float(i), float(i + 1)]
        if s > 0:
            for j in range(int(np.floor(g[i])) + 1, int(np.ceil(g[i + 1]))):
                xs.append(i + (j - g[i]) / s)
        xs.sort()
        f = [np.sum((_ref_lerp(q1, x) - np.sqrt(max(s, 0.0)) * _ref_lerp(q2, g[i] + s * (x - i))) ** 2) for x in xs]
        total += sum((xs[p + 1] - xs[p]) * (f[p] + f[p + 1]) / 2 for p in range(len(xs) - 1))
    return total / (T - 1)


def path_to_gamma(vertices, T: int) -> np.ndarray:
    """γ on the grid for a grid path given by its vertices (k, l), linear in between."""
    v = np.asarray(vertices, float)
    return np.interp(np.arange(T), v[:, 0], v[:, 1]) / (T - 1)


def reference_dp(q1: np.ndarray, q2: np.ndarray, neighbourhood: int) -> tuple[np.ndarray, float]:
    """Plain DP over the T×T grid with the coprime moves; segment cost = reference energy of
    the segment. Returns (γ on the grid, minimum energy)."""
    q1, q2 = np.asarray(q1, float), np.asarray(q2, float)
    T = len(q1)
    moves = reference_moves(neighbourhood)
    E = np.full((T, T), np.inf)
    E[0, 0] = 0.0
    back = {}
    for k in range(1, T):
        for l in range(1, T):
            for a, b in moves:
                if k - a < 0 or l - b < 0 or not np.isfinite(E[k - a, l - b]):
                    continue
                # The segment's energy: the energy of a γ that is this segment, on a sub-grid.
                seg1 = q1[k - a : k + 1]
                seg2 = q2[l - b : l + 1]
                c = _ref_segment(seg1, seg2, a, b) / (T - 1)
                if E[k - a, l - b] + c < E[k, l]:
                    E[k, l] = E[k - a, l - b] + c
                    back[k, l] = (k - a, l - b)
    path = [(T - 1, T - 1)]
    while path[-1] != (0, 0):
        path.append(back[path[-1]])
    return path_to_gamma(path[::-1], T), float(E[-1, -1])


def _ref_segment(seg1: np.ndarray, seg2: np.ndarray, a: int, b: int) -> float:
    """∫ over one straight move from (0, 0) to (a, b), in grid units of t (times a, not h)."""
    from fractions import Fraction

    s = b / a
    pts = sorted({Fraction(i, a) for i in range(a + 1)} | {Fraction(j, b) for j in range(b + 1)})
    xs = [a * float(p) for p in pts]
    f = [np.sum((_ref_lerp(seg1, a * float(p)) - np.sqrt(s) * _ref_lerp(seg2, b * float(p))) ** 2) for p in pts]
    return sum((xs[i + 1] - xs[i]) * (f[i] + f[i + 1]) / 2 for i in range(len(xs) - 1))


def all_grid_paths(T: int, neighbourhood: int):
    """Every path from (0, 0) to (T−1, T−1) made of the coprime moves (brute force; small T)."""
    moves = reference_moves(neighbourhood)

    def extend(path):
        k, l = path[-1]
        if (k, l) == (T - 1, T - 1):
            yield path
            return
        for a, b in moves:
            if k + a <= T - 1 and l + b <= T - 1:
                yield from extend(path + [(k + a, l + b)])

    yield from extend([(0, 0)])
