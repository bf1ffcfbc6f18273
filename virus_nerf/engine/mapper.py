"""Mapping while driving: a VIRUS-NeRF whose frame set grows as the robot drives (issue 12).

`Mapper` is the training engine (docs/method.md 3.6) without a run folder: field, occupancy grid,
optimiser, seeded random streams and a growing `FrameStore`. Frames are added one at a time;
`train(seconds)` trains on the frames added so far; the current 2D map and scans can be queried
at any time. The VIRUS grid's sensor prior (docs/method.md 3.4) is applied to every frame once,
at the first step after it was added. `Trainer` (trainer/loop.py) drives one Mapper for
`virus-nerf train` (offline: every frame added before the first step; `--online`: each frame
when the training clock, scaled by the playback speed, passes its timestamp); `virus-nerf
map-bag` streams a bag through one in real time (mapping/stream.py; mapping/replay.py with
--import-first).

Example, in a ROS node or a script (metres, seconds, RGB; OpenCV camera axes)::

    from virus_nerf import Intrinsics, Mapper, MapperConfig, SceneBox, SyncFrame, warm_up

    intr = Intrinsics(fx=386.0, fy=386.0, cx=320.0, cy=240.0, width=640, height=480)
    warm_up(MapperConfig())               # at start-up: kernels and torch's optimiser loaded here
    mapper = Mapper(MapperConfig(), {1: intr, 3: intr}, SceneBox((-5, -5, -1), (5, 5, 2)))
    # on every synchronised set of messages:
    mapper.add_frame(SyncFrame(time=t, stack_id=1, rgb=rgb, cam_to_world=pose,
                               uss_range=uss_m, irs_range=zones_8x8_m))
    # between messages, e.g. in a timer:
    report = mapper.train(0.5)            # TrainSlice(steps, seconds, loss, frames, ...)
    grid_map = mapper.map2d()             # maps.occupancy.OccupancyMap2D (write_map_server)
    scans = mapper.scans(poses)           # [maps.scans.Scan2D] at (N, 4, 4) poses
    mapper.snapshot(Path("maps/0001"))    # map.pgm/.yaml/.png (+ prob.*) and snapshot.json
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virus_nerf.data.frame import SyncFrame, check_frame, check_intrinsics, valid_ranges
from virus_nerf.engine.adam import Adam
from virus_nerf.engine.checkpoint import MapperCheckpoint
from virus_nerf.engine.clock import FrameClock, PlacedFrame
from virus_nerf.engine.config import MapperConfig
from virus_nerf.engine.extent import MapExtent
from virus_nerf.engine.model import SceneModel, build_grid, resolve_device, start_box
from virus_nerf.engine.schedule import Schedules, StepSchedule
from virus_nerf.engine.state import (
    frames_mismatch,
)
from virus_nerf.engine.step_loss import colour_rays, step_loss, stereo_line_of_sight
from virus_nerf.engine.views import MapViews, serialised
from virus_nerf.errors import UsageError
from virus_nerf.field.field import NerfField
from virus_nerf.grid.base import GridUpdateBatch
from virus_nerf.grid.extent import first_box
from virus_nerf.losses import LossTerms
from virus_nerf.maps.observed import frames_observed
from virus_nerf.render.marching import ray_box_interval
from virus_nerf.sampler.batch import BatchSampler, RayBatch, recent_frame_odds
from virus_nerf.sampler.frames import SPILL_ABOVE_BYTES, FrameStore, resize_depth_mm, resize_rgb
from virus_nerf.sampler.sensor_rays import irs_zone_rays
from virus_nerf.scene_box import SceneBox
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.stereo.depth import StereoDepth, StereoFeed


@dataclass(frozen=True)
class TrainSlice:
    """What one `Mapper.train` call did."""

    steps: int  # training steps in this slice
    seconds: float  # training clock spent in this slice (steps and grid updates)
    loss: float | None  # weighted total loss of the slice's last step (None: no step)
    frames: int  # frames the slice trained on
    total_steps: int  # steps since the mapper was made
    total_seconds: float  # training clock since the mapper was made

MAX_BOX_SIDE_M = 1000.0  # a room or a hall a robot maps; a larger box is a unit mistake


class Mapper(MapViews, MapperCheckpoint):
    """A VIRUS-NeRF (or Instant-NGP) map trained on frames as they arrive.

    config: the training configuration (`train` decides how long to train). intrinsics: stack
    id -> camera intrinsics at the frames' full resolution (frames are resized by
    config.image_scale). box: the scene box in metres: with `extent.mode` fitted the field's and grid's frame for the mapper's life (the
    room's extent, e.g. from a floor plan or a previous map); with grow the box around the first
    frame (grid/extent.py first_box), which grows as frames arrive to hold the camera positions
    and the points the depth sensors measured (or the reach around every camera; grid/extent.py).
    schedules: the offline and driving step schedules and the learning-rate horizon
    (engine/schedule.py; default: the config's, decaying over its max_steps / max_time; mapping
    while driving hands in `Schedules.of(config, Horizon.drive(drive_s, playback))`).
    """

    def __init__(self, config: MapperConfig, intrinsics: Mapping[int, Intrinsics], box: SceneBox,
                 schedules: Schedules | None = None):
        self._calls = threading.RLock()  # one call at a time, from any thread (views.serialised)
        check_intrinsics(intrinsics)
        if not intrinsics:
            raise UsageError("Mapper intrinsics {}: expected at least one stack id -> Intrinsics")
        if not isinstance(box, SceneBox):
            raise UsageError(f"Mapper box: got a {type(box).__name__}; expected a virus_nerf.scene_box.SceneBox "
                             "(lo, hi corners in metres)")
        if max(box.size) > MAX_BOX_SIDE_M:  # before a map of 10^10 pixels is asked for
            raise UsageError(f"Mapper box: a side of {max(box.size):g} m; expected metres, a box of at most "
                             f"{MAX_BOX_SIDE_M:g} m (millimetres?)")
        if not hasattr(config, "engine"):
            raise UsageError(f"Mapper config: got a {type(config).__name__}; expected a MapperConfig (or a "
                             "TrainConfig), e.g. MapperConfig(batch_size=1024)")
        config = config.engine()  # the engine's knobs alone (a TrainConfig's run knobs stay with the run)
        self.config = config
        self.schedules = schedules or Schedules.of(config)
        self.intrinsics = dict(intrinsics)
        self.device = resolve_device(config.device)
        torch.manual_seed(config.seed)
        field_gen = torch.Generator().manual_seed(config.seed)
        # grow: the field lives in a fixed cube around the first box, the grid's cells keep their
        # size while the box grows (grid/extent.py); fitted: both span the given box
        self.extent = MapExtent(config.extent, config.sensors, box)
        self.field = NerfField(self.extent.frame, self.extent.field_config(config.field),
                               generator=field_gen).to(self.device)
        self.grid = build_grid(config, box, self.device, self.extent.grid_spec())
        self.model = SceneModel(
            self.field, self.grid, config.march.step_size, config.march.near, config.march.max_samples,
            config.min_opacity, config.march.backend, config.march.min_transmittance,
        )
        self._optimizer: Adam | None = None  # built by the first step (`optimizer`)
        self._optimizer_state: dict | None = None  # a checkpoint's Adam state, until then
        self._optimizer_lock = threading.Lock()
        self.rng = np.random.default_rng(config.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed + 1)
        self.step = 0
        self.seconds = 0.0  # training clock: timed steps only
        self.samples = 0
        self.rays = 0  # rays rendered, summed over steps
        self.last_loss: float | None = None
        self.skipped_steps = 0  # steps whose loss was not finite: no update (this process's, not in the state)
        self.last_samples_per_ray = 0.0
        self.visible_share = 1.0  # the last step's visible sample share: picks the next render's path
        self.prior_s = 0.0  # seconds spent on the grid's sensor prior in `prepare`
        self._sampler: BatchSampler | None = None
        self._prior_done = 0  # frames (store rows 0..n-1) whose sensor prior the grid has had
        self._prior_skip = False  # an old checkpoint without the count: frames present count as done
        self._warm = False
        self._frames_at_start: int | None = None  # frames present at the first step
        self._viewed_frames = 0  # frames whose camera views the grid was given (warmup_restart)
        self.clock = FrameClock()  # the frames' stamps -> the store's times, across `restart_clock`
        # (N,) stack ids and store times (s) of the frames a loaded state was trained on: the frames
        # added again must be those, in that order (`load_state`); empty when nothing was loaded
        self._expected_frames = (np.zeros(0, np.int64), np.zeros(0, np.float64))
        self._seen_at_start = 0  # frames that count as seen at step 0 besides those at the first step
        self.stereo: StereoDepth | None = None  # triangulated depth targets of the store's rows
        self._stereo_feed: StereoFeed | None = None  # fed by track_image (mapping while driving)
        self._stereo_points_done = 0  # stereo points (the first n of `stereo.points`) the grid has had

    @property
    def box(self) -> SceneBox:
        """The map's box now (the grid's; grown while driving with `extent.mode` grow)."""
        return self.extent.box

    @property
    def frame(self) -> SceneBox:
        """The field's fixed frame: the box (fitted) or the cube around the first box (grow)."""
        return self.extent.frame

    @classmethod
    def for_recording(cls, recording, config: MapperConfig, schedules: Schedules | None = None) -> Mapper:
        """A mapper for a recording's stacks and scene box, no frames: the box fitted to the room
        (data.room_box.fit_scene_box), or with `extent.mode` grow the first frame's box."""
        return cls(config, {s: st.intrinsics for s, st in recording.stacks.items()}, start_box(recording, config),
                   schedules)

    @classmethod
    def growing(cls, config: MapperConfig, intrinsics: Mapping[int, Intrinsics], first_position,
                schedules: Schedules | None = None) -> Mapper:
        """A mapper for a room never seen: the map starts around a camera at `first_position`
        ((3,) m, the first frame's cam_to_world[:3, 3]) and grows as the robot drives
        (`extent.mode` grow, set here; grid/extent.py first_box, docs/extent.md)."""
        p = np.asarray(first_position, dtype=np.float64)
        if p.shape not in ((3,), (1, 3)) or not np.isfinite(p).all():
            raise UsageError(f"Mapper.growing first_position of shape {p.shape}: expected a finite (3,) camera "
                             "position in metres")
        if config.extent.mode != "grow":
            config = dataclasses.replace(config, extent=dataclasses.replace(config.extent, mode="grow"))
        return cls(config, intrinsics, first_box(p.reshape(3), config.extent, config.sensors), schedules)

    # ------------------------------------------------------------------ frames
    @property
    def sampler(self) -> BatchSampler:
        if self._sampler is None:
            with self._calls:  # made once: a thread reading `frames` while the first frame is added
                if self._sampler is None:
                    scaled = {s: i.scaled(self.config.image_scale) for s, i in self.intrinsics.items()}
                    store = FrameStore.empty(scaled, with_depth="rgbd" in self.config.sensors)
                    self._sampler = BatchSampler(store, self.config.sensors, self.config.shares, self.stereo)
        return self._sampler

    @property
    def store(self) -> FrameStore:
        """The frames added so far at training resolution (row = order of arrival)."""
        return self.sampler.store

    @property
    def frames(self) -> int:
        return len(self.store)

    @serialised
    def spill_frames(self, folder: Path, above_bytes: int = SPILL_ABOVE_BYTES) -> None:
        """Keep the growing store's images beyond `above_bytes` in a file under `folder` (a disk,
        not a tmpfs) instead of RAM: mapping while driving for an hour stays within memory
        (sampler.frames.FrameStore.spill_to)."""
        self.store.spill_to(folder, above_bytes)

    @serialised
    def add_frame(self, frame: SyncFrame) -> int:
        """Add one synchronised frame (checked: stack, image shapes, pose, ranges, and its time after
        the stack's previous frame: the newest frames' share of each batch and the stereo tracker
        go by time); returns its row."""
        check_frame(frame, self.intrinsics)
        placed = self._place(frame)
        time_s = placed.time
        self._check_expected(np.array([frame.stack_id]), np.array([time_s]), f"add_frame: SyncFrame (time {frame.time!r})")
        small = self.store.intrinsics[frame.stack_id]
        size = (small.width, small.height)
        depth = None
        if self.store.depths_mm is not None and frame.depth is not None:
            depth = resize_depth_mm(np.asarray(frame.depth, dtype=np.float32), size)
        self.extent.check_inside(np.asarray(frame.cam_to_world, dtype=np.float64)[None, :3, 3], np.array([frame.time]))
        row = self.store.append(frame.stack_id, self.frames, time_s, np.asarray(frame.cam_to_world),
                                resize_rgb(frame.rgb, size), depth, *valid_ranges(frame.uss_range, frame.irs_range))
        self.clock.keep(placed)  # only with a frame kept: a refused one leaves the clock as it was
        self._grow(self.extent.add_frames(self.store, np.array([row])))
        self.track_image(row, frame.rgb)
        return row

    @serialised
    def add_stack(self, stack_id: int, intrinsics: Intrinsics) -> None:
        """A camera stack the mapper was not made with (live: a camera driver that started after
        the map, its camera_info late): its frames are taken from now on. Its images must have the
        other stacks' size; a stack it has already is refused (a camera does not change its lens
        mid-drive). One-line UsageError, nothing changed."""
        if isinstance(stack_id, bool) or not isinstance(stack_id, numbers.Integral):
            raise UsageError(f"Mapper.add_stack stack_id {stack_id!r}: a {type(stack_id).__name__}; expected the "
                             "stack id as an int (SyncFrame.stack_id)")
        stack_id = int(stack_id)
        if stack_id in self.intrinsics:
            raise UsageError(f"Mapper.add_stack stack_id {stack_id}: already mapped; expected a new stack id")
        check_intrinsics({**self.intrinsics, stack_id: intrinsics}, "Mapper.add_stack intrinsics")  # and one size
        self.intrinsics[stack_id] = intrinsics
        if self._sampler is not None:  # else made with every stack when first needed
            scaled = intrinsics.scaled(self.config.image_scale)
            self.store.add_stack(stack_id, scaled)
            if self._stereo_feed is not None:
                self._stereo_feed.builder.add_stack(stack_id, intrinsics, scaled)

    @property
    def newest_stamp(self) -> float | None:
        """The stamp, as the robot sent it, of the frame newest in the store's time."""
        return self.clock.newest_stamp

    @serialised
    def restart_clock(self) -> None:
        """The robot's clock restarted (a bag played again, a clock reset): the next frames may be
        stamped before those already added. From the first frame stamped at or before its stack's
        previous one, times continue after the newest frame's (engine/clock.RESTART_GAP_S on), so
        the order of arrival stays the order in time (engine/clock.FrameClock)."""
        self.clock.restart()

    def _place(self, frame: SyncFrame) -> PlacedFrame:
        """The frame's place on the store's clock; refused when not after its stack's previous
        frame. Changes nothing: `add_frame` keeps the clock's state once the frame is in."""
        store_newest = float(self.store.times.max()) if self.frames else None
        placed = self.clock.place(int(frame.stack_id), float(frame.time), store_newest)
        mine = self.store.times[self.store.stack_ids == frame.stack_id]
        newest = float(mine.max()) if len(mine) else -math.inf  # the stack's previous frame, in the store
        if placed.time <= newest:
            previous = self.clock.previous_stamp(placed.stack_id)
            previous = newest - placed.shift if previous is None else previous
            raise UsageError(f"SyncFrame.time {frame.time!r} (stack {frame.stack_id}): not after the stack's "
                             f"previous frame at {previous!r} s; expected each stack's frames in "
                             "time order, once each (after a clock reset, call Mapper.restart_clock() first)")
        return placed

    def _check_expected(self, stack_ids: np.ndarray, times: np.ndarray, what: str) -> None:
        """Frames about to become rows `frames`.. must be the loaded state's frames of those rows
        (same stack, same time): other frames would train on with a field and grid fitted to a
        drive they are not part of, without a word. A one-line UsageError ("Mapper.<what>: ..."),
        nothing added."""
        problem = frames_mismatch(self._expected_frames, self.frames, stack_ids, times)
        if problem is not None:
            raise UsageError(f"Mapper.{what}: {problem}")

    def _grow(self, box: SceneBox | None) -> None:
        """The grid grown to the extent's new box (None: it stayed)."""
        if box is not None:
            self.grid.grow(box)

    @serialised
    def track_image(self, row: int, rgb: np.ndarray) -> None:
        """Feed frame `row`'s full-resolution image (H, W, 3) uint8 to the stereo sensor's tracker
        (frames in time order; nothing without the `stereo` sensor); new targets as tracks end."""
        if "stereo" not in self.config.sensors:
            return
        if self._stereo_feed is None:
            self._stereo_feed = StereoFeed(self.intrinsics, self.store.intrinsics, self.config.stereo)
        store = self.store
        depth = self._stereo_feed.add(row, int(store.stack_ids[row]), float(store.times[row]),
                                      store.cam_to_world[row], rgb)
        if depth is not None:
            self.set_stereo(depth)

    @serialised
    def add_store(self, store: FrameStore, rows: np.ndarray | None = None,
                  images: Callable[[int], np.ndarray] | None = None) -> None:
        """Add frames already decoded at training resolution: `rows` of `store` in that order, or
        all of them (taken over without a copy when the mapper has none yet). `images`: a
        `store` row -> its full-resolution image (H, W, 3) uint8, fed to the stereo tracker as
        `add_frame` does (rows in time order); without it the tracker hears nothing (offline,
        the stereo targets of the whole drive come at once through `set_stereo`)."""
        if store.intrinsics != self.store.intrinsics:
            raise ValueError(f"store intrinsics {store.intrinsics} differ from the mapper's {self.store.intrinsics}")
        picked = np.arange(len(store)) if rows is None else np.asarray(rows)
        self._check_expected(store.stack_ids[picked], store.times[picked], f"add_store: rows {picked[:3].tolist()}"
                             f"{'...' if len(picked) > 3 else ''}")
        self.extent.check_inside(store.cam_to_world[picked, :3, 3], store.times[picked])
        self._grow(self.extent.add_frames(store, picked))
        first = self.frames
        if rows is None and first == 0:
            self._sampler = BatchSampler(store, self.config.sensors, self.config.shares, self.stereo)
        else:
            self.store.append_rows(store, picked)
        for sid in np.unique(store.stack_ids[picked]):  # each stack's newest frame, on the clock as it is
            self.clock.keep_newest(int(sid), float(store.times[picked][store.stack_ids[picked] == sid].max()))
        if images is not None and "stereo" in self.config.sensors:
            for row, src in enumerate(picked, start=first):
                self.track_image(row, images(int(src)))

    @serialised
    def set_stereo(self, depth: StereoDepth | None) -> None:
        """Triangulated depth targets (stereo.StereoDepth) for the frames added so far, rows in
        the mapper's store order; used by the `stereo` sensor's share of each batch. With sensed
        growth the box grows to hold the new triangulated points (grid/extent.py)."""
        self.stereo = depth
        if depth is not None:
            self._grow(self.extent.add_stereo(depth.points))
            # the points not given yet (a refresh appends its own, stereo/depth.py `_extend`; a resumed
            # run's rebuilt ones come again in the same order) are surfaces for the grid
            self.grid.surface_points(depth.points[self._stereo_points_done :])
            self._stereo_points_done = max(self._stereo_points_done, len(depth.points))
        if self._sampler is not None:
            self._sampler.stereo = depth

    def _apply_pending_prior(self) -> None:
        """The grid's sensor prior (VIRUS: Depth-Update along every IRS zone) for the frames added
        since the last call; each frame is used once."""
        n = self.frames
        want = self.grid.prior_request
        if self._prior_skip:
            self._prior_done, self._prior_skip = n, False
        if n > self._prior_done and want is not None:
            if "irs" in self.config.sensors:
                frames = np.arange(self._prior_done, n)
                self.grid.initialise(irs_zone_rays(self.store, frames, want.zone_samples).valid())
        self._prior_done = n

    # ------------------------------------------------------------------ training
    @serialised
    def prepare(self) -> None:
        """Start-up before the first step: the prior of the frames present, kernels loaded."""
        if self.frames == 0:
            raise UsageError("Mapper.train: no frames yet; expected add_frame (at least one frame) first")
        t0 = time.perf_counter()
        self._apply_pending_prior()
        self.prior_s += time.perf_counter() - t0
        if not self._warm:
            self._warm_kernels()
            self._warm = True

    def _warm_kernels(self) -> None:
        """Load (or compile) the marching, field and compositing kernels on a few rays, so the
        first timed step is an ordinary one. Draws no random numbers and leaves no gradient."""
        n = min(8, self.store.images.shape[1] * self.store.images.shape[2])  # an image may have fewer pixels
        rays = self.sampler._rays(np.zeros(n, dtype=np.int64), np.arange(n, dtype=np.int64)).to(self.device)
        out, _ = self.model.render(rays.origins, rays.directions, generator=None, visible_share=self.visible_share)
        warm = out.rgb.sum() + out.depth.sum()
        if warm.requires_grad:  # rays that march no occupied cell (a pruned grid on resume) have no graph
            warm.backward()
        self.field.zero_grad(set_to_none=True)

    @property
    def optimizer(self) -> Adam:
        """Adam on the field (engine/adam.py: torch's update and state_dict), built when first
        asked for (a training step, a checkpoint's state)."""
        with self._optimizer_lock:  # one Adam, and the pending state taken once, whichever thread asks
            if self._optimizer is None:
                optim = self.config.optim
                fused = self.device.type == "cpu" or self.device.type == "cuda"
                adam = Adam(self.field.parameters(), lr=optim.lr, eps=optim.eps, betas=optim.betas, fused=fused)
                if self._optimizer_state is not None:
                    adam.load_state_dict(self._optimizer_state)
                self._optimizer, self._optimizer_state = adam, None
            return self._optimizer

    def build_optimizer(self) -> None:
        """Build Adam now if it is not yet (`optimizer`): before a training step's clock starts, and
        for a caller whose own clock starts before the first step (a real-time replay)."""
        _ = self.optimizer

    def _check_optimizer_state(self, saved) -> None:
        """A checkpoint's Adam state fits this field (one group of its parameters, moments of their
        shapes): checked when read, though Adam takes it at the first step; a ValueError as Adam's
        own loading would raise (a damaged checkpoint is named before any work)."""
        params = list(self.field.parameters())
        groups = saved.get("param_groups") if isinstance(saved, dict) else None
        moments = saved.get("state") if isinstance(saved, dict) else None
        if not isinstance(groups, list) or len(groups) != 1 or not isinstance(groups[0], dict) \
                or len(groups[0].get("params", ())) != len(params) or not isinstance(moments, dict):
            raise ValueError(f"optimizer: expected Adam's state of one group of {len(params)} parameters")
        for i, one in moments.items():
            for key in ("exp_avg", "exp_avg_sq"):
                value = one.get(key) if isinstance(one, dict) and isinstance(i, int) and 0 <= i < len(params) else None
                if not isinstance(value, torch.Tensor) or value.shape != params[i].shape:
                    raise ValueError(f"optimizer: parameter {i}'s {key} does not fit the field")

    def progress(self) -> float:
        """Share of the learning-rate horizon (`schedules.horizon`) used: drives the lr decay."""
        return self.schedules.horizon.share(self.step, self.seconds)

    def train_step(self, progress: float | None = None) -> LossTerms:
        """The one training step, on the training clock: every frame added so far (the prior of
        new frames first); `progress` in [0, 1] of the budget sets the learning rate (the
        schedule's lr * lr_decay_to ** progress; default `self.progress()`)."""
        if progress is not None and (isinstance(progress, bool) or not isinstance(progress, numbers.Real)
                                     or not 0.0 <= progress <= 1.0):  # NaN too: it made every weight NaN
            raise UsageError(f"Mapper.train_step progress {progress!r}: expected a number in [0, 1] or None")
        return self._timed_step(progress)[0]

    @serialised
    def _timed_step(self, progress: float | None = None) -> tuple[LossTerms, float]:
        """`train_step` and the seconds it added to the training clock."""
        self.build_optimizer()  # before the clock starts
        t_start = time.perf_counter()
        terms = self._step(progress)
        took = time.perf_counter() - t_start
        self.seconds += took
        return terms, took

    def _step(self, progress: float | None) -> LossTerms:
        """`train_step` off the clock, as named steps: the step's start-up, the learning rate,
        a batch, the render, the loss (a pure assembly), Adam, the counters, the grid update."""
        self._begin_step()
        schedule = self.schedule
        self._set_learning_rate(schedule, self.progress() if progress is None else progress)
        batch = self._sample(schedule)
        rgb_rays = colour_rays(self.config, batch)
        out, stats = self.model.render(batch.origins, batch.directions, generator=self.generator, rgb_rays=rgb_rays,
                                       visible_share=self.visible_share)
        terms = step_loss(self.config, batch, out, stats.samples, rgb_rays,
                          stereo_line_of_sight(self.config, self.box, self.extent.growing, self.driving))
        self._optimise(terms)
        self._count(stats)
        self._update_grid(schedule, batch, stats)
        return terms

    def _begin_step(self) -> None:
        """Kernels loaded, the sensor prior of frames added since the last step applied, and the
        frames present at the first step remembered (they count as seen at step 0)."""
        if not self._warm:
            self.prepare()
        self._apply_pending_prior()
        if self._frames_at_start is None:
            self._frames_at_start = self.frames

    def _set_learning_rate(self, schedule: StepSchedule, progress: float) -> None:
        lr = schedule.learning_rate(progress)
        for g in self.optimizer.param_groups:
            g["lr"] = lr

    def _sample(self, schedule: StepSchedule) -> RayBatch:
        """The step's rays: as many as the schedule's sample cap allows, the newest frames
        favoured while driving (RecentFrames)."""
        n_rays = schedule.rays(self.config.batch_size, self.last_samples_per_ray)
        batch = self.sampler.sample(self.rng, n_rays, np.arange(self.frames), self._frame_odds(schedule))
        return batch.to(self.device)

    def _optimise(self, terms: LossTerms) -> None:
        """Adam on the field; a batch that marched no occupied cell (all rays out of the box)
        has no graph and changes nothing, nor does a loss that is not finite (one such step would
        make every weight NaN, and a NaN field maps everything free: counted in `skipped_steps`)."""
        self.optimizer.zero_grad(set_to_none=True)
        loss = float(terms.total.detach())  # read here, before the update (a sync on a GPU)
        self.last_loss = loss if math.isfinite(loss) else None  # snapshot.json: a number or null
        if self.last_loss is None:
            self.skipped_steps += 1
            return
        if terms.total.requires_grad:
            terms.total.backward()
            self.optimizer.step()

    def _count(self, stats) -> None:
        if stats.visible_share is not None:
            self.visible_share = stats.visible_share
        self.step += 1
        self.samples += stats.n_samples
        self.rays += stats.n_rays
        self.last_samples_per_ray = stats.n_samples / max(1, stats.n_rays)

    def _update_grid(self, schedule: StepSchedule, batch: RayBatch, stats) -> None:
        """Every `update_interval` steps: the warm-up restarted where the cameras first look
        while driving, then the grid's own update from this step's rays and densities."""
        if self.step % self.grid.update_interval == 0:
            self._restart_warmup_in_view()
            self.grid.update(self.step, self.field.density, self._grid_batch(batch, stats), self.generator,
                             driving=schedule.driving)

    def _restart_warmup_in_view(self) -> None:
        """virus_grid.warmup_restart "view": the grid columns in the camera view wedges of the
        frames added since the last grid update (maps/observed.py, 12 m), for the grid to restart
        the warm-up of those seen for the first time after the first step (frames present at the
        first step count as seen at step 0)."""
        grid = self.grid
        if getattr(grid.config, "warmup_restart", "run") != "view" or not self.driving:
            return  # offline every frame is there from the first step: nothing to restart
        at_start = max(self._frames_at_start or 0, self._seen_at_start)
        if self._viewed_frames < at_start:  # the frames of the first step: seen at step 0
            grid.restart_warmup_in_view(self._viewed_columns(self._viewed_frames, at_start), 0)
        new = max(self._viewed_frames, at_start)  # the first frame that arrived while driving
        if new < self.frames:
            grid.restart_warmup_in_view(self._viewed_columns(new, self.frames), self.step)
        self._viewed_frames = self.frames

    def _viewed_columns(self, first: int, last: int) -> np.ndarray:
        """(rx, ry) bool: the grid columns inside the view wedges of store rows first..last-1."""
        spec = self.grid.spec
        rows = np.arange(first, last)
        cell = spec.cell_size
        return frames_observed(self.store.cam_to_world[rows], self.store.stack_ids[rows], self.intrinsics,
                               np.asarray(spec.box.lo[:2]), spec.resolution[:2], (float(cell[0]), float(cell[1])))

    @property
    def schedule(self) -> StepSchedule:
        """The next step's schedule: offline, or driving once frames arrive after the first step."""
        return self.schedules.pick(self.driving)

    @property
    def driving(self) -> bool:
        """True once frames were added after the first training step (mapping while driving):
        the batch then favours the newest frames (config.recent), the learning rate decays to
        optim.lr_decay_driving instead of optim.lr_decay_to, a step's samples are capped by
        max_samples_per_step_driving, and the grid is told (its warm-up:
        virus_grid.warmup_steps_driving)."""
        return self._frames_at_start is not None and self.frames > self._frames_at_start

    def _frame_odds(self, schedule: StepSchedule) -> np.ndarray | None:
        """Per-frame odds of the next batch: None (uniform) offline, the schedule's share on
        the newest frames while driving."""
        if schedule.recent_share <= 0.0:
            return None
        return recent_frame_odds(self.store.times, schedule.recent_share, schedule.recent_window)

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

    def train(self, seconds: float, steps: int | None = None) -> TrainSlice:
        """Train on the frames added so far for `seconds` of training clock (and at most `steps`
        steps); the one-off start-up of the first call (kernel loading) is not counted."""
        if isinstance(seconds, bool) or not isinstance(seconds, numbers.Real) or not math.isfinite(seconds) \
                or seconds < 0:
            raise UsageError(f"Mapper.train seconds {seconds!r}: expected a finite number >= 0")
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 0):
            raise UsageError(f"Mapper.train steps {steps!r}: expected an integer >= 0 or None")
        self.prepare()
        done, spent, loss = 0, 0.0, None  # this call's own steps and clock (another thread may load_state meanwhile)
        while spent < seconds and (steps is None or done < steps):
            terms, took = self._timed_step()
            done, spent, loss = done + 1, spent + took, float(terms.total.detach())
        return TrainSlice(steps=done, seconds=spent, loss=loss, frames=self.frames, total_steps=self.step,
                          total_seconds=self.seconds)


def warm_up(config: MapperConfig) -> float:
    """Load the mapper's kernels on a throwaway mapper (one small synthetic frame, one step) before
    the drive's clock starts, as a robot starts its mapper before it drives off: the first real
    frame is then not seconds late, and a callback adding frames does not wait for the first
    `train` (measured on 2 shared cores: the first render 0.2-0.8 s, tens of seconds when numba
    compiles the kernels, the first time after an install; the first snapshot 0.2 s).
    Returns the seconds of its training step (a first step on one small frame)."""
    import tempfile

    from virus_nerf.sensors.camera import Intrinsics

    intr = Intrinsics(fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48)
    cfg = dataclasses.replace(config, max_steps=1, max_time=None)
    mapper = Mapper(cfg, {0: intr}, SceneBox((-3.0, -3.0, -1.0), (3.0, 3.0, 2.0)))
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]]  # level, looking along +x
    rgb = np.full((intr.height, intr.width, 3), 128, dtype=np.uint8)
    depth = np.full((intr.height, intr.width), 2.0, dtype=np.float32) if "rgbd" in cfg.sensors else None
    mapper.add_frame(SyncFrame(time=0.0, stack_id=0, rgb=rgb, cam_to_world=pose, uss_range=2.0,
                               irs_range=np.full((8, 8), 2.0), depth=depth))
    t = time.perf_counter()
    mapper.train(1.0, steps=1)  # the optimiser's and backward's first calls: longer than a later step
    step_s = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp:  # the map code's first call (imports)
        mapper.snapshot(Path(tmp) / "warm", n_rays=8, max_poses=1)
    return step_s
