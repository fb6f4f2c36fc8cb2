"""Files written whole or not at all (`rootshape_jax._atomic`)."""

import os
import stat

import pytest

from rootshape_jax import _atomic
from rootshape_jax._atomic import atomic_write


def test_atomic_write_replaces_whole_or_keeps_the_old_file(tmp_path):
    path = tmp_path / "table.csv"
    path.write_text("old")

    def fails(p):
        p.write_text("half of the new")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write(path, fails)
    assert path.read_text() == "old"  # unchanged
    assert sorted(os.listdir(tmp_path)) == ["table.csv"] and not _atomic.PENDING  # no temporary left
    atomic_write(path, lambda p: p.write_text("new"), durable=True)
    assert path.read_text() == "new"
    # The mode a plainly created file gets (mkstemp's own is 0o600), and no umask change.
    plain = tmp_path / "plain"
    plain.write_text("x")
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(plain.stat().st_mode)
    mask = os.umask(0o022)
    os.umask(mask)
    atomic_write(tmp_path / "again", lambda p: p.write_text("y"))
    now = os.umask(0o022)
    os.umask(now)
    assert now == mask


def test_a_symlink_at_the_target_is_replaced_not_written_through(tmp_path):
    target = tmp_path / "elsewhere.txt"
    target.write_text("keep me")
    link = tmp_path / "out.txt"
    link.symlink_to(target)
    atomic_write(link, lambda p: p.write_text("result"))
    assert target.read_text() == "keep me" and not link.is_symlink() and link.read_text() == "result"


def test_files_written_together_land_all_or_none(tmp_path):
    """`atomic_write_all`: a failure in the second file leaves neither (an extracted image's
    RSML without its overlay was the old behaviour); `recording_writes` lists what landed."""
    from rootshape_jax._atomic import atomic_write_all, recording_writes

    a, b = tmp_path / "p.rsml", tmp_path / "p_overlay.png"

    def fails(p):
        p.write_bytes(b"\x89PNG half")
        raise KeyboardInterrupt

    with recording_writes() as written, pytest.raises(KeyboardInterrupt):
        atomic_write_all([(a, lambda p: p.write_text("rsml")), (b, fails)])
    assert os.listdir(tmp_path) == [] and not _atomic.PENDING and written == []
    with recording_writes() as written:
        atomic_write_all([(a, lambda p: p.write_text("rsml")), (b, lambda p: p.write_bytes(b"png"))])
        atomic_write(tmp_path / "summary.json", lambda p: p.write_text("[]"))
    assert a.read_text() == "rsml" and b.read_bytes() == b"png"
    assert written == [a, b, tmp_path / "summary.json"]


def test_an_interrupt_during_the_renames_runs_after_the_last(tmp_path, monkeypatch):
    """The command line's Ctrl-C handler ends the process at once; between two renames of a
    group it is deferred (`defer_interrupt`) to the group's end, so both files are there."""
    from rootshape_jax._atomic import atomic_write_all, defer_interrupt

    seen = []
    replace = os.replace

    def replace_then_interrupt(src, dst):
        replace(src, dst)
        if not seen:  # what `_on_sigint` does when Ctrl-C arrives after the first rename
            assert defer_interrupt(lambda: seen.append(sorted(os.listdir(tmp_path))))
            seen.append("deferred")

    monkeypatch.setattr(_atomic.os, "replace", replace_then_interrupt)
    atomic_write_all([(tmp_path / "a", lambda p: p.write_text("a")), (tmp_path / "b", lambda p: p.write_text("b"))])
    assert seen == ["deferred", ["a", "b"]]  # the handler ran once, after both renames
    assert not defer_interrupt(lambda: None)  # outside a group: not deferred
