"""Bad input gets a clear error naming file, row and field; nothing in the input is changed."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from virus_nerf.data.csvtable import read_numeric_csv
from virus_nerf.data.ethz import load_recording, read_intrinsics, read_poses, read_tof, read_uss
from virus_nerf.data.pcd import read_pcd_xyz
from virus_nerf.data.split import make_split
from virus_nerf.errors import DataFormatError

POSE_HEADER = "time,x,y,z,qx,qy,qz,qw\n"


@pytest.fixture()
def sample_copy(sample_dir, tmp_path) -> Path:
    dst = tmp_path / "data"
    shutil.copytree(sample_dir, dst)
    return dst


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_missing_file(tmp_path):
    with pytest.raises(DataFormatError, match="nope.csv: file not found"):
        read_poses(tmp_path / "nope.csv")


def test_wrong_header_names_missing_columns(tmp_path):
    p = write(tmp_path, "poses.csv", "time,x,y,z,qx,qy,qw\n1,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match=r"row 1: .*lacks column\(s\) \['qz'\]"):
        read_poses(p)


def test_wrong_column_count_names_row(tmp_path):
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="row 3: has 7 values; expected 8"):
        read_poses(p)


def test_non_numeric_names_field(tmp_path):
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,abc,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="row 2, field 'y': value 'abc' is not a number"):
        read_poses(p)


def test_non_finite_pose(tmp_path):
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,nan,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="row 3, field 'x/y/z': pose is not finite"):
        read_poses(p)


def test_zero_quaternion(tmp_path):
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,0\n")
    with pytest.raises(DataFormatError, match="row 2.*cannot be normalised"):
        read_poses(p)


def test_a_blank_line_between_rows_is_named_and_one_at_the_end_is_read(tmp_path):
    """A blank line inside the table is refused at its row: the checks after reading (the quaternion,
    the time order, the box) name data row i as file row i + 2, which a skipped line would shift (a
    review saw row 3 named for the bad pose on row 4)."""
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n\n2,0,0,0,0,0,0,2\n")
    with pytest.raises(DataFormatError, match=r"poses.csv, row 3: a blank line between rows; expected one row per line"):
        read_poses(p)
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,2\n\n\n")
    with pytest.raises(DataFormatError, match=r"row 3, field 'qx/qy/qz/qw'"):  # blank lines at the end: read
        read_poses(p)
    # Python's csv.writer on Windows without newline="" ends each row with \r\r\n: read, not blank lines
    p = tmp_path / "poses_crcrlf.csv"
    p.write_bytes((POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,1\n").replace("\n", "\r\r\n").encode())
    assert len(read_poses(p)) == 2


def test_unsorted_timestamps(tmp_path):
    p = write(tmp_path, "poses.csv", POSE_HEADER + "2,0,0,0,0,0,0,1\n1,0,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="row 3, field 'time': timestamps not strictly increasing"):
        read_poses(p)


def test_tof_needs_64_zones(tmp_path):
    header = "time," + ",".join(f"meas_{k}" for k in range(63)) + "\n"
    p = write(tmp_path, "TOF1.csv", header + "1," + ",".join(["500"] * 63) + "\n")
    with pytest.raises(DataFormatError, match=r"lacks column\(s\) \['meas_63'\]"):
        read_tof(p)


def test_unsupported_pcd(tmp_path):
    p = write(tmp_path, "scan.pcd", "this is not a pcd\n")
    with pytest.raises(DataFormatError, match="scan.pcd: not a readable PCD"):
        read_pcd_xyz(p)


def test_pcd_without_xyz(tmp_path):
    p = tmp_path / "scan.pcd"
    p.write_bytes(
        b"VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
        b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n"
    )
    with pytest.raises(DataFormatError, match="expected x, y, z"):
        read_pcd_xyz(p)


def test_stack_files_disagree_in_row_count(sample_copy):
    uss = sample_copy / "office" / "measurements" / "USS1.csv"
    lines = uss.read_text().splitlines()
    uss.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(DataFormatError, match="stack 1 files disagree in sample count"):
        load_recording(sample_copy, "office")


@pytest.mark.parametrize("name", ["USS1.csv", "TOF3.csv", "CAM1_color_image_raw"])
def test_a_stack_with_a_missing_file_is_refused_not_left_out(sample_copy, name):
    """Any of a stack's files names the stack: without its USS table it fails on that file instead
    of training silently on the other stack alone."""
    target = sample_copy / "office" / "measurements" / name
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(DataFormatError, match=rf"{name}: (file|folder) not found"):
        load_recording(sample_copy, "office")


def test_image_size_must_match_intrinsics(sample_copy):
    from PIL import Image

    img = sample_copy / "office" / "measurements" / "CAM3_color_image_raw" / "img2.png"
    Image.new("RGB", (320, 240)).save(img)
    with pytest.raises(DataFormatError, match=r"img2.png: image is 320x240; the intrinsics of CAM3 expect 640x480"):
        load_recording(sample_copy, "office")


def test_missing_room(sample_dir):
    with pytest.raises(DataFormatError, match="room folder not found"):
        load_recording(sample_dir, "kitchen")


def test_missing_split_is_made_in_memory_without_writing(sample_copy):
    split = sample_copy / "office" / "split" / "split.csv"
    split.unlink()
    before = sorted(p.relative_to(sample_copy) for p in sample_copy.rglob("*"))
    rec = load_recording(sample_copy, "office")
    assert list(rec.stacks[1].split) == list(rec.stacks[3].split)
    assert (rec.stacks[1].split == "test").sum() == 2  # 40 % of 5
    assert sorted(p.relative_to(sample_copy) for p in sample_copy.rglob("*")) == before
    load_recording(sample_copy, "office", write_split=True)
    assert split.is_file()


def test_reading_changes_nothing(sample_dir):
    stamp = {p: p.stat().st_mtime_ns for p in sample_dir.rglob("*")}
    rec = load_recording(sample_dir, "office")
    rec.stacks[1].image(0)
    rec.lidar_map()
    assert {p: p.stat().st_mtime_ns for p in sample_dir.rglob("*")} == stamp


@pytest.mark.parametrize("n", [0, 1, 5, 17, 100])
def test_make_split_ratios(n):
    labels = make_split(n, (0.6, 0.1, 0.3))
    assert len(labels) == n
    # held-out count within 1 of 40 %, and its test/val share within 1 again
    assert abs((labels != "train").sum() - 0.4 * n) <= 1
    assert abs((labels == "test").sum() - 0.3 * n) <= 2
    assert abs((labels == "val").sum() - 0.1 * n) <= 2


cell = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(alphabet="0123456789.-eabc ,\"", max_size=8),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.lists(cell, min_size=1, max_size=10), max_size=6))
def test_fuzzed_pose_files_parse_or_fail_clearly(tmp_path, rows):
    p = tmp_path / "poses.csv"
    p.write_text(POSE_HEADER + "\n".join(",".join(r) for r in rows) + "\n")
    try:
        times, poses = read_poses(p)
    except DataFormatError as exc:
        assert str(p) in str(exc)
        assert "row" in str(exc) or "file" in str(exc)
    else:
        assert poses.shape == (len(times), 4, 4)
        assert np.isfinite(poses).all()
        assert np.all(np.diff(times) > 0)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    header=st.lists(st.sampled_from(["time", "meas", "x", "foo", ""]), min_size=0, max_size=4),
    body=st.text(alphabet="0123456789.,\n-x", max_size=60),
)
def test_fuzzed_uss_tables_parse_or_fail_clearly(tmp_path, header, body):
    p = tmp_path / "USS1.csv"
    p.write_text(",".join(header) + "\n" + body)
    try:
        table = read_numeric_csv(p, ("time", "meas"))
    except DataFormatError as exc:
        assert str(exc).startswith(str(p))
    else:
        assert table["time"].shape == table["meas"].shape


def test_intrinsics_with_and_without_size(tmp_path):
    from virus_nerf.data.ethz import read_intrinsics

    p = write(tmp_path, "a.CSV", "cam_id,fx,fy,cx,cy\nCAM1,388,388,320,240\n")
    assert (read_intrinsics(p)[1].width, read_intrinsics(p)[1].height) == (640, 480)
    p = write(tmp_path, "b.CSV", "cam_id,fx,fy,cx,cy,width,height\nCAM3,194,194,160,120,320,240\n")
    assert (read_intrinsics(p)[3].width, read_intrinsics(p)[3].height) == (320, 240)
    p = write(tmp_path, "c.CSV", "cam_id,fx,fy,cx,cy,width,height\nCAM3,194,194,160,120,-320,240\n")
    with pytest.raises(DataFormatError, match="row 2, field 'width'"):
        read_intrinsics(p)


# ------------------------------------------------------------------------------ silent garbage
def test_non_unit_quaternion_is_refused_with_row_and_field(tmp_path):
    from virus_nerf.data.ethz import QUATERNION_NORM_TOLERANCE

    assert QUATERNION_NORM_TOLERANCE == 1e-3
    p = write(tmp_path, "poses.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,0,0,1,2,3,4\n")
    with pytest.raises(DataFormatError, match=r"poses.csv, row 3, field 'qx/qy/qz/qw': quaternion \(1, 2, 3, 4\) "
                                              r"has norm 5.47723; expected a unit quaternion \(\| \|q\| - 1 \| <= 0.001\)"):
        read_poses(p)


@pytest.mark.parametrize("w, ok", [(1.0009, True), (0.9991, True), (1.0011, False), (0.9989, False)])
def test_quaternion_tolerance_edges(tmp_path, w, ok):
    p = write(tmp_path, "poses.csv", POSE_HEADER + f"1,0,0,0,0,0,0,{w}\n")
    if ok:
        _, poses = read_poses(p)
        np.testing.assert_allclose(poses[0, :3, :3], np.eye(3), atol=1e-12)  # normalised
    else:
        with pytest.raises(DataFormatError, match="row 2, field 'qx/qy/qz/qw'"):
            read_poses(p)


def test_real_sample_quaternions_are_within_tolerance(sample_dir):
    from virus_nerf.data.ethz import QUATERNION_NORM_TOLERANCE

    for path in sorted((sample_dir / "office" / "poses").glob("*.csv")):
        table = read_numeric_csv(path, ("qx", "qy", "qz", "qw"))
        q = np.stack([table[c] for c in ("qx", "qy", "qz", "qw")], axis=1)
        assert np.abs(np.linalg.norm(q, axis=1) - 1).max() < QUATERNION_NORM_TOLERANCE / 1000, path


def test_float_depth_in_metres_is_refused(tmp_path):
    from virus_nerf.data.ethz import read_depth
    from virus_nerf.sensors.camera import Intrinsics

    intr = Intrinsics(10.0, 10.0, 2.0, 1.5, width=4, height=3)
    p = tmp_path / "img0.npy"
    np.save(p, np.full((3, 4), 2.5, dtype=np.float32))
    with pytest.raises(DataFormatError, match=r"img0.npy: depth map is float32 \(values up to 2.5 look like metres\); "
                                              r"expected uint16 millimetres"):
        read_depth(p, intr)
    np.save(p, np.full((3, 4), 2500, dtype=np.int32))  # other integer types: fine if they fit
    np.testing.assert_allclose(read_depth(p, intr), 2.5)
    np.save(p, np.full((3, 4), 70000, dtype=np.int32))
    with pytest.raises(DataFormatError, match=r"img0.npy: depth map \(int32\) has values 70000..70000"):
        read_depth(p, intr)
    np.save(p, np.array([[1, 2], [3, 4]], dtype=np.uint16))
    with pytest.raises(DataFormatError, match=r"depth map has shape \(2, 2\); expected \(3, 4\)"):
        read_depth(p, intr)


def test_float_depth_file_in_a_recording_is_refused_on_loading(sample_copy):
    depth = sample_copy / "office" / "measurements" / "CAM3_aligned_depth_to_color_image_raw" / "img1.npy"
    metres = np.load(depth).astype(np.float32) / 1000.0
    np.save(depth, metres)
    with pytest.raises(DataFormatError, match=r"CAM3_aligned_depth_to_color_image_raw/img1.npy: depth map is float32"):
        load_recording(sample_copy, "office")


# ------------------------------------------------------------------------------ bad input, round two (issue 30)
LATIN1 = b"\xe9"  # 'é' in Latin-1: not UTF-8 on its own


def test_non_utf8_byte_in_a_csv_header_names_file_and_row(tmp_path):
    p = tmp_path / "USS1.csv"
    p.write_bytes(b"time,m" + LATIN1 + b"as\n1,3752\n")
    with pytest.raises(DataFormatError, match=r"USS1.csv, row 1: byte 0xe9 at column 7 is not UTF-8 text"):
        read_numeric_csv(p, ("time", "meas"))


def test_non_utf8_byte_in_a_numeric_cell_names_row_and_field(tmp_path):
    p = tmp_path / "USS1.csv"
    p.write_bytes(b"time,meas\n1,3752\n2,37" + LATIN1 + b"2\n")
    with pytest.raises(DataFormatError, match=r"USS1.csv, row 3, field 'meas': value '37\\xe92' is not a number "
                                              r"\(it holds bytes that are not UTF-8 text\)"):
        read_numeric_csv(p, ("time", "meas"))


def test_non_utf8_bytes_in_a_comment_column_and_a_bom_are_read(tmp_path):
    p = tmp_path / "USS1.csv"
    p.write_bytes(b"\xef\xbb\xbftime,meas,comment\n1,3752,caf" + LATIN1 + b"\n2,3751,ok\n")
    table = read_numeric_csv(p, ("time", "meas"))
    np.testing.assert_array_equal(table["meas"], [3752, 3751])


def test_non_utf8_intrinsics_split_and_description(tmp_path):
    from virus_nerf.data.ethz import read_intrinsics
    from virus_nerf.data.split import read_split, read_split_ratios

    p = tmp_path / "camera_intrinsics.CSV"
    p.write_bytes(b"cam_id,fx,fy,cx,cy\nCAM1,388,388,320,240\nCAM" + LATIN1 + b",388,388,320,240\n")
    with pytest.raises(DataFormatError, match=r"camera_intrinsics.CSV, row 3, field 'cam_id': cam_id 'CAM\\xe9' "
                                              r"is not CAM<number>"):
        read_intrinsics(p)
    p = tmp_path / "split.csv"
    p.write_bytes(b"CAM1\ntrain\ntr" + LATIN1 + b"in\n")
    with pytest.raises(DataFormatError, match=r"split.csv, row 3, field 'CAM1': label 'tr\\xe9in' is not one of"):
        read_split(p, {1: 2})
    p = tmp_path / "split_description.csv"  # free text in 'info' may be Latin-1: read
    p.write_bytes(b"train,val,test,keep_N_observations,info\n0.6,0.0,0.4,all,r" + LATIN1 + b"sum" + LATIN1 + b"\n")
    assert read_split_ratios(p) == (0.6, 0.0, 0.4)


def write_scene(tmp_path: Path, data: bytes) -> Path:
    p = tmp_path / "scene.json"
    p.write_bytes(data)
    return p


def test_scene_json_non_utf8_list_and_missing_extent(tmp_path):
    from virus_nerf.sim.scene import Scene

    ok = b'{"format": "virus-nerf-scene", "objects": [], "extent_lo": [0, 0, 0], "extent_hi": [1, 1, 1]}'
    assert Scene.load(write_scene(tmp_path, ok)).extent_hi == (1, 1, 1)
    with pytest.raises(DataFormatError, match=r"scene.json, row 2: byte 0xe9 at column 10 is not UTF-8 text"):
        Scene.load(write_scene(tmp_path, b'{"format":\n "virus-n' + LATIN1 + b'rf-scene"}'))
    with pytest.raises(DataFormatError, match=r"scene.json: expected a JSON object \(a virus-nerf scene\), got a list"):
        Scene.load(write_scene(tmp_path, b"[1, 2]"))
    with pytest.raises(DataFormatError, match=r"scene.json, field 'extent_lo': missing; expected the room's lower "
                                              r"corner \[x, y, z\] in metres"):
        Scene.load(write_scene(tmp_path, ok.replace(b'"extent_lo"', b'"extent_low"')))
    with pytest.raises(DataFormatError, match=r"scene.json, field 'extent_hi': \['a', 1\] is not 3 finite numbers"):
        Scene.load(write_scene(tmp_path, ok.replace(b"[1, 1, 1]", b'["a", 1]')))


def pcd_bytes(points: np.ndarray, header_points: int | None = None, data: str = "binary") -> bytes:
    n = len(points) if header_points is None else header_points
    head = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()
    if data == "ascii":
        return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()
    return head + np.asarray(points, dtype=np.float32).tobytes()


@pytest.fixture()
def map_copy(sample_copy) -> Path:
    return sample_copy / "office" / "maps" / "map_balm.pcd"


def test_empty_map_is_refused_when_read(sample_copy, map_copy):
    map_copy.write_bytes(pcd_bytes(np.zeros((0, 3))))
    rec = load_recording(sample_copy, "office")
    with pytest.raises(DataFormatError, match=r"map_balm.pcd: the LiDAR map has no points; expected the room's map"):
        rec.lidar_map()


def test_all_nan_map_is_refused(sample_copy, map_copy):
    map_copy.write_bytes(pcd_bytes(np.full((5, 3), np.nan)))
    with pytest.raises(DataFormatError, match=r"map_balm.pcd: the LiDAR map has no points \(all 5 points are NaN or "
                                              r"infinite\)"):
        load_recording(sample_copy, "office").lidar_map()


def test_map_with_a_garbage_body_is_refused(sample_copy, map_copy):
    rng = np.random.default_rng(0)
    map_copy.write_bytes(pcd_bytes(np.zeros((1000, 3))).replace(bytes(12000), rng.bytes(12000)))
    with pytest.raises(DataFormatError, match=r"map_balm.pcd: point 0 of 1000 \(.*\) lies beyond 10 km of the "
                                              r"origin; expected metres \(a garbage body or wrong units\?\)"):
        load_recording(sample_copy, "office").lidar_map()


@pytest.mark.parametrize("data", ["binary", "ascii"])
def test_truncated_pcd_is_refused(tmp_path, data):
    p = tmp_path / "scan.pcd"
    p.write_bytes(pcd_bytes(np.ones((7, 3)), header_points=10, data=data))
    with pytest.raises(DataFormatError, match=r"scan.pcd: header says 10 points, body holds 7"):
        read_pcd_xyz(p)
    p.write_bytes(pcd_bytes(np.ones((7, 3)), header_points=10)[:-5])  # a partial last point as well
    with pytest.raises(DataFormatError, match=r"scan.pcd: header says 10 points, body holds 6 \(and 7 bytes"):
        read_pcd_xyz(p)


def test_split_ratios_negative_or_all_zero(tmp_path):
    from virus_nerf.data.split import read_split_ratios
    from virus_nerf.errors import UsageError

    p = write(tmp_path, "split_description.csv", "train,val,test\n0.6,-0.1,0.5\n")
    with pytest.raises(DataFormatError, match=r"split_description.csv, row 2, field 'val': ratio -0.1 is negative; "
                                              r"expected non-negative train,val,test ratios with a positive sum"):
        read_split_ratios(p)
    p = write(tmp_path, "split_description.csv", "train,val,test\n0,0,0\n")
    with pytest.raises(DataFormatError, match=r"split_description.csv, row 2, field 'train/val/test': the ratios "
                                              r"sum to 0"):
        read_split_ratios(p)
    p = write(tmp_path, "split_description.csv", "train,val,test\nnan,0,1\n")
    with pytest.raises(DataFormatError, match=r"row 2, field 'train': ratio nan is not finite"):
        read_split_ratios(p)
    with pytest.raises(UsageError, match=r"split ratios \(0, 0, 0\): expected non-negative numbers with a positive"):
        make_split(5, (0, 0, 0))


def test_stacks_of_different_image_sizes_are_refused_in_one_line(sample_copy):
    from PIL import Image

    from virus_nerf.sampler.frames import FrameStore, build_frame_store
    from virus_nerf.sensors.camera import Intrinsics

    intr = sample_copy / "camera_intrinsics.CSV"
    intr.write_text("cam_id,fx,fy,cx,cy,width,height\nCAM1,388,388,320,240,640,480\nCAM3,194,194,160,120,320,240\n")
    meas = sample_copy / "office" / "measurements"
    for k in range(5):
        img = meas / "CAM3_color_image_raw" / f"img{k}.png"
        with Image.open(img) as im:
            im.resize((320, 240)).save(img)
        np.save(meas / "CAM3_aligned_depth_to_color_image_raw" / f"img{k}.npy", np.zeros((240, 320), np.uint16))
    rec = load_recording(sample_copy, "office")  # reading works: each stack agrees with its intrinsics
    with pytest.raises(DataFormatError, match=r"camera_intrinsics.CSV: the stacks' images differ in size \(CAM1 "
                                              r"640x480, CAM3 320x240\); expected one image size for all stacks"):
        build_frame_store(rec, use_cache=False)
    with pytest.raises(ValueError, match=r"CAM1 640x480, CAM3 320x240.*one image size"):
        FrameStore.empty({1: Intrinsics(388, 388, 320, 240), 3: Intrinsics(194, 194, 160, 120, 320, 240)})


@pytest.mark.parametrize("values, field, fragment", [
    ("1e-9,1e-9,320,240", "fx", r"focal length 1e-09 px gives a 180.0 degree field of view over 640 px; expected "
                                r"a field of view of 1 to 170 degrees \(fx from 28 to 36668 px\)"),
    ("388,1e6,320,240", "fy", r"focal length 1e\+06 px gives a 0.0 degree field of view over 480 px"),
    ("388,388,700,240", "cx", r"principal point 700 px lies outside the image \(0 to 640 px\)"),
    ("388,388,320,-3", "cy", r"principal point -3 px lies outside the image \(0 to 480 px\)"),
    ("388,388,320,240,640.7,480", "width", r"image width 640.7 px is not a whole number of pixels"),
    ("388,388,320,240,640,1e9", "height", r"image height 1e\+09 px; expected a size from 1 to 100000 px"),
])
def test_implausible_intrinsics_are_refused(tmp_path, values, field, fragment):
    from virus_nerf.data.ethz import read_intrinsics

    header = "cam_id,fx,fy,cx,cy" + (",width,height" if values.count(",") == 5 else "")
    p = write(tmp_path, "camera_intrinsics.CSV", f"{header}\nCAM1,{values}\n")
    with pytest.raises(DataFormatError, match=rf"camera_intrinsics.CSV, row 2, field '{field}': {fragment}"):
        read_intrinsics(p)


def test_irs_reading_beyond_a_physical_bound_is_refused(tmp_path):
    from virus_nerf.data.ethz import IRS_MAX_PLAUSIBLE_MM

    assert IRS_MAX_PLAUSIBLE_MM == 100_000
    header = "time," + ",".join(f"meas_{k}" for k in range(64)) + "\n"
    ok = "1," + ",".join(["500"] * 64) + "\n"
    bad = "2," + ",".join(["500"] * 10 + ["1e12"] + ["500"] * 53) + "\n"
    p = write(tmp_path, "TOF1.csv", header + ok + bad)
    with pytest.raises(DataFormatError, match=r"TOF1.csv, row 3, field 'meas_10': 1e\+12 mm \(1e\+09 m\) is beyond "
                                              r"any IRS reading \(> 100000 mm = 100 m\); expected millimetres"):
        read_tof(p)
    p = write(tmp_path, "TOF1.csv", header + ok + bad.replace("1e12", "99999"))  # far but possible: kept
    assert read_tof(p)[1].shape == (2, 8, 8)


def png_header_only(width: int, height: int) -> bytes:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0")) + chunk(b"IEND", b"")


def test_png_claiming_a_huge_size_is_refused(sample_copy, tmp_path):
    from virus_nerf.data.images import image_size, read_rgb
    from virus_nerf.sensors.camera import Intrinsics

    p = tmp_path / "img0.png"
    p.write_bytes(png_header_only(30000, 30000))
    expected = (r"img0.png: image header claims 30000x30000 px \(900 Mpx\), beyond the 179 Mpx an image may have; "
                r"corrupt file\?")
    with pytest.raises(DataFormatError, match=expected):
        image_size(p)
    with pytest.raises(DataFormatError, match=expected):
        read_rgb(p, Intrinsics(388, 388, 320, 240))
    (sample_copy / "office" / "measurements" / "CAM1_color_image_raw" / "img0.png").write_bytes(p.read_bytes())
    with pytest.raises(DataFormatError, match=r"CAM1_color_image_raw/img0.png: image header claims 30000x30000"):
        load_recording(sample_copy, "office")


def test_topics_file_stack_id_superscript_and_missing_stacks(tmp_path):
    from virus_nerf.data.bags.topics import read_topics
    from virus_nerf.errors import ConfigError

    f = tmp_path / "t.toml"
    f.write_text('[stacks."\u00b9"]\ncolor = "/c"\n'
                 "camera_in_lidar = { translation = [0, 0, 0], rotation_xyzw = [0, 0, 0, 1] }\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"t.toml, key 'stacks.\u00b9': stack id '\u00b9': expected a non-negative "
                                          r"integer \(digits 0-9\)"):
        read_topics(f)
    f.write_text("[sync]\nuss_tolerance_s = 0.05\n")
    cfg = read_topics(f)
    assert sorted(cfg.stacks) == [1, 3]
    assert cfg.notes == (f"{f}: no [stacks] section: the ETHZ robot's stacks 1 and 3 are used (/CAM1/color/image_raw, "
                         "/CAM3/color/image_raw, ...)",)


def test_bare_mcap_file_is_read(sample_dir, tmp_path):
    pytest.importorskip("rosbags")
    from virus_nerf.data.bags.reader import BagReader
    from virus_nerf.data.bags.writer import write_bag

    folder = write_bag(sample_dir, tmp_path / "bag", ros_version=2, storage="mcap", lidar_topic=None)
    bare = tmp_path / "office.mcap"
    shutil.copyfile(next(folder.glob("*.mcap")), bare)
    with BagReader(bare) as reader:
        assert reader.ros_version == 2
        assert reader.topics["/USS1"].count == 5
        assert [m.msg.meas for m in reader.iter_topic("/USS1")][0] == 3752
    bare.with_suffix(".zip").write_bytes(b"x")
    with pytest.raises(DataFormatError, match=r"office.zip: expected a ROS 1 .bag file, a ROS 2 bag folder "
                                              r"\(metadata.yaml \+ .db3/.mcap\) or a single ROS 2 .mcap/.db3 file"):
        BagReader(bare.with_suffix(".zip"))
    truncated = tmp_path / "cut.mcap"
    truncated.write_bytes(bare.read_bytes()[:300])
    with pytest.raises(DataFormatError, match=r"cut.mcap: cannot be read"):
        with BagReader(truncated):
            pass


def test_pcd_header_without_data_line_is_refused(tmp_path):
    p = tmp_path / "scan.pcd"
    p.write_bytes(pcd_bytes(np.ones((3, 3)), data="ascii").replace(b"DATA ascii\n", b""))
    with pytest.raises(DataFormatError, match=r"scan.pcd: not a readable PCD file: no DATA line in the header.s "
                                              r"first 10 lines"):
        read_pcd_xyz(p)


def test_bare_mcap_imports_and_the_report_says_the_ethz_stacks_were_used(sample_dir, tmp_path):
    pytest.importorskip("rosbags")
    from virus_nerf.data.bags.importer import import_bag
    from virus_nerf.data.bags.writer import write_bag

    folder = write_bag(sample_dir, tmp_path / "bag", ros_version=2, storage="mcap", lidar_topic=None)
    bare = tmp_path / "office.mcap"
    shutil.copyfile(next(folder.glob("*.mcap")), bare)
    topics = tmp_path / "t.toml"
    topics.write_text("[sync]\nuss_tolerance_s = 0.15\n[lidar]\ntopic = ''\n")
    report = import_bag(bare, tmp_path / "out", topics=topics, poses="csv",
                        poses_file=sample_dir / "office" / "poses" / "poses_lidar_balm_sync1.csv")
    assert report.room == "office" and report.samples == {1: 5, 3: 5}
    assert f"  note: {topics}: no [stacks] section: the ETHZ robot's stacks 1 and 3 are used" in report.summary()
    rec = load_recording(tmp_path / "out", "office")
    np.testing.assert_array_equal(rec.stacks[1].uss_range, load_recording(sample_dir, "office").stacks[1].uss_range)


def test_sensor_rows_on_another_clock_are_refused_with_row_and_offset(sample_copy):
    """Issue 30: rows are matched to the camera's by index, so a USS file whose times are 5000 s
    off (another clock) is refused, not paired silently."""
    path = sample_copy / "office" / "measurements" / "USS1.csv"
    lines = path.read_text().splitlines()
    head = lines[0].split(",")
    t = head.index("time")
    for k in range(1, len(lines)):  # every row on a clock 5000 s ahead
        cells = lines[k].split(",")
        cells[t] = f"{float(cells[t]) + 5000.0:.6f}"
        lines[k] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=r"USS1.csv, row 2, field 'time': time .* is \+5000.000 s from the "
                                              r"camera's .*5 of 5 rows"):
        load_recording(sample_copy, "office")


def test_a_camera_pose_that_jumps_is_refused_with_its_row(sample_copy):
    """Issue 30: one pose at x = 1e6 m (a GPS glitch) would grow the box to fit it."""
    path = sample_copy / "office" / "poses" / "poses_cam_balm_sync3.csv"
    lines = path.read_text().splitlines()
    head = lines[0].split(",")
    cells = lines[3].split(",")
    cells[head.index("x")] = "1000000.0"
    lines[3] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=r"poses_cam_balm_sync3.csv, row 4, field 'x': the camera jumps "
                                              r"\d+\.\d+ m in 0.208 s"):
        load_recording(sample_copy, "office")


def test_timestamps_in_nanoseconds_are_refused_with_file_row_and_field(sample_copy, tmp_path):
    """A recording whose tables hold nanoseconds (1.7e18) would load and score garbage (its
    LiDAR scans, named in seconds, match no frame): refused as the Mapper refuses a frame's time."""
    from virus_nerf.data.bags.odometry import csv_track

    p = write(tmp_path, "poses.csv", POSE_HEADER + "1702374040,0,0,0,0,0,0,1\n1702374040500000000,0,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match=r"poses.csv, row 3, field 'time': timestamp 1.7023740405e\+18 beyond "
                                              r"1e\+11 s \(the year 5138\); expected seconds, not milli-, micro- or "
                                              r"nanoseconds"):
        read_poses(p)
    uss = sample_copy / "office" / "measurements" / "USS1.csv"
    lines = uss.read_text().splitlines()
    t, rest = lines[1].split(",", 1)
    lines[1] = f"{int(float(t) * 1e9)},{rest}"
    uss.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFormatError, match=r"USS1.csv, row 2, field 'time': timestamp .* expected seconds"):
        load_recording(sample_copy, "office")
    track = write(tmp_path, "track.txt", "# TUM\n1702374040000 0 0 0 0 0 0 1\n")
    with pytest.raises(DataFormatError, match=r"track.txt, row 2, field 'time': timestamp 1702374040000.0 beyond"):
        csv_track(track)


def test_a_pose_track_names_the_field_that_is_wrong(tmp_path):
    """--poses csv / a TUM file: a NaN names its field, a quaternion off unit norm says its norm."""
    from virus_nerf.data.bags.odometry import csv_track

    p = write(tmp_path, "p.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,nan,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match=r"p.csv, row 3, field 'y': nan is not a finite number"):
        csv_track(p)
    p = write(tmp_path, "q.csv", POSE_HEADER + "1,0,0,0,0,0,0,1\n2,0,0,0,0,0,0,2\n")
    with pytest.raises(DataFormatError, match=r"q.csv, row 3, field 'qx/qy/qz/qw': quaternion \(0.0, 0.0, 0.0, 2.0\) "
                                              r"has norm 2; expected a unit quaternion"):
        csv_track(p)
    (tmp_path / "dir.csv").mkdir()
    with pytest.raises(DataFormatError, match=r"dir.csv: is a directory; expected a pose file"):
        csv_track(tmp_path / "dir.csv")


def test_a_folder_where_a_table_should_be_is_named_as_a_folder(sample_copy):
    uss = sample_copy / "office" / "measurements" / "USS1.csv"
    uss.unlink()
    uss.mkdir()
    with pytest.raises(DataFormatError, match=r"USS1.csv: is a directory; expected a CSV file"):
        load_recording(sample_copy, "office")


def test_a_tof_table_in_metres_is_refused(tmp_path):
    """Every target reading below 10 mm (no VL53L5CX reads under 20 mm) is a table in metres: its
    zones would all read as invalid and training would go on without the IRS."""
    header = "time," + ",".join(f"meas_{k}" for k in range(64)) + "\n"
    metres = header + "".join(f"{t}," + ",".join(["1.523"] * 62 + ["0", "3.9"]) + "\n" for t in (1, 2))
    with pytest.raises(DataFormatError, match=r"TOF1.csv: every reading is below 10 mm \(the largest 3.9\); expected "
                                              r"millimetres \(the file holds metres\?\)"):
        read_tof(write(tmp_path, "TOF1.csv", metres))
    mm = header + "1," + ",".join(["0"] * 62 + ["25", "250"]) + "\n"  # targets at 25 and 250 mm: millimetres
    assert np.nanmax(read_tof(write(tmp_path, "TOF3.csv", mm))[1]) == 0.25  # 25 mm is under the 0.1 m validity


@pytest.mark.parametrize("name", ["1702374040.5.pcd", "scan_0.pcd"])
def test_a_lidar_scan_not_named_by_its_time_in_nanoseconds_is_refused(sample_copy, name):
    """lidars/filtered/<seconds>.<9 digits of nanoseconds>.pcd: "…​.5.pcd" would read as 5 ns and
    "scan_0.pcd" would be left out, each scoring the LiDAR against the wrong scans or none."""
    folder = sample_copy / "office" / "lidars" / "filtered"
    first = sorted(folder.glob("*.pcd"))[0]
    first.rename(folder / name)
    with pytest.raises(DataFormatError, match=rf"{name}: LiDAR scan name: expected <seconds>.<nanoseconds, 9 digits>"):
        load_recording(sample_copy, "office")


def _shift_times(path: Path, seconds: float) -> None:
    """Every row of a CSV with a `time` column `seconds` later."""
    lines = path.read_text().splitlines()
    t = lines[0].split(",").index("time")
    for k in range(1, len(lines)):
        cells = lines[k].split(",")
        cells[t] = repr(float(cells[t]) + seconds)
        lines[k] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(("name", "seconds", "refused"), [
    ("measurements/USS1.csv", 0.3, True),  # the reviewer's offset: the reader took it silently at 0.5 s
    ("measurements/TOF3.csv", -0.2, True),
    ("poses/poses_lidar_balm_sync1.csv", 0.2, True),  # the LiDAR's poses are the camera's rows too
    ("measurements/USS1.csv", 0.1, False),  # within 0.15 s: one sample (import-bag's USS tolerance)
])
def test_a_sensor_file_off_the_camera_by_more_than_0_15_s_is_refused(sample_copy, name, seconds, refused):
    """Row i of a stack's files is one sample: a file 0.2-0.3 s off the camera's times (a reading
    the robot took 10-15 cm away at 0.5 m/s) is refused with its row and offset; 0.1 s is read."""
    _shift_times(sample_copy / "office" / name, seconds)
    if not refused:
        load_recording(sample_copy, "office")
        return
    with pytest.raises(DataFormatError, match=rf"{Path(name).name}, row 2, field 'time': time .* is \{seconds:+.3f} s "
                                              r"from the camera's .* \(5 of 5 rows are more than 0.15 s off\)"):
        load_recording(sample_copy, "office")


def test_a_stack_on_another_clock_leaves_the_test_points_with_stack_1_alone(sample_copy):
    """Stack 3's four files 1 s later (its own clock): no stack-3 frame lies within 0.15 s of a
    stack-1 test frame, so the sample's 2 test points go without one, and a warning says so."""
    from virus_nerf.evaluation.testpoints import make_test_points, recording_warnings

    room = sample_copy / "office"
    for name in ("poses/poses_cam_balm_sync3.csv", "poses/poses_lidar_balm_sync3.csv", "measurements/USS3.csv",
                 "measurements/TOF3.csv"):
        _shift_times(room / name, 1.0)
    rec = load_recording(sample_copy, "office")
    points = make_test_points(rec)
    assert [p.index3 for p in points] == [None, None]
    assert "2 of 2 test points have no stack-3 frame within 0.15 s: they are scored with stack 1's cameras, USS " \
           "and IRS alone" in recording_warnings(rec)


def test_a_lidar_that_stops_early_scores_only_the_test_points_it_scanned(sample_copy):
    """The sample's LiDAR scans at -0.036 .. 0.964 s from stack 1's first frame; its test frames are
    at 0.208 and 0.624 s. With the scans after 0.3 s removed, the test point at 0.624 s has no scan
    within 0.15 s (the nearest, 0.264 s, is 0.36 s away): its LiDAR scan is empty, not the one
    taken 0.36 s earlier, and a warning counts it."""
    from virus_nerf.evaluation.sensor_scans import lidar_scan_2d
    from virus_nerf.evaluation.testpoints import make_test_points, recording_warnings

    full = load_recording(sample_copy, "office")
    t0 = full.stacks[1].times[0]
    assert lidar_scan_2d(full, make_test_points(full)[1]).points.shape[0] > 100  # with every scan
    for p in (sample_copy / "office" / "lidars" / "filtered").glob("*.pcd"):
        if float(p.stem) > t0 + 0.3:
            p.unlink()
    rec = load_recording(sample_copy, "office")
    first, second = make_test_points(rec)
    assert np.round([first.time - t0, second.time - t0], 3).tolist() == [0.208, 0.624]
    assert len(lidar_scan_2d(rec, first).points) > 100
    assert lidar_scan_2d(rec, second).points.shape == (0, 2)
    assert "1 of 2 test points have no LiDAR scan within 0.15 s: the LiDAR row leaves them out" in \
        recording_warnings(rec)
    assert recording_warnings(full) == []


def test_quaternions_written_w_x_y_z_are_warned_of(sample_copy):
    """The LiDAR poses with their quaternions written w,x,y,z under the qx,qy,qz,qw header read as
    half turns (the LiDAR upside down): the recording reads, and a warning names the likely cause."""
    from virus_nerf.evaluation.testpoints import recording_warnings

    for s in (3, 1):
        path = sample_copy / "office" / "poses" / f"poses_lidar_balm_sync{s}.csv"
        lines = path.read_text().splitlines()
        for k in range(1, len(lines)):
            c = lines[k].split(",")
            lines[k] = ",".join(c[:4] + [c[7], c[4], c[5], c[6]])  # w, x, y, z
        path.write_text("\n".join(lines) + "\n")
        warnings = recording_warnings(load_recording(sample_copy, "office"))
        if s == 3:  # one stack's file alone: half of all the poses, said of that file
            assert ("the up axis of 100% of stack 3's LiDAR poses (poses/poses_lidar_*sync3.csv) points below the "
                    "horizon: an upside-down LiDAR, or quaternions in w,x,y,z order? They are read as qx,qy,qz,qw") \
                in warnings
    assert ("the up axis of 100% of the LiDAR poses (poses/poses_lidar_*) points below the horizon: an upside-down "
            "LiDAR, or quaternions in w,x,y,z order? They are read as qx,qy,qz,qw") in warnings
    assert not any("stack 3's LiDAR poses" in w for w in warnings)  # both: said once, of all


def test_images_under_other_names_are_named_not_counted_as_none(sample_copy):
    """JPEG frames img0.jpg.. where the layout reads img0.png..: the folder is named with what it
    holds, not counted as 0 images among the stack's sample counts."""
    folder = sample_copy / "office" / "measurements" / "CAM1_color_image_raw"
    for p in sorted(folder.glob("img*.png")):
        p.rename(p.with_suffix(".jpg"))
    with pytest.raises(DataFormatError, match=r"CAM1_color_image_raw: no img<i>.png among its 5 files \(e.g. "
                                              r"img0.jpg\); expected them named img0.png, img1.png, ...$"):
        load_recording(sample_copy, "office")


def test_a_recording_without_stack_1_names_the_way_to_map_it(sample_copy):
    """Only stack 3 (a robot with one stack, numbered 3): the scores need stack 1's test frames; the
    refusal says how to map it anyway."""
    from virus_nerf.evaluation.testpoints import make_test_points

    rec = load_recording(sample_copy, "office", stacks=[3])
    with pytest.raises(DataFormatError, match=r"measurements: stack 1 \(USS1.csv, CAM1\) is needed for the test "
                                              r"points; train --gt none maps the recording without scoring it, or "
                                              r"number the main stack's files 1$"):
        make_test_points(rec)


def test_a_stack_whose_poses_are_in_another_frame_is_warned_of(sample_copy):
    """Stack 3's pose files 0.5 m along x (another world frame): both stacks' files hold the one
    LiDAR's poses, which agree to 0.08 mm in the real sample; 0.50 m apart is said."""
    from virus_nerf.evaluation.testpoints import recording_warnings

    assert recording_warnings(load_recording(sample_copy, "office")) == []
    for kind in ("cam", "lidar"):
        path = sample_copy / "office" / "poses" / f"poses_{kind}_balm_sync3.csv"
        lines = path.read_text().splitlines()
        for k in range(1, len(lines)):
            c = lines[k].split(",")
            lines[k] = ",".join([c[0], repr(float(c[1]) + 0.5)] + c[2:])
        path.write_text("\n".join(lines) + "\n")
    assert recording_warnings(load_recording(sample_copy, "office")) == [
        "stack 3's LiDAR poses lie a median 0.50 m from stack 1's at the same times (one LiDAR: they should agree): "
        "are the stacks' files on different clocks or in different frames?"]


def test_a_stack_without_lidar_poses_leaves_the_lidar_placed_by_the_other(sample_copy):
    """Stack 1's poses_lidar file missing: the LiDAR's track is stack 3's poses alone (before, its
    NaN rows were slerped into the track and the scores crashed in an SVD); both missing while the
    scans are there: refused in one line naming the poses folder."""
    full = load_recording(sample_copy, "office")
    (sample_copy / "office" / "poses" / "poses_lidar_balm_sync1.csv").unlink()
    rec = load_recording(sample_copy, "office")
    t3 = rec.stacks[3].times
    for t in (t3[0], t3[len(t3) // 2], 0.5 * (t3[1] + t3[2])):  # a stack-3 sample, and between two
        pose = rec.lidar_pose_at(float(t))
        assert np.isfinite(pose).all() and np.allclose(pose[:3, 3], full.lidar_pose_at(float(t))[:3, 3], atol=0.01)
    np.testing.assert_array_equal(rec.lidar_pose_at(float(t3[3])), rec.stacks[3].lidar_to_world[3])
    (sample_copy / "office" / "poses" / "poses_lidar_balm_sync3.csv").unlink()
    with pytest.raises(DataFormatError, match=r"office/poses: no LiDAR poses \(poses_lidar_\*sync<id>.csv\) for the "
                                              r"\d+ LiDAR scans in lidars/filtered"):
        load_recording(sample_copy, "office")


def test_rgbd_on_a_recording_without_depth_images_is_refused_before_the_run(sample_copy, tmp_path):
    from helpers import run_cli

    shutil.rmtree(sample_copy / "office" / "measurements" / "CAM3_aligned_depth_to_color_image_raw")
    code, _, err = run_cli(["train", "--data", sample_copy, "--room", "office", "--out", tmp_path / "run",
                            "--max-steps", 2, "--gt", "none", "--quiet", "--sensors", "camera,uss,irs,rgbd"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "CAM3_aligned_depth_to_color_image_raw: missing: this recording has no depth images" in err
    assert not (tmp_path / "run").exists()


def test_a_uss_table_in_metres_or_nanoseconds_is_refused(tmp_path):
    """USS<id>.csv holds the echo time in microseconds (5000 a metre): 0.648 (metres) read as an echo
    of 0.13 mm, 3.752e6 (nanoseconds) as no echo at all, both silently before."""
    def table(values):
        return write(tmp_path, "USS1.csv", "time,meas\n" + "".join(f"{k},{v}\n" for k, v in enumerate(values)))

    t, r = read_uss(table([3752, 50000, 0, 9802]))  # microseconds, a no-echo code and a 0: read
    np.testing.assert_allclose(r, [0.7504, np.nan, np.nan, 1.9604])
    with pytest.raises(DataFormatError, match=r"USS1.csv: every echo time is below 100 us, the sensor's nearest range "
                                              r"of 2 cm \(the largest 1.96\); expected microseconds \(the file holds "
                                              r"metres\?\)$"):
        read_uss(table([0.7504, 1.96, 0, 50000]))
    with pytest.raises(DataFormatError, match=r"USS1.csv, row 3, field 'meas': 3.752e\+06 is beyond any echo time "
                                              r"\(> 500000 us; the sensor's no-echo code is 50000\); expected "
                                              r"microseconds \(the file holds nanoseconds\?\)$"):
        read_uss(table([50000, 3752000, 9802000]))


def test_a_camera_calibrated_twice_is_refused_with_its_row(tmp_path):
    p = write(tmp_path, "camera_intrinsics.CSV", "cam_id,fx,fy,cx,cy\nCAM1,380,380,320,240\nCAM3,381,381,321,241\n"
                                                 "CAM1,300,300,320,240\n")
    with pytest.raises(DataFormatError, match=r"row 4, field 'cam_id': cam_id CAM1 again \(an earlier row has it\); "
                                              r"expected one row per camera$"):
        read_intrinsics(p)


def test_a_16_bit_image_is_refused_not_read_as_white(tmp_path):
    """PIL's convert("RGB") clips a 16-bit grey PNG's values to 255: every pixel white, silently."""
    from PIL import Image

    from virus_nerf.data.images import read_rgb
    from virus_nerf.sensors.camera import Intrinsics

    grey = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1000)
    Image.fromarray(grey).save(tmp_path / "img0.png")  # mode I;16
    with pytest.raises(DataFormatError, match=r"img0.png: image mode I;16 \(16-bit grey\); expected 8-bit colour or "
                                              r"grey \(RGB, RGBA, P, L\)$"):
        read_rgb(tmp_path / "img0.png", Intrinsics(8, 8, 3.5, 2.5, width=8, height=6))
    Image.fromarray((grey // 256).astype(np.uint8)).save(tmp_path / "img1.png")  # 8-bit grey: read, as RGB
    rgb = read_rgb(tmp_path / "img1.png", Intrinsics(8, 8, 3.5, 2.5, width=8, height=6))
    assert rgb.shape == (6, 8, 3) and (rgb[..., 0] == grey // 256).all() and (rgb[..., 2] == grey // 256).all()


@pytest.mark.parametrize("where", ["split/split.csv", "poses/poses_lidar_balm_sync3.csv",
                                   "measurements/CAM3_aligned_depth_to_color_image_raw", "lidars/filtered"])
def test_an_optional_file_behind_a_broken_link_is_refused_not_taken_for_absent(sample_copy, where):
    """A split file behind a link to an unmounted share gave the default split, silently (other
    test frames); a LiDAR pose file or depth folder so, no LiDAR poses or no depth."""
    path = sample_copy / "office" / where
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink()
    path.symlink_to("/mnt/unmounted/share/x")
    with pytest.raises(DataFormatError, match=rf"office/{where}: a link to /mnt/unmounted/share/x, which does not "
                                              r"exist; expected the (file|folder) itself \(or nothing here\)$"):
        load_recording(sample_copy, "office")
    path.unlink()
    path.mkdir() if where.endswith(".csv") else path.write_text("x")  # the other kind where one belongs
    want = "is a folder; expected a file" if where.endswith(".csv") else "is a file; expected a folder"
    with pytest.raises(DataFormatError, match=rf"office/{where}: {want} \(or nothing here\)$"):
        load_recording(sample_copy, "office")


def test_an_empty_pcd_and_a_bad_header_line_are_named_in_short(tmp_path):
    """pypcd4's header model is pydantic's: its message ran over several errors and a web link."""
    head = "VERSION 0.7\nFIELDS x y z\n{size}TYPE {t} F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n" \
           "POINTS 1\nDATA ascii\n1 2 3\n"
    (tmp_path / "empty.pcd").write_bytes(b"")
    with pytest.raises(DataFormatError, match=r"empty.pcd: empty file; expected a PCD file"):
        read_pcd_xyz(tmp_path / "empty.pcd")
    (tmp_path / "q.pcd").write_text(head.format(size="SIZE 4 4 4\n", t="Q"))
    with pytest.raises(DataFormatError, match=r"q.pcd: not a readable PCD file \(expected ascii/binary/binary_compressed\): "
                                              r"header TYPE, value 1: Input should be 'F', 'U' or 'I' \(got 'Q'\)$"):
        read_pcd_xyz(tmp_path / "q.pcd")
    (tmp_path / "nosize.pcd").write_text(head.format(size="", t="F"))
    with pytest.raises(DataFormatError, match=r"nosize.pcd: .*: header line SIZE missing$"):
        read_pcd_xyz(tmp_path / "nosize.pcd")
    (tmp_path / "ok.pcd").write_text(head.format(size="SIZE 4 4 4\n", t="F"))
    np.testing.assert_array_equal(read_pcd_xyz(tmp_path / "ok.pcd"), [[1, 2, 3]])


def test_a_split_made_from_ratios_without_test_frames_names_the_ratios_file(sample_copy):
    from virus_nerf.evaluation.testpoints import require_test_points

    split = sample_copy / "office" / "split"
    (split / "split.csv").unlink()
    (split / "split_description.csv").write_text("train,val,test\n1,0,0\n")
    with pytest.raises(DataFormatError, match=r"office/split/split_description.csv \(the ratios the split was made "
                                              r"from; split.csv absent\), field 'CAM1': no CAM1 rows labelled 'test'"):
        require_test_points(load_recording(sample_copy, "office"))


def test_a_recording_with_a_lidar_map_but_no_scans_says_the_lidar_row_stays_empty(sample_copy):
    from virus_nerf.evaluation.testpoints import recording_warnings

    assert recording_warnings(load_recording(sample_copy, "office")) == []
    for p in (sample_copy / "office" / "lidars" / "filtered").iterdir():
        p.unlink()
    assert recording_warnings(load_recording(sample_copy, "office")) == [
        f"{sample_copy / 'office' / 'lidars' / 'filtered'}: no LiDAR scans, though the recording has a LiDAR map: "
        "the LiDAR's row stays empty (scans named <seconds>.<nanoseconds>.pcd)"]
