"""Strict numeric CSV reading: every problem is reported with file, row and column."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError


def read_numeric_csv(
    path: str | Path,
    required: Sequence[str],
    *,
    allow_extra: bool = True,
) -> dict[str, np.ndarray]:
    """Read a headed CSV whose `required` columns are numbers -> {column: (N,) float64}.

    Rows are 1-based with the header as row 1, as a spreadsheet shows them.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "file not found")
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise DataFormatError(path, f"empty file; expected a header with {list(required)}") from None
        missing = [c for c in required if c not in header]
        if missing:
            raise DataFormatError(
                path,
                f"header {header[:8]}{'...' if len(header) > 8 else ''} lacks column(s) {missing}; "
                f"expected {list(required)[:8]}{'...' if len(required) > 8 else ''}",
                row=1,
            )
        if not allow_extra and len(header) != len(required):
            raise DataFormatError(path, f"expected exactly columns {list(required)}", row=1)
        index = [header.index(c) for c in required]
        rows: list[list[float]] = []
        for row_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise DataFormatError(
                    path, f"has {len(row)} values; expected {len(header)} (one per header column)", row=row_no
                )
            values = []
            for col, i in zip(required, index, strict=True):
                try:
                    values.append(float(row[i]))
                except ValueError:
                    raise DataFormatError(
                        path, f"value {row[i]!r} is not a number", row=row_no, field=col
                    ) from None
            rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(len(rows), len(required))
    return {c: data[:, k] for k, c in enumerate(required)}


def check_sorted_times(path: Path, times: np.ndarray, field: str = "time") -> None:
    """Timestamps must be finite and strictly increasing."""
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise DataFormatError(path, "timestamp is not finite", row=int(bad[0]) + 2, field=field)
    back = np.flatnonzero(np.diff(times) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise DataFormatError(
            path,
            f"timestamps not strictly increasing ({times[i - 1]!r} then {times[i]!r})",
            row=i + 2,
            field=field,
        )
