"""A training killed with SIGKILL and resumed with --resume ends exactly where an uninterrupted
run ends, with one log row per step (issue 13)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_trainer import small_config

from virus_nerf.config_io import to_dict


def _train(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "virus_nerf.cli", "train", *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _logged_steps(run: Path) -> list[int]:
    path = run / "train_log.csv"
    if not path.is_file():
        return []
    return [int(line.split(",")[0]) for line in path.read_text().splitlines()[1:] if line.strip()]


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL (POSIX)")
def test_sigkill_then_resume_equals_an_uninterrupted_run(tiny_office, tmp_path):
    # bit-for-bit equality is the CPU promise: on a GPU the hash table's backward adds with atomics
    # in no fixed order, so two uninterrupted CUDA runs already differ in the last bits
    cfg = small_config(max_steps=40, log_every=1, checkpoint_every=0.05, device="cpu")
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps(to_dict(cfg)))
    env = dict(os.environ)
    base = ["--data", str(tiny_office), "--room", "office", "--config", str(cfg_file), "--quiet"]

    full = tmp_path / "full"
    proc = _train([*base, "--out", str(full)], env)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()

    killed = tmp_path / "killed"
    proc = _train([*base, "--out", str(killed)], env)
    deadline = time.time() + 600
    while time.time() < deadline and not (
        (killed / "checkpoint.pt").is_file() and len(_logged_steps(killed)) >= 15
    ):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert not (killed / "metrics.json").exists(), "killed before the end"
    steps_at_kill = _logged_steps(killed)
    assert 15 <= len(steps_at_kill) < 40

    proc = _train(["--out", str(killed), "--resume", "--quiet"], env)
    assert proc.wait(timeout=600) == 0, proc.stderr.read()
    assert _logged_steps(killed) == list(range(1, 41)), "one row per step, no duplicates"
    a = torch.load(full / "checkpoint.pt", map_location="cpu", weights_only=False)
    b = torch.load(killed / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert a["step"] == b["step"] == 40
    for key, tensor in a["field"].items():
        assert torch.equal(tensor, b["field"][key]), key
    assert torch.equal(a["grid"]["logodds"], b["grid"]["logodds"])
    assert not list(killed.glob(".checkpoint.pt.*")), "no orphaned temporary checkpoint"
