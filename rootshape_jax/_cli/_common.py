"""Names shared by the command-line modules."""

from __future__ import annotations

import contextlib
import sys
import threading

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


# Progress bars are redrawn at least this often (seconds), even while one block or one
# compilation runs for longer (issue 17: a bar sat at 0 % for 85 s while the first block compiled).
HEARTBEAT = 5.0


@contextlib.contextmanager
def heartbeat(interval: float = HEARTBEAT):
    """Redraw every live progress bar every `interval` seconds (their elapsed time moves),
    from a background thread, while the block runs."""
    from tqdm import tqdm as std_tqdm

    stop = threading.Event()

    def beat():
        while not stop.wait(interval):
            # tqdm keeps its live bars in a class-level set; copy it under tqdm's own lock.
            with std_tqdm.get_lock():
                bars = list(getattr(std_tqdm, "_instances", ()))
            for bar in bars:
                with contextlib.suppress(Exception):  # a bar closing meanwhile
                    if not bar.disable:
                        bar.refresh()

    thread = threading.Thread(target=beat, name="rootshape-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@contextlib.contextmanager
def ticking(args, desc: str):
    """A progress line for a step without a bar of its own: its elapsed time, redrawn by
    `heartbeat` (silenced by --quiet)."""
    from tqdm.auto import tqdm

    with tqdm(desc=desc, total=None, bar_format="{desc}: {elapsed}", disable=getattr(args, "quiet", False)) as bar:
        yield bar


def fmt(x: float, digits: int = 4) -> str:
    return f"{float(x):.{digits}g}"


def make_weights(args):
    import rootshape_jax as rs

    deeper = getattr(args, "level_weights", ())  # commands without the option: none
    if deeper and (getattr(args, "depth", None) or 2) < 3:
        raise CLIError(
            "--level-weights weighs second-order laterals and below, which the analysis keeps "
            "only with --depth 3 or 4; add --depth 3, or leave --level-weights out."
        )
    # One value per term, in the order of rs.TERMS; then (λs, λp) per order from the second.
    return rs.Weights(*args.weights, deeper=deeper)


def version() -> str:
    import rootshape_jax as rs

    return rs.__version__
