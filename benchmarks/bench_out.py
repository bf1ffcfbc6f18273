"""A benchmark's --out: a new file, refused before the run when it exists (a committed result in
benchmarks/results/ is never overwritten), written whole after it."""

from __future__ import annotations

import sys
from pathlib import Path


def new_out(path: Path | None, flag: str = "--out") -> None:
    """Exit with one line when the output file exists already, or its folder cannot be made (a
    parent that is a file, a read-only place): checked before the benchmark runs, not after."""
    if path is None:
        return
    if Path(path).exists():
        sys.exit(f"{flag} {path}: exists; choose a new file (nothing is overwritten)")
    from virus_nerf.utils.io import folder_problem

    if (problem := folder_problem(Path(path).absolute().parent)) is not None:
        sys.exit(f"{flag} {path}: cannot be written: {problem}")



def write_out(path: Path, text: str) -> None:
    """`text` into the new file `path` (parents made), atomically; refused if another run wrote it meanwhile."""
    from virus_nerf.utils.io import write_text_atomic

    new_out(path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(Path(path), text)


if __name__ == "__main__":
    sys.exit("bench_out.py is the benchmarks' helper for --out, not a benchmark: run a bench_*.py script")
