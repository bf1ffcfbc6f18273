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

from virus_nerf.trainer.run_folder import TENSORBOARD, TRAIN_LOG
from virus_nerf.utils.io import write_text_atomic
from virus_nerf.utils.stop import stops_deferred


@dataclass(frozen=True)
class LogRow:
    """One line of train_log.csv: loss terms (unweighted; 0 when off), PSNR (dB) of the colour
    term, samples per ray of the step, the grid's occupied share and the frames available
    (online), then the terms added later (at the end, so that a column keeps its place):
    stereo and distortion (unweighted) and line_of_sight (the free-space terms, already
    weighted). loss = the weights' sum of colour, irs, uss, rgbd, stereo and distortion, plus
    line_of_sight."""

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
    stereo: float = 0.0
    distortion: float = 0.0
    line_of_sight: float = 0.0

    FIELDS: ClassVar[tuple[str, ...]] = (
        "step", "seconds", "loss", "colour", "irs", "uss", "rgbd", "psnr", "samples_per_ray", "occupied", "frames",
        "stereo", "distortion", "line_of_sight",
    )
    # an earlier release's header: its rows are kept on resume, the later columns left empty
    LEGACY_FIELDS: ClassVar[tuple[str, ...]] = FIELDS[:11]

    def values(self) -> tuple:
        return astuple(self)


assert LogRow.FIELDS == tuple(f.name for f in fields(LogRow))


def psnr_db(mse: float) -> float:
    """PSNR of a colour MSE on [0, 1] values (floored at 1e-10, i.e. 100 dB)."""
    return -10.0 * math.log10(max(mse, 1e-10))


def truncate_log(path: Path, step: int) -> None:
    """Cut train_log.csv back to the rows up to `step` (the checkpoint's; a crash after it left
    the later ones, which the resumed run writes again) and to complete lines.

    A kill or a full disk can tear the last row (e.g. `8` of `85,1.2,...`, no newline): it is
    dropped, so the next row does not fuse with it; so is a last row that is not numbers. An
    unreadable row before the last is damage nobody can repair here: a DataFormatError naming
    the file and the row. A missing or torn header is written again.
    """
    from virus_nerf.errors import DataFormatError

    path = Path(path)
    text = path.read_bytes().decode("utf-8", errors="replace")
    header = ",".join(LogRow.FIELDS)
    lines = text.split("\n")
    complete = [ln.removesuffix("\r") for ln in lines[:-1]]  # after the last newline: a torn row, or ""
    if not complete:
        write_text_atomic(path, header + "\r\n")
        return
    legacy = complete[0] == ",".join(LogRow.LEGACY_FIELDS)
    if complete[0] != header and not legacy:
        raise DataFormatError(path, f"header {complete[0][:80]!r}: expected {header!r}", row=1)
    n_old = len(LogRow.LEGACY_FIELDS)
    pad = "," * (len(LogRow.FIELDS) - n_old)  # an earlier release's row: the later columns empty
    keep = [header]
    for i, line in enumerate(complete[1:], start=2):
        cells = line.split(",")
        try:
            if len(cells) != (n_old if legacy else len(LogRow.FIELDS)):
                raise ValueError
            row_step = int(cells[0])
            [float(c) for c in cells[1:n_old]]
            [float(c) for c in cells[n_old:] if c != ""]
        except ValueError:
            if i == len(complete):
                break  # the last row: torn or garbage, dropped
            raise DataFormatError(
                path, f"expected {complete[0].count(',') + 1} comma-separated numbers ({complete[0]}); the log is damaged "
                      "before its last row (move the file away to resume without it)", row=i) from None
        if row_step <= step:
            keep.append(line + pad if legacy else line)
    new = "\r\n".join(keep) + "\r\n"
    if new != text:
        write_text_atomic(path, new)


class TrainLog:
    """train_log.csv (appended; cut back to the checkpoint's step on resume), TensorBoard scalars
    when the optional package is installed, and a tqdm bar (hidden off a terminal). A stop signal
    waits until a call is done: both libraries hand work to a thread of their own, which a signal
    cut inside that hand-over can leave asleep (utils/stop.stops_deferred)."""

    def __init__(self, run_dir: Path, step: int, total_steps: int | None, quiet: bool):
        from tqdm import tqdm

        path = Path(run_dir) / TRAIN_LOG
        self.path = path
        new = not path.exists()
        if not new:
            truncate_log(path, step)  # rows after the checkpoint are trained again
        self._file = path.open("a", newline="")
        self._csv = csv.writer(self._file)  # rows end in \r\n (the csv module's default)
        if new:
            self._append(LogRow.FIELDS)
        self._tb = _tensorboard(Path(run_dir) / TENSORBOARD)
        self._bar = tqdm(total=total_steps, initial=step, disable=quiet, unit="step", dynamic_ncols=True)

    def _append(self, values) -> None:
        try:
            self._csv.writerow(values)
            self._file.flush()
        except OSError as exc:  # a full disk: name the file (a torn row is dropped on resume)
            raise type(exc)(exc.errno, exc.strerror, str(self.path)) from exc

    def write(self, row: LogRow) -> None:
        with stops_deferred():
            self._append(row.values())
            for name in LogRow.FIELDS[2:]:
                self.scalar(f"train/{name}", getattr(row, name), row.step)
            self._bar.set_postfix(loss=f"{row.loss:.4f}", psnr=f"{row.psnr:.1f}", t=f"{row.seconds:.0f}s")

    def scalar(self, tag: str, value: float | None, step: int) -> None:
        if self._tb is not None and value is not None:
            try:
                with stops_deferred():
                    self._tb.add_scalar(tag, value, step)
            except OSError:  # its folder became read-only or vanished: the run's own writes say so
                self._tb = None

    def advance(self) -> None:
        """One more step on the progress bar."""
        with stops_deferred():
            self._bar.update(1)

    def close(self) -> None:
        with stops_deferred():
            self._close()

    def _close(self) -> None:
        self._bar.close()
        try:
            self._file.close()
        except OSError as exc:  # the last flush on a full disk: name the file
            raise type(exc)(exc.errno, exc.strerror, str(self.path)) from exc
        if self._tb is not None:
            try:  # TensorBoard's own writer thread met the same folder: the run's outputs speak for it
                self._tb.close()
            except OSError:
                pass


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
