"""Shared pytest configuration: every correctness test runs in float64."""

import contextlib
import os
import signal
import time

import jax
import pytest

# Import hypothesis now, not at the end of the session. Its pytest plugin imports the package in
# its terminal summary; in an xdist worker that ran no hypothesis test that happened after the
# worker had reported "finished", and the import (assertion rewriting of ~100 modules) took
# 5-11 s under load. execnet gives a finished worker 5 s, then sends it SIGINT, which surfaced as
# a `KeyboardInterrupt` traceback from JAX's `_xla_gc_callback` at the end of `make test`.
# Only xdist workers need it (elsewhere pytest waits for the import at the end anyway).
if os.environ.get("PYTEST_XDIST_WORKER"):
    with contextlib.suppress(ImportError):
        import hypothesis  # noqa: F401

jax.config.update("jax_enable_x64", True)
# The CLI run as a program keeps compiled programs in ~/.cache/rootshape_jax (unless
# JAX_COMPILATION_CACHE_DIR is set, as `make test` does): not the developer's from tests.
os.environ.setdefault("ROOTSHAPE_COMPILATION_CACHE", "0")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    # Each compiled XLA:CPU program holds memory maps of its own. A test process that keeps every
    # program of every module reaches Linux's limit of 65,530 maps per process (vm.max_map_count)
    # near the end of the suite, and the next compilation dies inside LLVM (segfault or abort:
    # seen in make test, 64,812 maps in the failing worker). After a module its programs go.
    yield
    jax.clear_caches()


def pytest_sessionfinish(session):
    # An xdist worker has run all its tests and is about to report them. What is left (pytest's
    # final garbage collections, 1-3 s under load) must not be cut short by execnet's SIGINT,
    # which lands in whatever runs (JAX's gc callback). If a worker ever hangs here, execnet
    # still ends it 10 s later with os._exit.
    if hasattr(session.config, "workerinput"):
        signal.signal(signal.SIGINT, signal.SIG_IGN)


#: Slow tests CI always runs, first: the notebooks must execute in CI.
ALWAYS_IN_CI = ("test_notebooks.py",)


def _always_in_ci(item) -> bool:
    return item.path.name in ALWAYS_IN_CI


def pytest_collection_modifyitems(config, items):
    # Scheduled first (xdist hands out files in this order), so the time budget below never
    # reaches them.
    items.sort(key=lambda item: not _always_in_ci(item))


def pytest_runtest_setup(item):
    # CI's time budget for the slow tests (`.ci/run` sets RS_SLOW_TESTS_UNTIL, a Unix time): a
    # slow test that would start after it is skipped, named, so CI ends well within its limit
    # on a slow day. Fast tests and the notebooks always run; `make test-slow` without the
    # variable runs every slow test.
    until = os.environ.get("RS_SLOW_TESTS_UNTIL")
    slow = item.get_closest_marker("slow") is not None
    if until and slow and not _always_in_ci(item) and time.time() > float(until):
        pytest.skip(f"{item.nodeid}: CI time budget for the slow tests is spent; run `make test-slow`")
