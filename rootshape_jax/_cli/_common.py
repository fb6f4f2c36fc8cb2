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
    log file is one endless line of carriage returns; nested bars also move the cursor with
    newlines and escape codes. Here each bar (told apart by its description, the text before
    its first ":") writes its first state at once (the step has started), then a state at most
    every `interval` seconds; its latest state is written before any other text (on stderr, or
    on stdout through `BarsFirst`) and at the end, so a finished bar's last line is there, in
    order. A bar whose count or elapsed time goes back is a new bar of the same description
    (the demo has two "distances"): its first state is written at once too, unless bars of
    that description clear themselves when done (a nested bar per step of an outer one). Other text is written line
    by line as is.
    """

    def __init__(self, stream, interval: float = 30.0):
        self._stream = stream
        self._interval = interval
        self._text = ""  # other text waiting for its newline
        self._bar = ""  # the bar state being received (after a "\\r")
        self._in_bar = False
        self._pending: dict[str, str] = {}  # bar description -> latest state not written
        self._written: dict[str, float] = {}  # bar description -> when its last line was written
        self._progress: dict[str, tuple] = {}  # bar description -> (count, elapsed) it last showed
        self._transient: set[str] = set()  # descriptions of bars that cleared themselves
        self._last_desc = ""  # the bar drawn last
        # Re-entrant: the Ctrl-C handler writes to stderr from the main thread, which may be
        # inside `write` already.
        self._lock = threading.RLock()

    def write(self, text: str) -> int:
        with self._lock:
            clean = _ANSI.sub("", text)
            if not clean:
                return len(text)  # only cursor movements (nested bars)
            if self._in_bar and clean[:1] not in ("\r", "\n"):
                self._end_bar()  # a bar writes "\\r" + its state in one call: this is other text
            for piece in re.split(r"([\r\n])", clean):
                if piece == "\r":
                    self._end_bar()
                    if self._text.strip():
                        self._line(self._text)  # text without its newline yet: its own line
                    self._text, self._in_bar = "", True
                elif piece == "\n":
                    if self._in_bar:
                        self._end_bar()  # a bar's newline ends it or moves the cursor: no line
                    else:
                        self._line(self._text)
                        self._text = ""
                elif self._in_bar:
                    self._bar += piece
                else:
                    self._text += piece
            self._end_bar(keep=True)
        return len(text)

    def _end_bar(self, keep: bool = False) -> None:
        """Take the bar state received so far (`keep`: the bar may still write more of it)."""
        raw = self._bar
        state = raw.rstrip()  # a bar pads over its longer previous state with spaces
        if not keep:
            self._bar, self._in_bar = "", False
        if not state:
            if raw:  # only spaces: a bar cleared (closed with leave=False), gone from the screen
                self._pending.pop(self._last_desc, None)
                # Such bars (a nested bar per step) stay throttled when they come back.
                self._transient.add(self._last_desc)
                self._bar = ""
            return
        desc = self._last_desc = state.split(":", 1)[0]
        now = time.monotonic()
        progress = _progress(state)
        if _went_back(progress, self._progress.get(desc)) and desc not in self._transient:
            self._written.pop(desc, None)  # a new bar of this description
        self._progress[desc] = progress
        if desc not in self._written:
            self._flush_pending()  # a new bar: the others' latest states first
            self._write(state)
            self._written[desc] = now
            self._pending.pop(desc, None)
        elif now - self._written[desc] >= self._interval:
            self._write(state)
            self._written[desc] = now
            self._pending.pop(desc, None)
        else:
            self._pending[desc] = state
        if keep:
            self._bar = ""  # taken: what follows in the next write is a new state

    def _flush_pending(self) -> None:
        for desc, state in list(self._pending.items()):
            self._write(state)
            self._written[desc] = time.monotonic()
        self._pending.clear()

    def _line(self, text: str) -> None:
        self._flush_pending()
        self._write(text)

    def _write(self, line: str) -> None:
        self._stream.write(line + "\n")

    def flush(self) -> None:
        with self._lock:
            self._stream.flush()

    def flush_bars(self) -> None:
        """Write the bars' latest states now (before a line on stdout, which may share the log)."""
        with self._lock:
            if self._pending:
                self._flush_pending()
                self._stream.flush()

    def close_line(self) -> None:
        """Write out what is pending: bars' latest states, then text without its newline."""
        with self._lock:
            self._end_bar()
            self._flush_pending()
            if self._text.strip():
                self._write(self._text)
            self._text = ""
            self._stream.flush()

    def isatty(self) -> bool:
        return False

    def __getattr__(self, name):  # encoding, fileno, ... of the real stream
        return getattr(self._stream, name)


# A bar's count: "| 3/10 [" or "| 1.50k/10.0k [" (a total), ": 3step [" (none); its elapsed
# time: "[01:02" or "[1:02:03", or ": 00:12" (`ticking`'s format).
_COUNT = re.compile(r"(?:\|\s*|:\s+)(\d+(?:\.\d+)?)([kMGTPEZY]?)(?:/|[^\d\s|/:]*\s*\[)")
_ELAPSED = re.compile(r"(?:\[|: )(?:(\d+):)?(\d+):(\d\d)\b")
_SI = {"": 1.0, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12, "P": 1e15, "E": 1e18, "Z": 1e21, "Y": 1e24}


def _progress(state: str) -> tuple[float | None, float | None]:
    """(count, elapsed seconds) a bar's state shows; None for what it does not show (a bar cut
    short by a narrow terminal, or a format of its own)."""
    c = _COUNT.search(state)
    e = _ELAPSED.search(state)
    elapsed = None
    if e is not None:
        h, mi, se = e.groups()
        elapsed = 3600.0 * int(h or 0) + 60.0 * int(mi) + int(se)
    return (float(c.group(1)) * _SI[c.group(2)] if c else None, elapsed)


def _went_back(now: tuple, before: tuple | None) -> bool:
    """True when a bar's count or elapsed time is below what it showed before: a new bar."""
    if before is None:
        return False
    return any(x is not None and y is not None and x < y for x, y in zip(now, before))


class BarsFirst:
    """stdout while stderr is a `LogStream`: the bars' pending states are written before each
    stdout write, so a log of both streams (``> log 2>&1``) keeps a finished step's last bar
    line before the lines that report its results."""

    def __init__(self, stream, bars: LogStream):
        self._stream, self._bars = stream, bars

    def write(self, text: str) -> int:
        self._bars.flush_bars()
        return self._stream.write(text)

    def __getattr__(self, name):  # flush, encoding, isatty, ... of the real stream
        return getattr(self._stream, name)


@contextlib.contextmanager
def log_friendly_stderr():
    """`LogStream` on stderr while a command runs, unless stderr is a terminal."""
    real, real_out = sys.stderr, sys.stdout
    if real is None or real.isatty():
        yield
        return
    sys.stderr = stream = LogStream(real)
    if real_out is not None:
        sys.stdout = BarsFirst(real_out, stream)
    try:
        yield
    finally:
        stream.close_line()
        sys.stderr, sys.stdout = real, real_out


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
    depth = getattr(args, "depth", None) or 2
    if not deeper and depth >= (4 if getattr(args, "per", "root") == "plant" else 3):
        # A weights.csv from learn-weights at --depth 3 carries the deeper orders' weights; at a
        # depth that keeps no second-order laterals they have nothing to weigh.
        deeper = getattr(args.weights, "deeper", ())
    if deeper and getattr(args, "per", "root") == "plant" and depth < 4:
        # A plant's system puts its axes at level 1: their laterals (level 2) take --weights'
        # L,P, and the axes' second-order laterals, the first weighed by --level-weights, are level 3.
        raise CLIError(
            "--level-weights weighs second-order laterals and below; with --per plant these are "
            "level 3 of a plant's system (its axes are level 1, their laterals level 2, weighed by "
            "--weights), which the analysis keeps only with --depth 4; add --depth 4, or leave "
            "--level-weights out"
            + (f" (got --depth {depth})." if getattr(args, "depth", None) else " (the default depth is 2).")
        )
    if deeper and depth < 3:
        raise CLIError(
            "--level-weights weighs second-order laterals and below, which the analysis keeps "
            "only with --depth 3 or 4; add --depth 3, or leave --level-weights out."
        )
    # One value per term, in the order of rs.TERMS; then (λs, λp) per order from the second.
    return rs.Weights(*args.weights, deeper=deeper)


def version() -> str:
    import rootshape_jax as rs

    return rs.__version__
