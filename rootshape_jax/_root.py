"""`Root`: one unpadded root system as plain numpy polylines (the I/O-facing type)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from ._errors import InvalidRootError


def check_polyline(points: Any, *, what: str, dim: int | None = None) -> np.ndarray:
    """Return ``points`` as a float (n, d) array, or raise `InvalidRootError` naming ``what``."""
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise InvalidRootError(f"{what}: coordinates must be numbers, got dtype {arr.dtype}.")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    if arr.ndim != 2:
        raise InvalidRootError(
            f"{what}: expected an (n_points, d) array of coordinates, got shape {arr.shape}."
        )
    if arr.shape[1] not in (2, 3):
        raise InvalidRootError(
            f"{what}: points must be 2D or 3D, got d = {arr.shape[1]} (shape {arr.shape})."
        )
    if dim is not None and arr.shape[1] != dim:
        raise InvalidRootError(
            f"{what}: has dimension {arr.shape[1]} but the main root has dimension {dim}; "
            "all branches of a root must share d (store 2D data with z = 0 to mix)."
        )
    if arr.shape[0] < 2:
        raise InvalidRootError(
            f"{what}: a branch needs at least 2 points, got {arr.shape[0]}. "
            "Drop single-point branches before building a Root."
        )
    if not np.all(np.isfinite(arr)):
        bad = int(np.argmax(~np.all(np.isfinite(arr), axis=1)))
        raise InvalidRootError(
            f"{what}: coordinates contain NaN or inf (first at point {bad}). "
            "Remove or repair those points."
        )
    return arr


def project_onto_polyline(main: np.ndarray, point: np.ndarray) -> float:
    """Arc-length fraction in [0, 1] of the point of ``main`` closest to ``point``."""
    seg = np.diff(main, axis=0)
    seg_len2 = np.sum(seg * seg, axis=1)
    rel = point[None, :] - main[:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(seg_len2 > 0, np.sum(rel * seg, axis=1) / seg_len2, 0.0)
    u = np.clip(u, 0.0, 1.0)
    foot = main[:-1] + u[:, None] * seg
    best = int(np.argmin(np.sum((foot - point[None, :]) ** 2, axis=1)))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(seg_len2))])
    total = cum[-1]
    if total <= 0:
        return 0.0
    return float((cum[best] + u[best] * np.sqrt(seg_len2[best])) / total)


@dataclasses.dataclass(frozen=True, eq=False)
class Root:
    """One root system: a main root and its first-order laterals, as numpy polylines.

    **Fields**

    - `main`: (n, d) polyline of the main root, from its base (collar / seed) to its tip; d = 2 or 3.
    - `laterals`: tuple of (m_i, d) polylines, each starting at (or near) the main root.
    - `attach`: (n_laterals,) arc-length fractions in [0, 1] of each lateral's attachment point
      along the main root. When not given, it is computed by projecting each lateral's first
      point onto the main root.
    - `name`: a label (file name, plant id, ...).
    - `metadata`: free-form dict (unit, resolution, species, condition, time index, ...).
    - `children`: optional deeper topology: one `Root` per lateral whose `main` is that lateral
      and whose `laterals` are its own (order-3) children, recursively. Empty when unknown. The
      shape analysis uses main + first-order laterals only; this keeps higher orders for I/O.

    Coordinates are in physical units when known (see `metadata["unit"]`).
    """

    main: np.ndarray
    laterals: tuple[np.ndarray, ...] = ()
    attach: np.ndarray | None = None
    name: str = ""
    metadata: dict = dataclasses.field(default_factory=dict)
    children: tuple["Root", ...] = ()

    def __post_init__(self):
        label = f"root {self.name!r}" if self.name else "root"
        main = check_polyline(self.main, what=f"{label}: main root")
        if isinstance(self.laterals, np.ndarray) and self.laterals.ndim == 3:
            lats_in: Sequence = list(self.laterals)
        else:
            lats_in = self.laterals
        lats = tuple(
            check_polyline(lat, what=f"{label}: lateral {i}", dim=main.shape[1]).astype(
                main.dtype, copy=False
            )
            for i, lat in enumerate(lats_in)
        )
        if self.attach is None:
            attach = np.array([project_onto_polyline(main, lat[0]) for lat in lats], dtype=main.dtype)
        else:
            attach = np.asarray(self.attach, dtype=main.dtype).reshape(-1)
            if attach.shape[0] != len(lats):
                raise InvalidRootError(
                    f"{label}: {attach.shape[0]} attachment fractions for {len(lats)} laterals; "
                    "give one per lateral, or attach=None to compute them by projection."
                )
            if not np.all(np.isfinite(attach)) or np.any(attach < 0) or np.any(attach > 1):
                raise InvalidRootError(
                    f"{label}: attachment fractions must lie in [0, 1] (arc-length fraction "
                    f"along the main root), got {attach.tolist()}."
                )
        if self.children and len(self.children) != len(lats):
            raise InvalidRootError(
                f"{label}: `children` must hold one entry per lateral ({len(lats)}), "
                f"got {len(self.children)}."
            )
        object.__setattr__(self, "main", main)
        object.__setattr__(self, "laterals", lats)
        object.__setattr__(self, "attach", attach)
        object.__setattr__(self, "metadata", dict(self.metadata))

    @property
    def dim(self) -> int:
        return int(self.main.shape[1])

    @property
    def n_laterals(self) -> int:
        return len(self.laterals)

    @property
    def main_length(self) -> float:
        return polyline_length(self.main)

    @property
    def lateral_lengths(self) -> np.ndarray:
        return np.array([polyline_length(lat) for lat in self.laterals], dtype=self.main.dtype)

    def scaled(self, factor: float) -> "Root":
        """The same root with every coordinate multiplied by ``factor`` (about the main base)."""
        o = self.main[0]
        return dataclasses.replace(
            self,
            main=o + (self.main - o) * factor,
            laterals=tuple(o + (lat - o) * factor for lat in self.laterals),
            children=tuple(c.scaled_about(o, factor) for c in self.children),
        )

    def scaled_about(self, origin: np.ndarray, factor: float) -> "Root":
        return dataclasses.replace(
            self,
            main=origin + (self.main - origin) * factor,
            laterals=tuple(origin + (lat - origin) * factor for lat in self.laterals),
            children=tuple(c.scaled_about(origin, factor) for c in self.children),
        )

    def __repr__(self) -> str:
        return (
            f"Root(name={self.name!r}, d={self.dim}, main_points={self.main.shape[0]}, "
            f"n_laterals={self.n_laterals}, main_length={self.main_length:.4g})"
        )


def polyline_length(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def limit_laterals(root: Root, n: int | None) -> Root:
    """The root with only its `n` longest laterals, kept in their original order.

    `n = None` (or a root with at most `n` laterals) returns `root` itself. Ties in length keep
    the earlier lateral. `Root.children` (deeper topology) is sliced alongside the laterals.
    """
    if n is None:
        return root
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"limit_laterals: n must be a whole number >= 0 or None, got {n!r}.")
    if root.n_laterals <= n:
        return root
    keep = np.sort(np.argsort(-root.lateral_lengths, kind="stable")[: int(n)])
    return dataclasses.replace(
        root,
        laterals=tuple(root.laterals[i] for i in keep),
        attach=root.attach[keep],
        children=tuple(root.children[i] for i in keep) if root.children else (),
    )
