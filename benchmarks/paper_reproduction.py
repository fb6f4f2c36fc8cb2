"""Reproduce the experiments of the paper's Section 6 with the two comparison methods (issue 7).

    python benchmarks/paper_reproduction.py [--tiny] [--out DIR] [--T 50] [--no-cache]

Writes ``DIR/paper_reproduction.md`` (default DIR: benchmarks/results), its figures in
``DIR/paper_reproduction/`` and every number in ``DIR/paper_reproduction.json``:

(a) geodesics between pairs of the bundled 53-root data set — ours (λ = 0.02, 1, 1) beside
    QED (Feragen et al.) and father–child SRVF (Wang et al.), with the shrinkage of every
    geodesic; (b) the paper's λ study on a toy pair; (c) the mean root, ours and the
    baselines'; (d) the first two modes; (e) random roots grouped by distance to the mean;
    (f) regression sweeps for the three traits; (g) hierarchical clustering and leave-one-out
    classification (ours vs QED vs fc-SRVF vs tree edit distance) on the synthetic conditions
    and on CPlantBox-simulated species; (h) the paper's timing table, with its Matlab figures.

Heavy intermediate results (distance matrices, means) are cached as .npz in
``DIR/paper_reproduction/cache``, keyed by the configuration, a fingerprint of the input
roots and of the library's source: a change in any of them recomputes. The report lists what
was loaded from the cache (with the timings measured when it was computed). ``--no-cache``
recomputes everything.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _common import PAPER_STATS, RESULTS, machine, setup_jax, timed, write_json  # noqa: E402

NAME = "paper_reproduction"
CACHE_VERSION = 1  # bump when this script changes what a cached result means
OURS_WEIGHTS = (0.02, 1.0, 1.0)
PAPER_LAMBDAS = ((1.0, 0.01, 0.01), (0.01, 1.0, 0.01), (0.01, 0.01, 1.0), (0.01, 1e-5, 1.0))
METHODS = ("ours", "qed", "fc_srvf")
METHOD_LABEL = {
    "ours": "ours (elastic SRVF tree)",
    "qed": "QED (Feragen et al.)",
    "fc_srvf": "fc-SRVF (Wang et al.)",
    "ted": "tree edit distance",
    "tmd": "TMD (Kanari et al.)",
}

# The paper's Table (timing_geodesics), seconds, Matlab on an Intel i5-4460 @ 3.2 GHz, 8 GB.
# (example, size = number of laterals after adding virtual ones, approach, alignment,
#  correspondence, geodesic, overall); None = "N/A" in the paper.
PAPER_TIMING = (
    ("Example 1", 23, "This paper", 147.0, None, 0.04, 147.04),
    ("Example 1", 23, "Feragen et al.", 147.0, None, 10.98, 157.98),
    ("Example 1", 23, "Wang et al.", 147.0, 0.0050, 11.40, 158.40),
    ("Example 2", 14, "This paper", 137.0, None, 0.04, 137.04),
    ("Example 2", 14, "Feragen et al.", 137.0, None, 10.60, 147.60),
    ("Example 2", 14, "Wang et al.", 137.0, 0.0028, 11.31, 148.31),
)


@dataclasses.dataclass(frozen=True)
class Config:
    name: str
    n_per_condition: int | None  # None: the whole bundled data set (53 roots)
    T: int
    n_steps: int
    n_pairs: int
    mean_max_steps: int
    n_landmarks: int
    fc_n_points: int
    fc_mean_steps: int
    species: tuple[str, ...]
    n_per_species: int
    species_days: float
    n_random: int
    sweep_size: int
    alphas: tuple[float, ...]
    chunk_size: int
    shared_capacity: bool  # one K for every batch: fewer compilations (tiny run)
    max_laterals_per_root: int | None  # keep only the first laterals (tiny run: small K)


FULL = Config(
    name="full",
    n_per_condition=None,
    T=50,
    n_steps=9,
    n_pairs=3,
    mean_max_steps=50,
    n_landmarks=20,
    fc_n_points=50,
    fc_mean_steps=10,
    species=("wheat", "maize", "pea"),
    n_per_species=10,
    species_days=12.0,
    n_random=24,
    sweep_size=5,
    alphas=(-2.0, -1.0, 0.0, 1.0, 2.0),
    chunk_size=32,
    shared_capacity=False,
    max_laterals_per_root=None,
)
TINY = Config(
    name="tiny",
    n_per_condition=2,
    T=20,
    n_steps=5,
    n_pairs=2,
    mean_max_steps=3,
    n_landmarks=8,
    fc_n_points=20,
    fc_mean_steps=2,
    species=("wheat", "maize"),
    n_per_species=3,
    species_days=10.0,
    n_random=6,
    sweep_size=3,
    alphas=(-1.0, 0.0, 1.0),
    chunk_size=8,
    shared_capacity=True,
    max_laterals_per_root=6,
)


# --------------------------------------------------------------------------------------------
# Small utilities


def _sha(text: str | bytes) -> str:
    return hashlib.sha1(text.encode() if isinstance(text, str) else text).hexdigest()[:16]


def fingerprint_roots(roots) -> str:
    import numpy as np

    h = hashlib.sha1()
    for r in roots:
        for arr in (r.main, *r.laterals, r.attach):
            h.update(np.ascontiguousarray(arr, np.float64).tobytes())
            h.update(b"|")
        h.update(b"#")
    return h.hexdigest()[:16]


def fingerprint_library() -> str:
    import rootshape_jax

    root = Path(rootshape_jax.__file__).parent
    h = hashlib.sha1()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


class Cache:
    """.npz files keyed by (name, configuration, inputs, library source); a key mismatch is a miss."""

    def __init__(self, folder: Path, *, enabled: bool, base: dict):
        self.folder = folder
        self.enabled = enabled
        self.base = base
        self.hits: list[str] = []
        self.misses: list[str] = []

    def _key(self, name: str, key: dict) -> tuple[Path, str]:
        text = json.dumps({"name": name, **self.base, **key}, sort_keys=True, default=str)
        return self.folder / f"{name}-{_sha(text)}.npz", text

    def load(self, name: str, key: dict) -> dict | None:
        import numpy as np

        path, text = self._key(name, key)
        if self.enabled and path.exists():
            with np.load(path, allow_pickle=False) as z:
                if str(z["_key"]) == text:
                    self.hits.append(name)
                    return {k: z[k] for k in z.files if k != "_key"}
        self.misses.append(name)
        return None

    def save(self, name: str, key: dict, arrays: dict) -> None:
        import numpy as np

        path, text = self._key(name, key)
        self.folder.mkdir(parents=True, exist_ok=True)
        np.savez(path, _key=np.asarray(text), **arrays)


def module_arrays(prefix: str, module) -> dict:
    import numpy as np

    return {f"{prefix}.{f.name}": np.asarray(getattr(module, f.name)) for f in dataclasses.fields(module)}


def module_from(cls, prefix: str, data: dict):
    import jax.numpy as jnp

    return cls(**{f.name: jnp.asarray(data[f"{prefix}.{f.name}"]) for f in dataclasses.fields(cls)})


def root_arrays(prefix: str, root) -> dict:
    import numpy as np

    out = {
        f"{prefix}.main": root.main,
        f"{prefix}.attach": root.attach,
        f"{prefix}.n_laterals": np.asarray(root.n_laterals),
    }
    out.update({f"{prefix}.lateral{i}": lat for i, lat in enumerate(root.laterals)})
    return out


def root_from(prefix: str, data: dict, name: str = ""):
    from rootshape_jax import Root

    n = int(data[f"{prefix}.n_laterals"])
    return Root(
        main=data[f"{prefix}.main"],
        laterals=tuple(data[f"{prefix}.lateral{i}"] for i in range(n)),
        attach=data[f"{prefix}.attach"],
        name=name,
    )


def fmt(x, digits: int = 3) -> str:
    if x is None:
        return "N/A"
    if isinstance(x, str):
        return x
    x = float(x)
    if x != x:
        return "nan"
    if x == 0:
        return "0"
    if abs(x) >= 1e4:
        return f"{x:,.0f}"
    if abs(x) < 1e-3:
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}" if abs(x) < 100 else f"{x:.1f}"


def md_table(header, rows) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(c) if not isinstance(c, str) else c for c in row) + " |" for row in rows]
    return lines + [""]


class Report:
    def __init__(self, out: Path):
        self.out = out
        self.fig_dir = out / NAME
        self.fig_dir.mkdir(parents=True, exist_ok=True)
        self.lines: list[str] = []
        self.figures: list[str] = []

    def add(self, *lines: str) -> None:
        self.lines.extend(lines)

    def figure(self, fig, name: str, caption: str) -> None:
        fig.savefig(self.fig_dir / name, dpi=100)
        if "matplotlib.pyplot" in sys.modules:  # a pyplot figure (if anything imported pyplot)
            sys.modules["matplotlib.pyplot"].close(fig)
        rel = f"{NAME}/{name}"
        self.figures.append(rel)
        self.lines.extend([f"![{caption}]({rel})", "", f"*{caption}*", ""])

    def write(self) -> Path:
        path = self.out / f"{NAME}.md"
        path.write_text("\n".join(self.lines) + "\n")
        return path


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --------------------------------------------------------------------------------------------
# Figures


def strip_figure(rows, taus, title: str):
    """Geodesic strips, one row per (label, path); every panel at one scale."""
    from matplotlib.figure import Figure

    from rootshape_jax.plot import plot_geodesic

    n_rows, n_cols = len(rows), len(taus)
    fig = Figure(figsize=(1.45 * n_cols + 1.2, 2.3 * n_rows + 0.7), layout="constrained")
    gs = fig.add_gridspec(n_rows, n_cols)
    every = []
    for i, (label, path) in enumerate(rows):
        axes = [fig.add_subplot(gs[i, j]) for j in range(n_cols)]
        plot_geodesic(path, axes=axes, taus=taus, title=None)
        axes[0].set_ylabel(label, fontsize=9)
        every += axes
    same_frame(every)
    fig.suptitle(title, fontsize=11)
    return fig


def same_frame(axes) -> None:
    """One region for every panel (the union of their limits), depth pointing down."""
    xs = [ax.get_xlim() for ax in axes]
    ys = [ax.get_ylim() for ax in axes]
    xlo, xhi = min(min(x) for x in xs), max(max(x) for x in xs)
    ylo, yhi = min(min(y) for y in ys), max(max(y) for y in ys)
    for ax in axes:
        ax.set_xlim(xlo, xhi)
        ax.set_ylim(yhi, ylo)


# --------------------------------------------------------------------------------------------
# Inputs


def limit_laterals(roots, n: int | None):
    """The roots with only their first `n` laterals (all of them when n is None)."""
    if n is None:
        return list(roots)
    # select_laterals keeps radii with their laterals; deeper orders are dropped here.
    return [dataclasses.replace(r.select_laterals(range(min(n, r.n_laterals))), children=()) for r in roots]


def dataset(cfg: Config):
    from rootshape_jax.datasets import default_dataset

    roots = default_dataset()
    if cfg.n_per_condition is not None:
        out, seen = [], {}
        for r in roots:
            c = r.metadata["condition"]
            if seen.get(c, 0) < cfg.n_per_condition:
                out.append(r)
                seen[c] = seen.get(c, 0) + 1
        roots = out
    return limit_laterals(roots, cfg.max_laterals_per_root)


def toy_pair():
    """Two small roots for the λ study (the paper's toy figure): the upper lateral slides down
    the main root by 8 % of its length while it grows and bends; the lower one stays."""
    import numpy as np

    from rootshape_jax import Root

    def main_root(bend):
        y = np.linspace(0.0, 100.0, 60)
        return np.stack([bend * np.sin(np.pi * y / 100.0), y], axis=1)

    def point_at(main, s):
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(main, axis=0), axis=1))])
        t = s * cum[-1]
        return np.array([np.interp(t, cum, main[:, 0]), np.interp(t, cum, main[:, 1])])

    def lateral(base, angle_deg, length, curl_deg, n=25):
        # Heading angle from straight down, turning by curl_deg in total along the lateral.
        ang = np.radians(np.linspace(angle_deg, angle_deg + curl_deg, n - 1))
        steps = (length / (n - 1)) * np.stack([np.sin(ang), np.cos(ang)], axis=1)
        return np.concatenate([base[None], base + np.cumsum(steps, axis=0)])

    main_a, main_b = main_root(0.0), main_root(4.0)
    a = Root(
        main=main_a,
        laterals=(lateral(point_at(main_a, 0.30), 60.0, 45.0, 0.0), lateral(point_at(main_a, 0.65), -60.0, 30.0, 0.0)),
        attach=np.array([0.30, 0.65]),
        name="toy A",
        metadata={"unit": "mm"},
    )
    b = Root(
        main=main_b,
        laterals=(
            lateral(point_at(main_b, 0.38), 60.0, 55.0, -25.0),
            lateral(point_at(main_b, 0.65), -60.0, 30.0, 5.0),
        ),
        attach=np.array([0.38, 0.65]),
        name="toy B",
        metadata={"unit": "mm"},
    )
    return a, b


def rotated_root(root, rotation):
    """The root rotated about its base by the rotation our registration found (SRVFs rotate
    as ``q @ Oᵀ``, so curves do too)."""
    import numpy as np

    from rootshape_jax import Root

    O = np.asarray(rotation, dtype=np.float64)
    o = root.main[0]
    rot = lambda x: o + (np.asarray(x, np.float64) - o) @ O.T  # noqa: E731
    return Root(
        main=rot(root.main), laterals=tuple(rot(lat) for lat in root.laterals), attach=root.attach, name=root.name
    )


# --------------------------------------------------------------------------------------------
# Distance matrices (cached)


def distance_matrices(tag, roots, trees, cfg, cache, weights, *, progress):
    """Ours, QED, fc-SRVF and tree-edit distance matrices of one labelled set, with timings."""
    import jax
    import numpy as np

    import rootshape_jax as rs
    from rootshape_jax import baselines as bl

    key = {
        "set": tag,
        "roots": fingerprint_roots(roots),
        "T": cfg.T,
        "K": trees.capacity,
        "dtype": str(trees.main.dtype),
        "weights": OURS_WEIGHTS,
        "chunk": cfg.chunk_size,
        "n_landmarks": cfg.n_landmarks,
        "fc_n_points": cfg.fc_n_points,
    }
    hit = cache.load(f"distances_{tag}", key)
    base = rs.to_roots(trees)
    if hit is not None:
        out = {m: hit[m] for m in ("ours", "qed", "fc_srvf", "ted")}
        timing = json.loads(str(hit["timing"]))
        out["tmd"], timing["tmd"] = tmd_matrix(base)
        return out, timing, True
    timing = {}
    # Compile on two roots (same T, K and chunk size: the same program), then time the matrix.
    small = jax.tree.map(lambda x: x[:2], trees)
    t0 = time.perf_counter()
    rs.pairwise_distances(small, weights=weights, chunk_size=cfg.chunk_size, progress=False)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    D, stats = rs.pairwise_distances(
        trees, weights=weights, chunk_size=cfg.chunk_size, progress=progress, return_stats=True
    )
    D = np.asarray(D, dtype=np.float64)
    timing["ours"] = {"wall_s": time.perf_counter() - t0, "compile_s": compile_s, **stats}
    out = {"ours": D}
    for m, fn in (
        ("qed", lambda: bl.qed_distance_matrix(base, n_landmarks=cfg.n_landmarks)),
        ("fc_srvf", lambda: bl.fc_srvf_distance_matrix(base, n_points=cfg.fc_n_points, progress=progress)),
        ("ted", lambda: bl.tree_edit_distance_matrix(base)),
    ):
        say(f"  {tag}: {m} distance matrix ({len(base)} roots)")
        t0 = time.perf_counter()
        out[m] = np.asarray(fn(), dtype=np.float64)
        timing[m] = {"wall_s": time.perf_counter() - t0}
    cache.save(f"distances_{tag}", key, {**out, "timing": np.asarray(json.dumps(timing))})
    out["tmd"], timing["tmd"] = tmd_matrix(base)
    return out, timing, False


def tmd_matrix(base):
    """TMD distances (`rootshape_jax.baselines.tmd_distance_matrix`, the `tmd` package):
    seconds to compute, so never cached (the cache's keys predate it)."""
    import numpy as np

    from rootshape_jax import baselines as bl

    t0 = time.perf_counter()
    D = np.asarray(bl.tmd_distance_matrix(base), dtype=np.float64)
    return D, {"wall_s": time.perf_counter() - t0}


def symmetric(D, name, notes):
    import numpy as np

    asym = float(np.max(np.abs(D - D.T))) if D.size else 0.0
    if asym > 1e-9 * max(float(np.abs(D).max()), 1e-300):
        notes.append(f"{name}: matrix not symmetric (max |D − Dᵀ| = {asym:.3g}); (D + Dᵀ)/2 used.")
        D = 0.5 * (D + D.T)
    return D, asym


def purity(D, labels, k: int) -> float:
    import numpy as np

    from rootshape_jax import cluster

    cl = cluster(D, n_clusters=k, method="average")
    labels = np.asarray(labels)
    total = 0
    for c in range(cl.n_clusters):
        members = labels[cl.labels == c]
        if members.size:
            total += max(np.sum(members == v) for v in np.unique(members))
    return total / len(labels)


# --------------------------------------------------------------------------------------------
# Karcher mean (cached)


def our_mean(trees, D, cfg, cache, weights, key_roots):
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np
    import optimistix as optx

    from rootshape_jax import KarcherMean, SRVFTree, karcher_mean, to_curves

    key = {
        "roots": key_roots,
        "T": cfg.T,
        "K": trees.capacity,
        "dtype": str(trees.main.dtype),
        "weights": OURS_WEIGHTS,
        "max_steps": cfg.mean_max_steps,
        "D": _sha(np.asarray(D).tobytes()),
    }
    hit = cache.load("mean_ours", key)
    if hit is not None:
        mean_srvf = module_from(SRVFTree, "mean_srvf", hit)
        km = KarcherMean(
            mean=to_curves(mean_srvf),
            mean_srvf=mean_srvf,
            fitted=module_from(SRVFTree, "fitted", hit),
            registered=module_from(SRVFTree, "registered", hit),
            energies=jnp.asarray(hit["energies"]),
            energy=jnp.asarray(hit["energy"]),
            energy_trace=jnp.asarray(hit["energy_trace"]),
            steps=jnp.asarray(hit["steps"]),
            result=eqx.tree_at(lambda r: r._value, optx.RESULTS.successful, jnp.asarray(hit["result"])),
            init_index=int(hit["init_index"]),
            lateral_lengths=jnp.asarray(hit["lateral_lengths"]),
            dropped=jnp.asarray(hit["dropped"]),
            weights=weights,
        )
        return km, float(hit["seconds"]), True
    t0 = time.perf_counter()
    km = karcher_mean(trees, weights=weights, distances=jnp.asarray(D), max_steps=cfg.mean_max_steps, throw=False)
    seconds = time.perf_counter() - t0
    arrays = {
        **module_arrays("mean_srvf", km.mean_srvf),
        **module_arrays("fitted", km.fitted),
        **module_arrays("registered", km.registered),
    }
    arrays.update(
        energies=np.asarray(km.energies),
        energy=np.asarray(km.energy),
        energy_trace=np.asarray(km.energy_trace),
        steps=np.asarray(km.steps),
        result=np.asarray(km.result._value),
        init_index=np.asarray(km.init_index),
        lateral_lengths=np.asarray(km.lateral_lengths),
        dropped=np.asarray(km.dropped),
        seconds=np.asarray(seconds),
    )
    cache.save("mean_ours", key, arrays)
    return km, seconds, False


def baseline_means(base_roots, cfg, cache, key_roots):
    from rootshape_jax import baselines as bl

    key = {
        "roots": key_roots,
        "T": cfg.T,
        "n_landmarks": cfg.n_landmarks,
        "fc_n_points": cfg.fc_n_points,
        "fc_mean_steps": cfg.fc_mean_steps,
    }
    hit = cache.load("mean_baselines", key)
    if hit is not None:
        return (
            {m: root_from(m, hit, name=f"{m} mean") for m in ("qed", "fc_srvf")},
            {m: float(hit[f"{m}.seconds"]) for m in ("qed", "fc_srvf")},
            True,
        )
    means, seconds = {}, {}
    t0 = time.perf_counter()
    means["qed"] = bl.qed_mean(base_roots, n_landmarks=cfg.n_landmarks)
    seconds["qed"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    means["fc_srvf"] = bl.fc_srvf_mean(base_roots, n_points=cfg.fc_n_points, max_steps=cfg.fc_mean_steps)
    seconds["fc_srvf"] = time.perf_counter() - t0
    import numpy as np

    arrays = {}
    for m in means:
        arrays.update(root_arrays(m, means[m]))
        arrays[f"{m}.seconds"] = np.asarray(seconds[m])
    cache.save("mean_baselines", key, arrays)
    return means, seconds, False


def scale_trees(trees, factors):
    """Scale each root of a batched RootTree about its base."""
    import jax.numpy as jnp

    from rootshape_jax import RootTree

    f = jnp.asarray(factors, trees.main.dtype)
    o = trees.main[:, :1, :]
    main = o + (trees.main - o) * f[:, None, None]
    lats = o[:, None] + (trees.laterals - o[:, None]) * f[:, None, None, None]
    return RootTree(main=main, laterals=lats, attach=trees.attach, mask=trees.mask)


# --------------------------------------------------------------------------------------------
# The run


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiny", action="store_true", help="6 roots, T = 20, few steps: a smoke run (< 3 min)")
    p.add_argument("--out", default=str(RESULTS), help="output folder (default benchmarks/results)")
    p.add_argument("--T", type=int, default=None, help="points per branch (default 50; tiny 20)")
    p.add_argument("--no-cache", action="store_true", help="recompute everything")
    args = p.parse_args(argv)
    cfg = TINY if args.tiny else FULL
    if args.T is not None:
        cfg = dataclasses.replace(cfg, T=args.T)
    start_all = time.perf_counter()

    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    jax = setup_jax()  # every core as an XLA device, before JAX starts
    import numpy as np
    import optimistix as optx
    from matplotlib.figure import Figure

    import rootshape_jax as rs
    from rootshape_jax import baselines as bl
    from rootshape_jax.datasets import available_species, simulated_roots
    from rootshape_jax.plot import (
        plot_dendrogram,
        plot_mean,
        plot_modes,
        plot_regression_sweep,
        plot_root,
        plot_samples_by_distance,
    )

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = Report(out)
    notes: list[str] = []
    weights = rs.Weights(*OURS_WEIGHTS)
    info = machine()
    cache = Cache(
        report.fig_dir / "cache",
        enabled=not args.no_cache,
        base={"version": CACHE_VERSION, "library": fingerprint_library(), "config": cfg.name},
    )
    results: dict = {
        "config": dataclasses.asdict(cfg),
        "machine": info,
        "paper_timing": PAPER_TIMING,
        "paper_stats": PAPER_STATS,
    }
    section_s: dict = {}

    # ---------------------------------------------------------------- inputs
    roots = dataset(cfg)
    conditions = [r.metadata["condition"] for r in roots]
    names = [r.name for r in roots]
    T = cfg.T
    toy_a, toy_b = toy_pair()
    sim_raw = []
    for sp in cfg.species:
        if sp not in available_species():
            raise SystemExit(f"species {sp!r} is not available in this CPlantBox installation")
        sim_raw += simulated_roots(sp, cfg.n_per_species, days=cfg.species_days, seed=0, dim=2)
    sim_raw = limit_laterals(sim_raw, cfg.max_laterals_per_root)
    sim_names = [f"{r.metadata['species']}_{r.metadata['index']}" for r in sim_raw]
    species_labels = [r.metadata["species"] for r in sim_raw]
    K_data = max(2, 2 * max(r.n_laterals for r in roots))
    K_species = max(2, 2 * max(r.n_laterals for r in sim_raw))
    if cfg.shared_capacity:
        K_data = K_species = K_toy = max(K_data, K_species)
    else:
        K_toy = 4
    trees = rs.batch(roots, n_points=T, max_laterals=K_data, normalise_scale=True)
    base_roots = rs.to_roots(trees, names=names)  # what the baselines see: the same geometry
    key_roots = fingerprint_roots(roots)
    dtype = str(trees.main.dtype)
    results["data"] = {
        "n_roots": len(roots),
        "conditions": sorted(set(conditions)),
        "T": T,
        "K": K_data,
        "dtype": dtype,
        "laterals": [r.n_laterals for r in roots],
    }
    say(f"{len(roots)} roots, T = {T}, K = {K_data}, {dtype}, {len(jax.devices())} devices")

    report.add(
        "# Reproducing the paper's experiments (Section 6) with both comparison methods",
        "",
        f"Generated by `python benchmarks/paper_reproduction.py{' --tiny' if args.tiny else ''}` "
        f"({cfg.name} configuration) on {info['date']}.",
        "",
        f"- **Data**: the bundled synthetic data set (`rootshape_jax.datasets.default_dataset()`), "
        f"{len(roots)} roots ({', '.join(f'{conditions.count(c)} {c}' for c in sorted(set(conditions)))}), "
        f"{min(r.n_laterals for r in roots)}–{max(r.n_laterals for r in roots)} laterals"
        + (
            f" (only the first {cfg.max_laterals_per_root} laterals of each root kept, here and for "
            "the simulated species)"
            if cfg.max_laterals_per_root
            else ""
        )
        + "; the paper used "
        "53 scanned wheat roots, which are not public, so figures show the same experiments on other roots.",
        f"- **Ours**: λ = (λm, λs, λp) = {OURS_WEIGHTS} (the paper's), T = {T} points per branch, "
        f"K = {K_data} lateral slots, scale normalised (main root length 1), {dtype}, "
        f"{len(jax.devices())} XLA CPU devices.",
        "- **Baselines** (`rootshape_jax.baselines`, re-implemented from the published descriptions, "
        "not the authors' code): QED — Feragen et al., father–child tree-space with the quotient "
        f"Euclidean distance ({cfg.n_landmarks} landmarks per edge, correspondence by order along "
        "the main root); fc-SRVF — Wang et al. 2018, father–child topology with SRVF edges and an "
        f"elastic warp per edge ({cfg.fc_n_points} points per edge); a classic tree edit distance on "
        "the topology; TMD — Kanari et al. 2018, the persistence barcode of the radial-distance "
        "filtration through the `tmd` package, persistence-image distance "
        "(`rootshape_jax.baselines.tmd_distance_matrix`). They get exactly the roots ours gets "
        "(resampled, scale normalised).",
        f"- **Machine**: {info['cpu']}, {info['cores']} cores, {info['memory_gib']} GiB, Python "
        f"{info['python']}, jax {info['jax']}; 1-min load average at start "
        f"{fmt(info['load_average_1min_at_start'])} (the machine is shared: timings are wall "
        "times on a busy machine).",
        "",
    )

    # ---------------------------------------------------------------- distance matrices
    t_sec = time.perf_counter()
    say("distance matrices of the data set")
    D_data, timing_data, cached_data = distance_matrices(
        "data", roots, trees, cfg, cache, weights, progress=not args.tiny
    )
    sim_trees = rs.batch(sim_raw, n_points=T, max_laterals=K_species, normalise_scale=True)
    say(f"distance matrices of the simulated species ({len(sim_raw)} roots, K = {K_species})")
    D_sim, timing_sim, cached_sim = distance_matrices(
        "species", sim_raw, sim_trees, cfg, cache, weights, progress=not args.tiny
    )
    for D in (D_data, D_sim):
        for m in list(D):
            D[m], _ = symmetric(D[m], METHOD_LABEL[m], notes)
    section_s["distance_matrices"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (a) geodesics
    t_sec = time.perf_counter()
    say("(a) geodesics")
    by_cond: dict = {}
    for i, c in enumerate(conditions):
        by_cond.setdefault(c, []).append(i)
    conds = list(by_cond)
    candidates = [
        (by_cond[conds[0]][0], by_cond[conds[0]][1]),  # within one condition
        (by_cond[conds[0]][0], by_cond[conds[1]][0]),
        (by_cond[conds[1]][1], by_cond[conds[2]][1]),
        (by_cond[conds[0]][1], by_cond[conds[2]][0]),
    ]
    pairs = candidates[: cfg.n_pairs]
    singles = rs.unstack(trees)
    taus = np.linspace(0.0, 1.0, cfg.n_steps)
    geodesics = []  # every geodesic of the report, with its shrinkage
    pair_timing = []

    def taus_of(n):
        return np.linspace(0.0, 1.0, n)

    def shrink_row(gid, label, method, path, extra=None):
        s = bl.geodesic_shrinkage(path)
        lengths = np.asarray(s.lengths, np.float64)
        interp = np.asarray(s.interpolated, np.float64)
        ratio = lengths / np.maximum(interp, 1e-300)
        row = {
            "id": gid,
            "geodesic": label,
            "method": method,
            "steps": int(lengths.shape[0]),
            "length_start": float(lengths[0]),
            "length_end": float(lengths[-1]),
            "min_ratio": float(s.min_ratio),
            "tau_at_min": float(taus_of(lengths.shape[0])[int(np.argmin(ratio))]),
            "mean_shortfall": float(s.mean_shortfall),
            "lengths": lengths.tolist(),
            "interpolated": interp.tolist(),
            **(extra or {}),
        }
        geodesics.append(row)
        return row

    report.add(
        "## (a) Geodesics between roots of the data set",
        "",
        "Paper Fig. 6: for each pair, the geodesic of ours (top row, λ = (0.02, 1, 1)), QED "
        "(Feragen et al., middle) and fc-SRVF (Wang et al., bottom). Colour = lateral slot, so "
        "one colour follows one lateral along a row (for the baselines, the lateral's index "
        "in each step's root). Ours registers b onto a (rotation, warps, lateral "
        "correspondence); as in the paper, the baselines start from the same alignment: b "
        "rotated by our rotation. Their own correspondence is by order along the main root.",
        "",
    )
    for p_i, (i, j) in enumerate(pairs):
        a, b = singles[i], singles[j]
        ra, rb = base_roots[i], base_roots[j]
        first_reg, align_s, reg = timed(rs.register, a, b, weights=weights)
        first_geo, geo_s, path = timed(rs.geodesic, a, b, n_steps=cfg.n_steps, weights=weights, registration=reg)
        rb_aligned = rotated_root(rb, reg.rotation)
        q_first, q_s, qed_path = timed(
            bl.qed_geodesic, ra, rb_aligned, n_steps=cfg.n_steps, n_landmarks=cfg.n_landmarks, repeats=1
        )
        f_first, f_s, fc_path = timed(
            bl.fc_srvf_geodesic, ra, rb_aligned, n_steps=cfg.n_steps, n_points=cfg.fc_n_points, repeats=1
        )
        label = f"pair {p_i + 1}: {names[i]} → {names[j]}"
        d_q = float(bl.qed_distance(ra, rb_aligned, n_landmarks=cfg.n_landmarks))
        d_f = float(bl.fc_srvf_distance(ra, rb_aligned, n_points=cfg.fc_n_points))
        for method, pth, dist in (
            ("ours", path, float(reg.distance)),
            ("qed", qed_path, d_q),
            ("fc_srvf", fc_path, d_f),
        ):
            shrink_row(f"a{p_i + 1}-{method}", label, method, pth, {"distance": dist})
        both = np.asarray(a.mask & reg.registered.mask)
        pair_timing.append(
            {
                "pair": label,
                "laterals": [base_roots[i].n_laterals, base_roots[j].n_laterals],
                "K": K_data,
                "ours": {
                    "alignment_s": align_s,
                    "alignment_first_call_s": first_reg,
                    "geodesic_s": geo_s,
                    "geodesic_first_call_s": first_geo,
                },
                "qed": {"geodesic_s": q_s},
                "fc_srvf": {"geodesic_s": f_s},
                "matched_laterals": int(both.sum()),
            }
        )
        fig = strip_figure([("ours", path), ("QED\n(Feragen)", qed_path), ("fc-SRVF\n(Wang)", fc_path)], taus, label)
        report.figure(
            fig,
            f"geodesic_pair{p_i + 1}.png",
            f"{label} ({ra.n_laterals} and {rb.n_laterals} laterals). Distances: ours "
            f"{fmt(reg.distance)}, QED {fmt(d_q)}, fc-SRVF {fmt(d_f)} (each in its own metric).",
        )
    section_s["a_geodesics"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (b) λ study
    t_sec = time.perf_counter()
    say("(b) λ study")
    toy = rs.batch([toy_a, toy_b], n_points=T, max_laterals=K_toy, normalise_scale=True)
    ta, tb = rs.unstack(toy)
    lam_rows, lam_strips = [], []
    for k, lam in enumerate(PAPER_LAMBDAS):
        w = rs.Weights(*lam)
        reg = rs.register(ta, tb, weights=w)
        # As the paper draws it: b registered onto a at the end (not turned back into its pose).
        path = rs.geodesic(ta, tb, n_steps=cfg.n_steps, weights=w, registration=reg, in_place=False)
        real_a = np.asarray(ta.mask)
        real_b = np.asarray(reg.registered.mask)
        matched = int(np.sum(real_a & real_b))
        created = int(np.sum(real_a ^ real_b))
        terms = reg.terms
        lam_rows.append(
            {
                "lambda": lam,
                "distance": float(reg.distance),
                "main_term": float(terms.main),
                "lateral_term": float(terms.lateral),
                "position_term": float(terms.position),
                "matched_laterals": matched,
                "grown_or_removed_laterals": created,
                "upper_lateral": "slides" if matched == 2 else "removed and re-grown",
            }
        )
        shrink_row(f"b{k + 1}", f"toy, λ = {lam}", "ours", path, {"distance": float(reg.distance)})
        lam_strips.append((f"λ = {lam}", path))
    report.add(
        "## (b) Influence of the weights λ (toy pair)",
        "",
        "Paper Fig. 7: rows λ = (1, .01, .01), (.01, 1, .01), (.01, .01, 1), (.01, 1e-5, 1). "
        "Toy pair: the upper lateral moves 8 % of the main root down while it grows "
        "(45 → 55 mm, main root 100 mm) and bends; the main root bends slightly; the lower "
        "lateral stays. The paper finds the first three geodesics similar (the lateral "
        "slides) and the fourth growing a new lateral instead of sliding the old one.",
        "",
    )
    fig = strip_figure(lam_strips, taus, "Geodesics of the toy pair for the paper's four weight triplets")
    report.figure(fig, "lambda_study.png", "one row per λ = (λm, λs, λp); colour = lateral slot")
    report.add(
        *md_table(
            [
                "λ = (λm, λs, λp)",
                "distance",
                "λm term",
                "λs term",
                "λp term",
                "real–real matches",
                "laterals grown / removed",
                "upper lateral",
            ],
            [
                [
                    str(r["lambda"]),
                    r["distance"],
                    r["main_term"],
                    r["lateral_term"],
                    r["position_term"],
                    str(r["matched_laterals"]),
                    str(r["grown_or_removed_laterals"]),
                    r["upper_lateral"],
                ]
                for r in lam_rows
            ],
        )
    )
    results["lambda_study"] = lam_rows
    section_s["b_lambda"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- shrinkage table
    report.add(
        "## Shrinkage of every geodesic",
        "",
        "Total root length (main + laterals) along each geodesic, L(τ), against the straight "
        "interpolation of the end lengths, (1 − τ) L(0) + τ L(1) "
        "(`rootshape_jax.baselines.geodesic_shrinkage`). A ratio below 1 is shrinkage; "
        "the paper's claim is that ours does not shrink and the father–child methods do. "
        "Lengths in units of the main-root length (scale normalised).",
        "",
    )
    report.add(
        *md_table(
            ["id", "geodesic", "method", "steps", "L(0)", "L(1)", "min L(τ)/interp.", "τ at min", "mean shortfall"],
            [
                [
                    g["id"],
                    g["geodesic"],
                    METHOD_LABEL[g["method"]],
                    str(g["steps"]),
                    g["length_start"],
                    g["length_end"],
                    g["min_ratio"],
                    g["tau_at_min"],
                    g["mean_shortfall"],
                ]
                for g in geodesics
            ],
        )
    )
    summary = []
    for m in METHODS:
        rows = [g for g in geodesics if g["method"] == m and g["id"].startswith("a")]
        if rows:
            summary.append(
                [
                    METHOD_LABEL[m],
                    str(len(rows)),
                    min(g["min_ratio"] for g in rows),
                    float(np.mean([g["min_ratio"] for g in rows])),
                    float(np.mean([g["mean_shortfall"] for g in rows])),
                ]
            )
    report.add("Summary over the data-set pairs of (a):", "")
    report.add(*md_table(["method", "geodesics", "worst min ratio", "mean min ratio", "mean shortfall"], summary))
    report.add(
        "Reading the measure: no straight-line geodesic can be longer than the interpolation (up to discretisation). "
        "In QED an edge's length is a sum of norms of landmark differences, and "
        "|(1 − τ) u + τ v| ≤ (1 − τ)|u| + τ|v|; in the SRVF methods (ours and fc-SRVF) a "
        "branch's length is ‖q‖², and ‖(1 − τ) q_a + τ q_b‖² ≤ (1 − τ)‖q_a‖² + τ‖q_b‖². "
        "Equality needs corresponding branches to be parallel (QED) or equal (SRVF), and a "
        "lateral grown from a null (virtual) lateral has length τ L in QED but τ² L in the "
        "SRVF methods. The table measures how much each path shrinks, not whether.",
        "",
    )
    results["geodesics"] = geodesics

    # ---------------------------------------------------------------- (c) means
    t_sec = time.perf_counter()
    say("(c) means")
    km, mean_s, mean_cached = our_mean(trees, D_data["ours"], cfg, cache, weights, key_roots)
    b_means, b_mean_s, b_cached = baseline_means(base_roots, cfg, cache, key_roots)
    mean_root = rs.to_roots(km.mean)[0]
    fig, _ = plot_mean(trees, km.mean, title=f"Mean of the {len(roots)} roots (ours)")
    report.add(
        "## (c) Mean root",
        "",
        f"Paper Figs. 5 and 8. Ours: Karcher mean (fixed point, start at the medoid of our "
        f"distance matrix), {int(km.steps)} steps, energy {fmt(float(km.energy_trace[0]))} → "
        f"{fmt(float(km.energy))}, status {'converged' if bool(km.result == optx.RESULTS.successful) else 'step limit reached'}"
        f"; baselines: `qed_mean` and `fc_srvf_mean` (max_steps = {cfg.fc_mean_steps}) on "
        "the same roots.",
        "",
    )
    report.figure(fig, "mean_ours.png", "input roots (left) and our mean root (right)")
    fig = Figure(figsize=(10, 4.6), layout="constrained")
    axs = fig.subplots(1, 3)
    for ax, (m, r) in zip(axs, (("ours", km.mean), ("qed", b_means["qed"]), ("fc_srvf", b_means["fc_srvf"]))):
        plot_root(r, ax=ax, title=METHOD_LABEL[m])
    same_frame(axs)
    fig.suptitle(f"Mean of the {len(roots)} roots: ours vs the baselines")
    report.figure(fig, "means_compared.png", "mean root by each method (same roots, same scale normalisation)")
    dataset_traits = rs.traits(base_roots)
    mean_rows = []
    for m, r in (("ours", mean_root), ("qed", b_means["qed"]), ("fc_srvf", b_means["fc_srvf"])):
        t = rs.traits(r)
        mean_rows.append(
            [METHOD_LABEL[m], t["main_length"], str(t["n_laterals"]), t["mean_lateral_length"], t["total_length"]]
        )
    med = lambda k: float(np.median([t[k] for t in dataset_traits]))  # noqa: E731
    mean_rows.append(
        [
            "data set (median)",
            med("main_length"),
            fmt(med("n_laterals")),
            med("mean_lateral_length"),
            med("total_length"),
        ]
    )
    report.add(*md_table(["mean by", "main length", "laterals", "mean lateral length", "total length"], mean_rows))
    results["means"] = {
        "ours": {
            "steps": int(km.steps),
            "energy": float(km.energy),
            "energy_trace": np.asarray(km.energy_trace).tolist(),
            "seconds": mean_s,
            "cached": mean_cached,
            "init_index": km.init_index,
        },
        "baselines_seconds": b_mean_s,
        "baselines_cached": b_cached,
        "traits_table": [[str(c) for c in r] for r in mean_rows],
    }
    section_s["c_means"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (d) modes
    t_sec = time.perf_counter()
    say("(d) modes")
    pca_first, pca_s, pc = timed(rs.tangent_pca, km)
    ratio = np.asarray(pc.explained_variance_ratio, np.float64)
    n_modes = min(2, int(pc.components.shape[0]))
    mode_trees = rs.modes(pc, list(cfg.alphas), component=list(range(n_modes)))
    fig, _ = plot_modes(mode_trees, list(cfg.alphas), explained=ratio[:n_modes])
    report.add(
        "## (d) Principal modes of variation",
        "",
        f"Paper Fig. 9: mean ± α √σ_i Λ_i for the first {n_modes} tangent-PCA components. "
        f"They explain {', '.join(f'{100 * r:.1f} %' for r in ratio[:n_modes])} of the variance; "
        f"{pc.n_components} components reach 99 %.",
        "",
    )
    report.figure(fig, "modes.png", f"first {n_modes} modes, α = {', '.join(f'{a:g}' for a in cfg.alphas)}")
    results["pca"] = {"explained_ratio": ratio[:10].tolist(), "n_components_99": pc.n_components, "seconds": pca_s}
    section_s["d_modes"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (e) random roots
    t_sec = time.perf_counter()
    say("(e) random roots")
    key = jax.random.PRNGKey(0)
    _, one_s, _ = timed(rs.sample, pc, key, 1)
    samples = rs.sample(pc, key, cfg.n_random)
    d_mean = np.asarray(
        rs.cross_distances(rs.stack([km.mean]), samples, weights=weights, chunk_size=cfg.chunk_size, progress=False)
    )[0]
    fig, _ = plot_samples_by_distance(samples, d_mean, n_groups=3)
    report.add(
        "## (e) Random roots from the fitted model",
        "",
        f"Paper Fig. 10: {cfg.n_random} roots sampled with b ~ N(0, I) on the {pc.n_components} "
        "kept components, in three rows by their elastic distance to the mean (each sample "
        "registered onto the mean root).",
        "",
    )
    report.figure(fig, "random_roots.png", "random roots grouped by distance to the mean (closest first)")
    results["random"] = {"distances_to_mean": d_mean.tolist(), "one_root_s": one_s}
    section_s["e_random"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (f) regression
    t_sec = time.perf_counter()
    say("(f) regression")
    trait_names = ("main_length", "mean_lateral_length", "std_lateral_length")
    raw_traits = rs.traits(roots)
    P = np.array([[float(t[k]) for k in trait_names] for t in raw_traits])
    # The shapes are scale normalised, so the traits (in mm, measured on the roots as given)
    # enter as covariates and each predicted root is scaled to its requested main length.
    _, fit_s, reg_model = timed(rs.TraitRegression.fit, pc, None, traits=(), covariates=P, covariate_names=trait_names)
    _, one_reg_s, _ = timed(reg_model.synthesize, P[0])

    def predict(values):
        t = reg_model.synthesize(values)
        lengths = np.linalg.norm(np.diff(np.asarray(t.main, np.float64), axis=1), axis=-1).sum(-1)
        return scale_trees(t, values[:, 0] / np.maximum(lengths, 1e-12))

    fitted = rs.traits(rs.to_roots(predict(P)))
    got = np.array([[float(t[k]) for k in trait_names] for t in fitted])
    r2 = {}
    for k, nm in enumerate(trait_names):
        ss = float(np.sum((P[:, k] - P[:, k].mean()) ** 2))
        r2[nm] = 1.0 - float(np.sum((got[:, k] - P[:, k]) ** 2)) / ss if ss > 0 else float("nan")
    report.add(
        "## (f) Roots regressed from traits",
        "",
        "Paper Figs. 11–13: M = B P⁺ maps (main length, mean lateral length, std of lateral "
        f"lengths) to the {reg_model.n_components} kept PCA coefficients. Each sweep varies one "
        "trait from its 10th to its 90th percentile in the data set with the others at their "
        "median (the paper's Figs. 12–13 fix one lateral statistic and vary the other); the "
        "value measured on the predicted root is shown under the requested one. R² of measured "
        "vs requested on the training roots: "
        + ", ".join(f"{k.replace('_', ' ')} {fmt(v)}" for k, v in r2.items())
        + ".",
        "",
    )
    sweeps = {}
    for k, nm in enumerate(trait_names):
        values = np.tile(np.median(P, axis=0), (cfg.sweep_size, 1))
        values[:, k] = np.percentile(P[:, k], np.linspace(10, 90, cfg.sweep_size))
        pred = predict(values)
        measured = np.array([float(t[nm]) for t in rs.traits(rs.to_roots(pred))])
        fig, _ = plot_regression_sweep(
            pred, values[:, k], trait_name=nm.replace("_", " "), trait_unit="mm", measured=measured
        )
        report.figure(fig, f"regression_{nm}.png", f"{nm.replace('_', ' ')} varied, other traits at their median")
        sweeps[nm] = {"requested": values[:, k].tolist(), "measured": measured.tolist()}
    results["regression"] = {"r2_training": r2, "sweeps": sweeps, "fit_s": fit_s, "one_root_s": one_reg_s}
    section_s["f_regression"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (g) clustering
    t_sec = time.perf_counter()
    say("(g) clustering and classification")
    n_cond = len(set(conditions))
    cl = rs.cluster(D_data["ours"], n_clusters=n_cond, method="average")
    fig, _ = plot_dendrogram(
        D_data["ours"],
        labels=names,
        n_clusters=n_cond,
        roots=trees,
        title="Hierarchical clustering (ours, average linkage)",
    )
    report.add(
        "## (g) Hierarchical clustering and classification",
        "",
        "Paper Figs. 14–15: average-linkage clustering of our distance matrix, cut into as many "
        "clusters as there are labels. Below, leave-one-out classification from each method's "
        "distance matrix alone: nearest neighbour (the label of the closest other root; ties "
        "to the lowest index) and nearest "
        "class mean (from distances, `rootshape_jax.loo_accuracy`); purity of the "
        "average-linkage clusters against the labels.",
        "",
    )
    report.figure(
        fig, "dendrogram_conditions.png", "synthetic conditions: dendrogram (ours) with members of each cluster"
    )
    cont = [
        [c] + [str(int(np.sum((np.asarray(conditions) == c) & (cl.labels == g)))) for g in range(cl.n_clusters)]
        for c in sorted(set(conditions))
    ]
    report.add("Conditions per cluster (ours):", "")
    report.add(*md_table(["condition"] + [f"cluster {g + 1}" for g in range(cl.n_clusters)], cont))
    n_sp = len(set(species_labels))
    fig, _ = plot_dendrogram(
        D_sim["ours"],
        labels=sim_names,
        n_clusters=n_sp,
        roots=sim_trees,
        title="Hierarchical clustering of CPlantBox species (ours)",
    )
    report.figure(
        fig,
        "dendrogram_species.png",
        f"CPlantBox-simulated {', '.join(cfg.species)} ({cfg.n_per_species} each, "
        f"{cfg.species_days:g} days, 2D projection): dendrogram (ours)",
    )
    acc_rows, acc = [], {}
    for tag, D, labels, what in (
        ("conditions", D_data, conditions, f"synthetic conditions ({len(roots)} roots)"),
        ("species", D_sim, species_labels, f"CPlantBox species ({len(sim_raw)} roots)"),
    ):
        k = len(set(labels))
        acc[tag] = {}
        for m in ("ours", "qed", "fc_srvf", "ted", "tmd"):
            nn = rs.loo_accuracy(D[m], np.asarray(labels), rule="nearest_neighbour")["accuracy"]
            nm_ = rs.loo_accuracy(D[m], np.asarray(labels), rule="nearest_mean")["accuracy"]
            pur = purity(D[m], labels, k)
            acc[tag][m] = {"nearest_neighbour": nn, "nearest_mean": nm_, "cluster_purity": pur}
            acc_rows.append([what, METHOD_LABEL[m], f"{100 * nn:.1f} %", f"{100 * nm_:.1f} %", f"{100 * pur:.1f} %"])
        acc_rows.append(
            [
                what,
                "chance (largest class)",
                f"{100 * max(labels.count(v) for v in set(labels)) / len(labels):.1f} %",
                "",
                "",
            ]
        )
    report.add(
        *md_table(
            ["labelled set", "distance", "LOO nearest neighbour", "LOO nearest class mean", "cluster purity"], acc_rows
        )
    )
    results["classification"] = acc
    section_s["g_clustering"] = time.perf_counter() - t_sec

    # ---------------------------------------------------------------- (h) timing
    say("(h) timing")
    report.add(
        "## (h) Timing", "", "The paper's table (Matlab, Intel i5-4460 @ 3.2 GHz, 8 GB RAM; seconds), quoted:", ""
    )
    report.add(
        *md_table(
            ["", "Size", "Approach", "Alignment", "Correspondence", "Geodesic", "Overall"],
            [
                [e, str(s), a] + [("N/A" if v is None else f"{v:g}") for v in (al, co, ge, ov)]
                for e, s, a, al, co, ge, ov in PAPER_TIMING
            ],
        )
    )
    report.add(
        "Ours, same layout, for the pairs of (a) (this machine, warm calls after a first "
        "call that compiles: best of 3 for ours, one for the baselines). *Alignment* is our registration of b onto "
        "a (rotation, warps and lateral correspondence together, so *Correspondence* is part of "
        "it); the baselines start from that alignment, as in the paper, and their own "
        "correspondence (by order along the main root, plus per-edge DP warps for fc-SRVF) is "
        "part of their *Geodesic* call. Size: laterals of a / b; K lateral slots after adding "
        "virtual ones.",
        "",
    )
    rows = []
    for pt in pair_timing:
        size = f"{pt['laterals'][0]} / {pt['laterals'][1]} (K = {pt['K']})"
        al = pt["ours"]["alignment_s"]
        rows.append(
            [pt["pair"], size, "ours", al, "in alignment", pt["ours"]["geodesic_s"], al + pt["ours"]["geodesic_s"]]
        )
        rows.append(
            ["", size, "QED (Feragen et al.)", al, "in geodesic", pt["qed"]["geodesic_s"], al + pt["qed"]["geodesic_s"]]
        )
        rows.append(
            [
                "",
                size,
                "fc-SRVF (Wang et al.)",
                al,
                "in geodesic",
                pt["fc_srvf"]["geodesic_s"],
                al + pt["fc_srvf"]["geodesic_s"],
            ]
        )
    report.add(*md_table(["", "Size", "Approach", "Alignment", "Correspondence", "Geodesic", "Overall"], rows))
    first_calls = ", ".join(f"{fmt(pt['ours']['alignment_first_call_s'])} s" for pt in pair_timing)
    report.add(f"First calls of our registration (compilation included): {first_calls}.", "")
    n_pairs_data = len(roots) * (len(roots) - 1) // 2
    paper_matrix_h = 147.0 * n_pairs_data / 3600
    mrows = []
    for m in ("ours", "qed", "fc_srvf", "ted", "tmd"):
        t = timing_data[m]
        mrows.append(
            [
                METHOD_LABEL[m],
                t["wall_s"],
                fmt(t.get("compile_s")) if "compile_s" in t else "–",
                n_pairs_data / t["wall_s"],
                f"≈ {paper_matrix_h:.0f} h (147 s × {n_pairs_data})" if m == "ours" else "not reported",
            ]
        )
    report.add(
        f"Overall: the {len(roots)}-root distance matrix ({n_pairs_data} pairs){' — loaded from the cache; times measured when it was computed' if cached_data else ''}. "
        "Ours registers every pair (rotation, warps, correspondence); the baselines' matrices "
        "use no rotation. The paper reports no matrix time; its 147 s alignment per pair "
        "gives the estimate.",
        "",
    )
    report.add(*md_table(["method", "wall (s)", "compile (s)", "pairs / s", "paper (Matlab)"], mrows))
    srows = [
        ["Karcher mean, ours" + (" (cached)" if mean_cached else ""), mean_s, "32,640 (9 h 4 min)"],
        ["mean, QED" + (" (cached)" if b_cached else ""), b_mean_s["qed"], None],
        ["mean, fc-SRVF" + (" (cached)" if b_cached else ""), b_mean_s["fc_srvf"], None],
        ["tangent PCA", pca_s, PAPER_STATS["pca_s"]],
        ["one random root", one_s, PAPER_STATS["random_root_s"]],
        ["regression fit", fit_s, PAPER_STATS["regression_fit_s"]],
        ["one regressed root", one_reg_s, PAPER_STATS["regressed_root_s"]],
    ]
    report.add(
        "Statistics (paper Section 6.5; ours: the mean's single call includes compilation, the "
        "others are best warm calls):",
        "",
    )
    report.add(*md_table(["task", "ours (s)", "paper (s)"], srows))
    results["timing"] = {
        "pairs": pair_timing,
        "matrix_data": timing_data,
        "matrix_species": timing_sim,
        "statistics": {r[0]: r[1] for r in srows},
    }

    # ---------------------------------------------------------------- notes
    report.add("## Notes", "")
    if cache.hits:
        report.add(
            f"- Loaded from the cache (same configuration, inputs and library source): "
            f"{', '.join(cache.hits)}. Delete `{NAME}/cache` or pass `--no-cache` to recompute."
        )
    for n in notes:
        report.add(f"- {n}")
    report.add(
        "- Section run times (s): "
        + ", ".join(f"{k} {v:.1f}" for k, v in section_s.items())
        + f"; whole script {time.perf_counter() - start_all:.1f} s.",
        "",
    )
    results["cache_hits"] = cache.hits
    results["section_seconds"] = section_s
    results["figures"] = report.figures
    # Written by bench_learn.py (nested CV of learned weights) and learn_oracle.py (what any
    # fixed λ could reach on the same folds).
    for part in ("learn_weights.md", "learn_oracle.md"):
        if (out / part).is_file():
            report.add((out / part).read_text())
    path = report.write()
    if out.resolve() == RESULTS.resolve():
        jpath = write_json(NAME, results)
    else:
        jpath = out / f"{NAME}.json"
        jpath.write_text(json.dumps(results, indent=2, default=float))
    say(f"wrote {path} and {jpath} in {time.perf_counter() - start_all:.1f} s")


if __name__ == "__main__":
    main()
