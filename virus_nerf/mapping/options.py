"""The flags `map-bag` and `ros2` share, declared once as typed groups with one set of checks.

Each group is a frozen dataclass that a command takes as one parameter flattened into its flags
(`Annotated[MapRaster, tyro.conf.arg(name="")]`: `--resolution`, not `--maps.resolution`); a
field's comment is its help. `check()` refuses a bad value in one line naming the flag, before
anything is read or made; the commands hand the groups on as they are.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from virus_nerf.errors import OutputExistsError, UsageError, require_int, require_number
from virus_nerf.maps.occupancy import MAP_POSES, MAP_RAYS


@dataclass(frozen=True)
class MapRaster:
    """The maps of every snapshot and the final map."""

    resolution: float = 0.05  # Metres per map pixel.
    n_rays: int = MAP_RAYS  # Rays per 360 deg scan of the maps.
    max_poses: int = MAP_POSES  # Camera positions scanned for each map (evenly over the frames so far).

    def check(self) -> None:
        require_number("--resolution", self.resolution, 0.0)
        require_int("--n-rays", self.n_rays, 1, 1_000_000)
        require_int("--max-poses", self.max_poses, 1)

    def kwargs(self) -> dict:
        """resolution, n_rays, max_poses as keyword arguments (Mapper.snapshot, StreamRun, replay)."""
        return dataclasses.asdict(self)


DEFAULT_RASTER = MapRaster()  # the commands' defaults (frozen: shared safely)


@dataclass(frozen=True)
class RerunSinks:
    """The live view in Rerun (the live extra; docs/live-view.md)."""

    rerun: bool = False  # Spawn a Rerun viewer and watch the mapping live.
    # Send the live view to a running Rerun viewer at this URL instead (e.g. rerun+http://192.168.1.7:9876/proxy).
    rerun_connect: str | None = None
    rerun_save: Path | None = None  # Record the live view into this new .rrd file (play it later with `rerun FILE`).

    @property
    def wanted(self) -> bool:
        return bool(self.rerun or self.rerun_connect or self.rerun_save)

    def check(self) -> None:
        """A .rrd name that does not exist yet in a folder that does, a viewer URL rerun takes,
        and the live extra installed (their one-line messages now, not after the start-up)."""
        if self.rerun_save is not None:
            save = Path(self.rerun_save)
            if save.suffix != ".rrd":
                raise UsageError(f"--rerun-save {save}: expected a .rrd file name")
            if save.exists():
                raise OutputExistsError(save, "--rerun-save")
            if not save.absolute().parent.is_dir():
                raise UsageError(f"--rerun-save {save}: no folder {save.absolute().parent}; expected a .rrd file "
                                 "in an existing folder")
        if self.rerun:
            from virus_nerf.mapping.live_view import no_display_problem

            if (problem := no_display_problem()) is not None:
                raise UsageError(problem)
        if self.wanted:
            from virus_nerf.mapping.live_view import _rerun

            given = "--rerun" if self.rerun else ("--rerun-connect" if self.rerun_connect else "--rerun-save")
            rr = _rerun(given)
            if self.rerun_connect:
                from virus_nerf.errors import one_line

                try:
                    rr.GrpcSink(self.rerun_connect)  # parses the URL, connects nothing
                except RuntimeError as exc:
                    raise UsageError(f"--rerun-connect {self.rerun_connect}: {one_line(exc, 200)}; expected e.g. "
                                     "rerun+http://127.0.0.1:9876/proxy") from None


NO_VIEW = RerunSinks()


def load_stream_config(config: Path | None):
    """The --config of a stream (a TrainConfig; None: the defaults), checked as `train` checks
    it: the file's keys and values, and that a step's samples fit in memory."""
    if config is None:
        return None
    from virus_nerf.engine.memory import check_batch_memory
    from virus_nerf.trainer.run_folder import load_config_file

    cfg = load_config_file(config)
    check_batch_memory(cfg, what=f"--config {config}: batch_size")
    return cfg
