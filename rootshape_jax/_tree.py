"""Padded, fixed-size root trees: `RootTree` (geometry) and `SRVFTree` (shape).

Both are frozen `eqx.Module`s whose array leaves have fixed capacities — ``T`` points per
branch and ``K`` lateral slots — so every computation on them compiles once per (T, K, d, dtype)
and vmaps over batches. A batch is the same Module with a leading axis on every leaf.

Padding: a slot with ``mask = False`` is one of the paper's *null* (virtual) laterals. It holds
finite zeros in the SRVF (``q = 0``) and, in a `RootTree`, a lateral collapsed to its attachment
point. Never NaN: a NaN in a masked branch of ``jnp.where`` still poisons gradients.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._curves import interpolate_at_fraction, srvf, srvf_to_curve
from ._errors import CapacityError, InvalidRootError
from ._root import Root, check_range, coordinate_limit, polyline_length
from ._thickness import extended_srvf, integrate_branch, wants_thickness


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray))


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

    Radius padding: null slots have radius 0; so does every branch of a root that came without
    radius data in a batch where other roots have it (`batch` warns and names those roots).
    """

    main: Float[Array, "*B T d"]
    laterals: Float[Array, "*B K T d"]
    attach: Float[Array, "*B K"]
    mask: Bool[Array, "*B K"]
    main_radius: Float[Array, "*B T"] | None = None
    lateral_radius: Float[Array, "*B K T"] | None = None

    def __check_init__(self):
        _check_shapes("RootTree", self.main, self.laterals, self.attach, self.mask, names=("main", "laterals"))
        _check_radius_shapes("RootTree", self.main, self.laterals, self.main_radius, self.lateral_radius)

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
    """

    q0: Float[Array, "*B T C"]
    q: Float[Array, "*B K T C"]
    s: Float[Array, "*B K"]
    mask: Bool[Array, "*B K"]
    origin: Float[Array, "*B d"]
    base_radius: Float[Array, "*B K1"] | None = None
    thickness_scale: Float[Array, "*B"] | None = None

    def __check_init__(self):
        _check_shapes("SRVFTree", self.q0, self.q, self.s, self.mask, names=("q0", "q"))
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
        # The length of the resampled main root, so that the padded tree's main root has length 1.
        length = polyline_length(resample_polyline(main, n_points))
        if length <= 0:
            raise InvalidRootError(f"root {root.name!r}: main root has zero length; cannot normalise scale.")
        scale = 1.0 / length
    o = main[0]
    main = o + (main - o) * scale
    d = main.shape[1]
    main_resampled = resample_polyline(main, n_points)
    main_radius = np.zeros((n_points,))
    if root.main_radius is not None:
        main_radius = resample_values(main, root.main_radius.astype(np.float64) * scale, n_points)
    lats = np.zeros((capacity, n_points, d))
    lat_radius = np.zeros((capacity, n_points))
    attach = np.zeros((capacity,))
    mask = np.zeros((capacity,), dtype=bool)
    for k, (lat, s) in enumerate(zip(root.laterals, root.attach)):
        lat = o + (lat.astype(np.float64) - o) * scale
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
        lat = lat + (_point_at_fraction(main_resampled, float(s)) - base)
        lats[k] = resample_polyline(lat, n_points)
        if radius is not None:
            lat_radius[k] = resample_values(lat, radius, n_points)
        attach[k] = s
        mask[k] = True
    for k in range(root.n_laterals, capacity):
        lats[k] = np.repeat(main_resampled[:1], n_points, axis=0)
    # Checked in float64, before the cast (which would overflow to inf with a warning).
    limit = coordinate_limit(dtype, n_points)
    label = f"root {root.name!r}" if root.name else "root"
    for x, what in (
        (main_resampled, "main root"),
        (lats, "laterals"),
        (main_radius, "main radius"),
        (lat_radius, "lateral radii"),
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
    )


def batch(
    roots: Root | Sequence[Root],
    *,
    n_points: int = 100,
    max_laterals: int | None = None,
    normalise_scale: bool = False,
    dtype=None,
) -> RootTree:
    """Resample and pad roots into one batched `RootTree` (leading axis = roots).

    - `n_points`: ``T``, points per branch (uniform in arc length).
    - `max_laterals`: ``K``, lateral slots. Default ``2 × (most laterals of any root)`` (at least
      2), enough to register any pair (docs/design.md §2).
    - `normalise_scale`: divide each root by its main-root length (the paper's scale invariance;
      leave off for growth studies).
    - `dtype`: float dtype of the arrays; default JAX's default float (float32 unless x64 is on).

    Radii (`Root.main_radius`, `Root.lateral_radii`) are resampled like the coordinates (and
    scaled with them by `normalise_scale`) into `RootTree.main_radius` / `lateral_radius`. If
    no root has radius data both fields are ``None``; if only some have, the others get radius
    0 and a warning names them.

    Raises ``ValueError`` for a dtype other than float32 / float64 (float16 rounds small
    distances to 0), and `CoordinateRangeError` (naming the root and the fix) for coordinates
    whose squared lengths would overflow ``dtype`` (`coordinate_limit`: about 1e16 in float32
    and 8e150 in float64 at ``n_points = 100``).

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
    if not isinstance(n_points, int) or n_points < 2:
        raise ValueError(f"n_points must be an integer >= 2, got {n_points!r}.")
    if max_laterals is None:
        max_laterals = max(2, 2 * max(r.n_laterals for r in roots_list))
    if dtype is None:
        dtype = jnp.zeros(()).dtype  # JAX's default float: respects jax_enable_x64
    dtype = _working_dtype(dtype)
    arrays = [
        root_to_arrays_with_radius(
            r, n_points=n_points, capacity=max_laterals, normalise_scale=normalise_scale, dtype=dtype
        )
        for r in roots_list
    ]
    main, lats, attach, mask, main_r, lat_r = (np.stack(a) for a in zip(*arrays))
    radii = {}
    if any(r.has_radius for r in roots_list):
        _warn_missing_radius(roots_list)
        radii = dict(main_radius=jnp.asarray(main_r), lateral_radius=jnp.asarray(lat_r))
    tree = RootTree(jnp.asarray(main), jnp.asarray(lats), jnp.asarray(attach), jnp.asarray(mask), **radii)
    return unstack(tree)[0] if single else tree


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
            UserWarning,
            stacklevel=3,
        )


def to_roots(tree: RootTree, *, names: Sequence[str] | None = None, unit: str | None = None) -> list[Root]:
    """Unpadded `Root`s from a (batched or single) `RootTree`; null slots are dropped.

    `unit` is recorded as ``metadata["unit"]`` (`write_rsml` writes it): the inputs' unit, or
    for trees built with ``batch(normalise_scale=True)`` (means, modes, geodesics of them)
    ``rootshape_jax.io.NORMALISED_UNIT`` = "normalised (main-root length = 1)". Without it
    `write_rsml` cannot know and writes "pixel"."""
    if not isinstance(tree, RootTree):
        raise TypeError(f"to_roots expects a RootTree, got {type(tree).__name__}.")
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
    out = []
    for i in range(main.shape[0]):
        keep = np.flatnonzero(mask[i])
        out.append(
            Root(
                main=main[i],
                laterals=tuple(lats[i, k] for k in keep),
                attach=np.clip(attach[i, keep], 0.0, 1.0),
                name=names[i] if names is not None else "",
                main_radius=main_r[i] if has_radius else None,
                lateral_radii=tuple(lat_r[i, k] for k in keep) if has_radius else None,
                metadata={} if unit is None else {"unit": unit},
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
    leaves = jax.tree.leaves(tree)
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
        return tree
    if not isinstance(tree, RootTree):
        raise TypeError(
            f"expected a RootTree or SRVFTree, got {type(tree).__name__}; "
            "use rootshape_jax.batch(roots) to build one from Root objects."
        )
    origin = tree.main[..., 0, :]
    if wants_thickness(tree, weights):
        q0, q, base, c = extended_srvf(
            tree.main, tree.laterals, tree.main_radius, tree.lateral_radius, tree.mask, weights.thickness
        )
        return SRVFTree(q0=q0, q=q, s=tree.attach, mask=tree.mask, origin=origin, base_radius=base, thickness_scale=c)
    q0 = srvf(tree.main)
    q = srvf(tree.laterals) * tree.mask[..., None, None]
    return SRVFTree(q0=q0, q=q, s=tree.attach, mask=tree.mask, origin=origin)


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
        return RootTree(main=main, laterals=lats, attach=t.s, mask=t.mask)
    c = t.thickness_scale
    main, r0 = integrate_branch(t.q0, t.origin, t.base_radius[0], c)
    bases = interpolate_at_fraction(main, t.s)
    q = t.q * t.mask[:, None, None]
    lats, r = jax.vmap(integrate_branch, in_axes=(0, 0, 0, None))(q, bases, t.base_radius[1:], c)
    r = r * t.mask[:, None]
    return RootTree(main=main, laterals=lats, attach=t.s, mask=t.mask, main_radius=r0, lateral_radius=r)


def to_curves(tree: SRVFTree | RootTree) -> RootTree:
    """Curves of a (batched) `SRVFTree`: integrate the main root from `origin`, then each
    lateral from the main-root point at arc-length fraction `s` (docs/design.md §5). With a
    thickness channel the radii come back too (from `base_radius`)."""
    if isinstance(tree, RootTree):
        return tree
    if not isinstance(tree, SRVFTree):
        raise TypeError(f"expected an SRVFTree, got {type(tree).__name__}.")
    fn = _to_curves_single
    for _ in tree.batch_shape:
        fn = jax.vmap(fn)
    return fn(tree)


def check_compatible(a: RootTree | SRVFTree, b: RootTree | SRVFTree, what: str = "trees") -> None:
    """Raise a clear ValueError when two trees cannot be compared (capacities, d, dtype)."""
    if isinstance(a, SRVFTree) and isinstance(b, SRVFTree) and a.has_thickness != b.has_thickness:
        raise ValueError(
            f"{what}: one has a thickness channel and the other not; build both with "
            "to_srvf(tree, weights=weights) from trees that both carry radii."
        )
    if (a.n_points, a.capacity, a.dim) != (b.n_points, b.capacity, b.dim):
        raise ValueError(
            f"{what} have different capacities: (T, K, d) = {(a.n_points, a.capacity, a.dim)} vs "
            f"{(b.n_points, b.capacity, b.dim)}. Build them in one call to batch() or pass the same "
            "n_points and max_laterals."
        )


def scale_tree(tree: RootTree, scales) -> RootTree:
    """A (batched) `RootTree` with each root scaled about its main-root base.

    `scales` broadcasts to the tree's batch shape (one factor per root, or a scalar); factors
    must be finite and positive; radii, when present, scale too. Attachment fractions and masks
    are kept.
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
    s = eqx.error_if(s, ~(jnp.isfinite(s) & (s > 0)), "scale_tree: scales must be finite and > 0.")
    o = tree.main[..., :1, :]  # [*B, 1, d] main-root base
    main = o + (tree.main - o) * s[..., None, None]
    o_lat = o[..., None, :, :]
    laterals = o_lat + (tree.laterals - o_lat) * s[..., None, None, None]
    out = eqx.tree_at(lambda t: (t.main, t.laterals), tree, (main, laterals))
    if tree.main_radius is not None:  # radii are lengths: they scale with the coordinates
        radii = (tree.main_radius * s[..., None], tree.lateral_radius * s[..., None, None])
        out = eqx.tree_at(lambda t: (t.main_radius, t.lateral_radius), out, radii)
    return out
