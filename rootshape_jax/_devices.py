"""Cores and devices (docs/design.md §8): how many cores, and splitting a batch over devices.

`usable_cores` is the one count of CPU cores: the local executor runs that many worker threads
(divided by the devices), and `use_all_cores` asks for that many devices.

XLA:CPU runs one compiled call on about one core. The default path uses every core without any
global setting: blocks of work run on worker threads, one per core (`_executor.LocalExecutor`;
XLA releases the GIL). Several host devices (``jax.config.update("jax_num_cpu_devices", n)``
*before* JAX initialises: `use_all_cores`, or ``rootshape --devices N``; the library never
changes global configuration by itself) split each call instead: `split_over_devices` pads the
batch to a multiple of the device count, gives each device an equal slice with
`jax.shard_map`, and drops the padding. With one device it calls the function as is.
`device_vmap` is the same splitter around ``jax.vmap(fn)``. A call split over devices waits for
its slowest share, so on a busy machine threads are faster (measured on the pea matrix:
99.1 s on threads, 149.5 s on two devices; BENCHMARKS.md).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ._errors import InvalidRootError, user_stacklevel


def split_over_devices(fn: Callable, batched: tuple, shared: tuple = (), *, devices: Sequence[Any] | None = None):
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


# XLA:CPU waits for every device at a collective (e.g. gathering a split batch's results). When
# one device's share runs long on a busy machine, XLA logs "This thread has been waiting ... and
# may be stuck" after 20 s and aborts the process after 40 s (measured with a 2-device shard_map
# whose halves differ by 25 s and 130 s). The rows are independent and do finish: wait longer.
COLLECTIVE_TIMEOUT_FLAGS = {
    "--xla_cpu_collective_call_warn_stuck_timeout_seconds": 1800,
    "--xla_cpu_collective_call_terminate_timeout_seconds": 3600,
}


def relax_collective_timeouts() -> None:
    """Add `COLLECTIVE_TIMEOUT_FLAGS` to ``XLA_FLAGS``, keeping any value the user set. XLA reads
    the variable when its CPU backend starts, so this acts only before the first computation."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    given = {f.split("=", 1)[0] for f in flags}
    flags += [f"{k}={v}" for k, v in COLLECTIVE_TIMEOUT_FLAGS.items() if k not in given]
    os.environ["XLA_FLAGS"] = " ".join(flags)


def usable_cores() -> int:
    """CPU cores this process may run on (its CPU affinity; else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def use_all_cores(n: int | None = None) -> int:
    """Give JAX one CPU device per usable core (`usable_cores`, or `n`), so that each batched
    computation is split over the cores. Call it right after ``import rootshape_jax``, before
    any JAX computation: XLA fixes its devices when it starts.

    You do not need it to use every core: by default distance matrices, means and batched curve
    distances already run their blocks on one worker thread per core, which is faster (a call
    split over devices waits for its slowest share): on an idle 2-core machine the default was
    1.5–3.2× faster for every matrix and mean in BENCHMARKS.md's grid. Use it for your own
    batched computations (`split_over_devices`).

    This is the one place where the library changes JAX's global configuration, and only when
    you call it. It also relaxes XLA's timeouts for devices waiting on each other
    (`relax_collective_timeouts`), so a busy machine gets no false "may be stuck" lines. Returns
    the number of devices in use; if JAX has already started, nothing changes and a warning
    says how many devices it has.
    """
    import warnings

    want = int(n) if n is not None else usable_cores()
    if want < 1:
        raise ValueError(f"use_all_cores: n must be >= 1, got {n!r}.")
    relax_collective_timeouts()
    try:
        jax.config.update("jax_num_cpu_devices", want)
    except RuntimeError:
        have = jax.local_device_count()
        if have != want:
            warnings.warn(
                f"use_all_cores: JAX has already started with {have} device(s), so {want} cannot be "
                "set now; call rootshape_jax.use_all_cores() right after importing it, before any "
                "computation (restart the kernel in a notebook).",
                stacklevel=user_stacklevel(),
            )
        return have
    return want
