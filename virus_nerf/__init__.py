"""VIRUS-NeRF: Vision, InfraRed and UltraSonic based Neural Radiance Fields.

Data flow (docs/method.md 2): data -> sensors -> stereo -> sampler -> grid -> render (marching,
compositing) -> field -> losses -> maps -> engine (the Mapper) -> trainer (the run) -> evaluation
-> exports, mapping -> experiments -> cli.
"""

__version__ = "0.1.0"

# No OpenMP settings on import: the runtime's default (spin briefly, then sleep) trains 1.4x faster
# than OMP_WAIT_POLICY=PASSIVE when the run has the cores to itself; runs that share the CPU
# (experiments with several workers) get PASSIVE from their launcher (docs/method.md 10).

# The public API, for a robot program (README, "On a robot"): loaded on first use, so that
# `import virus_nerf` (and the command line's error path) does not pull in torch.
_PUBLIC = {
    "Mapper": "virus_nerf.engine.mapper",
    "warm_up": "virus_nerf.engine.mapper",
    "TrainSlice": "virus_nerf.engine.mapper",
    "MapperConfig": "virus_nerf.engine.config",
    "StepSchedule": "virus_nerf.engine.schedule",
    "Schedules": "virus_nerf.engine.schedule",
    "Horizon": "virus_nerf.engine.schedule",
    "TrainConfig": "virus_nerf.trainer.config",
    "SyncFrame": "virus_nerf.data.frame",
    "Intrinsics": "virus_nerf.sensors.camera",
    "SceneBox": "virus_nerf.scene_box",
    "StereoConfig": "virus_nerf.stereo.depth",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'virus_nerf' has no attribute {name!r}")
