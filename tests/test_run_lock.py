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
