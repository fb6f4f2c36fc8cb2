"""Distance matrices and Karcher means on a Dask cluster (`client=`; extra ``rootshape_jax[dask]``).

We do not schedule anything ourselves: Dask distributed does, and labs already run it on
SLURM/PBS (dask-jobqueue) or Kubernetes. Dask is imported only when a client is passed.

**Distance matrices.** The pair list of the local path (the upper triangle for
`pairwise_distances`, every (i, j) for `cross_distances`) is cut into blocks of `block_size`
pairs, a multiple of `chunk_size`. The padded arrays are scattered once to every worker; each
task runs `_pairwise._run_pairs` — the same compiled, vmapped kernel as the local path — on its
block. Since a block starts on a chunk boundary, every chunk holds the same pairs and the same
padding as in the local run, so the matrix is bitwise equal to the local one (both on one XLA
device per process).

**Store.** With `store=DIR` the client writes each finished block as ``block_NNNNNNN.npz``
(temporary file, then `os.replace`: a block is on disk whole or not at all) beside a
``manifest.json`` recording the sizes, `block_size`, `chunk_size` and a SHA-256 of the input
arrays and options. A run with ``resume=True`` loads the blocks already there and submits only
the others; a store written for other inputs is refused before any task is submitted.

**Workers.** Tasks set the worker's ``jax_enable_x64`` to the client's (a float64 batch needs it
before any array is made, so JAX objects travel pickled and are unpickled inside the task).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import re
import uuid
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._errors import MissingDependencyError, RootShapeError

_FORMAT = "rootshape_jax.pair_blocks/1"
_BLOCK = re.compile(r"^block_(\d+)\.npz$")


class StoreMismatchError(RootShapeError, ValueError):
    """A `store=` directory holds blocks of another run (other inputs, options or block size)."""


# --------------------------------------------------------------------------------------------
# Shared helpers


def _distributed():
    try:
        import distributed
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise MissingDependencyError(
            "client= needs Dask distributed; install it with `pip install 'rootshape_jax[dask]'`."
        ) from e
    return distributed


def check_client(client, what: str):
    """The client, or a clear error (MissingDependencyError without dask, TypeError otherwise)."""
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


def _pack(obj) -> bytes:
    """JAX objects travel as bytes, unpickled inside the task once x64 is set."""
    return pickle.dumps(obj)


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}.")
    return int(value)


def _cancel(client, futures) -> None:
    pending = [f for f in futures if not f.done()]
    if pending:
        client.cancel(pending)


# --------------------------------------------------------------------------------------------
# Distance matrices


def _pair_block(I, J, s, t, payload: bytes, chunk_size: int, x64: bool):
    """Task: squared distances of one block of pairs, with the local path's own loop."""
    from ._pairwise import _run_pairs

    _set_x64(x64)
    weights, options = pickle.loads(payload)
    e, stats = _run_pairs(
        s, t, I, J, weights=weights, chunk_size=chunk_size, progress=False, desc="", options=options
    )
    return e, stats["lateral_dp"], stats["lateral_skipped"]


def _fingerprint(kind: str, s, t, weights, options) -> str:
    h = hashlib.sha256(kind.encode())
    for leaf in jax.tree.leaves((s, t)):
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    dynamic, static = options
    small = [np.asarray(x).tolist() for x in jax.tree.leaves((weights, dynamic))]
    h.update(repr((small, sorted(static.items()))).encode())
    return h.hexdigest()


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class _BlockStore:
    """One ``.npz`` per finished block plus ``manifest.json``; see the module docstring."""

    def __init__(self, path, manifest: dict):
        self.path = Path(path)
        self.manifest = manifest

    def open(self) -> None:
        """Create the store, or check that it belongs to this run (before any task is sent)."""
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
                    f"{k}: stored {old.get(k)!r} vs now {self.manifest[k]!r}"
                    for k in diff
                    if k != "fingerprint"
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
                f"store {str(p)!r} is not empty and has no manifest.json: not a distance store. "
                "Give a new or empty directory."
            )
        p.mkdir(parents=True, exist_ok=True)
        _atomic_write(mf, lambda f: f.write(json.dumps(self.manifest, indent=1).encode()))

    def block_path(self, b: int) -> Path:
        return self.path / f"block_{b:07d}.npz"

    def finished(self) -> set[int]:
        return {int(m.group(1)) for name in os.listdir(self.path) if (m := _BLOCK.match(name))}

    def read(self, b: int, size: int):
        """(energies, lateral_dp, lateral_skipped) of block b, or None if unreadable."""
        try:
            with np.load(self.block_path(b)) as z:
                e = z["energies"]
                dp, sk = int(z["lateral_dp"]), int(z["lateral_skipped"])
        except (OSError, ValueError, KeyError):
            return None
        return (e, dp, sk) if e.shape == (size,) else None

    def write(self, b: int, e, dp: int, sk: int) -> None:
        _atomic_write(
            self.block_path(b),
            lambda f: np.savez(f, energies=e, lateral_dp=np.int64(dp), lateral_skipped=np.int64(sk)),
        )


def run_pairs(
    client,
    s,
    t,
    I,
    J,
    *,
    kind: str,
    weights,
    chunk_size: int,
    block_size: int | None,
    store,
    resume: bool,
    progress: bool,
    desc: str,
    options,
):
    """`_pairwise._run_pairs` on a Dask cluster, in blocks: same (energies, stats), bitwise.

    Every input is checked before anything is sent. Stats add ``blocks``,
    ``blocks_computed`` (submitted in this call) and ``blocks_from_store``.
    """
    distributed = check_client(client, desc)
    block_size = 8 * chunk_size if block_size is None else _positive_int(block_size, "block_size")
    if block_size % chunk_size:
        raise ValueError(
            f"block_size ({block_size}) must be a multiple of chunk_size ({chunk_size}), so that "
            "every chunk holds the same pairs as in the local run (bitwise-equal results)."
        )
    if not isinstance(resume, bool):
        raise TypeError(f"resume must be True or False, got {resume!r}.")
    n_pairs = len(I)
    n_blocks = math.ceil(n_pairs / block_size)
    dtype = np.asarray(s.q0).dtype
    energies = np.zeros(n_pairs, dtype=dtype)
    stats = {"pairs": n_pairs, "lateral_dp": 0, "lateral_skipped": 0, "blocks": n_blocks,
             "blocks_computed": 0, "blocks_from_store": 0}

    def span(b):
        return b * block_size, min((b + 1) * block_size, n_pairs)

    todo = list(range(n_blocks))
    st = None
    if store is not None:
        manifest = {
            "format": _FORMAT, "kind": kind, "n": int(s.q0.shape[0]), "m": int(t.q0.shape[0]),
            "n_pairs": n_pairs, "block_size": block_size,
            "chunk_size": chunk_size, "dtype": str(dtype),
            "fingerprint": _fingerprint(kind, s, t, weights, options),
        }
        st = _BlockStore(store, manifest)
        st.open()
        if resume:
            todo = []
            done = st.finished()
            for b in range(n_blocks):
                a, z = span(b)
                got = st.read(b, z - a) if b in done else None
                if got is None:
                    todo.append(b)
                    continue
                energies[a:z] = got[0]
                stats["lateral_dp"] += got[1]
                stats["lateral_skipped"] += got[2]
                stats["blocks_from_store"] += 1
    if not todo:
        return energies, stats

    x64 = _x64()
    payload = _pack((weights, options))
    s_np = _to_numpy(s)
    [s_fut] = client.scatter([s_np], broadcast=True, hash=False)
    t_fut = s_fut if t is s else client.scatter([_to_numpy(t)], broadcast=True, hash=False)[0]
    run = uuid.uuid4().hex[:8]
    futures = {}
    try:
        spans = [span(b) for b in todo]
        submitted = client.map(
            _pair_block, [I[a:z] for a, z in spans], [J[a:z] for a, z in spans],
            s=s_fut, t=t_fut, payload=payload, chunk_size=chunk_size, x64=x64,
            key=[f"rootshape-{kind}-{run}-{b}" for b in todo],
        )
        futures = dict(zip(submitted, todo))
        with tqdm(total=sum(span(b)[1] - span(b)[0] for b in todo), desc=desc, unit="pair",
                  disable=not progress) as bar:
            for f in distributed.as_completed(list(futures)):
                e, dp, sk = f.result()  # re-raises a task's error (or KilledWorker)
                b = futures[f]
                a, z = span(b)
                e = np.asarray(e)
                if st is not None:
                    st.write(b, e, dp, sk)
                energies[a:z] = e
                stats["lateral_dp"] += dp
                stats["lateral_skipped"] += sk
                stats["blocks_computed"] += 1
                bar.update(z - a)
                f.release()
    finally:
        _cancel(client, list(futures))
    return energies, stats


# --------------------------------------------------------------------------------------------
# Karcher mean: the registrations of every sample onto the current mean, in blocks


def _slice_pad(tree, a: int, z: int, size: int):
    """Rows a:z of every leaf, padded to `size` rows by repeating row a (valid input; dropped)."""
    idx = np.concatenate([np.arange(a, z), np.full(size - (z - a), a)])
    return jax.tree.map(lambda x: np.asarray(x)[idx], tree)


def _mean_full_block(samples, a, z, size, mu, payload: bytes, x64: bool):
    """Task: full registration (rotation search) of samples a:z onto mu."""
    from ._mean import _full_registration

    _set_x64(x64)
    weights, origin, opts = pickle.loads(payload)
    block = _slice_pad(samples, a, z, size)
    out = _full_registration(jax.tree.map(jnp.asarray, mu), block, weights, origin, opts)
    return jax.tree.map(lambda x: np.asarray(x)[: z - a], out)


@eqx.filter_jit
def _fp_register_jit(y, samples, weights, origin, opts):
    from ._mean import _fp_register

    return _fp_register(y, samples, weights, origin, opts)


def _mean_step_block(samples, a, z, size, y_rows, mu, payload: bytes, x64: bool):
    """Task: one fixed-point registration step (`_mean._fp_register`) of samples a:z."""
    from ._mean import _FPIterate

    _set_x64(x64)
    weights, origin, opts = pickle.loads(payload)
    block = _slice_pad(samples, a, z, size)
    rows = _slice_pad(y_rows, 0, z - a, size)
    y = _FPIterate(jax.tree.map(jnp.asarray, mu), *rows)
    out = _fp_register_jit(y, block, weights, origin, opts)
    return jax.tree.map(lambda x: np.asarray(x)[: z - a], out)


class MeanOnCluster:
    """The two per-sample stages of `karcher_mean`'s fixed point, run on a Dask client.

    `full_registration` and `solve_fixed_point` have the signatures of `_mean`'s local
    `_full_registration` and `_solve_fixed_point`. Samples are scattered once; each call sends
    the mean (and, per step, each block's carried registrations) and gathers the results.
    """

    def __init__(self, client, samples, *, block_size: int):
        self.distributed = check_client(client, "karcher_mean")
        self.client = client
        self.block_size = _positive_int(block_size, "block_size")
        self.n = int(samples.q0.shape[0])
        self.size = min(self.block_size, self.n)
        self.spans = [(a, min(a + self.block_size, self.n)) for a in range(0, self.n, self.block_size)]
        self.samples = samples
        self._fut = None
        self.x64 = _x64()

    def _samples_future(self):
        if self._fut is None:
            [self._fut] = self.client.scatter([_to_numpy(self.samples)], broadcast=True, hash=False)
        return self._fut

    def _map(self, fn, per_block, *args):
        """Submit fn(samples, a, z, size, *per_block(a, z), *args) per block; gather in order."""
        fut = self._samples_future()
        futures = [
            self.client.submit(fn, fut, a, z, self.size, *per_block(a, z), *args, pure=False)
            for a, z in self.spans
        ]
        try:
            parts = self.client.gather(futures)
        finally:
            _cancel(self.client, futures)
        return jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs)), *parts)

    def full_registration(self, mu, samples, weights, origin, opts):
        payload = _pack((weights, origin, opts))
        return self._map(_mean_full_block, lambda a, z: (), _to_numpy(mu), payload, self.x64)

    def solve_fixed_point(self, y, samples, weights, origin, opts, wrapped, max_steps, throw):
        """`optx.fixed_point` with `_MonitoredFixedPoint(FixedPointIteration(0, 0))`, as a host
        loop: stop when F changes by at most ``atol + rtol|F|`` between two steps."""
        import optimistix as optx

        from ._mean import _fp_update

        payload = _pack((weights, origin, opts))
        rtol, atol = float(wrapped.rtol), float(wrapped.atol)
        trace = []
        result = optx.RESULTS.nonlinear_max_steps_reached
        for _ in range(max_steps):
            rows = _to_numpy((y.rotations, y.warped_q0, y.warped_q, y.reg_s, y.reg_real))
            registered, energies = self._map(
                _mean_step_block,
                lambda a, z: (jax.tree.map(lambda x: x[a:z], rows),),
                _to_numpy(y.mu), payload, self.x64,
            )
            y, energy = _fp_update_jit(y, registered, energies, weights, origin)
            trace.append(float(energy))
            if len(trace) >= 2 and abs(trace[-2] - trace[-1]) <= atol + rtol * abs(trace[-1]):
                result = optx.RESULTS.successful
                break
        if throw and result != optx.RESULTS.successful:
            raise RuntimeError(
                f"karcher_mean: the fixed point did not converge in max_steps={max_steps} steps; "
                "raise max_steps or rtol, or pass throw=False."
            )
        steps = len(trace)
        return y, np.asarray(trace), steps, steps, result


@eqx.filter_jit
def _fp_update_jit(y, registered, energies, weights, origin):
    from ._mean import _fp_update

    return _fp_update(y, registered, energies, weights, origin)
