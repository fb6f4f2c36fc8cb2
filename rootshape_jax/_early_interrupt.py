"""Ctrl-C before the command line's own handler is in place (standard library only).

Run as the ``rootshape`` program, the package imports JAX before `_cli.main` can install its
handler (`_cli._main._on_sigint`). Python's default KeyboardInterrupt then surfaced inside
JAX's import (a traceback) or inside one of JAX's garbage-collection callbacks, where Python
prints "Exception ignored" and the run went on to write its results (measured by an audit of
interrupts in the first 2 s). Nothing is written before `main` runs, so ending at once is
clean.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

#: The exit code of a run stopped by Ctrl-C (as `_cli._common.EXIT_INTERRUPTED`).
EXIT_INTERRUPTED = 130


def _end(signum, frame) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not interrupt the exit
    with contextlib.suppress(Exception):
        sys.stderr.write("\nrootshape: interrupted while starting; nothing was written.\n")
        sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def is_the_program() -> bool:
    """True while the process is the ``rootshape`` program: its script, or ``python -m
    rootshape_jax`` (``sys.argv[0]`` is "-m" while Python imports the package to run it; the
    module named after ``-m`` must be this package, not another one that imports it)."""
    argv0 = sys.argv[0] if sys.argv else ""
    if os.path.basename(argv0).removesuffix(".exe") == "rootshape":
        return True
    return argv0 == "-m" and _module_after_m(getattr(sys, "orig_argv", [])) in (
        "rootshape_jax",
        "rootshape_jax.__main__",
    )


def _module_after_m(argv: list[str]) -> str | None:
    """The module of ``python -m MODULE`` (also written ``-mMODULE``) in the interpreter's own
    command line, or None."""
    i = 1
    while i < len(argv):
        arg = argv[i]
        if arg == "-m":
            return argv[i + 1] if i + 1 < len(argv) else None
        if arg.startswith("-m"):
            return arg[2:]
        if not arg.startswith("-") or arg.startswith("-c"):  # a script or -c: no -m
            return None
        i += 2 if arg in ("-W", "-X", "--check-hash-based-pycs") else 1  # options with a value
    return None


def end_on_ctrl_c() -> None:
    """Make Ctrl-C end the process at once (exit 130) until the command line replaces this."""
    with contextlib.suppress(ValueError):  # not the main thread
        signal.signal(signal.SIGINT, _end)
