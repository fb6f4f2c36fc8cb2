"""Topological morphology descriptor (TMD) baseline, through the `tmd` package.

Kanari, L., Dłotko, P., Scolamiero, M., Levi, R., Shillcock, J., Hess, K., Markram, H. (2018).
A topological representation of branching neuronal morphologies. Neuroinformatics 16, 3–13;
and Kanari et al. (2019), Objective morphological classification of neocortical pyramidal
cells, Cerebral Cortex 29. Package: https://github.com/BlueBrain/TMD (``pip install tmd``,
LGPL-3.0 by its package metadata; the ``bench`` extra), imported only when called.

- **Tree**: a `Root` becomes a `tmd.Tree.Tree`: the main root's points form a chain from its
  base (point 0, the tree's root); each lateral's points form a chain whose first point hangs
  from the main-root point nearest its attachment fraction (excluding the base and the tip). Diameters are ``2 × radius`` when
  the root has radii (unused by the radial filtration), else 1; 2-D roots get z = 0.
- **Barcode**: `tmd.methods.get_persistence_diagram` with the radial-distance filtration
  (distance of every point from the base): each branch is a bar (birth at its farthest point,
  death where it merges into a longer one), the main root the last bar.
- **Distance**: persistence images as in the package (`persistence_image_data`: Gaussian KDE,
  Scott's bandwidth, normalised to maximum 1) on limits common to the whole population, and
  the total absolute difference of two images (`total_persistence_image_diff`) divided by
  the number of pixels. A diagram with fewer than 3 bars has a singular KDE; its image is then
  a sum of isotropic Gaussians of standard deviation 5 % of the common range (counted in
  `TMDImages.n_fallback`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import MissingDependencyError


def _tmd():
    try:
        import tmd.Topology.methods as methods
        import tmd.Topology.vectorizations as vec
        from tmd.Tree.Tree import Tree
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(
            "the TMD baseline needs the `tmd` package: pip install 'rootshape_jax[bench]' (or pip install tmd)."
        ) from e
    return Tree, methods, vec


def to_tmd_tree(root):
    """A `rootshape_jax.Root` as a `tmd.Tree.Tree` (module docstring)."""
    Tree, _, _ = _tmd()
    main = np.asarray(root.main, np.float64)
    d = main.shape[1]
    seg = np.linalg.norm(np.diff(main, axis=0), axis=1)
    frac = np.concatenate([[0.0], np.cumsum(seg)]) / max(seg.sum(), 1e-300)
    pts = [main]
    parents = [np.arange(-1, len(main) - 1)]
    rad = [np.asarray(root.main_radius, np.float64) if root.main_radius is not None else np.full(len(main), 0.5)]
    start = len(main)
    for k, lat in enumerate(root.laterals):
        lat = np.asarray(lat, np.float64)
        # Never the base or the tip: tmd needs the base as the tree's only root and a lateral
        # on the tip would merge into the main root's section instead of branching.
        anchor = int(np.clip(np.argmin(np.abs(frac - float(root.attach[k]))), 1, max(len(main) - 2, 1)))
        pts.append(lat)
        parents.append(np.concatenate([[anchor], np.arange(start, start + len(lat) - 1)]))
        r = root.lateral_radii[k] if root.lateral_radii is not None else None
        rad.append(np.asarray(r, np.float64) if r is not None else np.full(len(lat), 0.5))
        start += len(lat)
    P = np.concatenate(pts)
    z = P[:, 2] if d == 3 else np.zeros(len(P))
    return Tree(x=P[:, 0], y=P[:, 1], z=z, d=2 * np.concatenate(rad), t=np.full(len(P), 3), p=np.concatenate(parents))


def tmd_barcode(root) -> np.ndarray:
    """Persistence barcode ``(n_bars, 2)`` (birth, death) of a root under the radial-distance
    filtration (`tmd.Topology.methods.get_persistence_diagram`)."""
    _, methods, _ = _tmd()
    ph = methods.get_persistence_diagram(to_tmd_tree(root), feature="radial_distances")
    return np.asarray(ph, np.float64).reshape(-1, 2)


@dataclasses.dataclass(frozen=True)
class TMDImages:
    """Persistence images of a population on common limits: `images` ``(n, R, R)``,
    `xlim`, `ylim`, and `n_fallback`, the images built with the isotropic kernel."""

    images: np.ndarray
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    n_fallback: int


def tmd_images(roots, *, resolution: int = 100) -> TMDImages:
    """Persistence images of every root's barcode, on limits common to all (module docstring);
    `resolution`: pixels per side of each image."""
    _, _, vec = _tmd()
    bars = [tmd_barcode(r) for r in roots]
    allb = np.concatenate(bars)
    xlim = (float(allb[:, 0].min()), float(allb[:, 0].max()))
    ylim = (float(allb[:, 1].min()), float(allb[:, 1].max()))
    span = max(xlim[1] - xlim[0], ylim[1] - ylim[0], 1e-12)
    res = complex(0, resolution)
    X, Y = np.mgrid[xlim[0] : xlim[1] : res, ylim[0] : ylim[1] : res]
    images, fallback = [], 0
    for b in bars:
        try:
            if len(b) < 3:
                raise np.linalg.LinAlgError("too few bars for a KDE")
            Z = vec.persistence_image_data(b.tolist(), xlim=list(xlim), ylim=list(ylim), resolution=resolution)
        except (np.linalg.LinAlgError, ValueError):
            sigma = 0.05 * span
            Z = np.zeros_like(X)
            for x0, y0 in b:
                Z += np.exp(-((X - x0) ** 2 + (Y - y0) ** 2) / (2 * sigma**2))
            Z = Z / Z.max()
            fallback += 1
        images.append(np.asarray(Z, np.float64))
    return TMDImages(images=np.stack(images), xlim=xlim, ylim=ylim, n_fallback=fallback)


def tmd_distance_matrix(roots, *, resolution: int = 100) -> np.ndarray:
    """(n, n) TMD distances: mean absolute difference of the roots' persistence images (as
    `tmd.Topology.distances.total_persistence_image_diff`, per pixel), common limits."""
    Z = tmd_images(roots, resolution=resolution).images.reshape(len(roots), -1)
    return np.abs(Z[:, None, :] - Z[None, :, :]).mean(axis=-1)
