"""One error type for bad input, so every message names where the problem is."""

from __future__ import annotations

import errno
from pathlib import Path


class DataFormatError(ValueError):
    """Input that does not match the expected format.

    The message always names the file and, where known, the row (1-based, header = row 1)
    and the field, followed by what was expected.
    """

    def __init__(
        self,
        path: str | Path,
        problem: str,
        *,
        row: int | None = None,
        field: str | None = None,
    ) -> None:
        self.path = Path(path)
        self.row = row
        self.field = field
        self.problem = problem
        where = str(self.path)
        if row is not None:
            where += f", row {row}"
        if field is not None:
            where += f", field '{field}'"
        super().__init__(f"{where}: {problem}")


class OutputExistsError(FileExistsError):
    """Refusal to touch an output file or folder that already exists (nothing is overwritten)."""

    def __init__(self, path: str | Path, flag: str = "--out") -> None:
        """flag: the argument that named `path`, the one to change."""
        kind = "folder" if Path(path).is_dir() else "file"
        super().__init__(
            f"{path}: output {kind} already exists; choose a new {flag} (nothing was overwritten)"
        )
        self.path = Path(path)


class OutputGoneError(Exception):
    """The command's output folder vanished while it ran (removed by hand, a cleaner): nothing more
    is written, so that it is not rebuilt half-empty and unlocked (exit code 2, one line)."""

    def __init__(self, folder: str | Path, what: str = "the output folder") -> None:
        super().__init__(f"{folder}: {what} was removed while the command ran; nothing more is written (the "
                         "files it held are gone: run the command again into a new folder)")
        self.folder = Path(folder)


def require_folder(folder: str | Path, what: str = "the output folder") -> None:
    """`folder` still exists (a writer must not rebuild a folder removed under it), else OutputGoneError."""
    if not Path(folder).is_dir():
        raise OutputGoneError(folder, what)


# the errnos of a disk that cannot take more: full (ENOSPC) or over the user's quota (EDQUOT)
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)})


class NotWrittenError(OSError):
    """Final outputs that could not be written (a full disk, ENOSPC): one line naming what was not
    written and what was kept (utils/io.py `Outputs`, which writes the small files first)."""

    def __init__(self, message: str, errno_: int | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.errno = errno_

    def __str__(self) -> str:
        return self.message


def install_extra(extra: str) -> str:
    """How to install an optional extra, the way the README installs the package (from its clone)."""
    return f"pip install -e '.[{extra}]' in the virus-nerf repository"


class UsageError(ValueError):
    """A mistake on the command line or in a config file, found before any work is done.

    The message is one line: the argument, file, key or field that is wrong, the value given
    and what was expected (e.g. "--batch-size 0: expected a positive integer").
    """


class ConfigError(UsageError):
    """A bad key or value in a JSON config (a `--config` file or a run's config.json).

    `key` is the dotted path inside the document ("march.step_size", "optim.betas[1]");
    the message names the file (or "config" when the dict did not come from a file) and key.
    """

    def __init__(self, problem: str, *, file: str | Path | None = None, key: str = "") -> None:
        self.file = None if file is None else Path(file)
        self.key = key
        self.problem = problem
        if file is None:
            where = "config" + (f".{key}" if key else "")
        else:
            where = f"{file}" + (f", key '{key}'" if key else "")
        super().__init__(f"{where}: {problem}")


def one_line(text: object, limit: int = 400) -> str:
    """`text` as a single line (newlines and runs of spaces collapsed), cut at `limit` characters."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def is_plain_name(text: object) -> bool:
    """A name that is one folder's name, not a path: not empty, no slash, not . or .."""
    return isinstance(text, str) and bool(text.strip()) and not {"/", "\\"} & set(text) and text not in (".", "..")


def require_room_name(room: object, flag: str = "--room") -> None:
    """A room is a folder's name inside the dataset folder (--data), not a path: `../other/office`
    would read a room of another dataset, and "" the dataset folder itself."""
    if not is_plain_name(room):
        raise UsageError(f"{flag} {room!r}: expected the name of a room folder inside --data (e.g. office)")


def require_input_file(flag: str, path: str | Path, expected: str) -> None:
    """The file argument `flag` names must be a file: else a one-line UsageError saying whether it
    is a folder or missing, and what was `expected`."""
    if not Path(path).is_file():
        what = "a folder" if Path(path).is_dir() else "no such file"
        raise UsageError(f"{flag} {path}: {what}; expected {expected}")


def require_int(name: str, value: object, lo: int, hi: int | None = None) -> None:
    """`value` of argument `name` must be an integer (numpy's too) in [lo, hi]; else a one-line UsageError."""
    import numbers

    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= lo and (hi is None or value <= hi)
    if not ok:
        expected = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
        raise UsageError(f"{name} {value}: expected {expected}")


def require_number(name: str, value: object, lo: float, hi: float | None = None, *, lo_open: bool = True) -> None:
    """`value` of argument `name` must be a finite number above lo (or at least lo) and <= hi."""
    import math
    import numbers

    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > lo if lo_open else value >= lo) and (hi is None or value <= hi)  # type: ignore[operator]
    if not ok:
        kind = "a finite number" if isinstance(value, float) and not math.isfinite(value) else "a number"
        if hi is None:
            expected = f"{kind} {'>' if lo_open else '>='} {lo:g}"
        else:
            expected = f"{kind} in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise UsageError(f"{name} {value}: expected {expected}")


PENDING_NOTES: list[str] = []  # notes on the arguments, said once they are all accepted (`say_notes`)


def renamed_flag(new: str, new_value, old: str, old_value):
    """The value of flag `new`, or of its deprecated old name `old` (a note, said by `say_notes`
    once the command's arguments are accepted: a refused command prints its one error line
    alone); both given is a UsageError."""
    if old_value is None:
        return new_value
    if new_value is not None:
        raise UsageError(f"{old} {old_value!r}: the old name of {new}; give {new} alone")
    PENDING_NOTES.append(f"virus-nerf: note: {old} is deprecated; use {new} (the same recording seconds per second)")
    return old_value


def say_notes() -> None:
    """The pending notes on stderr, once (a command calls this where its work begins)."""
    import sys

    for note in PENDING_NOTES:
        print(note, file=sys.stderr)
    PENDING_NOTES.clear()
