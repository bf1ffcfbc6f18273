"""Run folders through the command line: resume never damages a run, a failed start leaves no
half-made folder, run folders and checkpoints that are missing or corrupt are named, a bad
split is refused before training, and the atomic-write helpers leave no temporaries."""

from __future__ import annotations

import os

import pytest


# ------------------------------------------------------------------------------ item 8: atomic writes
def test_atomic_path_fsyncs_before_the_rename(tmp_path, monkeypatch):
    from virus_nerf.utils import io as vio

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(vio.os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(vio.os, "replace", lambda a, b: (events.append("replace"), real_replace(a, b))[1])
    vio.write_text_atomic(tmp_path / "a.txt", "hello")
    assert (tmp_path / "a.txt").read_text() == "hello"
    assert events[:2] == ["fsync", "replace"]


def test_atomic_path_leaves_no_temporary_on_error(tmp_path):
    from virus_nerf.utils.io import atomic_path

    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x").write_text("a folder in the way")
    with pytest.raises(OSError):
        with atomic_path(tmp_path / "b") as tmp:  # the rename itself fails
            tmp.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b"]
    assert (tmp_path / "a.txt").read_text() == "old"


def test_new_output_dir_removes_its_partial_folder_on_error(tmp_path):
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.utils.io import new_output_dir

    with pytest.raises(RuntimeError):
        with new_output_dir(tmp_path / "out") as tmp:
            (tmp / "half.txt").write_text("x")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("old")
    with pytest.raises(OutputExistsError):
        with new_output_dir(tmp_path / "out"):
            pass
    with new_output_dir(tmp_path / "out", replace=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["new.txt"]
