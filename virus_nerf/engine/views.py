"""What a `Mapper` (engine/mapper.py) answers about its current map: NeRF 360 deg scans, the 2D
occupancy map, the VIRUS grid's probability map, and snapshots of them as map_server files.

A mixin so that the training engine and the queries read apart; it uses the mapper's `model`,
`field`, `grid`, `box`, `store`, `step`, `seconds` and `last_loss`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virus_nerf.errors import UsageError, require_int, require_number
from virus_nerf.grid.virus import VirusGrid
from virus_nerf.maps.evidence import stereo_sight_lines
from virus_nerf.maps.extract import (
    camera_height,
    check_raster,
    low_front_level,
    low_shadow_depth,
    occupancy_map,
    probability_map,
)
from virus_nerf.maps.observed import frames_observed, with_camera_pixels
from virus_nerf.maps.occupancy import MAP_POSES, MAP_RAYS, raster_shape
from virus_nerf.maps.planner import RangeEvidence
from virus_nerf.maps.scans import FieldOfView, Scan2D, points_from_ranges, scan_ranges


@dataclass(frozen=True)
class SnapshotInfo:
    """snapshot.json of a `Mapper.snapshot` folder."""

    frames: int
    steps: int
    seconds: float  # training clock
    last_frame_time: float | None  # s, recording time of the newest frame
    loss: float | None
    map_occupied: float  # share of the map's known pixels that are occupied
    map_known: float  # share of the map's pixels that are known (free or occupied)
    grid_occupied: float  # share of the occupancy grid's cells the marcher samples
    observed: float = 0.0  # share of the map's pixels some sensor looked at (maps/observed.py)

    FILE = "snapshot.json"

    @classmethod
    def read(cls, folder: Path) -> SnapshotInfo:
        """The snapshot.json of a snapshot folder: frames, steps and seconds; the map's figures and
        stamps as far as it holds them (null and 0 when not: a file of an older version)."""
        doc = json.loads((Path(folder) / cls.FILE).read_text())
        names = {f.name for f in dataclasses.fields(cls)}
        given = {k: v for k, v in doc.items() if k in names}
        return cls(**{"last_frame_time": None, "loss": None, "map_occupied": 0.0, "map_known": 0.0,
                      "grid_occupied": 0.0, **given})


def serialised(method):
    """One call into the mapper at a time: its methods may be called from several threads (a
    sensor callback adds frames while a timer trains and reads the map); a call waits for the one
    in progress (`Mapper.train` lets others in between its steps). Needs the mapper's `_calls`
    re-entrant lock."""

    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._calls:
            return method(self, *args, **kwargs)

    return call


class MapViews:
    """Queries of the current map (mixed into `Mapper`)."""

    _calls = contextlib.nullcontext()  # the Mapper's lock (`serialised`); none for a bare MapViews

    @serialised
    def scans(self, poses: np.ndarray, n_rays: int = 512) -> list:
        """NeRF 360 deg horizontal scans (maps.scans.Scan2D, world x, y in metres) from each
        pose's position: poses (N, 4, 4) camera-to-world, (4, 4), or positions (N, 3)."""
        positions = _positions(poses)
        require_int("Mapper.scans n_rays", n_rays, 1)
        out = []
        self.field.eval()
        try:
            for p in positions:
                _, dirs, r = scan_ranges(self.model, p, n_rays)
                out.append(Scan2D("NeRF", points_from_ranges(p[:2], dirs, r), p[:2], FieldOfView.full(p[:2])))
        finally:
            self.field.train()
        return out

    @serialised
    def map2d(self, resolution: float = 0.05, n_rays: int = MAP_RAYS, max_poses: int = MAP_POSES):
        """The current 2D occupancy map (maps.occupancy.OccupancyMap2D, trinary, over the box's
        x, y; `resolution` in metres per pixel, `n_rays` per 360 deg scan): NeRF scans from up to
        `max_poses` camera positions of the frames added so far (evenly spread), cells a scan passed free, end cells occupied, the rest unknown; and
        unknown wherever no sensor looked (`observed`), whatever the NeRF says there; then
        occupied where the frames' IRS hits and unexplained USS echoes lie (maps/planner.py). The same
        extraction as `virus-nerf export` (maps/extract.py). A query: the map `update_map` made
        last (a copy) while the mapper has not changed since (no step, frame, box or stereo
        targets) and the settings are the same; otherwise `update_map` first."""
        key = self._map_key(resolution, n_rays, max_poses)
        cached = getattr(self, "_map_cache", None)
        if cached is None or cached[0] != key:
            return self.update_map(resolution, n_rays, max_poses)
        return dataclasses.replace(cached[1], image=cached[1].image.copy())

    @serialised
    def update_map(self, resolution: float = 0.05, n_rays: int = MAP_RAYS, max_poses: int = MAP_POSES):
        """Render the 2D map (`map2d`) from the current state now, and keep it for the queries
        that follow (a snapshot, the live view, the safety figure)."""
        key = self._map_key(resolution, n_rays, max_poses)
        lo, hi = self._raster_box("Mapper.map2d resolution", resolution)
        self.field.eval()
        try:
            m = occupancy_map(self.model, self.store.cam_to_world[:, :3, 3], lo, hi, resolution, int(n_rays),
                              int(max_poses), self.observed(resolution), self.range_evidence(),
                              low_front_level(self.step),  # D / A while the field is haze (D94)
                              self.store.stack_ids, self.store.times,
                              low_shadow_depth(self.box.lo, self.box.hi, self.extent.growing),  # D111
                              scan=self.step > 0)  # an untrained field's haze is no wall
        finally:
            self.field.train()
        self._map_cache = (key, dataclasses.replace(m, image=m.image.copy()))
        return m

    def _map_key(self, resolution, n_rays, max_poses) -> tuple:
        """The settings (n_rays and max_poses checked; a resolution no cached map has goes to
        `update_map`, which checks it) and what the map depends on: the training state (step and
        clock: a loaded state changes both), the frames, the box (and with it the shadow's depth,
        maps.extract.low_shadow_depth) and the stereo targets."""
        require_int("Mapper.map2d n_rays", n_rays, 1)
        require_int("Mapper.map2d max_poses", max_poses, 1)
        stereo = getattr(self, "stereo", None)
        return (self.step, self.seconds, self.frames, self.box, resolution, int(n_rays), int(max_poses),
                id(stereo), None if stereo is None else (len(stereo.points), len(stereo)))

    @serialised
    def range_evidence(self) -> RangeEvidence:
        """What the frames' IRS, USS and stereo measured at camera height (maps/planner.py), for
        the sensors the mapper trains with. Kept while the frames (the store only grows), the
        height, the stereo targets and the sensors are the same: offline every map after the first
        reuses it (the IRS rays of every frame cost a tenth of a snapshot)."""
        st = self.store
        stereo = getattr(self, "stereo", None)
        height = self.camera_height()
        sensors = tuple(self.config.sensors)
        key = (self.frames, float(height), sensors, None if stereo is None else (len(stereo.points), len(stereo)))
        cached = getattr(self, "_evidence_cache", None)
        if cached is not None and cached[1] == key and (cached[0]() if cached[0] is not None else None) is stereo:
            return cached[2]
        sight = None
        if stereo is not None and "stereo" in sensors:
            sight = self._sight_lines(stereo, height)
        evidence = RangeEvidence.of_frames(st.cam_to_world, st.uss_range, st.irs_range, height, sensors,
                                           stereo_points=None if stereo is None else stereo.points,
                                           sight_lines=sight)
        self._evidence_cache = (None if stereo is None else weakref.ref(stereo), key, evidence)
        return evidence

    def _sight_lines(self, stereo, height: float):
        """The stereo views' sight lines at `height` (maps.evidence.stereo_sight_lines), kept while
        the stereo targets, the height and the frames they see are the same: offline they never
        change, and while driving they change only when the tracker hands over new targets."""
        st = self.store
        seen = min(len(st.cam_to_world), int(stereo.frames.max()) + 1) if len(stereo) else 0  # rows the views see
        key = (len(stereo), float(height), seen)
        cached = getattr(self, "_sight_cache", None)
        if cached is None or cached[0]() is not stereo or cached[1] != key:  # weak: the old targets may go
            lines = stereo_sight_lines(stereo, st.cam_to_world, st.stack_ids, st.intrinsics, height)
            cached = (weakref.ref(stereo), key, lines)
            self._sight_cache = cached
        return cached[2]

    def _raster_box(self, what: str, resolution) -> tuple[np.ndarray, np.ndarray]:
        """The box's (x, y) corners, once `resolution` is checked (maps.extract.check_raster)."""
        lo, hi = np.asarray(self.box.lo[:2]), np.asarray(self.box.hi[:2])
        check_raster(what, lo, hi, resolution)
        return lo, hi

    @serialised
    def observed(self, resolution: float = 0.05) -> np.ndarray:
        """(nx, ny) bool [ix, iy] over the box's x, y raster: pixels inside some frame's camera
        view wedge or holding a camera (maps/observed.py); outside it every map is unknown."""
        key = (self.frames, float(resolution), self.box)  # a grown box is another raster
        if getattr(self, "_observed_cache", (None,))[0] != key:
            lo, hi = np.asarray(self.box.lo[:2]), np.asarray(self.box.hi[:2])
            seen = frames_observed(self.store.cam_to_world, self.store.stack_ids, self.intrinsics, lo,
                                   raster_shape(lo, hi, resolution), resolution)
            self._observed_cache = (key, with_camera_pixels(seen, self.store.cam_to_world[:, :2, 3], lo, resolution))
        return self._observed_cache[1]

    @serialised
    def grid_observed(self) -> np.ndarray:
        """(rx, ry) bool [ix, iy]: the occupancy grid's columns inside some frame's camera view
        wedge or holding a camera (maps/observed.py at the grid's cell size), as `observed` is for
        the 2D maps; elsewhere the grid holds its warm-up and prior, not evidence."""
        spec = self.grid.spec
        return with_camera_pixels(self._viewed_columns(0, self.frames), self.store.cam_to_world[:self.frames, :2, 3],
                                  np.asarray(spec.box.lo[:2]), np.asarray(spec.cell_size[:2], dtype=np.float64))

    @serialised
    def probability_map(self, resolution: float = 0.05, band: float = 0.1):
        """The VIRUS grid's occupancy probability at camera height (an OccupancyMap2D of `mode: raw`:
        round(100 p), 255 where no sensor looked; maps.extract.probability_map); None for the
        Instant-NGP grid."""
        lo, hi = self._raster_box("Mapper.probability_map resolution", resolution)
        require_number("Mapper.probability_map band", band, 0.0, 10.0, lo_open=False)  # as export --band
        if not isinstance(self.grid, VirusGrid):
            return None
        return probability_map(self.grid.probability.numpy(), self.box.lo, self.box.hi, self.camera_height(), band,
                               lo, hi, resolution, self.observed(resolution))

    def camera_height(self) -> float:
        """Median height (m) of the main stack's cameras (all stacks' without it) so far."""
        return camera_height(self.store.cam_to_world, self.store.stack_ids, default=float(self.box.center[2]))

    @serialised
    def snapshot(self, folder: Path, resolution: float = 0.05, n_rays: int = MAP_RAYS, max_poses: int = MAP_POSES,
                 with_state: bool = False, replace: bool = False, maps: tuple | None = None) -> SnapshotInfo:
        """Write the current map into the new folder `folder` (refused if it exists; built under a
        temporary name and renamed): map.pgm/.yaml/.png (map2d), prob.pgm/.yaml/.png (VIRUS grid),
        snapshot.json and, with `with_state`, mapper.pt (`state()`). `replace`: an existing folder
        is replaced once the new one is complete (a resumed run's own map). `maps`: (map2d,
        probability_map) already computed at these settings for this state (not recomputed)."""
        from virus_nerf.maps.observed import observed_share
        from virus_nerf.maps.occupancy import FREE, OCCUPIED, preview, write_map_server, write_png
        from virus_nerf.utils.io import new_output_dir, write_json_atomic

        folder = Path(folder)
        for given in maps or ():
            if given is not None and abs(given.resolution - float(resolution)) > 1e-9:
                raise UsageError(f"Mapper.snapshot maps: computed at resolution {given.resolution:g} m; expected the "
                                 f"snapshot's resolution {float(resolution):g} m (or leave maps out)")
        with new_output_dir(folder, replace=replace, flag="snapshot folder") as tmp:
            m, prob = maps if maps is not None else (self.map2d(resolution, n_rays, max_poses),
                                                     self.probability_map(resolution))
            write_map_server(m, tmp, "map")
            write_png(tmp / "map.png", m.image)
            if prob is not None:
                write_map_server(prob, tmp, "prob")
                write_png(tmp / "prob.png", preview(prob))
            occupied, known = int((m.image == OCCUPIED).sum()), int(np.isin(m.image, (OCCUPIED, FREE)).sum())
            info = SnapshotInfo(
                frames=self.frames, steps=self.step, seconds=round(self.seconds, 3),
                # the newest frame's own stamp (the store's times run on past a `restart_clock`)
                last_frame_time=self.newest_stamp if self.frames else None,
                loss=self.last_loss,
                map_occupied=occupied / known if known else 0.0, map_known=known / m.image.size,
                grid_occupied=round(self.grid.occupancy_share(), 4),
                observed=round(observed_share(self.observed(resolution)), 4),
            )
            write_json_atomic(tmp / SnapshotInfo.FILE, dataclasses.asdict(info))
            if with_state:
                torch.save(self.state(), tmp / "mapper.pt")
        return info


def _positions(poses) -> np.ndarray:
    """(N, 4, 4) or (4, 4) poses, or (N, 3) positions -> (N, 3) float64 positions."""
    p = np.asarray(poses, dtype=np.float64)
    if p.shape == (4, 4):
        p = p[None]
    if p.ndim == 3 and p.shape[1:] == (4, 4):
        p = p[:, :3, 3]
    if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
        raise UsageError(f"Mapper.scans poses of shape {np.shape(poses)}: expected finite (N, 4, 4) camera-to-world "
                         "poses or (N, 3) positions in metres")
    return p

