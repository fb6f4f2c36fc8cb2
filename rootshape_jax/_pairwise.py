"""Distance matrices: every pair through one compiled, batched registration, in chunks."""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from ._metric import Weights
import functools

from ._registration import _apply, _device_safe, _options, _search_split_args, split_over_devices
from ._metric import preshape_terms
from ._tree import RootTree, SRVFTree, batch_size, check_compatible, to_srvf


@eqx.filter_jit
def _chunk_energies(a: SRVFTree, b: SRVFTree, active, weights: Weights, dynamic, **options):
    """Squared distances of the pairs (a[k], b[k]); inactive pairs do no DP work. The shapes
    depend on the chunk size only, so one compiled program serves every chunk and every N."""
    search = functools.partial(_search_split_args, **_device_safe(options))
    O, perm, g0, gam, _, n_dp, n_skipped = split_over_devices(search, (a, b, active), (weights, dynamic))
    registered = jax.vmap(_apply)(a, b, O, perm, g0, gam)
    energy = preshape_terms(a, registered, weights).total
    return energy, n_dp, n_skipped


def _as_batch(trees, name) -> SRVFTree:
    if not isinstance(trees, (RootTree, SRVFTree)):
        raise TypeError(
            f"{name} must be a batched RootTree or SRVFTree (rootshape_jax.batch(roots)), "
            f"got {type(trees).__name__}."
        )
    s = to_srvf(trees)
    n = batch_size(s)
    if n == 0:
        raise ValueError(f"{name} is an empty batch; give at least one root.")
    return s


def _run_pairs(s, t, I, J, *, weights, chunk_size, progress, desc, options):
    dynamic, opts = options
    n = len(I)
    energies = np.zeros(n, dtype=np.asarray(s.q0).dtype)
    stats = {"pairs": n, "lateral_dp": 0, "lateral_skipped": 0}
    with tqdm(total=n, desc=desc, unit="pair", disable=not progress) as bar:
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
            e, n_dp, n_skipped = _chunk_energies(a, b, jnp.asarray(active), weights, dynamic, **opts)
            energies[start:stop] = np.asarray(e)[:m]
            stats["lateral_dp"] += int(np.sum(np.asarray(n_dp)[:m]))
            stats["lateral_skipped"] += int(np.sum(np.asarray(n_skipped)[:m]))
            bar.update(m)
    return energies, stats


def _dispatch(s, t, I, J, kind, *, client, block_size, store, resume, **kwargs):
    """The local loop, or the same loop in blocks on a Dask client (`_dask.run_pairs`)."""
    chunk_size = kwargs["chunk_size"]
    if not isinstance(chunk_size, int) or isinstance(chunk_size, bool) or chunk_size < 1:
        raise ValueError(f"chunk_size must be an integer >= 1, got {chunk_size!r}.")
    if client is None:
        if block_size is not None or store is not None:
            raise ValueError("block_size and store apply to a Dask run only; pass client= too.")
        return _run_pairs(s, t, I, J, **kwargs)
    from ._dask import run_pairs

    return run_pairs(client, s, t, I, J, kind=kind, block_size=block_size, store=store,
                     resume=resume, **kwargs)


def pairwise_distances(
    trees: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    chunk_size: int = 32,
    progress: bool = True,
    return_stats: bool = False,
    rotation: bool = True,
    max_iterations: int = 4,
    rtol: float = 1e-4,
    neighbourhood: int = 7,
    prune: bool = True,
    dp_batch_size: int = 32,
    assignment: str = "callback",
    client=None,
    block_size: int | None = None,
    store: str | os.PathLike | None = None,
    resume: bool = True,
) -> Float[Array, "N N"]:
    """Symmetric (N, N) matrix of elastic distances between the roots of a batch.

    Every pair i < j is registered (b = root j onto a = root i) by one compiled program, in
    chunks of `chunk_size` pairs so memory stays bounded; a tqdm bar shows progress and Ctrl-C
    stops between chunks. The diagonal is 0. With `return_stats=True` also returns a dict with
    the number of lateral DPs run and skipped by the exact pruning bound. Registration options
    as in `register`.

    **On a Dask cluster** (extra ``rootshape_jax[dask]``): with `client` (a
    ``dask.distributed.Client``) the pairs are sent in blocks of `block_size` pairs (a multiple
    of `chunk_size`; default ``8 × chunk_size``) through the same compiled kernel, so the matrix
    equals the local one bit for bit. With `store` (a directory) every finished block is saved;
    a rerun with ``resume=True`` computes only the missing blocks, and a store of another run is
    refused. The stats then also count ``blocks``, ``blocks_computed`` and ``blocks_from_store``.
    """
    weights = Weights() if weights is None else weights
    opts = _options(rotation, max_iterations, rtol, neighbourhood, prune, dp_batch_size, assignment)
    s = _as_batch(trees, "pairwise_distances: trees")
    n = batch_size(s)
    I, J = np.triu_indices(n, 1)
    e, stats = _dispatch(
        s, s, I, J, "pairwise", weights=weights, chunk_size=chunk_size, progress=progress,
        desc="distances", options=opts, client=client, block_size=block_size, store=store,
        resume=resume,
    )
    D = np.zeros((n, n), dtype=e.dtype)
    D[I, J] = np.sqrt(np.maximum(e, 0.0))
    D[J, I] = D[I, J]
    D = jnp.asarray(D)
    return (D, stats) if return_stats else D


def cross_distances(
    A: RootTree | SRVFTree,
    B: RootTree | SRVFTree,
    *,
    weights: Weights | None = None,
    chunk_size: int = 32,
    progress: bool = True,
    rotation: bool = True,
    max_iterations: int = 4,
    rtol: float = 1e-4,
    neighbourhood: int = 7,
    prune: bool = True,
    dp_batch_size: int = 32,
    assignment: str = "callback",
    client=None,
    block_size: int | None = None,
    store: str | os.PathLike | None = None,
    resume: bool = True,
) -> Float[Array, "N M"]:
    """(N, M) matrix of distances between every root of batch `A` and every root of batch `B`
    (root ``B[j]`` registered onto ``A[i]``). `client`, `block_size`, `store`, `resume`: as in
    `pairwise_distances`."""
    weights = Weights() if weights is None else weights
    opts = _options(rotation, max_iterations, rtol, neighbourhood, prune, dp_batch_size, assignment)
    s = _as_batch(A, "cross_distances: A")
    t = _as_batch(B, "cross_distances: B")
    check_compatible(s, t, "cross_distances: A and B")
    n, m = batch_size(s), batch_size(t)
    I, J = (x.ravel() for x in np.meshgrid(np.arange(n), np.arange(m), indexing="ij"))
    e, _ = _dispatch(
        s, t, I, J, "cross", weights=weights, chunk_size=chunk_size, progress=progress,
        desc="cross distances", options=opts, client=client, block_size=block_size, store=store,
        resume=resume,
    )
    return jnp.asarray(np.sqrt(np.maximum(e, 0.0)).reshape(n, m))


