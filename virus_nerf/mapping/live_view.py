"""A live view of the mapper in Rerun (issue 29, item 4): what the robot senses and the map it makes.

`LiveView` sends to a viewer it spawns (spawn=True), to a running viewer (connect=URL, e.g.
"rerun+http://192.168.1.7:9876/proxy") and/or into a recording file (save=PATH.rrd, played later
with `rerun PATH.rrd`). Rerun is imported only here, from the `live` extra.

One timeline, "drive_time": the frames' recording time minus `start_time`, in seconds.

Entity paths (world: metres, right-handed, z up; S = the sensor stack id):

- world/robot                    Transform3D, base_link in ROS body axes (x forward, y left,
                                 z up; mapping.ros_maps.base_pose, the /tf of the MCAP) + axes
- world/trajectory               LineStrips3D, the robot's positions so far (one every
                                 `trajectory_step` metres)
- world/camera_S                 Transform3D, the camera pose (OpenCV axes: x right, y down, z forward)
- world/camera_S/image           Pinhole + the RGB image (downscaled by `image_scale`, JPEG)
- world/camera_S/irs             Points3D, the IRS zones' end points (8x8 zones, 45x45 deg,
                                 coloured by range, red = near); only valid zones
- world/camera_S/irs/rays        LineStrips3D, a ray from the sensor to each valid zone's end point
- world/camera_S/uss             LineStrips3D, the USS cone (55x35 deg) at its echo range: the
                                 ellipse and four edges, labelled with the range; empty: no echo
- world/scan                     Points3D, the NeRF's 360 deg 2D scan at the camera's height
- map/trinary                    Image, the 2D occupancy map (maps.occupancy raster: row 0 = largest y;
                                 0 occupied, 254 free, 205 unknown)
- map/probability                Image, the VIRUS grid's probability map (255 (1 - p), mid grey unknown)
- map/scan                       Points2D, the same scan in the map images' pixel coordinates
- map/robot                      Points2D, the robot in the map images' pixel coordinates
- ranges/uss_S, ranges/irs_min_S Scalars, the USS range and the nearest valid IRS zone (m)

The USS and IRS share their stack camera's origin and axes (sensors/rig.py), so they are
children of world/camera_S and drawn from the camera's mount.

The recording carries a default layout (`layout`): the map and the probability map with the
scan and the robot on them, the 3D world, each camera's image, and the ranges over time; the
time panel follows the newest data, so a viewer shows the map as it is now, and a saved .rrd
opens at its end.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from virus_nerf.data.frame import SyncFrame
from virus_nerf.errors import OutputExistsError, UsageError, install_extra, one_line
from virus_nerf.mapping.ros_maps import RobotStacks, base_pose
from virus_nerf.maps.occupancy import MAP_POSES, MAP_RAYS, OccupancyMap2D, preview
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.irs import IRS_MAX_RANGE_M, zone_directions
from virus_nerf.sensors.uss import USS_FOV_H_DEG, USS_FOV_V_DEG

TIMELINE = "drive_time"
DEFAULT_PORT = 9876


def layout(stacks: list[int]):
    """The viewer's default layout (a Rerun blueprint) for these sensor stacks: maps on the
    left, the 3D world and the cameras on the right, the ranges below; the time panel follows
    the newest frame on the drive_time timeline."""
    import rerun.blueprint as rrb

    maps = [rrb.Spatial2DView(origin="map", name=name, contents=[f"map/{image}", "map/scan", "map/robot"])
            for name, image in (("map", "trinary"), ("probability", "probability"))]
    cameras = [rrb.Spatial2DView(origin=f"world/camera_{s}/image", name=f"camera {s}") for s in stacks]
    right = [rrb.Spatial3DView(origin="world", name="world")]
    if cameras:
        right.append(rrb.Horizontal(*cameras))
    right.append(rrb.TimeSeriesView(origin="ranges", name="ranges (m)"))
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(*maps), rrb.Vertical(*right, row_shares=[3, 2, 2][:len(right)]),
                       column_shares=[2, 3]),
        rrb.TimePanel(timeline=TIMELINE, play_state="following"),
        collapse_panels=True,
    )


def _rerun(flag: str = "--rerun"):
    """The rerun module, or a one-line UsageError naming the flag given and the extra that brings it."""
    try:
        import rerun
    except ImportError:
        raise UsageError(f"{flag} needs the live extra: {install_extra('live')}") from None
    return rerun


def _viewer_executable() -> str | None:
    """The `rerun` viewer installed beside this Python (a venv's bin/, on PATH or not: the README
    runs `.venv/bin/virus-nerf` without activating the venv); None: rerun looks on PATH."""
    beside = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    return str(beside) if beside.is_file() else None


def no_display_problem(environ=None, platform: str = sys.platform) -> str | None:
    """Why a viewer window cannot open here (Linux without DISPLAY or WAYLAND_DISPLAY: a robot's
    computer over ssh), else None. Rerun's spawn says nothing then: the viewer dies, the view's
    messages wait for a port that never opens, and the drive maps without a viewer."""
    env = os.environ if environ is None else environ
    if platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        return ("--rerun: no display for the Rerun viewer (neither DISPLAY nor WAYLAND_DISPLAY is set); on a "
                "computer without a screen, send the view to a viewer elsewhere with --rerun-connect "
                "rerun+http://HOST:9876/proxy, or save it with --rerun-save FILE.rrd")
    return None


def uss_cone_lines(range_m: float, n: int = 32) -> list[np.ndarray]:
    """Camera-frame polylines of the USS cone at radial range `range_m`: the ellipse (n + 1, 3)
    closed, then four edges (2, 3) from the sensor to the ellipse's ends (wide axis = camera x)."""
    a, b = np.deg2rad(USS_FOV_H_DEG / 2), np.deg2rad(USS_FOV_V_DEG / 2)
    theta = np.linspace(0.0, 2 * np.pi, n + 1)
    ax, ay = a * np.cos(theta), b * np.sin(theta)  # angles about camera y and x, as uss.in_cone
    d = np.stack([np.tan(ax), np.tan(ay), np.ones_like(ax)], axis=-1)
    ring = range_m * d / np.linalg.norm(d, axis=-1, keepdims=True)  # (n + 1, 3), radial range
    ends = ring[[0, n // 4, n // 2, 3 * n // 4]]
    return [ring] + [np.stack([np.zeros(3), e]) for e in ends]


def irs_points(irs_range: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame end points (M, 3) of the valid IRS zones and their z-depths (M,) in metres.
    The ranges are z-depths, so a zone centre's unit direction d ends at d * z / d_z."""
    z = np.asarray(irs_range, dtype=np.float64).reshape(8, 8)
    d = zone_directions(1)[:, :, 0, :]  # (8, 8, 3), [image zone row, column] like irs_range
    ok = np.isfinite(z) & (z > 0)
    return d[ok] * (z[ok] / d[ok][:, 2])[:, None], z[ok]


def range_colors(r: np.ndarray, far: float = IRS_MAX_RANGE_M) -> np.ndarray:
    """(M, 3) uint8 colours: red at 0 m through yellow to green at `far` metres."""
    t = np.clip(np.asarray(r, dtype=np.float64) / far, 0.0, 1.0)
    return np.stack([255 * np.minimum(1, 2 - 2 * t), 255 * np.minimum(1, 2 * t), np.zeros_like(t)],
                    axis=-1).astype(np.uint8)


def map_pixels(xy: np.ndarray, m: OccupancyMap2D) -> np.ndarray:
    """World (N, 2) x, y in metres -> (N, 2) continuous pixel coordinates (u right, v down, the
    image's top-left corner at 0, 0) of map `m`'s raster (maps.occupancy: row 0 = largest y)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    h = np.shape(m.image)[0]
    u = (xy[:, 0] - m.origin[0]) / m.resolution
    v = h - (xy[:, 1] - m.origin[1]) / m.resolution
    return np.stack([u, v], axis=-1)


class LiveView:
    """Logs frames and maps to Rerun (module docstring: sinks, timeline, entity paths).

    spawn: start a viewer on this machine (port `port`); connect: the gRPC URL of a running
    viewer; save: a new .rrd file; any combination, at least one. start_time: the recording time
    (s) that is drive_time 0. image_scale: the camera images' downscale before sending
    (bandwidth); jpeg_quality: their JPEG quality (None: raw pixels). camera_in_base: stack id ->
    (4, 4) camera-to-base_link mount; without one, the robot is the levelled camera of the first
    stack seen (so that two cameras looking apart do not make the robot jitter).
    """

    def __init__(self, *, spawn: bool = False, connect: str | None = None, save: str | Path | None = None,
                 start_time: float = 0.0, image_scale: float = 0.5, jpeg_quality: int | None = 75,
                 camera_in_base: Mapping[int, np.ndarray] | None = None, trajectory_step: float = 0.05,
                 application_id: str = "virus_nerf", port: int = DEFAULT_PORT) -> None:
        if not (spawn or connect or save):
            raise UsageError("LiveView: no sink; expected spawn=True, connect=URL and/or save=PATH.rrd")
        if not 0 < image_scale <= 1:
            raise UsageError(f"LiveView image_scale {image_scale!r}: expected a number in (0, 1]")
        if save is not None:
            save = Path(save)
            if save.suffix != ".rrd":
                raise UsageError(f"LiveView save {save}: expected a .rrd file name")
            if save.exists():
                raise OutputExistsError(save, "save path")
        rr = self.rr = _rerun()
        self.start_time, self.image_scale, self.jpeg_quality = float(start_time), image_scale, jpeg_quality
        self.camera_in_base = {int(k): np.asarray(v, dtype=np.float64) for k, v in (camera_in_base or {}).items()}
        self.trajectory_step = trajectory_step
        self.rec = rr.RecordingStream(application_id)
        urls = []
        if spawn:
            if (problem := no_display_problem()) is not None:
                raise UsageError(problem)
            try:
                rr.spawn(port=port, connect=False, executable_path=_viewer_executable(), recording=self.rec)
            except (RuntimeError, OSError) as exc:  # no viewer executable, or one that does not start
                raise UsageError(f"--rerun: cannot start the Rerun viewer ({one_line(exc, 200)}); install the live "
                                 "extra, or save the view with --rerun-save FILE.rrd and open it with `rerun "
                                 "FILE.rrd`") from None
            urls.append(f"rerun+http://127.0.0.1:{port}/proxy")
        if connect and connect not in urls:
            urls.append(connect)
        try:
            sinks = [rr.GrpcSink(u) for u in urls] + ([rr.FileSink(str(save))] if save is not None else [])
            self.rec.set_sinks(*sinks)
        except RuntimeError as exc:  # a URL rerun does not take, a .rrd it cannot create
            raise UsageError(f"LiveView sinks {urls + ([str(save)] if save is not None else [])}: "
                             f"{one_line(exc, 200)}") from None
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.send_blueprint(layout([]))
        self._pinholes: set[int] = set()
        self.robot_stacks = RobotStacks(self.camera_in_base)
        self._trajectory: list[np.ndarray] = []  # (3,) robot positions, metres
        self._robot_xyz: np.ndarray | None = None
        self._camera_z: float | None = None
        self._closed = False
        self.flush_timeout_s = 10.0  # at close: how long the sinks may take the last data

    # ------------------------------------------------------------------ frames
    def _set_time(self, time_s: float) -> None:
        if self._closed:
            raise UsageError("LiveView: already closed")
        self.rec.set_time(TIMELINE, duration=float(time_s) - self.start_time)

    def _log_robot(self, pose: np.ndarray) -> None:
        rr = self.rr
        self.rec.log("world/robot", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]),
                     rr.TransformAxes3D(0.3))
        p = pose[:3, 3].copy()
        self._robot_xyz = p
        if not self._trajectory or np.linalg.norm(p - self._trajectory[-1]) >= self.trajectory_step:
            self._trajectory.append(p)
            self.rec.log("world/trajectory", rr.LineStrips3D([np.asarray(self._trajectory)], radii=0.01,
                                                             colors=[[40, 120, 255]]))

    def _log_camera(self, cam: str, frame: SyncFrame, intr: Intrinsics) -> None:
        """Camera pose, pinhole (once per stack, static) and the downscaled image."""
        rr = self.rr
        pose = np.asarray(frame.cam_to_world, dtype=np.float64)
        self.rec.log(cam, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        small = intr.scaled(self.image_scale) if self.image_scale != 1 else intr
        if frame.stack_id not in self._pinholes:
            self._pinholes.add(frame.stack_id)
            self.rec.send_blueprint(layout(sorted(self._pinholes)))  # a view for the new camera
            self.rec.log(f"{cam}/image", rr.Pinhole(image_from_camera=small.matrix, resolution=[small.width,
                         small.height], camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3), static=True)
        rgb = np.asarray(frame.rgb)
        if (small.width, small.height) != (rgb.shape[1], rgb.shape[0]):
            from PIL import Image as PILImage

            rgb = np.asarray(PILImage.fromarray(rgb).resize((small.width, small.height), PILImage.BOX))
        image = rr.Image(rgb, color_model="RGB")
        self.rec.log(f"{cam}/image", image.compress(jpeg_quality=self.jpeg_quality) if self.jpeg_quality else image)

    def _log_ranges(self, cam: str, frame: SyncFrame) -> None:
        """IRS zone points and rays, the USS cone, and both as time series."""
        rr, s = self.rr, frame.stack_id
        pts, z = irs_points(frame.irs_range)  # (M, 3), (M,)
        colors = range_colors(z)
        self.rec.log(f"{cam}/irs", rr.Points3D(pts, colors=colors, radii=0.02))
        self.rec.log(f"{cam}/irs/rays", rr.LineStrips3D([np.stack([np.zeros(3), p]) for p in pts], colors=colors,
                                                        radii=0.003))
        if len(z):
            self.rec.log(f"ranges/irs_min_{s}", rr.Scalars(float(z.min())))
        r = float(frame.uss_range)
        if np.isfinite(r) and r > 0:
            lines = uss_cone_lines(r)
            color = range_colors([r], far=4.0)[0]
            self.rec.log(f"{cam}/uss", rr.LineStrips3D(lines, colors=[color], radii=0.005,
                                                       labels=[f"USS {r:.2f} m"] + [""] * (len(lines) - 1)))
            self.rec.log(f"ranges/uss_{s}", rr.Scalars(r))
        else:  # no echo: nothing in the cone
            self.rec.log(f"{cam}/uss", rr.LineStrips3D([]))

    def log_frame(self, frame: SyncFrame, intrinsics: Intrinsics | Mapping[int, Intrinsics]) -> None:
        """One synchronised frame at drive_time = frame.time - start_time: the robot pose and
        trajectory, the camera pose and image, the IRS zones and the USS cone. intrinsics: the
        frame's camera intrinsics at full resolution, or stack id -> intrinsics."""
        intr = intrinsics if isinstance(intrinsics, Intrinsics) else intrinsics[frame.stack_id]
        self._set_time(frame.time)
        cam = f"world/camera_{frame.stack_id}"
        pose = np.asarray(frame.cam_to_world, dtype=np.float64)
        self._camera_z = float(pose[2, 3])
        if self.robot_stacks.drives(frame.stack_id):
            self._log_robot(base_pose(pose, self.camera_in_base.get(frame.stack_id)))
        self._log_camera(cam, frame, intr)
        self._log_ranges(cam, frame)

    # ------------------------------------------------------------------ maps
    def log_map(self, time: float, map2d: OccupancyMap2D | None = None, prob: OccupancyMap2D | None = None,
                scan_points: np.ndarray | None = None, scan_height: float | None = None) -> None:
        """The maps at drive_time = time - start_time: map/trinary (map2d), map/probability
        (prob), the scan (N, 2) world x, y in metres in 3D at `scan_height` (default the last
        camera's height) and in the map's pixels, and the robot's position on the map."""
        rr = self.rr
        self._set_time(time)
        for path, m in (("map/trinary", map2d), ("map/probability", prob)):
            if m is not None:
                self.rec.log(path, rr.Image(preview(m), color_model="L"))
        raster = map2d if map2d is not None else prob
        if scan_points is not None:
            xy = np.asarray(scan_points, dtype=np.float64).reshape(-1, 2)
            zs = scan_height if scan_height is not None else (self._camera_z or 0.0)
            self.rec.log("world/scan", rr.Points3D(np.column_stack([xy, np.full(len(xy), zs)]), radii=0.02,
                                                   colors=[[255, 0, 255]]))
            if raster is not None:
                self.rec.log("map/scan", rr.Points2D(map_pixels(xy, raster), radii=1.0, colors=[[255, 0, 255]]))
        if raster is not None and self._robot_xyz is not None:
            self.rec.log("map/robot", rr.Points2D(map_pixels(self._robot_xyz[:2], raster), radii=3.0,
                                                  colors=[[40, 120, 255]]))

    def close(self) -> None:
        """Flush everything to the sinks and finish the .rrd; a second call does nothing."""
        if not self._closed:
            self._closed = True
            try:
                self.rec.flush(timeout_sec=self.flush_timeout_s)  # a viewer gone away must not hang the mapper
            except RuntimeError as exc:  # nor fail it: the maps are written by then
                print(f"warning: the live view did not take its last data ({one_line(exc, 120)}); a viewer that "
                      "went away or was never there? The maps are not affected", file=sys.stderr)
            self.rec.disconnect()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def log_mapper(view: LiveView, mapper, time: float, resolution: float = 0.05, n_rays: int = MAP_RAYS,
               max_poses: int = MAP_POSES) -> tuple[OccupancyMap2D, OccupancyMap2D | None, np.ndarray | None]:
    """Log a Mapper's current maps with `view.log_map` through the Mapper's public API only (the
    calls a robot program makes): map2d, probability_map and the NeRF scan from the newest
    frame's camera. Returns (map2d, prob, scan points (N, 2)) for other consumers, e.g.
    `RosMapBag.write_maps`, so that the maps are computed once."""
    m = mapper.map2d(resolution, n_rays, max_poses)
    prob = mapper.probability_map(resolution)
    points = None
    if mapper.frames:
        pose = np.asarray(mapper.store.cam_to_world[-1], dtype=np.float64)  # (4, 4) newest frame's camera
        points = mapper.scans(pose, n_rays)[0].points  # (N, 2) world x, y
        view.log_map(time, m, prob, points, scan_height=float(pose[2, 3]))
    else:
        view.log_map(time, m, prob)
    return m, prob, points
