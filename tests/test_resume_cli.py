"""Run folders through the command line: resume never damages a run, a failed start leaves no
half-made folder, run folders and checkpoints that are missing or corrupt are named, a bad
split is refused before training, and the atomic-write helpers leave no temporaries."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest
from helpers import run_cli, tiny_train_config

from virus_nerf.config_io import to_dict

PREFIX = "virus-nerf: error: "


def one_line_error(code: int, err: str, *fragments: str) -> str:
    assert code == 2, err
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith(PREFIX), err
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def snapshot(folder: Path) -> dict[str, tuple[str, int]]:
    """Every file under `folder` -> (sha256, mtime_ns): equal snapshots = nothing touched."""
    return {
        str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def finished_run(tiny_office, tmp_path_factory) -> Path:
    """A 5-step run trained through the CLI (config file + flags), kept pristine for copying."""
    root = tmp_path_factory.mktemp("finished")
    cfg = root / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", root / "run", "--config", cfg,
                         "--quiet"])
    assert code == 0, err
    return root / "run"


@pytest.fixture()
def run_copy(finished_run, tmp_path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(finished_run, dst)
    return dst


# ------------------------------------------------------------------------------ item 1: resume
def test_resume_of_a_finished_run_is_refused_and_touches_nothing(run_copy, tiny_office):
    before = snapshot(run_copy)
    assert {"checkpoint.pt", "metrics.json", "metrics_vs_time.csv", "plots/metrics_bars.png"} <= set(before)
    for extra in ([], ["--data", tiny_office, "--room", "office"]):
        code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet", *extra])
        one_line_error(code, err, f"--resume {run_copy}: the run is finished (step 5", "budget max_steps 5",
                       "nothing to resume")
        assert snapshot(run_copy) == before


def test_resume_after_a_crash_before_the_metrics_only_evaluates(run_copy):
    """Budget reached, metrics.json never written (killed during the final evaluation, plots
    already there): resume evaluates without training and replaces the plots whole."""
    (run_copy / "metrics.json").unlink()
    (run_copy / "plots" / "metrics_bars.png").unlink()  # a stale, incomplete plots folder
    ckpt = snapshot(run_copy)["checkpoint.pt"]
    log = (run_copy / "train_log.csv").read_bytes()
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])
    assert code == 0, err
    doc = json.loads((run_copy / "metrics.json").read_text())
    assert doc["train"]["steps"] == 5
    assert snapshot(run_copy)["checkpoint.pt"] == ckpt  # no training step, not even a rewrite
    assert (run_copy / "train_log.csv").read_bytes() == log
    assert (run_copy / "plots" / "metrics_bars.png").is_file()
    assert not [p.name for p in run_copy.iterdir() if p.name.startswith(".")]  # no temporaries left
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])  # and now it is finished
    one_line_error(code, err, "the run is finished")


def test_resume_with_a_larger_budget_trains_on_and_replaces_the_results(run_copy):
    stale = run_copy / ".checkpoint.pt.abc123.tmp"  # left by a process killed while saving
    stale.write_bytes(b"half a checkpoint")
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--quiet"])
    assert code == 0, err
    assert json.loads((run_copy / "metrics.json").read_text())["train"]["steps"] == 7
    assert json.loads((run_copy / "config.json").read_text())["max_steps"] == 7
    assert (run_copy / "plots" / "metrics_bars.png").is_file()
    assert not stale.exists()
    assert not [p.name for p in run_copy.iterdir() if p.name.startswith(".")]


def test_resume_with_another_grid_is_refused(run_copy):
    before = snapshot(run_copy)
    (run_copy / "metrics.json").unlink()  # an unfinished run: only the grid is wrong
    before.pop("metrics.json")
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--grid", "ngp"])
    one_line_error(code, err, "grid 'ngp':", "trained with grid 'virus'", "a run keeps its grid")
    assert snapshot(run_copy) == before


def test_resume_with_another_network_shape_is_refused(run_copy, tmp_path):
    cfg = json.loads((run_copy / "config.json").read_text())
    cfg["field"]["log2_table_size"] += 1
    (tmp_path / "bigger.json").write_text(json.dumps(cfg))
    (run_copy / "metrics.json").unlink()
    before = snapshot(run_copy)
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--config", tmp_path / "bigger.json"])
    one_line_error(code, err, "field.log2_table_size 17:", "was trained with field.log2_table_size 16",
                   "a run keeps its network and grid shape")
    assert snapshot(run_copy) == before


def test_resume_with_other_data_is_refused(run_copy, tmp_path):
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--data", tmp_path, "--room", "office"])
    one_line_error(code, err, f"--data {tmp_path}: the run in {run_copy} was trained on")


# ------------------------------------------------------------------------------ item 7: run folders
@pytest.mark.parametrize("command", ["resume", "evaluate", "export"])
@pytest.mark.parametrize(
    "damage, fragment",
    [
        ("no-checkpoint", "checkpoint.pt: missing: the run has no checkpoint"),
        ("garbage-checkpoint", "checkpoint.pt: not a readable checkpoint ("),
        ("truncated-checkpoint", "checkpoint.pt: not a readable checkpoint ("),
        ("foreign-checkpoint", "checkpoint.pt: not a complete virus-nerf checkpoint: lacks ['field'"),
        ("no-run-json", "run.json: missing; "),
        ("bad-run-json", "run.json, field 'data': expected a non-empty string"),
        ("bad-config", "config.json, key 'batch_size': expected an integer, got string"),
    ],
)
def test_damaged_run_folders_are_named(run_copy, tmp_path, command, damage, fragment):
    import torch

    ckpt = run_copy / "checkpoint.pt"
    if damage == "no-checkpoint":
        ckpt.unlink()
    elif damage == "garbage-checkpoint":
        ckpt.write_bytes(b"\x00garbage" * 100)
    elif damage == "truncated-checkpoint":
        ckpt.write_bytes(ckpt.read_bytes()[:5000])
    elif damage == "foreign-checkpoint":
        torch.save({"weights": torch.zeros(3)}, ckpt)
    elif damage == "no-run-json":
        (run_copy / "run.json").unlink()
    elif damage == "bad-run-json":
        (run_copy / "run.json").write_text('{"data": 3, "room": "office"}')
    elif damage == "bad-config":
        cfg = json.loads((run_copy / "config.json").read_text())
        cfg["batch_size"] = "128"
        (run_copy / "config.json").write_text(json.dumps(cfg))
    (run_copy / "metrics.json").unlink()  # so a resume would otherwise go ahead
    before = snapshot(run_copy)
    argv = {
        "resume": ["train", "--out", run_copy, "--resume"],
        "evaluate": ["evaluate", "--run", run_copy],
        "export": ["export", "--run", run_copy, "--out", tmp_path / "map"],
    }[command]
    code, _, err = run_cli(argv)
    one_line_error(code, err, fragment)
    assert snapshot(run_copy) == before
    assert not (tmp_path / "map").exists()


def test_evaluate_and_export_still_work(run_copy, tmp_path):
    code, _, err = run_cli(["evaluate", "--run", run_copy, "--n-rays", "32"])
    assert code == 0, err
    assert json.loads((run_copy / "evaluation" / "metrics.json").read_text())["train"]["steps"] == 5
    assert (run_copy / "evaluation" / "metrics_plots" / "metrics_bars.png").is_file()
    code, _, err = run_cli(["evaluate", "--run", run_copy])
    one_line_error(code, err, "evaluation/metrics.json: output file already exists")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "map", "--max-poses", "2", "--n-rays", "16"])
    assert code == 0, err
    assert (tmp_path / "map" / "map.pgm").read_bytes().startswith(b"P5")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "map2", "--resolution", "1e-6"])
    one_line_error(code, err, "--resolution 1e-06: the", "expected at most 100 M px")
    assert not (tmp_path / "map2").exists()


def test_export_makes_its_output_folder_before_computing(run_copy, tmp_path, monkeypatch):
    import virus_nerf.trainer.command as train_command

    def no_work(*args, **kwargs):
        raise AssertionError("the model was loaded although the output folder cannot be made")

    monkeypatch.setattr(train_command, "load_trained", no_work)
    (tmp_path / "afile").write_text("a file where a folder should be")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "afile" / "map"])
    one_line_error(code, err, f"{tmp_path / 'afile' / 'map'}: cannot create this folder (a parent is not a folder)")


# ------------------------------------------------------------------------------ item 7: bad splits
def recording_copy(tiny_office: Path, tmp_path: Path, relabel: dict[str, str]) -> Path:
    data = tmp_path / "data"
    shutil.copytree(tiny_office, data)
    split = data / "office" / "split" / "split.csv"
    lines = split.read_text().splitlines()
    out = [lines[0]] + [",".join(relabel.get(c, c) for c in ln.split(",")) for ln in lines[1:]]
    split.write_text("\n".join(out) + "\n")
    return data


@pytest.mark.parametrize(
    "relabel, fragment",
    [
        ({"train": "val"}, "split.csv: no rows labelled 'train'; training needs at least one"),
        ({"test": "train"}, "split.csv, field 'CAM1': no CAM1 rows labelled 'test'"),
    ],
)
def test_split_without_train_or_test_rows_is_refused_before_training(tiny_office, tmp_path, relabel, fragment):
    data = recording_copy(tiny_office, tmp_path, relabel)
    code, _, err = run_cli(["train", "--data", data, "--room", "office", "--out", tmp_path / "run", "--max-steps", "2"])
    one_line_error(code, err, fragment)
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------------------ item 8: half-made runs
def test_a_training_that_fails_at_the_start_leaves_no_run_folder(tiny_office, tmp_path):
    """A training image that is readable in its header but corrupt inside fails while the frames
    are decoded, after the run folder was made: the folder goes again, the error is one line."""
    data = recording_copy(tiny_office, tmp_path, {})
    img = data / "office" / "measurements" / "CAM1_color_image_raw" / "img0.png"
    img.write_bytes(img.read_bytes()[:60])  # IHDR intact (size check passes), pixel data cut
    code, _, err = run_cli(["train", "--data", data, "--room", "office", "--out", tmp_path / "run", "--max-steps", "2",
                         "--quiet"])
    one_line_error(code, err, "img0.png: not a readable image")
    assert not (tmp_path / "run").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["data"]  # no partial or temporary folder either


def test_plots_are_written_before_metrics(tiny_office, tmp_path, monkeypatch):
    """metrics.json marks a finished run, so it comes last: a failure while plotting leaves no
    metrics.json (and a resumable run), never metrics without plots."""
    import virus_nerf.trainer.report as report
    from virus_nerf.trainer.command import run_training

    def broken(*args, **kwargs):
        raise RuntimeError("plotting failed")

    monkeypatch.setattr(report, "write_run_plots", broken)
    with pytest.raises(RuntimeError, match="plotting failed"):
        run_training(tiny_office, "office", tmp_path / "run", tiny_train_config(max_steps=2), quiet=True)
    assert (tmp_path / "run" / "checkpoint.pt").is_file()
    assert not (tmp_path / "run" / "metrics.json").exists()
    monkeypatch.undo()
    code, _, err = run_cli(["train", "--out", tmp_path / "run", "--resume", "--quiet"])
    assert code == 0, err
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["train"]["steps"] == 2


# ------------------------------------------------------------------------------ item 8: atomic writes
def test_atomic_path_fsyncs_before_the_rename(tmp_path, monkeypatch):
    from virus_nerf.utils import io as vio

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(vio.os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(vio.os, "replace", lambda a, b: (events.append("replace"), real_replace(a, b))[1])
    vio.write_text_atomic(tmp_path / "a.txt", "hello")
    assert (tmp_path / "a.txt").read_text() == "hello"
    assert events[:2] == ["fsync", "replace"]


def test_atomic_path_leaves_no_temporary_on_error(tmp_path):
    from virus_nerf.utils.io import atomic_path

    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x").write_text("a folder in the way")
    with pytest.raises(OSError):
        with atomic_path(tmp_path / "b") as tmp:  # the rename itself fails
            tmp.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b"]
    assert (tmp_path / "a.txt").read_text() == "old"


def test_new_output_dir_removes_its_partial_folder_on_error(tmp_path):
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.utils.io import new_output_dir

    with pytest.raises(RuntimeError):
        with new_output_dir(tmp_path / "out") as tmp:
            (tmp / "half.txt").write_text("x")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("old")
    with pytest.raises(OutputExistsError):
        with new_output_dir(tmp_path / "out"):
            pass
    with new_output_dir(tmp_path / "out", replace=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["new.txt"]


# ------------------------------------------------------------------------------ item 11: experiments
def test_demo_copies_metrics_atomically(tmp_path, monkeypatch):
    """The copy of run/metrics.json goes through a temporary file: a copy that fails half-way
    leaves no OUT/metrics.json (the demo's marker of a complete result)."""
    import virus_nerf.sim.command as sim_command
    import virus_nerf.trainer.command as train_command
    from virus_nerf.experiments.demo import demo

    doc = {"zones": {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]}, "sensors": {},
           "train": {"seconds": 1.0, "steps": 2, "steps_per_s": 2.0, "samples_per_s": 1e6}}

    def fake_simulate(**kwargs):
        Path(kwargs["out"]).mkdir()

    def fake_training(data, room, out, cfg, quiet=None):
        (out / "plots").mkdir(parents=True)
        (out / "metrics.json").write_text(json.dumps(doc) * 50)
        return doc

    def half_copy(src, dst, *args, **kwargs):
        Path(dst).write_text(Path(src).read_text()[:10])
        raise OSError(28, "No space left on device", str(dst))

    monkeypatch.setattr(sim_command, "simulate", fake_simulate)
    monkeypatch.setattr(train_command, "run_training", fake_training)
    monkeypatch.setattr(shutil, "copyfile", half_copy)
    with pytest.raises(OSError, match="No space left"):
        demo(out=tmp_path / "demo", quiet=True)
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["data", "run"]


@pytest.mark.parametrize("experiment, summary", [("ablation", "ablation.md"), ("ablation", "ablation.png"),
                                                 ("online", "online.json"), ("online", "online.md")])
def test_experiments_refuse_to_overwrite_their_summaries(tmp_path, monkeypatch, experiment, summary):
    """A finished experiment folder is refused before anything runs; the summary stays as it was."""
    import virus_nerf.sim.command as sim_command

    def no_work(*args, **kwargs):
        raise AssertionError("work started although the summary exists")

    monkeypatch.setattr(sim_command, "simulate", no_work)
    monkeypatch.setattr("virus_nerf.experiments.executors.run_all", no_work)
    monkeypatch.setattr(f"virus_nerf.experiments.{experiment}.run_all", no_work)
    out = tmp_path / "exp"
    out.mkdir()
    (out / summary).write_text("the earlier result")
    before = snapshot(out)
    code, _, err = run_cli([experiment, "--out", out, "--quick"])
    one_line_error(code, err, f"{out / summary}: output file already exists")
    assert snapshot(out) == before
