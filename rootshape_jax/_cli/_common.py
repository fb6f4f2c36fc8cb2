"""Names shared by the command-line modules."""

from __future__ import annotations

import contextlib
import re
import sys
import threading
import time

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


# Cursor movements tqdm uses to stack nested bars on a terminal.
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class LogStream:
    """stderr redirected to a file or pipe: progress bars as whole lines, no cursor codes.

    A bar redraws itself in place ("\\r" + its new state) many times a second, which in a
    log file is one endless line of carriage returns. Here a bar's first state is written at
    once (the step has started), then each redraw replaces the pending line, which is written
    out when the bar ends ("\\n"), when other text follows, or when `interval` seconds have
    passed since the last line (so a long step still shows progress).
    """

    def __init__(self, stream, interval: float = 30.0):
        self._stream = stream
        self._interval = interval
        self._line = ""
        self._bar = False  # the pending line is a bar's state
        self._first = False  # the running bar's first state is still to be written
        self._last = -float("inf")
        self._lock = threading.Lock()

    def write(self, text: str) -> int:
        with self._lock:
            clean = _ANSI.sub("", text)
            if not clean:
                return len(text)
            if self._bar and clean[:1] not in ("\r", "\n"):
                self._emit()  # other text after a bar: the bar's state stays on its own line
            for piece in re.split(r"([\r\n])", clean):
                if piece == "\n":
                    self._emit(blank_ok=not self._bar)
                elif piece == "\r":
                    if not self._bar:
                        self._first = True  # a bar starts (or starts again after other text)
                    elif time.monotonic() - self._last >= self._interval:
                        self._emit(bar=True)
                    self._line, self._bar = "", True
                else:
                    self._line += piece
            if self._bar and self._first and self._line.strip():
                self._emit(bar=True)
                self._first = False
        return len(text)

    def _emit(self, blank_ok: bool = False, bar: bool = False) -> None:
        line = self._line.rstrip()  # a bar pads over its longer previous state with spaces
        if line or blank_ok:
            self._stream.write(line + "\n")
            self._last = time.monotonic()
        self._line, self._bar = "", bar

    def flush(self) -> None:
        with self._lock:
            self._stream.flush()

    def close_line(self) -> None:
        """Write out what is pending (the last state of a bar still running)."""
        with self._lock:
            self._emit()
            self._stream.flush()

    def isatty(self) -> bool:
        return False

    def __getattr__(self, name):  # encoding, fileno, ... of the real stream
        return getattr(self._stream, name)


@contextlib.contextmanager
def log_friendly_stderr():
    """`LogStream` on stderr while a command runs, unless stderr is a terminal."""
    real = sys.stderr
    if real is None or real.isatty():
        yield
        return
    sys.stderr = stream = LogStream(real)
    try:
        yield
    finally:
        stream.close_line()
        sys.stderr = real


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
