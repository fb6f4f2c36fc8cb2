"""The scale-out seam (docs/design.md §13): blocks of work, and executors that map them.

The maths and statistics layers cut their work into blocks (a list of pairs, or a block of
samples for one mean step) and give a pure, module-level function that computes one block. An
executor maps that function over the blocks:

- `LocalExecutor` (the default) runs them here, on one thread per free core, with a progress bar;
- `rootshape_jax._dask.DaskExecutor` (when a ``dask.distributed.Client`` is given) runs them on
  a cluster. It registers itself with `register_client_executor` when the package is imported,
  so no maths module imports Dask.

Either can keep finished blocks in a `BlockStore` (a directory), so an interrupted run resumes
and computes only the missing blocks. Executors never look inside a block's result beyond
what `BlockStore` saves (a dict of numpy arrays).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from ._atomic import atomic_write
from ._devices import usable_cores
from ._errors import StoreMismatchError, as_count

_FORMAT = "rootshape_jax.pair_blocks/1"
_BLOCK = re.compile(r"^block_(\d+)\.npz$")


# --------------------------------------------------------------------------------------------
# Store


def fingerprint(*parts) -> str:
    """SHA-256 of arrays and small values (pytrees), for a store's manifest."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(parts):
        if isinstance(leaf, (str, int, float, bool)) or leaf is None:
            h.update(repr(leaf).encode())
            continue
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class BlockStore:
    """One ``block_NNNNNNN.npz`` per finished block plus a ``manifest.json`` that names the run
    (sizes, block size, a fingerprint of inputs and options). A store of another run is refused
    before any work starts."""

    def __init__(self, path, manifest: dict):
        self.path = Path(path)
        self.manifest = {"format": _FORMAT, **manifest}

    def open(self) -> None:
        """Create the store, or check that it belongs to this run."""
        p = self.path
        if p.exists() and not p.is_dir():
            raise ValueError(f"store {str(p)!r} exists and is not a directory.")
        mf = p / "manifest.json"
        if mf.exists():
            try:
                old = json.loads(mf.read_text())
            except (OSError, ValueError) as e:
                raise StoreMismatchError(f"store {str(p)!r}: manifest.json is unreadable ({e}).") from e
            diff = [k for k in self.manifest if old.get(k) != self.manifest[k]]
            if diff:
                details = ", ".join(
                    f"{k}: stored {old.get(k)!r} vs now {self.manifest[k]!r}" for k in diff if k != "fingerprint"
                )
                if "fingerprint" in diff:
                    details = "different input arrays or options" + (f"; {details}" if details else "")
                raise StoreMismatchError(
                    f"store {str(p)!r} holds another run ({details}). Use a new directory, or delete "
                    "this one to start over."
                )
            return
        if p.exists() and any(p.iterdir()):
            raise StoreMismatchError(
                f"store {str(p)!r} is not empty and has no manifest.json: not a block store. "
                "Give a new or empty directory."
            )
        p.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.manifest, indent=1)
        atomic_write(mf, lambda p: p.write_text(text), durable=True)

    def block_path(self, b: int) -> Path:
        return self.path / f"block_{b:07d}.npz"

    def finished(self) -> set[int]:
        return {int(m.group(1)) for name in os.listdir(self.path) if (m := _BLOCK.match(name))}

    def read(self, b: int) -> dict | None:
        """Block b's arrays, or None if missing or unreadable."""
        try:
            with np.load(self.block_path(b)) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError):
            return None

    def write(self, b: int, result: dict) -> None:
        def save(p: Path) -> None:
            with open(p, "wb") as f:  # a file object: np.savez would add ".npz" to a path
                np.savez(f, **result)

        atomic_write(self.block_path(b), save, durable=True)


# --------------------------------------------------------------------------------------------
# Executors


class Executor:
    """Maps a block function over blocks. Subclasses implement `_run`."""

    def map_blocks(
        self,
        fn: Callable[..., dict],
        blocks: Sequence[tuple],
        *,
        shared: tuple = (),
        sizes: Sequence[int] | None = None,
        store: BlockStore | None = None,
        resume: bool = True,
        progress: bool = True,
        desc: str = "",
        unit: str = "item",
        leave: bool = True,
    ) -> tuple[list[dict], dict]:
        """``[fn(*block, *shared) for block in blocks]`` (each a dict of numpy arrays), and
        counts ``blocks``, ``blocks_computed``, ``blocks_from_store``.

        `sizes` (items per block) drive the progress bar. With a `store`, finished blocks are
        saved as they come and, with ``resume=True``, blocks already there are loaded instead
        of computed.
        """
        n = len(blocks)
        sizes = [1] * n if sizes is None else list(sizes)
        results: list[dict | None] = [None] * n
        counts = {"blocks": n, "blocks_computed": 0, "blocks_from_store": 0}
        todo = list(range(n))
        if store is not None:
            store.open()
            if resume:
                done = store.finished()
                todo = []
                for b in range(n):
                    got = store.read(b) if b in done else None
                    if got is None:
                        todo.append(b)
                    else:
                        results[b] = got
                        counts["blocks_from_store"] += 1
        total = sum(sizes[b] for b in todo)
        with tqdm(total=total, desc=desc, unit=unit, disable=not progress, leave=leave) as bar:
            for b, result in self._run(fn, blocks, todo, shared):
                result = {k: np.asarray(v) for k, v in result.items()}
                if store is not None:
                    store.write(b, result)
                results[b] = result
                counts["blocks_computed"] += 1
                bar.update(sizes[b])
        return results, counts

    def _run(self, fn, blocks, todo, shared):
        """Yield ``(b, fn(*blocks[b], *shared))`` for every b in `todo`, in any order."""
        raise NotImplementedError


# Signatures of block calls already run in this process: a block function called again with
# the same shapes is compiled already, so its first block need not run alone.
_COMPILED: set = set()


def _call_signature(fn, block: tuple, shared: tuple):
    leaves, treedef = jax.tree.flatten((block, shared))
    parts = []
    for x in leaves:
        if hasattr(x, "shape") and hasattr(x, "dtype"):
            parts.append((tuple(x.shape), str(x.dtype)))
        else:
            parts.append((type(x).__name__, x if isinstance(x, (int, float, str, bool)) else id(x)))
    return (getattr(fn, "__module__", ""), getattr(fn, "__qualname__", repr(fn)), str(treedef), tuple(parts))


class LocalExecutor(Executor):
    """Runs every block in this process, on `workers` threads (Ctrl-C stops between blocks).

    XLA:CPU runs one compiled call on about one core, and releases the GIL while it runs, so
    blocks on several threads use several cores with no global JAX setting. The default,
    ``workers=None``, takes one thread per usable core left over by the devices: with
    `use_all_cores` each call is already split over every core, so one thread. The first block
    of a block function not yet run with these shapes runs alone, so its compilation is done
    once and then shared by the threads.
    """

    def __init__(self, workers: int | None = None):
        if workers is not None:
            workers = as_count(workers, "workers (or None)")
        self.workers = workers

    def n_workers(self) -> int:
        if self.workers is not None:
            return self.workers
        return max(1, usable_cores() // max(1, jax.local_device_count()))

    def _run(self, fn, blocks, todo, shared):
        todo = list(todo)
        workers = min(self.n_workers(), len(todo))
        if workers <= 1:
            for b in todo:
                yield b, fn(*blocks[b], *shared)
            return
        first = []
        key = _call_signature(fn, blocks[todo[0]], shared)
        if key not in _COMPILED:
            # Its compilation is done once, then shared by the threads.
            yield todo[0], fn(*blocks[todo[0]], *shared)
            _COMPILED.add(key)
            first = todo[:1]
        pool = ThreadPoolExecutor(workers, thread_name_prefix="rootshape")
        try:
            pending = {pool.submit(fn, *blocks[b], *shared): b for b in todo[len(first) :]}
            for future in as_completed(pending):
                yield pending[future], future.result()
        finally:
            # On Ctrl-C (or an error) drop the blocks not started; running ones finish.
            pool.shutdown(wait=False, cancel_futures=True)


_CLIENT_EXECUTORS: list[Callable[[Any], Executor | None]] = []


def register_client_executor(factory: Callable[[Any], Executor | None]) -> None:
    """Let `executor_for` turn a client object into an executor (``None``: not mine)."""
    _CLIENT_EXECUTORS.append(factory)


def executor_for(client) -> Executor:
    """The executor for a `client=` argument: local for None, else the one registered for it."""
    if client is None:
        return LocalExecutor()
    if isinstance(client, Executor):
        return client
    for factory in _CLIENT_EXECUTORS:
        ex = factory(client)
        if ex is not None:
            return ex
    raise TypeError(
        f"client must be a dask.distributed.Client (or None for the local path), got {type(client).__name__}."
    )
