"""Father–child elastic baseline (Wang et al. 2018 style): a re-implementation from the
published description.

References: G. Wang, H. Laga, N. Xie, J. Jia, H. Tabia, "The shape space of 3D botanical tree
models", ACM Transactions on Graphics 37(1), 2018; G. Wang, H. Laga, J. Jia, N. Xie, H. Tabia,
"Statistical modeling of the 3D geometry and topology of botanical trees", Computer Graphics
Forum 37(5), 2018 — the second baseline of the paper's geodesic and mean comparisons.

Representation: the father–child edges of Feragen et al. (`_fatherchild`: the main root cut
at the attachment points into main-root edges, plus one edge per lateral), but every edge is an
SRVF (``n_points`` samples uniform in arc length) instead of landmarks, so bending and
stretching are measured elastically. Correspondence is FIXED as in the QED baseline (laterals
by order along the main root, the tree with fewer laterals padded at its tip with collapsed,
zero-SRVF edges); Wang et al.'s own correspondence search and their rotation / scale alignment
are not reproduced (align the roots first if needed).

- Distance: every corresponding edge pair is registered by the library's exact DP warp (`b`'s
  edge onto `a`'s, `dp_warp_batch`); the distance is ``sqrt(Σ_edges min_γ ||q_a − (q_b∘γ)√γ'||²)``
  (`warp_energy` of the DP warp). A real edge against a collapsed one costs ``||q||²`` (its
  length): warping cannot change it. The DP is not exactly symmetric in its two arguments
  (a few percent on coarse grids); matrices register the later root onto the earlier one.
- Geodesic: the straight line between ``q_a`` and the registered ``q_b`` of every edge, mapped
  back by integrating each edge from the end of its father (main edges end to end from the
  interpolated base, lateral k from the end of main edge k).
- Mean: a Karcher iteration — register every root's edges onto the current mean's, average the
  registered SRVFs — from the plain average of the SRVFs.

All DPs of a call (every edge of every pair) go through `dp_warp_batch` in fixed-size chunks,
so each (chunk, T, d) compiles once.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .._curves import l2_norm_squared, srvf, srvf_to_curve
from .._root import Root
from .._warp import apply_warp_srvf, dp_warp_batch, warp_energy
from ._fatherchild import (
    assemble,
    check_count,
    check_root,
    check_roots,
    check_same_dim,
    edge_slots,
    result_dtype,
)


@eqx.filter_jit
def _register_chunk(q1, q2, *, neighbourhood: int):
    gamma = dp_warp_batch(q1, q2, neighbourhood=neighbourhood)
    energy = jax.vmap(warp_energy)(q1, q2, gamma)
    return gamma, energy, jax.vmap(apply_warp_srvf)(q2, gamma)


def _srvf_tables(roots: list[Root], n_points: int):
    """``(Q (N, 2C+1, T, d), origins (N, d))``: SRVFs of every father–child edge slot."""
    capacity = max(r.n_laterals for r in roots)
    dtype = result_dtype(roots)
    reps = [edge_slots(r, capacity, n_points) for r in roots]
    curves = jnp.asarray(np.stack([e for e, _ in reps]).astype(dtype))
    return srvf(curves), np.stack([o for _, o in reps])


def _match(table1, i1, table2, i2, *, neighbourhood, chunk_size, keep=True, progress=False, desc=""):
    """Register ``table2[i2[k]]`` onto ``table1[i1[k]]`` for every k.

    Returns ``(energy (P,), gamma (P, T), registered (P, T, d))`` as numpy (the last two are
    None unless `keep`: a distance matrix needs only the energies). Pairs with a
    collapsed (zero) edge need no DP: the energy is the other edge's ``||q||²`` and the warp is
    the identity; the others go through `dp_warp_batch` in chunks of a fixed size (padded with
    repeats of a real pair, whose results are dropped).
    """
    neighbourhood = check_count(neighbourhood, "neighbourhood", 1)
    chunk_size = check_count(chunk_size, "chunk_size", 1)
    i1 = np.asarray(i1, np.int64)
    i2 = np.asarray(i2, np.int64)
    table1, table2 = np.asarray(table1), np.asarray(table2)
    n1 = np.asarray(l2_norm_squared(table1))
    n2 = np.asarray(l2_norm_squared(table2))
    size = table1.shape[-2]
    energy = n1[i1] + n2[i2]  # exact when one side is collapsed
    gamma = registered = None
    if keep:
        gamma = np.broadcast_to(np.linspace(0.0, 1.0, size, dtype=n1.dtype), (len(i1), size)).copy()
        registered = table2[i2]
    todo = np.flatnonzero((n1[i1] > 0) & (n2[i2] > 0))
    if len(todo):
        # Two chunk shapes at most (each compiles once): chunk_size for big jobs, 16 for small.
        chunk = chunk_size if len(todo) >= chunk_size else min(chunk_size, 16)
        with tqdm(total=len(todo), desc=desc, unit="edge pair", disable=not progress) as bar:
            for start in range(0, len(todo), chunk):
                rows = todo[start : start + chunk]
                m = len(rows)
                padded = np.concatenate([rows, np.full(chunk - m, rows[0])])
                g, e, r = _register_chunk(table1[i1[padded]], table2[i2[padded]], neighbourhood=neighbourhood)
                energy[rows] = np.asarray(e)[:m]
                if keep:
                    gamma[rows] = np.asarray(g)[:m]
                    registered[rows] = np.asarray(r)[:m]
                bar.update(m)
    return energy, gamma, registered


def _pair(a, b, what: str) -> list[Root]:
    pair = [check_root(a, f"{what}: a"), check_root(b, f"{what}: b")]
    check_same_dim(pair, what)
    return pair


def _register_pair(a: Root, b: Root, *, n_points, neighbourhood, what):
    """Edge SRVFs of a and b, and b's edges registered onto a's: ``(Q, origins, energy,
    gamma, registered)`` with one row per edge slot."""
    pair = _pair(a, b, what)
    n_points = check_count(n_points, "n_points", 2)
    Q, origins = _srvf_tables(pair, n_points)
    E = Q.shape[1]
    flat = Q.reshape((-1,) + Q.shape[2:])
    slots = np.arange(E)
    energy, gamma, registered = _match(flat, slots, flat, E + slots, neighbourhood=neighbourhood, chunk_size=256)
    return Q, origins, energy, gamma, registered


def fc_srvf_distance(a: Root, b: Root, *, n_points: int = 50, neighbourhood: int = 7) -> float:
    """Father–child elastic distance: ``sqrt`` of the summed DP warp energies of the
    corresponding edges (b's edges registered onto a's; fixed correspondence).

    `n_points`: samples per edge's SRVF, uniform in arc length; `neighbourhood`: the DP's move
    set (coprime steps up to this size), as in `dp_warp`."""
    _, _, energy, _, _ = _register_pair(a, b, n_points=n_points, neighbourhood=neighbourhood, what="fc_srvf_distance")
    return float(np.sqrt(max(float(np.sum(energy)), 0.0)))


def fc_srvf_distance_matrix(
    roots,
    *,
    n_points: int = 50,
    neighbourhood: int = 7,
    chunk_size: int = 512,
    progress: bool = False,
) -> np.ndarray:
    """``(N, N)`` matrix of `fc_srvf_distance`: entry (i, j), i < j, registers root j onto
    root i and is mirrored (exactly symmetric, zero diagonal). Every edge DP of every pair runs
    through `dp_warp_batch` in chunks of `chunk_size` edge pairs (tqdm bar with `progress`).
    `n_points`, `neighbourhood`: as in `fc_srvf_distance`."""
    roots = check_roots(roots, "fc_srvf_distance_matrix")
    n_points = check_count(n_points, "n_points", 2)
    n = len(roots)
    Q, _ = _srvf_tables(roots, n_points)
    E = Q.shape[1]
    flat = Q.reshape((-1,) + Q.shape[2:])
    I, J = np.triu_indices(n, k=1)
    e = np.arange(E)
    i1 = (I[:, None] * E + e[None]).reshape(-1)
    i2 = (J[:, None] * E + e[None]).reshape(-1)
    energy, _, _ = _match(
        flat,
        i1,
        flat,
        i2,
        neighbourhood=neighbourhood,
        chunk_size=chunk_size,
        keep=False,
        progress=progress,
        desc="fc-SRVF distances",
    )
    D = np.zeros((n, n), dtype=energy.dtype)
    D[I, J] = np.sqrt(np.maximum(energy.reshape(len(I), E).sum(1), 0.0))
    return D + D.T


def fc_srvf_geodesic(a: Root, b: Root, *, n_steps: int = 9, n_points: int = 50, neighbourhood: int = 7) -> list[Root]:
    """The straight line ``(1 − τ) q_a + τ q̃_b`` for every edge (``q̃_b`` = b's edge registered
    onto a's), integrated back father to child. Slot k of every step is the k-th lateral along
    the main root (padded laterals grow from zero). The first step is a resampled (through its
    SRVF), the last is b with each edge reparameterised by its warp."""
    n_steps = check_count(n_steps, "n_steps", 2)
    Q, origins, _, _, registered = _register_pair(
        a, b, n_points=n_points, neighbourhood=neighbourhood, what="fc_srvf_geodesic"
    )
    qa = np.asarray(Q[0])
    taus = np.linspace(0.0, 1.0, n_steps)
    path = (1 - taus)[:, None, None, None] * qa[None] + taus[:, None, None, None] * registered[None]
    curves = np.asarray(srvf_to_curve(jnp.asarray(path)))
    dtype = result_dtype([a, b])
    return [
        assemble(
            (1 - t) * origins[0] + t * origins[1],
            curves[i],
            dtype=dtype,
            name=f"fc_srvf_geodesic_{i}",
            metadata={"method": "fc_srvf", "tau": float(t)},
        )
        for i, t in enumerate(taus)
    ]


def fc_srvf_mean(
    roots,
    *,
    n_points: int = 50,
    max_steps: int = 10,
    neighbourhood: int = 7,
    rtol: float = 1e-4,
) -> Root:
    """Karcher mean under the father–child elastic metric: start from the average of the edge
    SRVFs; each step registers every root's edges onto the current mean's and averages the
    registered SRVFs; stop when the mean energy ``(1/N) Σ_i d²(μ, x_i)`` changes by less than
    `rtol` (relative) or after `max_steps` steps. The energy trace is in
    ``metadata["energies"]``."""
    roots = check_roots(roots, "fc_srvf_mean")
    n_points = check_count(n_points, "n_points", 2)
    max_steps = check_count(max_steps, "max_steps", 1)
    Q, origins = _srvf_tables(roots, n_points)
    n, E = Q.shape[:2]
    flat = Q.reshape((-1,) + Q.shape[2:])
    mu = np.asarray(Q).mean(0)
    i1 = np.tile(np.arange(E), n)
    i2 = np.arange(n * E)
    energies = []
    for _ in range(max_steps):
        energy, _, registered = _match(mu, i1, flat, i2, neighbourhood=neighbourhood, chunk_size=512)
        energies.append(float(energy.sum() / n))
        mu = registered.reshape((n, E) + registered.shape[1:]).mean(0)
        if len(energies) > 1 and abs(energies[-2] - energies[-1]) <= rtol * energies[-2]:
            break
    curves = np.asarray(srvf_to_curve(jnp.asarray(mu)))
    return assemble(
        origins.mean(0),
        curves,
        dtype=result_dtype(roots),
        name="fc_srvf_mean",
        metadata={"method": "fc_srvf", "n_roots": n, "energies": energies, "steps": len(energies)},
    )
