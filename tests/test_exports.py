"""`virus-nerf export`: every format read back by an independent reader (PIL for PGM/PNG, a
small YAML parser, numpy on the PLY and PCD binary layouts, json/np.load) with values known by
hand on analytic inputs, and a tiny trained run exported end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, tiny_train_config
from PIL import Image

from virus_nerf.exports import clouds, grid3d
from virus_nerf.maps import esdf
from virus_nerf.maps import occupancy as maps

# ------------------------------------------------------------------ independent readers


def read_yaml(path: Path) -> dict:
    """The flat map_server YAML: `key: scalar` and `key: [a, b, c]` lines, '#' comments."""
    doc = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        key, _, value = line.partition(":")
        value = value.strip()
        if value.startswith("["):
            doc[key.strip()] = [float(v) for v in value.strip("[]").split(",")]
        else:
            try:
                doc[key.strip()] = float(value)
            except ValueError:
                doc[key.strip()] = value
    return doc


def map_value_at(yaml_path: Path, x: float, y: float) -> tuple[int, dict]:
    """Pixel value of a map_server map at world (x, y), as map_server places the image."""
    doc = read_yaml(yaml_path)
    img = np.asarray(Image.open(yaml_path.parent / doc["image"]))
    res, (ox, oy, _) = doc["resolution"], doc["origin"]
    col = int(math.floor((x - ox) / res))
    row = img.shape[0] - 1 - int(math.floor((y - oy) / res))
    return int(img[row, col]), doc


def read_ply(path: Path) -> np.ndarray:
    """Binary little-endian PLY with one vertex element -> structured array."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    kinds = {"float": "<f4", "uchar": "u1"}
    n, fields = 0, []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts[0] == "property":
            fields.append((parts[2], kinds[parts[1]]))
    arr = np.frombuffer(raw[end:], dtype=fields)
    assert len(arr) == n
    return arr


def read_pcd(path: Path) -> np.ndarray:
    """Binary PCD (DATA binary) -> structured array, from the header's FIELDS/SIZE/TYPE/COUNT."""
    raw = path.read_bytes()
    head, pos = {}, 0
    while True:
        nl = raw.index(b"\n", pos)
        line = raw[pos:nl].decode("ascii").strip()
        pos = nl + 1
        if line and not line.startswith("#"):
            key, *vals = line.split()
            head[key] = vals
            if key == "DATA":
                break
    assert head["DATA"] == ["binary"], head["DATA"]
    dt = [(f, {"F": "<f", "U": "<u", "I": "<i"}[t] + s) for f, s, t in zip(head["FIELDS"], head["SIZE"], head["TYPE"],
                                                                           strict=True)]
    arr = np.frombuffer(raw[pos:], dtype=dt, count=int(head["POINTS"][0]))
    return arr


# ------------------------------------------------------------------ analytic inputs


def test_probability_map_of_an_analytic_grid(tmp_path):
    # grid box 4 x 2 x 1 m, 8 x 4 x 2 cells of 0.5 m; p = 0.1 everywhere except a block of 2 cells,
    # ix 2..3, iy 1, iz 1 (x in [1, 2), y in [0.5, 1), z in [0.5, 1)) at p = 0.9: 4 x 2 map pixels of 0.25 m
    prob = np.full((8, 4, 2), 0.1)
    prob[2:4, 1, 1] = 0.9
    lo, hi = np.zeros(2), np.array([4.0, 2.0])
    p = maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), height=0.75, band=0.1, lo=lo, hi=hi, resolution=0.25)
    assert p.shape == (16, 8)
    assert np.all(p[4:8, 2:4] == 0.9) and np.count_nonzero(p == 0.9) == 8 and np.all(p[p != 0.9] == 0.1)
    # a slice through the lower layer never sees the block; a wide band takes the maximum of both
    assert np.all(maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 0.25, 0.1, lo, hi, 0.25) == 0.1)
    assert np.count_nonzero(maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 0.5, 0.25, lo, hi, 0.25) == 0.9) == 8
    # at 0.4 m the upper layer's centre (0.75 m) lies 0.35 m off: outside a 0.2 m band, on a 0.35 m one
    assert np.all(maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 0.4, 0.2, lo, hi, 0.25) == 0.1)
    assert np.count_nonzero(maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 0.4, 0.35, lo, hi, 0.25) == 0.9) == 8
    # a raster larger than the grid: no cell knows the outside pixels (NaN), nor a height above the box
    big = maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 0.75, 0.1, np.array([-1.0, 0]), hi, 0.25)
    assert big.shape == (20, 8) and np.isnan(big[:4]).all() and np.isfinite(big[4:]).all()
    assert np.all(big[8:12, 2:4] == 0.9)
    assert np.isnan(maps.probability_slice(prob, (0, 0, 0), (4, 2, 1), 1.5, 0.1, lo, hi, 0.25)).all()
    # ... and the raw map serves them as unknown even where a sensor looked (a raster rounded up past the box)
    assert np.array_equal(np.unique(maps.raw_map(big, np.array([-1.0, 0]), 0.25).image[:, :4]), [255])

    # a sensor looked everywhere but at the column x in [3.75, 4) m
    known = np.ones(p.shape, dtype=bool)
    known[15, :] = False
    maps.write_map_server(maps.raw_map(p, lo, 0.25, known), tmp_path, "prob")
    # map_server's raw mode serves a pixel of 0..100 as itself, any other as -1 (unknown)
    for (x, y), want in {(1.5, 0.75): 90, (1.01, 0.51): 90, (0.2, 0.2): 10, (3.7, 1.9): 10, (2.1, 0.75): 10,
                         (3.9, 1.9): -1, (3.76, 0.1): -1}.items():
        value, doc = map_value_at(tmp_path / "prob.yaml", x, y)
        assert doc["negate"] == 0 and doc["mode"] == "raw"
        assert (value if value <= 100 else -1) == want, (x, y)
    assert doc["image"] == "prob.pgm" and doc["resolution"] == 0.25 and doc["origin"] == [0.0, 0.0, 0.0]
    assert doc["occupied_thresh"] == 0.65 and doc["free_thresh"] == 0.196
    assert Image.open(tmp_path / "prob.pgm").size == (16, 8)


class _OrangeWall:
    """A model stand-in for the export's renderer: an opaque orange wall at x = 3 m (R, G, B 1.0,
    0.5, 0.0), nothing elsewhere; `render` returns D (the depth weighted by opacity) and A as the
    field's renderer does."""

    device, min_opacity = "cpu", 0.5

    def render(self, origins, directions, generator=None):
        from types import SimpleNamespace

        import torch

        toward = directions[:, 0] > 1e-6
        t = torch.where(toward, (3.0 - origins[:, 0]) / directions[:, 0].clamp(min=1e-6), torch.zeros_like(origins[:, 0]))
        opacity = toward.to(origins.dtype)
        rgb = torch.tensor([1.0, 0.5, 0.0]).expand(len(origins), 3) * opacity[:, None]
        return SimpleNamespace(depth=t * opacity, opacity=opacity, rgb=rgb), None


def test_the_surface_cloud_lies_on_the_rendered_surface_in_its_colours():
    """cloud.pcd/ply's points: each training pixel's ray to its rendered depth, coloured by the
    rendered colour, RGB: on the wall every point has x = 3 m and colour (255, 128, 0); the rays
    that see nothing give no point."""
    from types import SimpleNamespace

    from virus_nerf.exports.views import surface_cloud
    from virus_nerf.sensors.camera import Intrinsics

    cams = []
    for yaw in (0.0, 0.6, np.pi):  # looking at the wall, at it obliquely, away from it
        fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = np.cross([0, 0, -1.0], fwd), [0, 0, -1.0], fwd, (0.5, 0.2, 1.0)
        cams.append(pose)
    stack = SimpleNamespace(intrinsics=Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48), cam_to_world=np.stack(cams),
                            indices=lambda split: np.arange(3))
    points, colours = surface_cloud(_OrangeWall(), SimpleNamespace(stacks={1: stack}), max_points=600, image_scale=1.0)
    assert 200 < len(points) <= 400  # two of three frames see the wall
    np.testing.assert_allclose(points[:, 0], 3.0, atol=1e-5)
    assert (colours == [255, 128, 0]).all()


def test_esdf_of_one_occupied_pixel_is_the_distance_to_it(tmp_path):
    occ = np.zeros((11, 13), dtype=bool)
    occ[4, 6] = True
    d = esdf.signed_distance(occ, 0.1)
    r, c = np.mgrid[0:11, 0:13]
    want = 0.1 * np.hypot(r - 4, c - 6)
    want[4, 6] = -0.1  # inside: minus the distance to the nearest free pixel
    np.testing.assert_allclose(d, want, atol=1e-6)
    esdf.write_esdf(esdf.DistanceField2D(d, 0.1, (-1.0, 2.0)), tmp_path)
    back = np.load(tmp_path / "esdf.npy")
    assert back.dtype == np.float32 and back.shape == (11, 13)
    doc = read_yaml(tmp_path / "esdf.yaml")
    assert doc["data"] == "esdf.npy" and doc["resolution"] == 0.1 and doc["origin"] == [-1.0, 2.0, 0.0]
    # world point of the obstacle pixel centre: x = ox + (6 + 0.5) res, y = oy + (11 - 1 - 4 + 0.5) res
    row = 11 - 1 - int((2.0 + 6.5 * 0.1 - 2.0) / 0.1)
    assert back[row, int((-1.0 + 0.65 + 1.0) / 0.1)] == pytest.approx(-0.1)
    png = np.asarray(Image.open(tmp_path / "esdf.png"))
    assert png.shape == (11, 13, 3) and png[4, 6, 0] < 128 < png[0, 0, 0]
    d[0, :] = np.nan  # a row no sensor looked at: blue in the preview, not the black of "deep inside"
    esdf.write_esdf(esdf.DistanceField2D(d, 0.1, (-1.0, 2.0)), tmp_path / "unseen")
    png = np.asarray(Image.open(tmp_path / "unseen" / "esdf.png"))
    assert (png[0] == esdf.UNKNOWN_RGB).all() and (png[1:, :, 0] == png[1:, :, 2]).all()
    assert np.all(np.isinf(esdf.signed_distance(np.zeros((3, 3), bool), 0.1)))  # no obstacle: infinitely far


def test_grid3d_npy_and_sidecar_locate_cells(tmp_path):
    logodds = np.full((4, 3, 2), -2.0, dtype=np.float32)
    logodds[1, 2, 0] = 3.0
    prob = 1 / (1 + np.exp(-logodds))
    info = grid3d.Grid3DInfo(lo=(-1.0, 0.0, 0.0), hi=(1.0, 1.5, 1.0), resolution=(4, 3, 2), cell_size=(0.5, 0.5, 0.5))
    observed = np.ones((4, 3), dtype=bool)
    observed[3, 0] = False  # the column x in [0.5, 1), y in [0, 0.5): no sensor looked there
    grid3d.write_grid3d(prob, logodds, observed, info, tmp_path)
    side = json.loads((tmp_path / "grid.json").read_text())
    arr = np.load(tmp_path / side["data"])
    assert arr.dtype == np.float32 and list(arr.shape) == side["shape"] and side["axis_order"] == ["x", "y", "z"]
    point = np.array([-0.3, 1.2, 0.2])  # inside cell (1, 2, 0)
    ijk = np.floor((point - side["lo"]) / (np.array(side["hi"]) - side["lo"]) * side["shape"]).astype(int)
    assert tuple(ijk) == (1, 2, 0) and arr[tuple(ijk)] == pytest.approx(1 / (1 + math.exp(-3)))
    np.testing.assert_allclose(np.array(side["lo"]) + (ijk + 0.5) * side["cell_size"], [-0.25, 1.25, 0.25])
    # unknown: the whole column NaN (a planner must not read the prior 0.12 there as free), the rest p
    assert np.isnan(arr[3, 0]).all() and np.isnan(arr).sum() == 2 and side["observed"] == pytest.approx(11 / 12, abs=1e-4)
    assert "NaN" in side["unknown"]
    np.testing.assert_allclose(np.load(tmp_path / side["logodds"]), logodds)  # the grid's state everywhere


def test_point_clouds_round_trip_through_independent_parsers(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(50, 3)).astype(np.uint8)
    clouds.write_ply(tmp_path / "a.ply", xyz, rgb)
    clouds.write_pcd(tmp_path / "a.pcd", xyz, rgb)
    clouds.write_ply(tmp_path / "b.ply", xyz)
    clouds.write_pcd(tmp_path / "b.pcd", xyz)
    for name in ("a", "b"):
        ply, pcd = read_ply(tmp_path / f"{name}.ply"), read_pcd(tmp_path / f"{name}.pcd")
        for arr in (ply, pcd):
            np.testing.assert_array_equal(np.column_stack([arr["x"], arr["y"], arr["z"]]), xyz)
    ply, pcd = read_ply(tmp_path / "a.ply"), read_pcd(tmp_path / "a.pcd")
    np.testing.assert_array_equal(np.column_stack([ply["red"], ply["green"], ply["blue"]]), rgb)
    packed = pcd["rgb"].view(np.uint32)
    np.testing.assert_array_equal(np.column_stack([packed >> 16 & 255, packed >> 8 & 255, packed & 255]), rgb)
    clouds.write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    assert len(read_ply(tmp_path / "empty.ply")) == 0


# ------------------------------------------------------------------ a tiny trained run


@pytest.fixture(scope="module")
def trained_run(tiny_office, tmp_path_factory) -> Path:
    from virus_nerf.config_io import to_dict

    root = tmp_path_factory.mktemp("export_run")
    (root / "small.json").write_text(json.dumps(to_dict(tiny_train_config())))
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", root / "run",
                            "--config", root / "small.json", "--quiet"])
    assert code == 0, err
    return root / "run"


@pytest.fixture(scope="module")
def exported(trained_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export_out") / "export"
    code, stdout, err = run_cli(["export", "--run", trained_run, "--out", out, "--what", "all", "--max-poses", "2",
                                 "--n-rays", "90", "--cloud-points", "3000", "--image-scale", "0.5"])
    assert code == 0, err
    assert "wrote" in stdout
    return out


def test_export_all_writes_every_format(exported):
    names = {p.relative_to(exported).as_posix() for p in exported.rglob("*") if p.is_file()}
    assert {"map.pgm", "map.yaml", "map.png", "prob.pgm", "prob.yaml", "esdf.npy", "esdf.yaml", "esdf.png",
            "grid_probability.npy", "grid_logodds.npy", "grid.json", "poses.csv", "cloud.pcd", "cloud.ply",
            "export.json", "scans/scan_0000.pcd", "scans/scan_0001.ply", "images/color_0001.png",
            "images/depth_0000.png"} <= names
    trinary, prob = read_yaml(exported / "map.yaml"), read_yaml(exported / "prob.yaml")
    assert trinary["mode"] == "trinary" and prob["mode"] == "raw"
    doc = json.loads((exported / "export.json").read_text())  # the frame and how the map was made
    assert doc["frame"].startswith("world: the recording's pose frame")
    assert (doc["map"]["n_rays"], doc["map"]["max_poses"]) == (90, 2)
    assert doc["map"]["height"] == pytest.approx(doc["prob_map"]["height"])  # the median camera height
    assert trinary["origin"] == prob["origin"] and trinary["resolution"] == prob["resolution"] == 0.05
    a, b = np.asarray(Image.open(exported / "map.pgm")), np.asarray(Image.open(exported / "prob.pgm"))
    assert a.shape == b.shape and set(np.unique(a)) <= {0, 205, 254}
    # the ESDF is the signed distance to the trinary map's occupied pixels
    d = np.load(exported / "esdf.npy")
    assert d.shape == a.shape
    seen = ~np.isnan(d)  # NaN: no sensor looked there (maps/observed.py), and the map is unknown
    assert (a[~seen] == 205).all() and seen.any()
    if (a == 0).any():
        assert np.all(d[a == 0] < 0) and np.all(d[(a != 0) & seen] > 0)
    side = json.loads((exported / "grid.json").read_text())
    p3 = np.load(exported / "grid_probability.npy")
    known = ~np.isnan(p3)
    np.testing.assert_allclose(p3[known], 1 / (1 + np.exp(-np.load(exported / "grid_logodds.npy")[known])), atol=1e-6)
    assert list(p3.shape) == side["shape"] and 0 <= p3[known].min() <= p3[known].max() <= 1
    np.testing.assert_allclose(np.array(side["hi"]) - side["lo"], np.array(side["cell_size"]) * side["shape"])
    # NaN: whole columns no sensor looked at; they agree with prob.pgm's unknown (255) at the columns'
    # centres, read from the files (the two rasters' cells differ: edges may disagree)
    columns = known.all(axis=2)
    assert (columns == known.any(axis=2)).all() and side["observed"] == pytest.approx(columns.mean(), abs=1e-4)
    assert 0.0 < columns.mean() < 1.0 and doc["grid3d"]["observed"] == side["observed"]
    ix, iy = np.meshgrid(np.arange(p3.shape[0]), np.arange(p3.shape[1]), indexing="ij")
    centres = np.array(side["lo"])[:2] + (np.stack([ix, iy], -1) + 0.5) * np.array(side["cell_size"])[:2]
    looked = _looked_at(exported, centres.reshape(-1, 2)).reshape(columns.shape)
    assert (looked == columns).mean() > 0.9, (looked == columns).mean()


def _looked_at(folder: Path, points: np.ndarray) -> np.ndarray:
    """(M,) bool: the points whose pixel of folder/prob.pgm is not 255 (no sensor looked), read as
    map_server reads it (origin = the lower-left corner, row 0 = the largest y)."""
    meta, prob = read_yaml(folder / "prob.yaml"), np.asarray(Image.open(folder / "prob.pgm"))
    res, (x0, y0) = meta["resolution"], meta["origin"][:2]
    col = np.floor((points[:, 0] - x0) / res).astype(int)
    row = prob.shape[0] - 1 - np.floor((points[:, 1] - y0) / res).astype(int)
    inside = (col >= 0) & (col < prob.shape[1]) & (row >= 0) & (row < prob.shape[0])
    out = np.zeros(len(points), dtype=bool)
    out[inside] = prob[row[inside], col[inside]] != 255
    return out


def test_scans_lie_at_the_model_ranges(exported, trained_run):
    from virus_nerf.maps.scans import horizontal_directions
    from virus_nerf.trainer.run import load_trained

    trainer, _, _ = load_trained(trained_run, "--run")
    rows = [ln.split(",") for ln in (exported / "poses.csv").read_text().splitlines()[1:]]
    assert len(rows) == 2
    pos = np.array([float(v) for v in rows[0][2:5]])
    ply, pcd = read_ply(exported / "scans" / "scan_0000.ply"), read_pcd(exported / "scans" / "scan_0000.pcd")
    pts = np.column_stack([ply["x"], ply["y"], ply["z"]])
    np.testing.assert_array_equal(pts, np.column_stack([pcd["x"], pcd["y"], pcd["z"]]))
    dirs = horizontal_directions(90)
    r = trainer.mapper.model.ranges(np.tile(pos, (90, 1)), dirs)
    ok = np.isfinite(r) & (r > 0)
    hits = pos + dirs[ok] * r[ok, None]
    seen = _looked_at(exported, hits)  # a review: 65 % of a scan lay where no sensor looked
    assert seen.any() and not seen.all()
    np.testing.assert_allclose(pts, hits[seen].astype(np.float32), atol=1e-4)
    doc = json.loads((exported / "export.json").read_text())
    assert doc["scans"]["unobserved_left_out"] >= int((~seen).sum()) and (doc["steps"], doc["run_finished"]) == (
        trainer.mapper.step, True)
    cloud = read_ply(exported / "cloud.ply")
    assert 0 < len(cloud) <= 3000 and len(read_pcd(exported / "cloud.pcd")) == len(cloud)


def test_rendered_depth_png_matches_the_model_ranges(exported, trained_run):
    from virus_nerf.sensors.camera import pixel_directions
    from virus_nerf.trainer.run import load_trained

    trainer, _, _ = load_trained(trained_run, "--run")
    doc = json.loads((exported / "export.json").read_text())["images"]
    from virus_nerf.sensors.camera import Intrinsics

    intr = Intrinsics(doc["fx"], doc["fy"], doc["cx"], doc["cy"], doc["width"], doc["height"])
    depth = np.asarray(Image.open(exported / "images" / "depth_0000.png"))
    colour = np.asarray(Image.open(exported / "images" / "color_0000.png"))
    assert depth.dtype == np.uint16 and depth.shape == (intr.height, intr.width)
    assert colour.shape == (intr.height, intr.width, 3)
    row = (exported / "poses.csv").read_text().splitlines()[1].split(",")
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat([float(v) for v in row[5:9]]).as_matrix()
    pose[:3, 3] = [float(v) for v in row[2:5]]
    v, u = np.mgrid[0 : intr.height : 3, 0 : intr.width : 3]
    dirs_cam = pixel_directions(intr, u.ravel(), v.ravel())
    r = trainer.mapper.model.ranges(np.tile(pose[:3, 3], (len(dirs_cam), 1)), dirs_cam @ pose[:3, :3].T)
    want = np.where(np.isfinite(r), np.rint(r * dirs_cam[:, 2] * 1000), 0)
    got = depth[v.ravel(), u.ravel()].astype(float)
    assert np.mean((got > 0) == (want > 0)) >= 0.99  # hit / no hit as SceneModel.ranges says
    both = (got > 0) & (want > 0)
    assert both.sum() > 0 and np.abs(got[both] - want[both]).max() <= 1  # mm


def test_user_poses_csv_drives_scans(trained_run, tmp_path):
    csv = tmp_path / "poses.csv"
    csv.write_text("time,x,y,z,qx,qy,qz,qw\n0.0,1.0,0.5,-0.1,0,0,0,1\n1.5,2.0,0.0,0.1,0,0,0.7071068,0.7071068\n")
    out = tmp_path / "exp"
    code, _, err = run_cli(["export", "--run", trained_run, "--out", out, "--what", "scans", "--poses", csv,
                            "--n-rays", "16"])
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["export.json", "poses.csv", "scans"]
    rows = [[float(v) for v in ln.split(",")] for ln in (out / "poses.csv").read_text().splitlines()[1:]]
    np.testing.assert_allclose(np.array(rows)[:, 1:5], [[0.0, 1.0, 0.5, -0.1], [1.5, 2.0, 0.0, 0.1]])
    np.testing.assert_allclose(np.array(rows)[1, 5:], [0, 0, 0.7071068, 0.7071068], atol=1e-6)
    for k, z in ((0, -0.1), (1, 0.1)):
        ply = read_ply(out / "scans" / f"scan_{k:04d}.ply")
        assert np.allclose(ply["z"], z, atol=1e-6)
    assert json.loads((out / "export.json").read_text())["poses"] == {"source": str(csv), "count": 2}
    # the same poses in millimetres lie hundreds of metres outside the run's box: refused, not an
    # export of empty scans
    mm = tmp_path / "poses_mm.csv"
    mm.write_text("time,x,y,z,qx,qy,qz,qw\n0.0,1.0,0.5,-0.1,0,0,0,1\n1.5,2000.0,0.0,100.0,0,0,0,1\n")
    code, _, err = run_cli(["export", "--run", trained_run, "--out", tmp_path / "exp_mm", "--what", "scans",
                            "--poses", mm])
    assert code == 2 and err.count("\n") == 1, err
    assert "poses_mm.csv, row 3, field 'x/y/z': camera at (2e+03, 0, 100) m lies outside the run's scene box" in err
    assert "expected poses in the run's world frame, in metres" in err and not (tmp_path / "exp_mm").exists()
    # images need the cameras' orientation: a ROS body frame's (identity: the camera looks up) is
    # refused in one line (a review: the ceiling was rendered); the scans above took it (positions)
    code, _, err = run_cli(["export", "--run", trained_run, "--out", tmp_path / "exp_img", "--what", "images",
                            "--poses", csv])
    assert code == 2 and err.count("\n") == 1 and not (tmp_path / "exp_img").exists(), err
    assert "poses.csv, row 2, field 'qx/qy/qz/qw': the camera looks straight up; expected camera-to-world" in err
    # a scale of no pixel is refused before anything is rendered, and the parents made for OUT go
    code, _, err = run_cli(["export", "--run", trained_run, "--out", tmp_path / "n1" / "n2" / "exp", "--what",
                            "map,images", "--image-scale", "0.001"])
    assert code == 2 and "--image-scale 0.001: CAM1's" in err and not (tmp_path / "n1").exists(), err


@pytest.mark.parametrize(
    "csv, fragment",
    [
        ("time,x,y,z,qx,qy,qz,qw\n0,1,2,3,0,0,0,2\n", "poses.csv, row 2, field 'qx/qy/qz/qw': quaternion (0, 0, 0, 2)"),
        ("time,x,y\n0,1,2\n", "poses.csv, row 1: header ['time', 'x', 'y'] lacks column(s) ['z', 'qx', 'qy', 'qz', 'qw']"),
        ("time,x,y,z,qx,qy,qz,qw\n", "poses.csv: no poses"),
    ],
)
def test_bad_pose_files_are_named(tmp_path, csv, fragment):
    (tmp_path / "poses.csv").write_text(csv)
    code, _, err = run_cli(["export", "--run", tmp_path / "no-run", "--out", tmp_path / "exp", "--poses",
                            tmp_path / "poses.csv"])
    assert code == 2 and err.count("\n") == 1 and fragment in err, err
    assert not (tmp_path / "exp").exists()


def test_grid_exports_need_a_virus_run(trained_run, tmp_path):
    run = tmp_path / "ngp_run"
    run.mkdir()
    cfg = json.loads((trained_run / "config.json").read_text())
    cfg["grid"] = "ngp"
    (run / "config.json").write_text(json.dumps(cfg))
    (run / "run.json").write_text((trained_run / "run.json").read_text())
    code, _, err = run_cli(["export", "--run", run, "--out", tmp_path / "exp", "--what", "map,prob"])
    assert code == 2 and "--what 'map,prob': 'prob' needs the Bayesian VIRUS grid" in err, err
    assert not (tmp_path / "exp").exists()
    from virus_nerf.exports.command import parse_what

    assert parse_what(None, "ngp") == ("map", "esdf", "scans")
    assert parse_what("all", "virus") == ("map", "prob", "grid3d", "esdf", "scans", "cloud", "images")
    assert parse_what("esdf,map", "virus") == ("map", "esdf")


def test_a_full_disk_under_numpy_is_one_line_and_leaves_no_export(trained_run, tmp_path, monkeypatch):
    """numpy's short write on a full disk carries no errno and no file name ("N requested and M
    written"); it is the file being written and a full disk, in one line, not a traceback."""
    import virus_nerf.exports.grid3d as grid3d

    def short_write(fh, arr):
        fh.write(b"\x93NUMPY")
        raise OSError(f"{arr.nbytes} requested and 6 written")

    monkeypatch.setattr(grid3d.np, "save", short_write)
    out = tmp_path / "export"
    code, _, err = run_cli(["export", "--run", trained_run, "--out", out, "--what", "grid3d"])
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"virus-nerf: error: {out}") and "grid_probability.npy: could not be written (no space "\
        "left on device (" in err and "requested and 6 written)); nothing was lost" in err, err
    assert not out.exists() and not list(tmp_path.glob(".export*"))


def test_export_sizes_that_cannot_be_made_are_one_line(trained_run, tmp_path):
    """Issue 30: a resolution so fine its pixel count overflows, and images scaled to 0 x 0 px."""
    for argv, fragment in ((["--resolution", "1e-300"], "would be a 1000000000000x1000000000000 px map"),
                           (["--what", "images", "--image-scale", "1e-6"], "would be 0x0 px")):
        out = tmp_path / "e"
        code, _, err = run_cli(["export", "--run", trained_run, "--out", out, *argv])
        assert code == 2 and len(err.strip().splitlines()) == 1 and fragment in err, err
        assert not out.exists()


def test_evaluate_and_export_wait_for_no_one_in_the_run(trained_run, tmp_path):
    """A run another process holds (a `train` working in it) is neither evaluated nor exported:
    one line naming --run, and nothing written."""
    from virus_nerf.errors import UsageError
    from virus_nerf.exports.command import export
    from virus_nerf.trainer.command import evaluate
    from virus_nerf.trainer.run_folder import RunLock

    with RunLock(trained_run, "--out"):
        with pytest.raises(UsageError, match=rf"--run {trained_run}: the run is in use by another virus-nerf process"):
            evaluate(run=trained_run, out=tmp_path / "metrics.json")
        with pytest.raises(UsageError, match=rf"--run {trained_run}: the run is in use"):
            export(run=trained_run, out=tmp_path / "export")
    assert not (tmp_path / "metrics.json").exists() and not (tmp_path / "export").exists()


_READ_ONLY_COMMANDS = """
import contextlib, io, json, sys
from virus_nerf.cli import main
run, out = sys.argv[1], sys.argv[2]
codes = {}
for name, argv in (("export", ["export", "--run", run, "--out", out + "/export", "--max-poses", "2", "--n-rays", "16"]),
                   ("evaluate", ["evaluate", "--run", run, "--out", out + "/eval/metrics.json", "--n-rays", "32",
                                 "--no-plots"]),
                   ("evaluate_into_run", ["evaluate", "--run", run, "--no-plots"])):
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            main(argv)
        codes[name] = [0, err.getvalue()]
    except SystemExit as exc:
        codes[name] = [exc.code, err.getvalue()]
print(json.dumps(codes))
"""


def test_a_run_on_read_only_media_exports_and_evaluates_elsewhere(trained_run, tmp_path):
    """A run copied to read-only media (an archive, a share mounted read-only; here a read-only bind
    mount in a mount namespace of its own, gone with the process): export and evaluate --out
    elsewhere read it (before: 'run.lock: Read-only file system', exit 2); evaluate into the run
    names --out in one line."""
    import shutil
    import subprocess
    import sys

    if shutil.which("unshare") is None:
        pytest.skip("needs util-linux unshare for a private read-only mount")
    src, ro, out = tmp_path / "src", tmp_path / "ro", tmp_path / "out"
    shutil.copytree(trained_run, src / "run")
    ro.mkdir()
    out.mkdir()
    mount = f"mount --bind '{src}' '{ro}' && mount -o remount,bind,ro '{ro}'"
    probe = subprocess.run(["unshare", "--mount", "--map-root-user", "sh", "-c", f"{mount} && ! touch '{ro}/x' 2>/dev/null"],
                           capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private read-only mount here (user namespaces off?): {probe.stderr.decode().strip()}")
    proc = subprocess.run(["unshare", "--mount", "--map-root-user", "sh", "-c",
                           f'{mount} && exec "$0" -c "$1" "$2" "$3"', sys.executable, _READ_ONLY_COMMANDS,
                           str(ro / "run"), str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    codes = json.loads(proc.stdout.strip().splitlines()[-1])
    assert codes["export"][0] == 0 and (out / "export" / "map.pgm").read_bytes().startswith(b"P5"), codes
    assert codes["evaluate"][0] == 0 and json.loads((out / "eval" / "metrics.json").read_text())["train"]["steps"] == 5
    code, err = codes["evaluate_into_run"]
    assert code == 2 and err.count("\n") == 1 and "--out " in err and "Read-only file system" in err, err
    assert sorted(p.name for p in (src / "run").iterdir()) == sorted(p.name for p in trained_run.iterdir())


def test_a_readers_frames_go_to_the_user_cache_and_a_killed_readers_are_removed(trained_run, tmp_path, monkeypatch):
    """evaluate and export decode a run's frames into a folder of their own under the user cache (a
    disk: a /tmp in memory would hold an hour's drive in RAM), gone with the trainer; one a killed
    reader left (its pid dead) is removed by the next."""
    import gc
    import subprocess
    import sys

    from virus_nerf.trainer.run import READER_FRAMES, load_trained

    monkeypatch.setenv("VIRUS_NERF_CACHE_DIR", str(tmp_path / "cache"))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / "cache" / f".{READER_FRAMES}.partial-{dead.pid}-abc"
    stale.mkdir(parents=True)
    trainer, _, _ = load_trained(trained_run, "--run")
    scratch = trainer.scratch
    assert scratch.parent == tmp_path / "cache" and scratch.is_dir() and not stale.exists()
    del trainer
    gc.collect()
    assert not scratch.exists()


def test_default_map_is_the_snapshots_map_and_scans_stay_fine(trained_run, tmp_path):
    """Without --n-rays / --max-poses, map.pgm is scanned as every snapshot's map (360 rays from
    30 positions: the counts its safety is measured at, D75) and the scans keep 720 rays."""
    from virus_nerf.maps.scans import horizontal_directions
    from virus_nerf.trainer.run import load_trained

    default, explicit = tmp_path / "default", tmp_path / "explicit"
    code, _, err = run_cli(["export", "--run", trained_run, "--out", default, "--what", "map,prob,scans"])
    assert code == 0, err
    code, _, err = run_cli(["export", "--run", trained_run, "--out", explicit, "--what", "map", "--n-rays", "360",
                            "--max-poses", "30"])
    assert code == 0, err
    assert (default / "map.pgm").read_bytes() == (explicit / "map.pgm").read_bytes()
    trainer, _, _ = load_trained(trained_run, "--run")
    rows = [ln.split(",") for ln in (default / "poses.csv").read_text().splitlines()[1:]]
    pos = np.array([float(v) for v in rows[0][2:5]])
    dirs = horizontal_directions(720)
    r = trainer.mapper.model.ranges(np.tile(pos, (720, 1)), dirs)
    ok = np.isfinite(r) & (r > 0)
    assert len(read_ply(default / "scans" / "scan_0000.ply")) == int(_looked_at(default, pos + dirs[ok] * r[ok, None]).sum())


def test_poses_csv_keeps_epoch_times_and_reads_back(tmp_path):
    """A robot's stamps are seconds since 1970 (1.7e9): poses.csv keeps them to the microsecond,
    so two frames 0.1 s apart stay apart and the file goes back in as --poses."""
    from virus_nerf.exports.views import PoseSet, read_pose_csv

    times = np.array([1702374040.1003, 1702374040.2007, 1702374041.0])
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, 0, 3] = [0.5, 1.25, -2.0]
    path = tmp_path / "poses.csv"
    path.write_text(PoseSet(times, poses, "test").csv())
    assert path.read_text().splitlines()[1].startswith("0,1702374040.100300,0.5,0,0,")
    back = read_pose_csv(path)
    np.testing.assert_allclose(back.times, times, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.cam_to_world, poses, atol=1e-9)


def test_map_yaml_numbers_read_back_as_numbers_in_yaml_1_1(tmp_path):
    """PyYAML (YAML 1.1) reads `3e-05` as a string; the map's YAML writes `3.0e-05`, the same float.
    The shortest text otherwise (a LiDAR point on a pixel edge falls in the same pixel for a reader)."""
    from virus_nerf.maps.occupancy import map_yaml, yaml_float

    yaml = pytest.importorskip("yaml")  # PyYAML: there with the dev extras (a dependency of theirs)

    assert [yaml_float(v) for v in (3e-05, 1e22, -2.5e-07, 0.1, -4.05, 1e16)] == [
        "3.0e-05", "1.0e+22", "-2.5e-07", "0.1", "-4.05", "1.0e+16"]
    doc = yaml.safe_load(map_yaml("map.pgm", 0.05, (3e-05, -1e-07)))
    assert doc["origin"] == [3e-05, -1e-07, 0.0] and doc["resolution"] == 0.05


def test_a_run_whose_training_did_not_finish_is_exported_with_a_note(trained_run, tmp_path):
    """A run stopped while it trained past an earlier budget (`train --resume --max-steps` more,
    then Ctrl-C) keeps the earlier budget's metrics.json: export says the checkpoint's steps are not
    the finished run's (a review: run_finished was true), and exports it as it stands."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    doc = json.loads((run / "metrics.json").read_text())
    steps = doc["train"]["steps"]
    doc["train"]["steps"] = steps - 1  # the earlier budget's file, one step short of the checkpoint
    (run / "metrics.json").write_text(json.dumps(doc))
    code, stdout, err = run_cli(["export", "--run", run, "--out", tmp_path / "exp", "--what", "map"])
    assert code == 0, err
    assert stdout.startswith(f"note: --run {run}: its training did not finish (no metrics.json of its last step; stopped at step "
                              f"{steps})")
    assert json.loads((tmp_path / "exp" / "export.json").read_text())["run_finished"] is False
