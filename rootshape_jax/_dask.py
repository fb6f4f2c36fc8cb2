"""The Dask executor (`client=`; extra ``rootshape_jax[dask]``): blocks of work on a cluster.

We do not schedule anything ourselves: Dask distributed does, and labs already run it on
SLURM/PBS (dask-jobqueue) or Kubernetes. Dask is imported only when a client is used.

`DaskExecutor` implements `_executor.Executor`: the shared arguments of a map (the padded
arrays, weights, options) are scattered once to every worker; each block is one task calling
the block function (`_pairwise.pair_block`, `_mean.mean_step_block`, ...) — the same compiled
kernels as the local path, so results equal the local ones bit for bit (both on one XLA device
per process). Finished blocks go to the caller's `BlockStore` as they arrive.

Tasks set the worker's ``jax_enable_x64`` to the client's before touching any array (arrays
travel as numpy, so a float64 batch is not cast on a worker whose JAX starts in float32).

The package registers `dask_executor_for` with `_executor.register_client_executor` on import,
so `client=` reaches this module without any maths module importing it.
"""

from __future__ import annotations

import uuid

import jax
import numpy as np

from ._errors import MissingDependencyError
from ._executor import Executor, register_client_executor


def _distributed():
    try:
        import distributed
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise MissingDependencyError(
            "client= needs Dask distributed; install it with `pip install 'rootshape_jax[dask]'`."
        ) from e
    return distributed


def check_client(client, what: str):
    """The `distributed` module, or a clear error (MissingDependencyError without dask,
    TypeError for anything but a Client)."""
    distributed = _distributed()
    if not isinstance(client, distributed.Client):
        raise TypeError(
            f"{what}: client must be a dask.distributed.Client (or None for the local path), "
            f"got {type(client).__name__}."
        )
    return distributed


def _x64() -> bool:
    return bool(jax.config.read("jax_enable_x64"))


def _set_x64(enabled: bool) -> None:
    """In a worker: use the client's float width (a float64 batch would otherwise be cast)."""
    if _x64() != enabled:
        jax.config.update("jax_enable_x64", enabled)


def _to_numpy(tree):
    return jax.tree.map(np.asarray, tree)


def _task(fn, x64: bool, block, shared):
    _set_x64(x64)
    return fn(*block, *shared)


def _cancel(client, futures) -> None:
    pending = [f for f in futures if not f.done()]
    if pending:
        client.cancel(pending)


class DaskExecutor(Executor):
    """Runs blocks as tasks on a ``dask.distributed.Client`` (results as they complete)."""

    def __init__(self, client):
        self.distributed = check_client(client, "client")
        self.client = client

    def _run(self, fn, blocks, todo, shared):
        if not todo:
            return
        client = self.client
        x64 = _x64()
        [shared_future] = client.scatter([_to_numpy(shared)], broadcast=True, hash=False)
        run = uuid.uuid4().hex[:8]
        name = getattr(fn, "__name__", "block")
        futures = client.map(
            _task,
            [fn] * len(todo),
            [x64] * len(todo),
            [_to_numpy(blocks[b]) for b in todo],
            shared=shared_future,
            key=[f"rootshape-{name}-{run}-{b}" for b in todo],
            pure=False,
        )
        index = dict(zip(futures, todo))
        try:
            for f in self.distributed.as_completed(list(futures)):
                result = f.result()  # re-raises a task's error (or KilledWorker)
                yield index[f], result
                f.release()
        finally:
            _cancel(client, list(futures))


def dask_executor_for(client) -> DaskExecutor | None:
    """A `DaskExecutor` for a Dask client (checked, so a missing extra is named); None for
    objects that are not Dask clients."""
    if type(client).__module__.split(".")[0] != "distributed":
        return None
    return DaskExecutor(client)


register_client_executor(dask_executor_for)
