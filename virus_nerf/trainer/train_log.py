"""What a training run reports while it trains: typed log rows (train_log.csv, TensorBoard, the
progress bar) and the clock-driven schedule of evaluations and checkpoints.

Kept apart from the loop so that `Trainer.fit` reads as its steps, and so that the CSV layout is
written in one place (`LogRow.FIELDS`), never as positional lists.
"""

from __future__ import annotations

import csv
import math
from dataclasses import astuple, dataclass, fields
from pathlib import Path
from typing import ClassVar

from virus_nerf.utils.io import write_text_atomic


@dataclass(frozen=True)
class LogRow:
    """One line of train_log.csv: loss terms (unweighted), PSNR (dB) of the colour term, samples
    per ray of the step, the grid's occupied share and the frames available (online)."""

    step: int
    seconds: float  # training clock (start-up and evaluations excluded)
    loss: float
    colour: float
    irs: float
    uss: float
    rgbd: float
    psnr: float
    samples_per_ray: float
    occupied: float
    frames: int

    FIELDS: ClassVar[tuple[str, ...]] = (
        "step", "seconds", "loss", "colour", "irs", "uss", "rgbd", "psnr", "samples_per_ray", "occupied", "frames",
    )

    def values(self) -> tuple:
        return astuple(self)


assert LogRow.FIELDS == tuple(f.name for f in fields(LogRow))


def psnr_db(mse: float) -> float:
    """PSNR of a colour MSE on [0, 1] values (floored at 1e-10, i.e. 100 dB)."""
    return -10.0 * math.log10(max(mse, 1e-10))


def truncate_log(path: Path, step: int) -> None:
    """Drop the rows of train_log.csv after `step` (a crash after the last checkpoint left them)."""
    lines = path.read_text().splitlines(keepends=True)
    keep = lines[:1] + [ln for ln in lines[1:] if ln.strip() and int(ln.split(",", 1)[0]) <= step]
    if len(keep) != len(lines):
        write_text_atomic(path, "".join(keep))


class TrainLog:
    """train_log.csv (appended; cut back to the checkpoint's step on resume), TensorBoard scalars
    when the optional package is installed, and a tqdm bar (hidden off a terminal)."""

    def __init__(self, run_dir: Path, step: int, total_steps: int | None, quiet: bool):
        from tqdm import tqdm

        path = Path(run_dir) / "train_log.csv"
        new = not path.exists()
        if not new:
            truncate_log(path, step)  # rows after the checkpoint are trained again
        self._file = path.open("a", newline="")
        self._csv = csv.writer(self._file)
        if new:
            self._csv.writerow(LogRow.FIELDS)
        self._tb = _tensorboard(Path(run_dir) / "tensorboard")
        self._bar = tqdm(total=total_steps, initial=step, disable=quiet, unit="step", dynamic_ncols=True)

    def write(self, row: LogRow) -> None:
        self._csv.writerow(row.values())
        self._file.flush()
        for name in LogRow.FIELDS[2:]:
            self.scalar(f"train/{name}", getattr(row, name), row.step)
        self._bar.set_postfix(loss=f"{row.loss:.4f}", psnr=f"{row.psnr:.1f}", t=f"{row.seconds:.0f}s")

    def scalar(self, tag: str, value: float | None, step: int) -> None:
        if self._tb is not None and value is not None:
            self._tb.add_scalar(tag, value, step)

    def advance(self) -> None:
        """One more step on the progress bar."""
        self._bar.update(1)

    def close(self) -> None:
        self._bar.close()
        self._file.close()
        if self._tb is not None:
            self._tb.close()


@dataclass
class Every:
    """A deadline on the training clock that fires every `period` seconds (inf = never)."""

    period: float
    next_at: float

    @classmethod
    def aligned(cls, period: float, now: float) -> Every:
        """Fires at the next whole multiple of `period` after `now` (evaluations: a resumed run
        keeps the grid of evaluation times)."""
        return cls(period, (math.floor(now / period) + 1) * period if period > 0 else math.inf)

    @classmethod
    def after(cls, period: float, now: float) -> Every:
        """Fires `period` seconds after `now`, then `period` after each firing (checkpoints)."""
        return cls(period, now + period)

    def due(self, now: float) -> bool:
        return now >= self.next_at


def _tensorboard(folder: Path):
    """A TensorBoard writer if the optional `tensorboard` package is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except Exception:
        return None
    return SummaryWriter(str(folder))
