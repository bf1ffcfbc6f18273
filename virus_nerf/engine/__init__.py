"""The method's own room (docs/architecture.md): the robot's mapping engine, with no run folder,
command line or evaluation.

config: `MapperConfig`, every knob the engine reads
mapper: `Mapper`, frames in, training steps, map queries out (its public API)
adam: `Adam`, torch's Adam update and state_dict without torch's optimiser class (no torch._dynamo)
clock: `FrameClock`, the frames' stamps made one forward time per stack across clock restarts
checkpoint: the Mapper's `state()` / `load_state` (mixed into `Mapper`)
step_loss: a step's loss as pure functions of the config, the batch and the render
extent: `MapExtent`, the map's bounds the Mapper holds (fitted, or grown as frames arrive)
model: `SceneModel` (field + occupancy grid + marcher), the grid and device it runs on
schedule: how long and how wide a step is, offline or while driving, and the learning-rate
  horizon (`Schedules`, handed to the Mapper by its caller)
views: the map queries mixed into `Mapper` (scans, 2D maps, snapshots)
state: what a `Mapper.state()` must hold, checked before `load_state` touches the mapper
memory: what a training step needs, checked before any work (`check_batch_memory`)
"""

# its public modules; none is imported here, so `import virus_nerf.engine` loads nothing else
__all__ = ["adam", "checkpoint", "clock", "config", "extent", "mapper", "memory", "model", "schedule", "state",
           "step_loss", "views"]
