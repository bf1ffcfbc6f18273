"""The run folder's lock, and trainings that die with the experiment that started them (issue 30)."""

from __future__ import annotations

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
    child = ("from virus_nerf.trainer.command import watch_parent\nimport time\n"
             "assert watch_parent(0.05)\nprint('watching', flush=True)\ntime.sleep(60)")
    parent = ("import os, subprocess, sys, time\n"
              "from virus_nerf.trainer.command import PARENT_ENV\n"
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
    from virus_nerf.trainer.command import PARENT_ENV, watch_parent

    monkeypatch.delenv(PARENT_ENV, raising=False)
    assert not watch_parent()
    monkeypatch.setenv(PARENT_ENV, "1" if os.getppid() != 1 else "2")  # not this process's parent
    assert not watch_parent()


def test_online_tells_its_runs_to_die_with_it(monkeypatch):
    import virus_nerf.experiments.online as online
    from virus_nerf.trainer.command import PARENT_ENV

    seen = {}

    def fake_run_all(specs, workers):
        seen["env"] = os.environ.get(PARENT_ENV)
        return []

    monkeypatch.delenv(PARENT_ENV, raising=False)
    monkeypatch.setattr(online, "run_all", fake_run_all)
    assert online._run_all_as_parent([], 1) == []
    assert seen["env"] == str(os.getpid())
    assert PARENT_ENV not in os.environ
