"""The robot program of docs/usage.md runs as written, its callbacks called as a robot calls them."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

USAGE = Path(__file__).resolve().parents[1] / "docs" / "usage.md"


@pytest.mark.slow
def test_the_robot_program_of_usage_md_runs_with_its_callbacks(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", USAGE.read_text(), flags=re.S)
    program = next(b for b in blocks if "def on_messages" in b)
    monkeypatch.chdir(tmp_path)
    space: dict = {}
    exec(compile(program, str(USAGE), "exec"), space)  # noqa: S102 - the docs' own code
    rng = np.random.default_rng(0)
    look_x = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # a level camera looking along +x (OpenCV axes)
    for k in range(4):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = look_x, (0.1 * k, 0.0, 0.5)
        rgb = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
        space["on_messages"](0.2 * k, rgb, pose, 2.0, np.full((8, 8), 2.5))
    space["on_timer"]()
    space["on_snapshot_timer"]()
    assert (tmp_path / "mapping" / "map.pgm").is_file() and (tmp_path / "mapping" / "map.yaml").is_file()
    assert (tmp_path / "mapping" / "0001" / "snapshot.json").is_file()
    assert space["mapper"].frames == 4 and space["mapper"].step > 0
