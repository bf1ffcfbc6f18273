"""Atomic writes and safe output folders: results are never half-written or overwritten."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from virus_nerf.errors import OutputExistsError


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path` in one step."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; results are ordinary files
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: str | Path, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def create_new_dir(path: str | Path) -> Path:
    """Create `path` (and parents); refuse if it already exists, so nothing is overwritten."""
    path = Path(path)
    if path.exists():
        raise OutputExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.mkdir()
    return path


@contextmanager
def new_output_dir(path: str | Path) -> Iterator[Path]:
    """Build an output folder under a temporary name and rename it into place when complete.

    A crash leaves a `.<name>.partial-*` folder beside it, never a half-written `path`.
    """
    path = Path(path)
    if path.exists():
        raise OutputExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=path.parent))
    yield tmp
    os.chmod(tmp, 0o755)  # mkdtemp makes 0700
    if path.exists():
        raise OutputExistsError(path)
    os.replace(tmp, path)
