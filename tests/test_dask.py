"""Distance matrices and Karcher means on a real Dask LocalCluster (2 worker processes, loopback).

The cluster's workers are fresh processes: x64 is not on there, so these tests also check that
float64 inputs are computed in float64 on the workers (bitwise equality would fail otherwise).
"""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import random_root

import rootshape_jax as rs
from rootshape_jax import StoreMismatchError

# ~5 min on the 2-core dev machine, mostly compiling the kernels in fresh worker processes.
pytestmark = pytest.mark.slow

distributed = pytest.importorskip("distributed")
cloudpickle = pytest.importorskip("cloudpickle")
# The worker-side patches below are defined here; workers cannot import this module.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

T, K = 20, 6
W = rs.Weights(main=0.5, lateral=1.0, position=1.0)
CHUNK = 2
BLOCK = 2  # 8 roots: 28 pairs, 14 blocks


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    )
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def trees():
    rng = np.random.default_rng(0)
    roots = [random_root(rng, n_laterals=n) for n in (0, 1, 2, 3, 2, 3, 1, 2)]
    return rs.batch(roots, n_points=T, max_laterals=K, normalise_scale=True)


@pytest.fixture(scope="module")
def local(trees):
    D, stats = rs.pairwise_distances(trees, weights=W, chunk_size=CHUNK, progress=False, return_stats=True)
    return np.asarray(D), stats


def _run(trees, client, **kw):
    D, stats = rs.pairwise_distances(
        trees, weights=W, chunk_size=CHUNK, progress=False, return_stats=True, client=client, **kw
    )
    return np.asarray(D), stats


def _mtimes(store):
    return {n: os.stat(store / n).st_mtime_ns for n in os.listdir(store) if n.startswith("block_")}


# Worker-side patch of the pair loop the tasks call. A worker's first `after` tasks run
# normally; at the next one it waits until `after` blocks are on disk (its own, at least), then
# either kills its process in the middle of the task (once: a marker file records it, with the
# blocks on disk at that moment) or fails this and every later task (an interrupted run).
def _install_crash(store, marker, after, mode):
    import time

    from rootshape_jax import _pairwise

    original = getattr(_pairwise, "_original_run_pair_chunks", _pairwise.run_pair_chunks)
    _pairwise._original_run_pair_chunks = original
    calls = [0]

    def blocks():
        return sorted(n for n in os.listdir(store) if n.startswith("block_"))

    def run_pairs(*args, **kwargs):
        calls[0] += 1
        if calls[0] > after:
            deadline = time.monotonic() + 60
            while len(blocks()) < after and time.monotonic() < deadline:
                time.sleep(0.01)
            if mode == "fail":
                raise RuntimeError("simulated crash")
            try:
                fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                fd = None
            if fd is not None:
                stamps = {n: os.stat(os.path.join(store, n)).st_mtime_ns for n in blocks()}
                os.write(fd, json.dumps(stamps).encode())
                os.close(fd)
                os._exit(1)
        return original(*args, **kwargs)

    _pairwise.run_pair_chunks = run_pairs


def _remove_crash():
    from rootshape_jax import _pairwise

    if hasattr(_pairwise, "_original_run_pair_chunks"):
        _pairwise.run_pair_chunks = _pairwise._original_run_pair_chunks


def test_bitwise_equal_to_local_and_resume_from_store(client, trees, local, tmp_path):
    D0, stats0 = local
    store = tmp_path / "store"
    D, stats = _run(trees, client, block_size=BLOCK, store=store)
    assert D.dtype == np.float64
    assert np.array_equal(D, D0)
    assert stats["blocks"] == stats["blocks_computed"] == 14 and stats["blocks_from_store"] == 0
    assert (stats["lateral_dp"], stats["lateral_skipped"]) == (stats0["lateral_dp"], stats0["lateral_skipped"])
    assert sorted(os.listdir(store)) == sorted(["manifest.json"] + [f"block_{b:07d}.npz" for b in range(14)])
    before = _mtimes(store)
    # A finished run resumed: nothing is computed or rewritten.
    D2, stats2 = _run(trees, client, block_size=BLOCK, store=store)
    assert np.array_equal(D2, D0)
    assert stats2["blocks_computed"] == 0 and stats2["blocks_from_store"] == 14
    assert stats2["lateral_dp"] == stats0["lateral_dp"]
    assert _mtimes(store) == before
    # Without a store, and with the default block size.
    D3, _ = _run(trees, client)
    assert np.array_equal(D3, D0)


def test_cross_distances_equal_to_local(client, trees):
    A = jax.tree.map(lambda x: x[:3], trees)
    C0 = np.asarray(rs.cross_distances(A, trees, weights=W, chunk_size=CHUNK, progress=False))
    C = np.asarray(
        rs.cross_distances(A, trees, weights=W, chunk_size=CHUNK, progress=False, client=client, block_size=4)
    )
    assert C.shape == (3, 8)
    assert np.array_equal(C, C0)


def test_worker_killed_mid_run_loses_nothing(client, trees, local, tmp_path):
    store, marker = tmp_path / "store", tmp_path / "killed.json"
    store.mkdir()
    client.run(_install_crash, str(store), str(marker), 3, "kill")
    try:
        D, stats = _run(trees, client, block_size=BLOCK, store=store)
    finally:
        client.run(_remove_crash)
    assert marker.exists(), "no worker was killed: the test did not exercise anything"
    on_disk_at_kill = json.loads(marker.read_text())
    assert len(on_disk_at_kill) >= 3
    # Dask rescheduled the killed task; every block was written once and is still the same file.
    after = _mtimes(store)
    assert all(after[n] == t for n, t in on_disk_at_kill.items())
    assert len(after) == 14 and stats["blocks_computed"] == 14
    assert np.array_equal(D, local[0])
    client.wait_for_workers(2, timeout=60)


def test_interrupted_run_resumes_without_recomputing(client, trees, local, tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    client.run(_install_crash, str(store), str(tmp_path / "unused"), 2, "fail")
    try:
        with pytest.raises(RuntimeError, match="simulated crash"):
            _run(trees, client, block_size=BLOCK, store=store)
    finally:
        client.run(_remove_crash)
    finished = _mtimes(store)
    assert 2 <= len(finished) < 14
    D, stats = _run(trees, client, block_size=BLOCK, store=store)
    assert stats["blocks_from_store"] == len(finished)
    assert stats["blocks_computed"] == 14 - len(finished)
    assert stats["lateral_dp"] == local[1]["lateral_dp"]
    after = _mtimes(store)
    assert len(after) == 14 and all(after[n] == t for n, t in finished.items())
    assert np.array_equal(D, local[0])


def test_bad_inputs_fail_before_any_task(client, trees, tmp_path, monkeypatch):
    # A store written by a (real) run on other inputs.
    other_store = tmp_path / "other"
    _run(jax.tree.map(lambda x: x[:3], trees), client, block_size=BLOCK, store=other_store)

    def submitted(*args, **kwargs):
        raise AssertionError("a task or data was sent to the cluster")

    monkeypatch.setattr(client, "submit", submitted)
    monkeypatch.setattr(client, "scatter", submitted)
    other = rs.batch([random_root(np.random.default_rng(1), n_laterals=4)], n_points=T)  # K = 8
    with pytest.raises(ValueError, match="different capacities"):
        rs.cross_distances(trees, other, client=client, progress=False)
    with pytest.raises(ValueError, match="empty batch"):
        rs.pairwise_distances(jax.tree.map(lambda x: x[:0], trees), client=client, progress=False)
    with pytest.raises(ValueError, match="block_size must be an integer >= 1"):
        _run(trees, client, block_size=0)
    with pytest.raises(ValueError, match="multiple of chunk_size"):
        _run(trees, client, block_size=3)
    with pytest.raises(TypeError, match="dask.distributed.Client"):
        _run(trees, "tcp://127.0.0.1:8786")
    with pytest.raises(ValueError, match="multiple of chunk_size"):
        _run(trees, None, block_size=3)  # the local path checks the same
    with pytest.raises(StoreMismatchError, match="holds another run .different input arrays"):
        _run(trees, client, block_size=BLOCK, store=other_store)
    small = jax.tree.map(lambda x: x[:3], trees)
    with pytest.raises(StoreMismatchError, match="block_size: stored 2 vs now 4"):
        _run(small, client, block_size=4, store=other_store)
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "notes.txt").write_text("mine")
    with pytest.raises(StoreMismatchError, match="no manifest.json"):
        _run(trees, client, block_size=BLOCK, store=stray)
    # Without the extra installed, a clear MissingDependencyError names it.
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(rs.MissingDependencyError, match=r"rootshape_jax\[dask\]"):
        _run(trees, client)


def test_library_imports_without_dask():
    code = "import sys, rootshape_jax; assert not any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})


def test_karcher_mean_on_cluster_matches_local(client):
    rng = np.random.default_rng(11)
    roots = [random_root(rng, n_laterals=int(k)) for k in (3, 2, 3, 2, 3)]
    samples = rs.batch(roots, n_points=T, max_laterals=K)
    kw = dict(weights=W, max_steps=4, throw=False, registration=dict(max_iterations=2))
    m0 = rs.karcher_mean(samples, **kw)
    m = rs.karcher_mean(samples, client=client, block_size=2, **kw)
    assert int(m.steps) == int(m0.steps) and m.init_index == m0.init_index
    assert m.result == m0.result
    for a, b in zip(
        jax.tree.leaves((m.fitted, m.registered, m.energies, m.energy_trace)),
        jax.tree.leaves((m0.fitted, m0.registered, m0.energies, m0.energy_trace)),
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="fixed_point"):
        rs.karcher_mean(samples, method="gradient", client=client)
    with pytest.raises(ValueError, match="block_size"):
        rs.karcher_mean(samples, client=client, block_size=0)
