"""A child process that dies with its parent: the experiments' `train` runs (`virus-nerf online`,
ablation, tune) must not outlive the experiment that started them."""

from __future__ import annotations

import os

# set by a parent (`virus-nerf online`) to its pid: the `train` child dies with that parent
PARENT_ENV = "VIRUS_NERF_PARENT_PID"


def watch_parent(poll_s: float = 0.5) -> bool:
    """Die (SIGTERM to itself) when the parent named by $VIRUS_NERF_PARENT_PID is gone.

    The experiments start each training as a child process; killing the experiment must not
    leave its trainings running as orphans. A daemon thread polls os.getppid(), which changes
    when the parent dies (the child is handed to init). Linux's prctl(PR_SET_PDEATHSIG) is not
    used: it fires when the parent *thread* ends, and the runs are started from pool threads.
    Returns whether it watches (only if the variable names the actual parent).
    """
    import signal
    import threading
    import time

    want = os.environ.get(PARENT_ENV, "")
    if not want.isdigit() or os.getppid() != int(want):
        return False
    parent = int(want)

    def poll() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)  # the run folder stays resumable, as after any kill

    threading.Thread(target=poll, name="watch-parent", daemon=True).start()
    return True
