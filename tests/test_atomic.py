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
