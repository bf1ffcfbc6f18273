"""Why a run's map may not be trusted: one line each, printed and kept in metrics.json (issue 30).

A run can finish without an error and still give a map that means little: a sensor it was told
to train on never answered, the grid never left its warm-up (every cell still occupied), it saw a
handful of frames, or its LiDAR row is scored against a map made from those same scans. None of
these is an error (a user may want exactly that run); each is said once, in words.
"""

from __future__ import annotations

import numpy as np

from virus_nerf.evaluation.evaluate import LIDAR_OWN_MAP, lidar_scored_against_own_map
from virus_nerf.evaluation.testpoints import recording_warnings

MIN_TRAINING_FRAMES = 10  # fewer training frames than this: the map rests on a few views


def map_warnings(trainer) -> list[str]:
    """The warnings of a trained run (trainer.loop.Trainer after `fit`)."""
    cfg, mapper = trainer.config, trainer.mapper
    store = mapper.store
    out: list[str] = []
    if len(store) < MIN_TRAINING_FRAMES:
        out.append(f"only {len(store)} training frame(s) (fewer than {MIN_TRAINING_FRAMES}): the map rests on "
                   "very few views")
    silent = []
    if "uss" in cfg.sensors and len(store) and not np.isfinite(store.uss_range).any():
        silent.append("uss (no echo in any training frame)")
    if "irs" in cfg.sensors and len(store) and not np.isfinite(store.irs_range).any():
        silent.append("irs (no valid zone in any training frame)")
    if "stereo" in cfg.sensors and (mapper.stereo is None or len(mapper.stereo.ranges) == 0):
        silent.append("stereo (no triangulated point)")
    if silent:
        out.append(f"configured sensor(s) silent in the recording: {'; '.join(silent)}; their losses were zero")
    if mapper.skipped_steps:
        out.append(f"{mapper.skipped_steps} training step(s) had a loss that was not finite and changed nothing")
    done = getattr(mapper.grid, "warmup_done", None)
    if done is not None and not done:
        out.append(f"the run ended inside the occupancy grid's warm-up (step {mapper.step}, "
                   f"{mapper.grid.occupancy_share():.0%} of cells still occupied): the grid has not yet "
                   "separated free from occupied space; train longer")
    if lidar_scored_against_own_map(trainer.recording):
        out.append(LIDAR_OWN_MAP)
    return out + recording_warnings(trainer.recording, scored=bool(cfg.evaluation.gt))
