"""Bad input gets a clear error naming file, row and field; nothing in the input is changed."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from virus_nerf.data.csvtable import read_numeric_csv
from virus_nerf.data.ethz import load_recording, read_poses, read_tof
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
