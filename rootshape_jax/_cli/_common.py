"""Names shared by the command-line modules."""

from __future__ import annotations

import sys

PROG = "rootshape"
RSML_SUFFIXES = (".rsml",)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
PAPER_TRAITS = ("main_length", "mean_lateral_length", "std_lateral_length")
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class CLIError(Exception):
    """A problem the user can fix; its message is printed as one line."""


def say(args, message: str) -> None:
    """A progress message on stderr (silenced by --quiet)."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr, flush=True)


def warn(message: str) -> None:
    """One warning line on stderr (shown even with --quiet)."""
    print(f"{PROG}: warning: {message}", file=sys.stderr, flush=True)


def fmt(x: float, digits: int = 4) -> str:
    return f"{float(x):.{digits}g}"


def make_weights(args):
    import rootshape_jax as rs

    return rs.Weights(*args.weights)  # one value per term, in the order of rs.TERMS


def version() -> str:
    import rootshape_jax as rs

    return rs.__version__
