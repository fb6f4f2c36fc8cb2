"""Padded, fixed-size root trees: `RootTree` (geometry) and `SRVFTree` (shape).

Both are frozen `eqx.Module`s whose array leaves have fixed capacities — ``T`` points per
branch and ``K`` lateral slots — so every computation on them compiles once per (T, K, d, dtype)
and vmaps over batches. A batch is the same Module with a leading axis on every leaf.

Padding: a slot with ``mask = False`` is one of the paper's *null* (virtual) laterals. It holds
finite zeros in the SRVF (``q = 0``) and, in a `RootTree`, a lateral collapsed to its attachment
point. Never NaN: a NaN in a masked branch of ``jnp.where`` still poisons gradients.

Deeper orders (docs/design.md §11): a tree of depth ``D > 2`` carries levels ℓ = 2 … D−1 of
laterals (second-order laterals and below) in `deeper`, one padded `BranchLevel` (geometry) or
`SRVFLevel` (shape) per level, shaped ``[K1, …, Kℓ, T, d]``. A depth-2 tree has ``deeper = ()``
and is exactly the paper's main root + first-order laterals.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._curves import interpolate_at_fraction, require_finite, srvf, srvf_to_curve
from ._errors import (
    CapacityError,
    InvalidRootError,
    MissingRadiusWarning,
    UnitError,
    as_count,
    as_flag,
    user_stacklevel,
)
from ._root import Root, check_range, coordinate_limit, is_plant_system, polyline_length
from ._thickness import extended_srvf, integrate_branch, wants_thickness
from ._traits import deepest_order
from ._units import check_unit_name, unit_key


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray))


class BranchLevel(eqx.Module):
    """One deeper level ℓ ≥ 2 of a `RootTree`: the children of the level-(ℓ−1) branches, padded.

    Level 1 is `RootTree.laterals` (children of the main root); level 2 holds the laterals of
    those laterals, and so on. Write ``P = (K1, …, K(ℓ−1))`` for the parent slots and ``Kℓ``
    for this level's capacity of children per parent slot.

    **Fields** (a batch adds leading axes ``*B`` to every field)

    - `curves`: ``[*P, Kℓ, T, d]`` child branches, each starting at its parent's point at
      `attach` (``T`` points uniform in arc length). Null slots are collapsed to their parent's
      first point.
    - `attach`: ``[*P, Kℓ]`` arc-length fraction in [0, 1] of the attachment point along the
      parent branch (0 in null slots).
    - `mask`: ``[*P, Kℓ]`` True for real branches. A child slot of a null parent is null.
    - `radius`: ``[*P, Kℓ, T]`` radius along each child (0 in null slots), or ``None``; set
      exactly when the tree's `RootTree.main_radius` is.
    """

    curves: Float[Array, "*B *P K T d"]
    attach: Float[Array, "*B *P K"]
    mask: Bool[Array, "*B *P K"]
    radius: Float[Array, "*B *P K T"] | None = None

    def __check_init__(self):
        _check_level("BranchLevel", self.curves, self.attach, self.mask, "curves", "attach")
        if self.radius is not None and _is_array(self.radius) and _is_array(self.curves):
            if self.radius.shape != self.curves.shape[:-1]:
                raise ValueError(
                    f"BranchLevel: radius has shape {self.radius.shape}, expected {self.curves.shape[:-1]} "
                    "(one radius per point of each child, 0 in null slots)."
                )

    @property
    def capacity(self) -> int:
        return self.mask.shape[-1]


class SRVFLevel(eqx.Module):
    """One deeper level ℓ ≥ 2 of an `SRVFTree` (the shape of a `BranchLevel`).

    **Fields** (``*P`` the parent slots ``K1, …, K(ℓ−1)``; a batch adds ``*B`` in front)

    - `q`: ``[*P, Kℓ, T, C]`` SRVFs of the children; null slots are exactly 0. ``C = d``, or
      ``d + 1`` with a thickness channel (as in `SRVFTree`).
    - `s`: ``[*P, Kℓ]`` attachment arc-length fractions along the parent branch.
    - `mask`: ``[*P, Kℓ]`` True for real branches; a child slot of a null parent is null.
    - `base_radius`: ``[*P, Kℓ]`` starting radius of each child, present exactly when the tree
      has a thickness channel; otherwise None.
    """

    q: Float[Array, "*B *P K T C"]
    s: Float[Array, "*B *P K"]
    mask: Bool[Array, "*B *P K"]
    base_radius: Float[Array, "*B *P K"] | None = None

    def __check_init__(self):
        _check_level("SRVFLevel", self.q, self.s, self.mask, "q", "s")
        if self.base_radius is not None and _is_array(self.base_radius) and _is_array(self.mask):
            if self.base_radius.shape != self.mask.shape:
                raise ValueError(
                    f"SRVFLevel: base_radius has shape {self.base_radius.shape}, expected {self.mask.shape}."
                )

    @property
    def capacity(self) -> int:
        return self.mask.shape[-1]


def _check_level(cls, curves, attach, mask, curves_name, attach_name):
    if not all(_is_array(x) for x in (curves, attach, mask)):
        return
    if curves.ndim < 3 or curves.shape[:-2] != mask.shape:
        raise ValueError(f"{cls}: {curves_name} has shape {curves.shape}, expected mask's shape {mask.shape} + (T, d).")
    if attach.shape != mask.shape:
        raise ValueError(f"{cls}: {attach_name} has shape {attach.shape}, expected {mask.shape} (the mask's).")
    if mask.dtype != jnp.bool_:
        raise ValueError(f"{cls}: mask must be boolean, got {mask.dtype}.")


def _check_deeper(cls, parent_curves, parent_mask, deeper, level_cls, curves_of, *, radius: bool | None):
    """Each level's slots nest in the previous level's, with the same ``T`` and channels, and
    no real child under a null parent (checked when the values are concrete)."""
    if not isinstance(deeper, tuple):
        raise ValueError(f"{cls}: deeper must be a tuple of {level_cls.__name__}, got {type(deeper).__name__}.")
    for i, level in enumerate(deeper):
        if not isinstance(level, level_cls):
            raise ValueError(f"{cls}: deeper[{i}] is a {type(level).__name__}, expected a {level_cls.__name__}.")
        if radius is not None and (level_radius(level) is not None) != radius:
            raise ValueError(
                f"{cls}: deeper[{i}] (level {i + 2}) must carry radii exactly when the tree does "
                "(pass zeros for branches whose radius is unknown)."
            )
    prev_curves, prev_mask = parent_curves, parent_mask
    for i, level in enumerate(deeper):
        curves = curves_of(level)
        if not all(_is_array(x) for x in (prev_curves, prev_mask, curves, level.mask)):
            return
        if level.mask.shape[:-1] != prev_mask.shape:
            raise ValueError(
                f"{cls}: level {i + 2} has slots {level.mask.shape}, expected the parent level's "
                f"{prev_mask.shape} + (K{i + 2},)."
            )
        if curves.shape[-2:] != prev_curves.shape[-2:]:
            raise ValueError(
                f"{cls}: level {i + 2} branches have (T, channels) = {curves.shape[-2:]}, expected "
                f"{prev_curves.shape[-2:]} as in the level above."
            )
        if not isinstance(level.mask, jax.core.Tracer) and not isinstance(prev_mask, jax.core.Tracer):
            orphan = np.asarray(level.mask) & ~np.asarray(prev_mask)[..., None]
            if np.any(orphan):
                raise ValueError(
                    f"{cls}: level {i + 2} has real branches under null parent slots "
                    f"(first at {tuple(int(v) for v in np.argwhere(orphan)[0])}); a null branch has no children."
                )
        prev_curves, prev_mask = curves, level.mask


def level_radius(level):
    """The radius data of a level (`BranchLevel.radius` or `SRVFLevel.base_radius`)."""
    return level.radius if isinstance(level, BranchLevel) else level.base_radius


class RootTree(eqx.Module):
    """Geometry of a root (or a batch of roots) resampled onto fixed capacities.

    **Fields** (a batch adds leading axes ``*B`` to every field)

    - `main`: ``[T, d]`` main root, ``T`` points uniform in arc length from base to tip.
    - `laterals`: ``[K, T, d]`` lateral roots, each starting at the main root point at `attach`.
      Null slots (``mask = False``) are collapsed to a single repeated point.
    - `attach`: ``[K]`` arc-length fraction in [0, 1] of each lateral's attachment point.
    - `mask`: ``[K]`` True for real laterals, False for padding (null laterals).
    - `main_radius`: ``[T]`` radius of the main root at each point (same unit as the
      coordinates), or ``None`` when the batch has no radius data at all.
    - `lateral_radius`: ``[K, T]`` radius of each lateral at each point, or ``None`` (set
      together with `main_radius`).

    - `deeper`: ``()`` for the paper's depth-2 tree; otherwise one `BranchLevel` per deeper
      level ℓ = 2 … D−1 (second-order laterals, their laterals, ...), level ℓ shaped
      ``[K1, …, Kℓ, T, d]`` (docs/design.md §11). ``depth = 2 + len(deeper)``.
    - `virtual_main` (static): True for plants' systems (`rootshape_jax.io.plant_system`,
      ``read_rsml(by="plant")``): the main root is a virtual one of zero length and the level-1
      branches are the plant's axes. Registration then weighs the axes as main roots and each
      deeper level as the level above it (`rootshape_jax.Weights`, docs/design.md §11), so one
      axis per plant is exactly the taproot analysis. `batch` sets it.

    Radius padding: null slots have radius 0; so does every branch of a root that came without
    radius data in a batch where other roots have it (`batch` warns and names those roots).
    """

    main: Float[Array, "*B T d"]
    laterals: Float[Array, "*B K T d"]
    attach: Float[Array, "*B K"]
    mask: Bool[Array, "*B K"]
    main_radius: Float[Array, "*B T"] | None = None
    lateral_radius: Float[Array, "*B K T"] | None = None
    deeper: tuple[BranchLevel, ...] = ()
    virtual_main: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        _check_shapes("RootTree", self.main, self.laterals, self.attach, self.mask, names=("main", "laterals"))
        _check_radius_shapes("RootTree", self.main, self.laterals, self.main_radius, self.lateral_radius)
        _check_deeper(
            "RootTree",
            self.laterals,
            self.mask,
            self.deeper,
            BranchLevel,
            lambda lv: lv.curves,
            radius=self.main_radius is not None,
        )

    @property
    def depth(self) -> int:
        """2 for main root + first-order laterals; 3 with second-order laterals; ..."""
        return 2 + len(self.deeper)

    @property
    def capacities(self) -> tuple[int, ...]:
        """``(K1, …, K(D−1))``: child slots per parent slot at each level."""
        return (self.capacity,) + tuple(lv.capacity for lv in self.deeper)

    @property
    def n_points(self) -> int:
        return self.main.shape[-2]

    @property
    def capacity(self) -> int:
        return self.laterals.shape[-3]

    @property
    def dim(self) -> int:
        return self.main.shape[-1]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.main.shape[:-2])


class SRVFTree(eqx.Module):
    """Shape of a root (or a batch): the SRVF tree of docs/design.md §2.

    **Fields** (a batch adds leading axes ``*B`` to every field)

    - `q0`: ``[T, d]`` SRVF of the main root.
    - `q`: ``[K, T, d]`` SRVFs of the laterals; null slots are exactly 0.
    - `s`: ``[K]`` attachment arc-length fractions along the main root.
    - `mask`: ``[K]`` True for real laterals.
    - `origin`: ``[d]`` start of the main root (SRVFs forget translation; kept to rebuild curves).
    - `base_radius`, `thickness_scale`: present only with a thickness channel (docs/design.md §11,
      `Weights.thickness` > 0 and radii in the data): then `q0` and `q` have ``d + 1``
      channels, the last being the SRVF channel of ``c·r`` with ``c = thickness_scale``
      (``√λr``), and `base_radius` ``[K + 1]`` holds the starting radius of the main root
      (slot 0) and of each lateral, which the SRVF forgets. Otherwise both are None.
    - `deeper`: ``()`` at depth 2; otherwise one `SRVFLevel` per deeper level ℓ = 2 … D−1,
      shaped ``[K1, …, Kℓ, T, C]`` (with their own `SRVFLevel.base_radius` under a thickness
      channel).
    - `virtual_main` (static): a plant's system, as in `RootTree` (kept by `to_srvf` and
      `to_curves`).
    """

    q0: Float[Array, "*B T C"]
    q: Float[Array, "*B K T C"]
    s: Float[Array, "*B K"]
    mask: Bool[Array, "*B K"]
    origin: Float[Array, "*B d"]
    base_radius: Float[Array, "*B K1"] | None = None
    thickness_scale: Float[Array, "*B"] | None = None
    deeper: tuple[SRVFLevel, ...] = ()
    virtual_main: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        _check_shapes("SRVFTree", self.q0, self.q, self.s, self.mask, names=("q0", "q"))
        _check_deeper(
            "SRVFTree",
            self.q,
            self.mask,
            self.deeper,
            SRVFLevel,
            lambda lv: lv.q,
            radius=self.thickness_scale is not None,
        )
        if (self.base_radius is None) != (self.thickness_scale is None):
            raise ValueError("SRVFTree: give both base_radius and thickness_scale, or neither.")
        if _is_array(self.origin) and _is_array(self.q0):
            extra = 0 if self.thickness_scale is None else 1
            if self.origin.shape != self.q0.shape[:-2] + (self.q0.shape[-1] - extra,):
                raise ValueError(
                    f"SRVFTree: origin has shape {self.origin.shape}, expected "
                    f"{self.q0.shape[:-2] + (self.q0.shape[-1] - extra,)} (batch + (d,))."
                )

    @property
    def n_points(self) -> int:
        return self.q0.shape[-2]

    @property
    def capacity(self) -> int:
        return self.q.shape[-3]

    @property
    def dim(self) -> int:
        """Spatial dimension d (a thickness channel, when present, comes on top)."""
        return self.origin.shape[-1]

    @property
    def has_thickness(self) -> bool:
        return self.thickness_scale is not None

    @property
    def depth(self) -> int:
        """2 for main root + first-order laterals; 3 with second-order laterals; ..."""
        return 2 + len(self.deeper)

    @property
    def capacities(self) -> tuple[int, ...]:
        """``(K1, …, K(D−1))``: child slots per parent slot at each level."""
        return (self.capacity,) + tuple(lv.capacity for lv in self.deeper)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.q0.shape[:-2])


def _check_shapes(cls, main, lats, attach, mask, *, names):
    if not all(_is_array(x) for x in (main, lats, attach, mask)):
        return  # leaves replaced by placeholders (e.g. inside jax transformations)
    if main.ndim < 2 or main.shape[-1] not in (2, 3, 4):
        raise ValueError(f"{cls}: {names[0]} must be (..., T, d) with d in (2, 3), got {main.shape}.")
    batch = main.shape[:-2]
    T, d = main.shape[-2:]
    if lats.ndim != main.ndim + 1 or lats.shape[:-3] != batch or lats.shape[-2:] != (T, d):
        raise ValueError(
            f"{cls}: {names[1]} has shape {lats.shape}, expected {batch} + (K, {T}, {d}) to match "
            f"{names[0]} {main.shape}."
        )
    K = lats.shape[-3]
    for nm, x in (("attach" if cls == "RootTree" else "s", attach), ("mask", mask)):
        if x.shape != batch + (K,):
            raise ValueError(f"{cls}: {nm} has shape {x.shape}, expected {batch + (K,)}.")
    if mask.dtype != jnp.bool_:
        raise ValueError(f"{cls}: mask must be boolean, got {mask.dtype}.")


def _check_radius_shapes(cls, main, lats, main_radius, lateral_radius):
    """Radii are both None or both arrays shaped like the coordinates without ``d``."""
    if (main_radius is None) != (lateral_radius is None):
        raise ValueError(
            f"{cls}: main_radius and lateral_radius must be given together (both None means no "
            "radius data); pass zeros for the branches whose radius is unknown."
        )
    if main_radius is None:
        return
    if not all(_is_array(x) for x in (main, lats, main_radius, lateral_radius)):
        return
    if main_radius.shape != main.shape[:-1]:
        raise ValueError(
            f"{cls}: main_radius has shape {main_radius.shape}, expected {main.shape[:-1]} "
            "(one radius per main-root point)."
        )
    if lateral_radius.shape != lats.shape[:-1]:
        raise ValueError(
            f"{cls}: lateral_radius has shape {lateral_radius.shape}, expected {lats.shape[:-1]} "
            "(one radius per lateral point, 0 in null slots)."
        )
    for nm, r in (("main_radius", main_radius), ("lateral_radius", lateral_radius)):
        if not jnp.issubdtype(r.dtype, jnp.floating):
            raise ValueError(f"{cls}: {nm} must be a float array, got dtype {r.dtype}.")


# --------------------------------------------------------------------------------------------
# Root (numpy, unpadded) <-> RootTree (padded)


def resample_polyline(points: np.ndarray, n_points: int) -> np.ndarray:
    """numpy: resample a polyline to ``n_points`` points uniform in arc length."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return np.repeat(points[:1], n_points, axis=0)
    keep = np.concatenate([[True], seg > 0])  # drop repeated points so cum is increasing
    cum, pts = cum[keep], points[keep]
    target = np.linspace(0.0, cum[-1], n_points)
    return np.stack([np.interp(target, cum, pts[:, k]) for k in range(points.shape[1])], axis=1)


def resample_values(points: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """numpy: values carried by the points of a polyline (e.g. radii), at the ``n_points``
    points of `resample_polyline` (linear in arc length, same repeated-point handling)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return np.repeat(values[:1], n_points, axis=0)
    keep = np.concatenate([[True], seg > 0])
    cum, vals = cum[keep], values[keep]
    target = np.linspace(0.0, cum[-1], n_points)
    return np.interp(target, cum, vals)


def _point_at_fraction(main: np.ndarray, fraction: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(main, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return main[0]
    target = fraction * cum[-1]
    return np.array([np.interp(target, cum, main[:, k]) for k in range(main.shape[1])])


def normalising_length(root: Root, n_points: int) -> float:
    """The length `batch(normalise_scale=True)` divides `root` by: its main root's, resampled at
    `n_points` (so the padded tree's main root has length 1). A plant's virtual main root
    (several axes, docs/design.md §11) has length 0: its longest axis sets the scale, as the one
    axis of a taproot system would. 0 when the root has no length at all."""
    length = polyline_length(resample_polyline(root.main.astype(np.float64), n_points))
    if length <= 0 and root.n_laterals:
        length = max(polyline_length(resample_polyline(lat.astype(np.float64), n_points)) for lat in root.laterals)
    return length


def root_to_arrays(
    root: Root, *, n_points: int, capacity: int, normalise_scale: bool = False, dtype=np.float64
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """numpy arrays (main, laterals, attach, mask) for one root at the given capacities."""
    main, lats, attach, mask, _, _ = root_to_arrays_with_radius(
        root, n_points=n_points, capacity=capacity, normalise_scale=normalise_scale, dtype=dtype
    )
    return main, lats, attach, mask


def root_to_arrays_with_radius(
    root: Root, *, n_points: int, capacity: int, normalise_scale: bool = False, dtype=np.float64
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """numpy arrays (main, laterals, attach, mask, main_radius, lateral_radius) for one root.

    Radii are resampled at the same arc-length positions as the coordinates and scaled with
    them; unknown radii (and null slots) are 0. Raises `CoordinateRangeError` when the arrays
    exceed what ``dtype`` can compute with (`coordinate_limit`)."""
    return root_to_level_arrays(
        root, n_points=n_points, capacities=(capacity,), normalise_scale=normalise_scale, dtype=dtype
    )[:6]


def root_to_level_arrays(
    root: Root, *, n_points: int, capacities: tuple[int, ...], normalise_scale: bool = False, dtype=np.float64
) -> tuple:
    """`root_to_arrays_with_radius` plus the deeper levels: (main, laterals, attach, mask,
    main_radius, lateral_radius, levels) where `levels` holds one (curves, attach, mask, radius)
    tuple per level ℓ = 2 … len(capacities), built from `Root.children` (docs/design.md §11)."""
    capacity = capacities[0]
    if not isinstance(root, Root):
        raise TypeError(f"expected a rootshape_jax.Root, got {type(root).__name__}.")
    if root.n_laterals > capacity:
        raise CapacityError(
            f"root {root.name!r} has {root.n_laterals} laterals but the capacity is K = {capacity}; "
            "pass a larger `max_laterals` (registration needs K >= n_a + n_b)."
        )
    main = root.main.astype(np.float64)
    scale = 1.0
    if normalise_scale:
        length = normalising_length(root, n_points)
        if length <= 0:
            raise InvalidRootError(f"root {root.name!r}: main root has zero length; cannot normalise scale.")
        scale = 1.0 / length
    # Scaled about the coordinate origin (0, 0), not about the base: a root far from (0, 0)
    # keeps the relative precision its coordinates had (scaled about a base at 5e4 µm, a
    # length-1 root keeps ~2 digits in float32). Back in place: `scale_tree(..., base=...)`.
    main = main * scale
    d = main.shape[1]
    main_resampled = resample_polyline(main, n_points)
    main_radius = np.zeros((n_points,))
    if root.main_radius is not None:
        main_radius = resample_values(main, root.main_radius.astype(np.float64) * scale, n_points)
    lats = np.zeros((capacity, n_points, d))
    lat_radius = np.zeros((capacity, n_points))
    attach = np.zeros((capacity,))
    mask = np.zeros((capacity,), dtype=bool)
    placed = []  # each lateral's polyline joined to the main root, before the resampling shift
    for k, (lat, s) in enumerate(zip(root.laterals, root.attach)):
        lat = lat.astype(np.float64) * scale
        radius = None
        if root.lateral_radii is not None:
            radius = root.lateral_radii[k].astype(np.float64) * scale
        base = _point_at_fraction(main, float(s))
        # A lateral emerges from the main root: join its first point to the attachment point.
        if np.linalg.norm(lat[0] - base) > 1e-9 * max(1.0, np.abs(main).max()):
            lat = np.concatenate([base[None], lat], axis=0)
            if radius is not None:  # the joining segment has the lateral's base radius
                radius = np.concatenate([radius[:1], radius])
        # Resampling the main root moves its points slightly (chords); move the lateral with it
        # so that it starts exactly at the resampled main root's point at `attach`.
        placed.append(lat)
        lat = lat + (_point_at_fraction(main_resampled, float(s)) - base)
        lats[k] = resample_polyline(lat, n_points)
        if radius is not None:
            lat_radius[k] = resample_values(lat, radius, n_points)
        attach[k] = s
        mask[k] = True
    for k in range(root.n_laterals, capacity):
        lats[k] = np.repeat(main_resampled[:1], n_points, axis=0)
    levels = _deeper_levels(root, placed, lats, capacities, n_points=n_points, scale=scale)
    # Checked in float64, before the cast (which would overflow to inf with a warning).
    limit = coordinate_limit(dtype, n_points)
    label = f"root {root.name!r}" if root.name else "root"
    deeper_checks = []
    for i, (curves, _, _, radius) in enumerate(levels):
        deeper_checks += [(curves, f"level-{i + 2} laterals"), (radius, f"level-{i + 2} radii")]
    for x, what in (
        (main_resampled, "main root"),
        (lats, "laterals"),
        (main_radius, "main radius"),
        (lat_radius, "lateral radii"),
        *deeper_checks,
    ):
        check_range(
            x,
            limit=limit,
            what=f"{label}: {what}",
            fix=f"With dtype={np.dtype(dtype).name} and n_points={n_points}, rescale the "
            "coordinates (another unit, or normalise_scale=True), or use dtype=float64 "
            "(jax.config.update('jax_enable_x64', True)).",
        )
    return (
        main_resampled.astype(dtype),
        lats.astype(dtype),
        attach.astype(dtype),
        mask,
        main_radius.astype(dtype),
        lat_radius.astype(dtype),
        [(c.astype(dtype), a.astype(dtype), m, r.astype(dtype)) for c, a, m, r in levels],
    )


def _deeper_levels(root, placed, lats, capacities, *, n_points, scale):
    """numpy (curves, attach, mask, radius) of levels 2 … len(capacities) for one root.

    Each child is placed as `root_to_arrays_with_radius` places a lateral on the main root: its
    first point is joined to its parent's point at its attachment fraction, then it moves with
    the parent's resampling. Joining lengthens the parent, so a grandchild's fraction (given
    along the parent's own polyline) is converted to a fraction along the joined polyline, so
    that it attaches at the same physical point."""
    d = lats.shape[-1]
    levels = []
    for ell in range(2, len(capacities) + 1):
        shape = tuple(capacities[:ell])
        levels.append(
            (
                np.zeros(shape + (n_points, d)),
                np.zeros(shape),
                np.zeros(shape, dtype=bool),
                np.zeros(shape + (n_points,)),
            )
        )
    if not levels:
        return levels

    def fill(node: Root | None, slot: tuple, parent_poly, parent_res, ell: int):
        """Children (level ell) of the branch at `slot` (level ell − 1): joined to `parent_poly`
        (the parent in the input's frame), then moved with it onto `parent_res` (resampled)."""
        curves, attach, mask, radius = levels[ell - 2]
        if node is None or node.n_laterals == 0:
            return
        if node.n_laterals > capacities[ell - 1]:
            raise CapacityError(
                f"root {root.name!r}: a level-{ell - 1} branch has {node.n_laterals} laterals but the "
                f"capacity at level {ell} is K{ell} = {capacities[ell - 1]}; pass max_children with "
                f"K{ell} >= {node.n_laterals} (registration needs twice the largest count)."
            )
        L0 = polyline_length(node.main) * scale
        L = polyline_length(parent_poly)
        joined_parent = len(parent_poly) != len(node.main)
        for k, (child, s) in enumerate(zip(node.laterals, node.attach)):
            # The fraction along the node's own polyline, moved to the joined parent polyline.
            # An unjoined parent keeps `s` bitwise (its lengths L, L0 differ in the last bit), so
            # that a one-axis plant's level 2 is exactly its taproot's laterals.
            if not L > 0:
                frac = 0.0
            elif joined_parent:
                frac = float(np.clip((L - L0 + float(s) * L0) / L, 0.0, 1.0))
            else:
                frac = float(s)
            poly = child.astype(np.float64) * scale
            rad = None if node.lateral_radii is None else node.lateral_radii[k].astype(np.float64) * scale
            base = _point_at_fraction(parent_poly, frac)
            if np.linalg.norm(poly[0] - base) > 1e-9 * max(1.0, np.abs(parent_poly).max()):
                poly = np.concatenate([base[None], poly], axis=0)
                if rad is not None:
                    rad = np.concatenate([rad[:1], rad])
            # Children are placed on this polyline before it moves with its parent's resampling
            # (their coordinates are in the frame of the input, as the parent's are).
            joined = poly
            poly = poly + (_point_at_fraction(parent_res, frac) - base)
            here = slot + (k,)
            curves[here] = resample_polyline(poly, n_points)
            if rad is not None:
                radius[here] = resample_values(poly, rad, n_points)
            attach[here] = frac
            mask[here] = True
            if ell < len(capacities):
                grand = node.children[k] if node.children else None
                fill(grand, here, joined, curves[here], ell + 1)

    def fill_nulls(slot: tuple, ell: int):
        # Every descendant slot of a null or childless branch collapses to its first point.
        if ell > len(capacities):
            return
        curves, mask = levels[ell - 2][0], levels[ell - 2][2]
        parent = lats if ell == 2 else levels[ell - 3][0]
        for k in range(capacities[ell - 1]):
            here = slot + (k,)
            if not mask[here]:
                curves[here] = parent[slot][:1]
            fill_nulls(here, ell + 1)

    for k, poly in enumerate(placed):
        node = root.children[k] if root.children else None
        fill(node, (k,), poly, lats[k], 2)
    for k in range(capacities[0]):
        fill_nulls((k,), 2)
    return levels


def batch(
    roots: Root | Sequence[Root],
    *,
    n_points: int = 100,
    max_laterals: int | None = None,
    normalise_scale: bool = False,
    dtype=None,
    depth: int | None = None,
    max_children: Sequence[int] | None = None,
) -> RootTree:
    """Resample and pad roots into one batched `RootTree` (leading axis = roots).

    - `n_points`: ``T``, points per branch (uniform in arc length).
    - `max_laterals`: ``K``, lateral slots. Default ``2 × (most laterals of any root)`` (at least
      2), enough to register any pair (docs/design.md §2).
    - `normalise_scale`: divide each root by its main-root length (the paper's scale invariance;
      leave off for growth studies), about (0, 0): the base moves to ``seed / length`` and a root
      far from (0, 0) keeps its precision. `scale_tree(..., base=...)` puts results back.
    - `dtype`: float dtype of the arrays; default JAX's default float (float32 unless x64 is on).
    - `depth`: ``D``, levels kept (docs/design.md §11): 2 = main root + first-order laterals (the
      paper's trees), 3 adds second-order laterals (from `Root.children`), and so on. Default
      (None) is 2, ignoring deeper orders silently as before; an explicit `depth`, and any
      depth for plants' systems (`read_rsml(..., by="plant")`, whose laterals are level 2),
      warns once when roots have deeper branches than it keeps, saying how many were left out.
    - `max_children`: ``(K1, …, K(D−1))``, child slots per parent slot at each level (``K1`` is
      `max_laterals`; give one or the other, or equal values). Default, level by level,
      ``2 × (most children of any branch at that level)`` (at least 2). A capacity below the
      largest count raises `CapacityError` naming the level and the capacity needed.

    Resampling cuts the corners of a polyline a little, so it is not idempotent: a tree
    written out (`to_roots`, `write_rsml`) and batched again at the same `n_points` moves by a
    fraction of a segment (on the plate tracings at T = 50: 0.5 px on main roots, 1.5 px on
    laterals, for 10.6 px segments; distances 0.9 %). Analyse the original tracings, not
    resampled results.

    Radii (`Root.main_radius`, `Root.lateral_radii`) are resampled like the coordinates (and
    scaled with them by `normalise_scale`) into `RootTree.main_radius` / `lateral_radius`. If
    no root has radius data both fields are ``None``; if only some have, the others get radius
    0 and a warning names them.

    Raises `UnitError` for roots in different units (``metadata["unit"]``; convert them with
    `rootshape_jax.io.convert_units`, or pass ``normalise_scale=True`` to compare shapes only),
    ``ValueError`` for a dtype other than float32 / float64 (float16 rounds small distances to
    0) and for float64 while JAX's 64-bit mode is off, and `CoordinateRangeError` (naming the
    root and the fix) for coordinates whose squared lengths would overflow ``dtype``
    (`coordinate_limit`: about 1e16 in float32 and 8e150 in float64 at ``n_points = 100``).

    A single `Root` gives an unbatched `RootTree`.
    """
    single = isinstance(roots, Root)
    roots_list = [roots] if single else list(roots)
    if not roots_list:
        raise ValueError("batch() needs at least one Root; got an empty sequence.")
    for i, r in enumerate(roots_list):
        if not isinstance(r, Root):
            raise TypeError(f"batch(): item {i} is a {type(r).__name__}, expected a Root.")
    dims = {r.dim for r in roots_list}
    if len(dims) != 1:
        raise InvalidRootError(f"batch(): roots mix dimensions {sorted(dims)}; convert 2D roots to 3D (z = 0) first.")
    normalise_scale = as_flag(normalise_scale, "batch(): normalise_scale")
    if not normalise_scale:
        _check_units(roots_list)
    n_points = as_count(n_points, "n_points", minimum=2)
    explicit_depth = depth is not None
    depth = 2 if depth is None else depth
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 2:
        raise ValueError(f"batch(): depth must be an integer >= 2 (2 = main root + laterals), got {depth!r}.")
    depth = int(depth)
    counts = [max(levels) for levels in zip(*(_children_counts(r, depth) for r in roots_list))]
    capacities = _capacities(counts, depth, max_laterals, max_children)
    if max_laterals is None:
        max_laterals = capacities[0]
    if explicit_depth or is_plant_system(roots_list[0]):
        # A plant's system at the default depth keeps its axes only: every lateral would be
        # dropped without a word, so plants always get the warning.
        _warn_truncated(roots_list, depth)
    if dtype is None:
        dtype = jnp.zeros(()).dtype  # JAX's default float: respects jax_enable_x64
    dtype = _working_dtype(dtype)
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        # JAX would store float32 without a word, after the precision check ran on float64.
        raise ValueError(
            "batch(): dtype=float64 needs JAX's 64-bit mode, which is off; turn it on first with "
            "jax.config.update('jax_enable_x64', True), or leave dtype out (float32)."
        )
    arrays = [
        root_to_level_arrays(r, n_points=n_points, capacities=capacities, normalise_scale=normalise_scale, dtype=dtype)
        for r in roots_list
    ]
    main, lats, attach, mask, main_r, lat_r = (np.stack(a) for a in list(zip(*arrays))[:6])
    _warn_imprecise(roots_list, main, lats)
    has_radius = any(_has_radius(r, depth) for r in roots_list)
    radii = {}
    if has_radius:
        _warn_missing_radius(roots_list)
        radii = dict(main_radius=jnp.asarray(main_r), lateral_radius=jnp.asarray(lat_r))
    deeper = []
    for i in range(depth - 2):
        curves, s_, m, r = (np.stack(x) for x in zip(*(a[6][i] for a in arrays)))
        deeper.append(
            BranchLevel(
                curves=jnp.asarray(curves),
                attach=jnp.asarray(s_),
                mask=jnp.asarray(m),
                radius=jnp.asarray(r) if has_radius else None,
            )
        )
    tree = RootTree(
        jnp.asarray(main),
        jnp.asarray(lats),
        jnp.asarray(attach),
        jnp.asarray(mask),
        **radii,
        deeper=tuple(deeper),
        virtual_main=_virtual_main(roots_list),
    )
    return unstack(tree)[0] if single else tree


def _virtual_main(roots: Sequence[Root]) -> bool:
    flags = [is_plant_system(r) for r in roots]
    if any(flags) and not all(flags):
        systems = [_root_label(r, i) for i, r in enumerate(roots) if flags[i]][:3]
        single = [_root_label(r, i) for i, r in enumerate(roots) if not flags[i]][:3]
        raise InvalidRootError(
            f"batch(): the roots mix plants' systems (a virtual main root, e.g. {', '.join(systems)}) "
            f"with single roots (e.g. {', '.join(single)}); they cannot be compared. Read every file "
            "with the same `by` (read_rsml(path, by='plant') for all), or wrap single roots with "
            "rootshape_jax.io.plant_system([root])."
        )
    return bool(flags and flags[0])


def _children_counts(root: Root, depth: int) -> list[int]:
    """Most children of any branch at each level 1 … depth − 1 of one root."""
    counts = [0] * (depth - 1)

    def walk(node: Root, ell: int):
        counts[ell - 1] = max(counts[ell - 1], node.n_laterals)
        if ell < depth - 1:
            for child in node.children:
                walk(child, ell + 1)

    walk(root, 1)
    return counts


def _capacities(counts, depth, max_laterals, max_children) -> tuple[int, ...]:
    """(K1, …, K(D−1)) from the user's capacities or today's rule, level by level."""
    if max_laterals is not None:
        max_laterals = as_count(max_laterals, "batch(): max_laterals", minimum=0)
    if max_children is None:
        caps = [max(2, 2 * n) for n in counts]
        if max_laterals is not None:
            caps[0] = max_laterals
    else:
        caps = list(max_children) if isinstance(max_children, (Sequence, np.ndarray)) else [max_children]
        if len(caps) != depth - 1 or not all(
            isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k >= 0 for k in caps
        ):
            raise ValueError(
                f"batch(): max_children must hold {depth - 1} whole numbers (K1, ..., K{depth - 1}), one "
                f"per level for depth={depth}; got {max_children!r}."
            )
        caps = [int(k) for k in caps]
        if max_laterals is not None and max_laterals != caps[0]:
            raise ValueError(
                f"batch(): max_laterals={max_laterals} disagrees with max_children[0]={caps[0]} (both are "
                "K1); give only one of them."
            )
    for ell in range(2, depth):  # level 1 keeps its own (older) CapacityError, raised per root
        if counts[ell - 1] > caps[ell - 1]:
            raise CapacityError(
                f"batch(): a branch at level {ell - 1} has {counts[ell - 1]} children but the capacity "
                f"at level {ell} is K{ell} = {caps[ell - 1]}; level {ell} needs K{ell} >= {counts[ell - 1]} "
                f"(and 2 × {counts[ell - 1]} = {2 * counts[ell - 1]} to register any pair). Pass a larger "
                "max_children, or leave it to its default."
            )
    return tuple(caps)


def _count_beyond(node: Root, ell: int, depth: int) -> int:
    """Branches under `node` (whose `main` is a level-`ell` branch; the main root is level 0)
    at level ``depth`` or deeper: what a depth-`depth` tree leaves out."""
    here = node.n_laterals if ell + 1 >= depth else 0
    return here + sum(_count_beyond(c, ell + 1, depth) for c in node.children)


def _warn_truncated(roots: Sequence[Root], depth: int) -> None:
    left_out = [(i, _count_beyond(r, 0, depth)) for i, r in enumerate(roots)]
    left_out = [(i, n) for i, n in left_out if n]
    if left_out:
        total = sum(n for _, n in left_out)
        names = ", ".join(_root_label(roots[i], i) for i, _ in left_out[:5])
        more = f" and {len(left_out) - 5} more" if len(left_out) > 5 else ""
        need = 1 + max(deepest_order(roots[i]) for i, _ in left_out)
        if is_plant_system(roots[0]):
            # Level 1 of a plant's system is its axes: level 2 holds the axes' own laterals.
            what = f"{total} laterals of order {depth - 1} or higher (level 1 of a plant's system is its axes)"
        else:
            what = f"{total} laterals of order {depth} or higher (laterals of laterals ...)"
        warnings.warn(
            f"batch(depth={depth}): {what} were left out ({len(left_out)} roots: {names}{more}). Pass "
            f"depth={need} to keep them all (--depth {need} on the command line).",
            UserWarning,
            stacklevel=user_stacklevel(),
        )


#: Rounding of a coordinate, as a fraction of a main-root segment, above which `batch` warns.
_PRECISION_WARN = 0.01


def _warn_imprecise(roots, main, lats) -> None:
    """Warn when the dtype's rounding of the stored coordinates is a sizeable fraction of a
    segment: coordinates far from (0, 0) compared with the root's size (`normalise_scale`
    divides about (0, 0), so it keeps that ratio). The SRVFs are differences of neighbouring
    points, so they inherit that error. The segment
    is the main root's, or for plants' systems (zero-length main root) the longest axis's;
    a root whose branches all collapsed to a point in the rounding counts as lost entirely."""
    eps = float(np.finfo(main.dtype).eps)
    seg = np.linalg.norm(np.diff(main.astype(np.float64), axis=1), axis=-1)  # [N, T-1]
    flat = ~np.any(seg > 0, axis=1)  # plants' systems, and roots the rounding collapsed
    if np.any(flat):
        axes = np.linalg.norm(np.diff(lats[flat].astype(np.float64), axis=2), axis=-1)  # [n, K, T-1]
        seg[flat] = axes.max(axis=1, initial=0.0)
    seg = np.where(seg > 0, seg, np.nan)
    # Reductions, no full-size temporaries (a cluster batch holds thousands of roots). Padding
    # slots repeat the main root's first point, which the main root's reach already covers.
    reach = np.max([np.abs(main.max(axis=(1, 2))), np.abs(main.min(axis=(1, 2)))], axis=0)
    if lats.shape[1]:
        reach = np.max([reach, np.abs(lats.max(axis=(1, 2, 3))), np.abs(lats.min(axis=(1, 2, 3)))], axis=0)
    ratio = np.zeros(len(roots))
    for i in range(len(roots)):
        if np.any(np.isfinite(seg[i])):
            ratio[i] = reach[i] * eps / np.nanmedian(seg[i])
        elif normalising_length(roots[i], main.shape[1]) > 0:
            ratio[i] = np.inf  # a root with length came out as a point: all of it is lost
    bad = np.flatnonzero(ratio > _PRECISION_WARN)
    if not len(bad):
        return
    worst = int(bad[np.argmax(ratio[bad])])
    amount = "all" if np.isinf(ratio[worst]) else f"{ratio[worst]:.2g}"
    warnings.warn(
        f"batch(): {np.dtype(main.dtype).name} rounds the coordinates of {len(bad)} root(s) by up to "
        f"{amount} of a main-root segment (worst: {_root_label(roots[worst], worst)}, coordinates up "
        f"to {np.abs(main[worst]).max():.3g}): the roots are small compared with their distance from "
        "(0, 0). Distances and means then carry that error. Use "
        "dtype=float64 (jax.config.update('jax_enable_x64', True); on the command line --float64), or "
        "move the roots near (0, 0) first.",
        UserWarning,
        stacklevel=user_stacklevel(),
    )


def _has_radius(root: Root, depth: int) -> bool:
    if root.has_radius:
        return True
    return depth > 2 and any(_has_radius(c, depth - 1) for c in root.children)


def is_traced(*pytrees) -> bool:
    """Whether any array of `pytrees` (trees, weights, ...) is being traced (under jit or
    vmap): the host-driven loops (`pairwise_distances`, `karcher_mean`) refuse it with a clear
    error."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(pytrees))


def _check_units(roots: Sequence[Root]) -> None:
    """`UnitError` for roots in different units (``metadata["unit"]``, set by the readers): their
    sizes cannot be compared. Roots without a unit are not checked."""
    by_unit: dict[str, list[str]] = {}
    for i, r in enumerate(roots):
        unit = r.metadata.get("unit")
        key = unit_key(unit)
        if key is not None:
            by_unit.setdefault(key, []).append(f"{_root_label(r, i)} ({unit})")
    if len(by_unit) > 1:
        listed = "; ".join(", ".join(names[:2]) + (" ..." if len(names) > 2 else "") for names in by_unit.values())
        raise UnitError(
            f"batch(): the roots are in different units ({listed}), so their sizes cannot be compared. "
            "Convert them to one unit first (rootshape_jax.io.convert_units(roots, 'mm'); pixels need a "
            "resolution), or pass normalise_scale=True to compare shapes only."
        )


def _working_dtype(dtype) -> np.dtype:
    """float32 or float64; anything else is refused (float16 rounds every distance below ~0.1
    to 0, and integer or complex trees make no sense)."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"batch(): dtype={dtype!r} is not a dtype; use float32 or float64.") from None
    if dt not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(
            f"batch(): dtype={dt.name} is not supported; use float32 or float64 (float16 and "
            "bfloat16 are too coarse: distances below ~0.1 come out as exactly 0)."
        )
    return dt


def _root_label(r: Root, i: int) -> str:
    return repr(r.name) if r.name else f"#{i}"


def _warn_missing_radius(roots: Sequence[Root]) -> None:
    """One warning naming the roots (or their laterals) whose radius is taken as 0."""
    missing = []
    for i, r in enumerate(roots):
        if not r.has_radius:
            missing.append(f"root {_root_label(r, i)} has no radius data; its radius is taken as 0")
        elif r.main_radius is None:
            missing.append(f"root {_root_label(r, i)} has no main-root radius; it is taken as 0")
        elif r.lateral_radii is None and r.n_laterals:
            missing.append(f"root {_root_label(r, i)} has no lateral radii; they are taken as 0")
    if missing:
        shown = "; ".join(missing[:10])
        more = f"; ... and {len(missing) - 10} more" if len(missing) > 10 else ""
        warnings.warn(
            f"batch(): {shown}{more}. Give every root radii (or none) to avoid this.",
            MissingRadiusWarning,
            stacklevel=user_stacklevel(),
        )


def to_roots(tree: RootTree, *, names: Sequence[str] | None = None, unit: str | None = None) -> list[Root]:
    """Unpadded `Root`s from a (batched or single) `RootTree`; null slots are dropped.

    `unit` is recorded as ``metadata["unit"]`` (`write_rsml` writes it): the inputs' unit, or
    for trees built with ``batch(normalise_scale=True)`` (means, modes, geodesics of them)
    ``rootshape_jax.io.NORMALISED_UNIT`` = "normalised (main-root length = 1)". Without it
    `write_rsml` cannot know and writes "pixel"."""
    if not isinstance(tree, RootTree):
        raise TypeError(f"to_roots expects a RootTree, got {type(tree).__name__}.")
    if unit is not None:
        check_unit_name(unit, "to_roots")
    n_trees = int(np.prod(tree.batch_shape))
    if names is not None:
        names = [names] if isinstance(names, str) else list(names)
        if len(names) != n_trees:
            raise ValueError(f"to_roots: {len(names)} names for {n_trees} trees; give one name per tree.")
    main = np.asarray(tree.main)
    lats = np.asarray(tree.laterals)
    attach = np.asarray(tree.attach)
    mask = np.asarray(tree.mask)
    has_radius = tree.main_radius is not None
    T = main.shape[-2]
    main_r = np.asarray(tree.main_radius) if has_radius else None
    lat_r = np.asarray(tree.lateral_radius) if has_radius else None
    K = lats.shape[-3]
    n = int(np.prod(main.shape[:-2]))
    main = main.reshape((n,) + main.shape[-2:])
    lats = lats.reshape((n,) + lats.shape[-3:])
    attach = attach.reshape(n, K)
    mask = mask.reshape(n, K)
    if has_radius:
        # Radii come from arithmetic on trees (means, geodesics): clip tiny negatives to 0.
        main_r = np.maximum(main_r.reshape(n, T), 0.0)
        lat_r = np.maximum(lat_r.reshape(n, K, T), 0.0)
    levels = []
    for lv in tree.deeper:
        slots = lv.mask.shape[len(tree.batch_shape) :]
        levels.append(
            (
                np.asarray(lv.curves).reshape((n,) + slots + (T, main.shape[-1])),
                np.asarray(lv.attach).reshape((n,) + slots),
                np.asarray(lv.mask).reshape((n,) + slots),
                np.maximum(np.asarray(lv.radius).reshape((n,) + slots + (T,)), 0.0) if has_radius else None,
            )
        )

    def branch(i: int, slot: tuple, curve, radius) -> Root:
        """The level-len(slot) branch at `slot` of root i, with its own children."""
        curves, s, m, r = levels[len(slot) - 1]
        keep = np.flatnonzero(m[(i,) + slot])
        deeper = len(slot) < len(levels)
        return Root(
            main=curve,
            laterals=tuple(curves[(i,) + slot + (k,)] for k in keep),
            attach=np.clip(s[(i,) + slot][keep], 0.0, 1.0),
            children=tuple(
                branch(i, slot + (k,), curves[(i,) + slot + (k,)], r[(i,) + slot + (k,)] if has_radius else None)
                for k in keep
            )
            if deeper
            else (),
            main_radius=radius,
            lateral_radii=tuple(r[(i,) + slot + (k,)] for k in keep) if has_radius else None,
        )

    out = []
    for i in range(main.shape[0]):
        keep = np.flatnonzero(mask[i])
        children = ()
        if levels:
            children = tuple(branch(i, (k,), lats[i, k], lat_r[i, k] if has_radius else None) for k in keep)
        out.append(
            Root(
                main=main[i],
                laterals=tuple(lats[i, k] for k in keep),
                attach=np.clip(attach[i, keep], 0.0, 1.0),
                name=names[i] if names is not None else "",
                main_radius=main_r[i] if has_radius else None,
                lateral_radii=tuple(lat_r[i, k] for k in keep) if has_radius else None,
                metadata=({} if unit is None else {"unit": unit})
                | ({"virtual_main": True} if tree.virtual_main else {}),
                children=children,
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Batches of Modules


def stack(trees: Sequence[eqx.Module]) -> eqx.Module:
    """Stack Modules of the same type and shapes along a new leading axis."""
    trees = list(trees)
    if not trees:
        raise ValueError("stack() needs at least one tree.")
    shapes = {jax.tree.map(lambda x: tuple(x.shape), t).__repr__() for t in trees}
    if len(shapes) != 1:
        raise ValueError(
            "stack(): trees have different capacities or shapes; build them with the same "
            "n_points / max_laterals (e.g. one call to batch())."
        )
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def unstack(tree: eqx.Module) -> list:
    """Split a batched Module along its leading axis."""
    shape = getattr(tree, "batch_shape", None)
    if shape == ():
        raise ValueError(
            f"unstack: this {type(tree).__name__} is a single tree, not a batch (batch shape ()); "
            "use it as it is, or unstack the batch it came from."
        )
    leaves = jax.tree.leaves(tree)
    if not leaves or np.ndim(leaves[0]) == 0:
        raise ValueError(f"unstack: expected a batched {type(tree).__name__} with a leading axis.")
    n = leaves[0].shape[0]
    return [jax.tree.map(lambda x: x[i], tree) for i in range(n)]


def batch_size(tree: RootTree | SRVFTree) -> int:
    shape = tree.batch_shape
    if len(shape) != 1:
        raise ValueError(f"expected a batch with one leading axis, got batch shape {shape}.")
    return shape[0]


# --------------------------------------------------------------------------------------------
# RootTree <-> SRVFTree


def to_srvf(tree: RootTree | SRVFTree, *, weights=None) -> SRVFTree:
    """SRVF tree of a (batched) `RootTree`; an `SRVFTree` is returned unchanged.

    With `weights` whose `thickness` (λr) is positive and a tree with radii, each branch's SRVF
    is that of the extended curve ``(x, √λr·r)`` (docs/design.md §11; see `SRVFTree`). Otherwise
    radii are not used.
    """
    if isinstance(tree, SRVFTree):
        if weights is not None:
            check_thickness(tree, weights)
            _warn_unused_deeper_weights(tree, weights)
        _require_finite_tree(tree)
        _require_float_dtype(tree.q0.dtype, "SRVFTree")
        return tree
    if not isinstance(tree, RootTree):
        raise TypeError(
            f"expected a RootTree or SRVFTree, got {type(tree).__name__}; "
            "use rootshape_jax.batch(roots) to build one from Root objects."
        )
    _require_finite_tree(tree)
    _require_usable_coordinates(tree)
    if weights is not None and tree.main_radius is None and _concrete_positive(weights.thickness):
        warnings.warn(
            f"weights.thickness = {float(np.asarray(weights.thickness)):g} has no effect: these trees carry no "
            "radii (their roots have no diameters, or batch() dropped them). Read files with diameter "
            "functions, or leave thickness at 0.",
            MissingRadiusWarning,
            stacklevel=user_stacklevel(),
        )
    if weights is not None:
        _warn_unused_deeper_weights(tree, weights)
    lam = jnp.asarray(weights.thickness, tree.main.dtype) if wants_thickness(tree, weights) else None
    return _srvf_tree(tree, lam)


def _warn_unused_deeper_weights(tree: RootTree | SRVFTree, weights) -> None:
    """Warn when `weights.deeper` (second-order laterals and below) weighs no branch of `tree`:
    a taproot tree needs depth 3 for it, a plant's system (whose level 2 takes `lateral` and
    `position`, `system_weights`) depth 4."""
    deeper = getattr(weights, "deeper", ())
    first = 4 if tree.virtual_main else 3  # the shallowest depth whose branches use deeper[0]
    depth = len(tree.deeper) + 2
    if deeper and depth < first:
        what = "plants' systems" if tree.virtual_main else "trees"
        warnings.warn(
            f"weights.deeper has no effect: it weighs laterals of order 2 and below, and these {what} "
            f"have depth {depth}"
            + (
                " (a plant's axes take `main`, their laterals `lateral` and `position`)"
                if tree.virtual_main
                else " (first-order laterals only)"
            )
            + f". Build them with batch(..., depth={first}) to keep deeper orders, or leave deeper empty.",
            UserWarning,
            stacklevel=user_stacklevel(),
        )


def _concrete_positive(x) -> bool:
    return not isinstance(x, jax.core.Tracer) and bool(np.asarray(x) > 0)


def _require_float_dtype(dtype, what: str) -> np.dtype:
    """float32 or float64, else `TypeError`: float16 distances (a tree cast with `astype`) are
    too coarse to mean anything, and integer trees fail deep inside JAX."""
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise TypeError(
            f"{what} has {dt.name} values; the metric needs float32 or float64 (build trees with "
            "rootshape_jax.batch(roots, dtype=...), or cast the floating-point leaves)."
        )
    return dt


def _require_usable_coordinates(tree: RootTree) -> None:
    """A `RootTree` edited by hand or rescaled (`scale_tree`) must still be what `batch` builds:
    float32/float64 coordinates whose squares stay finite (`coordinate_limit`)."""
    dt = _require_float_dtype(tree.main.dtype, "RootTree")
    limit = coordinate_limit(dt, tree.main.shape[-2])
    for x, what in ((tree.main, "main"), (tree.laterals, "laterals"), *((lv.curves, "deeper") for lv in tree.deeper)):
        if isinstance(x, jax.core.Tracer):  # under jit or grad: not checked
            continue
        check_range(
            np.asarray(x),
            limit=limit,
            what=f"RootTree.{what}",
            fix="Rescale the roots (scale_tree with smaller factors, another unit, or normalise_scale=True "
            "in batch), or use float64.",
        )


def _require_finite_tree(tree: RootTree | SRVFTree) -> None:
    """`InvalidRootError` naming the field of a concrete tree that holds NaN or inf (a tree
    edited by hand: `batch` builds finite ones)."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if _is_array(leaf):
            name = type(tree).__name__ + jax.tree_util.keystr(path)
            require_finite(leaf, name)


# Compiled as one program: run op by op, the first call at each new batch size compiled every
# small op apart (measured 4.4 s for 2 CPlantBox pea roots at depth 3, against ~0.3 s).
@eqx.filter_jit
def _srvf_tree(tree: RootTree, lam) -> SRVFTree:
    """`to_srvf`'s arrays; `lam` is the thickness weight λr, or None to leave radii out."""
    origin = tree.main[..., 0, :]
    if lam is not None:
        q0, q, base, c = extended_srvf(tree.main, tree.laterals, tree.main_radius, tree.lateral_radius, tree.mask, lam)
        deeper = tuple(_level_srvf(lv, c) for lv in tree.deeper)
        return SRVFTree(
            q0=q0,
            q=q,
            s=tree.attach,
            mask=tree.mask,
            origin=origin,
            base_radius=base,
            thickness_scale=c,
            deeper=deeper,
            virtual_main=tree.virtual_main,
        )
    q0 = srvf(tree.main)
    q = srvf(tree.laterals) * tree.mask[..., None, None]
    deeper = tuple(_level_srvf(lv, None) for lv in tree.deeper)
    return SRVFTree(
        q0=q0, q=q, s=tree.attach, mask=tree.mask, origin=origin, deeper=deeper, virtual_main=tree.virtual_main
    )


def _level_srvf(level: BranchLevel, c) -> SRVFLevel:
    """SRVFs of one deeper level; with a thickness scale `c` (one per tree) those of ``(x, c·r)``."""
    if c is None:
        q = srvf(level.curves) * level.mask[..., None, None]
        return SRVFLevel(q=q, s=level.attach, mask=level.mask)
    cc = c.reshape(c.shape + (1,) * (level.radius.ndim - c.ndim))
    ext = jnp.concatenate([level.curves, (cc * level.radius)[..., None]], axis=-1)
    q = srvf(ext) * level.mask[..., None, None]
    return SRVFLevel(q=q, s=level.attach, mask=level.mask, base_radius=level.radius[..., 0])


def check_thickness(tree: SRVFTree, weights) -> None:
    """Refuse an `SRVFTree` built for another thickness weight than `weights.thickness`."""
    lam = weights.thickness
    if isinstance(lam, jax.core.Tracer) or isinstance(tree.thickness_scale, jax.core.Tracer):
        return
    lam = float(np.asarray(lam))
    if tree.thickness_scale is None:
        return  # no radii in the data, or built with λr = 0: the thickness term is 0
    c = np.asarray(tree.thickness_scale)
    if not np.allclose(c**2, lam, rtol=1e-6, atol=0.0):
        raise ValueError(
            f"this SRVFTree was built with thickness weight {float(np.ravel(c)[0]) ** 2:g} but "
            f"weights.thickness = {lam:g}; rebuild it with to_srvf(tree, weights=weights)."
        )


def _to_curves_single(t: SRVFTree) -> RootTree:
    if not t.has_thickness:
        main = srvf_to_curve(t.q0, t.origin)
        bases = interpolate_at_fraction(main, t.s)  # (K, d)
        q = t.q * t.mask[:, None, None]
        lats = jax.vmap(srvf_to_curve)(q, bases)
        deeper = _deeper_curves(t, lats)
        return RootTree(main=main, laterals=lats, attach=t.s, mask=t.mask, deeper=deeper, virtual_main=t.virtual_main)
    c = t.thickness_scale
    main, r0 = integrate_branch(t.q0, t.origin, t.base_radius[0], c)
    bases = interpolate_at_fraction(main, t.s)
    q = t.q * t.mask[:, None, None]
    lats, r = jax.vmap(integrate_branch, in_axes=(0, 0, 0, None))(q, bases, t.base_radius[1:], c)
    r = r * t.mask[:, None]
    deeper = _deeper_curves(t, lats)
    return RootTree(
        main=main,
        laterals=lats,
        attach=t.s,
        mask=t.mask,
        main_radius=r0,
        lateral_radius=r,
        deeper=deeper,
        virtual_main=t.virtual_main,
    )


def _deeper_curves(t: SRVFTree, lats: Array) -> tuple[BranchLevel, ...]:
    """Curves of the deeper levels of one tree: each child integrated from its parent's point
    at arc-length fraction `s` (null children collapse to their parent's first point)."""
    out = []
    parents = lats
    for lv in t.deeper:
        slots, Tn, d = lv.mask.shape, parents.shape[-2], parents.shape[-1]
        P, Kl = int(np.prod(slots[:-1])), slots[-1]
        flat_parents = parents.reshape(P, Tn, d)
        s = lv.s.reshape(P, Kl)
        bases = jax.vmap(interpolate_at_fraction)(flat_parents, s)  # (P, Kl, d)
        q = (lv.q * lv.mask[..., None, None]).reshape((P, Kl) + lv.q.shape[-2:])
        if not t.has_thickness:
            curves = jax.vmap(jax.vmap(srvf_to_curve))(q, bases)
            radius = None
        else:
            base_r = lv.base_radius.reshape(P, Kl)
            integrate = jax.vmap(jax.vmap(integrate_branch, in_axes=(0, 0, 0, None)), in_axes=(0, 0, 0, None))
            curves, radius = integrate(q, bases, base_r, t.thickness_scale)
            radius = radius.reshape(slots + (Tn,)) * lv.mask[..., None]
        curves = curves.reshape(slots + (Tn, d))
        out.append(BranchLevel(curves=curves, attach=lv.s, mask=lv.mask, radius=radius))
        parents = curves
    return tuple(out)


def to_curves(tree: SRVFTree | RootTree) -> RootTree:
    """Curves of a (batched) `SRVFTree`: integrate the main root from `origin`, then each
    lateral from the main-root point at arc-length fraction `s` (docs/design.md §5). With a
    thickness channel the radii come back too (from `base_radius`)."""
    if isinstance(tree, RootTree):
        return tree
    if not isinstance(tree, SRVFTree):
        raise TypeError(f"expected an SRVFTree, got {type(tree).__name__}.")
    return _curves_of(tree)


# One compiled program per shape instead of ~100 one-op programs: eager dispatch compiles each
# jnp call at each new shape (0.03-0.05 s apiece), most of a small job's first call. `to_srvf`
# stays eager on purpose: an eager op rounds each element the same whatever the batch shape, so
# a plant's one axis (a lateral slot) gets bit for bit its taproot's main-root SRVF; compiled,
# XLA's shape-dependent code changed the last bits, and a Karcher mean then took one more step.
@eqx.filter_jit
def _curves_of(tree: SRVFTree) -> RootTree:
    fn = _to_curves_single
    for _ in tree.batch_shape:
        fn = jax.vmap(fn)
    return fn(tree)


def check_compatible(a: RootTree | SRVFTree, b: RootTree | SRVFTree, what: str = "trees") -> None:
    """Raise a clear ValueError when two trees cannot be compared: thickness channel, (T, K, d),
    plant system or single root, and capacities per level. Not the dtype: callers that need
    one dtype check it themselves (`register`, `karcher_mean(init=...)`)."""
    if isinstance(a, SRVFTree) and isinstance(b, SRVFTree) and a.has_thickness != b.has_thickness:
        raise ValueError(
            f"{what}: one has a thickness channel and the other not; build both with "
            "to_srvf(tree, weights=weights) from trees that both carry radii."
        )
    if a.dim != b.dim:
        raise ValueError(
            f"{what} are in different dimensions ({a.dim}-D and {b.dim}-D); give 2-D roots a z = 0 "
            "column (Root(main=np.c_[xy, np.zeros(len(xy))], ...)) and batch all of them in one call."
        )
    if (a.n_points, a.capacity, a.dim) != (b.n_points, b.capacity, b.dim):
        raise ValueError(
            f"{what} have different capacities: (T, K, d) = {(a.n_points, a.capacity, a.dim)} vs "
            f"{(b.n_points, b.capacity, b.dim)}. Build them in one call to batch() or pass the same "
            "n_points and max_laterals."
        )
    if a.virtual_main != b.virtual_main:
        raise ValueError(
            f"{what}: one is a plant's system (virtual main root, read_rsml(by='plant')) and the other a "
            "single root; read both with the same `by`, or wrap single roots with "
            "rootshape_jax.io.plant_system([root])."
        )
    if a.capacities != b.capacities:
        raise ValueError(
            f"{what} have different depths or capacities per level: {a.capacities} vs {b.capacities} "
            "(K1, ..., K(D-1)). Build them in one call to batch() or pass the same depth and max_children."
        )


def upright_rotation(tree: RootTree | SRVFTree, like: RootTree | SRVFTree) -> np.ndarray | None:
    """The rotation ``[d, d]`` that turns `tree` (one root, e.g. a Karcher mean) about its base
    so its main root points where the main roots of `like` (a batch, e.g. the trees the mean
    was fitted to) point on average; None for plants' systems (no main root to point) or when
    `like` points every way (its mean direction is shorter than 0.5).

    The metric ignores rotation, so a Karcher mean keeps the tilt of the root its solver
    started from, as moved by the fit (on the 10 RootNav seedlings: 12.4° where the inputs
    average 3.7°). Turn it, and the roots built around it (modes, `sample`, predicted roots:
    they share its frame), with `turn_about_base(to_curves(x), rotation)`.
    """
    if like.virtual_main or tree.virtual_main:
        return None
    main = np.asarray(to_curves(like).main, np.float64)
    main = main.reshape((-1,) + main.shape[-2:])
    m = np.asarray(to_curves(tree).main, np.float64)
    if m.ndim != 2:
        raise ValueError(f"upright_rotation: `tree` must be one root (unbatched), got main of shape {m.shape}.")
    return rotation_towards_chords(m[-1] - m[0], main[:, -1] - main[:, 0])


def rotation_towards_chords(m: np.ndarray, chords: np.ndarray) -> np.ndarray | None:
    """The smallest rotation ``[d, d]`` turning the direction `m` to the mean direction of the
    `chords` ``[n, d]`` (each as a unit vector; zero ones ignored); None when they point every
    way (mean shorter than 0.5) or `m` is zero (`upright_rotation`)."""
    norms = np.linalg.norm(chords, axis=-1)
    if not np.any(norms > 0):
        return None
    target = np.sum(chords[norms > 0] / norms[norms > 0, None], axis=0) / np.sum(norms > 0)
    if np.linalg.norm(target) < 0.5 or np.linalg.norm(m) == 0:
        return None  # no common direction to turn to
    a, b = m / np.linalg.norm(m), target / np.linalg.norm(target)
    if a.shape[0] == 2:
        t = np.arctan2(b[1], b[0]) - np.arctan2(a[1], a[0])
        return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    # 3D: the smallest rotation taking a to b (Rodrigues), about their common normal.
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def turn_about_base(tree: RootTree, rotations) -> RootTree:
    """A (batched) `RootTree` with each root turned about its main-root base,
    ``x' = o + R (x − o)`` for every point of every level. `rotations`: one ``[d, d]`` rotation
    for every root, or ``[*B, d, d]`` one per root. Attachments, masks and radii are kept."""
    R = jnp.asarray(rotations, dtype=tree.main.dtype)
    R = jnp.broadcast_to(R, tree.batch_shape + (tree.dim, tree.dim))
    o = tree.main[..., :1, :]  # [*B, 1, d]

    def turned(x):  # x: [*B, (slot axes ...), T, d]
        extra = x.ndim - o.ndim  # slot axes
        o_x = o.reshape(o.shape[:-2] + (1,) * extra + o.shape[-2:])
        R_x = R.reshape(R.shape[:-2] + (1,) * (extra + 1) + R.shape[-2:])  # over slots and points
        return o_x + jnp.einsum("...j,...ij->...i", x - o_x, R_x)

    out = eqx.tree_at(lambda t: (t.main, t.laterals), tree, (turned(tree.main), turned(tree.laterals)))
    if tree.deeper:
        levels = tuple(eqx.tree_at(lambda lv: lv.curves, lv, turned(lv.curves)) for lv in tree.deeper)
        out = eqx.tree_at(lambda t: t.deeper, out, levels)
    return out


def scale_tree(tree: RootTree, scales, *, base=None) -> RootTree:
    """A (batched) `RootTree` with each root scaled about its main-root base.

    `scales` broadcasts to the tree's batch shape (one factor per root, or a scalar); factors
    must be finite and positive; radii, when present, scale too. Attachment fractions and masks
    are kept.

    `base`: where each scaled root's base goes (``[d]``, or ``[*B, d]`` one per root); default
    None keeps it where it is. `batch(normalise_scale=True)` divides each root by its length
    about (0, 0), so its base moves too: ``scale_tree(t, length, base=seed)`` puts a
    normalised root (or a mode) back at its real size where the data are, e.g. at the roots'
    mean seed ``np.mean([r.main[0] for r in roots], axis=0)``. A Karcher mean of normalised
    roots is a little shorter than 1 (averaging shapes shrinks them): divide the length by its
    own, ``curve_length(mean.main)``, to give it the roots' mean length.
    """
    if not isinstance(tree, RootTree):
        raise TypeError(f"scale_tree: expected a RootTree, got {type(tree).__name__}.")
    s = jnp.asarray(scales, dtype=tree.main.dtype)
    try:
        s = jnp.broadcast_to(s, tree.batch_shape)
    except ValueError:
        raise ValueError(
            f"scale_tree: scales of shape {s.shape} do not match the tree's batch shape "
            f"{tree.batch_shape}; give one factor per root."
        ) from None
    if not isinstance(s, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(s) & (s > 0))):
        raise ValueError(f"scale_tree: scales must be finite and > 0, got {np.asarray(scales)!r}.")
    s = eqx.error_if(s, ~(jnp.isfinite(s) & (s > 0)), "scale_tree: scales must be finite and > 0.")  # traced
    o = tree.main[..., :1, :]  # [*B, 1, d] main-root base
    to = o  # where the base goes
    if base is not None:
        b = jnp.asarray(base, dtype=tree.main.dtype)
        try:
            to = jnp.broadcast_to(b, tree.batch_shape + (tree.dim,))[..., None, :]
        except ValueError:
            raise ValueError(
                f"scale_tree: base of shape {b.shape} does not match the tree (batch shape "
                f"{tree.batch_shape}, d = {tree.dim}); give one point [d], or one per root [*B, d]."
            ) from None
    main = to + (tree.main - o) * s[..., None, None]
    o_lat, to_lat = o[..., None, :, :], to[..., None, :, :]
    laterals = to_lat + (tree.laterals - o_lat) * s[..., None, None, None]
    out = eqx.tree_at(lambda t: (t.main, t.laterals), tree, (main, laterals))
    if tree.main_radius is not None:  # radii are lengths: they scale with the coordinates
        radii = (tree.main_radius * s[..., None], tree.lateral_radius * s[..., None, None])
        out = eqx.tree_at(lambda t: (t.main_radius, t.lateral_radius), out, radii)
    if tree.deeper:
        deeper = []
        for lv in tree.deeper:
            extra = lv.curves.ndim - 2 - s.ndim  # slot axes K1 … Kℓ
            o_l = o.reshape(o.shape[:-2] + (1,) * extra + (1, o.shape[-1]))
            to_l = to.reshape(o_l.shape)
            sl = s.reshape(s.shape + (1,) * extra)
            curves = to_l + (lv.curves - o_l) * sl[..., None, None]
            radius = None if lv.radius is None else lv.radius * sl[..., None]
            deeper.append(BranchLevel(curves=curves, attach=lv.attach, mask=lv.mask, radius=radius))
        out = eqx.tree_at(lambda t: t.deeper, out, tuple(deeper))
    return out
