"""Atomic writes and safe output folders: results are never half-written or overwritten."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from virus_nerf.errors import OutputExistsError

_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")  # numpy's message for a short write


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path` in one step.

    The temporary file is flushed to disk (fsync) before the rename and the folder after it, so
    a power cut leaves either the old file or the complete new one. On any error inside the
    block (or in the rename) the temporary file is removed: no orphaned `.<name>.*.tmp` is left
    behind. (Only a kill during the write can leave one; `remove_stale_temps` clears those.)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        _fsync_file(tmp_path)
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; results are ordinary files
        os.replace(tmp_path, path)
        _fsync_dir(path.parent)
    except OSError as exc:
        if exc.filename in (None, str(tmp_path), tmp_path) and exc.errno is not None:
            # name the file being written, not its temporary (e.g. a full disk: ENOSPC)
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        if exc.errno is None and exc.filename is None and _SHORT_WRITE.fullmatch(str(exc)):
            # numpy's tofile on a full disk says only "N requested and M written": no errno, no file
            raise OSError(errno.ENOSPC, f"no space left on device ({exc})", str(path)) from exc
        raise
    finally:
        try:
            tmp_path.unlink(missing_ok=True)
        except OSError:  # pragma: no cover - the folder vanished or became read-only
            pass


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in `folder` durable (a no-op where folders cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Delete temporaries `atomic_path(path)` left when its process was killed mid-write.

    Only files named `.<name>.<random>.tmp` beside `path` are touched; returns what was removed.
    Call it only where this process owns the folder (e.g. resuming a run).
    """
    path = Path(path)
    removed = []
    if path.parent.is_dir():
        for p in path.parent.glob(f".{path.name}.*.tmp"):
            if p.is_file():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def copy_file_atomic(src: str | Path, dst: str | Path) -> None:
    """Copy `src` to `dst` in one rename: `dst` is never seen half-written."""
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: str | Path, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def folder_problem(path: str | Path) -> str | None:
    """Why a new folder `path` (and its missing parents) cannot be made, or None: it, or its nearest
    existing ancestor, is not a folder, or does not take a new folder (read-only, no permission,
    a virtual file system; tried with an empty folder made and removed at once)."""
    path = Path(path).absolute()
    ancestor = next((a for a in (path, *path.parents) if os.path.lexists(a)), Path("/"))
    if not ancestor.is_dir():
        return f"{ancestor} is a file, not a folder"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".virus-nerf-probe-", dir=ancestor))
    except OSError as exc:
        return f"{ancestor} takes no new folder ({exc.strerror or exc})"
    return None


def require_new_folder(flag: str, path: str | Path) -> Path:
    """`path` for a new output folder, checked before any work: it must not exist (nothing is
    overwritten) and must be makeable; else the one-line error names `flag`."""
    path = Path(path)
    if os.path.lexists(path):
        raise OutputExistsError(path, flag)
    require_makeable(flag, path)
    return path


def require_makeable(flag: str, path: str | Path, folder: str | Path | None = None) -> None:
    """A one-line UsageError naming `flag` and `path` when the folder `path` (or `folder`, the one
    the file `path` goes in) cannot be made: checked before any work, not after it."""
    from virus_nerf.errors import UsageError

    if (problem := folder_problem(path if folder is None else folder)) is not None:
        raise UsageError(f"{flag} {path}: cannot be made: {problem}")


def create_new_dir(path: str | Path) -> Path:
    """Create `path` (and parents); refuse if it already exists, so nothing is overwritten."""
    path = Path(path)
    if path.exists():
        raise OutputExistsError(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.mkdir()
    return path


@contextmanager
def new_output_dir(path: str | Path, *, replace: bool = False, flag: str = "--out") -> Iterator[Path]:
    """Build an output folder under a temporary name and rename it into place when complete.

    An error inside the block removes the temporary folder and the parents it made; a kill leaves a
    `.<name>.partial-<pid>-*` folder beside it, never a half-written `path`
    (`remove_stale_partials` removes it when the next attempt starts). With `replace=True` an
    existing `path` is swapped for the new folder once the new one is complete (used only where
    the caller owns `path`, e.g. the plots of a run being resumed); otherwise it is refused.
    """
    path = Path(path)
    if path.exists() and not replace:
        raise OutputExistsError(path, flag)  # flag: what named `path`, the one to change
    remove_stale_partials(path)  # a killed attempt's `.<name>.partial-<pid>-*` (its process is dead)
    missing = [p for p in path.absolute().parents if not p.exists()]  # made here: gone again if nothing lands
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-{os.getpid()}-", dir=path.parent))
    except OSError as exc:  # name the flag and the folder asked for, not a parent or the temporary name
        from virus_nerf.errors import UsageError

        if exc.errno == errno.ENOSPC:  # a full disk keeps its own one line and advice
            raise type(exc)(exc.errno, f"cannot create this folder ({exc.strerror})", str(path)) from None
        problem = folder_problem(path) or exc.strerror
        raise UsageError(f"{flag} {path}: cannot be made: {problem}") from None
    try:
        try:
            yield tmp
        except OSError as exc:  # name the file as it will be, not inside the temporary folder
            name = exc.filename
            if isinstance(name, str | os.PathLike) and exc.errno is not None and \
                    Path(name).is_relative_to(tmp):
                raise type(exc)(exc.errno, exc.strerror, str(path / Path(name).relative_to(tmp))) from exc
            raise
        os.chmod(tmp, 0o755)  # mkdtemp makes 0700
        if path.exists():
            if not replace:
                raise OutputExistsError(path)
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-{os.getpid()}-", dir=path.parent))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if not path.exists():  # refused or failed: the parents this call made go too (empty ones only)
            for p in missing:
                try:
                    p.rmdir()
                except OSError:
                    break


_PARTIAL = re.compile(r"^\.(?P<name>.+)\.(?:partial|old)-(?:(?P<pid>\d+)-)?[^.]*$")


def pid_alive(pid: int) -> bool:
    """True if a process `pid` exists on this machine (it may belong to another user)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return True
    return True


def remove_stale_partials(path: str | Path, *, owned: bool = False) -> list[Path]:
    """Delete the `.<name>.partial-*` / `.<name>.old-*` folders `new_output_dir(path)` left when
    its process was killed; returns what was removed.

    Only folders of this `path` are touched, and only those whose owning process (the pid in
    the name) is dead; `owned=True` (the caller holds the lock of the folder they are in, e.g. a
    run folder being resumed) also removes those without a pid or with a live one, which no
    other process can be writing.
    """
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    for p in path.parent.iterdir():
        m = _PARTIAL.match(p.name)
        if not m or m.group("name") != path.name or not p.is_dir() or p.is_symlink():
            continue
        pid = m.group("pid")
        stale = owned or (pid is not None and int(pid) != os.getpid() and not pid_alive(int(pid)))
        if stale:
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


class Outputs:
    """A command's final outputs, written in the order given (the small, important files first:
    the map, the report; the large state last), so that a full disk costs the least: an OSError
    in one is remembered and the next are still tried; `check()` then raises one
    NotWrittenError naming what was not written and what was kept (exit code 2)."""

    def __init__(self) -> None:
        self.kept: list[Path] = []
        self.failed: list[tuple[Path, OSError]] = []

    def write(self, path: str | Path, write) -> bool:
        """Call write() for the output `path`; False (remembered) when it raises an OSError."""
        try:
            write()
        except OSError as exc:
            self.failed.append((Path(path), exc))
            return False
        self.kept.append(Path(path))
        return True

    def check(self, hint: str = "") -> None:
        """hint: what to do, written for a full disk ("free some space; ..."); another reason
        (a read-only or vanished folder) gets its own first words."""
        import errno

        from virus_nerf.errors import DISK_FULL_ERRNOS, NotWrittenError

        if not self.failed:
            return
        path, exc = self.failed[0]
        reason = exc.strerror or str(exc)
        if exc.errno not in DISK_FULL_ERRNOS and hint.startswith("free some space"):
            instead = "make it writable" if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM) else "fix that"
            hint = instead + hint.removeprefix("free some space")
        more = "".join(f"; {p} neither" for p, _ in self.failed[1:])
        kept = ", ".join(str(p) for p in self.kept) or "nothing"
        raise NotWrittenError(f"{path}: could not be written ({reason}){more}; kept: {kept}"
                              f"{'; ' + hint if hint else ''}", exc.errno)


def save_torch_atomic(obj: Any, path: str | Path) -> None:
    """torch.save(obj) into `path` whole or not at all: serialised in memory, then written under
    a temporary name and renamed (torch.save straight into a file reports a full disk as a
    RuntimeError `unexpected pos`)."""
    import io

    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getbuffer())
