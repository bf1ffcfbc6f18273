"""One error type for bad input, so every message names where the problem is."""

from __future__ import annotations

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

    def __init__(self, path: str | Path) -> None:
        kind = "folder" if Path(path).is_dir() else "file"
        super().__init__(
            f"{path}: output {kind} already exists; choose a new --out (nothing was overwritten)"
        )
        self.path = Path(path)
