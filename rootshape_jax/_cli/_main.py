"""Entry point of ``rootshape``: JAX configuration, running a subcommand, errors as one line.

This is the only module of the package allowed to change JAX's global configuration
(docs/design.md §8, §10): it turns on float64 on request, and sets the number of XLA CPU devices
only when asked (``--devices N``). By default every core is used as from Python: one device, and
the work's blocks on one worker thread per core (`LocalExecutor`), which was 1.5 times faster
than one device per core on the pea matrix (a call split over devices waits for its slowest
share).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import sys
import warnings
from collections.abc import Sequence

from rootshape_jax._atomic import defer_interrupt, remove_pending, run_last_words

from ._common import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    PROG,
    CLIError,
    heartbeat,
    log_friendly_stderr,
    make_weights,
)
from ._parser import build_parser
from ._report import OPENED, remove_empty_outputs, unfinished_note


def configure_jax(*, devices: int | None, float64: bool, program: bool = False) -> None:
    """`devices` XLA CPU devices when given (None: JAX's default, one; blocks then run on worker
    threads, one per usable core) and optional float64; run as the program, compiled programs
    are kept on disk between runs (`keep_compiled_programs`).

    The device count can only be set before JAX has started; when it has already started
    (e.g. `main` called from a running Python session) the current devices are kept.
    """
    import jax

    from rootshape_jax._devices import relax_collective_timeouts

    relax_collective_timeouts()  # no false "may be stuck" lines (or aborts) from busy devices
    if devices is not None:
        with contextlib.suppress(RuntimeError):
            jax.config.update("jax_num_cpu_devices", int(devices))
    if float64:
        jax.config.update("jax_enable_x64", True)
    if program:
        keep_compiled_programs()


#: Disk space for compiled programs kept between runs (least recently used go first).
CACHE_BYTES = 2 * 1024**3


def keep_compiled_programs() -> str | None:
    """Turn on JAX's persistent compilation cache in ``$XDG_CACHE_HOME/rootshape_jax/xla``
    (``~/.cache/...``): the registration engine compiles for 5-25 s per shape of input, and
    its programs (no host callbacks) are then read back in later runs. Not when the user chose
    a cache (``JAX_COMPILATION_CACHE_DIR``) or none (``ROOTSHAPE_COMPILATION_CACHE=0``, or
    false/no/off), or the folder cannot be written. Returns the folder used, or None."""
    import jax

    opt_out = os.environ.get("ROOTSHAPE_COMPILATION_CACHE", "").strip().lower() in ("0", "false", "no", "off")
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or opt_out:
        return None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = os.path.join(base, "rootshape_jax", "xla")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return None
    if not os.access(folder, os.W_OK):
        return None
    jax.config.update("jax_compilation_cache_dir", folder)
    if importlib.util.find_spec("filelock") is not None:  # JAX needs it to enforce the size
        jax.config.update("jax_compilation_cache_max_size", CACHE_BYTES)
    return folder


def one_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0]


@contextlib.contextmanager
def _plain_warnings():
    """Library warnings (e.g. skipped parts of an RSML file) as one line each, no source."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{PROG}: warning: {one_line(message) if isinstance(message, Warning) else message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        old = warnings.showwarning
        warnings.showwarning = show
        try:
            yield
        finally:
            warnings.showwarning = old


def _end_process(code: int) -> None:
    """End the process now, skipping the interpreter's shutdown.

    After Ctrl-C, XLA may still be compiling on its own threads (KeyboardInterrupt comes out of
    `backend.compile_and_load` while they run) or running host callbacks; Python's shutdown
    then tears down objects those threads still use, which killed the process with SIGSEGV
    (measured: 5 of 5 interrupts during compilation). Every file is complete or absent (atomic
    writes), so skipping the shutdown loses nothing.
    """
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _on_sigint(signum, frame) -> None:
    """Ctrl-C when run as the program: remove half-written temporary files and end at once.

    Raising KeyboardInterrupt is not enough: it can surface inside a garbage-collection
    callback of JAX, where Python prints "Exception ignored" and the run goes on (measured).
    Within a group of files written together (`atomic_write_all`) it runs at the group's end.
    """
    if defer_interrupt(lambda: _on_sigint(signum, frame)):
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not interrupt the exit
    remove_pending()
    run_last_words()  # e.g. extract's summary.json brought up to the images finished
    print(file=sys.stderr)  # end the line of the progress bar
    _say_interrupted()
    _end_process(EXIT_INTERRUPTED)


def _say_interrupted() -> None:
    print(f"{PROG}: interrupted; every file written so far is complete.", file=sys.stderr)
    _print_unfinished()
    remove_empty_outputs()


def _print_unfinished() -> None:
    """Say which complete files a run that stopped early left in --out (and how to rerun)."""
    note = unfinished_note()
    if note:
        print(f"{PROG}: {note}.", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with `argv` (default ``sys.argv[1:]``); returns the exit code.

    Run as the program (`argv` None: the ``rootshape`` script, ``python -m rootshape_jax``),
    Ctrl-C ends the process at once with exit code 130 (`_on_sigint`); called with an `argv`
    list (from Python) a KeyboardInterrupt returns 130 instead.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (already printed)
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    configure_jax(devices=getattr(args, "devices", None), float64=getattr(args, "float64", False), program=argv is None)
    OPENED.clear()
    if argv is None:  # the program: Ctrl-C ends the process (`_on_sigint`)
        with contextlib.suppress(ValueError):  # not the main thread: keep KeyboardInterrupt
            signal.signal(signal.SIGINT, _on_sigint)
    with log_friendly_stderr():
        return _run(args, argv)


def _run(args, argv) -> int:
    try:
        with _plain_warnings(), heartbeat():
            if getattr(args, "level_weights", ()):
                make_weights(args)  # refuse options that do not fit together before reading any file
            args.func(args)
    except KeyboardInterrupt:
        _say_interrupted()
        if argv is None:
            _end_process(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - every failure becomes one line (and what it left in --out) unless --debug
        if getattr(args, "debug", False):
            raise
        import rootshape_jax as rs

        known = (CLIError, rs.RootShapeError, ValueError, TypeError, OSError)
        if isinstance(e, known):
            print(f"{PROG}: error: {one_line(e)}", file=sys.stderr)
        else:
            print(
                f"{PROG}: error: {type(e).__name__}: {one_line(e)} (this looks like a bug; "
                "run again with --debug and report the traceback)",
                file=sys.stderr,
            )
        _print_unfinished()
        remove_empty_outputs()
        return EXIT_ERROR
    return EXIT_OK
