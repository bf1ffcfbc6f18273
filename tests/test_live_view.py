"""The Rerun live view: synthetic frames and maps saved to a .rrd, read back with Rerun's own
reader (rerun.chunk.RrdReader): entity paths, the drive_time range, which entity has which times."""

from __future__ import annotations

import math
import re
import sys

import numpy as np
import pytest

from virus_nerf.data.frame import SyncFrame
from virus_nerf.errors import OutputExistsError, UsageError
from virus_nerf.mapping.live_view import irs_points, map_pixels, uss_cone_lines
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyMap2D
from virus_nerf.sensors.camera import Intrinsics

INTR = Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)
NS = 1_000_000_000


def _camera(x: float, yaw: float = 0.0) -> np.ndarray:
    """Upright level camera at (x, 0, 0.4) looking along world yaw (rad)."""
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([np.cross(down, fwd), down, fwd])
    pose[:3, 3] = (x, 0.0, 0.4)
    return pose


def _frame(t: float, stack: int, x: float, uss: float) -> SyncFrame:
    irs = np.full((8, 8), 1.5)
    irs[0, :] = np.nan  # one invalid row of zones
    rgb = np.zeros((48, 64, 3), dtype=np.uint8)
    rgb[:, :, 0] = np.arange(64, dtype=np.uint8)[None, :] * 4
    return SyncFrame(time=t, stack_id=stack, rgb=rgb, cam_to_world=_camera(x, 0.3 if stack == 3 else 0.0),
                     uss_range=uss, irs_range=irs)


def _maps() -> tuple[OccupancyMap2D, OccupancyMap2D]:
    img = np.full((20, 30), UNKNOWN, dtype=np.uint8)
    img[5:15, 5:25] = FREE
    img[5, 5:25] = OCCUPIED
    return (OccupancyMap2D(img, 0.1, (-1.0, -1.0)),
            OccupancyMap2D(np.full((20, 30), 128, dtype=np.uint8), 0.1, (-1.0, -1.0), "scale"))


def _read(path) -> dict[str, list[int]]:
    """entity path -> sorted drive_time values (ns) of its rows; static entities map to []."""
    from rerun.chunk import RrdReader

    times: dict[str, list[int]] = {}
    for chunk in RrdReader(path).stream():
        rows = times.setdefault(chunk.entity_path, [])
        if "drive_time" in chunk.timeline_names:
            rows += chunk.to_record_batch().column("drive_time").cast("int64").to_pylist()  # duration ns
    return {k: sorted(v) for k, v in times.items()}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rr = pytest.importorskip("rerun")
    from virus_nerf.mapping.live_view import LiveView

    path = tmp_path_factory.mktemp("live") / "drive.rrd"
    strict = rr.strict_mode()
    rr.set_strict_mode(True)  # a bad archetype raises instead of a warning and a missing entity
    with LiveView(save=path, start_time=10.0) as view:
        view.log_frame(_frame(10.0, 1, 0.0, 1.2), INTR)
        view.log_frame(_frame(10.25, 3, 0.1, math.nan), {1: INTR, 3: INTR})  # no echo
        view.log_frame(_frame(10.5, 1, 0.5, 0.8), INTR)
        view.log_frame(_frame(11.0, 1, 1.0, 0.9), INTR)
        m, p = _maps()
        view.log_map(11.5, m, p, np.array([[0.0, 0.5], [1.0, -0.5]]))
        view.log_map(12.0, m, None, None)
    rr.set_strict_mode(strict)
    return path


def test_entity_paths(recording):
    cams = [f"/world/camera_{s}{leaf}" for s in (1, 3) for leaf in ("", "/image", "/irs", "/irs/rays", "/uss")]
    want = {"/__properties", "/world", "/world/robot", "/world/trajectory", "/world/scan", *cams,
            "/map/trinary", "/map/probability", "/map/scan", "/map/robot",
            "/ranges/uss_1", "/ranges/irs_min_1", "/ranges/irs_min_3"}
    assert set(_read(recording)) == want


def test_drive_time_range_and_rows(recording):
    t = _read(recording)
    every = sorted(v for rows in t.values() for v in rows)
    assert (every[0], every[-1]) == (0, 2 * NS)  # 10.0 s and 12.0 s, start_time 10.0 s
    assert t["/world/camera_1"] == [0, NS // 2, NS]
    assert t["/world/camera_3"] == [NS // 4]
    assert t["/world/robot"] == [0, NS // 2, NS]  # driven by the first stack seen only
    assert t["/world/camera_3/uss"] == [NS // 4]  # logged empty: no echo
    assert t["/ranges/uss_1"] == [0, NS // 2, NS] and "/ranges/uss_3" not in t
    assert t["/map/trinary"] == [3 * NS // 2, 2 * NS]
    assert t["/map/probability"] == [3 * NS // 2]
    assert t["/map/scan"] == t["/world/scan"] == [3 * NS // 2]
    assert t["/world"] == [] and t["/world/camera_1/image"] == [0, NS // 2, NS]  # + its static pinhole


def test_trajectory_and_scan_values(recording):
    from rerun.chunk import RrdReader

    strips = scan = None
    for chunk in RrdReader(recording).stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/world/trajectory":
            strips = batch.column("LineStrips3D:strips").to_pylist()
        if chunk.entity_path == "/map/scan":
            scan = batch.column("Points2D:positions").to_pylist()
    last = np.asarray(strips[-1][0])  # the strip after the last frame: the 3 robot positions
    np.testing.assert_allclose(last, [[0.0, 0, 0.4], [0.5, 0, 0.4], [1.0, 0, 0.4]], atol=1e-6)
    # world (0, 0.5) on a 20-row raster at 0.1 m from (-1, -1): u = 10, v = 20 - 15 = 5
    np.testing.assert_allclose(scan[0], [[10.0, 5.0], [20.0, 15.0]], atol=1e-5)


def test_default_layout(recording):
    """The recording's last blueprint (sent when camera 3 first appeared) has a view for each map,
    the world, both cameras and the ranges, and its time panel follows the newest data."""
    from rerun.chunk import RrdReader

    reader = RrdReader(recording)
    blueprints = reader.blueprints()
    assert len(blueprints) == 3  # at the start, at camera 1's first frame, at camera 3's
    layouts = []  # per blueprint: (view name -> origin, the time panel's play states)
    for store in blueprints:
        views, play_states = {}, []
        for chunk in reader.stream(store=store):
            batch = chunk.to_record_batch()
            if "ViewBlueprint:space_origin" in batch.schema.names:
                name = batch.column("ViewBlueprint:display_name").to_pylist()[-1][0]
                views[name] = batch.column("ViewBlueprint:space_origin").to_pylist()[-1][0]
            if chunk.entity_path == "/time_panel" and "TimePanelBlueprint:play_state" in batch.schema.names:
                play_states += batch.column("TimePanelBlueprint:play_state").to_pylist()
        layouts.append((views, play_states))
    assert sorted(len(views) for views, _ in layouts) == [4, 5, 6]  # maps, world, ranges + cameras seen
    views, play_states = max(layouts, key=lambda layout: len(layout[0]))
    assert views == {"map": "map", "probability": "map", "world": "world", "camera 1": "world/camera_1/image",
                     "camera 3": "world/camera_3/image", "ranges (m)": "ranges"}
    assert play_states[-1] == [3]  # PlayState.Following


def test_sensor_geometry():
    pts, z = irs_points(np.where(np.eye(8) > 0, 2.0, np.nan))
    assert pts.shape == (8, 3) and np.allclose(pts[:, 2], 2.0) and np.allclose(z, 2.0)
    assert (np.diff(pts[:, 0]) > 0).all() and (np.diff(pts[:, 1]) > 0).all()  # row 0 = image top (y down)
    ring, *edges = uss_cone_lines(1.5)
    assert np.allclose(np.linalg.norm(ring, axis=1), 1.5) and len(edges) == 4
    half_h = math.degrees(math.atan2(edges[0][1, 0], edges[0][1, 2]))
    half_v = math.degrees(math.atan2(edges[1][1, 1], edges[1][1, 2]))
    assert (half_h, half_v) == pytest.approx((27.5, 17.5))
    m = OccupancyMap2D(np.zeros((4, 6), np.uint8), 0.5, (1.0, 2.0))
    np.testing.assert_allclose(map_pixels([[1.0, 2.0], [4.0, 4.0]], m), [[0, 4], [6, 0]])


def test_refusals(tmp_path, monkeypatch):
    pytest.importorskip("rerun")
    from virus_nerf.mapping.live_view import LiveView

    with pytest.raises(UsageError, match="no sink"):
        LiveView()
    with pytest.raises(UsageError, match=r"\.rrd"):
        LiveView(save=tmp_path / "x.txt")
    (tmp_path / "old.rrd").write_bytes(b"")
    with pytest.raises(OutputExistsError):
        LiveView(save=tmp_path / "old.rrd")
    from virus_nerf.mapping.options import RerunSinks

    with pytest.raises(UsageError, match=r"--rerun-save .*nodir/x.rrd: no folder .*nodir; expected a .rrd file in an "):
        RerunSinks(rerun_save=tmp_path / "nodir" / "x.rrd").check()
    with pytest.raises(UsageError, match=r"--rerun-connect http://127.0.0.1:9876/proxy: invalid endpoint .*scheme"):
        RerunSinks(rerun_connect="http://127.0.0.1:9876/proxy").check()
    with pytest.raises(UsageError, match=r"LiveView sinks \['http://x/proxy'\]: invalid endpoint"):
        LiveView(connect="http://x/proxy")
    # a viewer that cannot start (none beside this Python, none on PATH: a user's review gave a traceback)
    import virus_nerf.mapping.live_view as live_view

    monkeypatch.setattr(live_view, "_viewer_executable", lambda: str(tmp_path / "no-viewer"))
    monkeypatch.setenv("DISPLAY", ":0")  # a screen: the viewer itself is what fails
    with pytest.raises(UsageError) as err:
        LiveView(spawn=True, port=9)
    assert str(err.value).startswith("--rerun: cannot start the Rerun viewer (") and "--rerun-save FILE.rrd" in str(err.value)
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if the live extra were not installed
    with pytest.raises(UsageError, match=re.escape("pip install -e '.[live]' in the virus-nerf repository")):
        LiveView(save=tmp_path / "y.rrd")
    for flags, named in (({"rerun_save": tmp_path / "z.rrd"}, "--rerun-save"), ({"rerun": True}, "--rerun"),
                         ({"rerun_connect": "rerun+http://127.0.0.1:9/proxy"}, "--rerun-connect")):
        with pytest.raises(UsageError, match=f"^{named} needs the live extra: "):  # the flag given, not --rerun
            RerunSinks(**flags).check()


def test_rerun_without_a_display_is_refused_in_one_line(monkeypatch):
    """A robot's computer over ssh (Linux, neither DISPLAY nor WAYLAND_DISPLAY): --rerun is refused
    before anything starts, naming --rerun-connect and --rerun-save (before: the viewer died, the
    view waited 6 s for its port, the drive mapped without a viewer and the command exited 0)."""
    from virus_nerf.mapping.live_view import no_display_problem
    from virus_nerf.mapping.options import RerunSinks

    assert no_display_problem({}, "linux").startswith("--rerun: no display for the Rerun viewer")
    assert no_display_problem({"DISPLAY": ":0"}, "linux") is None
    assert no_display_problem({"WAYLAND_DISPLAY": "wayland-0"}, "linux") is None
    assert no_display_problem({}, "darwin") is None and no_display_problem({}, "win32") is None
    if not sys.platform.startswith("linux"):
        return
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(UsageError, match="--rerun-connect rerun.*--rerun-save FILE.rrd"):
        RerunSinks(rerun=True).check()
    RerunSinks(rerun_save=None).check()  # nothing asked: nothing refused


def test_a_viewer_that_is_not_there_is_a_warning_at_close_not_a_failure(tmp_path, capsys):
    """--rerun-connect to a port nobody listens on (loopback): the mapping went on, and at the end
    the sinks cannot take the last data; that is one warning, the .rrd beside it is whole."""
    pytest.importorskip("rerun")
    from virus_nerf.mapping.live_view import LiveView

    view = LiveView(connect="rerun+http://127.0.0.1:1/proxy", save=tmp_path / "v.rrd")
    view.flush_timeout_s = 1.0
    view.log_frame(_frame(0.0, 1, 0.0, 1.5), {1: INTR})
    view.close()
    assert "warning: the live view did not take its last data" in capsys.readouterr().err
    assert (tmp_path / "v.rrd").stat().st_size > 0


class _FakeMapper:
    """The Mapper's public query API (engine/views.py), answering fixed maps and one scan."""

    def __init__(self):
        from types import SimpleNamespace

        self.frames = 2
        self.store = SimpleNamespace(cam_to_world=np.stack([_camera(0.0), _camera(0.7)]))
        self.asked = []
        self._scan = SimpleNamespace(points=np.array([[1.0, 0.0], [0.0, 1.0]]))

    def map2d(self, resolution, n_rays, max_poses):
        self.asked.append(("map2d", resolution, n_rays, max_poses))
        return _maps()[0]

    def probability_map(self, resolution):
        return _maps()[1]

    def scans(self, poses, n_rays):
        self.asked.append(("scans", tuple(np.asarray(poses)[:3, 3]), n_rays))
        return [self._scan]


def test_log_mapper_uses_the_public_api(tmp_path):
    pytest.importorskip("rerun")
    from virus_nerf.mapping.live_view import LiveView, log_mapper

    mapper = _FakeMapper()
    with LiveView(save=tmp_path / "m.rrd") as view:
        m, prob, pts = log_mapper(view, mapper, 3.0, resolution=0.1, n_rays=90)
    assert m.mode == "trinary" and prob.mode == "scale" and pts.shape == (2, 2)
    assert mapper.asked == [("map2d", 0.1, 90, 30), ("scans", (0.7, 0.0, 0.4), 90)]  # newest frame's camera
    t = _read(tmp_path / "m.rrd")
    assert t["/map/trinary"] == t["/map/probability"] == t["/world/scan"] == [3 * NS]
