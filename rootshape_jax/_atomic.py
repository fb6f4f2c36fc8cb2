"""Files written whole or not at all: a temporary file beside the target, then a rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

# Temporary files being written; a Ctrl-C handler that ends the process at once removes them
# (`remove_pending`), so nothing half-written stays behind.
PENDING: set[str] = set()


_MODE: list[int] = []  # the file mode, found once

# Lists that `recording_writes` blocks fill with the files written meanwhile.
_RECORDERS: list[list[Path]] = []


@contextlib.contextmanager
def recording_writes():
    """Yield a list that collects the path of each file written (whole) within the block: what
    a command that stops early has left."""
    written: list[Path] = []
    _RECORDERS.append(written)
    try:
        yield written
    finally:
        _RECORDERS.remove(written)


def _record(path: Path) -> None:
    for written in _RECORDERS:
        written.append(path)


def _plain_mode() -> int:
    """The mode a plainly created file gets (0o666 less the umask). mkstemp makes 0o600 files;
    the result should look like any other file the user writes. Found once: reading the umask
    means setting it, which must not happen while other threads create files."""
    if not _MODE:
        mask = os.umask(0o022)
        os.umask(mask)
        _MODE.append(0o666 & ~mask)
    return _MODE[0]


def atomic_write(path: str | os.PathLike, write_to: Callable[[Path], object], *, durable: bool = False) -> Path:
    """Write `path` by ``write_to(temporary_path)`` in the same folder, then `os.replace`:
    an interrupted or failed write leaves the earlier file (or none) intact, and a symlink at
    `path` is replaced, never written through. `durable` also flushes the file to disk before
    the rename (a store that must survive a crash). `OSError` from the write propagates."""
    return atomic_write_all([(path, write_to)], durable=durable)[0]


def remove_pending() -> None:
    """Remove every temporary file still being written (for a Ctrl-C handler)."""
    for tmp in list(PENDING):
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def atomic_write_all(
    writes: Sequence[tuple[str | os.PathLike, Callable[[Path], object]]],
    *,
    durable: bool = False,
    then: Callable[[], object] | None = None,
) -> list[Path]:
    """Write several files as one result: each ``write_to(temporary_path)`` first, then every
    rename together, with Ctrl-C held back (`interrupts_held`) until the last. A failed or
    interrupted write leaves none of them (e.g. an image's RSML and its overlay). The renames
    are held together against the command line's Ctrl-C handler (`defer_interrupt`); a
    KeyboardInterrupt in library use, or a rename that fails (the target is a folder), can
    still land the first files without the others. Main thread only (signal handlers).
    `durable`: as in `atomic_write`. `then`: called right after the renames, still held (e.g.
    to record the files as done, so that a Ctrl-C handler's `last_words` count them)."""
    done: list[tuple[str, Path]] = []
    try:
        for path, write_to in writes:
            path = Path(path)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            os.close(fd)
            PENDING.add(tmp)
            done.append((tmp, path))
            write_to(Path(tmp))
            if durable:
                with open(tmp, "rb+") as f:
                    os.fsync(f.fileno())
            os.chmod(tmp, _plain_mode())  # after writing: a mode without write permission is allowed
        # One file needs no holding (and `atomic_write` also runs on worker threads).
        with interrupts_held() if len(done) > 1 else contextlib.nullcontext():
            for tmp, path in done:
                os.replace(tmp, path)
                _record(path)
            if then is not None:
                then()
    finally:
        for tmp, _ in done:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            PENDING.discard(tmp)
    return [path for _, path in done]


# Ctrl-C held back: a handler that ends the process at once (the command line's) asks
# `defer_interrupt` first, and while a group of renames runs it is called at their end instead.
_HOLDING: list[int] = [0]
_DEFERRED: list[Callable[[], object]] = []


@contextlib.contextmanager
def interrupts_held():
    """Within this block, a Ctrl-C handler that calls `defer_interrupt` runs at its end."""
    _HOLDING[0] += 1
    try:
        yield
    finally:
        _HOLDING[0] -= 1
        if not _HOLDING[0] and _DEFERRED:
            handler = _DEFERRED[0]
            _DEFERRED.clear()
            handler()


def defer_interrupt(handler: Callable[[], object]) -> bool:
    """True (and `handler` kept for the end of `interrupts_held`) while interrupts are held."""
    if _HOLDING[0]:
        _DEFERRED.append(handler)
        return True
    return False


# Quick, atomic writes of what is finished so far (a run's summary), made on the way out of an
# interruption: by a KeyboardInterrupt leaving a `last_words` block, or by a Ctrl-C handler
# that ends the process at once (`run_last_words`).
_LAST_WORDS: list[Callable[[], object]] = []


@contextlib.contextmanager
def last_words(callback: Callable[[], object]):
    """Within this block, an interruption runs `callback` before the run ends."""
    _LAST_WORDS.append(callback)
    try:
        yield
    except KeyboardInterrupt:
        _LAST_WORDS.remove(callback)
        callback()
        raise
    finally:
        if callback in _LAST_WORDS:
            _LAST_WORDS.remove(callback)


def run_last_words() -> None:
    """Run every `last_words` callback (for a Ctrl-C handler that ends the process); a failing
    one is skipped: the run is ending anyway, and the earlier file stays (atomic writes)."""
    callbacks = list(reversed(_LAST_WORDS))
    _LAST_WORDS.clear()
    for callback in callbacks:
        with contextlib.suppress(Exception):
            callback()
