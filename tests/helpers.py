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
