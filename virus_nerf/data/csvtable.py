"""Strict numeric CSV reading: every problem is reported with file, row and column."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError
from virus_nerf.utils.textfile import (
    BOM,
    decode_lenient,
    first_bad_byte,
    has_bad_bytes,
    not_a_number,
    read_bytes,
    utf8_error,
)

MAX_TIME_S = 1e11  # seconds since 1970 reach 1e11 in the year 5138: a larger stamp is in ms, us or ns


def time_unit_problem(t: float) -> str:
    """The refusal of a timestamp beyond MAX_TIME_S, in one wording for every table."""
    return f"timestamp {float(t)!r} beyond {MAX_TIME_S:g} s (the year 5138); expected seconds, not milli-, micro- or nanoseconds"


def read_csv_rows(path: str | Path, what: str = "file") -> list[list[str]]:
    """All rows of a CSV file as strings (row k of the list = spreadsheet row k + 1).

    Read as UTF-8 (a leading BOM dropped); bytes that are not UTF-8 are kept as surrogate escapes
    so that free-text cells still read: callers refuse them where a value matters (see
    virus_nerf.utils.textfile). A file the csv module cannot split is refused naming the row.
    """
    path = Path(path)
    data = read_bytes(path, what).replace(b"\r\r\n", b"\r\n")  # csv.writer on Windows without newline=""
    reader = csv.reader(io.StringIO(decode_lenient(data), newline=""))
    rows: list[list[str]] = []
    try:
        for row in reader:
            rows.append(row)
    except csv.Error as exc:
        raise DataFormatError(path, f"not a readable CSV row: {exc}", row=reader.line_num) from None
    return rows


def refuse_bad_header(path: Path, header: list[str]) -> None:
    """A header row that lacks what it needs because of bytes that are not UTF-8: say so."""
    if any(has_bad_bytes(h) for h in header):
        data = read_bytes(path).removeprefix(BOM)
        bad = first_bad_byte(data)
        if bad is not None:
            raise utf8_error(path, data, bad)


def read_numeric_csv(
    path: str | Path,
    required: Sequence[str],
    *,
    allow_extra: bool = True,
) -> dict[str, np.ndarray]:
    """Read a headed CSV whose `required` columns are numbers -> {column: (N,) float64}.

    Rows are 1-based with the header as row 1, as a spreadsheet shows them; a blank line is
    allowed at the end only, so that the checks after reading name data row i as row i + 2.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "is a directory; expected a CSV file" if path.is_dir() else "file not found")
    all_rows = read_csv_rows(path)
    reader = iter(all_rows)
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise DataFormatError(path, f"empty file; expected a header with {list(required)}") from None
    missing = [c for c in required if c not in header]
    if missing:
        refuse_bad_header(path, header)
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
    blank = None  # the first blank line: allowed at the end only, so that data row i is file row i + 2
    for row_no, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            blank = blank or row_no
            continue
        if blank is not None:
            raise DataFormatError(path, "a blank line between rows; expected one row per line (blank lines at "
                                        "the end only)", row=blank)
        if len(row) != len(header):
            raise DataFormatError(
                path, f"has {len(row)} values; expected {len(header)} (one per header column)", row=row_no
            )
        values = []
        for col, i in zip(required, index, strict=True):
            try:
                values.append(float(row[i]))
            except ValueError:
                raise DataFormatError(path, not_a_number(row[i]), row=row_no, field=col) from None
        rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(len(rows), len(required))
    return {c: data[:, k] for k, c in enumerate(required)}


def check_sorted_times(path: Path, times: np.ndarray, field: str = "time") -> None:
    """Timestamps must be finite seconds (not milli-, micro- or nanoseconds) and strictly increasing."""
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise DataFormatError(path, "timestamp is not finite", row=int(bad[0]) + 2, field=field)
    big = np.flatnonzero(np.abs(times) > MAX_TIME_S)
    if big.size:
        raise DataFormatError(path, time_unit_problem(times[big[0]]), row=int(big[0]) + 2, field=field)
    back = np.flatnonzero(np.diff(times) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise DataFormatError(
            path,
            f"timestamps not strictly increasing ({float(times[i - 1])!r} then {float(times[i])!r})",
            row=i + 2,
            field=field,
        )
