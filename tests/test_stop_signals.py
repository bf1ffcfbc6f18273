"""A mapping process a robot stops (issue 39, items 1, 2 and 5): SIGINT and SIGTERM to `map-bag`
and `train --online` keep the final map with one line and exit 130 / 143; SIGKILL leaves whole
snapshots and a mapper state that `map-bag --resume` turns into the final map; no child process
outlives its parent; a full disk costs the large mapper state, never the map; `evaluate` on a run
still training and a second `map-bag` into the same --out say so in one line.

The real commands run in subprocesses on the tiny simulated office (a 3 s drive) at a slow playback
so that a signal lands mid-drive."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from helpers import run_cli, tiny_train_config

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc, sends POSIX signals")

MAP_FILES = {"map.pgm", "map.yaml", "map.png", "prob.pgm", "prob.yaml", "prob.png", "snapshot.json"}


# ------------------------------------------------------------------------------ helpers
def _children(pid: int) -> list[int]:
    """Live processes whose parent is `pid` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has ended (it waits for init to reap it)


def _marked(pid: int) -> list[int]:
    """Processes whose command line names `pid` as their parent (the KISS-ICP worker's marker)."""
    out = []
    for cmd in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            argv = cmd.read_bytes().split(b"\0")
        except OSError:
            continue
        if b"virus_nerf.data.bags.kiss_worker" in argv and str(pid).encode() in argv and _alive(int(cmd.parent.name)):
            out.append(int(cmd.parent.name))
    return out


def _none_survive(pids: list[int], parent: int, within_s: float = 5.0) -> None:
    deadline = time.time() + within_s
    while time.time() < deadline and (any(_alive(p) for p in pids) or _marked(parent)):
        time.sleep(0.1)
    assert not [p for p in pids if _alive(p)] and not _marked(parent), "a child process outlived its parent"


def _start(argv: list, cwd: Path) -> subprocess.Popen:
    # faulthandler: a command that does not end after its stop shows where it is (`_ended`)
    return subprocess.Popen([sys.executable, "-m", "virus_nerf.cli", *map(str, argv)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONFAULTHANDLER": "1"})


def _ended(proc: subprocess.Popen, timeout_s: float = 60.0) -> tuple[str, str]:
    """proc.communicate(); a process still running after `timeout_s` fails the test with every
    thread's stack (SIGABRT: faulthandler's dump), not only with the timeout."""
    try:
        return proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        stdout, stderr = proc.communicate(timeout=60)
        pytest.fail(f"still running {timeout_s:g} s after its stop; stdout: {stdout!r}; its stacks:\n{stderr[-8000:]}")


def _wait_for(cond, proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.time() + timeout_s
    while not cond():
        assert proc.poll() is None, f"ended early ({proc.returncode}): {proc.stderr.read()}"
        assert time.time() < deadline, "timed out"
        time.sleep(0.05)


def _snapshots(out: Path) -> list[Path]:
    folder = out / "snapshots"
    return sorted(p for p in folder.glob("[0-9]*") if p.is_dir()) if folder.is_dir() else []


@pytest.fixture(scope="module")
def drive(tiny_office, tmp_path_factory) -> dict:
    """The tiny office as a ROS 1 bag, its LiDAR poses, and a tiny training config."""
    pytest.importorskip("rosbags")
    from virus_nerf.config_io import to_dict
    from virus_nerf.data.bags.writer import write_bag
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.data.writer import write_poses

    d = tmp_path_factory.mktemp("stop_drive")
    times, poses = load_recording(tiny_office, "office")._lidar_pose_track
    write_poses(d / "lidar.csv", times, poses)
    cfg = d / "cfg.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs")))))
    return {"bag": write_bag(tiny_office, d / "drive.bag", ros_version=1), "csv": d / "lidar.csv", "cfg": cfg}


def _map_bag(drive: dict, out: Path, playback: float = 0.3, poses=("--poses", "lidar-odometry")) -> list:
    return ["map-bag", drive["bag"], "--out", out, "--playback", playback, "--snapshot-every", "1", "--config",
            drive["cfg"], "--n-rays", "32", "--max-poses", "3", "--max-lag", "100", *poses]


# ------------------------------------------------------------------------------ the mechanism
def test_the_first_signal_stops_cleanly_and_the_second_at_once(tmp_path):
    """utils/stop.py in a process of its own: the first SIGTERM raises Stopped (its clean-up runs),
    a second one during that clean-up ends the process at once with 143 and one line."""
    script = textwrap.dedent("""
        import sys, time
        from virus_nerf.utils.stop import Stopped, stop_on_signals
        with stop_on_signals():
            try:
                print("ready", flush=True)
                time.sleep(60)
            except Stopped as exc:  # the final outputs are written inside the block
                print(f"cleaning up after {exc.name}", flush=True)
                time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGTERM)
    assert proc.stdout.readline().strip() == "cleaning up after SIGTERM"
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 130
    assert proc.stderr.read() == "virus-nerf: SIGINT again: stopped at once (files written so far are whole)\n"


def test_ctrl_c_outside_a_mapping_command_is_one_line_not_a_traceback(monkeypatch):
    import virus_nerf.cli as cli

    def interrupted(argv):
        def run():
            raise KeyboardInterrupt
        return run

    monkeypatch.setattr(cli, "_parse", interrupted)
    code, out, err = run_cli(["simulate"])
    assert (code, out, err) == (130, "", "virus-nerf: interrupted (Ctrl-C)\n")


# ------------------------------------------------------------------------------ map-bag
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_map_bag_stopped_by_a_signal_keeps_the_map_in_one_line(drive, tmp_path, sig):
    """SIGTERM after the first snapshot, SIGINT as soon as the mapper has its first frames (before
    any snapshot): the final map (with mapper.pt), stream.json, one line, exit 143 / 130, nothing on
    stderr, and the KISS-ICP worker ends with the process (before: SIGTERM left no map and two
    orphans, SIGINT a 30-57 line traceback)."""
    out = tmp_path / "out"
    proc = _start(_map_bag(drive, out), tmp_path)
    if sig == "SIGTERM":
        _wait_for(lambda: _snapshots(out), proc)
    else:
        _wait_for(lambda: (out / "snapshots" / "config.json").is_file(), proc)
    children = _children(proc.pid)
    assert children, "the KISS-ICP worker runs as a child process"
    proc.send_signal(getattr(signal, sig))
    stdout, stderr = _ended(proc)
    assert proc.returncode == 128 + getattr(signal, sig), stderr
    assert stderr == ""
    last = stdout.splitlines()[-1]
    assert last.startswith(f"map-bag: stopped by {sig} at ") and last.endswith(
        f"final map in {out / 'map'}, report in {out / 'stream.json'}"), last
    assert MAP_FILES | {"mapper.pt"} == {p.name for p in (out / "map").iterdir()}
    report = json.loads((out / "stream.json").read_text())
    assert report["stopped"] == f"interrupted ({sig})" and report["final"] == "map"
    assert report["running"] is False and report["frames"] >= 1
    assert json.loads((out / "map" / "snapshot.json").read_text())["frames"] == report["frames"]
    _none_survive(children, proc.pid)


def test_map_bag_import_first_holds_its_folder_against_a_resume(drive, tmp_path):
    """--import-first writes into OUT as the stream does: while it maps, `map-bag --resume --out OUT`
    is refused naming its pid (a user's review: the resume wrote OUT/map, then the live run lost
    its final map to "output folder already exists")."""
    out = tmp_path / "out"
    proc = _start([*_map_bag(drive, out), "--import-first"], tmp_path)
    try:
        _wait_for(lambda: len(_snapshots(out)) >= 1, proc)
        code, _, stderr = run_cli(["map-bag", "--resume", "--out", out])
        assert code == 2 and f"pid {proc.pid}" in stderr and "still being mapped" in stderr, stderr
        assert not (out / "map").exists()
    finally:
        proc.kill()
        proc.communicate(timeout=60)


def _pgm_size(path) -> tuple[int, int]:
    """(height, width) from a P5 header."""
    w, h = path.read_bytes().split(b"\n")[1].split()
    return int(h), int(w)


def test_map_bag_killed_then_resume_writes_the_final_map(drive, tmp_path):
    """SIGKILL after the second snapshot: whole snapshots and the mapper state of the last one; the
    worker dies with its parent; `map-bag --resume --out OUT` makes OUT/map/ from them (that
    snapshot's map and state) and stream.json, and rebuilds the --out-bag the kill left unfinished
    (no metadata.yaml) from the snapshots' maps, keeping the unfinished one aside; a second
    --resume and a folder without any snapshot are refused in one line."""
    out, ros = tmp_path / "out", tmp_path / "ros"
    proc = _start([*_map_bag(drive, out), "--out-bag", ros], tmp_path)
    _wait_for(lambda: len(_snapshots(out)) >= 2 and (out / "snapshots" / "mapper.pt").is_file(), proc)
    children = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    _none_survive(children, proc.pid)
    assert not (out / "map").exists()
    progress = json.loads((out / "stream.json").read_text())
    assert progress["running"] is True and progress["final"] is None
    import torch

    state = torch.load(out / "snapshots" / "mapper.pt", map_location="cpu", weights_only=False)
    snaps = _snapshots(out)
    assert state["snapshot"] in {p.name for p in snaps}
    # a flag the snapshot's map cannot honour is refused, not ignored, and nothing is written
    for extra, flag in ((["--out-bag", tmp_path / "maps_bag"], "--out-bag"), (["--resolution", "0.1"], "--resolution")):
        code, _, stderr = run_cli(["map-bag", "--resume", "--out", out, *extra])
        assert code == 2 and f"{flag}" in stderr and "cannot apply to it: drop it" in stderr, stderr
    assert not (out / "map").exists() and not (tmp_path / "maps_bag").exists()

    assert not (ros / "metadata.yaml").exists()  # killed: the MCAP is finished on close
    code, stdout, stderr = run_cli(["map-bag", "--resume", "--out", out])
    assert code == 0, stderr
    last = snaps[-1]
    kept = next(tmp_path.glob("ros.incomplete-*"))
    assert stdout == (f"map-bag: the stream in {out} was stopped after snapshot {len(snaps)}; final map (that "
                      f"snapshot's) in {out / 'map'}"
                      f"{'' if state['snapshot'] == last.name else f' (no mapper state of {last.name} was saved)'}"
                      f", report in {out / 'stream.json'}; --out-bag {ros} rebuilt from the {len(snaps)} snapshots' "
                      f"maps (the /tf poses were lost with the killed process; the unfinished bag kept as {kept})\n")
    from virus_nerf.data.bags.reader import BagReader

    with BagReader(ros) as bag:
        assert bag.topics["/map"].count == bag.topics["/map_probability"].count == len(snaps)
        maps = [msg.msg for _, msg in bag.iter_topics(["/map"])]
    stamp = json.loads((last / "snapshot.json").read_text())["last_frame_time"]
    newest = maps[-1]
    assert newest.header.stamp.sec + newest.header.stamp.nanosec * 1e-9 == pytest.approx(stamp, abs=1e-6)
    h, w = _pgm_size(last / "map.pgm")
    assert (newest.info.width, newest.info.height) == (w, h) and newest.header.frame_id == "map"
    for name in MAP_FILES:
        assert (out / "map" / name).read_bytes() == (last / name).read_bytes(), name
    if state["snapshot"] == last.name:
        saved = torch.load(out / "map" / "mapper.pt", map_location="cpu", weights_only=False)
        assert saved["step"] == state["mapper"]["step"] == json.loads((last / "snapshot.json").read_text())["steps"]
    report = json.loads((out / "stream.json").read_text())
    assert report["running"] is False and report["final"] == "map"
    assert report["stopped"] == f"killed after snapshot {len(snaps)} ({last.name})"
    assert report["snapshots"] == [f"snapshots/{p.name}" for p in snaps]  # relative to OUT

    code, _, stderr = run_cli(["map-bag", "--resume", "--out", out])
    assert code == 2 and stderr == (f"virus-nerf: error: --resume --out {out}: the stream ended (final map in "
                                    f"{out / 'map'}, {out / 'stream.json'}); nothing to finish\n")
    # a second signal stopped the final mapper.pt's write half-way: its temporary goes, the message says so
    (out / "map" / "mapper.pt").unlink(missing_ok=True)
    (out / "map" / ".mapper.pt.k1ll3d.tmp").write_bytes(b"half a state")
    code, _, stderr = run_cli(["map-bag", "--resume", "--out", out])
    assert code == 2 and stderr.endswith(f"nothing to finish; its mapper state was not saved (stopped while writing "
                                         f"{out / 'map' / 'mapper.pt'})\n") and stderr.count("\n") == 1
    assert not list((out / "map").glob(".mapper.pt.*"))
    early = tmp_path / "early"
    (early / "snapshots").mkdir(parents=True)
    (early / "snapshots" / "config.json").write_text("{}")
    code, _, stderr = run_cli(["map-bag", "--resume", "--out", early])
    assert code == 2 and "the stream was stopped before its first snapshot; there is no map" in stderr
    assert stderr.count("\n") == 1 and sorted(p.name for p in early.iterdir()) == ["run.lock", "snapshots"]


# ------------------------------------------------------------------------------ a full disk
def test_map_bag_on_a_full_disk_keeps_the_map_and_names_the_state(drive, tmp_path, monkeypatch):
    """No room for the mapper state (the large file): mapping goes on with one warning, the final
    map and stream.json are written, mapper.pt is named in one line, exit 2 (before: a 35-line torch
    RuntimeError, no map/, no stream.json)."""
    import virus_nerf.utils.io as io_mod

    def full(obj, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(io_mod, "save_torch_atomic", full)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(_map_bag(drive, out, playback=2.0, poses=("--poses", "csv", "--poses-file",
                                                                             drive["csv"])))
    assert code == 2 and stderr == (
        f"virus-nerf: error: {out / 'map' / 'mapper.pt'}: could not be written (No space left on device); kept: "
        f"{out / 'map'}, {out / 'stream.json'}; free some space; the snapshots in {out / 'snapshots'} are whole\n")
    assert stdout.count("warning:") == 1 and "snapshots/mapper.pt: could not be written" in stdout
    assert MAP_FILES == {p.name for p in (out / "map").iterdir()}
    assert json.loads((out / "stream.json").read_text())["final"] == "map"


@pytest.mark.skipif(os.geteuid() != 0, reason="mounts a small tmpfs (root only)")
def test_map_bag_on_a_real_full_tmpfs(drive, tmp_path):
    """--out on a 6 MB tmpfs: the maps (a few hundred KB) fit, the ~28 MB mapper state does not."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = disk / "out"
        proc = _start(_map_bag(drive, out, playback=2.0, poses=("--poses", "csv", "--poses-file", drive["csv"])),
                      tmp_path)
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 2 and stderr.count("\n") == 1, stderr
        assert stderr.startswith(f"virus-nerf: error: {out / 'map' / 'mapper.pt'}: could not be written (No space "
                                 f"left on device); kept: {out / 'map'}, {out / 'stream.json'}"), stderr
        assert MAP_FILES == {p.name for p in (out / "map").iterdir()}
        assert json.loads((out / "stream.json").read_text())["running"] is False
        assert not list(out.rglob(".*.tmp")), "no temporary left behind"
    finally:
        subprocess.run(["umount", str(disk)], check=False)


# ------------------------------------------------------------------------------ train --online, evaluate
def test_train_online_stopped_keeps_map_and_checkpoint_and_evaluate_says_it_trains(tiny_office, tmp_path):
    """While an online run trains (no checkpoint yet) `evaluate` says it is still training; SIGINT
    then writes OUT/map/ and checkpoint.pt, one line how to continue, exit 130, and no metrics.json
    (the run stays resumable)."""
    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "online.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs"), max_steps=None,
                                                        max_time=100.0, online=True, playback_speed=0.1,
                                                        checkpoint_every=1000.0))))
    out = tmp_path / "run"
    proc = _start(["train", "--data", tiny_office, "--room", "office", "--out", out, "--config", cfg, "--quiet"],
                  tmp_path)
    log = out / "train_log.csv"
    _wait_for(lambda: log.is_file() and len(log.read_text().splitlines()) >= 3, proc)
    assert not (out / "checkpoint.pt").exists()
    code, _, stderr = run_cli(["evaluate", "--run", out])
    assert code == 2 and stderr == (f"virus-nerf: error: --run {out}: the run is still training (`virus-nerf train`, "
                                    f"pid {proc.pid}); wait for it to end or stop it, then run again\n")
    children = _children(proc.pid)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = _ended(proc)
    assert proc.returncode == 130 and stderr == "", stderr
    assert stdout.startswith("train: stopped by SIGINT at step ") and stdout.count("\n") == 1
    assert stdout.rstrip().endswith(f"map in {out / 'map'}, checkpoint in {out / 'checkpoint.pt'}; continue with "
                                    f"`virus-nerf train --resume --out {out}`")
    assert MAP_FILES == {p.name for p in (out / "map").iterdir()}
    assert (out / "checkpoint.pt").is_file() and not (out / "metrics.json").exists()
    _none_survive(children, proc.pid)


def test_train_offline_stopped_resumes_exactly_as_the_run_never_stopped(tiny_office, tmp_path):
    """`systemctl stop` (SIGTERM; Ctrl-C alike) ends an offline run after the step in progress:
    map/ and a checkpoint of that step, one line, exit 143; `--resume` trains on to the budget and
    scores exactly as the run that was never stopped (bounded by steps: bit-reproducible on a CPU)."""
    sig = signal.SIGTERM
    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "offline.json"
    # one thread (--threads in the config): the numbers are the same only at the same thread count
    cfg.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs"), max_steps=60,
                                                        checkpoint_every=1000.0, threads=1))))
    args = ["train", "--data", tiny_office, "--room", "office", "--config", cfg, "--quiet"]
    # every part in a process of its own, as a user runs them: this test process's torch threads
    # (set by earlier tests) would sum in another order and differ in the last bits
    whole = _start([*args, "--out", tmp_path / "whole"], tmp_path)
    assert whole.wait(timeout=300) == 0, whole.stderr.read()
    out = tmp_path / "run"
    proc = _start([*args, "--out", out], tmp_path)
    log = out / "train_log.csv"
    _wait_for(lambda: log.is_file() and len(log.read_text().splitlines()) >= 4, proc)
    proc.send_signal(sig)
    stdout, stderr = _ended(proc)
    assert proc.returncode == 128 + sig and stderr == "", stderr
    assert stdout.startswith(f"train: stopped by {signal.Signals(sig).name} at step ") and stdout.count("\n") == 1
    step = int(stdout.split(" at step ")[1].split()[0])
    assert 6 <= step < 60, stdout
    assert MAP_FILES == {p.name for p in (out / "map").iterdir()} and not (out / "metrics.json").exists()
    resume = _start(["train", "--resume", "--out", out, "--quiet"], tmp_path)
    assert resume.wait(timeout=300) == 0, resume.stderr.read()
    resumed, whole = (json.loads((d / "metrics.json").read_text()) for d in (out, tmp_path / "whole"))
    assert resumed["train"]["steps"] == whole["train"]["steps"] == 60
    assert resumed["train"]["threads"] == whole["train"]["threads"] == 1  # what the steps ran on
    assert resumed["sensors"] == whole["sensors"] and resumed["safety"] == whole["safety"]


# ------------------------------------------------------------------------------ two map-bag, one --out
def test_a_second_map_bag_into_the_same_out_is_one_line(drive, tmp_path, monkeypatch):
    """Both passed the check before their start-up; the other one made OUT during this one's warm-up:
    one line naming the folder and --out (before: the bare OS text "File exists"), and the other's
    folder untouched."""
    import virus_nerf.mapping.stream as stream

    out = tmp_path / "out"

    def other_made_it(cfg):
        (out / "snapshots").mkdir(parents=True)
        return 0.1

    monkeypatch.setattr(stream, "warm_up", other_made_it)
    code, _, stderr = run_cli(_map_bag(drive, out, poses=("--poses", "csv", "--poses-file", drive["csv"])))
    assert code == 2 and stderr == (f"virus-nerf: error: {out}: output folder already exists; choose a new --out "
                                    "(nothing was overwritten)\n")
    assert [p.name for p in out.iterdir()] == ["snapshots"]


def test_train_online_on_a_full_disk_writes_the_map_before_naming_the_checkpoint(tiny_office, tmp_path,
                                                                                  monkeypatch):
    """The final checkpoint (the large file) does not fit: the map and metrics.json are written, the
    checkpoint is named in one line, exit 2 (before: the run ended at the checkpoint, no map)."""
    import pathlib

    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "online.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs"), max_steps=None,
                                                        max_time=100.0, online=True, playback_speed=3.0,
                                                        checkpoint_every=1000.0))))
    real = pathlib.Path.write_bytes

    def full(self, data):
        if self.name.startswith(".checkpoint.pt."):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    out = tmp_path / "run"
    code, stdout, stderr = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", out, "--config", cfg,
                                    "--quiet", "--gt", "none"])
    assert code == 2 and stderr == (
        f"virus-nerf: error: {out / 'checkpoint.pt'}: could not be written (No space left on device); kept: "
        f"{out / 'map'}, {out / 'metrics.json'}; free some space and run `virus-nerf train --resume --out {out}` to "
        "train it again\n")
    assert MAP_FILES == {p.name for p in (out / "map").iterdir()} and not (out / "checkpoint.pt").exists()
    assert f"map ({json.loads((out / 'map' / 'snapshot.json').read_text())['map_known']:.1%} known)" in stdout


def test_train_stopped_while_scoring_keeps_the_map_and_says_resume_scores_it(tiny_office, tmp_path, monkeypatch):
    """A signal after the last step, while the run is scored (evaluation, plots): map/ of the
    finished training, its checkpoint, no metrics.json, one line, exit 143; `--resume` then only
    scores it (a review found a bare "interrupted" and no map)."""
    import virus_nerf.trainer.run as run_module
    from virus_nerf.utils.stop import Stopped

    def stopped(*args, **kwargs):
        raise Stopped(signal.SIGTERM)

    from virus_nerf.config_io import to_dict

    out, cfg = tmp_path / "run", tmp_path / "tiny.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(max_steps=4))))  # no plots: 11 s of matplotlib twice
    args = ["train", "--data", tiny_office, "--room", "office", "--out", out, "--config", cfg, "--quiet"]
    with monkeypatch.context() as m:
        m.setattr(run_module, "_score", stopped)
        code, stdout, err = run_cli(args)
    assert code == 128 + signal.SIGTERM and err == "", err
    assert stdout == (f"train: stopped by SIGTERM while scoring the finished training (step 4); map in {out / 'map'}, "
                      f"checkpoint in {out / 'checkpoint.pt'}; score it with `virus-nerf train --resume --out {out}`\n")
    assert MAP_FILES == {p.name for p in (out / "map").iterdir()} and (out / "checkpoint.pt").is_file()
    assert not (out / "metrics.json").exists()
    code, stdout, err = run_cli(["train", "--resume", "--out", out, "--quiet"])
    assert code == 0, err
    block = json.loads((out / "metrics.json").read_text())["train"]
    assert block["steps"] == 4 and block["device"] == "cpu"  # the checkpoint's: where the steps ran
    import torch

    assert block["threads"] == torch.get_num_threads()  # and with how many threads


def test_after_a_stop_no_exception_ignored_report_follows_the_one_line():
    """A signal that lands in llvmlite's C callback (numba loading a kernel) is reported as
    "Exception ignored", and an object it cut half-built reports its __del__ at exit: after the
    stop's one line neither is printed (seen on a busy machine: llvmlite's `ValueRef.__del__`)."""
    script = textwrap.dedent("""
        import os, signal, sys, time
        from virus_nerf.cli import _interrupted
        from virus_nerf.utils.stop import Stopped, stop_on_signals

        class HalfBuilt:
            def __del__(self):
                raise AttributeError("half-built")

        keep = HalfBuilt()  # its __del__ raises at exit, after the one line
        try:
            with stop_on_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
        except Stopped as exc:
            doomed = HalfBuilt()
            del doomed  # raises in __del__ now, inside the stopped command
            print("stopped", file=sys.stderr)
            _interrupted(exc)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143
    assert proc.stderr == "stopped\nvirus-nerf: interrupted (SIGTERM)\n", proc.stderr


def test_any_command_stopped_by_sigterm_leaves_no_partial_folder(tmp_path):
    """SIGTERM to a command without a stop of its own (here `simulate`, as `export` and
    `import-bag`): as Ctrl-C, its temporary folder is removed, one line, exit 143; a folder a
    killed attempt left (its pid dead) goes when the next attempt at the same --out starts."""
    from virus_nerf.utils.io import new_output_dir

    out = tmp_path / "sim"
    proc = _start(["simulate", "--scene", "office", "--duration", "120", "--out", out], tmp_path)
    # once frames are written the kernels are loaded (a signal while numba loads one is swallowed by
    # llvmlite's callback: the command then stops only at its end, test below)
    _wait_for(lambda: any(tmp_path.glob(".sim.partial-*/**/*.png")), proc)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = _ended(proc)
    assert proc.returncode == 128 + signal.SIGTERM and stderr == "virus-nerf: interrupted (SIGTERM)\n", stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    stale = tmp_path / ".exp.partial-999999999-abc"  # no such pid
    stale.mkdir()
    with new_output_dir(tmp_path / "exp") as tmp:
        (tmp / "a.txt").write_text("a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp"]


def test_a_run_folder_removed_under_train_is_not_rebuilt(tiny_office, tmp_path):
    """`rm -rf RUN` while `train` runs: its next checkpoint does not make RUN again (holding only
    that checkpoint, unlocked); one line, exit 2 (a review found a rebuilt folder and a traceback)."""
    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs"), max_steps=100000,
                                                        checkpoint_every=0.5))))
    out = tmp_path / "run"
    proc = _start(["train", "--data", tiny_office, "--room", "office", "--config", cfg, "--out", out, "--quiet"],
                  tmp_path)
    _wait_for(lambda: (out / "checkpoint.pt").is_file(), proc)
    subprocess.run(["rm", "-rf", str(out)], check=True)  # as a user would (files vanishing as it goes)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2, stderr
    assert stderr.splitlines()[-1] == (f"virus-nerf: error: {out}: the run folder was removed while the command "
                                       "ran; nothing more is written (the files it held are gone: run the command "
                                       "again into a new folder)"), stderr
    assert "Traceback" not in stderr and not out.exists()


def test_an_import_first_folder_removed_under_map_bag_is_one_line(drive, tmp_path):
    """`rm -rf OUT` while `map-bag --import-first` replays OUT/recording: one line saying the
    folder was removed, exit 2 (a review found "OUT/recording/.../img58.png: image file not
    found"), and OUT is not made again."""
    out = tmp_path / "out"
    proc = _start([*_map_bag(drive, out), "--import-first"], tmp_path)
    _wait_for(lambda: _snapshots(out), proc)
    subprocess.run(["rm", "-rf", str(out)], check=True)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2, stderr
    assert stderr.splitlines()[-1] == (f"virus-nerf: error: {out}: the output folder was removed while the command "
                                       "ran; nothing more is written (the files it held are gone: run the command "
                                       "again into a new folder)"), stderr
    assert "Traceback" not in stderr and not out.exists()


def test_a_stop_swallowed_inside_the_block_is_raised_when_it_ends():
    """A signal's Stopped raised where a C callback swallows it (llvmlite's, while numba loads a
    kernel: "Exception ignored") is not lost: the block's work ends, then it raises, exit 143."""
    from virus_nerf.utils.stop import Stopped, stop_on_signals

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Stopped) as info:
        with stop_on_signals():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.5)  # the handler runs here
            except Stopped:
                pass  # as the ctypes callback swallows it
            finished = True
    assert finished and info.value.exit_code == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before
    with stop_on_signals():  # a later block starts clean
        pass


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_while_the_commands_modules_load_is_one_line(monkeypatch, signum):
    """SIGINT or SIGTERM in the second or two while a command's modules load (torch): one line and
    128 + the signal (a review: SIGINT then was a traceback, SIGTERM a silent kill). The signal is
    real, sent to this process from inside the import."""
    from helpers import ctrl_c_raises

    import virus_nerf.cli as cli

    def loading(name):
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the handler raises in here
        raise AssertionError("the signal was not taken")

    monkeypatch.setattr(cli, "_command", loading)
    with ctrl_c_raises():
        code, stdout, stderr = run_cli(["train", "--data", "nowhere", "--room", "office", "--out", "nowhere"])
    assert (code, stdout, stderr) == (128 + signum, "", f"virus-nerf: interrupted ({signal.Signals(signum).name})\n")


def test_a_stop_a_c_callback_swallowed_rises_at_the_next_steps_end():
    """A signal that lands where a C callback swallows the `Stopped` (llvmlite's, while numba loads
    a kernel between training steps) stops the run at the end of the next step, not after the whole
    budget."""
    from virus_nerf.utils.stop import Stopped, stop_on_signals, stops_deferred

    steps = []
    with pytest.raises(Stopped) as stopped, stop_on_signals():
        try:  # what a C callback does with the exception its Python code raised: reports and drops it
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises in here
        except Stopped:
            pass
        for k in range(3):
            with stops_deferred():
                steps.append(k)
    assert steps == [0] and stopped.value.signum == signal.SIGTERM


def test_a_deferring_block_in_the_unwinding_of_a_stop_adds_no_second_stop():
    """The stop rose between deferring blocks (kept for the next one's end, in case a C callback
    swallowed it); the log's close in a `finally` is such a block: it must not raise a second one."""
    from virus_nerf.utils.stop import Stopped, stop_on_signals, stops_deferred

    closed = []
    with pytest.raises(Stopped) as stopped, stop_on_signals():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises in here
        finally:
            with stops_deferred():
                closed.append(True)
    assert closed == [True] and stopped.value.__context__ is None


def test_a_stop_during_a_log_write_rises_once_the_row_and_its_tensorboard_scalars_are_written(tmp_path):
    """A signal inside a TensorBoard call (the CSV row just written: where a loaded suite run's
    stopped `train` landed) waits until the log's write is done. Cut there, TensorBoard's writer
    thread can miss its wake-up and sleep until its 120 s flush, and the stop's close waits for it
    (that run wrote its map two minutes after the signal). The stop rises once: the log's close in
    the unwinding adds none."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from virus_nerf.trainer.train_log import LogRow, TrainLog
    from virus_nerf.utils.stop import Stopped, stop_on_signals

    log = TrainLog(tmp_path, 0, 10, quiet=True)
    real, calls = log._tb.add_scalar, []

    def signalled_inside(tag, value, step):
        calls.append(tag)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.5)  # the handler runs in here: without the deferral the Stopped rises now
        real(tag, value, step)

    log._tb.add_scalar = signalled_inside
    row = LogRow(2, 0.1, 0.5, 0.25, 0.125, 0.0, 0.0, 20.0, 12.5, 0.3, 7)
    with pytest.raises(Stopped) as stopped, stop_on_signals():
        try:
            log.write(row)
        finally:
            log.close()
    assert stopped.value.signum == signal.SIGTERM and stopped.value.__context__ is None  # one stop, not two
    assert (tmp_path / "train_log.csv").read_text().splitlines()[-1].split(",")[:3] == ["2", "0.1", "0.5"]
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    assert sorted(events.Tags()["scalars"]) == sorted(f"train/{name}" for name in LogRow.FIELDS[2:])
    assert [(e.step, e.value) for e in events.Scalars("train/colour")] == [(2, 0.25)]
