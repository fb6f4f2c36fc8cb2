"""Shared test builders and comparisons."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

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


# --------------------------------------------------------------------------------------------
# A slow, obvious reference of the elastic distance between root systems of any depth
# (docs/design.md §4 and §11), in numpy and plain Python recursion. Only the padded SRVFs come
# from the library (`batch` + `to_srvf`: the data model); the warps (`reference_dp`), the
# warp action, the assignment (scipy), the rotation (Kabsch) and the alternation are here.


def _ref_trapezoid(T: int) -> np.ndarray:
    w = np.full(T, 1.0 / (T - 1))
    w[0] = w[-1] = 0.5 / (T - 1)
    return w


def _ref_norm2(q: np.ndarray) -> float:
    return float(np.sum(np.sum(q * q, axis=-1) * _ref_trapezoid(len(q))))


def _ref_warp_keep_norm(q: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """(q∘γ)√γ' on the grid (linear interpolation; √γ' at a node = mean of the adjacent
    √(finite differences)), rescaled to keep ||q|| (as the engine does: branch lengths exact)."""
    T = len(q)
    tiny = np.sqrt(np.finfo(float).tiny)
    x = np.clip(gamma * (T - 1), 0, T - 1)
    i0 = np.clip(np.floor(x).astype(int), 0, T - 2)
    f = (x - i0)[:, None]
    lerp = q[i0] * (1 - f) + q[i0 + 1] * f
    dg = np.diff(gamma) * (T - 1)
    rs_ = np.where(dg > tiny, np.sqrt(np.where(dg > tiny, dg, 1.0)), 0.0)
    speed = 0.5 * (np.concatenate([rs_[:1], rs_]) + np.concatenate([rs_, rs_[-1:]]))
    w = lerp * speed[:, None]
    n2, w2 = _ref_norm2(q), _ref_norm2(w)
    ratio = n2 / w2 if w2 > tiny else 0.0
    return w * (np.sqrt(ratio) if ratio > tiny else 0.0)


def _ref_kabsch(A: list, B: list, w: list) -> np.ndarray:
    """Rotation O in SO(d) maximising Σ_k w_k <A_k, O B_k> (trapezoid L2)."""
    d = A[0].shape[-1]
    M = np.zeros((d, d))
    for a, b, wk in zip(A, B, w):
        M += wk * np.einsum("t,ti,tj->ij", _ref_trapezoid(len(a)), b, a)
    if d == 2:
        x, y = M[0, 0] + M[1, 1], M[0, 1] - M[1, 0]
        if x == 0 and y == 0:
            return np.eye(2)
        r = np.hypot(x, y)
        c, s = x / r, y / r
        return np.array([[c, -s], [s, c]])
    U, _, Vt = np.linalg.svd(M)
    V = Vt.T
    det = np.linalg.det(V @ U.T)
    D = np.ones(d)
    D[-1] = np.sign(det) + (det == 0)
    return (V * D) @ U.T


def _ref_branches(tree, i: int) -> dict:
    """Tree i of a batched SRVFTree as nested dicts {q, s, children}, real branches only."""
    levels = [(np.asarray(tree.q[i]), np.asarray(tree.s[i]), np.asarray(tree.mask[i]))]
    levels += [(np.asarray(lv.q[i]), np.asarray(lv.s[i]), np.asarray(lv.mask[i])) for lv in tree.deeper]

    def kids(slot: tuple) -> list:
        if len(slot) >= len(levels):
            return []
        q, s, m = levels[len(slot)]
        return [
            {"q": q[slot + (k,)], "s": float(s[slot + (k,)]), "children": kids(slot + (k,))}
            for k in range(m.shape[-1])
            if m[slot + (k,)]
        ]

    return {"q": np.asarray(tree.q0[i]), "s": 0.0, "children": kids(())}


def reference_tree_distance(
    a_root,
    b_root,
    weights=None,
    depth: int = 2,
    *,
    level_weights=None,
    n_points: int = 12,
    neighbourhood: int = 7,
    max_iterations: int = 4,
    rtol: float = 1e-4,
    rotation: bool = True,
    normalise_scale: bool = False,
    max_children=None,
) -> tuple[float, dict]:
    """Register b onto a and return (minimised squared distance, details), slowly and plainly.

    - `weights`: a `rootshape_jax.Weights`; λm weights the main roots. With a thickness weight
      λr > 0 and roots with radii, every branch is the extended curve ``(x, √λr·r)``
      (`rootshape_jax.to_srvf`): its SRVF has one more channel, which the rotation leaves alone.
    - `level_weights`: ``[(λs, λp), …]`` for levels 1 … depth − 1; default ``(weights.lateral,
      weights.position)`` at level 1 and ``weights.deeper[ℓ − 2]`` at level ℓ ≥ 2 (its last
      entry beyond it, level 1's when it is empty).

    Plants' systems (the roots are `rootshape_jax.io.plant_system`s, a virtual main root of zero
    length): the axes (level 1) weigh as main roots, ``(λm, 0)``, and level ℓ ≥ 2 takes the
    weights level ℓ − 1 would have in a taproot system; the rotation starts from the Kabsch
    rotation of the longest axes (largest ``||q||²``, the first on ties) instead of the main
    roots'.

    At a fixed rotation O (applied to b), bottom-up (docs/design.md §11): a branch pair at level
    ℓ costs ``λs_ℓ ||qa − (O qb∘γ)√γ'||²`` with γ from `reference_dp` (the warped SRVF rescaled
    to keep its norm, as the engine does) ``+ λp_ℓ (sa − sb)² +`` the exact assignment cost of
    their children; a real branch left unmatched (matched to a null) costs its subtree's
    λ-weighted norm ``Σ λs_m ||q||²`` over itself and every descendant; the main roots cost
    ``λm ||q0a − (O q0b∘γ)√γ'||²`` plus the assignment of their children. Assignments are
    solved exactly with `scipy.optimize.linear_sum_assignment` on the matrix augmented with one
    null per branch. The rotation starts from the main roots' Kabsch rotation and is refitted by
    weighted Kabsch over every matched branch (weight λm for the main roots, λs_ℓ for a matched
    pair at level ℓ, using the warps found at the previous rotation); the two steps alternate
    while the energy falls by at least `rtol` (relative), for at most `max_iterations` rounds.
    """
    from scipy.optimize import linear_sum_assignment

    import rootshape_jax as rs

    weights = rs.Weights() if weights is None else weights
    lam_m = float(weights.main)
    kw = {} if depth == 2 and max_children is None else {"depth": depth, "max_children": max_children}
    tree = rs.to_srvf(
        rs.batch([a_root, b_root], n_points=n_points, normalise_scale=normalise_scale, dtype=np.float64, **kw),
        weights=weights,
    )
    d = tree.dim  # spatial channels; a thickness channel may follow

    def rot(q, O):
        out = np.array(q, dtype=float)
        out[:, :d] = q[:, :d] @ O.T
        return out

    system = bool(a_root.metadata.get("virtual_main")) and bool(b_root.metadata.get("virtual_main"))
    if level_weights is None:
        per_level = [(float(weights.lateral), float(weights.position))]
        per_level += [(float(ls), float(lp)) for ls, lp in weights.deeper]
        if system:  # every level takes the weights of the level above it in a taproot system
            per_level = [(lam_m, 0.0)] + per_level
        level_weights = [per_level[min(ell, len(per_level) - 1)] for ell in range(depth - 1)]
    A, B = _ref_branches(tree, 0), _ref_branches(tree, 1)
    n_dp = [0] * depth  # DPs run per level (0 = main)

    def null_cost(br: dict, ell: int) -> float:
        return level_weights[ell - 1][0] * _ref_norm2(br["q"]) + sum(null_cost(c, ell + 1) for c in br["children"])

    def branch_energy(qa, qb, O, ell):
        qbo = rot(qb, O)
        gamma, _ = reference_dp(qa, qbo, neighbourhood)
        n_dp[ell] += 1
        return _ref_norm2(qa - _ref_warp_keep_norm(qbo, gamma)), gamma

    def assign(ca: list, cb: list, O, ell: int):
        """(cost, matches) of the children lists at level ell; matches: (a, b, γ, ell) of every
        matched pair in the subtrees."""
        na, nb = len(ca), len(cb)
        if na + nb == 0:
            return 0.0, []
        big = np.inf
        C = np.full((na + nb, na + nb), big)
        sub = {}
        for i, x in enumerate(ca):
            for j, y in enumerate(cb):
                c, m = pair_cost(x, y, O, ell)
                C[i, j] = c
                sub[i, j] = m
        for i, x in enumerate(ca):
            C[i, nb + i] = null_cost(x, ell)
        for j, y in enumerate(cb):
            C[na + j, j] = null_cost(y, ell)
        C[na:, nb:] = 0.0
        rows, cols = linear_sum_assignment(np.where(np.isinf(C), 1e300, C))
        total, matches = 0.0, []
        for r, c in zip(rows, cols):
            total += C[r, c]
            if r < na and c < nb:
                matches += sub[r, c]
        return total, matches

    def pair_cost(x, y, O, ell):
        lam_s, lam_p = level_weights[ell - 1]
        e, gamma = branch_energy(x["q"], y["q"], O, ell)
        c = lam_s * e + lam_p * (x["s"] - y["s"]) ** 2
        matches = [(x, y, gamma, ell)]
        if ell < depth - 1:
            cc, m = assign(x["children"], y["children"], O, ell + 1)
            c += cc
            matches += m
        return c, matches

    def evaluate(O):
        e, gamma = branch_energy(A["q"], B["q"], O, 0)
        c, matches = assign(A["children"], B["children"], O, 1)
        return lam_m * e + c, [(A, B, gamma, 0)] + matches

    def refit(matches):
        qa = [x["q"][:, :d] for x, _, _, _ in matches]
        qb = [_ref_warp_keep_norm(y["q"], g)[:, :d] for _, y, g, _ in matches]
        w = [lam_m if ell == 0 else level_weights[ell - 1][0] for *_, ell in matches]
        return _ref_kabsch(qa, qb, w)

    if system:
        longest = [max(t["children"], key=lambda c: _ref_norm2(c["q"]))["q"] for t in (A, B)]
        O = _ref_kabsch([longest[0][:, :d]], [longest[1][:, :d]], [1.0]) if rotation else np.eye(d)
    else:
        O = _ref_kabsch([A["q"][:, :d]], [B["q"][:, :d]], [1.0]) if rotation else np.eye(d)
    if rotation and d == 3:
        if not system:
            O = reference_spin_start(A, B, O, lam_m, level_weights[0], rot)
        elif depth > 2:  # a plant's spins are its longest axis's, as a taproot with its laterals
            la, lb = (max(t["children"], key=lambda c: _ref_norm2(c["q"])) for t in (A, B))
            O = reference_spin_start(la, lb, O, lam_m, level_weights[1], rot)
    best_E, best_matches, best_O = np.inf, None, O
    rounds = max_iterations if rotation else 1
    for it in range(rounds):
        if it > 0:
            O = refit(best_matches)
        E, matches = evaluate(O)
        if not E < best_E:
            break
        rel = np.inf if np.isinf(best_E) else (best_E - E) / max(best_E, np.sqrt(np.finfo(float).tiny))
        best_E, best_matches, best_O = E, matches, O
        if rel < rtol:
            break
    return float(best_E), {"rotation": best_O, "n_dp": n_dp, "matches": best_matches}


def reference_spin_start(A: dict, B: dict, O, lam_m, level1, rot, n_spins=8, rounds=2):
    """The engine's 3D start (`_engine.spin_start`), plainly: the main-root start turned about
    ``∫ q|q| dt`` of a's main root (spatial channels) by each of `n_spins` spins; each improved
    by `rounds` rounds of [exact assignment of the first-order laterals with identity warps,
    an unmatched one costing λs ||q||² (its children left out, as a matched pair's) → Kabsch
    over the main roots and the matched pairs, or the same rotation when nothing is matched];
    the start is the improved rotation of the spin whose last matching costs least at it (the
    first of equal ones)."""
    from scipy.optimize import linear_sum_assignment

    lam_s, lam_p = level1
    ca, cb = A["children"], B["children"]
    na, nb = len(ca), len(cb)
    x0 = A["q"][:, :3]
    w = _ref_trapezoid(len(x0))
    chord = np.einsum("t,ti->i", w, x0 * np.linalg.norm(x0, axis=1, keepdims=True))
    k = chord / np.linalg.norm(chord) if np.linalg.norm(chord) > 0 else chord
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])

    def costs(O):
        """The main root's energy and the augmented (na + nb)² assignment matrix at O."""
        C = np.zeros((na + nb, na + nb))
        C[:na, nb:] = C[na:, :nb] = np.inf
        for i, x in enumerate(ca):
            for j, y in enumerate(cb):
                C[i, j] = lam_s * _ref_norm2(x["q"] - rot(y["q"], O)) + lam_p * (x["s"] - y["s"]) ** 2
            C[i, nb + i] = lam_s * _ref_norm2(x["q"])
        for j, y in enumerate(cb):
            C[na + j, j] = lam_s * _ref_norm2(y["q"])
        return lam_m * _ref_norm2(A["q"] - rot(B["q"], O)), np.where(np.isinf(C), 1e300, C)

    best = (np.inf, O)
    for s in range(n_spins):
        t = 2 * np.pi * s / n_spins
        Os = (np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K) @ O
        for _ in range(rounds):
            _, C = costs(Os)
            rows, cols = linear_sum_assignment(C)
            pairs = [(ca[r]["q"][:, :3], cb[c]["q"][:, :3]) for r, c in zip(rows, cols) if r < na and c < nb]
            if not pairs and lam_m * _ref_norm2(A["q"]) * _ref_norm2(B["q"]) == 0:
                continue  # nothing to align: the spin keeps its rotation
            Os = _ref_kabsch(
                [A["q"][:, :3]] + [x for x, _ in pairs],
                [B["q"][:, :3]] + [y for _, y in pairs],
                [lam_m] + [lam_s] * len(pairs),
            )
        e_main, C = costs(Os)
        score = e_main + C[rows, cols].sum()
        if score < best[0]:
            best = (score, Os)
    return best[1]


class RecordingBar:
    """Stands in for tqdm: records the bar's settings and every update."""

    def __init__(self, *args, **kwargs):
        self.kwargs, self.updates = kwargs, []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        self.updates.append(n)


def record_bars(monkeypatch) -> list:
    """Make the executor's progress bars `RecordingBar`s; returns the list they are added to."""
    import rootshape_jax._executor as executor

    made = []

    class Bar(RecordingBar):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(executor, "tqdm", Bar)
    return made


def run_cli(*args, cwd=None, timeout: float = 1800) -> subprocess.CompletedProcess:
    """Run ``python -m rootshape_jax ARGS`` as a user would (text output captured).

    A run still going after `timeout` seconds is stopped with SIGABRT, which makes Python's
    faulthandler print every thread's stack, and the test fails with that stack: a hang in CI
    then says where it hung instead of only that it timed out."""
    env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
    cmd = [sys.executable, "-m", "rootshape_jax", *map(str, args)]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env) as p:
        try:
            out, err = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGABRT)
            try:
                out, err = p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                out, err = p.communicate()
            raise AssertionError(
                f"`{' '.join(cmd[1:])}` still running after {timeout:g} s; its stacks and output:\n"
                f"{err[-20000:]}\n--- stdout ---\n{out[-3000:]}"
            ) from None
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def spy_on(monkeypatch, module, name: str) -> dict:
    """Replace ``module.name`` by a wrapper that calls it and keeps what it returned in the
    dict this returns (key "out"): tests read a figure a command drew."""
    original, seen = getattr(module, name), {}

    def spy(*args, **kwargs):
        seen["out"] = original(*args, **kwargs)
        return seen["out"]

    monkeypatch.setattr(module, name, spy)
    return seen
