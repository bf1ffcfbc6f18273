"""Property-based fuzz of every file reader (issue 30): valid files of each input format, corrupted
by byte flips, truncation, inserted bytes that are not UTF-8, deleted and repeated lines. A reader
either returns sane values or raises the tool's own one-line error naming the file
(DataFormatError / UsageError and subclasses); any other exception fails the test.

The valid files are small and built here in the formats of the real sample (same headers and
encodings), so the fuzz runs without ../shared/data; each reader gets FUZZ_EXAMPLES examples.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from virus_nerf.errors import DataFormatError, UsageError

# 40 fixed examples per reader keep the suite fast and repeatable; VIRUS_NERF_FUZZ_EXAMPLES=2000 runs
# a longer, random search (what found the cases fixed in issue 30).
FUZZ_EXAMPLES = int(os.environ.get("VIRUS_NERF_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize="VIRUS_NERF_FUZZ_EXAMPLES" not in os.environ,
                database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])
SAMPLE_TIMES = (1702374040.1040547, 1702374040.312025, 1702374040.5199897, 1702374040.7279692)


# ------------------------------------------------------------------------------ valid files
def uss_csv() -> bytes:
    return ("time,meas\n" + "".join(f"{t!r},{m}\n" for t, m in zip(SAMPLE_TIMES, (3752.0, 3751.0, 1200.0, 50000.0),
                                                                     strict=True))).encode()


def tof_csv() -> bytes:
    head = "time," + ",".join(f"meas_{k}" for k in range(64)) + "," + ",".join(f"stds_{k}" for k in range(64))
    rows = [f"{t!r}," + ",".join(str(500 + 7 * k + i) for k in range(64)) + "," + ",".join(["3"] * 64)
            for i, t in enumerate(SAMPLE_TIMES)]
    return (head + "\n" + "\n".join(rows) + "\n").encode()


def poses_csv() -> bytes:
    rows = [f"{t!r},{0.1 * i},{-0.2 * i},0.3,0.0,0.0,{np.sin(0.1 * i):.9f},{np.cos(0.1 * i):.9f}"
            for i, t in enumerate(SAMPLE_TIMES)]
    return ("time,x,y,z,qx,qy,qz,qw\n" + "\n".join(rows) + "\n").encode()


def intrinsics_csv() -> bytes:
    return (b"cam_id,fx,fy,cx,cy,width,height\n"
            b"CAM1,97.01180370,97.09127840,81.76898870,60.94916965,160,120\n"
            b"CAM3,96.87615758,96.92307510,83.49675195,60.35457148,160,120\n")


def split_csv() -> bytes:
    return b"CAM1,CAM3\ntrain,train\ntest,test\ntrain,val\ntest,test\n"


def split_description_csv() -> bytes:
    return (b"train,val,test,keep_N_observations,info\n"
            b"0.6,0.0,0.4,all,This file contains the split ratios for this dataset. \n")


def scene_json() -> bytes:
    from virus_nerf.sim.scene import Box, Material, Scene, SceneObject

    mat = Material(colour=(0.5, 0.4, 0.3), colour2=(0.2, 0.2, 0.2), pattern="plain", scale=0.1, smooth=False,
                   ir_reflectance=0.5, seed=1)
    scene = Scene(objects=[SceneObject(name="table", kind="furniture", material=mat,
                                       primitives=(Box(center=(1.0, 0.0, 0.4), size=(1.0, 0.6, 0.05), yaw=0.3),))],
                  name="office", extent_lo=(-2.0, -2.0, -0.5), extent_hi=(2.0, 2.0, 2.5))
    buf = io.BytesIO()
    import json

    buf.write(json.dumps(scene.to_dict(), indent=2).encode())
    return buf.getvalue()


def pcd(encoding: str) -> bytes:
    from pypcd4 import Encoding, PointCloud

    rng = np.random.default_rng(1)
    pts = np.round(rng.uniform(-3, 3, (24, 3)), 1).astype(np.float32)
    pts[:, 2] = 1.5  # a floor-parallel slice: compressible, so binary_compressed does not fall back to binary
    pts[3] = np.nan  # organised clouds carry NaN points: dropped, not refused
    buf = io.BytesIO()
    PointCloud.from_xyz_points(pts).save(buf, encoding=Encoding(encoding))
    return buf.getvalue()


def png() -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    rgb = (np.arange(8 * 6 * 3).reshape(6, 8, 3) * 5 % 256).astype(np.uint8)
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def depth_npy() -> bytes:
    buf = io.BytesIO()
    np.save(buf, (np.arange(48).reshape(6, 8) * 50).astype(np.uint16))
    return buf.getvalue()


def topics_toml() -> bytes:
    return (b'intrinsics_csv = "camera_intrinsics.CSV"\ntf_topics = ["/tf", "/tf_static"]\n\n'
            b'[lidar]\ntopic = "/velodyne_points"\nmin_range_m = 0.3\nmax_range_m = 30.0\n\n'
            b"[sync]\ndepth_tolerance_s = 0.02\nuss_tolerance_s = 0.15\ncamera_rate_hz = 5.0\n\n"
            b'[stacks.1]\ncolor = "/front/color/image_raw"\ndepth = "/front/aligned_depth_to_color/image_raw"\n'
            b'uss = "/sonar_front"\ntof = "/tof_front"\n'
            b"camera_in_lidar = { translation = [0.36, -0.15, -0.15], rotation_xyzw = [0.5476, 0.3955, 0.4688, "
            b"0.5692] }\n")


# ------------------------------------------------------------------------------ corruption
NON_UTF8 = [b"\xe9", b"\xff", b"\x80", b"\xc3", b"\xfe\xff", b"\xed\xa0\x80"]


@st.composite
def corrupted(draw, valid: bytes) -> bytes:
    """`valid` with 1-3 corruptions: byte flips, truncation, inserted non-UTF-8 bytes, deleted or
    repeated lines, a digit changed."""
    data = bytearray(valid)
    for op in draw(st.lists(st.sampled_from(["flip", "truncate", "non_utf8", "delete_line", "repeat_line",
                                             "digit", "bitflip"]), min_size=1, max_size=3)):
        n = len(data)
        if n == 0:
            break
        at = draw(st.integers(0, n - 1))
        if op == "flip":
            data[at] = draw(st.integers(0, 255))
        elif op == "bitflip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "truncate":
            del data[at:]
        elif op == "non_utf8":
            data[at:at] = draw(st.sampled_from(NON_UTF8))
        elif op == "digit":
            digits = [i for i, b in enumerate(data) if 48 <= b <= 57]
            if digits:
                data[digits[at % len(digits)]] = draw(st.sampled_from(b"0123456789-.e"))
        else:
            lines = bytes(data).split(b"\n")
            k = at % len(lines)
            lines[k:k + 1] = [] if op == "delete_line" else [lines[k], lines[k]]
            data = bytearray(b"\n".join(lines))
    return bytes(data)


def check(path: Path, data: bytes, read: Callable[[Path], object], sane: Callable[[object], None]) -> str:
    """Write `data` to `path` and read it: sane values or the tool's own error naming the file."""
    path.write_bytes(data)
    try:
        out = read(path)
    except (DataFormatError, UsageError) as exc:
        message = str(exc)
        assert path.name in message, message
        return "refused"
    sane(out)
    return "read"


def fuzz_reader(name: str, valid: Callable[[], bytes], read: Callable[[Path], object],
                sane: Callable[[object], None]):
    """A Hypothesis test of `read` over corrupted versions of `valid()` written as `name`."""
    base = valid()

    @FUZZ
    @given(data=corrupted(base))
    def run(tmp_path, data):
        check(tmp_path / name, data, read, sane)

    def test(tmp_path):
        assert check(tmp_path / name, base, read, sane) == "read"  # the valid file reads
        run(tmp_path)

    return test


# ------------------------------------------------------------------------------ sanity of what was read
def sane_times(times) -> None:
    assert np.isfinite(times).all() and np.all(np.diff(times) > 0)


def sane_uss(out) -> None:
    times, ranges = out
    sane_times(times)
    assert ranges.shape == times.shape
    assert np.all(np.isnan(ranges) | (ranges > 0))


def sane_tof(out) -> None:
    from virus_nerf.data.ethz import IRS_MAX_PLAUSIBLE_MM

    times, grid = out
    sane_times(times)
    assert grid.shape == (len(times), 8, 8)
    ok = grid[np.isfinite(grid)]
    assert np.all((ok > 0.1) & (ok <= IRS_MAX_PLAUSIBLE_MM / 1000))


def sane_poses(out) -> None:
    times, poses = out
    sane_times(times)
    assert poses.shape == (len(times), 4, 4) and np.isfinite(poses).all()
    r = poses[:, :3, :3]
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-6)


def sane_intrinsics(out) -> None:
    from virus_nerf.sensors.camera import intrinsics_problem

    for intr in out.values():
        assert isinstance(intr.width, int) and isinstance(intr.height, int)
        assert intrinsics_problem(intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) is None


def sane_split(out) -> None:
    from virus_nerf.data.split import LABELS

    assert set(out) == {1, 3}
    for labels in out.values():
        assert len(labels) == 4 and set(labels) <= set(LABELS)


def sane_ratios(out) -> None:
    assert len(out) == 3 and min(out) >= 0 and sum(out) > 0 and np.isfinite(out).all()


def sane_scene(scene) -> None:
    assert np.isfinite(scene.extent_lo).all() and np.isfinite(scene.extent_hi).all()


def sane_cloud(xyz) -> None:
    from virus_nerf.data.pcd import MAX_ABS_COORD_M

    assert xyz.ndim == 2 and xyz.shape[1] == 3 and len(xyz) > 0
    assert np.isfinite(xyz).all() and np.abs(xyz).max() <= MAX_ABS_COORD_M


def sane_rgb(arr) -> None:
    assert arr.shape == (6, 8, 3) and arr.dtype == np.uint8


def sane_depth(depth) -> None:
    assert depth.shape == (6, 8)
    ok = depth[np.isfinite(depth)]
    assert np.all((ok > 0) & (ok < 65.535))


def sane_topics(cfg) -> None:
    assert cfg.stacks and all(s.color.startswith("/") for s in cfg.stacks.values())
    assert 0 <= cfg.lidar.min_range_m < cfg.lidar.max_range_m


# ------------------------------------------------------------------------------ readers
def _read_split(p):
    from virus_nerf.data.split import read_split

    return read_split(p, {1: 4, 3: 4})


def _read_ratios(p):
    from virus_nerf.data.split import read_split_ratios

    return read_split_ratios(p)


def _read_intrinsics(p):
    from virus_nerf.data.ethz import read_intrinsics

    return read_intrinsics(p)


def _read_uss(p):
    from virus_nerf.data.ethz import read_uss

    return read_uss(p)


def _read_tof(p):
    from virus_nerf.data.ethz import read_tof

    return read_tof(p)


def _read_poses(p):
    from virus_nerf.data.ethz import read_poses

    return read_poses(p)


def _read_scene(p):
    from virus_nerf.sim.scene import Scene

    return Scene.load(p)


def _read_map(p):
    from virus_nerf.data.pcd import read_pcd_xyz

    return read_pcd_xyz(p, nonempty="the LiDAR map")


def _intr():
    from virus_nerf.sensors.camera import Intrinsics

    return Intrinsics(10.0, 10.0, 3.5, 2.5, width=8, height=6)


def _read_rgb(p):
    from virus_nerf.data.images import image_size, read_rgb

    size = image_size(p)
    arr = read_rgb(p, _intr())
    assert size == (8, 6)
    return arr


def _read_depth(p):
    from virus_nerf.data.images import check_depth_header, read_depth

    check_depth_header(p, _intr())
    return read_depth(p, _intr())


def _read_topics(p):
    from virus_nerf.data.bags.topics import read_topics

    return read_topics(p)


test_fuzz_uss_csv = fuzz_reader("USS1.csv", uss_csv, _read_uss, sane_uss)
test_fuzz_tof_csv = fuzz_reader("TOF1.csv", tof_csv, _read_tof, sane_tof)
test_fuzz_pose_csv = fuzz_reader("poses_cam_balm_sync1.csv", poses_csv, _read_poses, sane_poses)
test_fuzz_intrinsics_csv = fuzz_reader("camera_intrinsics.CSV", intrinsics_csv, _read_intrinsics, sane_intrinsics)
test_fuzz_split_csv = fuzz_reader("split.csv", split_csv, _read_split, sane_split)
test_fuzz_split_description = fuzz_reader("split_description.csv", split_description_csv, _read_ratios, sane_ratios)
test_fuzz_scene_json = fuzz_reader("scene.json", scene_json, _read_scene, sane_scene)
test_fuzz_pcd_binary = fuzz_reader("map_balm.pcd", lambda: pcd("binary"), _read_map, sane_cloud)
test_fuzz_pcd_ascii = fuzz_reader("map_balm.pcd", lambda: pcd("ascii"), _read_map, sane_cloud)
test_fuzz_pcd_compressed = fuzz_reader("map_balm.pcd", lambda: pcd("binary_compressed"), _read_map, sane_cloud)
test_fuzz_png = fuzz_reader("img0.png", png, _read_rgb, sane_rgb)
test_fuzz_depth_npy = fuzz_reader("img0.npy", depth_npy, _read_depth, sane_depth)
test_fuzz_topics_toml = fuzz_reader("topics.toml", topics_toml, _read_topics, sane_topics)


@pytest.fixture(scope="module")
def tiny_mcap(tmp_path_factory) -> bytes:
    """A bare ROS 2 .mcap file of four USS messages, written as the repository's bag writer does."""
    pytest.importorskip("rosbags")
    from virus_nerf.data.bags import messages as m
    from virus_nerf.data.bags.writer import _write

    store = m.make_typestore(2)
    t = store.types
    msgs = []
    for i, ts in enumerate(SAMPLE_TIMES):
        ns = int(round(ts * 1e9))
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        h = t["std_msgs/msg/Header"](stamp=stamp, frame_id="CAM1_color_optical_frame")
        msgs.append((ns, "/USS1", m.USS_TYPE, t[m.USS_TYPE](header=h, meas=3752 - i)))
    folder = tmp_path_factory.mktemp("bag") / "bag"
    _write(folder, 2, store, msgs, "mcap")
    return next(folder.glob("*.mcap")).read_bytes()


def _read_bag(p):
    from virus_nerf.data.bags.reader import BagReader

    with BagReader(p) as reader:
        reader.require("/USS1", "uss", "stacks.1.uss")
        return [msg.msg.meas for msg in reader.iter_topic("/USS1")]


def test_fuzz_bare_mcap(tiny_mcap, tmp_path):
    assert check(tmp_path / "office.mcap", tiny_mcap, _read_bag, lambda out: None) == "read"

    @FUZZ
    @given(data=corrupted(tiny_mcap))
    def run(data):
        check(tmp_path / "office.mcap", data, _read_bag, lambda out: None)

    run()
