"""Run folders through the command line: resume never damages a run, a failed start leaves no
half-made folder, run folders and checkpoints that are missing or corrupt are named, a bad
split is refused before training, and the atomic-write helpers leave no temporaries."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
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
    cfg.write_text(json.dumps(to_dict(tiny_train_config(plots=True))))  # resume replaces the plots: they are tested
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", root / "run", "--config", cfg,
                         "--quiet"])
    assert code == 0, err
    return root / "run"


@pytest.fixture()
def run_copy(finished_run, tmp_path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(finished_run, dst)
    return dst


def test_the_metrics_over_time_name_their_ground_truth(finished_run):
    """metrics_vs_time.csv's last row is the final evaluation: its zone-3 NeRF accuracy and its
    ground truth are metrics.json's."""
    from virus_nerf.trainer.run_folder import read_eval_history

    doc = json.loads((finished_run / "metrics.json").read_text())
    last = read_eval_history(finished_run / "metrics_vs_time.csv")[-1]
    assert last.ground_truth == doc["gt"] == "map"
    assert last.acc_mean == pytest.approx(doc["sensors"]["NeRF"]["zone3"]["acc_mean"])


# ------------------------------------------------------------------------------ item 1: resume
def test_resume_of_a_finished_run_is_refused_and_touches_nothing(run_copy, tiny_office):
    before = snapshot(run_copy)
    assert {"checkpoint.pt", "metrics.json", "metrics_vs_time.csv", "plots/metrics_bars.png"} <= set(before)
    for extra in ([], ["--data", tiny_office, "--room", "office"]):
        code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet", *extra])
        one_line_error(code, err, f"--resume {run_copy}: the run is finished (step 5", "budget max_steps 5",
                       "nothing to resume")
        assert snapshot(run_copy) == before
    # a larger --max-time cannot train on while the steps bind: the hint names the budget reached
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet", "--max-time", "600"])
    one_line_error(code, err, "(give a larger --max-steps to train on)")
    assert snapshot(run_copy) == before


def test_resume_after_a_crash_before_the_metrics_only_evaluates(run_copy):
    """Budget reached, metrics.json never written (killed during the final evaluation, plots
    already there): resume evaluates without training and replaces the plots whole, with the
    frames the run trained on: the same figures, the map's safety block among them."""
    before = json.loads((run_copy / "metrics.json").read_text())
    (run_copy / "metrics.json").unlink()
    (run_copy / "plots" / "metrics_bars.png").unlink()  # a stale, incomplete plots folder
    ckpt = snapshot(run_copy)["checkpoint.pt"]
    log = (run_copy / "train_log.csv").read_bytes()
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])
    assert code == 0, err
    doc = json.loads((run_copy / "metrics.json").read_text())
    assert doc["train"]["steps"] == 5
    assert doc["safety"] == before["safety"] and doc["safety"]["planner"]["paths"] > 0
    assert doc["sensors"] == before["sensors"] and doc.get("warnings") == before.get("warnings")
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
DAMAGES = [
    ("no-checkpoint", "checkpoint.pt: missing: the run has no checkpoint"),
    ("text-step", "checkpoint.pt, field 'step': expected an integer >= 0, got 'abc'"),
    ("wrong-shape-field", "checkpoint.pt, field 'field."),
    ("garbage-checkpoint", "checkpoint.pt: not a readable checkpoint ("),
    ("truncated-checkpoint", "checkpoint.pt: not a readable checkpoint ("),
    ("foreign-checkpoint", "checkpoint.pt: not a complete virus-nerf checkpoint: lacks ['field'"),
    ("no-run-json", "run.json: missing; "),
    ("bad-run-json", "run.json, field 'data': expected a non-empty string"),
    ("bad-config", "config.json, key 'batch_size': expected an integer, got string"),
    # Adam is built at the first step, but its saved state is checked when the checkpoint is read
    ("damaged-optimizer", "checkpoint.pt, field 'optimizer': parameter 0's exp_avg does not fit the field"),
]


# --resume of a run without checkpoint trains it from step 0 (test_resume_without_a_checkpoint_...)
@pytest.mark.parametrize("command, damage, fragment", [
    (command, damage, fragment) for damage, fragment in DAMAGES for command in ("resume", "evaluate", "export")
    if (command, damage) != ("resume", "no-checkpoint")])
def test_damaged_run_folders_are_named(run_copy, tmp_path, command, damage, fragment):
    import torch

    ckpt = run_copy / "checkpoint.pt"
    if damage == "no-checkpoint":
        ckpt.unlink()
    elif damage in ("text-step", "wrong-shape-field"):
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        if damage == "text-step":
            state["step"] = "abc"
        else:
            name = next(iter(state["field"]))
            state["field"][name] = torch.zeros(3)
            fragment += f"{name}': tensor of shape (3,)"
        torch.save(state, ckpt)
    elif damage == "garbage-checkpoint":
        ckpt.write_bytes(b"\x00garbage" * 100)
    elif damage == "truncated-checkpoint":
        ckpt.write_bytes(ckpt.read_bytes()[:5000])
    elif damage == "foreign-checkpoint":
        torch.save({"weights": torch.zeros(3)}, ckpt)
    elif damage == "damaged-optimizer":
        state = torch.load(ckpt, weights_only=False)
        state["optimizer"]["state"][0]["exp_avg"] = torch.zeros(3)
        torch.save(state, ckpt)
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
    (tmp_path / "notes.txt").write_text("a file")  # refused before the run is loaded (about 10 s)
    code, _, err = run_cli(["evaluate", "--run", run_copy, "--out", tmp_path / "notes.txt" / "m.json"])
    one_line_error(code, err, f"--out {tmp_path / 'notes.txt' / 'm.json'}: cannot be made: {tmp_path / 'notes.txt'} "
                              "is a file, not a folder")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "map", "--max-poses", "2", "--n-rays", "16"])
    assert code == 0, err
    assert (tmp_path / "map" / "map.pgm").read_bytes().startswith(b"P5")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "map2", "--resolution", "1e-6"])
    one_line_error(code, err, "--resolution 1e-06: the", "expected at most 100 M px")
    assert not (tmp_path / "map2").exists()


def test_export_makes_its_output_folder_before_computing(run_copy, tmp_path, monkeypatch):
    import virus_nerf.trainer.run as train_run

    def no_work(*args, **kwargs):
        raise AssertionError("the model was loaded although the output folder cannot be made")

    monkeypatch.setattr(train_run, "load_trained", no_work)
    (tmp_path / "afile").write_text("a file where a folder should be")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "afile" / "map"])
    one_line_error(code, err, f"--out {tmp_path / 'afile' / 'map'}: cannot be made: {tmp_path / 'afile'} is a file, "
                              "not a folder")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", "/proc/virus-nerf-map"])  # a virtual file system
    one_line_error(code, err, "--out /proc/virus-nerf-map: cannot be made: /proc takes no new folder (")


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
    from virus_nerf.trainer.run import run_training

    def broken(*args, **kwargs):
        raise RuntimeError("plotting failed")

    monkeypatch.setattr(report, "write_run_plots", broken)
    with pytest.raises(RuntimeError, match="plotting failed"):
        run_training(tiny_office, "office", tmp_path / "run", tiny_train_config(max_steps=2, plots=True), quiet=True)
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
    with pytest.raises(RuntimeError):  # the parents it made go too (a review: export left a/b/ behind)
        with new_output_dir(tmp_path / "a" / "b" / "out"):
            raise RuntimeError("refused after the folder was made")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "a").mkdir()
    with pytest.raises(RuntimeError):  # ... and only those: a parent that was there stays
        with new_output_dir(tmp_path / "a" / "b" / "out"):
            (tmp_path / "a" / "notes.txt").write_text("another's, written meanwhile")
            raise RuntimeError("crash")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["notes.txt"]
    with new_output_dir(tmp_path / "a" / "c" / "out") as tmp:
        (tmp / "kept.txt").write_text("kept")
    assert (tmp_path / "a" / "c" / "out" / "kept.txt").is_file()
    for p in sorted(tmp_path.rglob("*"), reverse=True):
        p.unlink() if p.is_file() else p.rmdir()
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
    import virus_nerf.trainer.run as train_run
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
    monkeypatch.setattr(train_run, "run_training", fake_training)
    monkeypatch.setattr(shutil, "copyfile", half_copy)
    with pytest.raises(OSError, match="No space left"):
        demo(out=tmp_path / "demo", quiet=True)
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["data", "demo.json", "run"]


def test_a_stopped_demo_is_finished_with_resume(tmp_path, monkeypatch, capsys):
    """A demo stopped while training says how to finish it; `demo --resume --out OUT` trains on
    from the run's checkpoint with the settings it was begun with and writes the report. A folder
    that is no stopped demo, a finished one and a flag asking for other settings are refused."""
    import virus_nerf.sim.command as sim_command
    import virus_nerf.trainer.run as train_run
    from virus_nerf.errors import UsageError
    from virus_nerf.experiments.demo import demo
    from virus_nerf.utils.stop import Stopped

    doc = {"zones": {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]}, "sensors": {},
           "train": {"seconds": 1.0, "steps": 2, "steps_per_s": 2.0, "samples_per_s": 1e6, "sensors": ["camera"]}}
    calls = []

    def fake_simulate(**kwargs):
        (Path(kwargs["out"]) / "office").mkdir(parents=True)

    def fake_training(data, room, out, cfg, quiet=None, resume=False):
        calls.append((resume, cfg.seed, cfg.max_time))
        if not resume:
            (out / "plots").mkdir(parents=True)
            raise Stopped(signal.SIGTERM)
        (out / "metrics.json").write_text(json.dumps(doc))
        return doc

    monkeypatch.setattr(sim_command, "simulate", fake_simulate)
    monkeypatch.setattr(train_run, "run_training", fake_training)
    out = tmp_path / "demo"
    with pytest.raises(Stopped):
        demo(out=out, seed=4, train_time=30.0, quiet=True)
    assert f"`virus-nerf demo --resume --out {out}` finishes it" in capsys.readouterr().out
    for kwargs, message in (({"out": tmp_path / "other"}, "not a stopped demo (no demo.json)"),
                            ({"out": out, "seed": 5}, "--seed 5: --resume finishes the demo as it was begun "
                                                      "(--seed 4,")):
        with pytest.raises(UsageError, match=re.escape(message)):
            demo(resume=True, quiet=True, **kwargs)
    demo(out=out, resume=True, quiet=True)
    assert calls == [(False, 4, 30.0), (True, 4, 30.0)] and (out / "report.md").is_file()
    assert json.loads((out / "metrics.json").read_text()) == doc
    with pytest.raises(UsageError, match="this demo is finished"):
        demo(out=out, resume=True, quiet=True)


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
    one_line_error(code, err, f"{out / summary}: output file already exists: this {experiment} is finished; to run "
                   "its failed runs (or more seeds) again, move")
    assert snapshot(out) == before


@pytest.mark.parametrize("experiment", ["ablation", "online"])
@pytest.mark.parametrize("what", ["unrelated", "other experiment"])
def test_experiments_refuse_a_folder_that_is_not_their_own_unfinished_one(tmp_path, monkeypatch, experiment, what):
    """An existing --out is continued only if it is the same command's unfinished experiment: a
    folder of notes (or a training run) and the other experiment's folder are refused in one line
    naming --out, before anything is written in them."""
    import virus_nerf.sim.command as sim_command

    def no_work(*args, **kwargs):
        raise AssertionError("work started in a folder that is not this experiment's")

    monkeypatch.setattr(sim_command, "simulate", no_work)
    monkeypatch.setattr(f"virus_nerf.experiments.{experiment}.run_all", no_work)
    out = tmp_path / "exp"
    out.mkdir()
    if what == "unrelated":
        (out / "notes.txt").write_text("my notes")
        expected = f"--out {out}: holds notes.txt, so it is not an unfinished {experiment}"
    else:
        other = "online" if experiment == "ablation" else "ablation"
        (out / "runs").mkdir()
        (out / "experiment.json").write_text(json.dumps({"command": other}))
        expected = f"--out {out}: holds another experiment (experiment.json says '{other}'), not an unfinished"
    before = snapshot(out)
    code, _, err = run_cli([experiment, "--out", out, "--quick"])
    one_line_error(code, err, expected)
    assert snapshot(out) == before


def test_an_experiment_folder_is_taken_new_or_continued(tmp_path):
    """A new folder gets the command's mark; one begun before the mark existed (only data/ and
    runs/) is continued and marked; a marked one is continued by the same command, and a finished
    one (a summary present) is refused."""
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.experiments.folder import marked_command, take_experiment_folder

    new = tmp_path / "new"
    take_experiment_folder(new, "online", [new / "online.json"])
    assert marked_command(new) == "online" and [p.name for p in new.iterdir()] == ["experiment.json"]
    take_experiment_folder(new, "online", [new / "online.json"])  # continued: unchanged
    assert marked_command(new) == "online"
    old = tmp_path / "old"
    (old / "runs" / "office").mkdir(parents=True)
    (old / "data").mkdir()
    take_experiment_folder(old, "ablation", [old / "ablation.md"])
    assert marked_command(old) == "ablation" and (old / "runs" / "office").is_dir()
    (old / "ablation.md").write_text("done")
    with pytest.raises(OutputExistsError, match="ablation.md: output file already exists"):
        take_experiment_folder(old, "ablation", [old / "ablation.md"])
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(OutputExistsError, match="a_file: output file already exists"):
        take_experiment_folder(a_file, "online", [a_file / "online.json"])


@pytest.mark.parametrize("experiment, first, then, fragment", [
    ("ablation", ["--quick", "--max-steps", "20"], ["--quick", "--max-steps", "500"],
     "this ablation was begun with --max-steps 20 (now 500)"),
    ("ablation", ["--quick"], ["--max-steps", "20"], "this ablation was begun with --quick True (now False)"),
    ("online", ["--quick", "--playback", "1"], ["--quick", "--playback", "0.5"],
     "this online was begun with --playback 1.0 (now 0.5)"),
])
def test_an_experiment_is_continued_only_with_the_settings_it_was_begun_with(tmp_path, monkeypatch, experiment,
                                                                            first, then, fragment):
    """An unfinished experiment continued with another budget, drive or config would mix runs of
    both in one table (and the summary would state the new settings): refused in one line naming
    the flag, before anything is written; the same settings (more seeds aside) continue it."""
    import virus_nerf.sim.command as sim_command

    class Stop(Exception):
        pass

    def stop_here(*args, **kwargs):
        raise Stop  # the folder was taken: no simulation, no training needed to see that

    monkeypatch.setattr(sim_command, "simulate", stop_here)
    out = tmp_path / "exp"
    from virus_nerf.cli import main

    with pytest.raises(Stop):
        main([experiment, "--out", str(out), *first])
    mark = json.loads((out / "experiment.json").read_text())
    before = snapshot(out)
    code, _, err = run_cli([experiment, "--out", out, *then])
    one_line_error(code, err, f"--out {out}: {fragment}", "give the same settings to continue it")
    assert snapshot(out) == before
    with pytest.raises(Stop):  # the same settings with more seeds: continued
        main([experiment, "--out", str(out), *first, "--seeds", "2"])
    assert json.loads((out / "experiment.json").read_text()) == mark


def test_a_run_without_ground_truth_killed_writing_its_map_resumes_to_the_same_map(tiny_office, tmp_path):
    """--gt none, killed while writing map/ after its last step (the budget reached, no metrics.json,
    a `.map.partial-*` left): the resume writes the same map from the frames it trained on (before:
    an empty mapper's map, 0 % known, and the run marked finished) and removes the partial folder."""
    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", run, "--config", cfg,
                            "--gt", "none", "--quiet"])
    assert code == 0, err
    first = json.loads((run / "map" / "snapshot.json").read_text())
    pgm = (run / "map" / "map.pgm").read_bytes()
    (run / "metrics.json").unlink()
    (run / "map").rename(run / ".map.partial-999999-killed")  # the map's folder as a killed writer leaves it
    code, _, err = run_cli(["train", "--out", run, "--resume", "--quiet"])
    assert code == 0, err
    again = json.loads((run / "map" / "snapshot.json").read_text())
    assert first["frames"] > 0 and again["frames"] == first["frames"] and again["map_known"] == first["map_known"] > 0
    assert (run / "map" / "map.pgm").read_bytes() == pgm
    assert not list(run.glob(".map.partial-*"))


def test_a_full_disk_before_the_first_checkpoint_says_the_run_is_gone(tiny_office, tmp_path, monkeypatch):
    """A new run whose first checkpoint does not fit is removed (nothing to resume): the one line
    says so and to run the command again, not "nothing was lost ... --resume"."""
    import errno

    from virus_nerf.trainer.loop import Trainer

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.run_dir / "checkpoint.pt"))

    monkeypatch.setattr(Trainer, "save_checkpoint", full)
    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    out = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", out, "--config", cfg,
                            "--quiet"])
    one_line_error(code, err, f"{out / 'checkpoint.pt'}: could not be written (No space left on device) before the "
                              f"run's first checkpoint, so {out} was removed (nothing to resume); free some space and "
                              "run the same `virus-nerf train` command again")
    assert not out.exists() and "--resume" not in err


# ------------------------------------------------------------------------------ issue 30: run folders
def _dead_pid() -> int:
    import subprocess

    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def test_a_failed_resume_leaves_the_run_as_it_was(run_copy, monkeypatch):
    """A batch whose rays cannot fit in memory is refused before any work; one that runs out of
    memory in its first step is one line too, and config.json keeps the run's own settings, so
    a plain --resume afterwards works (before: config.json got the new size and every later
    --resume died in MemoryError)."""
    from virus_nerf.trainer.loop import Trainer

    (run_copy / "metrics.json").unlink()
    before = snapshot(run_copy)
    # a machine of 128 GiB (a lent GPU server has that much; the check must not depend on this one's)
    monkeypatch.setattr("virus_nerf.utils.memory.memory_limit", lambda: 128 * 2**30)
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--batch-size", "1000000000"])
    one_line_error(code, err, "--batch-size 1000000000: a step may march up to 32 samples a ray (march.max_samples), "
                   "66518.8 GiB at 2232 bytes a sample", "this machine has 128.0 GiB; expected at most 962134 ")
    # the run's march.max_samples is 32: 64 GiB / (32 samples x 2232 bytes) = 962134.3 rays; 2 M rays
    # alone (96 bytes each, the old bound) would have passed, their samples do not
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--batch-size", "2000000"])
    one_line_error(code, err, "--batch-size 2000000: a step may march up to 32 samples a ray", "expected at most 962134 ")
    assert snapshot(run_copy) == before

    def out_of_memory(self):
        raise MemoryError("Unable to allocate 7.45 GiB for an array with shape (1000000000,)")

    monkeypatch.setattr(Trainer, "train_step", out_of_memory)
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--batch-size", "4096",
                            "--quiet"])
    one_line_error(code, err, "--batch-size 4096: a training step ran out of memory (Unable to allocate 7.45 GiB",
                   "expected a smaller --batch-size")
    after = snapshot(run_copy)
    for name in ("config.json", "checkpoint.pt", "train_log.csv", "run.json"):
        assert after[name] == before[name], name
    monkeypatch.undo()
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])  # the budget of 5: evaluates
    assert code == 0, err
    assert json.loads((run_copy / "metrics.json").read_text())["train"]["steps"] == 5


def test_resume_without_a_checkpoint_trains_from_step_0(run_copy):
    """Killed before its first checkpoint: config.json and run.json say how to start; --resume
    trains from step 0, keeps one log row per step and removes the plots folders of a killed
    attempt (before: refused, and a new run was refused too because the folder exists)."""
    for name in ("checkpoint.pt", "metrics.json", "metrics_vs_time.csv"):
        (run_copy / name).unlink()
    shutil.rmtree(run_copy / "plots")
    stale = [run_copy / ".plots.partial-12345-abc", run_copy / ".plots.old-xyz"]
    for p in stale:
        p.mkdir()
    with (run_copy / "train_log.csv").open("a", newline="") as fh:
        fh.write("6,0.1,1")  # torn by the kill
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])
    assert code == 0, err
    assert "no checkpoint yet (stopped before the first one); training from step 0" in err
    steps = [ln.split(",")[0] for ln in (run_copy / "train_log.csv").read_text().splitlines()[1:]]
    assert steps == ["2", "4", "5"]
    assert json.loads((run_copy / "metrics.json").read_text())["train"]["steps"] == 5
    assert not [p for p in stale if p.exists()]


def test_a_torn_log_row_is_dropped_and_a_damaged_one_named_on_resume(run_copy):
    (run_copy / "metrics.json").unlink()
    log = run_copy / "train_log.csv"
    good = log.read_bytes()
    log.write_bytes(good + b"8")  # the first character of a row, then the kill
    plots = {k: v for k, v in snapshot(run_copy).items() if k.startswith("plots/")}
    code, out, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--quiet", "--no-plots"])
    assert code == 0, err
    steps = [ln.split(",")[0] for ln in log.read_text().splitlines()[1:]]
    assert steps == ["2", "4", "5", "6", "7"]  # before: "890" ... fused rows
    # --no-plots on resume: the earlier plots are kept as they were, and said not to be this run's
    assert {k: v for k, v in snapshot(run_copy).items() if k.startswith("plots/")} == plots
    said = f"{run_copy / 'plots'}/ is from the run's earlier evaluation: plots are off, so they were not drawn again"
    assert said in json.loads((run_copy / "metrics.json").read_text())["warnings"][-1] and said in out
    (run_copy / "metrics.json").unlink()
    lines = good.decode().split("\r\n")
    lines[2] = "4,oops"
    log.write_bytes("\r\n".join(lines).encode())
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "9", "--quiet"])
    one_line_error(code, err, f"{log}, row 3: expected 14 comma-separated numbers")


def test_the_run_is_locked_while_a_process_trains_in_it(run_copy):
    """A second process on the same run folder (a --resume beside a running training or another
    --resume) is refused with the holder's pid; the lock goes with the holder however it dies
    (before: both ran and every log row appeared twice)."""
    import signal
    import subprocess
    import sys

    (run_copy / "metrics.json").unlink()
    before = snapshot(run_copy)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom virus_nerf.trainer.run_folder import RunLock\n"
         "RunLock(sys.argv[1]).acquire(); print('locked', flush=True); time.sleep(120)", str(run_copy)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--quiet"])
        one_line_error(code, err, f"--resume {run_copy}: the run is in use by another virus-nerf process "
                                  f"(pid {holder.pid}); wait for it to end or stop it")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    after = snapshot(run_copy)
    after.pop("run.lock"), before.pop("run.lock")  # holds the pid of the last process that trained here
    assert after == before
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--quiet"])  # the kill released it
    assert code == 0, err


def test_a_full_disk_is_one_line_and_keeps_the_last_checkpoint(run_copy, monkeypatch):
    """ENOSPC while writing a checkpoint (before: a RuntimeError `unexpected pos` traceback from
    torch.save writing straight into the file): one line naming checkpoint.pt, saying nothing was
    lost; the last good checkpoint stays and no temporary is left."""
    import errno
    import pathlib

    (run_copy / "metrics.json").unlink()
    ckpt = snapshot(run_copy)["checkpoint.pt"]
    real = pathlib.Path.write_bytes

    def full(self, data):
        if self.name.startswith(".checkpoint.pt."):
            real(self, bytes(data)[:1000])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    code, _, err = run_cli(["train", "--out", run_copy, "--resume", "--max-steps", "7", "--quiet"])
    one_line_error(code, err, f"{run_copy / 'checkpoint.pt'}: could not be written (No space left on device); "
                              "nothing was lost")
    assert snapshot(run_copy)["checkpoint.pt"] == ckpt
    assert not list(run_copy.glob(".checkpoint.pt.*"))


def test_a_full_disk_in_an_output_folder_names_the_final_path(tmp_path):
    import errno

    from virus_nerf.utils.io import new_output_dir, write_text_atomic

    with pytest.raises(OSError) as info:
        with new_output_dir(tmp_path / "map") as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "map.pgm"))
    assert info.value.filename == str(tmp_path / "map" / "map.pgm") and info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []

    def fail(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    import pathlib

    real = pathlib.Path.write_text
    pathlib.Path.write_text = fail
    try:
        with pytest.raises(OSError) as info:
            write_text_atomic(tmp_path / "a.json", "{}")
    finally:
        pathlib.Path.write_text = real
    assert info.value.filename == str(tmp_path / "a.json")


def test_stale_partial_folders_of_dead_processes_are_removed(tmp_path):
    import os

    from virus_nerf.utils.io import remove_stale_partials

    dead, alive = _dead_pid(), os.getppid()
    for name in (f".out.partial-{dead}-abc", f".out.old-{dead}-x", f".out.partial-{alive}-abc", ".out.partial-nopid",
                 f".other.partial-{dead}-abc"):
        (tmp_path / name).mkdir()
    removed = remove_stale_partials(tmp_path / "out")
    assert sorted(p.name for p in removed) == sorted([f".out.partial-{dead}-abc", f".out.old-{dead}-x"])
    assert sorted(p.name for p in remove_stale_partials(tmp_path / "out", owned=True)) == \
        sorted([f".out.partial-{alive}-abc", ".out.partial-nopid"])
    assert [p.name for p in tmp_path.iterdir()] == [f".other.partial-{dead}-abc"]


def test_evaluate_and_sensors_killed_before_their_metrics_finish_on_the_next_run(run_copy, tiny_office, tmp_path):
    """Plots written, metrics.json not (killed between them): the next run evaluates again,
    replaces the plots and writes metrics.json (before: refused, as the plots folder existed);
    `.partial-<pid>-*` folders of dead attempts are removed, a live process's are kept."""
    ev = run_copy / "evaluation"
    ev.mkdir()
    dead = _dead_pid()
    (ev / "metrics_plots").mkdir()
    (ev / "metrics_plots" / "scan_frame0001.png").write_bytes(b"from the killed attempt")
    (ev / f".metrics_plots.partial-{dead}-abc").mkdir()
    code, _, err = run_cli(["evaluate", "--run", run_copy, "--n-rays", "32"])
    assert code == 0, err
    assert (ev / "metrics.json").is_file() and (ev / "metrics_plots" / "metrics_bars.png").is_file()
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in (ev / "metrics_plots").iterdir())  # all drawn again
    assert sorted(p.name for p in ev.iterdir()) == ["metrics.json", "metrics_plots"]
    code, _, err = run_cli(["evaluate", "--run", run_copy])
    one_line_error(code, err, "evaluation/metrics.json: output file already exists")
    # --no-plots beside a killed attempt's plots: kept, and said not to be this evaluation's
    (tmp_path / "again_plots").mkdir()
    code, out, err = run_cli(["evaluate", "--run", run_copy, "--n-rays", "32", "--out", tmp_path / "again.json",
                              "--no-plots"])
    assert code == 0 and (tmp_path / "again.json").is_file() and list((tmp_path / "again_plots").iterdir()) == []
    assert f"warning: {tmp_path / 'again_plots'}/ is from an earlier evaluation stopped before its metrics.json" in out

    out = tmp_path / "sensors" / "metrics.json"
    (tmp_path / "sensors" / "metrics_plots").mkdir(parents=True)
    (tmp_path / "sensors" / f".metrics_plots.partial-{dead}-q").mkdir()
    code, _, err = run_cli(["sensors", "--data", tiny_office, "--room", "office", "--out", out, "--n-rays", "32"])
    assert code == 0, err
    assert sorted(p.name for p in out.parent.iterdir()) == ["metrics.json", "metrics_plots"]
    code, _, err = run_cli(["sensors", "--data", tiny_office, "--room", "office", "--out", out])
    one_line_error(code, err, f"{out}: output file already exists")


def test_a_new_run_removes_the_partial_folder_of_a_killed_start(tiny_office, tmp_path):
    dead = _dead_pid()
    partial = tmp_path / f".run.partial-{dead}-abc"
    partial.mkdir()
    (partial / "config.json").write_text("{}")
    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(max_steps=2))))
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", tmp_path / "run",
                            "--config", cfg, "--quiet"])
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "small.json"]
    assert (tmp_path / "run" / "run.lock").read_text().strip().isdigit()


def test_a_bad_flag_value_points_at_the_commands_own_help(tmp_path):
    code, _, err = run_cli(["train", "--data", tmp_path, "--room", "office", "--out", tmp_path / "r",
                            "--max-time", "abc"])
    one_line_error(code, err, "--max-time 'abc': expected a number (see virus-nerf train --help)")


def test_the_metric_vs_time_plot_names_its_ground_truth(tmp_path, monkeypatch):
    """plots/metric_vs_time.png draws one curve per protocol its points were scored against (a
    run resumed with another --gt continues under the new one: a review saw map's points drawn
    under the title "ground truth: exact") and names the zone's bounds."""
    from types import SimpleNamespace

    from virus_nerf.evaluation import plots
    from virus_nerf.evaluation.metrics import DEFAULT_ZONES
    from virus_nerf.trainer.report import write_run_plots
    from virus_nerf.trainer.run_folder import EvalPoint

    drawn = []
    monkeypatch.setattr(plots, "write_plot_files", lambda result, folder, max_maps: [])
    monkeypatch.setattr(plots, "plot_metric_vs_time", lambda curves, path, title: drawn.append((curves, title)))
    history = [EvalPoint(10, 10.0, 0.5, 0.6, 0.1, 0.1, 3, "map"), EvalPoint(20, 20.0, 0.4, 0.5, 0.2, 0.2, 3, "map"),
               EvalPoint(30, 30.0, 0.3, 0.4, 0.3, 0.3, 3, "exact")]
    write_run_plots(tmp_path / "run", SimpleNamespace(gt="exact", config=SimpleNamespace(zones=DEFAULT_ZONES)), history)
    (curves, title), = drawn
    assert title == "NeRF zone 3 (0-100 m) vs training time"
    assert {k: [e.step for e in v] for k, v in curves.items()} == {"NeRF, ground truth map": [10, 20],
                                                                   "NeRF, ground truth exact": [30]}


def test_evaluate_and_export_name_run_json_when_the_recording_moved_and_a_file_as_no_run(run_copy, tmp_path):
    """These commands have no --data: the error named one (it names run.json's field now); a --run
    that is a file was reported as an --out that cannot be made."""
    info = json.loads((run_copy / "run.json").read_text())
    info["data"] = str(tmp_path / "moved")
    (run_copy / "run.json").write_text(json.dumps(info))
    for argv in (["evaluate", "--run", run_copy], ["export", "--run", run_copy, "--out", tmp_path / "x", "--what", "map"]):
        code, _, err = run_cli(argv)
        line = one_line_error(code, err, f"{run_copy / 'run.json'}, field 'data': data {tmp_path / 'moved'}: no such "
                                         "folder; expected the recording the run was trained on")
        assert "--data" not in line
    assert not (tmp_path / "x").exists() and not (run_copy / "evaluation").exists()
    (tmp_path / "file").write_text("x")
    code, _, err = run_cli(["evaluate", "--run", tmp_path / "file"])
    one_line_error(code, err, f"--run {tmp_path / 'file'}: is a file; expected a run folder")
    code, _, err = run_cli(["export", "--run", run_copy, "--out", tmp_path / "y", "--poses", tmp_path])
    one_line_error(code, err, f"--poses {tmp_path}: a folder; expected a CSV")


def test_evaluate_of_a_run_stopped_part_way_says_so_as_export_does(run_copy, tmp_path):
    """A run without metrics.json of its checkpoint's step (stopped part-way) was scored without a
    word: the evaluation's metrics.json looked like a finished run's."""
    code, out, err = run_cli(["evaluate", "--run", run_copy, "--n-rays", "32", "--no-plots", "--out", tmp_path / "a.json"])
    assert code == 0, err
    assert "did not finish" not in out and not any("did not finish" in w for w in
                                                    json.loads((tmp_path / "a.json").read_text())["warnings"])
    (run_copy / "metrics.json").unlink()
    code, out, err = run_cli(["evaluate", "--run", run_copy, "--n-rays", "32", "--no-plots", "--out", tmp_path / "b.json"])
    assert code == 0, err
    step = json.loads((tmp_path / "b.json").read_text())["train"]["steps"]
    said = (f"the run's training did not finish (stopped at step {step}; no metrics.json of its last step): scored as "
            f"it stands (`virus-nerf train --resume --out {run_copy}` continues it)")
    assert f"note: --run {run_copy}: {said}" in out
    assert json.loads((tmp_path / "b.json").read_text())["warnings"][0] == said
