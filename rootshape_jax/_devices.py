"""Split a leading batch axis across every available device (DESIGN.md §8).

XLA:CPU runs most of a loop on one core. Several host devices (set with
``jax.config.update("jax_num_cpu_devices", n)`` *before* JAX initialises — the command line and
the benchmarks do this; the library never changes global configuration) let a batch run on every
core: `split_over_devices` pads the batch to a multiple of the device count, gives each device
an equal slice with `jax.shard_map`, and drops the padding. With one device it calls the
function as is. `device_vmap` is the same splitter around ``jax.vmap(fn)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ._errors import InvalidRootError


def split_over_devices(
    fn: Callable, batched: tuple, shared: tuple = (), *, devices: Sequence[Any] | None = None
):
    """``fn(*batched, *shared)`` with the leading axis of `batched` split evenly across devices.

    Rows are independent, so no collective runs inside: each device computes its own share
    (host callbacks included). The batch is padded with copies of its first row (valid input;
    the padded rows are dropped). `shared` arguments are replicated. Use it inside
    `jax.jit`/`eqx.filter_jit` so the split compiles once.

    ``fn`` must not raise runtime errors (`eqx.error_if`) on the data it gets: raised on one
    device of a multi-device program, the error leaves the other devices waiting in a
    collective until XLA aborts the process. Check inputs beforehand, or return NaN.
    """
    leaves = jax.tree.leaves(batched)
    if not leaves:
        raise InvalidRootError("split_over_devices: needs at least one batched array argument.")
    sizes = {jnp.shape(x)[0] if jnp.ndim(x) else None for x in leaves}
    if len(sizes) != 1 or None in sizes:
        raise InvalidRootError(
            "split_over_devices: every batched array needs the same leading axis, got leading "
            f"sizes {sorted(str(s) for s in sizes)}."
        )
    (size,) = sizes
    devs = list(jax.devices() if devices is None else devices)
    n_dev = len(devs)
    if n_dev <= 1 or size < n_dev:
        return fn(*batched, *shared)
    pad = (-size) % n_dev
    if pad:
        batched = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), batched)
    mesh = Mesh(np.asarray(devs), ("batch",))
    specs = (PartitionSpec("batch"),) * len(batched) + (PartitionSpec(),) * len(shared)
    # check_vma=False: scan carries (DP rows) are created inside, not varying over devices.
    out = jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"), check_vma=False)(
        *batched, *shared
    )
    return jax.tree.map(lambda x: x[:size], out) if pad else out


def device_vmap(fn: Callable, *, devices: Sequence[Any] | None = None) -> Callable:
    """``jax.vmap(fn)`` over the leading axis of every argument, split across devices
    (`split_over_devices`). Bind options with `functools.partial` first."""
    vfn = jax.vmap(fn)
    return lambda *args: split_over_devices(vfn, args, devices=devices)
