"""The map's extent as an object the `Mapper` holds (grid/extent.py has the rules, docs/extent.md).

`MapExtent` answers what the Mapper needs to know about its bounds, fitted or growing alike: the
box (the grid's and the map's), the field's fixed frame, whether a camera may be where a frame
puts it, and, as frames and stereo points arrive, the box grown to hold them. Its state is the
box (`Mapper.state()["box"]`); the sensed support is rebuilt from the frames added again on resume.
"""

from __future__ import annotations

import numpy as np

from virus_nerf.errors import UsageError
from virus_nerf.grid.base import GridSpec
from virus_nerf.grid.extent import (
    ExtentConfig,
    SensedSupport,
    camera_margin_m,
    field_config_for_frame,
    field_frame,
    fitted_field_frame,
    grows_from_sensors,
    growth_step_m,
    holding_box,
    inside_frame,
    needed_box,
)
from virus_nerf.sampler.frames import FrameStore
from virus_nerf.sampler.sensor_rays import irs_zone_rays
from virus_nerf.scene_box import SceneBox

# a fitted box's camera may stand this far (m) outside it (the box of a floor plan drawn to the
# walls, a camera on the threshold); farther is a pose in another frame or unit
FITTED_SLACK_M = 1.0


class MapExtent:
    """A mapper's bounds: `fitted` (the given box for the mapper's life) or `grow` (the box
    around the first frame, grown by whole grid cells to hold what the robot sensed, inside a
    fixed frame cube the field is normalised to; grid/extent.py)."""

    def __init__(self, config: ExtentConfig, sensors, box: SceneBox):
        self.config = config
        self.sensors = tuple(sensors)
        self.growing = config.mode == "grow"
        self.box = box
        self.frame = field_frame(box, config) if self.growing else fitted_field_frame(box, config)  # the field's fixed frame
        # grow, sensed: the points the depth sensors measured, counted per support cell
        self.support = SensedSupport(config, self.frame, (box.lo[2], box.hi[2])) \
            if self.growing and grows_from_sensors(config, self.sensors) else None
        self._stereo_counted = 0  # stereo points already counted in the support

    def field_config(self, field):
        """The field's config for this extent: growing, its resolutions set in metres of the frame."""
        return field_config_for_frame(field, self.config) if self.growing else field

    def grid_spec(self) -> GridSpec | None:
        """Growing: the grid over the box with cells of `grid_cell_m`; fitted: None (the grid's
        own max_resolution over the box)."""
        return GridSpec.from_cell(self.box, self.config.grid_cell_m) if self.growing else None

    def check_inside(self, positions: np.ndarray, times: np.ndarray) -> None:
        """A camera position (K, 3) outside the frame cube (growing) or more than FITTED_SLACK_M
        outside the box (fitted: a pose in millimetres or another frame) is a one-line UsageError
        naming the frame's time."""
        if not self.growing:
            for i in np.flatnonzero(~self.box.padded(FITTED_SLACK_M).contains(positions))[:1]:
                p, lo, hi = positions[i], np.round(self.box.lo, 2).tolist(), np.round(self.box.hi, 2).tolist()
                raise UsageError(
                    f"frame at time {float(times[i]):.3f} s (its pose, SyncFrame.cam_to_world): camera at "
                    f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) m lies outside the Mapper's box {lo}..{hi} m (extent.mode "
                    "fitted); expected a pose in metres (one in millimetres lands far outside), in the box's frame "
                    "(extent.mode grow maps a drive of any size)")
            return
        for p, t in zip(positions, times, strict=True):
            if not inside_frame(p, self.frame):
                raise UsageError(
                    f"frame at time {float(t):.3f} s (its pose, SyncFrame.cam_to_world): camera at ({p[0]:.2f}, "
                    f"{p[1]:.2f}, {p[2]:.2f}) m lies outside the map's frame {self.frame.lo}..{self.frame.hi} "
                    f"(extent.frame_m {self.config.frame_m:g} m around the first frame); expected a drive within it "
                    "(a larger extent.frame_m maps a larger area) and poses in metres (one in millimetres lands far "
                    "outside)")

    def add_frames(self, store: FrameStore, rows: np.ndarray) -> SceneBox | None:
        """Growing: the box that holds the camera positions of `store`'s `rows` plus the camera
        margin and, with sensed growth, their IRS returns (counted in the support first); None
        when the box stays."""
        if not self.growing or not len(rows):
            return None
        if self.support is not None and "irs" in self.sensors:
            rays = irs_zone_rays(store, rows, 1).valid()
            if len(rays):
                self.support.add((rays.origins + rays.directions * rays.ranges[:, None]).double().numpy())
        return self._grow_to(store.cam_to_world[rows, :3, 3])

    def add_stereo(self, points: np.ndarray) -> SceneBox | None:
        """Sensed growth: the box that holds the new triangulated points (N, 3) of a stereo set
        (the same set extended, or a new one counted whole); None when the box stays."""
        if self.support is None:
            return None
        points = np.asarray(points)
        if len(points) < self._stereo_counted:  # a new set, not the old one extended: count it all
            self._stereo_counted = 0
        grown = self._grow_to(np.zeros((0, 3))) if self.support.add(points[self._stereo_counted:]) else None
        self._stereo_counted = len(points)
        return grown

    def restore(self, saved: SceneBox) -> SceneBox | None:
        """Growing: a checkpoint's box when it had grown beyond this one; None otherwise."""
        if not self.growing or (np.allclose(saved.lo, self.box.lo) and np.allclose(saved.hi, self.box.hi)):
            return None
        self.box = saved
        return saved

    def _grow_to(self, positions: np.ndarray) -> SceneBox | None:
        """The box grown to hold camera positions (K, 3) + the camera margin and the supported
        sensed points + margin_m; None when it already does."""
        ext = self.config
        box = self.box
        margin = camera_margin_m(ext, self.sensors)
        step = growth_step_m(ext, self.sensors)
        if len(positions):
            for corner in (positions.min(axis=0), positions.max(axis=0)):
                box = needed_box(box, corner, ext, self.frame, margin, step) or box
        if self.support is not None and (sensed := self.support.bounds()) is not None:
            box = holding_box(box, sensed[0] - ext.margin_m, sensed[1] + ext.margin_m, ext, self.frame, step) or box
        if box is self.box:
            return None
        self.box = box
        return box
