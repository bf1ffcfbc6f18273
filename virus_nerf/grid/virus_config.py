"""The VIRUS grid's parameters (docs/method.md 3.4): one frozen dataclass, checked on creation."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from virus_nerf.checks import Checks


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class VirusGridConfig:
    """VIRUS grid parameters; every length in metres, rates per metre, densities in 1/m.

    update_interval, rays_per_update, std_per_m, false_rate and zeta come from the tuning study
    (see LossWeights); threshold_alpha (0.15, above the study's range; the study gave 0.0438) and
    warmup_steps (660; the study gave 330, D70) from the time-to-map benchmark; configs/paper.json
    restores the earlier values (128, 16, 1024, 0.03, 0.3, 0.25, 0.01).
    """

    max_resolution: int = 128  # cells along the longest box axis (GridSpec.from_box)
    logodds_min: float = -4.0  # clamp (p ~ 0.018)
    logodds_max: float = 4.0  # clamp (p ~ 0.982)
    init_probability: float = 0.55  # slightly above 0.5: everything is marched at first
    prior_probability: float = 0.49  # where unsupported cells end after the warm-up (empty)
    # training steps (not updates) of the decay init -> prior. 660, the driving length, by the
    # wall clock: better coverage in the office at 60 s and the common area at 180 s, the warehouse
    # the same (D70; earlier 330, D4; 1000 never leaves the warm-up in Table I's 75 s runs)
    warmup_steps: int = 660
    # while mapping while driving (frames keep arriving): a cell first seen after the warm-up can
    # only come back through the IRS, so the warm-up lasts longer (D6)
    warmup_steps_driving: int = 660
    # "view": while driving, a column of cells that a camera first looks at after the first step
    # starts its warm-up again from p_init (evidence kept), so a part of the room reached late is
    # marched and learnt as the first part was (otherwise it is already empty, and only the IRS
    # brings it back; D41); "run": one clock for every cell, the paper's. Offline both are the same
    warmup_restart: Literal["run", "view"] = "view"
    update_interval: int = 21  # training steps between grid updates (the trainer calls update)
    rays_per_update: int = 438  # rays per update, both kinds together (paper: ~1k)
    depth_share: float = 0.5  # share of rays_per_update for the Depth-Update (rest: NeRF)
    # Start-up: before step 0, a Depth-Update over every training IRS frame ("sensors"), so free
    # space and surfaces the IRS saw are known from the start; "none" = the paper's plain warm-up.
    init: Literal["sensors", "none"] = "sensors"
    init_zone_samples: int = 3  # rays per IRS zone and axis in that pass (3 -> 9 rays per zone)
    # the cells holding the stereo sensor's triangulated points (issue 28's measured surfaces) get
    # this log-odds increment once, as the points arrive (offline before step 0, while driving at
    # each refresh of the tracker): a surface the cameras measured stays marched, so the field can
    # learn it before the NeRF-Update empties it (D84: zone 3 accuracy and free recall better in
    # every room kind, offline and while driving); 0 = none
    stereo_point_increment: float = 2.0
    # NeRF-Update densities: "forward" (default, the paper's speed-up, D8) reuses the densities
    # of the training forward pass: no extra network pass, and only cells the marcher sampled get
    # evidence, so cells nothing renders through are not raised by haze. "resample" draws
    # nerf_points_per_ray points along rays of the batch and evaluates the density MLP there.
    nerf_update_source: Literal["resample", "forward"] = "forward"
    # Depth-Update (IRS, MURIEL model; sensor_model docstring)
    std_per_m: float = 0.0066  # range noise grows 0.66 cm per metre ...
    std_floor: float = 0.02  # ... on top of 2 cm (pose error, zone width)
    false_rate: float = 2.4043  # lambda: false detections per metre (docs/method.md 3.4)
    hit_probability: float = 0.4  # p_hit: an occupied cell crossed fully stops the beam (0.7 punched holes: a zone-median range is not every pixel ray's range)
    stop_length: float = 0.02  # metres of beam inside a cell for p_det to reach 63 % of p_hit
    max_increment: float = 2.0  # |log-odds change| per cell per measurement
    # NeRF-Update (eq. 9)
    zeta: float = 0.4196  # slope: a density ratio of 1000 moves a cell by 2.9
    nerf_points_per_ray: int = 64  # points drawn uniformly in [0, nerf_far] per ray
    pos_noise_per_m: float = 0.05  # std of the point jitter per metre along the ray
    threshold_step: float = 0.01  # sigma_T_max: density at which a step of this many metres ...
    # ... has this alpha (Instant-NGP: 0.01, docs/method.md 3.3); 0.15 gives sigma_T_max 16.3 /m
    # (D1; 0.4: D2)
    threshold_alpha: float = 0.15
    sigma_floor: float = 1e-6  # 1/m, keeps ln(sigma) finite

    def __post_init__(self) -> None:
        check = Checks(self, "virus_grid.")
        integer, number, choice = check.integer, check.number, check.choice
        integer("max_resolution", 1)
        number("logodds_min", -math.inf, 0.0, hi_open=True)
        number("logodds_max", 0.0)
        number("init_probability", 0.5, 1.0, hi_open=True)
        number("prior_probability", 0.0, 0.5, hi_open=True)
        integer("warmup_steps", 1)
        integer("warmup_steps_driving", 1)
        choice("warmup_restart", ("run", "view"))
        integer("update_interval", 1)
        integer("rays_per_update", 0)
        number("depth_share", 0.0, 1.0, lo_open=False)
        choice("init", ("sensors", "none"))
        integer("init_zone_samples", 1)
        number("stereo_point_increment", 0.0, lo_open=False)
        choice("nerf_update_source", ("resample", "forward"))
        number("std_per_m", 0.0, lo_open=False)
        number("std_floor", 0.0)
        number("false_rate", 0.0)
        number("hit_probability", 0.0, 1.0, hi_open=True)
        number("stop_length", 0.0)
        number("max_increment", 0.0)
        number("zeta", 0.0)
        integer("nerf_points_per_ray", 1)
        number("pos_noise_per_m", 0.0, lo_open=False)
        number("threshold_step", 0.0)
        number("threshold_alpha", 0.0, 1.0, hi_open=True)
        number("sigma_floor", 0.0)

    @property
    def sigma_threshold_max(self) -> float:
        """sigma_T_max (1/m): -ln(1 - alpha) / step, 16.3 /m by default (paper.json: 1.005)."""
        return -math.log(1.0 - self.threshold_alpha) / self.threshold_step

    @property
    def logodds_init(self) -> float:
        return _logit(self.init_probability)

    @property
    def logodds_prior(self) -> float:
        return _logit(self.prior_probability)
