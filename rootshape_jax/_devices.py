"""Split a leading batch axis across every available device (DESIGN.md §8).

XLA:CPU runs most of a loop on one core. Several host devices (set with
``jax.config.update("jax_num_cpu_devices", n)`` *before* JAX initialises — the command line and
the benchmarks do this; the library never changes global configuration) let a batch run on every
core: `device_vmap` pads the batch to a multiple of the device count, gives each device an equal
slice with `jax.shard_map`, and drops the padding. With one device it is plain `jax.vmap`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ._errors import InvalidRootError


def device_vmap(fn: Callable, *, devices: Sequence[Any] | None = None) -> Callable:
    """``jax.vmap(fn)`` over the leading axis of every argument, split across devices.

    **Arguments**

    - `fn`: function of unbatched arguments (pytrees of arrays). Bind options with
      `functools.partial` first.
    - `devices`: devices to use; default `jax.devices()` (all devices of the default backend).

    **Returns** a function of batched arguments (every array leaf has the same leading size B)
    returning `fn`'s outputs stacked along a leading axis of size B. The batch is padded (by
    repeating its last element, so padding is valid input) to a multiple of the device count.
    Use it inside `jax.jit`/`eqx.filter_jit` so the split compiles once.

    ``fn`` must not raise runtime errors (`eqx.error_if`) on the data it gets: raised on one
    device of a multi-device program, the error leaves the other devices waiting in a
    collective until XLA aborts the process. Check inputs beforehand, or return NaN.
    """
    vfn = jax.vmap(fn)

    def batched(*args):
        leaves = jax.tree.leaves(args)
        if not leaves:
            raise InvalidRootError("device_vmap: needs at least one batched array argument.")
        sizes = {jnp.shape(x)[0] if jnp.ndim(x) else None for x in leaves}
        if len(sizes) != 1 or None in sizes:
            raise InvalidRootError(
                "device_vmap: every array argument needs the same leading batch axis, got "
                f"leading sizes {sorted(str(s) for s in sizes)}."
            )
        (size,) = sizes
        devs = list(jax.devices() if devices is None else devices)
        n_dev = len(devs)
        if n_dev <= 1 or size <= 1:
            return vfn(*args)
        pad = (-size) % n_dev
        if pad:
            args = jax.tree.map(
                lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0), args
            )
        mesh = Mesh(np.asarray(devs), ("batch",))
        spec = PartitionSpec("batch")
        # check_vma=False: the DP's scan carries are created inside, not varying over devices.
        out = jax.shard_map(vfn, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)(*args)
        if pad:
            out = jax.tree.map(lambda x: x[:size], out)
        return out

    return batched
