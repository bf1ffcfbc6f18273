"""The run folder's typed files and the training schedule, on hand-made values."""

from __future__ import annotations

import math

import pytest

from virus_nerf.errors import DataFormatError
from virus_nerf.trainer.run_folder import EvalPoint, RunInfo, read_eval_history, write_eval_history
from virus_nerf.trainer.train_log import Every, LogRow, psnr_db, truncate_log


def test_eval_history_round_trips_with_missing_values(tmp_path):
    points = [EvalPoint(10, 1.5, 0.25, 0.5, 0.4, None, 2, "map"), EvalPoint(20, 3.0, None, None, None, None, 0, "map")]
    path = tmp_path / "metrics_vs_time.csv"
    write_eval_history(path, points)
    assert path.read_text().splitlines()[0] == ("step,seconds,acc_mean,cov_mean,acc_inlier,cov_inlier,"
                                                "n_test_points,ground_truth")
    assert path.read_text().splitlines()[2] == "20,3.0,,,,,0,map"  # None is an empty cell
    assert read_eval_history(path) == points
    assert read_eval_history(tmp_path / "absent.csv") == []


def test_eval_history_written_before_the_ground_truth_column_reads(tmp_path):
    """A run made before the column (resumed, or read by `tune`): its ground truth is unknown."""
    path = tmp_path / "metrics_vs_time.csv"
    path.write_text("step,seconds,acc_mean,cov_mean,acc_inlier,cov_inlier,n_test_points\n10,1.5,0.25,,,,2\n")
    assert read_eval_history(path) == [EvalPoint(10, 1.5, 0.25, None, None, None, 2, None)]


def test_eval_history_with_a_foreign_header_or_row_is_named(tmp_path):
    path = tmp_path / "metrics_vs_time.csv"
    path.write_text("step,seconds\n1,2\n")
    with pytest.raises(DataFormatError, match="header"):
        read_eval_history(path)
    path.write_text(",".join(EvalPoint.FIELDS) + "\n1,x,,,,,0\n")
    with pytest.raises(DataFormatError, match="row 2"):
        read_eval_history(path)


def test_run_info_round_trips_and_bad_files_are_named(tmp_path):
    RunInfo(data="/data/rec", room="office").write(tmp_path)
    assert RunInfo.read(tmp_path) == RunInfo(data="/data/rec", room="office")
    (tmp_path / "run.json").write_text('{"data": "", "room": "office"}')
    with pytest.raises(DataFormatError, match="data"):
        RunInfo.read(tmp_path)


def test_log_row_fields_and_psnr():
    row = LogRow(5, 1.25, 0.1, 0.01, 0.0, 0.0, 0.0, psnr_db(0.01), 12.5, 0.3, 7)
    assert row.values()[:2] == (5, 1.25) and len(row.values()) == len(LogRow.FIELDS)
    assert psnr_db(0.01) == pytest.approx(20.0)  # -10 log10(0.01)
    assert psnr_db(0.0) == pytest.approx(100.0)  # floored at 1e-10


HEADER = ",".join(LogRow.FIELDS)


def _row(step: int) -> str:
    return ",".join([str(step)] + ["0.5"] * (len(LogRow.FIELDS) - 2) + ["3"])


def _log(*lines: str, tail: str = "") -> str:
    return "".join(ln + "\r\n" for ln in lines) + tail


def test_truncate_log_keeps_rows_up_to_the_checkpoint(tmp_path):
    path = tmp_path / "train_log.csv"
    path.write_text(_log(HEADER, _row(5), _row(10), _row(15)), newline="")
    truncate_log(path, 10)
    assert path.read_bytes().decode() == _log(HEADER, _row(5), _row(10))


@pytest.mark.parametrize("tail", ["8", _row(12)[:-3], "\x00\x00garbage", "8,9"])
def test_truncate_log_drops_a_torn_last_row(tmp_path, tail):
    """A kill or a full disk tore the last row: without its newline it would fuse with the next
    row written on resume (`8` + `90,...` = `890,...`); with one it is garbage. Dropped."""
    path = tmp_path / "train_log.csv"
    path.write_text(_log(HEADER, _row(5), tail=tail), newline="")
    truncate_log(path, 10)
    assert path.read_bytes().decode() == _log(HEADER, _row(5))
    path.write_text(_log(HEADER, _row(5), tail) if tail else "", newline="")  # garbage with its newline
    truncate_log(path, 10)
    assert path.read_bytes().decode() == _log(HEADER, _row(5))


def test_truncate_log_names_a_damaged_row_and_mends_a_torn_header(tmp_path):
    path = tmp_path / "train_log.csv"
    path.write_text(_log(HEADER, _row(5), "5,x,oops", _row(15)), newline="")
    with pytest.raises(DataFormatError, match=r"train_log.csv, row 3: expected 14 comma-separated numbers"):
        truncate_log(path, 20)
    path.write_text("step,sec", newline="")  # killed while writing the header
    truncate_log(path, 0)
    assert path.read_bytes().decode() == _log(HEADER)


def test_every_fires_on_the_training_clock():
    evals = Every.aligned(10.0, 23.0)  # a resumed run at 23 s evaluates at 30, 40, ...
    assert evals.next_at == 30.0 and not evals.due(29.9) and evals.due(30.0)
    assert Every.aligned(0.0, 5.0).next_at == math.inf  # period 0: never
    ckpt = Every.after(60.0, 12.5)
    assert ckpt.next_at == 72.5


def test_a_full_disk_while_logging_names_train_log(tmp_path):
    import errno

    from virus_nerf.trainer.train_log import TrainLog

    log = TrainLog(tmp_path, 0, 10, quiet=True)

    class Full:
        def __init__(self, f):
            self._f = f

        def write(self, s):
            return self._f.write(s)

        def flush(self):
            raise OSError(errno.ENOSPC, "No space left on device")

        def close(self):
            self._f.close()

    log._file = Full(log._file)
    with pytest.raises(OSError, match="No space left") as info:
        log.write(LogRow(1, 0.1, 0.1, 0.01, 0.0, 0.0, 0.0, 20.0, 12.5, 0.3, 7))
    assert info.value.filename == str(tmp_path / "train_log.csv")
    log.close()


def test_a_log_of_an_earlier_release_is_resumed_with_the_later_columns_empty(tmp_path):
    """A run begun before stereo, distortion and line_of_sight were logged: --resume keeps its rows
    up to the checkpoint, each with three empty cells, under today's header; read again, they stand."""
    old_header = ",".join(LogRow.FIELDS[:11])
    old = [",".join([str(s), "1.5"] + ["0.5"] * 8 + ["3"]) for s in (5, 10, 15)]
    path = tmp_path / "train_log.csv"
    path.write_text(_log(old_header, *old), newline="")
    truncate_log(path, 10)
    want = _log(HEADER, old[0] + ",,,", old[1] + ",,,")
    assert path.read_bytes().decode() == want
    truncate_log(path, 10)
    assert path.read_bytes().decode() == want


def test_an_evaluation_is_logged_under_its_ground_truth(tmp_path):
    """TensorBoard's zone-3 curves are one per ground truth (a run resumed with another --gt drew
    both under one tag), and metrics_vs_time.csv gets the same point."""
    from types import SimpleNamespace

    from virus_nerf.trainer.loop import Trainer

    class Log:
        def __init__(self):
            self.scalars = []

        def scalar(self, tag, value, step):
            self.scalars.append((tag, value, step))

    zone = SimpleNamespace(acc_mean=0.25, cov_mean=0.5, acc_inlier=0.75, cov_inlier=None)
    result = SimpleNamespace(metrics={"NeRF": SimpleNamespace(zones={"zone3": zone})}, n_points=3, gt="exact")
    trainer = SimpleNamespace(mapper=SimpleNamespace(step=40, seconds=2.5), eval_history=[], run_dir=tmp_path)
    log = Log()
    Trainer.record_eval(trainer, result, log)
    assert log.scalars == [("eval_exact/zone3_acc_mean", 0.25, 40), ("eval_exact/zone3_cov_mean", 0.5, 40),
                           ("eval_exact/zone3_acc_inlier", 0.75, 40), ("eval_exact/zone3_cov_inlier", None, 40)]
    assert read_eval_history(tmp_path / "metrics_vs_time.csv") == [EvalPoint(40, 2.5, 0.25, 0.5, 0.75, None, 3, "exact")]
