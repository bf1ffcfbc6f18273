"""`train`'s flags come from the config dataclasses (virus_nerf/config_flags.py): every knob has
one (`--optim.lr`, `--virus-grid.warmup-steps`), its help the field's comment; a flag given
replaces that one value of the --config file, a flag not given keeps it; a bad value is one
line naming the flag (the dataclass checks are the only range checks)."""

from __future__ import annotations

import dataclasses
import json
import re

import pytest
from helpers import run_cli, tiny_train_config

from virus_nerf.config_io import load_json_config, to_dict
from virus_nerf.trainer.command import _resolve_config, train_flags
from virus_nerf.trainer.config import TrainConfig

PREFIX = "virus-nerf: error: "


def resolve(*argv: str, config=None, base=None) -> TrainConfig:
    """The TrainConfig `train ARGV` would run, parsed as the command line parses it."""
    import tyro

    from virus_nerf.trainer.command import TrainFlags

    knobs = tyro.cli(TrainFlags, args=list(argv), default=TrainFlags())
    given, flags = train_flags(knobs)
    return _resolve_config(config, given, flags, base=base)


def test_a_flag_given_replaces_one_value_and_one_not_given_keeps_the_files(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"batch_size": 128, "max_time": 30.0,
                                "optim": {"lr": 0.001, "lr_decay_to": 0.2},
                                "virus_grid": {"warmup_steps": 50, "zeta": 0.5}}))
    cfg = resolve("--optim.lr", "0.005", "--virus-grid.warmup-steps", "500", "--max-steps", "9", config=path)
    assert cfg.optim.lr == 0.005 and cfg.optim.lr_decay_to == 0.2  # the section's other value: the file's
    assert cfg.virus_grid.warmup_steps == 500 and cfg.virus_grid.zeta == 0.5
    assert cfg.batch_size == 128 and cfg.max_steps == 9
    assert cfg.max_time == 30.0  # --max-steps with a --config: the file's time budget stays
    assert cfg.march == TrainConfig().march  # no flag, not in the file: the default
    assert resolve(config=path) == load_json_config(TrainConfig, path)  # no flag: the file as it is
    assert resolve() == TrainConfig()
    # a file that sets no time budget: --max-steps bounds the run by steps alone, as without a file
    path.write_text(json.dumps({"virus_grid": {"warmup_steps": 700}}))
    cfg = resolve("--max-steps", "9", config=path)
    assert (cfg.max_steps, cfg.max_time, cfg.virus_grid.warmup_steps) == (9, None, 700)
    assert resolve(config=path).max_time == TrainConfig().max_time  # no --max-steps: the default budget
    # --resume --config FILE: the file's keys over the run's own config, as flags are (not over the defaults)
    run = dataclasses.replace(TrainConfig(), batch_size=256, max_steps=40, max_time=None, plots=False, seed=7)
    path.write_text(json.dumps({"max_steps": 45, "optim": {"lr": 0.002}}))
    cfg = resolve(config=path, base=run)
    assert (cfg.max_steps, cfg.max_time, cfg.batch_size, cfg.plots, cfg.seed) == (45, None, 256, False, 7)
    assert cfg.optim.lr == 0.002 and cfg.optim.lr_decay_to == run.optim.lr_decay_to


def test_the_short_flags_are_the_derived_ones_and_keep_their_meaning():
    cfg = resolve("--max-steps", "7", "--sensors", "camera,irs,camera", "--grid", "ngp", "--online",
                  "--playback", "2", "--odometry-poses", "--image-scale", "1", "--seed", "3", "--batch-size", "64",
                  "--eval-interval", "5")
    assert (cfg.max_steps, cfg.max_time) == (7, None)  # --max-steps alone: a step-bounded run
    assert cfg.sensors == ("camera", "irs") and cfg.grid == "ngp" and cfg.online and cfg.odometry_poses
    assert (cfg.playback_speed, cfg.image_scale, cfg.seed, cfg.batch_size, cfg.eval_interval) == (2.0, 1.0, 3, 64, 5.0)
    assert resolve("--max-steps", "7", "--max-time", "60").max_time == 60.0
    resumed = resolve("--max-steps", "7", base=TrainConfig(max_time=30.0))
    assert resumed.max_time == 30.0  # with --resume, the run's own budget stays
    assert resolve("--no-online", base=TrainConfig(online=True)).online is False
    base = TrainConfig(max_samples_per_step=4096)
    cfg = resolve("--max-samples-per-step", "None", base=base)
    assert cfg.max_samples_per_step is None  # None given is a value, not "unset"
    cfg = resolve("--optim.betas", "0.8", "0.9", "--field.color-hidden", "32", "--stereo.tracker.window", "9")
    assert cfg.optim.betas == (0.8, 0.9) and cfg.field.color_hidden == (32,) and cfg.stereo.tracker.window == 9


def test_a_nested_flag_reaches_config_json(tiny_office, tmp_path):
    """Checked by hand: the run's config.json holds the flag's value, the file's value where no
    flag was given, and the defaults below both."""
    path = tmp_path / "small.json"
    small = tiny_train_config(max_steps=2)
    path.write_text(json.dumps(to_dict(small)))
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", tmp_path / "run",
                            "--config", path, "--quiet", "--optim.lr", "0.005", "--virus-grid.rays-per-update", "32"])
    assert code == 0, err
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["optim"]["lr"] == 0.005 and saved["virus_grid"]["rays_per_update"] == 32  # the flags
    assert saved["virus_grid"]["warmup_steps"] == 16 and saved["batch_size"] == 128  # the file's
    assert saved["optim"]["lr_decay_to"] == 0.1 and saved["march"]["near"] == 0.05  # the defaults
    assert "step_size" not in saved["ngp_grid"]  # removed: the marcher's step sets the NGP threshold
    # the file's plots off: a finished run (metrics.json) without plots/
    assert saved["plots"] is False and (tmp_path / "run" / "metrics.json").is_file()
    assert not (tmp_path / "run" / "plots").exists()


def test_plots_must_be_a_bool():
    from virus_nerf.trainer.config import TrainConfig

    with pytest.raises(ValueError, match="plots 'no': expected a bool"):
        TrainConfig(plots="no")


@pytest.mark.parametrize("extra, line", [
    (("--optim.lr", "-1"), "--optim.lr -1.0: expected a finite number > 0"),
    (("--optim.lr", "abc"), "--optim.lr 'abc': expected a number"),
    (("--virus-grid.warmup-steps", "0"), "--virus-grid.warmup-steps 0: expected an integer >= 1"),
    (("--virus-grid.threshold-alpha", "1"), "--virus-grid.threshold-alpha 1.0: expected a finite number in (0, 1)"),
    (("--stereo.max-range", "0.1"), "--stereo.max-range 0.1: expected a finite number > 0.3"),
    (("--march.backend", "gpu"), "--march.backend 'gpu': expected 'auto', 'numba' or 'torch'"),
    (("--march.step-size", "0"), "--march.step-size 0.0: expected a finite number >= 0.0001"),
    (("--evaluation.n-rays", "0"), "--evaluation.n-rays 0: expected an integer in [1, 1000000]"),
    (("--field.log2-table-size", "40"), "--field.log2-table-size: log2_table_size must be in [4, 30], got 40"),
    (("--shares.irs", "0.7", "--shares.uss", "0.7"),
     "--shares.irs 0.7 + --shares.uss 0.7 + shares.stereo 0.1: expected a sum <= 1"),
    (("--max-time", "None"), "max_steps and --max-time are both None"),
    (("--virus-grid.init", "all"), "invalid choice 'all' for argument '--virus-grid.init'"),
    # an online run lasts its drive: the budget would be ignored (a user's review: 20 s trained 4.8 s)
    (("--online", "--max-time", "20"), "--max-time 20: an online run (--online) lasts its drive, the recording's "
                                       "duration / --playback; drop --max-time (--max-steps still bounds it)"),
])
def test_a_bad_flag_is_one_line_naming_it(tmp_path, extra, line):
    code, _, err = run_cli(["train", "--data", tmp_path / "no-data", "--room", "office", "--out", tmp_path / "run",
                            *extra])
    assert code == 2 and err.count("\n") == 1 and err.startswith(PREFIX) and line in err, err
    assert "Traceback" not in err and not (tmp_path / "run").exists()


def test_a_flag_clashing_with_the_config_file_names_the_flag(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"shares": {"irs": 0.5}}))
    code, _, err = run_cli(["train", "--data", tmp_path / "no-data", "--room", "office", "--out", tmp_path / "run",
                            "--config", path, "--shares.uss", "0.6"])
    assert code == 2 and "shares.irs 0.5 + --shares.uss 0.6 + shares.stereo 0.1: expected a sum <= 1" in err, err


def test_help_lists_the_product_knobs_and_help_all_every_knob():
    from virus_nerf.trainer.config import PRODUCT_KNOBS

    code, short, err = run_cli(["train", "--help"])
    assert code == 0 and err == ""
    shown = set(re.findall(r"(?m)^ {2}(--[a-z][a-z0-9.-]*[a-z0-9])", short))  # options start indented
    knobs = {"--" + ("playback" if k == "playback_speed" else k.replace("_", "-")) for k in PRODUCT_KNOBS}
    assert knobs <= shown and "--sensors NAMES" in short and "--help-all lists every knob" in " ".join(short.split())
    assert "--optim.eps" not in shown and "--virus-grid.zeta" not in shown and "--stereo.tracker.window" not in shown
    command_flags = {"--out", "--data", "--room", "--config", "--resume", "--no-resume", "--quiet", "--no-quiet",
                     "--gt", "--playback-speed", "--help", "--no-online", "--no-odometry-poses"}
    assert shown - command_flags == knobs, shown - command_flags - knobs
    assert len(PRODUCT_KNOBS) <= 25


def test_help_all_lists_every_knob_with_its_comment():
    code, out, err = run_cli(["train", "--help-all"])
    assert code == 0 and err == ""
    assert "--optim.lr FLOAT" in out and "Adam's learning rate" in out
    assert "--virus-grid.warmup-steps INT" in out and "training steps (not updates) of the decay init -> prior." in out
    assert "(default: 660)" in out and "virus-grid options" in out

    def paths(doc: dict, prefix: str = ""):
        for key, value in doc.items():
            if isinstance(value, dict):
                yield from paths(value, f"{prefix}{key}.")
            else:
                yield prefix + key

    flags = {"playback_speed": "--playback", "evaluation.gt": "--gt", "evaluation.zones": None}
    for path in paths(to_dict(TrainConfig())):
        flag = flags.get(path, "--" + path.replace("_", "-"))
        assert flag is None or f" {flag} " in out or f" {flag}," in out, path


def test_a_removed_switch_loads_at_the_value_the_method_keeps_and_is_refused_at_another(tmp_path, capsys):
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"virus_grid": {"threshold_mode": "mean", "init_stereo": "off", "warmup_steps": 64},
                                "field": {"density_bias": 0.0}}))
    cfg = load_json_config(TrainConfig, path)
    assert cfg.virus_grid.warmup_steps == 64
    note = capsys.readouterr().err
    assert note == (f"virus-nerf: note: {path}: keys 'field.density_bias', 'virus_grid.threshold_mode', "
                    "'virus_grid.init_stereo' ignored (no longer read: measured and not kept, docs/decisions.md D52)\n")
    path.write_text(json.dumps({"virus_grid": {"threshold_mode": "fixed"}}))
    with pytest.raises(ValueError, match=r"key 'virus_grid.threshold_mode': string \"fixed\": this switch was removed "
                                         r"\(measured and not kept, docs/decisions.md D52\); the method now always "
                                         r"runs as with \"mean\""):
        load_json_config(TrainConfig, path)
    assert capsys.readouterr().err == ""


def test_an_old_config_with_a_removed_key_still_loads(tmp_path, capsys):
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"ngp_grid": {"step_size": 0.01, "warmup_steps": 64}}))
    cfg = load_json_config(TrainConfig, path)
    assert cfg.ngp_grid.warmup_steps == 64
    note = capsys.readouterr().err
    assert note.count("\n") == 1 and f"{path}: key 'ngp_grid.step_size' ignored (no longer read" in note
    path.write_text(json.dumps({"ngp_grid": {"step_size": 0.01, "warmup_steps": -1}}))
    with pytest.raises(ValueError, match="ngp_grid.warmup_steps -1"):
        load_json_config(TrainConfig, path)
    assert capsys.readouterr().err == ""  # a bad file: the error alone


def test_a_run_saved_before_a_key_was_added_loads_at_the_value_it_was_made_with(tmp_path):
    # a run's config.json holds every key of its version: one without extent.fitted_frame was
    # trained with the field over the box per axis, whatever today's default is
    from virus_nerf.config_io import to_dict

    old = to_dict(TrainConfig())
    del old["extent"]["fitted_frame"]
    for key in ("free_stereo", "free_stereo_short", "free_stereo_room_m"):  # before D77
        del old["weights"][key]
    for key in ("small_room_min_views", "small_room_max_rel_sigma"):  # before D112
        del old["stereo"][key]
    path = tmp_path / "config.json"
    path.write_text(json.dumps(old))
    loaded = load_json_config(TrainConfig, path, saved=True)
    assert loaded.extent.fitted_frame == "box" and loaded.weights.free_stereo == 0.0
    assert (loaded.stereo.small_room_min_views, loaded.stereo.small_room_max_rel_sigma) == (4, 0.03)
    # a user's partial config file takes today's default
    path.write_text(json.dumps({"extent": {"mode": "fitted"}}))
    cfg = load_json_config(TrainConfig, path)
    assert cfg.extent.fitted_frame == TrainConfig().extent.fitted_frame and cfg.weights.free_stereo == 40.0


def test_a_comment_after_a_field_describes_the_next_field_only():
    """A block comment shared by fields (free_uss, free_margin) ends at the next
    comment: `weights.distortion` gets its own comment, not the block above it."""
    from virus_nerf.config_flags import field_comments
    from virus_nerf.losses import LossWeights

    comments = field_comments(LossWeights)
    assert comments["free_margin"].startswith("line-of-sight emptiness")
    assert comments["distortion"].startswith("interval distortion")


def test_a_sensor_named_twice_in_a_file_is_taken_once(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"sensors": ["camera", "irs", "camera"]}))
    assert resolve(config=path).sensors == ("camera", "irs")


@pytest.mark.slow
def test_an_image_scale_leaving_fewer_than_8_pixels_trains(tiny_office, tmp_path):
    """--image-scale 0.01 of 160x120 px images: 2x1 px frames (the refusal is for less than 1x1);
    the kernels' warm-up took 8 pixels of the first frame and ended in an IndexError."""
    from helpers import run_cli, tiny_train_config

    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(max_steps=2))))
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", tmp_path / "run", "--config",
                            cfg, "--image-scale", "0.01", "--quiet"])
    assert code == 0, err
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["train"]["steps"] == 2


def test_a_runs_config_json_passed_back_rebuilds_that_run(tmp_path):
    """A run's config.json written before a key was added (here D77's weights.free_stereo and
    D112's small-room filters) loads, with --config, at the values that run was made with, as
    `evaluate` and `--resume` load it; a file of a few keys keeps today's defaults."""
    from virus_nerf.config_io import to_dict

    doc = to_dict(TrainConfig())
    del doc["weights"]["free_stereo"], doc["stereo"]["small_room_min_views"]
    run = tmp_path / "old_run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(doc))
    (run / "run.json").write_text("{}")
    cfg = resolve(config=run / "config.json")
    assert (cfg.weights.free_stereo, cfg.stereo.small_room_min_views) == (0.0, 4)
    partial = tmp_path / "mine.json"
    partial.write_text(json.dumps({"weights": {"irs": 1.0}, "stereo": {}}))
    cfg = resolve(config=partial)
    assert cfg.weights.free_stereo == TrainConfig().weights.free_stereo
    assert cfg.stereo.small_room_min_views == TrainConfig().stereo.small_room_min_views
    # a review: map-bag --config and tune --config read a run's config.json with today's defaults
    # for the added keys; they read it as train does now (a copy elsewhere is any config file)
    from virus_nerf.experiments.tune import _base_config
    from virus_nerf.mapping.options import load_stream_config

    assert load_stream_config(run / "config.json").weights.free_stereo == 0.0
    assert _base_config(run / "config.json", None, None, None)["weights"]["free_stereo"] == 0.0
    copy = tmp_path / "copied.json"
    copy.write_text((run / "config.json").read_text())
    assert load_stream_config(copy).weights.free_stereo == TrainConfig().weights.free_stereo


def test_a_missing_ros_extra_names_the_command_that_needs_it(tmp_path, monkeypatch):
    """A review: map-bag without rosbags said "import-bag needs rosbags"; KISS-ICP is needed only
    for --poses lidar-odometry."""
    import importlib.util

    from helpers import run_cli

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in ("rosbags", "kiss_icp") else real(name, *a))
    bag = tmp_path / "drive.bag"
    bag.write_bytes(b"x")
    extra = "(not installed): pip install -e '.[ros]' in the virus-nerf repository\n"
    for argv, needs in ((["map-bag", bag], "map-bag needs rosbags and kiss_icp"),
                        (["map-bag", bag, "--poses", "tf", "--import-first"], "map-bag needs rosbags"),
                        (["import-bag", bag, "--poses", "tf"], "import-bag needs rosbags")):
        code, _, err = run_cli([*argv, "--out", tmp_path / "out"])
        assert (code, err) == (2, f"virus-nerf: error: {needs} {extra}"), argv
        assert not (tmp_path / "out").exists()

