"""The run's configuration: the engine's knobs (engine/config.py) and the run's own (the
evaluation, logs, checkpoints, the online clock), one typed tree saved as config.json."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field

from virus_nerf.engine.config import PRODUCT_KNOBS as MAPPER_PRODUCT_KNOBS
from virus_nerf.engine.config import Checks, MapperConfig
from virus_nerf.evaluation.config import SENSOR_NAMES, EvaluationConfig

# `train --help`'s knobs: the engine's product knobs and the run's own a user sets
PRODUCT_KNOBS = MAPPER_PRODUCT_KNOBS + ("online", "playback_speed", "odometry_poses", "eval_interval",
                                        "checkpoint_every", "threads")


@dataclass
class TrainConfig(MapperConfig):
    """A `virus-nerf train` run: the Mapper's config plus the run folder's knobs."""

    online: bool = False  # frames become available as the training clock passes their time
    playback_speed: float = 1.0  # online: recording seconds per training second
    odometry_poses: bool = False  # train on the odometry poses (ablation row 7)
    eval_interval: float = 0.0  # seconds of training between NeRF-scan evaluations (0 = end only)
    log_every: int = 25  # steps between log lines
    checkpoint_every: float = 60.0  # seconds of training between checkpoints
    # RUN/plots/ at the end (scan maps, metric bars, the curve, the map's safety picture): ~5 s of
    # matplotlib on a 2-core CPU, which a study of many runs or a test may not want; metrics.json,
    # the map and the checkpoint are written either way
    plots: bool = True
    # CPU threads of torch and the numba kernels (None: the machine's cores; at most those). A run is
    # bit-identical for the same seed only at the same thread count (torch sums in another order)
    threads: int | None = None
    evaluation: EvaluationConfig = dc_field(default_factory=EvaluationConfig)

    def __post_init__(self) -> None:
        """The engine's checks, then the run's knobs."""
        super().__post_init__()
        import math
        import numbers

        check = Checks(self)
        integer, number, flag, bad = check.integer, check.number, check.flag, check.bad
        flag("online")
        flag("odometry_poses")
        flag("plots")
        number("playback_speed", 0.0)
        number("eval_interval", 0.0, lo_open=False)
        integer("log_every", 1)
        integer("threads", 1, 4096, optional=True)
        number("checkpoint_every", 0.0)
        integer("evaluation.n_rays", 1, 1_000_000)
        for name in ("height_band_m", "raster_res_m", "uss_arc_step_deg", "inlier_m"):
            number(f"evaluation.{name}", 0.0)
        number("evaluation.map_voxel_m", 0.0, lo_open=False)
        number("evaluation.lidar_angle_range_deg", 0.0, 360.0)
        ev = self.evaluation
        known = SENSOR_NAMES
        if not all(isinstance(s, str) and s in known for s in ev.sensors):
            raise bad("evaluation.sensors", list(ev.sensors), f"a subset of {list(known)}")
        names = [getattr(z, "name", None) for z in ev.zones]
        if "zone3" not in names or len(set(names)) != len(names):
            raise bad("evaluation.zones", names, "distinct zone names including 'zone3' (the whole-room zone "
                                                 "the training curve and the ablation report)")
        for i, z in enumerate(ev.zones):
            ok = all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in (z.lo, z.hi))
            if not (ok and 0.0 <= z.lo < z.hi):
                raise bad(f"evaluation.zones[{i}]", f"[{z.lo}, {z.hi}]", "0 <= lo < hi metres")


def check_device(cfg) -> None:
    """A config asking for CUDA where there is none is refused up front (not a torch traceback)."""
    from virus_nerf.errors import UsageError

    if not cfg.device.startswith("cuda"):
        return
    import torch

    if not torch.cuda.is_available():
        raise UsageError(f"device {cfg.device!r}: no CUDA GPU is available here; use 'auto' or 'cpu'")
    index = cfg.device.partition(":")[2]
    if index and (not index.isdigit() or int(index) >= torch.cuda.device_count()):
        raise UsageError(f"device {cfg.device!r}: expected cuda:<index> with index < {torch.cuda.device_count()}")
