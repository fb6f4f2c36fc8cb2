"""One count of cores (issue 17, item 7): the local executor's worker threads and
`use_all_cores` both use `_devices.usable_cores`; the command line runs on one XLA device with
worker threads (as from Python) unless ``--devices N`` is given."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import rootshape_jax as rs
import rootshape_jax._devices as devices
import rootshape_jax._executor as executor

REPO = str(Path(__file__).resolve().parents[1])


def _python(code: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = REPO + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout.strip()


def test_executor_counts_cores_with_the_devices_function(monkeypatch):
    assert executor.usable_cores is devices.usable_cores
    monkeypatch.setattr(executor, "usable_cores", lambda: 7)
    assert rs.LocalExecutor().n_workers() == 7  # one device in the test process
    assert rs.LocalExecutor(workers=3).n_workers() == 3


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
def test_usable_cores_follows_the_affinity_and_use_all_cores_uses_it():
    # Pinned to one core, both counts say 1 (os.cpu_count() would still say every core).
    out = _python(
        """
        import os
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        import jax, rootshape_jax as rs
        from rootshape_jax._devices import usable_cores
        print(usable_cores(), rs.use_all_cores(), jax.local_device_count(), rs.LocalExecutor().n_workers())
        """
    )
    assert out.split() == ["1", "1", "1", "1"]


@pytest.mark.parametrize(("devices_arg", "expected"), [(None, "1"), (2, "2")])
def test_cli_uses_one_device_unless_asked(devices_arg, expected):
    out = _python(
        f"""
        import jax
        from rootshape_jax._cli import configure_jax
        configure_jax(devices={devices_arg!r}, float64=False)
        import rootshape_jax as rs
        from rootshape_jax._devices import usable_cores
        print(jax.local_device_count(), rs.LocalExecutor().n_workers(), usable_cores())
        """
    )
    n_dev, workers, cores = (int(x) for x in out.split())
    assert n_dev == int(expected)
    # Threads take the cores the devices leave: every core either way.
    assert workers == max(1, cores // n_dev)
