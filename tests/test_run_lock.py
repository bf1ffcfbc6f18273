"""The run folder's lock, and trainings that die with the experiment that started them (issue 30)."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from virus_nerf.errors import UsageError
from virus_nerf.trainer.run_folder import LOCK, RunLock

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock and SIGKILL are POSIX")


def test_a_second_holder_is_refused_with_the_first_ones_pid(tmp_path):
    with RunLock(tmp_path):
        assert (tmp_path / LOCK).read_text() == f"{os.getpid()}\n"
        with pytest.raises(UsageError, match=rf"--resume {tmp_path}: the run is in use by another virus-nerf "
                                             rf"process \(pid {os.getpid()}\)"):
            RunLock(tmp_path, "--resume").acquire()
    with RunLock(tmp_path):  # released on exit
        pass
    assert (tmp_path / LOCK).is_file()  # the file stays (removing it would race), the lock does not


def _gone(pid: int) -> bool:
    """No such process, or a zombie nobody reaped (it runs no more)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return state in ("Z", "X")
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        return False


def test_a_training_child_dies_with_its_killed_parent(tmp_path):
    """`virus-nerf online` killed with SIGKILL: its `train` children (which call watch_parent)
    end within a poll, instead of training on as orphans (before: they ran to their end)."""
    child = ("from virus_nerf.utils.parent import watch_parent\nimport time\n"
             "assert watch_parent(0.05)\nprint('watching', flush=True)\ntime.sleep(60)")
    parent = ("import os, subprocess, sys, time\n"
              "from virus_nerf.utils.parent import PARENT_ENV\n"
              "env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})\n"
              "p = subprocess.Popen([sys.executable, '-c', sys.argv[1]], env=env, stdout=subprocess.PIPE, text=True)\n"
              "assert p.stdout.readline().strip() == 'watching'\n"
              "print(p.pid, flush=True)\ntime.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", parent, child], stdout=subprocess.PIPE, text=True)
    try:
        child_pid = int(proc.stdout.readline())
        assert not _gone(child_pid)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 10
        while time.time() < deadline and not _gone(child_pid):
            time.sleep(0.05)
        assert _gone(child_pid), "the child outlived its parent"
    finally:
        proc.kill()
        proc.wait()


def test_watch_parent_only_watches_the_parent_it_is_told(monkeypatch):
    from virus_nerf.utils.parent import PARENT_ENV, watch_parent

    monkeypatch.delenv(PARENT_ENV, raising=False)
    assert not watch_parent()
    monkeypatch.setenv(PARENT_ENV, "1" if os.getppid() != 1 else "2")  # not this process's parent
    assert not watch_parent()


def test_every_experiment_tells_its_runs_to_die_with_it(monkeypatch):
    """ablation, tune, online and demo start their trainings with runs._worker_env: each child
    gets this process's pid, so its watch_parent ends it when the experiment is killed."""
    from virus_nerf.experiments.runs import _worker_env
    from virus_nerf.utils.parent import PARENT_ENV

    monkeypatch.delenv(PARENT_ENV, raising=False)
    env = _worker_env(1)
    assert env[PARENT_ENV] == str(os.getpid())
    assert env["OMP_NUM_THREADS"] == "1"
    assert PARENT_ENV not in os.environ  # the experiment's own environment is left alone


def _holding(folder: Path, shared: bool) -> subprocess.Popen:
    """Another process holding FOLDER's run lock (shared: as `export` does) until killed."""
    script = ("import sys, time\nfrom virus_nerf.trainer.run_folder import RunLock\n"
              f"RunLock(sys.argv[1], shared={shared}).acquire()\nprint('locked', flush=True)\ntime.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", script, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_readers_share_the_lock_write_nothing_and_a_writer_is_refused_naming_the_reader(tmp_path):
    """export reads a run under a shared lock: other readers go on beside it, nothing is written
    into the run, and a writer (train --resume) is refused naming the reader's pid as the kernel
    lists it, not the pid the last writer left in the file."""
    (tmp_path / LOCK).write_text("1\n")  # the last writer's pid, long gone
    before = (tmp_path / LOCK).stat().st_mtime_ns
    reader = _holding(tmp_path, shared=True)
    try:
        with RunLock(tmp_path, "--run", shared=True):  # a second export
            pass
        with pytest.raises(UsageError, match=rf"--resume {tmp_path}: the run is in use by another virus-nerf "
                                             rf"process \(pid {reader.pid}\)"):
            RunLock(tmp_path, "--resume").acquire()
    finally:
        reader.kill()
        reader.wait()
    assert (tmp_path / LOCK).read_text() == "1\n" and (tmp_path / LOCK).stat().st_mtime_ns == before
    writer = _holding(tmp_path, shared=False)
    try:  # and a reader waits for no writer
        with pytest.raises(UsageError, match=rf"--run {tmp_path}: the run is in use by another virus-nerf "
                                             rf"process \(pid {writer.pid}\)"):
            RunLock(tmp_path, "--run", shared=True).acquire()
    finally:
        writer.kill()
        writer.wait()


@pytest.mark.parametrize("errno_", [errno.EROFS, errno.EACCES])
def test_a_lock_file_that_cannot_be_written_is_no_lock(tmp_path, monkeypatch, errno_):
    """A run on read-only media (EROFS) or without write permission (EACCES): nobody can train in
    it, so reading it needs no lock (before: EROFS ended export and evaluate in one line)."""
    real_open = os.open

    def refused(path, flags, *args):
        if Path(path).name == LOCK:
            raise OSError(errno_, os.strerror(errno_), str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", refused)
    for shared in (False, True):
        with RunLock(tmp_path, "--run", shared=shared):
            pass
    monkeypatch.setattr(os, "open", lambda *a: (_ for _ in ()).throw(OSError(errno.EIO, "I/O error")))
    with pytest.raises(OSError, match="I/O error"):  # any other error is not swallowed
        RunLock(tmp_path).acquire()


def test_a_file_system_without_locks_is_used_unlocked_and_said_once(tmp_path, monkeypatch, capsys):
    """NFS without its lock service answers flock with ENOLCK (some FUSE mounts with EOPNOTSUPP):
    the run is used as where flock does not exist, with one warning naming the folder (before:
    'the run is in use by another virus-nerf process', so no run could ever train there)."""
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(fcntl, "flock", no_locks)
    run, other = tmp_path / "run", tmp_path / "other"
    run.mkdir()
    other.mkdir()
    (other / LOCK).write_text("")  # a reader makes none
    (tmp_path / "link").symlink_to(run)
    with RunLock(run, "--out") as lock:
        assert lock.holds(run) and (run / LOCK).read_text() == f"{os.getpid()}\n"
    for folder in (run, tmp_path / "link", other):  # the run again, by another name, another run
        with RunLock(folder, "--run", shared=True):
            pass
    out = capsys.readouterr().out
    assert out == (f"warning: --out {run}: its file system offers no file locks (No locks available); nothing "
                   "stops another process writing this run at the same time\n"
                   f"warning: --run {other}: its file system offers no file locks (No locks available); nothing "
                   "stops another process writing this run at the same time\n"), out


def test_a_writers_probe_sees_a_reader_and_a_gone_writers_pid_is_not_named(tmp_path, monkeypatch):
    """A review: `held_by_another` and `probe` (the experiment runner's wait, evaluate's early check)
    took the lock shared and so passed while an export read the run; and where /proc/locks cannot
    be read, a writer refused by an export was named the pid a long-gone writer left in the file."""
    from virus_nerf.trainer import run_folder

    (tmp_path / LOCK).write_text(f"{_dead_pid()}\n")
    reader = _holding(tmp_path, shared=True)
    try:
        assert RunLock(tmp_path).held_by_another()
        with pytest.raises(UsageError, match=rf"\(pid {reader.pid}\)"):
            RunLock(tmp_path, "--run").probe()
        RunLock(tmp_path, "--run", shared=True).probe()  # another reader may go on
        monkeypatch.setattr(run_folder, "_flock_holders", lambda fd: None)  # no /proc/locks
        with pytest.raises(UsageError, match=r"in use by another virus-nerf process \(another process\)"):
            RunLock(tmp_path, "--resume").acquire()
    finally:
        reader.kill()
        reader.wait()
    assert not RunLock(tmp_path).held_by_another()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid
