"""The engine's configuration: only the knobs the `Mapper` reads (the method, its sensors and
its schedule), validated in one place. `trainer.config.TrainConfig` adds the run's knobs (budget
checks, evaluation, logging, the online clock) on top; config.json holds both."""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Literal

from virus_nerf.checks import Checks
from virus_nerf.field.config import FieldConfig
from virus_nerf.grid.extent import ExtentConfig
from virus_nerf.grid.ngp_config import NgpGridConfig
from virus_nerf.grid.virus_config import VirusGridConfig
from virus_nerf.losses.weights import LossWeights
from virus_nerf.sampler.shares import SENSORS, BatchShares
from virus_nerf.stereo.depth import StereoConfig


@dataclass
class MarchConfig:
    """Ray marching along training and scan rays (metres)."""

    step_size: float = 0.03  # m, constant step; 0.01-0.05 m suits rooms
    near: float = 0.05  # m, start of every ray, in front of the lens
    max_samples: int = 256  # per ray, after occupancy skipping
    # training: samples behind a transmittance below this get no gradient pass (a density-only
    # pass finds them first). 0 renders every sample with gradients; 1e-4 is Instant-NGP's early
    # termination (docs/method.md 10, docs/decisions.md D12)
    min_transmittance: float = 1e-4
    backend: str = "auto"  # marching and compositing: auto (numba on CPU, torch on CUDA) | numba | torch

    def __post_init__(self) -> None:
        if self.backend not in ("auto", "numba", "torch"):
            raise ValueError(f"march.backend {self.backend!r}: expected 'auto', 'numba' or 'torch'")


@dataclass
class OptimConfig:
    """The Adam optimiser and its learning-rate decay."""

    lr: float = 0.0094  # Adam's learning rate; from the tuning study (docs/decisions.md D11; the paper's 5e-3 is a GPU's)
    eps: float = 1e-15  # Adam's epsilon
    betas: tuple[float, float] = (0.9, 0.99)  # Adam's decay rates of the moment estimates
    lr_decay_to: float = 0.1  # exponential decay to this fraction of lr at max_steps/max_time
    # the same while mapping while driving (frames added after the first step: --online,
    # map-bag). 1 = a constant lr: new frames keep arriving, and a decayed lr leaves the last part
    # of the drive half-trained (D25)
    lr_decay_driving: float = 1.0


@dataclass
class RecentFrames:
    """Mapping while driving: a share of every batch from the newest frames.

    Once frames arrive after training has begun (`--online`, `map-bag`, `Mapper.add_frame`
    between `train` calls), `share` of each batch's rays come from the frames of the last
    `window` seconds of recording time and the rest from all frames; a frame just driven past
    otherwise gets 1/N of the rays. Offline (every frame present at the first step) it does
    nothing. share 0 samples all frames alike.
    """

    share: float = 0.5  # of each batch, from the frames of the last `window` seconds
    window: float = 5.0  # seconds of recording time


# The knobs a robot user sets (dotted paths): the sensors, the budget, the resolution and the
# extent, the weights that matter. `train --help` lists these; every other field is a research
# knob (the sensor models, the grid's and the tracker's internals, the kernels, the optimiser's
# constants, the studies' switches), listed by `train --help-all` and set the same way.
PRODUCT_KNOBS = (
    "sensors", "max_steps", "max_time", "batch_size", "seed", "image_scale", "device",
    "extent.mode", "extent.reach_m", "extent.height_m", "extent.grid_cell_m",
    "march.step_size", "optim.lr", "virus_grid.max_resolution",
    "weights.colour", "weights.irs", "weights.uss", "weights.stereo",
)


@dataclass
class MapperConfig:
    """Every knob of the method (docs/method.md 3): the grid, the sensors, the field, the
    marcher, the losses, the optimiser and its schedule. max_steps / max_time only shape the
    learning-rate decay here (`Mapper.train(seconds)` decides how long to train)."""

    grid: Literal["virus", "ngp"] = "virus"  # occupancy grid for ray marching: virus (Bayesian) or ngp (Instant-NGP)
    # sensors trained on: camera, uss, irs, rgbd, stereo. The stereo sensor (depth triangulated
    # from the cameras' own tracks, docs/method.md 3.7) is on by default (docs/decisions.md D31)
    sensors: tuple[str, ...] = ("camera", "uss", "irs", "stereo")
    max_steps: int | None = None  # stop after this many steps (None: no step limit)
    max_time: float | None = 120.0  # seconds of training, evaluation excluded, checked after each step (None: no limit)
    batch_size: int = 2048  # rays per step (at most, with max_samples_per_step)
    # cap on a step's samples, like Instant-NGP's fixed sample budget per step. While rays are
    # long (the grid's warm-up, a large room, the first frames online) a step takes fewer rays,
    # min(batch_size, cap / the last step's samples per ray), at least batch_size / 8; None:
    # always batch_size rays. Off offline (D24); max_samples_per_step_driving replaces it while
    # mapping while driving (32768 = 2048 rays x 16 samples, D23)
    max_samples_per_step: int | None = None
    max_samples_per_step_driving: int | None = 32768  # the same while mapping while driving (frames arrive after the first step)
    seed: int = 0  # seed of everything random
    image_scale: float = 0.5  # training image resolution relative to the recording
    device: str = "auto"  # auto | cpu | cuda
    min_opacity: float = 0.5  # scan rays with lower opacity give no point (docs/method.md 3.1)
    # depth-supervised (IRS, RGB-D) rays train the density alone: no colour MLP, no colour loss
    density_only_depth_rays: bool = False
    field: FieldConfig = dc_field(default_factory=FieldConfig.cpu_default)
    march: MarchConfig = dc_field(default_factory=MarchConfig)
    optim: OptimConfig = dc_field(default_factory=OptimConfig)
    shares: BatchShares = dc_field(default_factory=BatchShares)
    recent: RecentFrames = dc_field(default_factory=RecentFrames)
    weights: LossWeights = dc_field(default_factory=LossWeights)
    ngp_grid: NgpGridConfig = dc_field(default_factory=NgpGridConfig)
    virus_grid: VirusGridConfig = dc_field(default_factory=VirusGridConfig)
    # the stereo sensor: depth triangulated from the cameras' own tracks (docs/method.md 3.7)
    stereo: StereoConfig = dc_field(default_factory=StereoConfig)
    # the map's extent: fitted to the room before the first step, or grown from the first frame
    # as the robot drives (a room never seen; grid/extent.py, docs/extent.md)
    extent: ExtentConfig = dc_field(default_factory=ExtentConfig)

    def __post_init__(self) -> None:
        """Types and ranges of every top-level knob (and the nested ones that would crash a
        step); a bad value is a ValueError naming the field, the value and what was expected."""
        check = Checks(self)
        integer, number, flag, bad = check.integer, check.number, check.flag, check.bad
        self._build_sections(bad)
        if isinstance(self.sensors, str):
            self.sensors = tuple(s.strip() for s in self.sensors.split(",") if s.strip())
        allowed = set(SENSORS)
        if not isinstance(self.sensors, tuple | list) or not all(isinstance(s, str) for s in self.sensors):
            raise bad("sensors", self.sensors, f"a non-empty subset of {sorted(allowed)}")
        self.sensors = tuple(dict.fromkeys(self.sensors))  # each once, as the --sensors flag takes them
        bad_sensors = set(self.sensors) - allowed
        if bad_sensors or not self.sensors:
            raise ValueError(f"sensors {self.sensors}: expected a non-empty subset of {sorted(allowed)}")
        if self.grid not in ("virus", "ngp"):
            raise ValueError(f"grid {self.grid!r}: expected 'virus' or 'ngp'")
        integer("max_steps", 1, optional=True)
        number("max_time", 0.0, optional=True)
        if self.max_steps is None and self.max_time is None:
            raise ValueError("max_steps and max_time are both None: set max_steps or max_time (or both)")
        integer("batch_size", 1)
        integer("max_samples_per_step", 1, optional=True)
        integer("max_samples_per_step_driving", 1, optional=True)
        integer("seed", 0, 2**32 - 1)
        number("image_scale", 0.0, 1.0)
        if not isinstance(self.device, str) or not (self.device in ("auto", "cpu", "cuda")
                                                    or self.device.startswith("cuda:")):
            raise bad("device", self.device, "'auto', 'cpu', 'cuda' or 'cuda:<index>'")
        number("min_opacity", 0.0, 1.0, lo_open=False)
        flag("density_only_depth_rays")
        # bounds that keep a step finite: a 0.1 mm step walks 10^4 samples a metre, a start
        # beyond 100 m leaves no ray in any room, exp(88.7) overflows float32
        number("march.step_size", 1e-4, lo_open=False)
        number("march.near", 0.0, 100.0, lo_open=False)
        integer("march.max_samples", 1)
        number("march.min_transmittance", 0.0, 1.0, lo_open=False)
        number("optim.lr", 0.0)
        number("optim.eps", 0.0)
        number("optim.lr_decay_to", 0.0)
        number("optim.lr_decay_driving", 0.0)
        integer("virus_grid.update_interval", 1)
        integer("ngp_grid.update_interval", 1)
        # the nested sections whose own classes take any number: a bad value would end in a
        # traceback (ZeroDivisionError, a torch shape error) after the data were read, or train
        # on silently (a zero-width layer, a negative share or weight)
        for name in ("density_hidden", "color_hidden"):
            for i, width in enumerate(getattr(self.field, name)):
                if not (isinstance(width, numbers.Integral) and width >= 1):
                    raise bad(f"field.{name}[{i}]", width, "an integer >= 1 (layer width)")
        number("field.density_clamp", 0.0, 80.0)
        integer("ngp_grid.max_resolution", 1)
        integer("ngp_grid.warmup_steps", 0)
        integer("ngp_grid.chunk_size", 1)
        number("ngp_grid.decay", 0.0, 1.0)
        number("ngp_grid.min_alpha", 0.0, 1.0, hi_open=True)
        for i, beta in enumerate(self.optim.betas):
            if not (isinstance(beta, numbers.Real) and not isinstance(beta, bool) and 0.0 <= beta < 1.0):
                raise bad(f"optim.betas[{i}]", beta, "a number in [0, 1)")
        number("recent.share", 0.0, 1.0, lo_open=False)
        number("recent.window", 0.0)
        number("shares.irs", 0.0, 1.0, lo_open=False)
        number("shares.uss", 0.0, 1.0, lo_open=False)
        number("shares.stereo", 0.0, 1.0, lo_open=False)
        if self.shares.irs + self.shares.uss + self.shares.stereo > 1.0:
            raise ValueError(f"shares.irs {self.shares.irs!r} + shares.uss {self.shares.uss!r} + shares.stereo "
                             f"{self.shares.stereo!r}: expected a sum <= 1 (the rest of the batch are random pixels)")
        for name in ("colour", "irs", "uss", "rgbd", "stereo", "distortion"):
            number(f"weights.{name}", 0.0, lo_open=False)
        number("weights.stereo_sigma_ref", 0.0)
        for name in ("free_uss", "free_margin", "free_stereo", "free_stereo_room_m"):
            number(f"weights.{name}", 0.0, lo_open=False)
        number("weights.free_stereo_short", 0.0, 1.0, lo_open=False, hi_open=True)

    def _build_sections(self, bad) -> None:
        """A section given as a dict (`MapperConfig(extent={"mode": "grow"})`, as a config file
        writes it) is built with the section's defaults for the keys it lacks; anything else but
        the section's own class is refused, naming it."""
        import dataclasses
        from collections.abc import Mapping

        for f in dataclasses.fields(MapperConfig):
            if f.default_factory is dataclasses.MISSING:
                continue
            kind = type(f.default_factory())
            value = getattr(self, f.name)
            if not dataclasses.is_dataclass(kind) or isinstance(value, kind):
                continue
            if not isinstance(value, Mapping):
                raise bad(f.name, value, f"{kind.__name__} or a dict of its keys")
            known = [g.name for g in dataclasses.fields(kind)]
            unknown = sorted(set(value) - set(known))
            if unknown:
                raise ValueError(f"{f.name} {dict(value)!r}: unknown key(s) {unknown}; expected keys of "
                                 f"{kind.__name__}: {known}")
            setattr(self, f.name, kind(**value))

    def engine(self) -> MapperConfig:
        """This config's engine knobs alone (a `TrainConfig` drops its run knobs; the sections
        are shared, not copied)."""
        import dataclasses

        return MapperConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(MapperConfig)})
