"""Atomic writes: a failed write keeps the old file, a finished one is flushed to disk before it takes its place."""
import os

import pytest

from cmlearn import io


def test_atomic_write_keeps_the_old_file_on_failure_and_syncs_the_new_one(tmp_path, monkeypatch):
    path = tmp_path / "table.md"
    io.write_text_atomic(path, "old\n")

    def broken(f):
        f.write(b"half")
        raise OSError("disk full")
    with pytest.raises(OSError, match="disk full"):
        io.atomic_write(path, broken)
    assert path.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["table.md"]
    synced, fsync = [], os.fsync
    monkeypatch.setattr(io.os, "fsync", lambda fd: synced.append(os.fstat(fd).st_size) or fsync(fd))
    io.write_text_atomic(path, "new\n")
    assert path.read_text() == "new\n"
    assert synced[0] == 4 and len(synced) == 2  # the file's four bytes, then the folder's entry


def test_check_writable_says_why_a_path_cannot_be_written_and_leaves_nothing_behind(tmp_path):
    (tmp_path / "f").write_text("x")
    assert io.check_writable(tmp_path / "new" / "deeper" / "c.pt") == tmp_path / "new" / "deeper" / "c.pt"
    assert io.check_writable(tmp_path / "new", folder=True) == tmp_path / "new"
    with pytest.raises(ValueError, match="'f' is a file, not a folder|f' is a file, not a folder"):
        io.check_writable(tmp_path / "f", folder=True)
    with pytest.raises(ValueError, match="is a folder, not a file"):
        io.check_writable(tmp_path)
    with pytest.raises(ValueError, match=r"cannot write .*/f/out/c\.pt'.*/f' is a file, not a folder"):
        io.check_writable(tmp_path / "f" / "out" / "c.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # no folder made, no probe left
