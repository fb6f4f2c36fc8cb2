"""Geodesics between roots: straight lines in SRVF-tree space, mapped back to curves."""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp

from ._engine import Registration, RegistrationOptions, apply_registration
from ._errors import as_count
from ._metric import Weights, as_weights, preshape_terms
from ._registration import register
from ._rotation import axis_angle_rotation
from ._tree import RootTree, SRVFLevel, SRVFTree, scale_tree, to_curves, to_srvf, turn_about_base


def geodesic_srvf(a: SRVFTree, registered_b: SRVFTree, taus) -> SRVFTree:
    """Points ``(1 − τ) a + τ b`` of the straight line between a and registered b.

    A null lateral takes its partner's attachment fraction at both ends, so a lateral that
    exists on one side only grows from (or shrinks to) zero length at a fixed position; it is
    real (masked in) at every point but that end, where it is a null as in the input.
    The result has a leading axis over `taus`. Deeper levels (docs/design.md §11) follow the
    same rule slot by slot, so matched branches keep their slot at every level.
    """
    s_a = jnp.where(a.mask, a.s, registered_b.s)
    s_b = jnp.where(registered_b.mask, registered_b.s, s_a)
    levels = []
    for la, lb in zip(a.deeper, registered_b.deeper):
        ls_a = jnp.where(la.mask, la.s, lb.s)
        base = None
        if la.base_radius is not None:  # as at level 1: a one-sided branch keeps its partner's
            rb_b = jnp.where(lb.mask, lb.base_radius, la.base_radius)
            base = (jnp.where(la.mask, la.base_radius, rb_b), rb_b)
        levels.append((la.q, lb.q, ls_a, jnp.where(lb.mask, lb.s, ls_a), (la.mask, lb.mask), base))

    def point(tau):
        lerp = lambda x, y: (1 - tau) * x + tau * y  # noqa: E731
        # A branch is real where it has length: on one side's end it is that side's null (of
        # zero length there), not a real branch of length 0 (which traits would count).
        union = lambda ma, mb: (ma & (tau < 1)) | (mb & (tau > 0))  # noqa: E731
        base = None
        if a.base_radius is not None:
            # A lateral present on one side only keeps its partner's starting radius.
            base_b = jnp.where(
                jnp.concatenate([jnp.ones(1, bool), registered_b.mask]), registered_b.base_radius, a.base_radius
            )
            base_a = jnp.where(jnp.concatenate([jnp.ones(1, bool), a.mask]), a.base_radius, base_b)
            base = lerp(base_a, base_b)
        return SRVFTree(
            q0=lerp(a.q0, registered_b.q0),
            q=lerp(a.q, registered_b.q),
            s=lerp(s_a, s_b),
            mask=union(a.mask, registered_b.mask),
            origin=lerp(a.origin, registered_b.origin),
            base_radius=base,
            thickness_scale=a.thickness_scale,
            deeper=tuple(
                SRVFLevel(q=lerp(qa, qb), s=lerp(sa, sb), mask=union(*m), base_radius=None if r is None else lerp(*r))
                for qa, qb, sa, sb, m, r in levels
            ),
            virtual_main=a.virtual_main,
        )

    return jax.vmap(point)(jnp.asarray(taus, a.q0.dtype))


def geodesic(
    a: RootTree | SRVFTree,
    b: RootTree | SRVFTree,
    *,
    n_steps: int = 9,
    weights: Weights | None = None,
    registration: Registration | RegistrationOptions | Mapping | None = None,
    in_place: bool = True,
    sizes: tuple[float, float] | None = None,
    **options,
) -> RootTree:
    """The geodesic from root a to root b as a batched `RootTree` of `n_steps` roots.

    `a`, `b`: two unbatched trees of one `batch` call (`unstack`), as curves or SRVFs.
    `n_steps` (>= 2): roots along the path, a and b included. `weights`: the metric's λ
    (default the paper's, `Weights()`): the path is the geodesic of that metric. Returns the
    roots in the trees' frame and unit: the coordinates of the data, or the normalised ones
    of `batch(normalise_scale=True)` unless `sizes` is given.

    Slot k of every step is the same lateral along the path (the correspondence colour); a
    lateral present on one side only grows from zero length at its partner's position. The
    first and last steps are a's and b's own SRVFs as curves (their round trip, docs/design.md
    §3; b not reparameterised, where a steep warp would cut its corners; so between the last
    two steps the points along a branch slide back to b's own parameterisation). Pass a
    precomputed `registration` (of b onto a) to skip registering again, or registration
    options (a `RegistrationOptions`, or its fields as keywords) as in `register`.

    Where the path lies: every step's base moves on the straight line from a's base to b's
    (the SRVFs forget translation; the trees' `origin` keeps it), so roots far from the
    coordinate origin stay where they are (scale-normalised trees: pass `sizes`, below; their
    stored bases are at seed / length).

    - `in_place`: True (default): the registration's rotation is undone gradually (step τ is
      turned about its base by the fraction τ of the inverse rotation), so the path starts at a
      and ends at b as given, where they lie. False: the path ends at b as registered (rotated
      about its base onto a), the usual picture of a shape-space geodesic. Rotations are
      quotiented out of the shape space, so both are the same shape path.
    - `sizes`: ``(length_a, length_b)``, the lengths `batch(normalise_scale=True)` divided a
      and b by: ``normalising_length(root_a, n_points)``, the main root's length resampled at
      the trees' `n_points` (a little shorter than `Root.main_length`, the raw polyline's,
      which would shift the path by the difference times the seed's distance from (0, 0)).
      That division is about
      (0, 0), so a's seed went to ``seed_a / length_a``; here step τ is scaled back about its
      base by ``(1 − τ) length_a + τ length_b`` and its base put at
      ``(1 − τ) seed_a + τ seed_b``: the path runs between the roots at their real sizes and
      positions. Leave it None for roots that were not scale-normalised.
    """
    n_steps = as_count(n_steps, "n_steps", minimum=2)
    for name, x in (("a", a), ("b", b)):
        if not isinstance(x, (RootTree, SRVFTree)):
            raise TypeError(
                f"geodesic: {name} must be a RootTree or SRVFTree, got {type(x).__name__}; "
                "build trees with rootshape_jax.batch(roots) and pick two with rootshape_jax.unstack."
            )
        if x.batch_shape != ():
            raise ValueError(
                f"geodesic works on one pair of roots, but {name} is a batch of shape {x.batch_shape}: pick "
                "single trees with rootshape_jax.unstack(trees)[i]; loop or vmap over pairs."
            )
    if sizes is not None:
        try:
            la, lb = (float(x) for x in sizes)
        except (TypeError, ValueError):
            la = lb = float("nan")
        if not (la > 0 and lb > 0 and jnp.isfinite(la) and jnp.isfinite(lb)):
            raise ValueError(f"sizes must be two positive main-root lengths (length_a, length_b), got {sizes!r}.")
    given = isinstance(registration, Registration)
    if registration is None or isinstance(registration, (RegistrationOptions, Mapping)):
        # Options, as `registration=` means in every other call: register with them.
        registration = register(a, b, weights=weights, registration=registration, **options)
    elif not given:
        raise TypeError(
            "geodesic: registration must be the Registration of b onto a (rootshape_jax.register(a, b)) "
            f"or registration options (RegistrationOptions or a dict), got a {type(registration).__name__}."
        )
    weights = as_weights(weights)
    # Whether a has a thickness channel is decided here, on concrete weights (static below).
    thick = registration.registered.has_thickness
    if given:
        _require_registration_of(a, b, registration, weights, thick)
    path = _geodesic_curves(a, b, registration, n_steps, weights if thick else None)
    taus = jnp.linspace(0.0, 1.0, n_steps, dtype=path.main.dtype)
    if in_place:
        path = _unrotate(path, registration.rotation, taus)
    if sizes is not None:
        # The stored seeds are seed / length (normalised about (0, 0)): scaled back, they are
        # the data's seeds, and the path's bases run on the straight line between them.
        seeds = (1 - taus)[:, None] * (la * path.main[0, 0]) + taus[:, None] * (lb * path.main[-1, 0])
        path = scale_tree(path, (1 - taus) * la + taus * lb, base=seeds)
    return path


def _require_registration_of(a, b, registration: Registration, weights: Weights, thick: bool) -> None:
    """A `Registration` given to `geodesic` must be of this b onto this a at these weights:
    applied to b again, it gives its own `registered` tree and energy. Another pair's (of the
    same batch, so of the same shapes) would give a path between other roots' shapes without
    any error. Not checked under jit (traced values)."""
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(registration)):
        return
    sa, sb = (to_srvf(x, weights=weights if thick else None) for x in (a, b))
    reg = registration
    shapes = (reg.permutation.shape, reg.main_warp.shape, reg.rotation.shape)
    if shapes != ((sa.capacity,), (sa.n_points,), (sa.dim, sa.dim)):
        raise ValueError(
            f"geodesic: registration has the shapes of another batch (permutation, warp, rotation {shapes}); "
            "pass rootshape_jax.register(a, b) of these two trees, or leave registration out."
        )
    children = tuple(zip(reg.child_permutations, reg.child_warps))
    again = apply_registration(sa, sb, reg.rotation, reg.permutation, reg.main_warp, reg.lateral_warps, children)
    energy = float(preshape_terms(sa, again, weights).total)
    # The size of the SRVFs (a plant's virtual main root is all zeros: its laterals set it).
    scale = max(float(jnp.max(jnp.abs(x))) for x in (reg.registered.q0, reg.registered.q)) + 1e-30
    same = bool(jnp.allclose(again.q0, reg.registered.q0, atol=1e-3 * scale, rtol=0)) and bool(
        jnp.allclose(again.q, reg.registered.q, atol=1e-3 * scale, rtol=0)
    )
    if not same or abs(energy - float(reg.energy)) > 1e-3 * abs(float(reg.energy)) + 1e-6 * scale**2:
        raise ValueError(
            f"geodesic: registration is not the registration of b onto a at these weights (applied to "
            f"b again it gives d² = {energy:.6g}, not its own {float(reg.energy):.6g}): it was computed for "
            "another pair, in the other order, or with other weights. Pass rootshape_jax.register(a, b, "
            "weights=weights), or leave registration out."
        )


def fractional_rotation(R, t):
    """``R^t``: the rotation by the fraction t of R's angle about R's axis (d = 2 or 3)."""
    if R.shape[-1] == 2:
        theta = jnp.arctan2(R[1, 0], R[0, 0]) * t
        c, s = jnp.cos(theta), jnp.sin(theta)
        return jnp.array([[c, -s], [s, c]])
    # Axis-angle (Rodrigues). Near angle 0 any axis works; near π the axis comes from R + I.
    cos = jnp.clip((jnp.trace(R) - 1) / 2, -1.0, 1.0)
    angle = jnp.arccos(cos)
    w = jnp.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sym = (R + jnp.eye(3)) / 2
    col = sym[:, jnp.argmax(jnp.diag(sym))]
    axis = jnp.where(jnp.linalg.norm(w) > 1e-6, w, col)
    axis = axis / jnp.maximum(jnp.linalg.norm(axis), 1e-30)
    return axis_angle_rotation(axis, angle * t)


def _unrotate(path: RootTree, rotation, taus) -> RootTree:
    """Turn step τ about its base by ``(Rᵀ)^τ``: the last step is b in its own pose (the
    registration put ``o + R (b − o)`` there)."""
    Rs = jax.vmap(lambda t: fractional_rotation(rotation, t))(taus)  # [S, d, d]
    return turn_about_base(path, jnp.swapaxes(Rs, -1, -2))


def unwarped_end(sa: SRVFTree, sb: SRVFTree, registration: Registration) -> SRVFTree:
    """b moved by the registration's rotation and correspondences but not reparameterised.

    Reparameterising does not change a curve's shape, but on the grid a steep warp (slope up
    to `neighbourhood`) skips nodes of b, and the curve rebuilt from the warped SRVF cuts
    those corners: a RootNav lateral came back 8 % shorter at the path's end. Without the
    warps the last step is b's own SRVF, as the first step is a's, so both ends differ from
    the inputs by no more than a root's own SRVF round trip."""
    T = sa.q0.shape[-2]
    same = jnp.linspace(0.0, 1.0, T, dtype=sa.q0.dtype)
    children = tuple((pm, jnp.broadcast_to(same, pm.shape + (T,))) for pm in registration.child_permutations)
    perm = registration.permutation
    return apply_registration(
        sa, sb, registration.rotation, perm, same, jnp.broadcast_to(same, perm.shape + (T,)), children
    )


@eqx.filter_jit
def _geodesic_curves(
    a: RootTree | SRVFTree, b: RootTree | SRVFTree, registration: Registration, n_steps: int, weights: Weights | None
) -> RootTree:
    # One compiled program, SRVF conversion included (eagerly it costs more than the path).
    sa = to_srvf(a, weights=weights)
    taus = jnp.linspace(0.0, 1.0, n_steps, dtype=sa.q0.dtype)
    path = geodesic_srvf(sa, registration.registered, taus)
    end = unwarped_end(sa, to_srvf(b, weights=weights), registration)
    # The last step's curves from b unwarped (its attachments, masks and radii are the same).
    path = eqx.tree_at(lambda t: (t.q0, t.q), path, (path.q0.at[-1].set(end.q0), path.q.at[-1].set(end.q)))
    if path.deeper:
        levels = tuple(
            eqx.tree_at(lambda lv: lv.q, lv, lv.q.at[-1].set(le.q)) for lv, le in zip(path.deeper, end.deeper)
        )
        path = eqx.tree_at(lambda t: t.deeper, path, levels)
    return to_curves(path)
