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
from pathlib import Path
from typing import Annotated

import tyro

from virus_nerf.config_flags import FlagSpec, apply_flags, flag_names, flag_tree, with_annotation
from virus_nerf.errors import (
    UsageError,
    renamed_flag,
    require_int,
    require_room_name,
    say_notes,
)
from virus_nerf.sampler.shares import SENSORS
from virus_nerf.trainer.config import PRODUCT_KNOBS, TrainConfig
from virus_nerf.trainer.run_folder import (
    RunLock,
    open_run,
)
from virus_nerf.utils.parent import watch_parent

# ---------------------------------------------------------------------------- flags
# The config fields whose `train` flag is not the one derived from the field (config_flags.py):
# --sensors takes a comma-separated list, --playback is playback_speed's flag (the old name
# --playback-speed is a parameter of `train`), evaluation.gt is set by `train --gt` and the
# evaluation zones (a list of objects) by a config file only.
TRAIN_FLAG_SPECS: dict[str, FlagSpec | None] = {
    "sensors": FlagSpec(type=str, metavar="NAMES", help=f"Sensors to train on, comma-separated, of {','.join(SENSORS)}."),
    "max_steps": FlagSpec(help="Training steps. With no time budget given (no --max-time, no max_time in the "
                               "--config file, no --resume) it also sets max_time None: a run bounded by steps, "
                               "bit-reproducible on CPU at the same --threads (not --online: its frames follow "
                               "the training clock)."),
    "playback_speed": FlagSpec(name="playback", help="Online mode: recording seconds per training second (the "
                                                     "frame feeder's speed, as map-bag's --playback on the wall clock)."),
    "evaluation.gt": None,
    "evaluation.zones": None,
}
TrainFlags = flag_tree(TrainConfig, TRAIN_FLAG_SPECS)
NO_FLAGS = TrainFlags()  # `train` called with no config flag (never changed: train_flags copies)
# `train --help` lists the product knobs (trainer/config.py PRODUCT_KNOBS); `--help-all` all
TrainProductFlags = flag_tree(TrainConfig, TRAIN_FLAG_SPECS, only=PRODUCT_KNOBS)


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
    from virus_nerf.evaluation.config import parse_gt_flag

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


def _layered(below: dict, above: dict) -> dict:
    """`above`'s keys over `below`'s, section by section (nested dicts merged, other values replaced)."""
    out = dict(below)
    for key, value in above.items():
        out[key] = _layered(below[key], value) if isinstance(value, dict) and isinstance(below.get(key), dict) \
            else value
    return out


def _resolve_config(config: Path | None, given: dict, flags: dict, base=None) -> TrainConfig:
    """The run's TrainConfig: the --config file's keys over `base` (the run's own on --resume) or
    over the defaults, with the fields the flags give on top; a key or flag not given keeps the
    value below it."""
    from virus_nerf.config_io import from_dict, read_json_config, to_dict, with_added_keys
    from virus_nerf.trainer.run_folder import is_run_config

    file_sets_time = False
    if config is not None:
        data = read_json_config(config)
        if is_run_config(config):  # a run's own: a key added since loads as the run was made
            data = with_added_keys(data)
        if base is not None and isinstance(data, dict):  # --resume: the file changes what it names, as flags do
            data = _layered(to_dict(base), data)
        cfg = from_dict(TrainConfig, data, file=Path(config))
        file_sets_time = "max_time" in data  # a file that gives its own budget keeps it
    else:
        cfg = base if base is not None else TrainConfig()
    if given.get("max_steps") is not None and "max_time" not in given and not file_sets_time and base is None:
        # --max-steps with no time budget given (flag or file): a step-bounded, bit-reproducible run
        given = {**given, "max_time": None}
    return apply_flags(cfg, given, flags)


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
    --help lists the knobs a robot user sets; --help-all lists every knob (the research ones:
    sensor models, grid and tracker internals, kernels, the studies' switches). The short flags
    are these derived flags themselves (a top-level field has no section), but for three:
    --sensors takes a comma-separated list, --playback sets playback_speed and --gt sets
    evaluation.gt. A flag given replaces that one value of the --config file (or of the run's
    config.json with --resume), which replaces the default; a value out of range is refused
    naming the flag. The evaluation zones are set in a config file only.

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
    if room is not None:
        require_room_name(room)
    if resume:
        saved_cfg, info = open_run(out, "--resume")
        if data is not None and Path(data).resolve() != Path(info.data).resolve():
            raise UsageError(f"--data {data}: the run in {out} was trained on {info.data} (see its run.json); "
                             "omit --data and --room with --resume")
        if room is not None and room != info.room:
            raise UsageError(f"--room {room}: the run in {out} was trained on room {info.room!r}; "
                             "omit --data and --room with --resume")
        cfg = _resolve_config(config, given, flags, base=saved_cfg)
        _refuse_unused_budget(cfg, given)
        # the training is imported here: the flags, --help and their errors need no torch
        from virus_nerf.trainer.run import run_training
        from virus_nerf.utils.stop import stop_on_signals

        say_notes()
        with stop_on_signals():  # Ctrl-C, `systemctl stop`: kept after the step in progress (run.py)
            run_training(Path(info.data), info.room, out, cfg, quiet=quiet or None, resume=True)
        return
    if data is None or room is None:
        raise UsageError(f"{'--data' if data is None else '--room'} is required: give --data DIR --room NAME "
                         "(or --resume to continue the run in --out)")
    cfg = _resolve_config(config, given, flags)
    _refuse_unused_budget(cfg, given)
    from virus_nerf.trainer.run import run_training
    from virus_nerf.utils.stop import stop_on_signals

    say_notes()
    with stop_on_signals():
        run_training(data, room, out, cfg, quiet=True if quiet else None, auto_gt=gt is None)


def _refuse_unused_budget(cfg, given: dict) -> None:
    """An online run lasts its drive (duration / playback; docs/method.md 3.6): a --max-time given
    with it would be ignored, so it is refused (a user's review: a 20 s budget trained 4.8 s)."""
    if cfg.online and given.get("max_time") is not None:
        raise UsageError(f"--max-time {given['max_time']:g}: an online run (--online) lasts its drive, the "
                         "recording's duration / --playback; drop --max-time (--max-steps still bounds it)")

def train_short_help():
    """`train` as `train --help` shows it: the product knobs' flags alone (the command parses all)."""
    return with_annotation(train, "knobs", Annotated[TrainProductFlags, tyro.conf.arg(name="")])


def evaluate(run: Path, out: Path | None = None, n_rays: int | None = None, gt: str | None = None,
             plots: bool = True) -> None:
    """Evaluate a trained run's 2D scans against the ground truth, beside the LiDAR, USS and IRS scans.

    Args:
        run: A run folder written by `virus-nerf train`.
        out: metrics.json to write (default RUN/evaluation/metrics.json; never overwritten). An
            evaluation killed before it wrote metrics.json (its plots there) is done again.
        n_rays: Rays per 360 deg scan (default: the run's setting, 512).
        gt: Ground truth, one or more of map, exact (simulated recordings only), paper,
            comma-separated (default: the run's setting, map); the first is the document's own.
        plots: The plots beside metrics.json (scan maps and metric bars: about 5 s of drawing on
            a 2-core CPU); --no-plots writes metrics.json alone, as `train --no-plots`.
    """
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.evaluation.config import parse_gt_flag
    from virus_nerf.evaluation.plots import plots_dir_for, stopped_attempts_plots
    from virus_nerf.utils.io import remove_stale_partials, require_makeable

    if n_rays is not None:
        require_int("--n-rays", n_rays, 1, 1_000_000)
    protocols = parse_gt_flag(gt, scores=True) if gt is not None else None
    out = Path(out) if out is not None else Path(run) / "evaluation" / "metrics.json"
    if out.exists():
        raise OutputExistsError(out)
    open_run(run, "--run")  # a --run that is no run folder is named as such, before --out is judged
    require_makeable("--out", out, out.parent)  # before ~10 s of loading and scoring
    # plots without metrics.json: an evaluation killed before its end, done again whole (plots
    # replaced once the new ones are complete); `.<plots>.partial-<pid>-*` of dead attempts go
    remove_stale_partials(plots_dir_for(out))
    redo = stopped_attempts_plots(plots_dir_for(out), out)  # a folder holding a user's files: refused
    # a run a `train` still works in is said to be so (with or without a checkpoint yet), before
    # its files are read; nothing is written into a run that cannot be evaluated
    RunLock(Path(run), "--run").probe()
    from virus_nerf.trainer.run import load_trained

    trainer, cfg, _ = load_trained(run, "--run")
    lock = RunLock(Path(run), "--run").acquire()  # not while a `train` (or another evaluate) works in it
    try:
        _evaluate_run(run, out, trainer, cfg, n_rays, protocols, redo, plots=plots)
    finally:
        lock.release()


def _evaluate_run(run: Path, out: Path, trainer, cfg, n_rays: int | None, protocols, redo: bool,
                  plots: bool = True) -> None:
    """`evaluate`'s work, holding the run's lock."""
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.evaluation.evaluate import check_ground_truth_inputs
    from virus_nerf.evaluation.plots import plots_dir_for, write_plots
    from virus_nerf.trainer.loop import TrainSummary
    from virus_nerf.trainer.report import RUN_SCAN_MAPS
    from virus_nerf.trainer.run import print_scores, score_run
    from virus_nerf.trainer.run_folder import train_summary_block, training_finished

    if n_rays is not None or protocols is not None:
        ev = cfg.evaluation
        ev = dataclasses.replace(ev, n_rays=n_rays if n_rays is not None else ev.n_rays,
                                 gt=protocols if protocols is not None else ev.gt)
        cfg = dataclasses.replace(cfg, evaluation=ev)
        trainer.config = cfg
    if not cfg.evaluation.gt:
        from virus_nerf.evaluation.evaluate import scene_path

        rec = trainer.recording
        usable = (["map", "paper"] if rec.map_path is not None else []) + \
            (["exact"] if scene_path(rec).is_file() else [])  # the protocols whose input the recording has
        if not usable:
            raise UsageError(f"--run {run}: the run was trained without ground truth, and its recording has no "
                             "LiDAR map (maps/map_*.pcd) to score it against; its map is in the run (export "
                             "writes it again)")
        raise UsageError(f"--run {run}: the run was trained without ground truth (evaluation.gt none); "
                         f"give --gt {' or '.join(usable)} to score it"
                         + ("" if rec.map_path is not None else " (its recording has no LiDAR map, only the "
                            "simulator's scene.json)"))
    check_ground_truth_inputs(trainer.recording, cfg.evaluation.gt)
    result, run_safety = score_run(trainer, run, cfg)  # as `train` scored it
    # the run's steps and rate, from its checkpoint: its device names where they ran
    summary = TrainSummary(trainer.mapper.step, trainer.mapper.seconds, trainer.mapper.samples,
                           device=trainer.trained_on, threads=trainer.trained_threads)
    from virus_nerf.trainer.trust import map_warnings

    warnings = map_warnings(trainer)  # the run's own (metrics.json's): this document stands alone
    if not training_finished(run, trainer.mapper.step):  # stopped part-way: said, as export says it
        unfinished = (f"the run's training did not finish (stopped at step {trainer.mapper.step}; no metrics.json "
                      f"of its last step): scored as it stands (`virus-nerf train --resume --out {run}` continues it)")
        print(f"note: --run {run}: {unfinished}")
        warnings = [unfinished, *warnings]
    if plots:
        write_plots(result, plots_dir_for(out), max_maps=RUN_SCAN_MAPS, replace=redo)
    elif redo:  # kept (never deleted), but not this evaluation's
        print(f"warning: {plots_dir_for(out)}/ is from an earlier evaluation stopped before its metrics.json; "
              "plots are off, so they were not drawn again")
    if out.exists():  # another process finished the same evaluation meanwhile
        raise OutputExistsError(out)
    result.write_json(out, train=train_summary_block(cfg, summary),
                      safety=None if run_safety is None else run_safety.document, warnings=warnings)
    print_scores(result, run_safety, warnings)
    print(f"wrote {out}" + (f" and {plots_dir_for(out)}/" if plots else ""))

