"""`Root`: one unpadded root system as plain numpy polylines (the I/O-facing type)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ._errors import CoordinateRangeError, InvalidRootError


def coordinate_limit(dtype: Any, n_points: int = 1) -> float:
    """Largest coordinate magnitude that computations in ``dtype`` with ``n_points`` points per
    branch can square without overflow: SRVFs square derivatives ~ ``n_points × |x|``, and
    rotations sum ``n_points`` squared coordinates. ``sqrt(max) / (16 n_points)``: about
    1e16 for float32 and 8e150 for float64 at ``n_points = 100``."""
    return float(np.sqrt(np.finfo(dtype).max)) / (16.0 * max(int(n_points), 1))


# A `Root` is checked in float64 (its numpy arithmetic); `batch` checks its own dtype and T.
ROOT_COORDINATE_LIMIT = coordinate_limit(np.float64, 1)


def check_range(points: np.ndarray, *, limit: float, what: str, fix: str) -> None:
    """Raise `CoordinateRangeError` naming ``what`` when ``|points|`` exceeds ``limit``."""
    big = float(np.max(np.abs(points))) if points.size else 0.0
    if not big <= limit:
        raise CoordinateRangeError(
            f"{what}: coordinates reach {big:.3g}, beyond {limit:.3g}, the largest magnitude whose "
            f"squared lengths stay finite in the working precision. {fix}"
        )


def check_polyline(points: Any, *, what: str, dim: int | None = None) -> np.ndarray:
    """Return ``points`` as a float (n, d) array, or raise `InvalidRootError` naming ``what``."""
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise InvalidRootError(f"{what}: coordinates must be numbers, got dtype {arr.dtype}.")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    if arr.ndim != 2:
        raise InvalidRootError(f"{what}: expected an (n_points, d) array of coordinates, got shape {arr.shape}.")
    if arr.shape[1] not in (2, 3):
        raise InvalidRootError(f"{what}: points must be 2D or 3D, got d = {arr.shape[1]} (shape {arr.shape}).")
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
            f"{what}: coordinates contain NaN or inf (first at point {bad}). Remove or repair those points."
        )
    check_range(
        arr,
        limit=ROOT_COORDINATE_LIMIT,
        what=what,
        fix="Rescale the coordinates (e.g. express them in another unit) before building a Root.",
    )
    return arr


def check_radius(radius: Any, *, n_points: int, what: str) -> np.ndarray:
    """Return ``radius`` as a float (n_points,) array, or raise `InvalidRootError` naming ``what``."""
    arr = np.asarray(radius)
    if arr.dtype.kind not in "fiu":
        raise InvalidRootError(f"{what}: radii must be numbers, got dtype {arr.dtype}.")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    if arr.shape != (n_points,):
        raise InvalidRootError(
            f"{what}: expected one radius per point, shape ({n_points},), got shape {arr.shape}. "
            "Give the radius at each polyline point (or None when it is unknown)."
        )
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        bad = int(np.argmax(~(np.isfinite(arr) & (arr >= 0))))
        raise InvalidRootError(
            f"{what}: radii must be finite and >= 0, got {arr[bad]!r} at point {bad}. "
            "Repair that value, or pass None when the radius is unknown."
        )
    check_range(arr, limit=ROOT_COORDINATE_LIMIT, what=what, fix="Rescale the radii with the coordinates.")
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
      and whose `laterals` are its own (second-order) laterals, recursively. Empty when unknown.
      `batch(..., depth=3)` (or more) brings these orders into the padded tree (`RootTree.deeper`);
      the default depth 2 uses main + first-order laterals only. Each child carries its own radii
      (`main_radius` = that lateral's radii, `lateral_radii` = its laterals').
    - `main_radius`: optional (n,) radius of the root at each main-root point, in the unit of the
      coordinates; ``None`` when unknown.
    - `lateral_radii`: optional tuple of (m_i,) radii, one array per lateral; ``None`` when
      unknown.

    Coordinates are in physical units when known (see `metadata["unit"]`).
    """

    main: np.ndarray
    laterals: tuple[np.ndarray, ...] = ()
    attach: np.ndarray | None = None
    name: str = ""
    metadata: dict = dataclasses.field(default_factory=dict)
    children: tuple["Root", ...] = ()
    main_radius: np.ndarray | None = None
    lateral_radii: tuple[np.ndarray, ...] | None = None

    def __post_init__(self):
        label = f"root {self.name!r}" if self.name else "root"
        main = check_polyline(self.main, what=f"{label}: main root")
        if isinstance(self.laterals, np.ndarray) and self.laterals.ndim == 3:
            lats_in: Sequence = list(self.laterals)
        else:
            lats_in = self.laterals
        lats = tuple(
            check_polyline(lat, what=f"{label}: lateral {i}", dim=main.shape[1]).astype(main.dtype, copy=False)
            for i, lat in enumerate(lats_in)
        )
        if self.attach is None:
            attach = np.array([project_onto_polyline(main, lat[0]) for lat in lats], dtype=main.dtype)
        else:
            try:
                attach = np.asarray(self.attach, dtype=main.dtype).reshape(-1)
            except (TypeError, ValueError):
                raise InvalidRootError(
                    f"{label}: attach must hold numbers (arc-length fractions in [0, 1]), got {self.attach!r}."
                ) from None
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
        if isinstance(self.children, Root) or not isinstance(self.children, (tuple, list)):
            raise InvalidRootError(
                f"{label}: `children` must be a tuple of Roots, one per lateral, got {type(self.children).__name__}."
            )
        if self.children and len(self.children) != len(lats):
            raise InvalidRootError(
                f"{label}: `children` must hold one entry per lateral ({len(lats)}), got {len(self.children)}."
            )
        bad = [i for i, c in enumerate(self.children) if not isinstance(c, Root)]
        if bad:
            raise InvalidRootError(
                f"{label}: children {bad[:5]} are not Roots (got {type(self.children[bad[0]]).__name__}); each "
                "child is the lateral as a Root with its own laterals."
            )
        if not isinstance(self.metadata, Mapping):
            raise InvalidRootError(f"{label}: metadata must be a dict, got {type(self.metadata).__name__}.")
        main_radius = None
        if self.main_radius is not None:
            main_radius = check_radius(
                self.main_radius, n_points=main.shape[0], what=f"{label}: main root radius"
            ).astype(main.dtype, copy=False)
        lateral_radii = None
        if self.lateral_radii is not None:
            radii_in = list(self.lateral_radii)
            if len(radii_in) != len(lats):
                raise InvalidRootError(
                    f"{label}: {len(radii_in)} lateral radius arrays for {len(lats)} laterals; "
                    "give one (m_i,) array per lateral, or lateral_radii=None when unknown."
                )
            lateral_radii = tuple(
                check_radius(r, n_points=lat.shape[0], what=f"{label}: lateral {i} radius").astype(
                    main.dtype, copy=False
                )
                for i, (r, lat) in enumerate(zip(radii_in, lats))
            )
        object.__setattr__(self, "main", main)
        object.__setattr__(self, "laterals", lats)
        object.__setattr__(self, "main_radius", main_radius)
        object.__setattr__(self, "lateral_radii", lateral_radii)
        object.__setattr__(self, "attach", attach)
        object.__setattr__(self, "metadata", dict(self.metadata))
        object.__setattr__(self, "children", tuple(self.children))

    @property
    def dim(self) -> int:
        return int(self.main.shape[1])

    @property
    def n_laterals(self) -> int:
        return len(self.laterals)

    @property
    def has_radius(self) -> bool:
        """True when any radius data (main root or laterals) is known."""
        return self.main_radius is not None or self.lateral_radii is not None

    @property
    def main_length(self) -> float:
        return polyline_length(self.main)

    @property
    def lateral_lengths(self) -> np.ndarray:
        return np.array([polyline_length(lat) for lat in self.laterals], dtype=self.main.dtype)

    def scaled(self, factor: float) -> "Root":
        """The same root with every coordinate multiplied by ``factor`` (about the main base).
        Radii are multiplied by ``|factor|``."""
        return self.scaled_about(self.main[0], factor)

    def scaled_about(self, origin: np.ndarray, factor: float) -> "Root":
        f = abs(float(factor))
        return dataclasses.replace(
            self,
            main=origin + (self.main - origin) * factor,
            laterals=tuple(origin + (lat - origin) * factor for lat in self.laterals),
            children=tuple(c.scaled_about(origin, factor) for c in self.children),
            main_radius=None if self.main_radius is None else self.main_radius * f,
            lateral_radii=(None if self.lateral_radii is None else tuple(r * f for r in self.lateral_radii)),
        )

    def select_laterals(self, indices: Sequence[int]) -> "Root":
        """The same root keeping only the laterals at ``indices`` (with their attachments,
        children and radii), in the order given."""
        idx = [int(i) for i in indices]
        return dataclasses.replace(
            self,
            laterals=tuple(self.laterals[i] for i in idx),
            attach=self.attach[idx] if idx else np.zeros((0,), self.main.dtype),
            children=tuple(self.children[i] for i in idx) if self.children else (),
            lateral_radii=(None if self.lateral_radii is None else tuple(self.lateral_radii[i] for i in idx)),
        )

    def __repr__(self) -> str:
        return (
            f"Root(name={self.name!r}, d={self.dim}, main_points={self.main.shape[0]}, "
            f"n_laterals={self.n_laterals}, main_length={self.main_length:.4g})"
        )


def polyline_length(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def is_plant_system(root: "Root") -> bool:
    """True for a plant's system (`rootshape_jax.io.plant_system`): marked by it
    (``metadata["virtual_main"]``), or a zero-length main root with laterals (a real root read
    from a file never has zero length; a mean or mode of systems has)."""
    return bool(root.metadata.get("virtual_main")) or (
        root.n_laterals > 0 and polyline_length(np.asarray(root.main, dtype=np.float64)) == 0.0
    )


def plant_axes(plant: "Root") -> tuple["Root", ...]:
    """The axes of a plant's system, one `Root` per lateral slot: its child (with the axis's
    own laterals), or the bare polyline as a root when the system has no children."""
    if plant.children:
        return tuple(plant.children)
    return tuple(Root(main=lat) for lat in plant.laterals)


def limit_laterals(root: Root, n: int | None) -> Root:
    """The root with only its `n` longest laterals, kept in their original order.

    `n = None` (or a root with at most `n` laterals) returns `root` itself. Ties in length keep
    the earlier lateral. `Root.children` (deeper topology) and radii are sliced alongside the
    laterals.
    """
    if n is None:
        return root
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"limit_laterals: n must be a whole number >= 0 or None, got {n!r}.")
    if root.n_laterals <= n:
        return root
    keep = np.sort(np.argsort(-root.lateral_lengths, kind="stable")[: int(n)])
    return root.select_laterals(keep)
