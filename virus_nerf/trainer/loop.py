"""The training loop (docs/method.md 3.6): sample rays, render, losses, Adam, grid updates, evaluation.

Reproducible: one seed drives the ray sampler (numpy Generator) and the marcher jitter and
grid updates (torch Generator); both states go into the checkpoint, so a resumed run continues
bit for bit on CPU. A run bounded by --max-steps alone is bit-identical for the same seed;
a --max-time bound depends on the machine's speed, as any time budget does.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virus_nerf.config_io import to_dict
from virus_nerf.data.ethz import Recording
from virus_nerf.evaluation.evaluate import EvaluationResult, build_ground_truth, evaluate
from virus_nerf.field.field import NerfField
from virus_nerf.grid.base import GridSpec, GridUpdateBatch, OccupancyGrid
from virus_nerf.grid.ngp import NgpGrid
from virus_nerf.grid.virus import VirusGrid
from virus_nerf.losses import LossTerms, distortion_loss, total_loss
from virus_nerf.render.marching import ray_box_interval
from virus_nerf.sampler.batch import BatchSampler, RayBatch
from virus_nerf.sampler.frames import build_frame_store
from virus_nerf.sampler.sensor_rays import irs_zone_rays, uss_cone_rays
from virus_nerf.scene_box import SceneBox
from virus_nerf.trainer.config import TrainConfig
from virus_nerf.trainer.model import SceneModel, fit_scene_box
from virus_nerf.trainer.run_folder import (
    CHECKPOINT,
    METRICS_VS_TIME,
    EvalPoint,
    write_eval_history,
)
from virus_nerf.trainer.train_log import Every, LogRow, TrainLog, psnr_db
from virus_nerf.utils.clock import since_process_start
from virus_nerf.utils.io import atomic_path


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def build_grid(config: TrainConfig, box: SceneBox, device: torch.device) -> OccupancyGrid:
    if config.grid == "ngp":
        cfg = config.ngp_grid
        return NgpGrid(GridSpec.from_box(box, cfg.max_resolution), cfg, step_size=config.march.step_size, device=device)
    cfg = config.virus_grid
    return VirusGrid(GridSpec.from_box(box, cfg.max_resolution), cfg, device=device)


@dataclass
class TrainSummary:
    steps: int
    seconds: float  # training clock: steps and grid updates (start-up and evaluations excluded)
    samples: int  # samples actually marched and rendered, summed over steps
    startup_s: float | None = None  # process start to the first training step (this process)
    wall_s: float | None = None  # process start to the end of training (this process)

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else 0.0


class Trainer:
    """Owns one run folder: config.json, train_log.csv, checkpoint.pt, metrics.json, plots/."""

    def __init__(self, recording: Recording, config: TrainConfig, run_dir: Path, quiet: bool | None = None):
        self.recording = recording
        self.config = config
        self.run_dir = Path(run_dir)
        self.quiet = (not sys.stderr.isatty()) if quiet is None else quiet
        self.device = resolve_device(config.device)
        torch.manual_seed(config.seed)
        self.box = fit_scene_box(recording)
        field_gen = torch.Generator().manual_seed(config.seed)
        self.field = NerfField(self.box, config.field, generator=field_gen).to(self.device)
        self.grid = build_grid(config, self.box, self.device)
        self.model = SceneModel(
            self.field, self.grid, config.march.step_size, config.march.near, config.march.max_samples,
            config.min_opacity, config.march.backend, config.march.min_transmittance,
        )
        fused = self.device.type == "cpu" or self.device.type == "cuda"
        self.optimizer = torch.optim.Adam(
            self.field.parameters(), lr=config.optim.lr, eps=config.optim.eps, betas=config.optim.betas, fused=fused
        )
        self._sampler: BatchSampler | None = None
        self.rng = np.random.default_rng(config.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed + 1)
        self.step = 0
        self.seconds = 0.0
        self.samples = 0
        self._gt = None
        self.eval_history: list[EvalPoint] = []
        self._prepared = False
        self.startup_s: float | None = None  # process start -> first step (set by prepare)
        self.grid_init_s = 0.0

    @property
    def sampler(self) -> BatchSampler:
        """Training frames decoded on first use (evaluating a checkpoint needs none)."""
        if self._sampler is None:
            store = build_frame_store(
                self.recording, ("train",), self.config.image_scale, with_depth="rgbd" in self.config.sensors,
                cache_dir=self.run_dir / "cache", progress=not self.quiet,
            )
            if len(store) == 0:
                raise ValueError(f"{self.recording.room_dir}: no frames labelled 'train' in the split")
            self._sampler = BatchSampler(store, self.config.sensors, self.config.shares)
        return self._sampler

    @property
    def store(self):
        return self.sampler.store

    def prepare(self) -> None:
        """One-off start-up before the first step: decode frames, give the grid its prior.

        Runs outside the training clock (a cold start must not eat a --max-time budget). The
        VIRUS grid's sensor prior uses the frames available at this moment only (online: the
        first one), and only on a fresh run: a resumed grid comes from its checkpoint.
        """
        if self._prepared:
            return
        _ = self.sampler
        want = self.grid.prior_request
        if self.step == 0 and want is not None:
            t0 = time.perf_counter()
            frames = self.available_frames()
            sensors = self.config.sensors
            depth = irs_zone_rays(self.store, frames, want.zone_samples).valid() if "irs" in sensors else None
            free = uss_cone_rays(self.store, frames).valid() if want.uss_free and "uss" in sensors else None
            self.grid.initialise(depth, free)
            self.grid_init_s = time.perf_counter() - t0
        self._warm_kernels()
        self._prepared = True
        self.startup_s = since_process_start()

    def _warm_kernels(self) -> None:
        """Load (or compile) the marching, field and compositing kernels on a few rays, so the
        first timed step is an ordinary one. Draws no random numbers and leaves no gradient."""
        rays = self.sampler._rays(np.zeros(8, dtype=np.int64), np.arange(8, dtype=np.int64)).to(self.device)
        out, _ = self.model.render(rays.origins, rays.directions, generator=None)
        (out.rgb.sum() + out.depth.sum()).backward()
        self.optimizer.zero_grad(set_to_none=True)

    @property
    def t0(self) -> float:
        """Recording time of the first training frame (the online clock starts here)."""
        return float(min(s.times[s.split == "train"].min() for s in self.recording.stacks.values()))

    @property
    def duration(self) -> float:
        end = max(s.times[s.split == "train"].max() for s in self.recording.stacks.values())
        return float(end) - self.t0

    # ------------------------------------------------------------------ limits and schedule
    @property
    def max_time(self) -> float | None:
        if self.config.online:
            return self.duration / self.config.playback_speed
        return self.config.max_time

    def _done(self) -> bool:
        c = self.config
        if c.max_steps is not None and self.step >= c.max_steps:
            return True
        return self.max_time is not None and self.seconds >= self.max_time

    def _progress(self) -> float:
        parts = []
        if self.config.max_steps is not None:
            parts.append(self.step / self.config.max_steps)
        if self.max_time is not None:
            parts.append(self.seconds / self.max_time)
        return min(1.0, max(parts))

    def available_frames(self) -> np.ndarray:
        """Frame rows the trainer may use now; online, only frames the clock has passed."""
        if not self.config.online:
            return np.arange(len(self.store))
        clock = self.t0 + self.seconds * self.config.playback_speed
        avail = np.flatnonzero(self.store.times <= clock)
        return avail if avail.size else np.array([int(np.argmin(self.store.times))])

    # ------------------------------------------------------------------ one step
    def train_step(self) -> LossTerms:
        self.prepare()
        c = self.config
        lr = c.optim.lr * c.optim.lr_decay_to ** self._progress()
        for g in self.optimizer.param_groups:
            g["lr"] = lr
        batch = self.sampler.sample(self.rng, c.batch_size, self.available_frames()).to(self.device)
        sensors = c.sensors
        rgb_rays = None
        if c.density_only_depth_rays:
            has_depth = torch.zeros(len(batch), dtype=torch.bool, device=self.device)
            if "irs" in sensors:
                has_depth |= torch.isfinite(batch.irs_range)
            if "rgbd" in sensors:
                has_depth |= torch.isfinite(batch.rgbd_range)
            rgb_rays = ~has_depth
        out, stats = self.model.render(batch.origins, batch.directions, generator=self.generator, rgb_rays=rgb_rays)
        terms = total_loss(
            c.weights,
            pred_rgb=out.rgb,
            target_rgb=batch.rgb,
            pred_depth=out.depth,
            irs_depth=batch.irs_range if "irs" in sensors else None,
            uss_range=batch.uss_range if "uss" in sensors else None,
            rgbd_depth=batch.rgbd_range if "rgbd" in sensors else None,
            rgb_mask=rgb_rays,
        )
        if c.weights.distortion > 0:
            smp = stats.samples
            ld = distortion_loss(out.weights, smp.t_starts, smp.t_ends, smp.ray_offsets)
            terms = dataclasses.replace(terms, total=terms.total + c.weights.distortion * ld, distortion=ld)
        self.optimizer.zero_grad(set_to_none=True)
        terms.total.backward()
        self.optimizer.step()
        self.step += 1
        self.samples += stats.n_samples
        self._last_samples_per_ray = stats.n_samples / max(1, stats.n_rays)
        if self.step % self.grid.update_interval == 0:
            self.grid.update(self.step, self.field.density, self._grid_batch(batch, stats), self.generator)
        return terms

    def _grid_batch(self, batch: RayBatch, stats) -> GridUpdateBatch:
        """Candidates for one grid update; the grid draws its own share of each at random.

        Depth-Update: every ray with an IRS range. NeRF-Update: every ray of the batch (the whole
        image, not only the sensor footprints), each to the box exit; plus the forward pass's
        samples and densities for a grid that reuses them.
        """
        has_irs = torch.isfinite(batch.irs_range).nonzero().squeeze(1)
        _, t_exit = ray_box_interval(batch.origins, batch.directions, self.grid.spec, 0.0, math.inf)
        far = t_exit.clamp(min=0.0).to(batch.origins.dtype)  # (B,) distance to the box exit
        return GridUpdateBatch(
            depth_origins=batch.origins[has_irs],
            depth_directions=batch.directions[has_irs],
            depth_ranges=batch.irs_range[has_irs],
            nerf_origins=batch.origins,
            nerf_directions=batch.directions,
            nerf_far=far,
            forward_points=stats.positions,
            forward_sigma=stats.sigma,
        )

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, with_sensors: bool = True) -> EvaluationResult | None:
        """Score the NeRF scan (and the instantaneous sensors) at the test points.

        Online, only test points the clock has reached count; None before the first one.
        """
        cfg = self.config.evaluation
        if self._gt is None:
            self._gt = build_ground_truth(self.recording, cfg)
        gts = self._gt
        if self.config.online:
            clock = self.t0 + self.seconds * self.config.playback_speed
            gts = [g for g in gts if g.test_point.time <= clock + 1e-9]
            if not gts:
                return None
        from dataclasses import replace

        cfg = cfg if with_sensors else replace(cfg, sensors=())
        self.field.eval()
        try:
            return evaluate(self.recording, {"NeRF": self.model}, cfg, ground_truth=gts)
        finally:
            self.field.train()

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        return {
            "field": self.field.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "grid": self.grid.state_dict(),
            "step": self.step,
            "seconds": self.seconds,
            "samples": self.samples,
            "numpy_rng": self.rng.bit_generator.state,
            "torch_generator": self.generator.get_state(),
            "eval_history": [dataclasses.asdict(p) for p in self.eval_history],
            "box": self.box.to_dict(),
            "config": to_dict(self.config),
        }

    def save_checkpoint(self) -> None:
        with atomic_path(self.run_dir / CHECKPOINT) as tmp:
            torch.save(self.state(), tmp)

    def load_checkpoint(self, path: Path) -> None:
        # CPU first: the RNG states must stay CPU byte tensors (Generator.set_state refuses
        # others); load_state_dict copies the tensors onto the field's and optimiser's device
        state = torch.load(path, map_location="cpu", weights_only=False)
        if "box" in state:
            saved = SceneBox.from_dict(state["box"])
            if not np.allclose(saved.lo, self.box.lo, atol=1e-6) or not np.allclose(saved.hi, self.box.hi, atol=1e-6):
                from virus_nerf.errors import DataFormatError

                raise DataFormatError(
                    path,
                    f"scene box lo={saved.lo} hi={saved.hi} does not match the recording's "
                    f"lo={self.box.lo} hi={self.box.hi}; the network would be read in another frame "
                    "(was the recording or its map changed?)",
                    field="box",
                )
        self.field.load_state_dict(state["field"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.grid.load_state_dict(state["grid"])
        self.step = int(state["step"])
        self.seconds = float(state["seconds"])
        self.samples = int(state["samples"])
        self.rng.bit_generator.state = state["numpy_rng"]
        self.generator.set_state(state["torch_generator"])
        self.eval_history = [EvalPoint(**e) for e in state.get("eval_history", [])]

    # ------------------------------------------------------------------ the loop
    def fit(self) -> TrainSummary:
        """Train until max_steps or max_time; logs, evaluations and checkpoints on the way."""
        c = self.config
        self.prepare()
        log = TrainLog(self.run_dir, self.step, c.max_steps, self.quiet)
        evaluations = Every.aligned(c.eval_interval, self.seconds)
        checkpoints = Every.after(c.checkpoint_every, self.seconds)
        try:
            while not self._done():
                terms = self._timed_step()
                if self.step % c.log_every == 0 or self._done():
                    log.write(self._log_row(terms))
                log.advance()
                if evaluations.due(self.seconds) and not self._done():
                    self._evaluate_during_training(log)
                    evaluations.next_at += evaluations.period
                if checkpoints.due(self.seconds):
                    self.save_checkpoint()
                    checkpoints = Every.after(c.checkpoint_every, self.seconds)
            wall_s = since_process_start()
            self.save_checkpoint()
        finally:
            log.close()
        return TrainSummary(self.step, self.seconds, self.samples, self.startup_s, wall_s)

    def _timed_step(self) -> LossTerms:
        """One training step on the training clock."""
        t_start = time.perf_counter()
        terms = self.train_step()
        self.seconds += time.perf_counter() - t_start
        return terms

    def _evaluate_during_training(self, log: TrainLog) -> None:
        result = self.evaluate(with_sensors=False)
        if result is not None:
            self.record_eval(result, log)

    def _log_row(self, terms: LossTerms) -> LogRow:
        t = terms.as_floats()
        return LogRow(
            step=self.step,
            seconds=round(self.seconds, 3),
            loss=t["total"],
            colour=t["colour"],
            irs=t["irs"],
            uss=t["uss"],
            rgbd=t["rgbd"],
            psnr=psnr_db(t["colour"]),
            samples_per_ray=round(self._last_samples_per_ray, 2),
            occupied=round(self.grid.occupancy_share(), 4),
            frames=len(self.available_frames()),
        )

    def record_eval(self, result: EvaluationResult, log: TrainLog | None = None) -> None:
        z3 = result.metrics["NeRF"].zones["zone3"]
        point = EvalPoint(step=self.step, seconds=round(self.seconds, 3),
                          acc_mean=z3.acc_mean, cov_mean=z3.cov_mean,
                          acc_inlier=z3.acc_inlier, cov_inlier=z3.cov_inlier,
                          n_test_points=len(result.points))
        self.eval_history.append(point)
        write_eval_history(self.run_dir / METRICS_VS_TIME, self.eval_history)
        if log is not None:
            for k in ("acc_mean", "cov_mean", "acc_inlier", "cov_inlier"):
                log.scalar(f"eval/zone3_{k}", getattr(point, k), self.step)
