"""Train/val/test split per sample (docs/method.md 4): read from split.csv or made deterministically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.data.csvtable import read_csv_rows, refuse_bad_header
from virus_nerf.errors import DataFormatError, UsageError
from virus_nerf.utils.io import write_text_atomic
from virus_nerf.utils.textfile import not_a_number, quoted

LABELS = ("train", "val", "test", "skip")
DEFAULT_RATIOS = (0.6, 0.0, 0.4)


def make_split(n: int, ratios: tuple[float, float, float] = DEFAULT_RATIOS) -> np.ndarray:
    """Interleaved labels for n samples: held-out samples spread evenly along the recording.

    Deterministic (no seed): sample i is held out where the running count i * (r_val + r_test)
    crosses an integer; held-out samples alternate between 'test' and 'val' in the same way.
    """
    r_train, r_val, r_test = ratios
    total = r_train + r_val + r_test
    if not np.isfinite(total) or total <= 0 or min(ratios) < 0:
        raise UsageError(f"split ratios ({', '.join(f'{r:g}' for r in ratios)}): expected non-negative numbers "
                         "with a positive sum (train, val, test)")
    r_val, r_test = r_val / total, r_test / total
    r_held = r_val + r_test
    i = np.arange(n)
    held = np.flatnonzero(np.floor((i + 1) * r_held + 1e-9) > np.floor(i * r_held + 1e-9))
    q = r_test / r_held if r_held > 0 else 0.0
    k = np.arange(len(held))
    held_is_test = np.floor((k + 1) * q + 1e-9) > np.floor(k * q + 1e-9)
    labels = np.full(n, "train", dtype=object)
    labels[held[held_is_test]] = "test"
    labels[held[~held_is_test]] = "val"
    return labels


def read_split(path: Path, stacks: dict[int, int]) -> dict[int, np.ndarray]:
    """Read split.csv (columns CAM<id>) -> {stack id: (N,) labels}; N must match each stack."""
    if not path.is_file():
        raise DataFormatError(path, "split file not found")
    rows = read_csv_rows(path, "split file")
    if not rows:
        raise DataFormatError(path, "empty split file; expected header CAM1,CAM3")
    header = [h.strip() for h in rows[0]]
    out: dict[int, np.ndarray] = {}
    for stack, n in stacks.items():
        col = f"CAM{stack}"
        if col not in header:
            refuse_bad_header(path, header)
            raise DataFormatError(path, f"header {header} lacks column {col}", row=1)
        k = header.index(col)
        labels = []
        for row_no, row in enumerate(rows[1:], start=2):
            if len(row) != len(header):
                raise DataFormatError(path, f"has {len(row)} values; expected {len(header)}", row=row_no)
            value = row[k].strip()
            if value == "":
                continue
            if value not in LABELS:
                raise DataFormatError(path, f"label {quoted(value)} is not one of {LABELS}", row=row_no, field=col)
            labels.append(value)
        if len(labels) != n:
            raise DataFormatError(
                path, f"column {col} has {len(labels)} labels; the stack has {n} samples", field=col
            )
        out[stack] = np.array(labels, dtype=object)
    return out


def read_split_ratios(path: Path) -> tuple[float, float, float]:
    """Ratios from split_description.csv (train,val,test columns) or the default."""
    if not path.is_file():
        return DEFAULT_RATIOS
    rows = read_csv_rows(path, "split description")
    header = [h.strip() for h in rows[0]] if rows else []
    names = ("train", "val", "test")
    missing = [c for c in names if c not in header]
    if missing:
        refuse_bad_header(path, header)
        raise DataFormatError(path, f"header lacks column(s) {missing}; expected train,val,test "
                                    "(other columns, e.g. a free-text info, may follow)", row=1)
    if len(rows) < 2 or not any(c.strip() for c in rows[1]):
        raise DataFormatError(path, "no ratios; expected one row of train,val,test numbers", row=2)
    row = rows[1]
    ratios = []
    for name in names:
        k = header.index(name)
        text = row[k] if k < len(row) else ""
        try:
            r = float(text)
        except ValueError:
            raise DataFormatError(path, not_a_number(text), row=2, field=name) from None
        if not np.isfinite(r):
            raise DataFormatError(path, f"ratio {r:g} is not finite", row=2, field=name)
        if r < 0:
            raise DataFormatError(path, f"ratio {r:g} is negative; expected non-negative train,val,test ratios "
                                        "with a positive sum", row=2, field=name)
        ratios.append(r)
    if sum(ratios) <= 0:
        raise DataFormatError(path, "the ratios sum to 0; expected non-negative train,val,test ratios with a "
                                    "positive sum", row=2, field="train/val/test")
    return (ratios[0], ratios[1], ratios[2])


def write_split(path: Path, splits: dict[int, np.ndarray]) -> None:
    """Write split.csv with one column per stack (shorter stacks padded with empty cells)."""
    stacks = sorted(splits)
    n = max(len(v) for v in splits.values())
    lines = [",".join(f"CAM{s}" for s in stacks)]
    for i in range(n):
        lines.append(",".join(str(splits[s][i]) if i < len(splits[s]) else "" for s in stacks))
    write_text_atomic(path, "\n".join(lines) + "\n")
