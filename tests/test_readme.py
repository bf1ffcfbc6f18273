"""The README names only files that exist (issue 13, item 11: it named benchmarks/run_all.py)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PATH = re.compile(r"(?<![\w./])((?:benchmarks|configs|docs|tests|virus_nerf)/[\w./{},-]*)")


def _expand(path: str) -> list[str]:
    """`a/b.{json,png}` -> a/b.json, a/b.png (one brace group)."""
    m = re.search(r"\{([^}]*)\}", path)
    if not m:
        return [path]
    return [path[: m.start()] + alt + path[m.end():] for alt in m.group(1).split(",")]


def test_every_path_the_readme_names_exists():
    text = (ROOT / "README.md").read_text()
    named = {p for raw in PATH.findall(text) for p in _expand(raw.rstrip(".,"))}
    assert "benchmarks/bench_train.py" in named  # the pattern finds the commands
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert missing == [], f"README.md names files that do not exist: {missing}"
