"""A Mapper's state for checkpoints (mixed into `Mapper`, as `views.MapViews` is): `state()`
copies everything but the frames; `load_state` continues from one after `state_problem` checked it
whole (engine/state.py's checks), so a damaged or foreign state is refused with the key that is
wrong and the mapper left as it was."""

from __future__ import annotations

import copy
from collections.abc import Mapping

import numpy as np
import torch

from virus_nerf.engine.state import (
    STATE_KEYS,
    counters_problem,
    expected_frames,
    frames_mismatch,
    generators_problem,
    optional_counters_problem,
    tensors_problem,
)
from virus_nerf.engine.views import serialised
from virus_nerf.errors import UsageError
from virus_nerf.scene_box import SceneBox


class MapperCheckpoint:
    """`state`, `state_problem` and `load_state` of a `Mapper` (its attributes, set in
    `Mapper.__init__`)."""

    @serialised
    def state(self) -> dict:
        """Everything to continue training (not the frames), copied: a timer thread may train on
        while another writes it out (torch.save) and it stays the state of this moment."""
        return {
            "field": copy.deepcopy(self.field.state_dict()),
            "optimizer": copy.deepcopy(self._optimizer_state_dict()),
            "grid": self.grid.state_dict(),  # copies already
            "step": self.step,
            "seconds": self.seconds,
            "samples": self.samples,
            "rays": self.rays,
            "last_samples_per_ray": self.last_samples_per_ray,  # sets the next step's ray count
            "numpy_rng": self.rng.bit_generator.state,
            "torch_generator": self.generator.get_state(),
            "box": self.box.to_dict(),
            "prior_frames": self._prior_done,
            "frames": self.frames,  # a driving run's loader adds exactly these (not all due at its clock)
            # which frames those were (load_state checks the frames added again against them)
            "frame_stacks": torch.from_numpy(self.store.stack_ids[:self.frames].astype(np.int64)),
            "frame_times": torch.from_numpy(self.store.times[:self.frames].astype(np.float64)),
            "stereo_points": self._stereo_points_done,
            "frames_at_start": self._frames_at_start,
            "viewed_frames": self._viewed_frames,
            "visible_share": self.visible_share,  # picks the next step's render path
        }

    def _optimizer_state_dict(self) -> dict:
        """Adam's state: a checkpoint's still pending (Adam not built yet), else Adam's own."""
        pending = self._optimizer_state  # read once: another thread may build Adam meanwhile
        return pending if pending is not None else self.optimizer.state_dict()

    def state_problem(self, state: dict) -> tuple[str, str] | None:
        """(key, what is wrong) of a state this mapper cannot continue from, checked whole before
        `load_state` touches anything; None when it can (engine/state.py)."""
        if not isinstance(state, Mapping):
            return "state", f"expected the dict of Mapper.state(), got a {type(state).__name__}"
        missing = [k for k in STATE_KEYS if k not in state]
        if missing:
            return "state", f"lacks {missing}; expected the dict of Mapper.state()"
        problem = counters_problem(state) or tensors_problem("field", state["field"], self.field.state_dict())
        if problem:
            return problem
        try:
            self._check_optimizer_state(state["optimizer"])
        except ValueError as exc:
            return "optimizer", str(exc).removeprefix("optimizer: ")
        if "box" in state:
            try:
                saved = SceneBox.from_dict(state["box"])
            except (TypeError, ValueError, KeyError) as exc:
                return "box", f"expected {{'lo': [x, y, z], 'hi': [x, y, z]}} in metres ({type(exc).__name__}: {exc})"
            box = self.box
            if not self.extent.growing and not (np.allclose(saved.lo, box.lo, atol=1e-6)
                                                and np.allclose(saved.hi, box.hi, atol=1e-6)):
                return "box", (f"lo={list(saved.lo)} hi={list(saved.hi)} does not match this mapper's lo={list(box.lo)} "
                               f"hi={list(box.hi)}; the field would be read in another frame")
        own_grid = {k: v for k, v in self.grid.state_dict().items() if k not in self.grid.optional_state_keys}
        return tensors_problem("grid", state["grid"], own_grid, shapes=not self.extent.growing) \
            or generators_problem(state) or self._frames_problem(state) or optional_counters_problem(state)

    def _frames_problem(self, state: dict) -> tuple[str, str] | None:
        """("frame_times", what) when the state's frame list is malformed or the frames present do
        not begin it (a state written before the list existed: None, nothing to check)."""
        expected = expected_frames(state)
        if isinstance(expected, str):
            return "frame_times", expected
        n = min(self.frames, len(expected[0]))
        problem = frames_mismatch(expected, 0, self.store.stack_ids[:n], self.store.times[:n])
        return None if problem is None else ("frame_times", problem)

    @serialised
    def load_state(self, state: dict) -> None:
        """Continue from `state()` (read on the CPU). The frames are not in it: add them again in
        the same order (before or after; a frame that is not the state's frame of its row is refused,
        by stack and time, with the same `restart_clock` calls); the first `prior_frames` of them do
        not get the sensor prior again. A state this mapper cannot continue from is a one-line
        UsageError naming the key, the mapper unchanged."""
        problem = self.state_problem(state)
        if problem is not None:
            raise UsageError(f"Mapper.load_state state[{problem[0]!r}]: {problem[1]}")
        if "box" in state:  # a grown box: the grid grows to it first
            self._grow(self.extent.restore(SceneBox.from_dict(state["box"])))
        self.field.load_state_dict(state["field"])
        self._expected_frames = expected_frames(state)
        self._check_optimizer_state(state["optimizer"])
        with self._optimizer_lock:
            if self._optimizer is None:
                self._optimizer_state = state["optimizer"]  # Adam takes it when first asked for (`optimizer`)
            else:
                self._optimizer.load_state_dict(state["optimizer"])
        self.grid.load_state_dict(state["grid"])
        self.step = int(state["step"])
        self.seconds = float(state["seconds"])
        self.samples = int(state["samples"])
        self.rays = int(state.get("rays", self.step * self.config.batch_size))
        self.last_samples_per_ray = float(state.get("last_samples_per_ray", 0.0))
        self.rng.bit_generator.state = state["numpy_rng"]
        self.generator.set_state(state["torch_generator"])
        self.visible_share = float(state.get("visible_share", 1.0))
        self._stereo_points_done = int(state.get("stereo_points", 0))  # its grid has had these
        self._frames_at_start = state.get("frames_at_start")
        # a state without it (written before the restart existed): the frames it was trained on
        # count as seen at step 0 when the grid first hears of them
        self._viewed_frames = int(state.get("viewed_frames", 0))
        self._seen_at_start = 0 if "viewed_frames" in state else int(state.get("prior_frames") or 0)
        if "prior_frames" in state:
            self._prior_done, self._prior_skip = int(state["prior_frames"]), False
        else:  # written before the count existed: the grid had the prior of every frame present
            self._prior_done, self._prior_skip = 0, True
