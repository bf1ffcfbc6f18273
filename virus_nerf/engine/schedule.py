"""How long and how wide a training step is: the learning-rate horizon (`Horizon`), the rays per
step and the offline / driving schedules (`StepSchedule`, `Schedules`), handed to a `Mapper` by
its caller (gsplat's strategies): `train` with the config's budget, `train --online`, `map-bag`
and the ROS 2 node with the drive's length (`Horizon.drive`)."""

from __future__ import annotations

from dataclasses import dataclass


def budget_share(step: int, seconds: float, max_steps: int | None, max_time: float | None) -> float:
    """Share in [0, 1] of a step and/or time budget used (the larger of the two)."""
    parts = [0.0]
    if max_steps is not None:
        parts.append(step / max_steps)
    if max_time is not None:
        parts.append(seconds / max_time)
    return min(1.0, max(parts))


def rays_for_step(batch_size: int, max_samples: int | None, last_samples_per_ray: float) -> int:
    """Rays of the next step under a sample budget (TrainConfig.max_samples_per_step).

    min(batch_size, max_samples / last_samples_per_ray), never below batch_size // 8 (at least
    1); batch_size without a budget or before the first step (no samples per ray measured yet).
    """
    if max_samples is None or last_samples_per_ray <= 0.0:
        return batch_size
    floor = max(1, batch_size // 8)
    return int(min(batch_size, max(floor, max_samples // max(1.0, last_samples_per_ray))))


@dataclass(frozen=True)
class Horizon:
    """The budget the learning rate decays over: `max_steps` steps and/or `max_time` seconds of
    training clock (the larger share counts; budget_share)."""

    max_steps: int | None = None
    max_time: float | None = None

    @classmethod
    def of(cls, config) -> Horizon:
        """The config's own budget (a MapperConfig's max_steps / max_time)."""
        return cls(config.max_steps, config.max_time)

    @classmethod
    def drive(cls, drive_s: float, playback: float, max_steps: int | None = None) -> Horizon:
        """Mapping while driving: the drive's length in training seconds (`drive_s` of recording
        at `playback` recording seconds per second; at least 1 ms), and a step bound if any."""
        return cls(max_steps, max(drive_s / playback, 1e-3))

    def share(self, step: int, seconds: float) -> float:
        """Share in [0, 1] of the horizon used after `step` steps and `seconds` s of training."""
        return budget_share(step, seconds, self.max_steps, self.max_time)


@dataclass(frozen=True)
class StepSchedule:
    """How a step behaves in one mode: offline (every frame present at the first step) or
    driving (frames still arriving: `train --online`, `map-bag`, `Mapper.add_frame` between
    `train` calls). Built once from the config (`for_mode`); the caller owns the state that picks
    the mode (`Mapper.driving`) and the budget share, and passes both each step."""

    driving: bool
    lr: float  # Adam's learning rate at the start
    lr_decay_to: float  # lr * lr_decay_to ** progress
    max_samples_per_step: int | None  # cap on a step's samples (rays_for_step)
    recent_share: float  # share of each batch from the newest frames (0: uniform)
    recent_window: float  # s of recording time that count as newest

    @classmethod
    def for_mode(cls, config, driving: bool) -> StepSchedule:
        """The schedule of `config` (a MapperConfig) offline or while driving."""
        return cls(
            driving=driving,
            lr=config.optim.lr,
            lr_decay_to=config.optim.lr_decay_driving if driving else config.optim.lr_decay_to,
            max_samples_per_step=config.max_samples_per_step_driving if driving else config.max_samples_per_step,
            recent_share=config.recent.share if driving else 0.0,
            recent_window=config.recent.window,
        )

    def learning_rate(self, progress: float) -> float:
        """lr after `progress` in [0, 1] of the budget."""
        return self.lr * self.lr_decay_to ** progress

    def rays(self, batch_size: int, last_samples_per_ray: float) -> int:
        """Rays of the next step under this mode's sample cap."""
        return rays_for_step(batch_size, self.max_samples_per_step, last_samples_per_ray)


@dataclass(frozen=True)
class Schedules:
    """A mapper's schedules: offline, driving, and the learning-rate horizon both decay over."""

    offline: StepSchedule
    driving: StepSchedule
    horizon: Horizon

    @classmethod
    def of(cls, config, horizon: Horizon | None = None) -> Schedules:
        """`config`'s schedules (a MapperConfig) over `horizon` (default: the config's budget)."""
        return cls(StepSchedule.for_mode(config, False), StepSchedule.for_mode(config, True),
                   horizon or Horizon.of(config))

    def pick(self, driving: bool) -> StepSchedule:
        return self.driving if driving else self.offline
