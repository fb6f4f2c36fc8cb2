"""Deterministic synthetic root populations with biologically named parameters.

**Coordinates and units.** Millimetres. Gravity points along the *last* axis, which grows
downward, as in scanner images and most RSML files: in 2D a point is ``(x, y)`` with ``y``
the depth below the root base; in 3D it is ``(x, y, z)`` with ``z`` the depth and ``(x, y)``
the horizontal plane. Every root's base (collar) is at the origin and the main root grows
towards +y (2D) or +z (3D).

**Growth model.** Each branch is a random walk of its unit heading ``h``, one step of length
``Δ ≈ segment_length`` at a time:

    h ← normalise(h + g Δ (down − (h·down) h) + τ √Δ ξ⊥),

where ``g`` is the branch's *gravitropism* (pull of the heading toward straight down, per mm),
``τ`` its *tortuosity* (random bending, rad / √mm) and ``ξ⊥`` a standard normal vector projected
perpendicular to ``h``. The polyline has exactly the sampled length.

Laterals emerge in the *branched zone*, between ``basal_zone`` mm below the base and
``apical_zone`` mm above the tip (the apical unbranched zone, where no lateral has emerged yet).
Their number is Poisson with mean ``lateral_density × branched-zone length`` (capped at
``max_laterals``), their positions uniform in that zone. Older laterals are longer: the mean
length falls linearly from ``lateral_length_base`` at the top of the zone to
``lateral_length_tip`` at its bottom, times a log-normal factor of mean 1 and coefficient of
variation ``lateral_length_cv``. A lateral starts exactly on the main root polyline at its
attachment fraction (given to `Root` exactly) with an insertion angle (between its initial
heading and the main root's local heading) drawn from N(``insertion_angle_mean``,
``insertion_angle_sd``). In 2D it goes left or right (``side_pattern``); in 3D its azimuth
around the main root is uniform.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import zlib

import numpy as np

from .._root import Root

_SIDE_PATTERNS = ("alternate", "random")


@dataclasses.dataclass(frozen=True)
class RootParameters:
    """Parameters of the synthetic root generator (lengths in mm, angles in degrees).

    **Main root**

    - `main_length_mean`, `main_length_sd`: main root length ~ Normal(mean, sd), truncated below
      at 20 % of the mean.
    - `main_tortuosity`: random bending of the main root's heading (rad / √mm).
    - `main_gravitropism`: pull of the main root's heading toward straight down (per mm).
    - `main_initial_angle_sd`: spread of the main root's initial heading around straight down.

    **Branching**

    - `basal_zone`: unbranched length just below the base.
    - `apical_zone`: unbranched length at the tip (young tissue without laterals yet).
    - `lateral_density`: mean number of laterals per mm of branched zone (Poisson).
    - `max_laterals`: hard cap on the number of laterals (keeps padded capacities small).

    **Laterals**

    - `lateral_length_base`, `lateral_length_tip`: mean lateral length at the top and at the
      bottom of the branched zone (linear in between: older laterals are longer).
    - `lateral_length_cv`: coefficient of variation of the log-normal length noise.
    - `lateral_min_length`: laterals shorter than this are lengthened to it.
    - `insertion_angle_mean`, `insertion_angle_sd`: angle between a lateral's initial heading
      and the main root's local heading (clipped to [0, 180]).
    - `side_pattern`: 2D only — ``"alternate"`` (left/right alternately along the main root,
      random first side) or ``"random"``. In 3D the azimuth is uniform.
    - `lateral_tortuosity`, `lateral_gravitropism`: as for the main root.

    **Higher orders** (used with ``synthetic_roots(..., depth=3)`` or more)

    - `sub_lateral_density`: mean number of laterals per mm on a lateral (Poisson), between 10 %
      and 80 % of its length.
    - `sub_lateral_length_ratio`: mean length of a sub-lateral as a fraction of the parent's
      length still ahead of its attachment point (older ones are longer), times the same
      log-normal noise as the laterals.

    **Discretisation**

    - `segment_length`: target distance between polyline points.
    """

    main_length_mean: float = 120.0
    main_length_sd: float = 15.0
    main_tortuosity: float = 0.04
    main_gravitropism: float = 0.05
    main_initial_angle_sd: float = 5.0
    basal_zone: float = 5.0
    apical_zone: float = 20.0
    lateral_density: float = 0.18
    max_laterals: int = 30
    lateral_length_base: float = 40.0
    lateral_length_tip: float = 5.0
    lateral_length_cv: float = 0.15
    lateral_min_length: float = 1.0
    insertion_angle_mean: float = 60.0
    insertion_angle_sd: float = 10.0
    side_pattern: str = "alternate"
    lateral_tortuosity: float = 0.012
    lateral_gravitropism: float = 0.01
    segment_length: float = 2.0
    sub_lateral_density: float = 0.08
    sub_lateral_length_ratio: float = 0.3

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "side_pattern":
                if value not in _SIDE_PATTERNS:
                    raise ValueError(f"RootParameters.side_pattern must be one of {_SIDE_PATTERNS}, got {value!r}.")
                continue
            if not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value):
                raise ValueError(f"RootParameters.{f.name} must be a finite number, got {value!r}.")
            if value < 0:
                raise ValueError(f"RootParameters.{f.name} must be >= 0, got {value!r}.")
        for name in ("main_length_mean", "segment_length", "lateral_min_length"):
            if getattr(self, name) <= 0:
                raise ValueError(f"RootParameters.{name} must be > 0, got {getattr(self, name)!r}.")
        if int(self.max_laterals) != self.max_laterals:
            raise ValueError(f"RootParameters.max_laterals must be an integer, got {self.max_laterals!r}.")
        if self.insertion_angle_mean > 180:
            raise ValueError(
                "RootParameters.insertion_angle_mean is in degrees and must lie in [0, 180], "
                f"got {self.insertion_angle_mean!r}."
            )


# Named treatments, written as differences from the control so the direction of each effect
# is visible (and tested in tests/test_datasets.py). The effects are strong enough, and the
# within-condition noise (lateral length spread, bending) low enough, that the conditions
# separate under the elastic metric about as the paper's wheat conditions did: on the default
# data set (T = 50, scale-normalised) LOO 1-NN accuracy 100 %, average-linkage purity 94 %,
# PERMANOVA R² 0.76 (BENCHMARKS.md, "Synthetic conditions").
_CONTROL = RootParameters()
CONDITIONS: dict[str, RootParameters] = {
    "control": _CONTROL,
    # Water deficit: the main root grows deeper and steeper; fewer, shorter laterals.
    "drought": dataclasses.replace(
        _CONTROL,
        main_length_mean=150.0,
        main_length_sd=18.0,
        main_gravitropism=0.08,
        lateral_density=0.045,
        lateral_length_base=12.0,
        lateral_length_tip=3.0,
    ),
    # Nitrate-rich patch / high N: more and longer laterals, a shorter main root.
    "high_nitrate": dataclasses.replace(
        _CONTROL,
        main_length_mean=100.0,
        main_length_sd=5.0,
        apical_zone=15.0,
        lateral_density=0.36,
        lateral_length_base=55.0,
        lateral_length_tip=12.0,
        lateral_length_cv=0.1,
    ),
    # Phosphate starvation: primary root growth is inhibited, laterals proliferate and grow
    # shallower.
    "low_phosphate": dataclasses.replace(
        _CONTROL,
        main_length_mean=70.0,
        main_length_sd=10.0,
        apical_zone=10.0,
        lateral_density=0.42,
        lateral_length_base=30.0,
        lateral_length_tip=5.0,
        insertion_angle_mean=75.0,
        lateral_gravitropism=0.003,
    ),
}


def _resolve(condition, overrides: dict) -> tuple[str, RootParameters]:
    if isinstance(condition, RootParameters):
        name, params = "custom", condition
    elif isinstance(condition, str):
        if condition not in CONDITIONS:
            raise ValueError(
                f"Unknown condition {condition!r}; choose one of {sorted(CONDITIONS)} or pass a "
                "RootParameters instance."
            )
        name, params = condition, CONDITIONS[condition]
    else:
        raise ValueError(f"`condition` must be a condition name or a RootParameters, got {type(condition).__name__}.")
    if overrides:
        valid = {f.name for f in dataclasses.fields(RootParameters)}
        unknown = sorted(set(overrides) - valid)
        if unknown:
            raise ValueError(f"Unknown root parameter(s) {unknown}; valid names are {sorted(valid)}.")
        params = dataclasses.replace(params, **overrides)
    return name, params


def _perpendicular_noise(rng: np.random.Generator, heading: np.ndarray) -> np.ndarray:
    xi = rng.standard_normal(heading.shape[0])
    return xi - (xi @ heading) * heading


def _grow(
    rng: np.random.Generator,
    start: np.ndarray,
    heading: np.ndarray,
    length: float,
    *,
    step: float,
    tortuosity: float,
    gravitropism: float,
) -> np.ndarray:
    """Polyline of exactly ``length`` from ``start``, bending by the heading random walk."""
    dim = start.shape[0]
    down = np.zeros(dim)
    down[-1] = 1.0
    n_seg = max(2, math.ceil(length / step))
    h = length / n_seg
    points = np.empty((n_seg + 1, dim))
    points[0] = start
    d = heading / np.linalg.norm(heading)
    for k in range(n_seg):
        points[k + 1] = points[k] + h * d
        d = d + gravitropism * h * (down - (d @ down) * d) + tortuosity * math.sqrt(h) * _perpendicular_noise(rng, d)
        d = d / np.linalg.norm(d)
    return points


def _rotate_from_down(rng: np.random.Generator, dim: int, angle_sd_deg: float) -> np.ndarray:
    down = np.zeros(dim)
    down[-1] = 1.0
    tilt = math.radians(abs(rng.normal(0.0, angle_sd_deg)))
    if dim == 2:
        side = 1.0 if rng.random() < 0.5 else -1.0
        return np.array([side * math.sin(tilt), math.cos(tilt)])
    phi = rng.uniform(0.0, 2 * math.pi)
    return np.array([math.sin(tilt) * math.cos(phi), math.sin(tilt) * math.sin(phi), math.cos(tilt)])


def _lateral_heading(tangent: np.ndarray, angle_deg: float, side: float, azimuth: float) -> np.ndarray:
    """Unit heading at ``angle_deg`` from ``tangent``; 2D uses ``side`` (±1), 3D ``azimuth``."""
    a = math.radians(angle_deg)
    if tangent.shape[0] == 2:
        normal = side * np.array([-tangent[1], tangent[0]])
    else:
        helper = np.eye(3)[int(np.argmin(np.abs(tangent)))]
        e1 = helper - (helper @ tangent) * tangent
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(tangent, e1)
        normal = math.cos(azimuth) * e1 + math.sin(azimuth) * e2
    return math.cos(a) * tangent + math.sin(a) * normal


def _one_root(rng: np.random.Generator, p: RootParameters, dim: int) -> tuple[np.ndarray, list, np.ndarray]:
    main_len = max(rng.normal(p.main_length_mean, p.main_length_sd), 0.2 * p.main_length_mean)
    main = _grow(
        rng,
        np.zeros(dim),
        _rotate_from_down(rng, dim, p.main_initial_angle_sd),
        main_len,
        step=p.segment_length,
        tortuosity=p.main_tortuosity,
        gravitropism=p.main_gravitropism,
    )
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(main, axis=0), axis=1))])
    total = cum[-1]

    zone_top, zone_bottom = p.basal_zone, total - p.apical_zone
    zone = zone_bottom - zone_top
    n_lat = 0
    if zone > 0:
        n_lat = min(int(rng.poisson(p.lateral_density * zone)), int(p.max_laterals))
    positions = np.sort(rng.uniform(zone_top, zone_bottom, size=n_lat))

    sigma2 = math.log1p(p.lateral_length_cv**2)
    first_side = 1.0 if rng.random() < 0.5 else -1.0
    laterals, attach = [], []
    for k, pos in enumerate(positions):
        u = (pos - zone_top) / zone
        mean_len = (1 - u) * p.lateral_length_base + u * p.lateral_length_tip
        noise = rng.lognormal(-sigma2 / 2, math.sqrt(sigma2))
        length = max(mean_len * noise, p.lateral_min_length)
        angle = float(np.clip(rng.normal(p.insertion_angle_mean, p.insertion_angle_sd), 0.0, 180.0))
        if p.side_pattern == "alternate":
            side = first_side * (1.0 if k % 2 == 0 else -1.0)
        else:
            side = 1.0 if rng.random() < 0.5 else -1.0
        azimuth = rng.uniform(0.0, 2 * math.pi)

        seg = min(int(np.searchsorted(cum, pos, side="right")) - 1, len(main) - 2)
        tangent = main[seg + 1] - main[seg]
        tangent /= np.linalg.norm(tangent)
        base = main[seg] + (pos - cum[seg]) * tangent
        heading = _lateral_heading(tangent, angle, side, azimuth)
        laterals.append(
            _grow(
                rng,
                base,
                heading,
                length,
                step=p.segment_length,
                tortuosity=p.lateral_tortuosity,
                gravitropism=p.lateral_gravitropism,
            )
        )
        attach.append(pos / total)
    return main, laterals, np.asarray(attach, dtype=float)


def _sub_laterals(rng: np.random.Generator, parent: np.ndarray, p: RootParameters, levels: int) -> Root:
    """`parent` as a `Root` with `levels` more orders of laterals grown on it (0: none)."""
    if levels == 0:
        return Root(main=parent)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(parent, axis=0), axis=1))])
    total = cum[-1]
    top, bottom = 0.1 * total, 0.8 * total
    n_sub = min(int(rng.poisson(p.sub_lateral_density * (bottom - top))), int(p.max_laterals))
    positions = np.sort(rng.uniform(top, bottom, size=n_sub))
    sigma2 = math.log1p(p.lateral_length_cv**2)
    laterals, attach, kids = [], [], []
    for pos in positions:
        noise = rng.lognormal(-sigma2 / 2, math.sqrt(sigma2))
        length = max(p.sub_lateral_length_ratio * (total - pos) * noise, p.lateral_min_length)
        angle = float(np.clip(rng.normal(p.insertion_angle_mean, p.insertion_angle_sd), 0.0, 180.0))
        side = 1.0 if rng.random() < 0.5 else -1.0
        azimuth = rng.uniform(0.0, 2 * math.pi)
        seg = min(int(np.searchsorted(cum, pos, side="right")) - 1, len(parent) - 2)
        tangent = parent[seg + 1] - parent[seg]
        tangent /= np.linalg.norm(tangent)
        base = parent[seg] + (pos - cum[seg]) * tangent
        lat = _grow(
            rng,
            base,
            _lateral_heading(tangent, angle, side, azimuth),
            length,
            step=min(p.segment_length, length / 2),
            tortuosity=p.lateral_tortuosity,
            gravitropism=p.lateral_gravitropism,
        )
        laterals.append(lat)
        attach.append(pos / total)
        kids.append(_sub_laterals(rng, lat, p, levels - 1))
    return Root(main=parent, laterals=tuple(laterals), attach=np.asarray(attach, dtype=float), children=tuple(kids))


def _stream(seed: int, condition: str, index: int) -> np.random.Generator:
    # One independent stream per (seed, condition, index): root i does not depend on n, and
    # the same seed gives unrelated noise in different conditions.
    key = zlib.crc32(condition.encode())
    return np.random.default_rng(np.random.SeedSequence([int(seed), key, int(index)]))


def synthetic_roots(
    n: int,
    *,
    condition: str | RootParameters = "control",
    seed: int = 0,
    dim: int = 2,
    depth: int = 2,
    **overrides,
) -> list[Root]:
    """Generate ``n`` synthetic root systems (main root + first-order laterals), deterministically.

    **Arguments**

    - `n`: number of roots.
    - `condition`: a name from `CONDITIONS` (``"control"``, ``"drought"``, ``"high_nitrate"``,
      ``"low_phosphate"``) or a `RootParameters` instance.
    - `seed`: seed of NumPy's generator. Root ``i`` depends only on (seed, condition, i), so
      ``synthetic_roots(5, seed=s)[:3] == synthetic_roots(3, seed=s)``.
    - `dim`: 2 for ``(x, y)`` with y down, 3 for ``(x, y, z)`` with z down.
    - `depth`: 2 (default) for main root + first-order laterals; 3 also grows second-order
      laterals on every lateral (kept in `Root.children`, see the "Higher orders" parameters),
      4 third-order ones, and so on. Higher orders come from a random stream of their own, so
      the main root and first-order laterals are those of ``depth=2``, bit for bit.
    - `**overrides`: any `RootParameters` field, replacing the condition's value, e.g.
      ``synthetic_roots(10, lateral_density=0.3)``.

    **Returns** a list of `Root` (units mm) named ``"{condition}_s{seed}_{i:03d}"`` with
    ``metadata = {"condition", "seed", "index", "unit": "mm", "source": "synthetic"}``.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"`n` must be a non-negative integer number of roots, got {n!r}.")
    if dim not in (2, 3):
        raise ValueError(f"`dim` must be 2 or 3, got {dim!r}.")
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 2:
        raise ValueError(f"`depth` must be an integer >= 2 (2 = main root + laterals), got {depth!r}.")
    name, params = _resolve(condition, overrides)
    roots = []
    for i in range(int(n)):
        main, laterals, attach = _one_root(_stream(seed, name, i), params, dim)
        children = ()
        if depth > 2:
            sub = np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(name.encode()), i, 2]))
            children = tuple(_sub_laterals(sub, lat, params, int(depth) - 2) for lat in laterals)
        roots.append(
            Root(
                main=main,
                laterals=tuple(laterals),
                attach=attach,
                children=children,
                name=f"{name}_s{seed}_{i:03d}",
                metadata={
                    "condition": name,
                    "seed": int(seed),
                    "index": i,
                    "unit": "mm",
                    "source": "synthetic",
                },
            )
        )
    return roots


# The paper's data set has 53 wheat roots; ours mixes three treatments.
DEFAULT_COMPOSITION: dict[str, int] = {"control": 18, "drought": 18, "high_nitrate": 17}
_DEFAULT_SEED = 2023


@functools.lru_cache(maxsize=2)
def _default_dataset_cached(dim: int) -> tuple[Root, ...]:
    roots = []
    for condition, count in DEFAULT_COMPOSITION.items():
        roots.extend(synthetic_roots(count, condition=condition, seed=_DEFAULT_SEED, dim=dim))
    for r in roots:  # shared by every caller: make the cached arrays read-only
        r.main.flags.writeable = False
        for lat in r.laterals:
            lat.flags.writeable = False
        r.attach.flags.writeable = False
    return tuple(roots)


def default_dataset(*, dim: int = 2) -> list[Root]:
    """The bundled default data set: 53 synthetic roots (18 control, 18 drought, 17 high_nitrate).

    Generated deterministically on first use and cached in memory (arrays are read-only).
    Labels are in each root's metadata: ``[r.metadata["condition"] for r in roots]``.
    """
    if dim not in (2, 3):
        raise ValueError(f"`dim` must be 2 or 3, got {dim!r}.")
    # Fresh Root objects (fresh metadata dicts) around the shared read-only arrays.
    return [dataclasses.replace(r) for r in _default_dataset_cached(dim)]
