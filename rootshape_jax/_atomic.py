"""Files written whole or not at all: a temporary file beside the target, then a rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

# Temporary files being written; a Ctrl-C handler that ends the process at once removes them
# (`remove_pending`), so nothing half-written stays behind.
PENDING: set[str] = set()


_MODE: list[int] = []  # the file mode, found once


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
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    PENDING.add(tmp)
    try:
        write_to(Path(tmp))
        if durable:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.chmod(tmp, _plain_mode())  # after writing: a mode without write permission is allowed
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        PENDING.discard(tmp)
    return path


def remove_pending() -> None:
    """Remove every temporary file still being written (for a Ctrl-C handler)."""
    for tmp in list(PENDING):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
