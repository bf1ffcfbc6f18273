"""OpenMP waiting: the package leaves the runtime's default alone; experiment launchers ask for
passive waiting only when their runs share the cores (docs/method.md 10)."""

from __future__ import annotations

import os
import subprocess
import sys

from virus_nerf.experiments.executors import LocalExecutor
from virus_nerf.experiments.runs import _worker_env


def test_importing_the_package_sets_no_openmp_policy():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = "import os, virus_nerf, virus_nerf.trainer.loop; print(os.environ.get('OMP_WAIT_POLICY', 'unset'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "unset"


def test_worker_env_is_passive_only_on_a_shared_cpu(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    alone = _worker_env(2)
    assert "OMP_WAIT_POLICY" not in alone
    assert alone["OMP_NUM_THREADS"] == alone["NUMBA_NUM_THREADS"] == alone["MKL_NUM_THREADS"] == "2"
    assert _worker_env(2, shared_cpu=True)["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # the user's own choice wins
    assert _worker_env(2, shared_cpu=True)["OMP_WAIT_POLICY"] == "ACTIVE"


def test_local_executor_knows_when_its_runs_share_the_cores(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    cases = {(1, None): False, (2, None): False, (4, None): False, (2, 2): False, (2, 3): True, (5, None): True}
    for (workers, threads), shared in cases.items():
        with LocalExecutor(workers, threads) as ex:
            # 4 cores: 1x4, 2x2, 4x1 and 2x2 threads fit; 2x3 and 5x1 do not
            assert ex.shared_cpu is shared, (workers, threads, ex.threads)
