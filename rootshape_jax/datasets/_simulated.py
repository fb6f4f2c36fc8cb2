"""Simulated root systems from CPlantBox (optional extra ``sim``: ``pip install 'rootshape_jax[sim]'``).

Each plant is simulated with one of the root-system parameter files that CPlantBox ships
(``plantbox/modelparameter/structural/rootsystem/*.xml``), written to RSML in a temporary
folder and read back with `rootshape_jax.io.read_rsml` — the same path real data takes.

CPlantBox notes (cplantbox 2.1): ``pb.RootSystem`` is used, although it prints a deprecation
notice, because ``pb.Plant`` loaded with these root-system files writes an RSML without any
root. The random generator is per simulation and seeded by ``setSeed`` after
``readParameters``: the same seed gives the same plant whatever was simulated before.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import os
import pathlib
import sys
import tempfile
import warnings

import numpy as np

from .._errors import InvalidRootError, MissingDependencyError, RSMLWarning
from .._root import Root

# Short names for common crops -> CPlantBox parameter file (without ".xml").
SPECIES_ALIASES: dict[str, str] = {
    "wheat": "wheat",
    "maize": "Zea_mays_4_Leitner_2014",
    "lupin": "Lupinus_albus_Leitner_2014",
    "pea": "Pisum_sativum_a_Pagès_2014",
    "soybean": "Glycine_max",
    "barley": "spring_barley_CF12",
    "rapeseed": "Brassica_napus_a_Leitner_2010",
    "sunflower": "Heliantus_Pagès_2013",
    "carrot": "Daucus_carota",
    "faba": "Faba_synMRI",
}

_UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def _plantbox():
    try:
        import plantbox
    except ImportError as e:
        raise MissingDependencyError(
            "Simulated roots need CPlantBox, an optional extra: pip install 'rootshape_jax[sim]' "
            f"(PyPI package `cplantbox`, imported as `plantbox`). Import failed with: {e}"
        ) from e
    return plantbox


def _parameter_dir() -> pathlib.Path:
    return pathlib.Path(_plantbox().data_path()) / "structural" / "rootsystem"


def available_species() -> list[str]:
    """Names accepted by `simulated_roots`: the short aliases (``"wheat"``, ``"maize"``,
    ``"lupin"``, ...) followed by every root-system parameter file CPlantBox ships (file name
    without ``.xml``). Raises `MissingDependencyError` when CPlantBox is not installed."""
    files = sorted(p.stem for p in _parameter_dir().glob("*.xml"))
    return list(SPECIES_ALIASES) + [f for f in files if f not in SPECIES_ALIASES]


def _parameter_file(species: str) -> pathlib.Path:
    as_path = pathlib.Path(species)
    if as_path.suffix == ".xml" and as_path.is_file():
        return as_path
    path = _parameter_dir() / f"{SPECIES_ALIASES.get(species, species)}.xml"
    if not path.is_file():
        raise ValueError(
            f"Unknown species {species!r}: not an alias, not a CPlantBox parameter set and not an "
            f"existing .xml file. Choose from available_species(), e.g. {list(SPECIES_ALIASES)}."
        )
    return path


@contextlib.contextmanager
def _silence_native(enabled: bool):
    """Send the C++ library's prints on file descriptors 1 and 2 to /dev/null."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)  # C stdio buffers still aimed at /dev/null
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _plant_seed(seed: int, index: int) -> int:
    state = np.random.SeedSequence([int(seed), int(index)]).generate_state(1, np.uint32)[0]
    return int(state) & 0x7FFFFFFF


def _cumlen(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _join_to_parent(root: Root) -> Root:
    """Give every lateral back its branching point, recursively.

    CPlantBox's RSML omits a lateral's first node, which is the parent node ``parent-node``,
    so read as is a lateral starts one segment away from its parent. Prepending that node
    restores CPlantBox's own geometry: the lateral starts exactly on its parent, at the
    arc-length fraction of that node.
    """
    if not root.children:
        return root
    main = root.main
    cum = _cumlen(main)
    lats, attach, kids, radii = [], [], [], []
    for k, (lat, a, child) in enumerate(zip(root.laterals, root.attach, root.children)):
        child = _join_to_parent(child)
        radius = root.lateral_radii[k] if root.lateral_radii is not None else None
        pn = child.metadata.get("parent_node")
        if isinstance(pn, (int, np.integer)) and 0 <= pn < len(main) and cum[-1] > 0:
            base = main[pn]
            a = cum[pn] / cum[-1]
            if np.any(lat[0] != base):
                old_len = _cumlen(lat)[-1]
                lat = np.vstack([base[None, :], lat])
                new_len = _cumlen(lat)[-1]
                # The new first segment has the lateral's own (base) radius.
                if radius is not None:
                    radius = np.concatenate([radius[:1], radius])
                child_radius = child.main_radius
                if child_radius is not None:
                    child_radius = np.concatenate([child_radius[:1], child_radius])
                # The child's own laterals keep their points; their fractions move along.
                child_attach = (child.attach * old_len + (new_len - old_len)) / new_len
                child = dataclasses.replace(
                    child, main=lat, attach=np.clip(child_attach, 0.0, 1.0), main_radius=child_radius
                )
        lats.append(lat)
        attach.append(a)
        kids.append(child)
        radii.append(radius)
    return dataclasses.replace(
        root,
        laterals=tuple(lats),
        attach=np.asarray(attach, dtype=main.dtype),
        children=tuple(kids),
        lateral_radii=tuple(radii) if root.lateral_radii is not None else None,
    )


def _to_library_frame(root: Root, scale: float, dim: int) -> Root:
    """CPlantBox's frame (cm, z up) -> ours (mm, depth down) by a 180° rotation about x (no
    mirror image); ``dim = 2`` then keeps (x, depth), the front view of a rhizobox or scan."""
    m = np.diag([scale, -scale, -scale])[:, [0, 2] if dim == 2 else [0, 1, 2]]
    # The RSML's resolution and (temporary) file name no longer describe these coordinates.
    metadata = {k: v for k, v in root.metadata.items() if k not in ("resolution", "file")}
    metadata["unit"] = "mm"
    return dataclasses.replace(
        root,
        metadata=metadata,
        main=root.main @ m,
        laterals=tuple(lat @ m for lat in root.laterals),
        children=tuple(_to_library_frame(c, scale, dim) for c in root.children),
        main_radius=None if root.main_radius is None else root.main_radius * scale,
        lateral_radii=(None if root.lateral_radii is None else tuple(r * scale for r in root.lateral_radii)),
    )


def simulated_roots(
    species: str,
    n: int,
    *,
    days: float = 21.0,
    seed: int = 0,
    dim: int = 3,
    by: str = "root",
    verbose: bool = False,
) -> list[Root]:
    """Simulate ``n`` plants with CPlantBox and return each plant's primary root system, or
    with ``by="plant"`` its whole root system.

    **Arguments**

    - `species`: an alias (``"wheat"``, ``"maize"``, ``"lupin"``, ``"pea"``, ``"soybean"``,
      ``"barley"``, ...), any name from `available_species`, or a path to a CPlantBox
      root-system ``.xml`` parameter file.
    - `n`: number of plants.
    - `days`: simulated growth time in days.
    - `seed`: plant ``i`` is simulated with a CPlantBox seed derived from ``(seed, i)``, so the
      output is deterministic and plant ``i`` does not depend on ``n``.
    - `dim`: 3, or 2 for the projection on the vertical (x, depth) plane — what a flatbed scan
      or a rhizobox photograph of the plant would show.
    - `by`: ``"root"`` (default): each plant's first top-level root, the primary / tap root
      (CPlantBox writes it first). ``"plant"``: every top-level root of the plant (the tap
      root, and the basal, seminal or shoot-borne roots when the species has them) as one
      system around a virtual main root of zero length at the collar, as
      ``read_rsml(by="plant")`` reads a plant (`rootshape_jax.io.plant_system`; the axes are
      its laterals at ``attach = 0``, ``metadata["n_axes"]`` counts them).
    - `verbose`: let CPlantBox print its messages (silenced by default).

    **Returns** one `Root` per plant, with every order CPlantBox simulated: a branch's own
    laterals are in `Root.children` (second-order laterals of the tap root, ...), so
    ``batch(roots, depth=3)`` (or more) keeps them. Coordinates are converted to the
    library's convention — millimetres, ``(x, y, z)`` with z the depth growing downward
    (CPlantBox writes cm with z up: a 180° rotation about x, no mirror image); in 2D,
    ``(x, y)`` with y the depth. CPlantBox's RSML leaves out each lateral's branching node;
    it is put back, so every lateral starts exactly on its parent, at the arc-length fraction
    of its RSML ``parent-node`` (laterals of a single node, just emerged, are dropped).
    Radii: CPlantBox gives each root one radius (its ``diameter`` RSML property, from the
    parameter ``a``); it is kept as a constant `Root.main_radius` / `Root.lateral_radii` per
    branch, in mm (the branching point put back takes the lateral's radius). Metadata:
    ``species``, ``parameter_file``, ``days``, ``seed``, ``index``, ``cplantbox_seed``,
    ``unit = "mm"``, ``source = "cplantbox"``, plus what the RSML reader records.

    Raises `MissingDependencyError` without CPlantBox, ``ValueError`` for an unknown species,
    and `InvalidRootError` if a simulated plant has no root with geometry yet (too few days).
    """
    pb = _plantbox()
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"`n` must be a non-negative integer number of plants, got {n!r}.")
    if by not in ("root", "plant"):
        raise ValueError(f"`by` must be 'root' (the primary root) or 'plant' (every axis), got {by!r}.")
    if dim not in (2, 3):
        raise ValueError(f"`dim` must be 2 or 3, got {dim!r}.")
    if not np.isfinite(days) or days <= 0:
        raise ValueError(f"`days` must be a positive simulation time in days, got {days!r}.")
    param_file = _parameter_file(species)
    from ..io import read_rsml  # imported here: the io layer is not needed to list species

    roots = []
    with tempfile.TemporaryDirectory(prefix="rootshape_cplantbox_") as tmp:
        for i in range(int(n)):
            plant_seed = _plant_seed(seed, i)
            out = os.path.join(tmp, f"plant_{i}.rsml")
            with _silence_native(not verbose):
                rs = pb.RootSystem()
                rs.readParameters(str(param_file))
                rs.setSeed(plant_seed)
                rs.initialize(verbose)
                rs.simulate(float(days), verbose)
                rs.writeRSML(out)
            with warnings.catch_warnings():
                # CPlantBox writes just-emerged laterals as one-point polylines; the reader
                # drops them with a warning that says nothing useful here.
                warnings.simplefilter("ignore", RSMLWarning)
                read = read_rsml(out, strict=False, by=by)
            if not read:
                raise InvalidRootError(
                    f"CPlantBox produced no root with geometry for species {species!r} after "
                    f"{days} days (seed {seed}, plant {i}); simulate for more days."
                )
            first = read[0]
            unit = str(first.metadata.get("unit", "cm")).lower()  # CPlantBox writes cm
            if unit not in _UNIT_TO_MM:
                raise InvalidRootError(
                    f"CPlantBox's RSML reads back in unit {unit!r}; expected one of {list(_UNIT_TO_MM)}."
                )
            scale = _UNIT_TO_MM[unit]
            root = _join_to_parent(_to_library_frame(first, scale, dim))
            metadata = dict(root.metadata)
            metadata.update(
                species=species,
                parameter_file=param_file.name,
                days=float(days),
                seed=int(seed),
                index=i,
                cplantbox_seed=plant_seed,
                unit="mm",
                source="cplantbox",
            )
            roots.append(dataclasses.replace(root, name=f"{param_file.stem}_s{seed}_{i:03d}", metadata=metadata))
    return roots
