"""Distance matrices: every pair through the registration engine, in chunks and blocks.

The pairs (the upper triangle for `pairwise_distances`, every (i, j) for `cross_distances`)
are cut into blocks of `block_size` pairs, a multiple of `chunk_size`; `pair_block` computes
one block with one compiled program per chunk shape (`chunk_energies`), and an executor
(`_executor`: here by default, on Dask with `client=`) maps it over the blocks. Since a block
starts on a chunk boundary, every chunk holds the same pairs and padding wherever it runs, so
the matrix does not depend on the executor or the block size.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._engine import METRIC_REVISION, RegistrationOptions, pair_distances_squared, registration_options
from ._executor import BlockStore, LocalExecutor, executor_for, fingerprint
from ._metric import Weights, as_weights
from ._registration import warn_forced_matches
from ._tree import RootTree, SRVFTree, batch_size, check_compatible, is_traced, to_srvf


@eqx.filter_jit
def chunk_energies(a: SRVFTree, b: SRVFTree, active, weights: Weights, options: RegistrationOptions):
    """Squared distances of the pairs (a[k], b[k]), each registered in canonical order (so the
    matrix agrees with `distance` either way round); inactive pairs do no DP work. The shapes
    depend on the chunk size only, so one compiled program serves every chunk and every N."""
    return pair_distances_squared(a, b, weights, options, active)


def run_pair_chunks(s, t, I, J, weights, options, chunk_size: int) -> dict:
    """Squared distances of the pairs (s[I[k]], t[J[k]]), `chunk_size` pairs per call."""
    n = len(I)
    energies = np.zeros(n, dtype=np.asarray(s.q0).dtype)
    n_dp = n_skipped = 0
    n_deeper = np.zeros(len(s.deeper), np.int64)
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        m = stop - start
        ii = np.zeros(chunk_size, np.int32)
        jj = np.zeros(chunk_size, np.int32)
        ii[:m] = I[start:stop]
        jj[:m] = J[start:stop]
        active = np.arange(chunk_size) < m
        a = jax.tree.map(lambda x: x[ii], s)
        b = jax.tree.map(lambda x: x[jj], t)
        e, dp, sk, deeper = chunk_energies(a, b, jnp.asarray(active), weights, options)
        energies[start:stop] = np.asarray(e)[:m]
        n_dp += int(np.sum(np.asarray(dp)[:m]))
        n_skipped += int(np.sum(np.asarray(sk)[:m]))
        n_deeper += np.sum(np.asarray(deeper)[:m], axis=0).astype(np.int64)
    return {
        "energies": energies,
        "lateral_dp": np.int64(n_dp),
        "lateral_skipped": np.int64(n_skipped),
        "deeper_dp": n_deeper,
    }


def pair_block(I, J, s, t, weights, options, chunk_size: int) -> dict:
    """The block function: one block of pairs (looked up by name, so a worker can patch it)."""
    return run_pair_chunks(s, t, I, J, weights, options, chunk_size)


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}.")
    return int(value)


#: Lateral-slot pairs (K × K per root pair) a chunk holds by default. The engine carries K × K
#: arrays for every pair of a chunk and loops until its slowest pair is done, so a chunk of
#: roots with many slots costs more than its pairs would alone. Measured (BENCHMARKS.md): the
#: CPlantBox pea matrix (K = 54) takes the same time in chunks of 32, 16 or 8; the RootNav
#: tracings' (K = 126) 22.1 s in chunks of 32 and 11.4 s in chunks of 8 (the default here),
#: same distances; SmartRoot maize (K = 842) with 3 roots 414 s in chunks of 32, 33 s in 1s.
CHUNK_SLOT_PAIRS = 32 * 64 * 64


def default_chunk_size(slots: int) -> int:
    """Pairs per compiled call for roots of `slots` lateral slots: a power of two (so it divides
    any power-of-two `block_size`, e.g. the CLI store's 64), at most 32, at least 1."""
    fit = max(1, CHUNK_SLOT_PAIRS // max(1, slots) ** 2)
    return int(min(32, 1 << (fit.bit_length() - 1)))


def run_pairs(
    s, t, I, J, kind: str, *, weights, options, chunk_size, client, block_size, store, resume, progress, desc
):
    """Squared distances of the listed pairs, and stats: local or on a cluster, with a store."""
    if chunk_size is None:
        chunk_size = default_chunk_size(s.capacity)  # t's equals it (check_compatible)
    chunk_size = _positive_int(chunk_size, "chunk_size")
    executor = executor_for(client)
    local = isinstance(executor, LocalExecutor)
    if block_size is None:
        # Locally a block is a chunk (progress and the store advance chunk by chunk).
        block_size = chunk_size if local else 8 * chunk_size
    block_size = _positive_int(block_size, "block_size")
    if block_size % chunk_size:
        raise ValueError(
            f"block_size ({block_size}) must be a multiple of chunk_size ({chunk_size}), so that "
            "every chunk holds the same pairs wherever it runs (equal results)."
        )
    if not isinstance(resume, bool):
        raise TypeError(f"resume must be True or False, got {resume!r}.")
    n_pairs = len(I)
    spans = [(a, min(a + block_size, n_pairs)) for a in range(0, n_pairs, block_size)]
    st = None
    if store is not None:
        dtype = np.asarray(s.q0).dtype
        st = BlockStore(
            store,
            {
                "kind": kind,
                "n": int(s.q0.shape[0]),
                "m": int(t.q0.shape[0]),
                "n_pairs": n_pairs,
                "block_size": block_size,
                "chunk_size": chunk_size,
                "dtype": str(dtype),
                "metric_revision": METRIC_REVISION,
                "fingerprint": fingerprint(kind, s, t, weights, options, repr(options)),
            },
        )
    results, counts = executor.map_blocks(
        pair_block,
        [(I[a:z], J[a:z]) for a, z in spans],
        shared=(s, t, weights, options, chunk_size),
        sizes=[z - a for a, z in spans],
        store=st,
        resume=resume,
        progress=progress,
        desc=desc,
        unit="pair",
    )
    energies = np.concatenate([r["energies"] for r in results]) if results else np.zeros(0)
    stats = {
        "pairs": n_pairs,
        "lateral_dp": int(sum(int(r["lateral_dp"]) for r in results)),
        "lateral_skipped": int(sum(int(r["lateral_skipped"]) for r in results)),
        # DPs run per deeper level (docs/design.md §11): [] at depth 2.
        "deeper_dp": [int(sum(int(r["deeper_dp"][k]) for r in results)) for k in range(len(s.deeper))],
        **counts,
    }
    return energies, stats


def _as_batch(trees, name, weights) -> SRVFTree:
    if not isinstance(trees, (RootTree, SRVFTree)):
        raise TypeError(
            f"{name} must be a batched RootTree or SRVFTree (rootshape_jax.batch(roots)), got {type(trees).__name__}."
        )
    if is_traced(trees, weights):
        raise TypeError(
            f"{name.split(':')[0]} cannot run under jax.jit or jax.vmap: it loops over chunks of pairs in "
            "Python (progress bar, Ctrl-C, store), each chunk a compiled program already. Call it outside "
            "jit; inside your own jitted code use jax.vmap(rootshape_jax.distance) over pairs."
        )
    s = to_srvf(trees, weights=weights)
    n = batch_size(s)
    if n == 0:
        raise ValueError(f"{name} is an empty batch; give at least one root.")
    return s


def pairwise_distances(
    trees: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    return_stats: bool = False,
    client=None,
    block_size: int | None = None,
    store: str | os.PathLike | None = None,
    resume: bool = True,
    **options,
) -> Float[Array, "N N"]:
    """Symmetric (N, N) matrix of elastic distances between the roots of a batch.

    Every pair i < j is registered (b = root j onto a = root i) by one compiled program, in
    chunks of `chunk_size` pairs so memory stays bounded (default: 32 for roots of up to 64
    lateral slots, a smaller power of two for more slots, 1 from 257; `default_chunk_size`); a tqdm bar
    shows progress and Ctrl-C stops between chunks. The diagonal is 0. With `return_stats=True` also returns a dict with
    the number of pairs, of lateral DPs run and skipped by the exact pruning bound, and of
    blocks computed and read from a store. Registration options: `registration` (a
    `RegistrationOptions`) or its fields as keywords, as in `register`. `weights`: the metric's
    λ (default the paper's); entries equal `distance`'s, in its units (unitless for
    scale-normalised trees, else depending on the coordinates' unit).

    **Store** (`store=DIR`): every finished block of `block_size` pairs (default: one chunk
    here, ``8 × chunk_size`` on a cluster) is saved; a rerun with ``resume=True`` computes only
    the missing blocks, and a store of another run is refused (`StoreMismatchError`).

    **On a Dask cluster** (extra ``rootshape_jax[dask]``): with `client` (a
    ``dask.distributed.Client``) the blocks run on the cluster through the same compiled
    kernel, so the matrix equals the local one bit for bit.
    """
    weights = as_weights(weights)
    opts = registration_options(registration, **options)
    s = _as_batch(trees, "pairwise_distances: trees", weights)
    warn_forced_matches(s, s, "pairwise_distances", pairs="all")
    n = batch_size(s)
    I, J = np.triu_indices(n, 1)
    e, stats = run_pairs(
        s,
        s,
        I,
        J,
        "pairwise",
        weights=weights,
        options=opts,
        chunk_size=chunk_size,
        client=client,
        block_size=block_size,
        store=store,
        resume=resume,
        progress=progress,
        desc="distances",
    )
    D = np.zeros((n, n), dtype=np.asarray(s.q0).dtype)
    D[I, J] = np.sqrt(np.maximum(e, 0.0))
    D[J, I] = D[I, J]
    D = jnp.asarray(D)
    return (D, stats) if return_stats else D


def cross_distances(
    A: RootTree | SRVFTree,
    B: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    registration: RegistrationOptions | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    client=None,
    block_size: int | None = None,
    store: str | os.PathLike | None = None,
    resume: bool = True,
    **options,
) -> Float[Array, "N M"]:
    """(N, M) matrix of distances between every root of batch `A` and every root of batch `B`
    (root ``B[j]`` registered onto ``A[i]``). Other arguments as in `pairwise_distances`."""
    weights = as_weights(weights)
    opts = registration_options(registration, **options)
    s = _as_batch(A, "cross_distances: A", weights)
    t = _as_batch(B, "cross_distances: B", weights)
    check_compatible(s, t, "cross_distances: A and B")
    warn_forced_matches(s, t, "cross_distances", pairs="cross")
    n, m = batch_size(s), batch_size(t)
    I, J = (x.ravel() for x in np.meshgrid(np.arange(n), np.arange(m), indexing="ij"))
    e, _ = run_pairs(
        s,
        t,
        I,
        J,
        "cross",
        weights=weights,
        options=opts,
        chunk_size=chunk_size,
        client=client,
        block_size=block_size,
        store=store,
        resume=resume,
        progress=progress,
        desc="cross distances",
    )
    return jnp.asarray(np.sqrt(np.maximum(e, 0.0)).reshape(n, m))
