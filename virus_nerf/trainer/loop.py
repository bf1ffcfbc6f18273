"""The training loop (docs/method.md 3.6) of one run folder, driving a `Mapper`.

The Mapper (engine/mapper.py) owns the model and one training step (sample rays, render,
losses, Adam, grid updates); the Trainer owns the run: which frames the Mapper has (offline:
every training frame before the first step; online: each frame once the training clock times
the playback speed passes its timestamp), the budget, evaluations, logs and checkpoints.

Reproducible: one seed drives the ray sampler (numpy Generator) and the marcher jitter and
grid updates (torch Generator); both states go into the checkpoint, so a resumed run continues
bit for bit on CPU. A run bounded by --max-steps alone is bit-identical for the same seed;
a --max-time bound depends on the machine's speed, as any time budget does.
"""

from __future__ import annotations

import dataclasses
import io
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virus_nerf.config_io import to_dict
from virus_nerf.data.ethz import Recording
from virus_nerf.data.playback import FrameFeeder, Playback
from virus_nerf.engine.mapper import Mapper
from virus_nerf.engine.model import start_box
from virus_nerf.engine.schedule import Horizon, Schedules
from virus_nerf.engine.step_loss import stereo_line_of_sight
from virus_nerf.evaluation.evaluate import EvaluationResult, build_ground_truth, evaluate
from virus_nerf.losses import LossTerms
from virus_nerf.sampler.batch import BatchSampler
from virus_nerf.sampler.frames import MMAP_ABOVE_BYTES, FrameStore, build_frame_store, release_pages
from virus_nerf.stereo.depth import StereoConfig, small_room_config
from virus_nerf.trainer.config import TrainConfig
from virus_nerf.trainer.run_folder import (
    CHECKPOINT,
    METRICS_VS_TIME,
    EvalPoint,
    write_eval_history,
)
from virus_nerf.trainer.train_log import Every, LogRow, TrainLog, psnr_db
from virus_nerf.utils.clock import since_process_start
from virus_nerf.utils.io import atomic_path
from virus_nerf.utils.stop import stops_deferred

__all__ = ["Trainer", "TrainSummary"]


@dataclass
class TrainSummary:
    steps: int
    seconds: float  # training clock: steps and grid updates (start-up and evaluations excluded)
    samples: int  # samples actually marched and rendered, summed over steps
    startup_s: float | None = None  # process start to the first training step (this process)
    wall_s: float | None = None  # process start to the end of training (this process)
    device: str | None = None  # where the steps ran ("cpu", "cuda"), so a rate names its machine
    threads: int | None = None  # torch's CPU threads of this process's steps (the numbers depend on it)

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else 0.0


class Trainer:
    """Owns one run folder: config.json, train_log.csv, checkpoint.pt, metrics.json, plots/."""

    def __init__(self, recording: Recording, config: TrainConfig, run_dir: Path, quiet: bool | None = None,
                 scratch: Path | None = None):
        self.recording = recording
        self.config = config
        self.run_dir = Path(run_dir)
        # where a large frame store is memory-mapped and spilled: the run folder, or for a reader of
        # the run (evaluate, export) a folder of its own, so that it writes nothing into the run
        self.scratch = self.run_dir if scratch is None else Path(scratch)
        self.quiet = (not sys.stderr.isatty()) if quiet is None else quiet
        box = start_box(recording, config)
        # the learning rate decays over the budget; online over the drive, whose frames arrive as
        # the training clock (times the playback speed) passes them
        horizon = Horizon.drive(self.duration, config.playback_speed, config.max_steps) if config.online \
            else Horizon.of(config)
        self.mapper = Mapper(config, {s: st.intrinsics for s, st in recording.stacks.items()}, box,
                             Schedules.of(config, horizon))
        if config.online:  # the frames arrive one by one: a long drive's beyond the budget go to disk
            self.mapper.spill_frames(self.scratch)
        self._source: FrameStore | None = None  # every training frame, decoded on first use
        self._feeder: FrameFeeder | None = None  # online: releases the source rows as the clock passes them
        # online, from a checkpoint: how many frames its mapper held (the first sync adds exactly these:
        # frames come due during a step and are added at the next one, so the clock alone would add more)
        self._frames_at_load: int | None = None
        self._gt = None
        self.eval_history: list[EvalPoint] = []
        self._prepared = False
        self.startup_s: float | None = None  # process start -> first step (set by prepare)
        self.checkpoint_error: OSError | None = None  # the final checkpoint did not fit (online)
        self.trained_on: str | None = None  # a loaded checkpoint's device ("cpu", "cuda"; None before it was kept)
        self.trained_threads: int | None = None  # and its torch CPU threads (None: a checkpoint before they were kept)
        self.grid_init_s = 0.0

    @property
    def store(self) -> FrameStore:
        """Every training frame of the recording, decoded on first use (evaluating a checkpoint
        needs none); online, the mapper gets them one by one as the clock passes them."""
        if self._source is None:
            store = build_frame_store(
                self.recording, ("train",), self.config.image_scale, with_depth="rgbd" in self.config.sensors,
                cache_dir=self.scratch / "cache", progress=not self.quiet,
                # online, the mapper copies each frame as it arrives: the source stays on disk
                mmap_above_bytes=0 if self.config.online else MMAP_ABOVE_BYTES,
            )
            if len(store) == 0:
                raise ValueError(f"{self.recording.room_dir}: no frames labelled 'train' in the split")
            self._source = store
        return self._source

    @property
    def sampler(self) -> BatchSampler:
        """The mapper's sampler, over the frames it has now."""
        self._sync_frames()
        return self.mapper.sampler

    def _sync_frames(self) -> None:
        """Hand the mapper the frames available now (offline: all at once, without a copy;
        online: the ones the clock has newly passed, in time order)."""
        store = self.store
        if self.mapper.frames == len(store):
            return  # every frame is there (offline from the start, online once the drive is over)
        if not self.config.online:
            self.mapper.add_store(store)
            return
        if self._frames_at_load is not None:  # a checkpoint's mapper: the frames it held, not all due by its clock
            new, self._frames_at_load = self.feeder.release_first(self._frames_at_load), None
        else:
            new = self.feeder.release(self.mapper.seconds)
        if new.size:  # the stereo tracker reads the recording's own images
            self.mapper.add_store(store, new, self._full_image)
            for pixels in (store.images, store.depths_mm):  # copied: the source's pages go back to the OS
                if pixels is not None:
                    release_pages(pixels, new)

    def _full_image(self, src: int) -> np.ndarray:
        """(H, W, 3) uint8: source row `src`'s image at the recording's resolution."""
        store = self.store
        return self.recording.stacks[int(store.stack_ids[src])].image(int(store.rows[src]))

    def prepare(self) -> None:
        """One-off start-up before the first step: decode frames, give the grid its prior.

        Runs outside the training clock (a cold start must not eat a --max-time budget). The
        VIRUS grid's sensor prior uses the frames available at this moment (online: the first
        one); later frames get theirs when they arrive. A resumed grid comes from its checkpoint
        and already holds the prior of the frames it had.
        """
        if self._prepared:
            return
        self._sync_frames()
        if "stereo" in self.config.sensors and not self.config.online:
            from virus_nerf.stereo.build import stereo_depth

            self.mapper.set_stereo(stereo_depth(self.recording, self.store.frame_list(), self.stereo_config(),
                                                progress=not self.quiet))
        self.mapper.prepare()
        self.grid_init_s = self.mapper.prior_s
        self._prepared = True
        self.startup_s = since_process_start()

    def stereo_config(self) -> StereoConfig:
        """The stereo pass's settings: the run's, offline with the small room's filters where the
        stereo targets' line-of-sight term trains (a fitted room up to weights.free_stereo_room_m,
        engine/step_loss.stereo_line_of_sight; docs/decisions.md D112). A drive's tracker keeps the
        run's own (the term does not train while driving)."""
        mapper = self.mapper
        if not self.config.online and stereo_line_of_sight(self.config, mapper.box, mapper.extent.growing,
                                                           driving=False):
            return small_room_config(self.config.stereo)
        return self.config.stereo

    @property
    def t0(self) -> float:
        """Recording time of the first training frame (the online clock starts here)."""
        return float(min(s.times[s.split == "train"].min() for s in self.recording.stacks.values()))

    @property
    def feeder(self) -> FrameFeeder:
        """Online: the feeder that releases the training frames as the training clock passes them."""
        if self._feeder is None:
            self._feeder = FrameFeeder(self.store.times, self.config.playback_speed)
        return self._feeder

    @property
    def playback(self) -> Playback:
        """The online clock: recording time from the first training frame at the playback speed."""
        return Playback(self.t0, self.config.playback_speed)

    @property
    def duration(self) -> float:
        end = max(s.times[s.split == "train"].max() for s in self.recording.stacks.values())
        return float(end) - self.t0

    # ------------------------------------------------------------------ limits and schedule
    @property
    def max_time(self) -> float | None:
        """The training seconds of the budget: online the drive's (duration / speed)."""
        return self.mapper.schedules.horizon.max_time

    def done(self) -> bool:
        c = self.config
        if c.max_steps is not None and self.mapper.step >= c.max_steps:
            return True
        return self.max_time is not None and self.mapper.seconds >= self.max_time

    def available_frames(self) -> np.ndarray:
        """Source frame rows the run may use now; online, only frames the clock has passed."""
        if not self.config.online:
            return np.arange(len(self.store))
        return self.feeder.due(self.mapper.seconds)

    # ------------------------------------------------------------------ one step
    def train_step(self) -> LossTerms:
        """One step of the mapper on the frames available now, on the training clock (the
        frames arrive off the clock; their grid prior is on it)."""
        self.prepare()
        self._sync_frames()
        return self.mapper.train_step()

    # ------------------------------------------------------------------ evaluation
    def evaluate_on(self, recording: Recording) -> None:
        """Judge the map against `recording` from now on (its ground truth and test points): the
        optimised frame of a run trained on odometry poses."""
        self.recording = recording
        self._gt = None

    def evaluate(self, with_sensors: bool = True, keep_scans: int | None = None) -> EvaluationResult | None:
        """Score the NeRF scan (and the instantaneous sensors) at the test points.

        Online, only test points the clock has reached count; None before the first one.
        None without ground truth (evaluation.gt empty, `--gt none`). keep_scans: the test points
        whose scans the result keeps (evaluation.evaluate; None: all).
        """
        cfg = self.config.evaluation
        if not cfg.gt:
            return None  # --gt none: no ground truth, nothing to score
        if self._gt is None:
            self._gt = build_ground_truth(self.recording, cfg)
        gts = self._gt
        if self.config.online:
            clock = self.playback.recording_time(self.mapper.seconds)
            gts = [g for g in gts if g.test_point.time <= clock + 1e-9]
            if not gts:
                return None
        from dataclasses import replace

        cfg = cfg if with_sensors else replace(cfg, sensors=())
        self.mapper.field.eval()
        try:
            return evaluate(self.recording, {"NeRF": self.mapper.model}, cfg, ground_truth=gts, keep_scans=keep_scans)
        finally:
            self.mapper.field.train()

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        return {**self.mapper.state(), "eval_history": [dataclasses.asdict(p) for p in self.eval_history],
                "config": to_dict(self.config), "device": self.mapper.device.type,
                "threads": torch.get_num_threads()}

    def save_checkpoint(self) -> None:
        """checkpoint.pt, whole or not at all: serialised in memory, then written to a temporary
        file renamed over the last one. A failed write (a full disk) raises an OSError naming
        checkpoint.pt and leaves the last good checkpoint in place (torch.save straight to the
        file reported a full disk as a RuntimeError `unexpected pos`)."""
        from virus_nerf.errors import require_folder

        require_folder(self.run_dir, "the run folder")  # removed under the run: not rebuilt by the write
        buffer = io.BytesIO()
        torch.save(self.state(), buffer)
        with atomic_path(self.run_dir / CHECKPOINT) as tmp:
            tmp.write_bytes(buffer.getbuffer())

    def load_checkpoint(self, path: Path, state: dict | None = None) -> None:
        """Continue from checkpoint.pt (`state`: its contents, where the caller read them already).
        A checkpoint whose tensors do not fit this run's model (damaged, edited, another model) is
        a DataFormatError naming the file and the tensor."""
        from virus_nerf.errors import DataFormatError, one_line

        # CPU first: the RNG states must stay CPU byte tensors (Generator.set_state refuses
        # others); load_state_dict copies the tensors onto the field's and optimiser's device
        if state is None:
            state = torch.load(path, map_location="cpu", weights_only=False)
        if not isinstance(state, dict):
            raise DataFormatError(path, f"not a virus-nerf checkpoint (holds a {type(state).__name__})")
        problem = self.mapper.state_problem(state)  # the whole state, before the mapper is touched
        if problem is not None:
            key, what = problem
            if key == "state":
                raise DataFormatError(path, "not a complete virus-nerf checkpoint: " + what.split(";")[0])
            if key in ("box", "frame_times"):
                what += " (was the recording or its map changed?)"
            raise DataFormatError(path, what, field=key)
        try:
            self.mapper.load_state(state)
            self.eval_history = [EvalPoint(**e) for e in state.get("eval_history", [])]
            self.eval_history += self._final_points(Path(path).parent)
            self.trained_on = state.get("device") if isinstance(state.get("device"), str) else None
            self.trained_threads = state.get("threads") if isinstance(state.get("threads"), int) else None
            if self.config.online and isinstance(state.get("frames"), int) and self.mapper.frames == 0:
                self._frames_at_load = state["frames"]
        except (KeyError, ValueError, TypeError, RuntimeError) as exc:  # optimiser, RNG states, history
            raise DataFormatError(path, f"does not fit this run's model ({type(exc).__name__}: "
                                        f"{one_line(exc, 160)})") from None

    def _final_points(self, run_dir: Path) -> list[EvalPoint]:
        """The run's final evaluation, scored after its last checkpoint at the checkpoint's step
        (metrics_vs_time.csv's points at that step the checkpoint lacks): a resumed run keeps it
        on its curve."""
        from virus_nerf.errors import DataFormatError
        from virus_nerf.trainer.run_folder import METRICS_VS_TIME, read_eval_history

        try:
            saved = read_eval_history(run_dir / METRICS_VS_TIME)
        except DataFormatError:  # a damaged curve: the checkpoint's history stands
            return []
        known = {(e.step, e.ground_truth) for e in self.eval_history}
        return [e for e in saved if e.step == self.mapper.step and (e.step, e.ground_truth) not in known]

    # ------------------------------------------------------------------ the loop
    def fit(self, started: Callable[[], None] | None = None) -> TrainSummary:
        """Train until max_steps or max_time; logs, evaluations and checkpoints on the way.

        started: called once the first step of this call has succeeded (a resume writes its new
        config.json then, so a resume that cannot start leaves the run as it was)."""
        c = self.config
        self.prepare()
        log = TrainLog(self.run_dir, self.mapper.step, c.max_steps, self.quiet)
        evaluations = Every.aligned(c.eval_interval, self.mapper.seconds)
        checkpoints = Every.after(c.checkpoint_every, self.mapper.seconds)
        try:
            while not self.done():
                try:
                    with stops_deferred():  # SIGINT/SIGTERM stop the run between steps (trainer/run.py)
                        terms = self.train_step()
                except (MemoryError, RuntimeError) as exc:
                    _raise_if_out_of_memory(exc, c.batch_size)
                    raise
                if started is not None:
                    started()
                    started = None
                if self.mapper.step % c.log_every == 0 or self.done():
                    log.write(self._log_row(terms))
                log.advance()
                if evaluations.due(self.mapper.seconds) and not self.done():
                    self._evaluate_during_training(log)
                    evaluations.next_at += evaluations.period
                if checkpoints.due(self.mapper.seconds):
                    self.save_checkpoint()
                    checkpoints = Every.after(c.checkpoint_every, self.mapper.seconds)
            wall_s = since_process_start()
            try:
                self.save_checkpoint()
            except OSError as exc:
                if not c.online:
                    raise
                # online (a robot's map): the map and the results are written first, then this
                # is named (trainer/run.py _check_final_checkpoint); the last periodic checkpoint stays
                self.checkpoint_error = exc
        finally:
            log.close()
        return TrainSummary(self.mapper.step, self.mapper.seconds, self.mapper.samples, self.startup_s, wall_s,
                            self.mapper.device.type, torch.get_num_threads())

    def _evaluate_during_training(self, log: TrainLog) -> None:
        result = self.evaluate(with_sensors=False, keep_scans=0)  # the metrics alone
        if result is not None:
            self.record_eval(result, log)

    def _log_row(self, terms: LossTerms) -> LogRow:
        t = terms.as_floats()
        return LogRow(
            step=self.mapper.step,
            seconds=round(self.mapper.seconds, 3),
            loss=t["total"],
            colour=t["colour"],
            irs=t["irs"],
            uss=t["uss"],
            rgbd=t["rgbd"],
            psnr=psnr_db(t["colour"]),
            samples_per_ray=round(self.mapper.last_samples_per_ray, 2),
            occupied=round(self.mapper.grid.occupancy_share(), 4),
            frames=len(self.available_frames()),
            stereo=t["stereo"],
            distortion=t["distortion"],
            line_of_sight=t["line_of_sight"],
        )

    def record_eval(self, result: EvaluationResult, log: TrainLog | None = None) -> None:
        z3 = result.metrics["NeRF"].zones["zone3"]
        point = EvalPoint(step=self.mapper.step, seconds=round(self.mapper.seconds, 3),
                          acc_mean=z3.acc_mean, cov_mean=z3.cov_mean,
                          acc_inlier=z3.acc_inlier, cov_inlier=z3.cov_inlier,
                          n_test_points=result.n_points, ground_truth=result.gt)
        self.eval_history.append(point)
        from virus_nerf.errors import require_folder

        require_folder(self.run_dir, "the run folder")
        write_eval_history(self.run_dir / METRICS_VS_TIME, self.eval_history)
        if log is not None:  # one curve per ground truth, as metric_vs_time.png draws them
            for k in ("acc_mean", "cov_mean", "acc_inlier", "cov_inlier"):
                log.scalar(f"eval_{point.ground_truth}/zone3_{k}", getattr(point, k), self.mapper.step)


def _raise_if_out_of_memory(exc: BaseException, batch_size: int) -> None:
    """A training step that ran out of memory (numpy's MemoryError, torch's `can't allocate
    memory` / CUDA `out of memory`) as a one-line UsageError naming --batch-size."""
    from virus_nerf.errors import UsageError, one_line

    text = str(exc)
    if isinstance(exc, MemoryError) or "out of memory" in text or "can't allocate memory" in text:
        raise UsageError(f"--batch-size {batch_size}: a training step ran out of memory ({one_line(exc, 120)}); "
                         "expected a smaller --batch-size") from None
