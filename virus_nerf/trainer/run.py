"""A training run as a library: train, resume and evaluate into a run folder (`run_training`), and
load a trained run (`load_trained`); `virus-nerf train` and `evaluate` (trainer/command.py) are the
command line around these, and the demo and the experiments call them directly.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import tempfile
from pathlib import Path

from virus_nerf.engine.memory import check_batch_memory
from virus_nerf.errors import DISK_FULL_ERRNOS, DataFormatError, NotWrittenError, UsageError
from virus_nerf.trainer.config import check_device
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
    read_checkpoint,
)
from virus_nerf.utils.io import write_json_atomic


# ---------------------------------------------------------------------------- checks on inputs
def check_recording_for_training(recording, cfg, eval_recording=None) -> None:
    """Refuse, before any training, a recording the run could not train on or be scored on."""
    from virus_nerf.evaluation.evaluate import check_ground_truth_inputs
    from virus_nerf.evaluation.testpoints import require_test_points, split_file

    if not any((s.split == "train").any() for s in recording.stacks.values()):
        raise DataFormatError(split_file(recording), "no rows labelled 'train'; training needs at least one")
    ev = eval_recording or recording
    if cfg.evaluation.gt:
        require_test_points(ev)
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
    from virus_nerf.utils.seeding import use_threads

    cfg, info = open_run(run, flag)
    check_device(cfg)
    use_threads(cfg.threads)  # the run's: its scans are rendered as it rendered them
    state = read_checkpoint(Path(run) / CHECKPOINT, cfg)  # before the recording: a bad file fails at once
    if not Path(info.data).is_dir():  # named as run.json's field: these commands have no --data
        raise DataFormatError(Path(run) / RUN_INFO, f"data {info.data}: no such folder; expected the recording the "
                              "run was trained on (moved? give its new place in run.json's data)", field="data")
    source, _ = resolve_pose_source(Path(info.data) / info.room, poses or "optimised")  # no LiDAR: odometry only
    recording = load_recording(info.data, info.room, poses=source)
    # the frames a large or driving run decodes go to a folder of this process's own, removed with
    # the trainer: nothing is written into the run (it may lie on read-only media; exports share it)
    scratch = _reader_scratch()
    trainer = Trainer(recording, cfg, run, quiet=quiet, scratch=Path(scratch.name))
    trainer.scratch_folder = scratch  # kept as long as the trainer
    trainer.load_checkpoint(Path(run) / CHECKPOINT, state)
    return trainer, cfg, info


READER_FRAMES = "reader-frames"  # the user cache's folders of the frames evaluate and export decode


def _reader_scratch() -> tempfile.TemporaryDirectory:
    """A folder of this process's own for the frames a reader of a run decodes (memory-mapped
    beyond 1 GiB, and a driving run's spilled frames): under the user cache, on a disk, where
    frames beyond memory belong (a /tmp in memory would hold them in RAM), and one a killed
    process left is removed by the next; else in $TMPDIR."""
    import os

    from virus_nerf.utils.cache import cache_root
    from virus_nerf.utils.io import remove_stale_partials

    root = cache_root()
    if root is not None:
        try:
            root.mkdir(parents=True, exist_ok=True)
            remove_stale_partials(root / READER_FRAMES)
            return tempfile.TemporaryDirectory(prefix=f".{READER_FRAMES}.partial-{os.getpid()}-", dir=root)
        except OSError:
            pass
    return tempfile.TemporaryDirectory(prefix="virus-nerf-frames-")


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
    from virus_nerf.trainer.trust import map_warnings
    from virus_nerf.utils.stop import Stopped

    out = Path(out)
    _refuse_existing_out(out, resume)
    cfg, recording, eval_recording = _prepare(data, room, cfg, auto_gt)
    lock = RunLock(out, "--resume" if resume else "--out")
    if resume:
        lock.acquire()  # one process trains in a run folder at a time (released when it dies)
    try:
        trainer, summary = _resume(out, recording, cfg, quiet) if resume else \
            _start(data, room, out, recording, cfg, lock, quiet)
        warnings = map_warnings(trainer)
        if resume and not cfg.plots and (out / PLOTS).is_dir():  # kept (never deleted), but not this run's
            warnings.append(f"{out / PLOTS}/ is from the run's earlier evaluation: plots are off, so "
                            "they were not drawn again; --plots draws this run's")
        if not cfg.evaluation.gt:
            _keep_resumed_config(out, cfg, resume)
            return _finish_without_ground_truth(trainer, out, cfg, summary, resume, warnings)
        try:
            result, run_safety = _score(trainer, out, cfg, eval_recording)
            doc = _write_results(trainer, out, cfg, summary, result, run_safety, warnings, resume)
        except Stopped as exc:  # SIGINT/SIGTERM while scoring: the training is whole, the results are not
            keep_stopped_scoring(trainer, exc)
            raise
    finally:
        lock.release()
    _print_results(trainer, out, summary, result, run_safety, warnings)
    return doc


def _refuse_existing_out(out: Path, resume: bool) -> None:
    """A new run's OUT must not exist (stale `.OUT.partial-*` of a killed start are cleared first)."""
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.utils.io import remove_stale_partials

    if resume:
        return
    remove_stale_partials(out)  # `.OUT.partial-<pid>-*` of a `train --out OUT` killed while starting
    if out.exists():
        raise OutputExistsError(out)


def _prepare(data: Path, room: str, cfg, auto_gt: bool):
    """(config, training recording, evaluation recording), every input checked before a file is
    written: the device, the batch's memory, the poses (odometry when the config asks or there is
    no LiDAR), no ground truth when `auto_gt` finds no LiDAR map, the recording's split and
    ground-truth inputs."""
    from virus_nerf.data.ethz import load_recording, resolve_pose_source
    from virus_nerf.utils.seeding import seed_everything, use_threads

    check_device(cfg)
    check_batch_memory(cfg)
    use_threads(cfg.threads)
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
    return cfg, recording, eval_recording


def _start(data: Path, room: str, out: Path, recording, cfg, lock, quiet):
    """A new run: OUT appears with config.json, run.json and its lock held in one rename, then
    the training; a failure before the first checkpoint (or map) removes OUT again."""
    from virus_nerf.config_io import to_dict
    from virus_nerf.trainer.loop import Trainer
    from virus_nerf.utils.io import new_output_dir

    with new_output_dir(out) as tmp:  # OUT appears with both files or not at all, and locked
        write_json_atomic(tmp / CONFIG, to_dict(cfg))
        RunInfo(data=str(Path(data).resolve()), room=room).write(tmp)
        lock.folder = tmp
        lock.acquire()  # the lock file's descriptor follows the folder's rename
    lock.folder = out
    try:
        trainer = Trainer(recording, cfg, out, quiet=quiet)
        return trainer, _fit(trainer)
    except BaseException as exc:
        if lock.holds(out) and not (out / CHECKPOINT).is_file() and not (out / MAP_DIR).is_dir():
            # nothing to resume: leave no half-made run behind (only our own folder: one renamed
            # aside by another process, and what took its name, are not ours)
            shutil.rmtree(out, ignore_errors=True)
            if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
                # not the command line's "nothing was lost ... --resume": there is no run left to resume
                raise NotWrittenError(
                    f"{exc.filename or out}: could not be written ({exc.strerror or exc}) before the run's first "
                    f"checkpoint, so {out} was removed (nothing to resume); free some space and run the same "
                    "`virus-nerf train` command again", exc.errno) from exc
        raise


def _keep_resumed_config(out: Path, cfg, resume: bool) -> None:
    """A resumed run is one of the config it was resumed with (config.json rewritten if it differs)."""
    from virus_nerf.config_io import to_dict

    if resume and to_dict(cfg) != _saved_config(out):
        write_json_atomic(out / CONFIG, to_dict(cfg))


def _score(trainer, out: Path, cfg, eval_recording):
    """(EvaluationResult, RunSafety | None) of `score_run`, in the true (optimised) frame, and the
    final point of the metric-vs-time curve."""
    if eval_recording is not trainer.recording:
        trainer.evaluate_on(eval_recording)  # the map and test points are judged in the true frame
    result, run_safety = score_run(trainer, out, cfg)
    trainer.record_eval(result, None)
    return result, run_safety


def score_run(trainer, run: Path, cfg):
    """(EvaluationResult, RunSafety | None): a trained run's scores, as `train` ends and `evaluate`
    gives them again: its scans with the instantaneous sensors against the ground truth
    (`final_evaluation`), and the map its snapshots write, judged against the LiDAR map on the
    frames it trained on (and their stereo points)."""
    from virus_nerf.evaluation.safety import mapper_safety

    result = final_evaluation(trainer, run)
    trainer.prepare()  # a trainer loaded from its checkpoint: the frames and stereo points it trained on
    return result, mapper_safety(trainer.mapper, trainer.recording, cfg.evaluation.height_band_m)


def print_scores(result, run_safety, warnings) -> None:
    """The scores' table, the warnings and the safety line, as `train` and `evaluate` print them."""
    from virus_nerf.evaluation.safety import safety_line

    print(result.table())
    for w in warnings:
        print(f"warning: {w}")
    if run_safety is not None:
        print(safety_line(run_safety.document))


def _write_results(trainer, out: Path, cfg, summary, result, run_safety, warnings, resume: bool) -> dict:
    """The run's final files: the map an interrupted online run left (replaced by this run's), the
    plots (unless the config's `plots` is off), the config of a resumed run, then metrics.json last
    (it marks a finished run)."""
    from virus_nerf.trainer.report import write_run_plots
    from virus_nerf.trainer.run_folder import write_run_metrics

    if (out / MAP_DIR).is_dir():  # the map an interrupted online run left: this run's map now
        trainer.mapper.snapshot(out / MAP_DIR, replace=True)
    if cfg.plots:  # plots first: metrics.json marks the end
        write_run_plots(out, result, trainer.eval_history, replace=resume, safety=run_safety)
    _keep_resumed_config(out, cfg, resume)  # a finished run's resume: evaluated with it
    return write_run_metrics(out, result, cfg, summary, safety=None if run_safety is None else run_safety.document,
                             warnings=warnings)


def _print_results(trainer, out: Path, summary, result, run_safety, warnings) -> None:
    """The table, the warnings, the safety lines and the speed; then a final checkpoint that did
    not fit is named (exit 2)."""
    print_scores(result, run_safety, warnings)
    print(
        f"trained {summary.steps} steps in {summary.seconds:.1f} s "
        f"({summary.steps_per_s:.2f} steps/s, {summary.samples_per_s / 1e6:.3f} M samples/s); "
        f"results in {out}"
    )
    _check_final_checkpoint(trainer, [out / PLOTS, out / METRICS])


def _fit(trainer, started=None):
    """trainer.fit(); stopped by SIGINT/SIGTERM (utils/stop.py, after the step in progress): the
    map and the checkpoint are kept first (`keep_stopped_run`)."""
    from virus_nerf.utils.stop import Stopped

    try:
        return trainer.fit(started)
    except Stopped as exc:
        keep_stopped_run(trainer, exc)
        raise


def keep_stopped_run(trainer, exc) -> None:
    """A run stopped by a signal (after its step in progress): OUT/map/ (map.pgm/.yaml/.png,
    prob.*, snapshot.json; small, written first), then checkpoint.pt (large), then one line saying
    where they are and how to continue. No metrics.json: the run stays resumable (`train --resume`
    trains on and scores it). What does not fit (a full disk) is named in one NotWrittenError
    instead (exit 2)."""

    out, mapper = trainer.run_dir, trainer.mapper
    exc.reported = True
    if mapper.step == 0 or not mapper.frames:
        kept = (f"the run stays as it was (continue with `virus-nerf train --resume --out {out}`)"
                if (out / CHECKPOINT).is_file() else "nothing to keep")
        print(f"train: stopped by {exc.name} before the first training step; {kept}")
        return
    _keep_map_and_checkpoint(trainer, f"free some space and continue with `virus-nerf train --resume --out {out}`")
    drive = ""
    if trainer.config.online:
        drive = f", drive at {trainer.playback.recording_time(mapper.seconds) - trainer.t0:.1f} of " \
                f"{trainer.duration:.1f} s"
    print(f"train: stopped by {exc.name} at step {mapper.step} ({mapper.seconds:.1f} s of training{drive}); "
          f"map in {out / MAP_DIR}, checkpoint in {out / CHECKPOINT}; continue with "
          f"`virus-nerf train --resume --out {out}`")


def keep_stopped_scoring(trainer, exc) -> None:
    """A run stopped by a signal after its last step, while it was scored (evaluation, plots):
    OUT/map/ and checkpoint.pt as `keep_stopped_run` keeps them (the checkpoint only if it is not
    there yet: the final one is), no metrics.json, and one line: `train --resume` scores it without
    training (run_training's docstring)."""
    out, mapper = trainer.run_dir, trainer.mapper
    exc.reported = True
    _keep_map_and_checkpoint(trainer, f"free some space and score it with `virus-nerf train --resume --out {out}`",
                             checkpoint=not (out / CHECKPOINT).is_file())
    print(f"train: stopped by {exc.name} while scoring the finished training (step {mapper.step}); map in "
          f"{out / MAP_DIR}, checkpoint in {out / CHECKPOINT}; score it with `virus-nerf train --resume --out {out}`")


def _keep_map_and_checkpoint(trainer, hint: str, checkpoint: bool = True) -> None:
    """OUT/map/ of the mapper now (small, first), then (`checkpoint`) checkpoint.pt; what did not
    fit is named in one NotWrittenError with `hint` (utils/io.Outputs)."""
    from virus_nerf.utils.io import Outputs

    out, mapper = trainer.run_dir, trainer.mapper
    outputs = Outputs()
    outputs.write(out / MAP_DIR, lambda: mapper.snapshot(out / MAP_DIR, replace=True))  # the run's lock is held
    if checkpoint:
        outputs.write(out / CHECKPOINT, trainer.save_checkpoint)
    outputs.check(hint)


def _check_final_checkpoint(trainer, kept) -> None:
    """An online run whose final checkpoint did not fit (Trainer.fit kept going): named now that
    the map and the results are written."""
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
    for folder in (PLOTS, MAP_DIR):  # a folder's `.NAME.partial-*` left by a process killed while writing it
        remove_stale_partials(out / folder, owned=True)
    trainer = Trainer(recording, cfg, out, quiet=quiet)
    if (out / CHECKPOINT).is_file():
        state = read_checkpoint(out / CHECKPOINT, cfg)
        trainer.load_checkpoint(out / CHECKPOINT, state)
        finished = trainer.done()
        if finished and (out / METRICS).is_file():
            raise UsageError(
                f"--resume {out}: the run is finished (step {state['step']}, {state['seconds']:.1f} s of training "
                f"reached the budget {_budget(cfg)}) and has its metrics.json; nothing to resume "
                f"(give a larger {_binding_flags(trainer)} to train on)"
            )
    else:  # stopped before its first checkpoint: its config.json and run.json say how to start it
        print(f"{out}: no checkpoint yet (stopped before the first one); training from step 0", file=sys.stderr)
        if (out / TRAIN_LOG).is_file():
            truncate_log(out / TRAIN_LOG, 0)
        finished = False
    if finished:  # budget reached before the metrics were written: evaluate only (no step, no file rewritten)
        trainer.prepare()  # on the frames and stereo points (cached) it trained on, as `export` does
        # the steps ran in the process that wrote the checkpoint: its device names their rate
        return trainer, TrainSummary(trainer.mapper.step, trainer.mapper.seconds, trainer.mapper.samples,
                                     device=trainer.trained_on, threads=trainer.trained_threads)

    def started() -> None:  # the first step worked: from now on the run is one of this config
        if to_dict(cfg) != _saved_config(out):
            write_json_atomic(out / CONFIG, to_dict(cfg))

    return trainer, _fit(trainer, started)


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


def _binding_flags(trainer) -> str:
    """The budget flag(s) whose limit the run reached: only a larger one of these trains on."""
    c, m = trainer.config, trainer.mapper
    flags = [flag for flag, reached in (("--max-steps", c.max_steps is not None and m.step >= c.max_steps),
                                        ("--max-time", trainer.max_time is not None and m.seconds >= trainer.max_time))
             if reached]
    return " and ".join(flags) or "--max-steps or --max-time"


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


def final_evaluation(trainer, run: Path):
    """The run's evaluation with the instantaneous sensors; online, only test points the drive
    has reached count, and a run stopped before the first one has nothing to score."""
    from virus_nerf.errors import UsageError
    from virus_nerf.trainer.report import RUN_SCAN_MAPS

    result = trainer.evaluate(with_sensors=True, keep_scans=RUN_SCAN_MAPS)  # the scans the plots draw
    if result is None:
        raise UsageError(
            f"{run}: the online run stopped at step {trainer.mapper.step} before the drive reached its first "
            "test point; there is nothing to score (train longer)"
        )
    return result
