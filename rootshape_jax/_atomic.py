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


def _umask_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask  # what a plainly created file would get


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
        os.chmod(tmp, _umask_mode())
        write_to(Path(tmp))
        if durable:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
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
