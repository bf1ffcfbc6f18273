"""Helpers shared by several test files (import as `from helpers import ...`; pytest puts tests/
on sys.path). Fixtures live in conftest.py."""

from __future__ import annotations

import contextlib
import dataclasses
import io

import numpy as np


def run_cli(argv) -> tuple[int, str, str]:
    """`virus-nerf ARGV` in this process -> (exit code, stdout, stderr)."""
    from virus_nerf.cli import main

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
    return code, out.getvalue(), err.getvalue()


@contextlib.contextmanager
def ctrl_c_raises():
    """SIGINT raises KeyboardInterrupt in this process while inside, as in a terminal: a shell
    without job control starts a background command (`pytest &`) with SIGINT ignored, and Python
    then keeps it ignored, so a test that sends itself SIGINT would wait in vain."""
    import signal

    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def tiny_train_config(**changes):
    """A 5-step training of 128 rays on a coarse grid: enough to write every file of a run but
    plots/ (~5 s of matplotlib a run; the tests of the plots pass plots=True)."""
    from virus_nerf.engine.config import MarchConfig
    from virus_nerf.grid.ngp import NgpGridConfig
    from virus_nerf.grid.virus import VirusGridConfig
    from virus_nerf.trainer.config import TrainConfig

    base = TrainConfig(
        max_steps=5, max_time=None, batch_size=128, image_scale=1.0, log_every=2, plots=False,
        march=MarchConfig(step_size=0.06, max_samples=32),
        virus_grid=VirusGridConfig(warmup_steps=16, update_interval=4, rays_per_update=64),
        ngp_grid=NgpGridConfig(warmup_steps=16, update_interval=4, max_resolution=32),
    )
    base.evaluation = dataclasses.replace(base.evaluation, n_rays=64)
    return dataclasses.replace(base, **changes)


def horizontal_test_point(x: float, y: float, z: float = 0.0, yaw: float = 0.0, index: int = 0):
    """A TestPoint whose camera 1 sits at (x, y, z) m looking along yaw (rad) in the horizontal plane."""
    from virus_nerf.evaluation.testpoints import TestPoint

    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    cam = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # camera x, y, z axes in the world
    pose = np.eye(4)
    pose[:3, :3] = rz @ cam
    pose[:3, 3] = (x, y, z)
    return TestPoint(index1=index, index3=None, time=float(index), time3=None, pose1=pose, pose3=None)
