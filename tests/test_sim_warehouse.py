"""The simulated warehouse (issue 28, item 5): a large hall with rows of shelving racks, aisles
and cross-aisles, a free drive corridor, deterministic for a seed. Geometry only, no rendering."""

from __future__ import annotations

import typing

import numpy as np
import pytest

from virus_nerf.sim.racks import RACK_KINDS
from virus_nerf.sim.rooms import PRESETS, ROOM_NAMES, build_room
from virus_nerf.sim.scene import (
    Cylinder,
    _prim_aabb,  # the scene's own axis-aligned box of a primitive
)
from virus_nerf.sim.trajectory import DrivePath

SEEDS = (0, 1, 3)
SHELL_KINDS = ("floor", "ceiling", "wall")
WALL_ITEMS = ("door", "dock_door", "poster", "whiteboard")  # flat boxes on the walls


@pytest.fixture(scope="module")
def rooms():
    return {s: build_room("warehouse", np.random.default_rng(s)) for s in SEEDS}


def _prims(room, kinds):
    return [p for o in room.scene.objects if o.kind in kinds for p in o.primitives]


def _footprint_distance(p, pts):
    """Horizontal distance (K,) from points (K, 2) to the primitive's footprint (0 inside)."""
    d = pts - np.asarray(p.center[:2])
    if isinstance(p, Cylinder):
        return np.maximum(np.linalg.norm(d, axis=1) - p.radius, 0.0)
    c, s = np.cos(p.yaw), np.sin(p.yaw)
    lx, ly = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    ex = np.maximum(np.abs(lx) - p.size[0] / 2, 0.0)
    ey = np.maximum(np.abs(ly) - p.size[1] / 2, 0.0)
    return np.hypot(ex, ey)


def test_warehouse_is_a_selectable_preset():
    assert "warehouse" in ROOM_NAMES and set(ROOM_NAMES) == set(PRESETS)
    from virus_nerf.sim.command import simulate

    hints = typing.get_type_hints(simulate)
    assert set(typing.get_args(hints["scene"])) == set(ROOM_NAMES)


def test_extent_and_meta(rooms):
    for seed, room in rooms.items():
        lo, hi = np.array(room.scene.extent_lo), np.array(room.scene.extent_hi)
        assert hi[0] - lo[0] >= 30.0 and hi[1] - lo[1] >= 15.0, seed
        meta = room.scene.meta
        assert meta["preset"] == "warehouse"
        assert meta["area_m2"] == pytest.approx((hi[0] - lo[0]) * (hi[1] - lo[1]))
        assert meta["placed"]["rack_row"] >= 5 and meta["placed"]["rack_bay"] >= 25
        assert meta["placed"]["goods"] > 50
        assert meta["placed"] == room.placed


def test_rack_heights_depths_and_aisles(rooms):
    for seed, room in rooms.items():
        zf = room.scene.meta["floor_z"]
        rows = room.scene.meta["racks"]["rows"]
        frames = [o for o in room.scene.objects if o.kind == "rack" and o.name.startswith("rack_frame")]
        assert len(frames) == room.placed["rack"]
        for o in frames:  # the uprights give a rack's height
            top = max(_prim_aabb(p)[1][2] for p in o.primitives) - zf
            assert 2.0 - 1e-9 <= top <= 4.0 + 1e-9, (seed, o.name, top)
        assert max(_prim_aabb(p)[1][2] for p in _prims(room, RACK_KINDS)) - zf <= 4.0 + 1e-9
        # goods stay inside a rack's footprint and below its top
        for p in _prims(room, ("goods",)):
            lo, hi = _prim_aabb(p)
            inside = [r for r in rows if r["y"] - r["depth"] / 2 - 1e-6 <= lo[1] and hi[1] <= r["y"] + r["depth"] / 2 + 1e-6]
            assert inside and hi[2] - zf <= inside[0]["height"] + 1e-9
        ys = np.array([r["y"] for r in rows])
        depth = np.array([r["depth"] for r in rows])
        assert ((depth >= 1.0 - 1e-9) & (depth <= 1.2 + 1e-9)).all()
        aisles = (ys[1:] - depth[1:] / 2) - (ys[:-1] + depth[:-1] / 2)
        assert ((aisles >= 2.5 - 1e-9) & (aisles <= 3.5 + 1e-9)).all(), aisles
        # the two drive legs (y = 0 and y = 2R) run down aisles on both sides of a rack row
        R = room.drive.radius
        assert any(abs(y - R) < 1e-6 for y in ys)
        assert (ys < 0).any() and (ys > 2 * R).any()


def test_drive_corridor_is_free(rooms):
    for seed, room in rooms.items():
        pts = DrivePath(room.drive).sample(0.05)
        # no primitive apart from the shell and flat wall items reaches within 0.5 m of the path
        for p in _prims(room, {o.kind for o in room.scene.objects} - set(SHELL_KINDS) - set(WALL_ITEMS)):
            assert _footprint_distance(p, pts).min() >= 0.5, (seed, p)
        # and nothing is hit by short horizontal rays from the path at sensor and rack heights
        zs = np.array([-0.6, -0.15, 0.0, 1.0, 2.5])
        o = np.array([[x, y, z] for x, y in pts[::5] for z in zs])
        for ang in np.deg2rad(np.arange(0, 360, 45)):
            d = np.broadcast_to([np.cos(ang), np.sin(ang), 0.0], o.shape)
            t = room.scene.cast(o, d, max_range=0.5).t
            assert np.isinf(t).all(), f"seed {seed}: something within 0.5 m of the path"


def test_there_is_an_open_cross_aisle(rooms):
    for seed, room in rooms.items():
        spans = sorted((_prim_aabb(p)[0][0], _prim_aabb(p)[1][0]) for p in _prims(room, RACK_KINDS))
        first, last = spans[0][0], max(hi for _, hi in spans)
        gaps, reach = [], first
        for lo, hi in spans:
            if lo > reach:
                gaps.append((reach, lo))
            reach = max(reach, hi)
        # a line across y at some x, strictly between the rows' ends, crosses no rack at all
        wide = [g for g in gaps if g[1] - g[0] >= 2.5]
        assert wide and all(first < g[0] and g[1] < last for g in wide), (seed, gaps)
        (c0, c1), = room.scene.meta["racks"]["cross_aisles"]
        assert c1 - c0 >= 2.5 and any(g[0] <= c0 + 1e-5 and c1 - 1e-5 <= g[1] for g in wide)  # 6-decimal rounding
        x_mid = (c0 + c1) / 2
        lo_, hi_ = np.array(room.scene.extent_lo), np.array(room.scene.extent_hi)
        ys = np.linspace(lo_[1] + 0.3, hi_[1] - 0.3, 200)
        o = np.column_stack([np.full_like(ys, x_mid), ys, np.full_like(ys, 0.5)])
        t = room.scene.cast(o, np.broadcast_to([1.0, 0.0, 0.0], o.shape), max_range=(c1 - c0) / 2 - 0.05).t  # the whole aisle
        t2 = room.scene.cast(o, np.broadcast_to([-1.0, 0.0, 0.0], o.shape), max_range=(c1 - c0) / 2 - 0.05).t
        assert np.isinf(t).all() and np.isinf(t2).all()
        # the U-turns lie in open cross-aisles at the back and the front of the hall
        assert first > 0.0 and last < room.drive.straight


def test_deterministic_for_a_seed_and_varies_with_it():
    a = build_room("warehouse", np.random.default_rng(7)).scene.to_dict()
    b = build_room("warehouse", np.random.default_rng(7)).scene.to_dict()
    c = build_room("warehouse", np.random.default_rng(8)).scene.to_dict()
    assert a == b
    assert a != c


def test_primitive_count_stays_moderate(rooms):
    common = max(sum(len(o.primitives) for o in build_room("common", np.random.default_rng(s)).scene.objects)
                 for s in SEEDS)
    for room in rooms.values():
        n = sum(len(o.primitives) for o in room.scene.objects)
        assert 150 < n <= 3 * common, n


def test_scene_json_round_trip(rooms, tmp_path):
    from virus_nerf.sim.scene import Scene

    room = rooms[SEEDS[0]]
    room.scene.save(tmp_path / "scene.json")
    back = Scene.load(tmp_path / "scene.json")
    assert back.meta["racks"] == room.scene.meta["racks"]
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to([5.0, 0.0, 0.0], d.shape)
    np.testing.assert_allclose(back.cast(o, d).t, room.scene.cast(o, d).t, atol=1e-6)
