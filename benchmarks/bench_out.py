"""A benchmark's --out: a new file, refused before the run when it exists (a committed result in
benchmarks/results/ is never overwritten), written whole after it."""

from __future__ import annotations

import sys
from pathlib import Path


def new_out(path: Path | None) -> None:
    """Exit with one line when --out exists already (checked before the benchmark runs)."""
    if path is not None and Path(path).exists():
        sys.exit(f"--out {path}: exists; choose a new file (nothing is overwritten)")


def write_out(path: Path, text: str) -> None:
    """`text` into the new file `path` (parents made), atomically; refused if another run wrote it meanwhile."""
    from virus_nerf.utils.io import write_text_atomic

    new_out(path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(Path(path), text)
