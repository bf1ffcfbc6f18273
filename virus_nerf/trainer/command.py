"""`virus-nerf train` and `virus-nerf evaluate` (docs/method.md 7).

Everything a user can get wrong is checked before any work is done and before any file is
written: the flags, the config file, the recording (split with 'train' rows and with 'test'
rows of stack 1, a LiDAR map), the run folder. A new run folder appears complete (config.json
and run.json) and is removed again if the training fails before its first checkpoint, so a
failed start never leaves a half-made folder behind.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Annotated

import tyro

from virus_nerf.config_flags import FlagSpec, apply_flags, flag_names, flag_tree
from virus_nerf.errors import (
    DataFormatError,
    UsageError,
    renamed_flag,
    require_int,
)
from virus_nerf.sampler.batch import SENSORS
from virus_nerf.trainer.config import TrainConfig, check_device
from virus_nerf.trainer.run_folder import (
    CHECKPOINT,
    CONFIG,
    MAP_DIR,
    METRICS,
    METRICS_VS_TIME,
    PLOTS,
    RUN_INFO,
    TRAIN_LOG,
    RunInfo,
    RunLock,
    open_run,
    read_checkpoint_header,
)
from virus_nerf.utils.io import write_json_atomic

# ---------------------------------------------------------------------------- flags
# The config fields whose `train` flag is not the one derived from the field (config_flags.py):
# --sensors takes a comma-separated list, --playback is playback_speed's flag (the old name
# --playback-speed is a parameter of `train`), evaluation.gt is set by `train --gt` and the
# evaluation zones (a list of objects) by a config file only.
TRAIN_FLAG_SPECS: dict[str, FlagSpec | None] = {
    "sensors": FlagSpec(type=str, metavar="NAMES", help=f"Sensors to train on, comma-separated, of {','.join(SENSORS)}."),
    "max_steps": FlagSpec(help="Training steps. Alone (no --max-time, no --config, no --resume) it also sets "
                               "max_time None: a run bounded by steps, bit-reproducible on CPU."),
    "playback_speed": FlagSpec(name="playback", help="Online mode: recording seconds per training second (the "
                                                     "frame feeder's speed, as map-bag's --playback on the wall clock)."),
    "evaluation.gt": None,
    "evaluation.zones": None,
}
TrainFlags = flag_tree(TrainConfig, TRAIN_FLAG_SPECS)
NO_FLAGS = TrainFlags()  # `train` called with no config flag (never changed: train_flags copies)


def _parse_sensors(sensors: str) -> tuple[str, ...]:
    """--sensors camera,uss,irs -> ("camera", "uss", "irs"); a bad name is one line naming the flag."""
    names = tuple(s.strip() for s in sensors.split(","))
    unknown = [s for s in names if s not in SENSORS]
    if unknown or not any(names):
        what = f"unknown sensor {unknown[0]!r}" if unknown and unknown[0] else "an empty sensor name"
        raise UsageError(f"--sensors {sensors!r}: {what}; expected a comma-separated subset of {','.join(SENSORS)}")
    return tuple(dict.fromkeys(names))


def train_flags(knobs: dict, gt: str | None = None, playback_speed: float | None = None) -> tuple[dict, dict]:
    """The config fields the `train` flags give (a nested dict, a section a dict) and, for each
    dotted field, the flag that gave it (for error messages): the derived flags in `knobs`, --gt
    and the deprecated --playback-speed."""
    from virus_nerf.evaluation.evaluate import parse_gt_flag

    given = copy.deepcopy(dict(knobs))
    flags = flag_names(given, TRAIN_FLAG_SPECS)
    if "sensors" in given:
        given["sensors"] = _parse_sensors(given["sensors"])
    if playback_speed is not None:
        given["playback_speed"] = renamed_flag("--playback", given.get("playback_speed"), "--playback-speed",
                                               playback_speed)
        flags["playback_speed"] = "--playback-speed"
    if gt is not None:
        given.setdefault("evaluation", {})["gt"] = parse_gt_flag(gt)
        flags["evaluation.gt"] = "--gt"
    return given, flags


def _resolve_config(config: Path | None, given: dict, flags: dict, base=None) -> TrainConfig:
    """The run's TrainConfig: `base` (the run's own on --resume), or the --config file, or the
    defaults, with the fields the flags give on top; a flag not given keeps the value below it."""
    from virus_nerf.config_io import load_json_config

    if config is not None:
        cfg = load_json_config(TrainConfig, config)
    else:
        cfg = base if base is not None else TrainConfig()
    if given.get("max_steps") is not None and "max_time" not in given and config is None and base is None:
        given = {**given, "max_time": None}  # --max-steps alone: a step-bounded, bit-reproducible run
    return apply_flags(cfg, given, flags)


# ---------------------------------------------------------------------------- checks on inputs
def _split_file(recording) -> str:
    path = recording.room_dir / "split" / "split.csv"
    return str(path) if path.is_file() else f"{path} (absent: the default split made in memory)"


def check_recording_for_training(recording, cfg, eval_recording=None) -> None:
    """Refuse, before any training, a recording the run could not train on or be scored on."""
    from virus_nerf.evaluation.evaluate import check_ground_truth_inputs
    from virus_nerf.evaluation.testpoints import MAIN_STACK, make_test_points

    if not any((s.split == "train").any() for s in recording.stacks.values()):
        raise DataFormatError(_split_file(recording), "no rows labelled 'train'; training needs at least one")
    ev = eval_recording or recording
    if cfg.evaluation.gt and not make_test_points(ev):
        raise DataFormatError(
            _split_file(ev),
            f"no CAM{MAIN_STACK} rows labelled 'test'; the evaluation scores the test frames of stack {MAIN_STACK}",
            field=f"CAM{MAIN_STACK}",
        )
    # the ground truth needs the LiDAR map (map, paper) or scene.json (exact): a missing or bad
    # one fails now, not after training
    check_ground_truth_inputs(ev, cfg.evaluation.gt)
    for sid, stack in recording.stacks.items():
        small = stack.intrinsics.scaled(cfg.image_scale)
        if small.width < 1 or small.height < 1:
            raise UsageError(
                f"image_scale {cfg.image_scale}: CAM{sid} images ({stack.intrinsics.width}x{stack.intrinsics.height})"
                f" would be {small.width}x{small.height} px; expected a scale giving at least 1x1 px"
            )


def load_trained(run: Path, flag: str, *, poses: str | None = None, quiet: bool = True):
    """(Trainer with the run's checkpoint loaded, TrainConfig, RunInfo) for `evaluate` and `export`.

    poses: "optimised" (default: the true frame, in which the map is judged) or "odometry"
    (the frame an odometry-trained model was trained in, e.g. to render its own views).
    """
    from virus_nerf.data.ethz import load_recording, resolve_pose_source
    from virus_nerf.trainer.loop import Trainer

    cfg, info = open_run(run, flag)
    check_device(cfg)
    read_checkpoint_header(Path(run) / CHECKPOINT, cfg)
    source, _ = resolve_pose_source(Path(info.data) / info.room, poses or "optimised")  # no LiDAR: odometry only
    recording = load_recording(info.data, info.room, poses=source)
    trainer = Trainer(recording, cfg, run, quiet=quiet)
    trainer.load_checkpoint(Path(run) / CHECKPOINT)
    return trainer, cfg, info


# ---------------------------------------------------------------------------- training
def run_training(data: Path, room: str, out: Path, cfg, quiet: bool | None = None, resume: bool = False,
                 auto_gt: bool = False) -> dict:
    """Train, evaluate and write everything into the run folder; returns the metrics document.

    New run: OUT must not exist; the recording is checked first, then OUT appears with
    config.json, run.json and its lock held in one rename, and if the training fails before its
    first checkpoint OUT is removed again. Resume: under OUT's lock (run_folder.RunLock), from
    OUT's checkpoint (none: from step 0); a run that already reached its budget and has its
    metrics.json is refused before any file but the lock is touched; one that reached its
    budget but stopped before its metrics only gets evaluated; `cfg` replaces config.json once
    the first step worked. The final results are written plots/ first, metrics.json last
    (metrics.json marks a finished run).

    Without ground truth (evaluation.gt empty: `--gt none`, or `auto_gt` and a recording with
    no LiDAR map) nothing is scored: the run writes its map to OUT/map/ (map.pgm/.yaml/.png,
    prob.*, snapshot.json) and a metrics.json with gt null and no sensors, and says so in one line.
    A recording with only odometry poses is trained on them (one line says so).
    """
    from virus_nerf.config_io import to_dict
    from virus_nerf.data.ethz import load_recording, resolve_pose_source
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.trainer.loop import Trainer
    from virus_nerf.trainer.report import write_run_plots
    from virus_nerf.trainer.run_folder import write_run_metrics
    from virus_nerf.trainer.trust import map_warnings
    from virus_nerf.utils.io import new_output_dir, remove_stale_partials
    from virus_nerf.utils.seeding import seed_everything

    out = Path(out)
    if not resume:
        remove_stale_partials(out)  # `.OUT.partial-<pid>-*` of a `train --out OUT` killed while starting
    if not resume and out.exists():
        raise OutputExistsError(out)
    check_device(cfg)
    check_batch_memory(cfg)
    seed_everything(cfg.seed)
    source, note = resolve_pose_source(Path(data) / room, "odometry" if cfg.odometry_poses else "optimised")
    if note:
        print(f"note: {note}")
    recording = load_recording(data, room, poses=source)
    if auto_gt and cfg.evaluation.gt and recording.map_path is None \
            and all(p in ("map", "paper") for p in cfg.evaluation.gt):
        cfg = dataclasses.replace(cfg, evaluation=dataclasses.replace(cfg.evaluation, gt=()))
        print(f"note: {recording.room_dir / 'maps'}: no LiDAR map (map_*.pcd); training without ground truth, "
              "no metrics will be computed (as with --gt none)")
    eval_source, _ = resolve_pose_source(Path(data) / room, "optimised")
    need_eval_frame = cfg.odometry_poses and cfg.evaluation.gt and eval_source != source
    eval_recording = load_recording(data, room, poses=eval_source) if need_eval_frame else recording
    check_recording_for_training(recording, cfg, eval_recording)

    lock = RunLock(out, "--resume" if resume else "--out")
    if resume:
        lock.acquire()  # one process trains in a run folder at a time (released when it dies)
    try:
        if resume:
            trainer, summary = _resume(out, recording, cfg, quiet)
        else:
            with new_output_dir(out) as tmp:  # OUT appears with both files or not at all, and locked
                write_json_atomic(tmp / CONFIG, to_dict(cfg))
                RunInfo(data=str(Path(data).resolve()), room=room).write(tmp)
                lock.folder = tmp
                lock.acquire()  # the lock file's descriptor follows the folder's rename
            lock.folder = out
            try:
                trainer = Trainer(recording, cfg, out, quiet=quiet)
                summary = _fit(trainer)
            except BaseException:
                if not (out / CHECKPOINT).is_file() and not (out / MAP_DIR).is_dir():
                    shutil.rmtree(out, ignore_errors=True)  # nothing to resume: leave no half-made run behind
                raise
        warnings = map_warnings(trainer)
        if not cfg.evaluation.gt:
            if resume and to_dict(cfg) != _saved_config(out):
                write_json_atomic(out / CONFIG, to_dict(cfg))
            return _finish_without_ground_truth(trainer, out, cfg, summary, resume, warnings)
        if eval_recording is not recording:
            # the map and test points are judged in the true (optimised) frame
            trainer.evaluate_on(eval_recording)
        result = _final_evaluation(trainer, out)
        trainer.record_eval(result, None)  # the final point of the metric-vs-time curve
        from virus_nerf.evaluation.safety import mapper_safety

        run_safety = mapper_safety(trainer.mapper, trainer.recording, cfg.evaluation.height_band_m)
        safety = None if run_safety is None else run_safety.document
        if (out / MAP_DIR).is_dir():  # the map an interrupted online run left: this run's map now
            trainer.mapper.snapshot(out / MAP_DIR, replace=True)
        write_run_plots(out, result, trainer.eval_history, replace=resume,  # plots first: metrics.json marks the end
                        safety_picture=None if run_safety is None else run_safety.picture)
        if resume and to_dict(cfg) != _saved_config(out):
            write_json_atomic(out / CONFIG, to_dict(cfg))  # a finished run's resume: evaluated with it
        doc = write_run_metrics(out, result, cfg, summary, safety=safety, warnings=warnings)
    finally:
        lock.release()
    print(result.table())
    for w in warnings:
        print(f"warning: {w}")
    if safety is not None:
        from virus_nerf.evaluation.safety import safety_line

        print(safety_line(safety))
    print(
        f"trained {summary.steps} steps in {summary.seconds:.1f} s "
        f"({summary.steps_per_s:.2f} steps/s, {summary.samples_per_s / 1e6:.3f} M samples/s); "
        f"results in {out}"
    )
    _check_final_checkpoint(trainer, [out / PLOTS, out / METRICS])
    return doc


def _fit(trainer, started=None):
    """trainer.fit(); stopped by SIGINT/SIGTERM (online runs, utils/stop.py): the map and the
    checkpoint are kept first (`keep_stopped_run`)."""
    from virus_nerf.utils.stop import Stopped

    try:
        return trainer.fit(started)
    except Stopped as exc:
        keep_stopped_run(trainer, exc)
        raise


def keep_stopped_run(trainer, exc) -> None:
    """An online run stopped by a signal: OUT/map/ (map.pgm/.yaml/.png, prob.*, snapshot.json;
    small, written first), then checkpoint.pt (large), then one line saying where they are and how
    to continue. No metrics.json: the run stays resumable (`train --resume` trains on and scores
    it). What does not fit (a full disk) is named in one NotWrittenError instead (exit 2)."""
    from virus_nerf.utils.io import Outputs

    out, mapper = trainer.run_dir, trainer.mapper
    exc.reported = True
    if mapper.step == 0 or not mapper.frames:
        kept = (f"the run stays as it was (continue with `virus-nerf train --resume --out {out}`)"
                if (out / CHECKPOINT).is_file() else "nothing to keep")
        print(f"train: stopped by {exc.name} before the first training step; {kept}")
        return
    outputs = Outputs()
    outputs.write(out / MAP_DIR, lambda: mapper.snapshot(out / MAP_DIR, replace=True))  # the run's lock is held
    outputs.write(out / CHECKPOINT, trainer.save_checkpoint)
    outputs.check(f"free some space and continue with `virus-nerf train --resume --out {out}`")
    drive = ""
    if trainer.config.online:
        drive = f", drive at {trainer.playback.recording_time(mapper.seconds) - trainer.t0:.1f} of " \
                f"{trainer.duration:.1f} s"
    print(f"train: stopped by {exc.name} at step {mapper.step} ({mapper.seconds:.1f} s of training{drive}); "
          f"map in {out / MAP_DIR}, checkpoint in {out / CHECKPOINT}; continue with "
          f"`virus-nerf train --resume --out {out}`")


def _check_final_checkpoint(trainer, kept) -> None:
    """An online run whose final checkpoint did not fit (Trainer.fit kept going): named now that
    the map and the results are written."""
    from virus_nerf.errors import NotWrittenError

    exc = trainer.checkpoint_error
    if exc is None:
        return
    have = ", ".join(str(p) for p in kept if p.exists()) or "nothing"
    earlier = (trainer.run_dir / CHECKPOINT).is_file()
    raise NotWrittenError(
        f"{trainer.run_dir / CHECKPOINT}: could not be written ({exc.strerror or exc}); kept: {have}"
        f"{' and the earlier checkpoint' if earlier else ''}; free some space and run `virus-nerf train --resume "
        f"--out {trainer.run_dir}` to train {'its last steps' if earlier else 'it'} again", exc.errno)


def _resume(out: Path, recording, cfg, quiet):
    """The resumed Trainer (from checkpoint.pt, or from step 0 if the run was stopped before its
    first checkpoint) and its TrainSummary after training on; called holding the run's lock."""
    from virus_nerf.config_io import to_dict
    from virus_nerf.trainer.loop import Trainer, TrainSummary
    from virus_nerf.trainer.train_log import truncate_log
    from virus_nerf.utils.io import remove_stale_partials, remove_stale_temps

    for name in (CHECKPOINT, METRICS, METRICS_VS_TIME, CONFIG, RUN_INFO, TRAIN_LOG):
        remove_stale_temps(out / name)  # left by a process killed while writing (the lock proves it)
    remove_stale_partials(out / PLOTS, owned=True)
    trainer = Trainer(recording, cfg, out, quiet=quiet)
    if (out / CHECKPOINT).is_file():
        header = read_checkpoint_header(out / CHECKPOINT, cfg)
        trainer.load_checkpoint(out / CHECKPOINT)
        finished = trainer.done()
        if finished and (out / METRICS).is_file():
            raise UsageError(
                f"--resume {out}: the run is finished (step {header['step']}, {header['seconds']:.1f} s of training "
                f"reached the budget {_budget(cfg)}) and has its metrics.json; nothing to resume "
                "(give a larger --max-steps or --max-time to train on)"
            )
    else:  # stopped before its first checkpoint: its config.json and run.json say how to start it
        print(f"{out}: no checkpoint yet (stopped before the first one); training from step 0", file=sys.stderr)
        if (out / TRAIN_LOG).is_file():
            truncate_log(out / TRAIN_LOG, 0)
        finished = False
    if finished:  # budget reached before the metrics were written: evaluate only (no step, no file rewritten)
        return trainer, TrainSummary(trainer.mapper.step, trainer.mapper.seconds, trainer.mapper.samples)

    def started() -> None:  # the first step worked: from now on the run is one of this config
        if to_dict(cfg) != _saved_config(out):
            write_json_atomic(out / CONFIG, to_dict(cfg))

    return trainer, _fit(trainer, started)


# bytes of working memory a marched sample takes in a training step (its positions, the hash
# encoding's levels and the MLPs' activations, forward and backward): the slope of peak RSS over
# the samples of a step, benchmarks/bench_step_memory.py (results/step_memory_d48.json, D48)
SAMPLE_BYTES = 2232


def check_batch_memory(cfg, limit: int | None = None, what: str = "--batch-size") -> None:
    """Refuse, before any work, a --batch-size whose step could need more than half the memory
    this process may use (utils.memory's rule). What a step needs grows with its samples, not its
    rays: the bound is the marcher's worst case, every ray keeping march.max_samples samples (a
    step in the grid's warm-up comes within a few times of it)."""
    from virus_nerf.utils.memory import memory_limit

    limit = memory_limit() if limit is None else limit
    per_ray = cfg.march.max_samples * SAMPLE_BYTES
    need = cfg.batch_size * per_ray
    if limit is not None and need > limit / 2:
        raise UsageError(
            f"{what} {cfg.batch_size}: a step may march up to {cfg.march.max_samples} samples a ray "
            f"(march.max_samples), {need / 2**30:.1f} GiB at {SAMPLE_BYTES} bytes a sample, and this machine has "
            f"{limit / 2**30:.1f} GiB; expected at most {int(limit // 2 // per_ray)} (the default is 2048)"
        )


def _finish_without_ground_truth(trainer, out: Path, cfg, summary, resume: bool, warnings=()) -> dict:
    """A run with no ground truth: its map into OUT/map/, then metrics.json (gt null, the train
    block; it marks the run finished as for a scored run) and one line that nothing was scored."""
    from virus_nerf.evaluation.metrics import metrics_document
    from virus_nerf.trainer.run_folder import train_summary_block
    from virus_nerf.utils.io import write_json_atomic

    info = trainer.mapper.snapshot(out / MAP_DIR, replace=resume or (out / MAP_DIR).is_dir())
    doc = metrics_document({}, cfg.evaluation.zones, train_summary_block(cfg, summary), gt=None, warnings=warnings)
    write_json_atomic(out / METRICS, doc)
    for w in warnings:
        print(f"warning: {w}")
    print(
        f"trained {summary.steps} steps in {summary.seconds:.1f} s; no ground truth (--gt none): no metrics "
        f"computed; map ({info.map_known:.1%} known) in {out / MAP_DIR}"
    )
    _check_final_checkpoint(trainer, [out / MAP_DIR, out / METRICS])
    return doc


def _budget(cfg) -> str:
    parts = []
    if cfg.max_steps is not None:
        parts.append(f"max_steps {cfg.max_steps}")
    if cfg.online:
        parts.append(f"online, playback_speed {cfg.playback_speed:g}")
    elif cfg.max_time is not None:
        parts.append(f"max_time {cfg.max_time:g} s")
    return ", ".join(parts)


def _saved_config(out: Path):
    try:
        return json.loads((out / CONFIG).read_text())
    except (OSError, ValueError):
        return None


# set by a parent (`virus-nerf online`) to its pid: the `train` child dies with that parent
PARENT_ENV = "VIRUS_NERF_PARENT_PID"


def watch_parent(poll_s: float = 0.5) -> bool:
    """Die (SIGTERM to itself) when the parent named by $VIRUS_NERF_PARENT_PID is gone.

    The experiments start each training as a child process; killing the experiment must not
    leave its trainings running as orphans. A daemon thread polls os.getppid(), which changes
    when the parent dies (the child is handed to init). Linux's prctl(PR_SET_PDEATHSIG) is not
    used: it fires when the parent *thread* ends, and the runs are started from pool threads.
    Returns whether it watches (only if the variable names the actual parent).
    """
    import signal
    import threading
    import time

    want = os.environ.get(PARENT_ENV, "")
    if not want.isdigit() or os.getppid() != int(want):
        return False
    parent = int(want)

    def poll() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)  # the run folder stays resumable, as after any kill

    threading.Thread(target=poll, name="watch-parent", daemon=True).start()
    return True


def train(
    out: Path,
    data: Path | None = None,
    room: str | None = None,
    config: Path | None = None,
    resume: bool = False,
    quiet: bool = False,
    gt: str | None = None,
    playback_speed: float | None = None,
    knobs: Annotated[TrainFlags, tyro.conf.arg(name="")] = NO_FLAGS,  # type: ignore[valid-type]
) -> None:
    """Train a VIRUS-NeRF (or Instant-NGP) on a recording, then evaluate its 2D scans.

    Writes OUT/ (refused if it exists, unless --resume): config.json, run.json, train_log.csv,
    checkpoint.pt, metrics.json (docs/method.md 7), metrics_vs_time.csv and plots/. Everything is
    checked before OUT is made; a training that fails before its first checkpoint removes OUT.
    --resume continues an interrupted run from its checkpoint (its data and room come from
    OUT/run.json; a run killed before its first checkpoint trains from step 0); a finished run
    (budget reached, metrics.json written) is refused untouched, unless a larger
    --max-steps/--max-time is given, whose results then replace the old ones. Flags given with
    --resume reach config.json only once the resumed run has made its first step. One process
    trains in OUT at a time (OUT/run.lock); a second is refused with the first one's pid.

    Every knob of the run's config (config.json) has a flag derived from its field, grouped by
    section: --batch-size, --optim.lr, --march.step-size, --virus-grid.warmup-steps and so on.
    The short flags are these derived flags themselves (a top-level field has no section), but
    for three: --sensors takes a comma-separated list, --playback sets playback_speed and --gt
    sets evaluation.gt. A flag given replaces that one value of the --config file (or of the
    run's config.json with --resume), which replaces the default; a value out of range is
    refused naming the flag. The evaluation zones are set in a config file only.

    Args:
        out: New run folder (with --resume: the run to continue).
        data: Dataset folder in the ETHZ format (holds camera_intrinsics.CSV and ROOM/); required unless --resume.
        room: Room folder name inside DATA (e.g. office); required unless --resume.
        config: JSON config file (a run's config.json works); flags given here override it.
        resume: Continue the run in OUT from its checkpoint.
        quiet: No progress bar.
        gt: Ground truth of the evaluation, one or more of map (default; LiDAR map slice as solid
            3 cm voxels), exact (the simulator's exact scene; simulated recordings only), paper (the
            authors' raster protocol), comma-separated; the first is the primary (metrics.json's
            own, metric vs time), the others go to by_gt; or none (no ground truth: train and write
            the map to OUT/map/, score nothing; also chosen, with a note, when the recording has no
            LiDAR map and --gt is not given).
        playback_speed: Deprecated: the old name of --playback.
        knobs: The config's knobs (config.json's fields), given ones only.
    """
    out = Path(out)
    given, flags = train_flags(knobs, gt, playback_speed)
    watch_parent()
    if room is not None and (not room.strip() or "/" in room or "\\" in room or room in (".", "..")):
        raise UsageError(f"--room {room!r}: expected the name of a room folder inside --data (e.g. office)")
    if resume:
        saved_cfg, info = open_run(out, "--resume")
        if data is not None and Path(data).resolve() != Path(info.data).resolve():
            raise UsageError(f"--data {data}: the run in {out} was trained on {info.data} (see its run.json); "
                             "omit --data and --room with --resume")
        if room is not None and room != info.room:
            raise UsageError(f"--room {room}: the run in {out} was trained on room {info.room!r}; "
                             "omit --data and --room with --resume")
        cfg = _resolve_config(config, given, flags, base=saved_cfg)
        with _stops(cfg):
            run_training(Path(info.data), info.room, out, cfg, quiet=quiet or None, resume=True)
        return
    if data is None or room is None:
        raise UsageError(f"{'--data' if data is None else '--room'} is required: give --data DIR --room NAME "
                         "(or --resume to continue the run in --out)")
    cfg = _resolve_config(config, given, flags)
    with _stops(cfg):
        run_training(data, room, out, cfg, quiet=True if quiet else None, auto_gt=gt is None)


def _stops(cfg):
    """Online (mapping while driving, a robot's process): SIGINT and SIGTERM keep the map and the
    checkpoint (keep_stopped_run) and exit 130 / 143; offline runs keep the old behaviour."""
    import contextlib

    from virus_nerf.utils.stop import stop_on_signals

    return stop_on_signals() if cfg.online else contextlib.nullcontext()


def evaluate(run: Path, out: Path | None = None, n_rays: int | None = None, gt: str | None = None) -> None:
    """Evaluate a trained run's 2D scans against the ground truth, beside the LiDAR, USS and IRS scans.

    Args:
        run: A run folder written by `virus-nerf train`.
        out: metrics.json to write (default RUN/evaluation/metrics.json; never overwritten). An
            evaluation killed before it wrote metrics.json (its plots there) is done again.
        n_rays: Rays per 360 deg scan (default: the run's setting, 512).
        gt: Ground truth, one or more of map, exact (simulated recordings only), paper,
            comma-separated (default: the run's setting, map); the first is the document's own.
    """
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.evaluation.evaluate import parse_gt_flag
    from virus_nerf.evaluation.plots import plots_dir_for
    from virus_nerf.utils.io import remove_stale_partials

    if n_rays is not None:
        require_int("--n-rays", n_rays, 1, 1_000_000)
    protocols = parse_gt_flag(gt) if gt is not None else None
    out = Path(out) if out is not None else Path(run) / "evaluation" / "metrics.json"
    if out.exists():
        raise OutputExistsError(out)
    # plots without metrics.json: an evaluation killed before its end, done again whole (plots
    # replaced once the new ones are complete); `.<plots>.partial-<pid>-*` of dead attempts go
    remove_stale_partials(plots_dir_for(out))
    redo = plots_dir_for(out).exists()
    open_run(run, "--run")
    # a run a `train` still works in is said to be so (with or without a checkpoint yet), before
    # its files are read; nothing is written into a run that cannot be evaluated
    RunLock(Path(run), "--run").probe()
    trainer, cfg, _ = load_trained(run, "--run")
    lock = RunLock(Path(run), "--run").acquire()  # not while a `train` (or another evaluate) works in it
    try:
        _evaluate_run(run, out, trainer, cfg, n_rays, protocols, redo)
    finally:
        lock.release()


def _evaluate_run(run: Path, out: Path, trainer, cfg, n_rays: int | None, protocols, redo: bool) -> None:
    """`evaluate`'s work, holding the run's lock."""
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.evaluation.evaluate import check_ground_truth_inputs
    from virus_nerf.evaluation.plots import plots_dir_for, write_plots
    from virus_nerf.trainer.loop import TrainSummary
    from virus_nerf.trainer.run_folder import train_summary_block

    if n_rays is not None or protocols is not None:
        ev = cfg.evaluation
        ev = dataclasses.replace(ev, n_rays=n_rays if n_rays is not None else ev.n_rays,
                                 gt=protocols if protocols is not None else ev.gt)
        cfg = dataclasses.replace(cfg, evaluation=ev)
        trainer.config = cfg
    if not cfg.evaluation.gt:
        raise UsageError(f"--run {run}: the run has no ground truth (evaluation.gt none) and --gt names none; "
                         "give --gt map, exact or paper to score it")
    check_ground_truth_inputs(trainer.recording, cfg.evaluation.gt)
    result = _final_evaluation(trainer, run)
    summary = TrainSummary(trainer.mapper.step, trainer.mapper.seconds, trainer.mapper.samples)
    from virus_nerf.evaluation.safety import mapper_safety, safety_line

    trainer.prepare()  # the frames the run trained on and its stereo points (cached): the map `train` judged
    run_safety = mapper_safety(trainer.mapper, trainer.recording, cfg.evaluation.height_band_m)
    write_plots(result, plots_dir_for(out), max_maps=8, replace=redo)
    if out.exists():  # another process finished the same evaluation meanwhile
        raise OutputExistsError(out)
    result.write_json(out, train=train_summary_block(cfg, summary),
                      safety=None if run_safety is None else run_safety.document)
    print(result.table())
    if run_safety is not None:
        print(safety_line(run_safety.document))
    print(f"wrote {out} and {plots_dir_for(out)}/")


def _final_evaluation(trainer, run: Path):
    """The run's evaluation with the instantaneous sensors; online, only test points the drive
    has reached count, and a run stopped before the first one has nothing to score."""
    from virus_nerf.errors import UsageError

    result = trainer.evaluate(with_sensors=True)
    if result is None:
        raise UsageError(
            f"{run}: the online run stopped at step {trainer.mapper.step} before the drive reached its first "
            "test point; there is nothing to score (train longer)"
        )
    return result
