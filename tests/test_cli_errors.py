"""Every user mistake on the command line or in a config file: exit code 2, one line on stderr
(`virus-nerf: error: ...`) naming the argument, file or key and what was expected, no
traceback, and no output written. All rejected before any recording is read or training starts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from virus_nerf.cli import tyro_error_line
from virus_nerf.config_io import from_dict, load_json_config, to_dict
from virus_nerf.errors import ConfigError, UsageError
from virus_nerf.trainer.config import TrainConfig

PREFIX = "virus-nerf: error: "


def assert_one_line_error(code: int, err: str, *fragments: str) -> str:
    assert code == 2, err
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1, err
    assert lines[0].startswith(PREFIX), err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


# ------------------------------------------------------------------------------ argument ranges
def train_args(tmp_path: Path, *extra: str) -> list[str]:
    return ["train", "--data", str(tmp_path / "no-data"), "--room", "office", "--out", str(tmp_path / "run"), *extra]


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (("--batch-size", "0"), "--batch-size 0: expected an integer >= 1"),
        (("--max-time", "-5"), "--max-time -5.0: expected a finite number > 0 or None"),
        (("--max-time", "0"), "--max-time 0.0: expected a finite number > 0 or None"),
        (("--max-time", "nan"), "--max-time nan: expected a finite number > 0"),
        (("--max-steps", "0"), "--max-steps 0: expected an integer >= 1"),
        (("--seed", "-1"), "--seed -1: expected an integer in [0, 4294967295]"),
        (("--image-scale", "0"), "--image-scale 0.0: expected a finite number in (0, 1]"),
        (("--image-scale", "2"), "--image-scale 2.0: expected a finite number in (0, 1]"),
        (("--playback", "0"), "--playback 0.0: expected a finite number > 0"),
        (("--eval-interval", "-1"), "--eval-interval -1.0: expected a finite number >= 0"),
        (("--sensors", "camera,lidar"), "--sensors 'camera,lidar': unknown sensor 'lidar'; expected a comma-separated"),
        (("--sensors", ","), "--sensors ',': an empty sensor name"),
        (("--batch-size", "abc"), "--batch-size 'abc': expected an integer"),
        (("--max-time", "fast"), "--max-time 'fast': expected a number"),
        (("--grid", "voxel"), "invalid choice 'voxel' for argument '--grid'"),
        (("--gt", "lidar"), "--gt 'lidar': unknown protocol 'lidar'; expected one or more of map,exact,paper, "
                            "comma-separated (e.g. map,exact), or none"),
        (("--gt", "map,map"), "--gt 'map,map': a protocol named twice"),
        (("--bogus", "1"), "Unrecognized options: --bogus"),
    ],
)
def test_train_argument_errors(tmp_path, extra, fragment):
    code, _, err = run_cli(train_args(tmp_path, *extra))
    assert_one_line_error(code, err, fragment)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--resolution", "0"], ["--resolution 0.0: expected a number > 0"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--n-rays", "0"], ["--n-rays 0: expected an integer in [1,"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map"], ["--run {tmp}/run: no such run folder"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--what", "map,bogus"],
         ["--what 'map,bogus': unknown export 'bogus'; expected 'all' or a comma-separated subset of map,prob,grid3d"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--what", "map,,esdf"], ["--what 'map,,esdf': an empty name"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--band", "-1"], ["--band -1.0: expected a number in [0, 10]"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--max-poses", "0"], ["--max-poses 0: expected an integer >= 1"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--cloud-points", "0"], ["--cloud-points 0: expected an integer in [1,"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--image-scale", "1.5"], ["--image-scale 1.5: expected a number in (0, 1]"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--poses", "{tmp}/p.csv"], ["--poses {tmp}/p.csv: no such file"]),
        (["export", "--run", "{tmp}/run", "--out", "{tmp}/map", "--resolution", "x"], ["--resolution 'x': expected a number"]),
        (["evaluate", "--run", "{tmp}/run", "--n-rays", "0"], ["--n-rays 0: expected an integer in [1,"]),
        (["evaluate", "--run", "{tmp}/run"], ["--run {tmp}/run: no such run folder"]),
        (["simulate", "--scene", "office", "--out", "{tmp}/sim", "--duration", "-1"], ["--duration -1.0: expected a number in (0, 3600]"]),
        (["simulate", "--scene", "office", "--out", "{tmp}/sim", "--seed", "-3"], ["--seed -3: expected an integer in [0,"]),
        (["simulate", "--scene", "kitchen", "--out", "{tmp}/sim"], ["invalid choice 'kitchen' for argument '--scene'"]),
        (["sensors", "--data", "{tmp}/d", "--room", "office", "--out", "{tmp}/m.json", "--n-rays", "0"], ["--n-rays 0"]),
        (["demo", "--out", "{tmp}/demo", "--train-time", "0"], ["--train-time 0.0: expected a number > 0"]),
        (["ablation", "--out", "{tmp}/abl", "--seeds", "0"], ["--seeds 0: expected an integer in [1, 1000]"]),
        (["ablation", "--out", "{tmp}/abl", "--scenes", "kitchen"], ["--scenes 'kitchen': expected one or more of office, common, warehouse (space-separated)"]),
        (["online", "--out", "{tmp}/onl", "--playback", "0"], ["--playback 0.0: expected a number > 0"]),
        (["sensors", "--data", "{tmp}/d", "--room", "office", "--out", "{tmp}/m.json", "--gt", "voxels"],
         ["--gt 'voxels': unknown protocol 'voxels'"]),
        (["evaluate", "--run", "{tmp}/run", "--gt", "exact,lidar"], ["--gt 'exact,lidar': unknown protocol 'lidar'"]),
        (["demo", "--out", "{tmp}/demo", "--gt", "mesh"], ["--gt 'mesh': unknown protocol"]),
        (["ablation", "--out", "{tmp}/abl", "--gt", "mesh"], ["--gt 'mesh': unknown protocol"]),
        (["online", "--out", "{tmp}/onl", "--gt", "mesh"], ["--gt 'mesh': unknown protocol"]),
        # commands that exist to compare with a ground truth: none is refused before any work
        (["sensors", "--data", "{tmp}/d", "--room", "office", "--out", "{tmp}/m.json", "--gt", "none"],
         ["--gt none: nothing to score; give --gt map, exact or paper"]),
        (["demo", "--out", "{tmp}/demo", "--gt", "none"], ["--gt none: nothing to score"]),
        (["ablation", "--out", "{tmp}/abl", "--gt", "none"], ["--gt none: nothing to score"]),
        (["online", "--out", "{tmp}/onl", "--gt", "none"], ["--gt none: nothing to score"]),
        (["evaluate", "--run", "{tmp}/run", "--gt", "none"], ["--gt none: nothing to score"]),
        (["train", "--out", "{tmp}/run"], ["--data is required"]),
        (["train", "--out", "{tmp}/run", "--resume"], ["--resume {tmp}/run: no such run folder"]),
        (["train", "--data", "{tmp}", "--room", "../x", "--out", "{tmp}/run"], ["--room '../x': expected the name of a room"]),
        # every command that reads a room of --data takes a name, not a path (one check)
        (["sensors", "--data", "{tmp}", "--room", "../x", "--out", "{tmp}/m.json"], ["--room '../x': expected the name"]),
        (["sensors", "--data", "{tmp}", "--room", "", "--out", "{tmp}/m.json"], ["--room '': expected the name of a room"]),
        (["tune", "--data", "{tmp}", "--room", "../x", "--study", "s", "--trials", "1", "--out", "{tmp}/t"],
         ["--room '../x': expected the name of a room"]),
        (["import-bag", "{tmp}/b.bag", "--out", "{tmp}/d", "--room", ""], ["--room '': expected letters, digits"]),
        (["train", "--data", "{tmp}/nope", "--room", "office", "--out", "{tmp}/run"],
         ["{tmp}/nope: no such folder; expected the dataset folder that holds the room folders (--data)"]),
        (["trian"], ["Unrecognized options: trian", "Available subcommands"]),
        ([], ["missing command"]),
        (["train", "--data", "x"], ["virus-nerf train: missing required argument(s) --out PATH"]),
        (["import-bag", "--out", "{tmp}/d"], ["virus-nerf import-bag: missing required argument(s) PATH (the "
                                             "positional argument: ROS 1 .bag file, ROS 2 bag folder"]),
    ],
)
def test_command_errors(tmp_path, argv, fragments):
    argv = [a.format(tmp=tmp_path) for a in argv]
    code, _, err = run_cli(argv)
    assert_one_line_error(code, err, *[f.format(tmp=tmp_path) for f in fragments])
    assert sorted(tmp_path.iterdir()) == []  # nothing was written


@pytest.mark.parametrize("command", ["demo", "sensors", "ablation", "online"])
def test_a_command_that_scores_offers_no_gt_none(tmp_path, command):
    """A user's review: the error offered `none`, which the next try was refused (nothing to score)."""
    data = ["--data", tmp_path / "d", "--room", "office"] if command == "sensors" else []
    code, _, err = run_cli([command, *data, "--out", tmp_path / "o", "--gt", "mesh"])
    assert_one_line_error(code, err)
    assert err.endswith("--gt 'mesh': unknown protocol 'mesh'; expected one or more of map,exact,paper, "
                        "comma-separated (e.g. map,exact)\n"), err


@pytest.mark.parametrize("argv", [["demo"], ["ablation", "--quick"], ["online", "--quick"]])
def test_an_out_under_a_file_is_one_line_before_any_work(tmp_path, argv):
    """A user's review: `File exists` or `Not a directory` without the flag (evaluate's after 10 s
    of loading), as train, simulate, export and map-bag already said."""
    (tmp_path / "notes.txt").write_text("a file")
    out = tmp_path / "notes.txt" / "sub"
    code, _, err = run_cli([*argv, "--out", out])
    assert_one_line_error(code, err, f"--out {out}: cannot be made: {tmp_path / 'notes.txt'} is a file, not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_existing_output_refused_before_any_work(tmp_path):
    (tmp_path / "map").mkdir()
    code, _, err = run_cli(["export", "--run", str(tmp_path / "no-run"), "--out", str(tmp_path / "map")])
    assert_one_line_error(code, err, f"{tmp_path / 'map'}: output folder already exists")


@pytest.mark.parametrize("flag, name", [("--out-bag", "maps_bag"), ("--rerun-save", "live.rrd")])
def test_an_existing_sink_names_its_own_flag(tmp_path, flag, name):
    """map-bag's other outputs: an existing one is refused naming the flag to change, not --out."""
    bag = tmp_path / "in.bag"
    bag.write_bytes(b"not read: refused before")
    (tmp_path / name).write_text("an earlier output")
    code, _, err = run_cli(["map-bag", str(bag), "--out", str(tmp_path / "out"), flag, str(tmp_path / name)])
    assert_one_line_error(code, err, f"{tmp_path / name}: output file already exists; choose a new {flag} "
                                     "(nothing was overwritten)")
    assert not (tmp_path / "out").exists() and (tmp_path / name).read_text() == "an earlier output"


@pytest.mark.parametrize("extra, fragment", [
    (["--map-frame", "odom"], "--map-frame and --base-frame name the frames of --out-bag's maps and /tf: "
                              "give --out-bag DIR"),
    (["--out-bag", "{tmp}/b", "--map-frame", "/map"], "--map-frame '/map': not a tf2 frame id"),
    (["--out-bag", "{tmp}/b", "--base-frame", "map"], "--map-frame and --base-frame are both 'map'"),
])
def test_map_bag_frames_are_checked_before_any_work(tmp_path, extra, fragment):
    """--map-frame/--base-frame: tf2 names, two of them, and only with --out-bag, whose frames they name."""
    bag = tmp_path / "in.bag"
    bag.write_bytes(b"not read: refused before")
    code, _, err = run_cli(["map-bag", str(bag), "--out", str(tmp_path / "out"),
                            *[a.format(tmp=tmp_path) for a in extra]])
    assert_one_line_error(code, err, fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.bag"]


def test_help_into_a_closed_pipe_ends_quietly():
    """`virus-nerf train --help | head`: the reader is gone before the help is written; the
    command ends with 141 (as SIGPIPE ends a Unix tool), no BrokenPipeError traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "virus_nerf.cli", "train", "--help-all"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # before the interpreter has started: every write of the help meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == ""


def test_real_process_prints_one_line_and_exits_2(tmp_path):
    """The console entry point itself: exit status 2 and a single stderr line (no tyro box)."""
    for extra in (("--batch-size", "0"), ("--batch-size", "x")):
        proc = subprocess.run([sys.executable, "-m", "virus_nerf.cli", *train_args(tmp_path, *extra)],
                              capture_output=True, text=True, timeout=120)
        assert_one_line_error(proc.returncode, proc.stderr, "--batch-size")
        assert proc.stdout == ""


def test_help_still_works():
    code, out, err = run_cli(["train", "--help"])
    assert code == 0 and "--max-steps" in out and err == ""


def test_the_top_level_help_gives_one_line_per_command():
    from virus_nerf.cli import _commands, _summary

    code, out, err = run_cli(["--help"])
    assert code == 0 and err == ""
    listed = " ".join(out.replace("\u2502", " ").split())
    for name, fn in _commands().items():
        assert f"\u2022 {name} {_summary(fn)}" in listed, name
    assert "Writes OUT/" not in out  # the paragraphs stay in each command's own --help
    code, out, _ = run_cli(["simulate", "--help"])
    assert code == 0 and "Writes OUT/camera_intrinsics.CSV" in out


def test_a_command_spelt_with_underscores_is_the_command():
    """tyro takes `map_bag` for `map-bag`: so does the command table (only the chosen module is imported)."""
    code, _, err = run_cli(["ros2_play"])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "ros2-play: missing required argument(s) PATH" in err
    code, out, _ = run_cli(["import_bag", "--help"])
    assert code == 0 and "--topics" in out


def test_ros2_play_refuses_a_bad_clock_rate_in_one_line(tmp_path):
    for value in ("0", "-1", "nan"):
        code, _, err = run_cli(["ros2-play", str(tmp_path), "--clock", "--clock-hz", value])
        assert code == 2 and len(err.strip().splitlines()) == 1 and "--clock-hz" in err and "> 0" in err, err


def test_the_top_level_help_without_the_sources_imports_the_commands(monkeypatch):
    """An installation without the modules' sources (no spec origin to read) lists the same lines."""
    import importlib.util

    _, listed, _ = run_cli(["--help"])
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, package=None: None)
    code, out, err = run_cli(["--help"])
    assert code == 0 and err == "" and out == listed


def test_the_help_and_a_misspelt_command_import_no_other_command():
    """`virus-nerf --help`, a misspelt command and `simulate --help` import the chosen command's
    module alone: no torch and no matplotlib (every command module at once took 6 s on a 2-core
    machine before the first line of output)."""
    code = ("import sys\nfrom virus_nerf.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print('loaded:', *sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'matplotlib') "
            "or m.endswith('.command')))")
    for argv, loaded in ((["--help"], set()), (["trian"], set()), (["simulate", "--help"], {"virus_nerf.sim.command"})):
        out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True)
        assert set(out.stdout.rsplit("loaded:", 1)[1].split()) == loaded, argv


def test_tyro_box_becomes_one_line():
    box = ("\u256d\u2500 Value error \u2500\u2500\u256e\n"
           "\u2502 Error parsing --batch-size: no type matching {None}|INT could be  \u2502\n"
           "\u2502 instantiated from ['abc'].  \u2502\n"
           "\u2502 \u2500\u2500\u2500\u2500\u2500\u2500 \u2502\n"
           "\u2502 For full helptext, see virus-nerf --help \u2502\n"
           "\u2570\u2500\u2500\u256f\n")
    assert tyro_error_line(box) == "--batch-size 'abc': expected an integer (see virus-nerf --help)"
    assert tyro_error_line("something unexpected\non two lines") == "something unexpected on two lines"


# ------------------------------------------------------------------------------ config files
def write_config(tmp_path: Path, doc) -> Path:
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return p


@pytest.mark.parametrize(
    "doc, fragment",
    [
        ({"online": "false"}, "key 'online': expected a JSON bool (true or false), got string \"false\""),
        ({"online": 0}, "key 'online': expected a JSON bool (true or false), got int 0"),
        ({"batch_size": "2048"}, "key 'batch_size': expected an integer, got string \"2048\""),
        ({"batch_size": 20.5}, "key 'batch_size': expected an integer, got float 20.5"),
        ({"batch_size": True}, "key 'batch_size': expected an integer, got bool true"),
        ({"max_steps": "5"}, "key 'max_steps': expected an integer or null, got string \"5\""),
        ({"max_time": "10"}, "key 'max_time': expected a number or null, got string \"10\""),
        ({"grid": "voxel"}, "key 'grid': expected one of \"virus\", \"ngp\", got string \"voxel\""),
        ({"sensors": "camera"}, "key 'sensors': expected a list, got string \"camera\""),
        ({"sensors": ["camera", 3]}, "key 'sensors[1]': expected a string, got int 3"),
        ({"optim": {"betas": [0.9, "x"]}}, "key 'optim.betas[1]': expected a number, got string \"x\""),
        ({"optim": {"betas": [0.9]}}, "key 'optim.betas': expected a list of 2 values, got 1"),
        ({"optim": 3}, "key 'optim': expected a JSON object with the keys of OptimConfig, got int 3"),
        ({"evaluation": {"zones": [{"name": "z", "lo": "0", "hi": 1}]}}, "key 'evaluation.zones[0].lo': expected a number"),
        ({"evaluation": {"gt": ["voxels"]}},
         "key 'evaluation.gt[0]': expected one of \"map\", \"exact\", \"paper\", got string \"voxels\""),
        ({"evaluation": {"gt": ["map", "map"]}}, "key 'evaluation.gt': evaluation.gt ('map', 'map'): expected distinct protocols"),
        ({"march": {"stepsize": 0.1}}, "key 'march': unknown key(s) ['stepsize'] (did you mean 'step_size'?)"),
        ({"bogus": 1}, "unknown key(s) ['bogus']"),
        ({"max_steps": 0}, "max_steps 0: expected an integer >= 1"),
        ({"batch_size": -1}, "batch_size -1: expected an integer >= 1"),
        ({"march": {"step_size": 0}}, "march.step_size 0.0: expected a finite number >= 0.0001"),
        ({"virus_grid": {"update_interval": 0}},
         "key 'virus_grid.update_interval': virus_grid.update_interval 0: expected an integer >= 1"),
        ({"field": {"log2_table_size": 40}}, "key 'field.log2_table_size': log2_table_size must be in [4, 30], got 40"),
        ({"optim": {"lr": None}}, "key 'optim.lr': expected a number, got null"),
        ({"batch_size": 2048.5}, "key 'batch_size': expected an integer, got float 2048.5"),
        ({"max_steps": None, "max_time": None}, "set max_steps or max_time"),
        ({"device": "tpu"}, "device 'tpu': expected 'auto', 'cpu', 'cuda'"),
        ({"threads": 0}, "threads 0: expected an integer in [1, 4096] or None"),
        ([1, 2], "expected a JSON object with the keys of TrainConfig, got list [1, 2]"),
        ("{not json", "not valid JSON: Expecting property name enclosed in double quotes at line 1 column 2"),
        ('{"max_time": NaN}', "key 'max_time': expected a number or null, got float NaN"),
    ],
)
def test_config_file_errors_name_file_and_key(tmp_path, doc, fragment):
    path = write_config(tmp_path, doc)
    with pytest.raises(ConfigError) as exc:
        load_json_config(TrainConfig, path)
    assert str(exc.value).startswith(str(path)) and fragment in str(exc.value)
    assert isinstance(exc.value, ValueError) and "\n" not in str(exc.value)
    code, _, err = run_cli(train_args(tmp_path, "--config", str(path)))
    assert_one_line_error(code, err, str(path), fragment)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "doc, fragment",
    [
        ({"grid": "ngp", "ngp_grid": {"max_resolution": 0}}, "ngp_grid.max_resolution 0: expected an integer >= 1"),
        ({"ngp_grid": {"min_alpha": 0}}, "ngp_grid.min_alpha 0.0: expected a finite number in (0, 1)"),
        ({"ngp_grid": {"min_alpha": 1}}, "ngp_grid.min_alpha 1.0: expected a finite number in (0, 1)"),
        ({"ngp_grid": {"decay": -1}}, "ngp_grid.decay -1.0: expected a finite number in (0, 1]"),
        ({"ngp_grid": {"chunk_size": 0}}, "ngp_grid.chunk_size 0: expected an integer >= 1"),
        ({"shares": {"irs": 2.0}}, "shares.irs 2.0: expected a finite number in [0, 1]"),
        ({"shares": {"uss": -0.5}}, "shares.uss -0.5: expected a finite number in [0, 1]"),
        ({"shares": {"irs": 0.7, "uss": 0.7}}, "shares.irs 0.7 + shares.uss 0.7 + shares.stereo 0.1: expected a sum <= 1"),
        ({"weights": {"colour": -1}}, "weights.colour -1.0: expected a finite number >= 0"),
        ({"recent": {"share": 1.5}}, "recent.share 1.5: expected a finite number in [0, 1]"),
        ({"recent": {"window": 0}}, "recent.window 0.0: expected a finite number > 0"),
        ({"optim": {"lr_decay_driving": 0}}, "optim.lr_decay_driving 0.0: expected a finite number > 0"),
        ({"evaluation": {"zones": []}}, "evaluation.zones []: expected distinct zone names including 'zone3'"),
        ({"evaluation": {"zones": [{"name": "zone3", "lo": 5, "hi": 1}]}}, "evaluation.zones[0] '[5.0, 1.0]': expected 0 <= lo < hi"),
        ({"evaluation": {"raster_res_m": 0}}, "evaluation.raster_res_m 0.0: expected a finite number > 0"),
        ({"evaluation": {"height_band_m": -1}}, "evaluation.height_band_m -1.0: expected a finite number > 0"),
        ({"evaluation": {"uss_arc_step_deg": 0}}, "evaluation.uss_arc_step_deg 0.0: expected a finite number > 0"),
        ({"evaluation": {"inlier_m": -1}}, "evaluation.inlier_m -1.0: expected a finite number > 0"),
        ({"evaluation": {"lidar_angle_range_deg": 0}}, "evaluation.lidar_angle_range_deg 0.0: expected a finite number in (0, 360]"),
        ({"evaluation": {"sensors": ["radar"]}}, "evaluation.sensors ['radar']: expected a subset of ['LiDAR', 'USS', 'IRS']"),
        ({"field": {"density_hidden": [0]}}, "field.density_hidden[0] 0: expected an integer >= 1"),
        ({"field": {"color_hidden": [64, -3]}}, "field.color_hidden[1] -3: expected an integer >= 1"),
        ({"field": {"density_clamp": -1}}, "field.density_clamp -1.0: expected a finite number in (0, 80]"),
        ({"optim": {"betas": [1.5, 0.9]}}, "optim.betas[0] 1.5: expected a number in [0, 1)"),
    ],
)
def test_nested_config_values_are_checked_before_any_work(tmp_path, doc, fragment):
    """Values of the nested sections (grids, shares, weights, evaluation, field, optimiser) that
    would crash the run after the data were read (ZeroDivisionError, KeyError 'zone3', a torch
    shape error) or train on silently: a one-line error naming the file and the field, before
    the (here missing) recording is even looked at."""
    path = write_config(tmp_path, doc)
    code, _, err = run_cli(train_args(tmp_path, "--config", str(path)))
    assert_one_line_error(code, err, str(path), fragment)
    assert not (tmp_path / "run").exists()


def test_missing_config_file(tmp_path):
    code, _, err = run_cli(train_args(tmp_path, "--config", str(tmp_path / "nope.json")))
    assert_one_line_error(code, err, f"{tmp_path / 'nope.json'}: config file not found")


def test_config_types_that_are_accepted():
    cfg = from_dict(TrainConfig, {"batch_size": 2048.0, "max_time": 10, "online": False,
                                  "optim": {"betas": [0, 0.5]}, "sensors": ["camera", "irs"]})
    assert cfg.batch_size == 2048 and type(cfg.batch_size) is int
    assert cfg.max_time == 10.0 and type(cfg.max_time) is float
    assert cfg.optim.betas == (0.0, 0.5) and type(cfg.optim.betas[0]) is float and cfg.sensors == ("camera", "irs")
    assert from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg)))) == cfg
    with pytest.raises(ConfigError, match=r"^config\.march: unknown key\(s\) \['stepsize'\]"):
        from_dict(TrainConfig, {"march": {"stepsize": 0.1}})


def test_train_config_checks_types_and_ranges_itself():
    for bad, fragment in [(dict(batch_size=0), "batch_size 0"), (dict(max_steps=0), "max_steps 0"),
                          (dict(max_time=0.0), "max_time 0.0"), (dict(online="false"), "online 'false'"),
                          (dict(batch_size="2048"), "batch_size '2048'"), (dict(seed=-1), "seed -1"),
                          (dict(image_scale=0.0), "image_scale 0.0"), (dict(playback_speed=0.0), "playback_speed")]:
        with pytest.raises(ValueError, match=fragment.replace("(", r"\(")):
            TrainConfig(**bad)


# ------------------------------------------------------------------------------ fuzzing
FLAG_NAMES = ["--max-time", "--max-steps", "--batch-size", "--seed", "--playback", "--image-scale",
              "--eval-interval", "--sensors", "--grid", "--config", "--optim.lr", "--virus-grid.warmup-steps",
              "--optim.betas", "--shares.uss", "--online"]
values = st.one_of(
    st.integers(-(10**12), 10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", "0", "-0", "1e400", "camera,lidar", "virus", ",", "true", "None", "--", "x y"]),
    st.text(alphabet="0123456789.-+eEinfa,x ", max_size=8),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(command=st.sampled_from(["train", "export", "evaluate", "simulate"]),
       flags=st.lists(st.tuples(st.sampled_from(FLAG_NAMES + ["--resolution", "--n-rays", "--duration", "--bogus"]),
                                values), max_size=4))
def test_fuzzed_arguments_exit_2_with_one_line(tmp_path, command, flags):
    """Any mix of flags and values: a one-line error and exit 2, never a traceback, never output."""
    existing = tmp_path / "existing"
    existing.mkdir(exist_ok=True)
    base = {
        "train": ["--data", str(tmp_path / "no-data"), "--room", "office", "--out", str(tmp_path / "run")],
        "export": ["--run", str(tmp_path / "no-run"), "--out", str(tmp_path / "map")],
        "evaluate": ["--run", str(tmp_path / "no-run")],
        "simulate": ["--scene", "office", "--out", str(existing)],
    }[command]
    argv = [command, *base, *[x for flag, value in flags for x in (flag, value)]]
    code, _, err = run_cli(argv)
    assert_one_line_error(code, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing"]


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**6), 10**6) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)
CONFIG_KEYS = list(to_dict(TrainConfig()).keys())


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.dictionaries(st.sampled_from(CONFIG_KEYS + ["bogus"]), json_values, min_size=1, max_size=3))
def test_fuzzed_config_files_exit_2_with_one_line(tmp_path, doc):
    """Random values for real keys: a bad one is named (file and key); a good file reaches the
    (missing) recording, also a one-line error; nothing is trained and nothing written."""
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(doc))
    code, _, err = run_cli(train_args(tmp_path, "--config", str(path)))
    line = assert_one_line_error(code, err)
    assert str(path) in line or "no-data: no such folder; expected the dataset folder" in line
    assert not (tmp_path / "run").exists()


def test_usage_error_is_a_value_error():
    assert issubclass(UsageError, ValueError) and issubclass(ConfigError, UsageError)


def test_cuda_device_without_a_gpu_is_refused(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is present")
    path = write_config(tmp_path, {"device": "cuda"})
    code, _, err = run_cli(train_args(tmp_path, "--config", str(path)))
    assert_one_line_error(code, err, "device 'cuda': no CUDA GPU is available here; use 'auto' or 'cpu'")


def test_a_helper_threads_write_error_is_one_line(capsys, monkeypatch):
    """TensorBoard's event writer thread on a read-only run folder: one warning line naming the
    file (decoded, not b'...'), not a traceback; other thread errors keep Python's report."""
    import errno
    import threading

    from virus_nerf import cli

    monkeypatch.setattr(threading, "excepthook", threading.__excepthook__)
    cli._one_line_thread_errors()
    cli._one_line_thread_errors()  # a second command in the same process adds no second hook

    def fail():
        raise OSError(errno.EROFS, "Read-only file system", b"run/tensorboard/events.out")

    thread = threading.Thread(target=fail, name="tb-writer")
    thread.start()
    thread.join()
    assert capsys.readouterr().err == "virus-nerf: warning: tb-writer: run/tensorboard/events.out: Read-only file system\n"
    thread = threading.Thread(target=lambda: 1 / 0, name="buggy")
    thread.start()
    thread.join()
    assert "Traceback" in capsys.readouterr().err


def test_sensors_on_a_recording_without_test_frames_is_one_line(tmp_path):
    """A one-frame drive has no test frame: `sensors` refuses it as `train` does (it wrote a table of
    dashes and exit 0), naming the split and the stack, before writing anything."""
    from virus_nerf.sim.command import simulate

    simulate(scene="office", out=tmp_path / "sim", seed=0, duration=0.2, resolution_scale=0.25)
    code, _, err = run_cli(["sensors", "--data", tmp_path / "sim", "--room", "office", "--out", tmp_path / "m.json"])
    assert_one_line_error(code, err, "field 'CAM1'", "no CAM1 rows labelled 'test'")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]


def test_a_flag_suggested_for_a_typo_names_the_help_that_lists_it(tmp_path):
    """`train --help` lists the product knobs alone: a typo near a flag only `--help-all` lists
    points there (a review: --evaluation.zones suggested --evaluation.n-rays "in train --help")."""
    code, _, err = run_cli(["train", "--data", "x", "--room", "y", "--out", tmp_path / "r", "--evaluation.zones", "3"])
    line = assert_one_line_error(code, err, "Perhaps you meant: --evaluation.n-rays")
    assert "in virus-nerf train --help-all" in line
    code, _, err = run_cli(["train", "--data", "x", "--room", "y", "--out", tmp_path / "r", "--max-step", "3"])
    line = assert_one_line_error(code, err, "Perhaps you meant: --max-steps")
    assert "train --help-all" not in line and "in virus-nerf train --help" in line
