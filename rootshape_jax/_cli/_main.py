"""Entry point of ``rootshape``: JAX configuration, running a subcommand, errors as one line.

This is the only module of the package allowed to change JAX's global configuration
(DESIGN.md §8, §10): it asks for one XLA CPU device per core before JAX starts and turns on
float64 on request.
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Sequence

from ._common import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, PROG, CLIError
from ._parser import build_parser


def configure_jax(*, devices: int | None, float64: bool) -> None:
    """One XLA CPU device per core (so batches run on every core) and optional float64.

    The device count can only be set before JAX has started; when it has already started
    (e.g. `main` called from a running Python session) the current devices are kept.
    """
    import jax

    n = (os.cpu_count() or 1) if devices is None else devices
    with contextlib.suppress(RuntimeError):
        jax.config.update("jax_num_cpu_devices", int(n))
    if float64:
        jax.config.update("jax_enable_x64", True)


def one_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0]


@contextlib.contextmanager
def _plain_warnings():
    """Library warnings (e.g. skipped parts of an RSML file) as one line each, no source."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{PROG}: warning: {one_line(message) if isinstance(message, Warning) else message}",
              file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        old = warnings.showwarning
        warnings.showwarning = show
        try:
            yield
        finally:
            warnings.showwarning = old


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with `argv` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (already printed)
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    configure_jax(devices=args.devices, float64=args.float64)
    try:
        with _plain_warnings():
            args.func(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted.", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 - every failure becomes one line unless --debug
        if args.debug:
            raise
        import rootshape_jax as rs

        known = (CLIError, rs.RootShapeError, ValueError, TypeError, OSError)
        if isinstance(e, known):
            print(f"{PROG}: error: {one_line(e)}", file=sys.stderr)
        else:
            print(f"{PROG}: error: {type(e).__name__}: {one_line(e)} (this looks like a bug; "
                  "run again with --debug and report the traceback)", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK
