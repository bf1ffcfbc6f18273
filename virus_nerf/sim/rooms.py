"""Room presets (docs/method.md 5): an office (~72 m^2) and a common area (~216 m^2) from primitives.

Each room is a box shell (4 walls, floor, ceiling as slabs) with furniture placed at random
(numpy Generator) outside a corridor around the robot's drive loop, so nothing ever blocks the
path. Wall items (cupboards, shelves, kitchen counter) stand against a wall; free items
(desks with chairs, tables, couches, plants, pillars) stand in the open. Every surface carries
a procedural texture (per-object colours plus stripes / checker / noise / wood patterns).
The robot starts at the origin heading +x with its LiDAR `rig.LIDAR_HEIGHT_M` above the floor,
so the floor is at z = -LIDAR_HEIGHT_M.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from virus_nerf.sim.rig import LIDAR_HEIGHT_M
from virus_nerf.sim.scene import Box, Cylinder, Material, Primitive, Scene, SceneObject
from virus_nerf.sim.trajectory import DrivePath, DriveSpec

RoomName = Literal["office", "common"]
ROOM_NAMES: tuple[str, ...] = ("office", "common")


@dataclass(frozen=True)
class RoomSpec:
    """Preset parameters (metres). length along x (the drive direction), width along y.
    start_margin: start point to the back wall; end_margin: far U-turn apex to the front wall.
    corridor: clearance kept free around the drive centreline; gap: minimum free space between
    furniture groups (larger = more spread). counts: furniture kind -> how many to try to place."""

    name: str
    length: float
    width: float
    height: float
    counts: dict[str, int]
    turn_radius: float = 0.9
    start_margin: float = 1.8
    end_margin: float = 0.8
    corridor: float = 0.6
    gap: float = 0.35
    floor_pattern: str = "checker"
    wall_colours: tuple[tuple[float, float, float], ...] = ((0.85, 0.83, 0.78),)


PRESETS: dict[str, RoomSpec] = {
    "office": RoomSpec(
        name="office", length=9.0, width=8.0, height=2.6,
        counts={"desk": 4, "cupboard": 3, "shelf": 2, "plant": 2, "bin": 2, "poster": 5, "door": 1,
                "whiteboard": 1},
        gap=0.3,
    ),
    "common": RoomSpec(
        name="common", length=18.0, width=12.0, height=3.0, turn_radius=1.0,
        counts={"table": 3, "round_table": 2, "couch": 2, "kitchen": 1, "shelf": 1, "plant": 3,
                "pillar": 2, "poster": 6, "door": 2},
        gap=1.2, corridor=0.7,
    ),
}


@dataclass
class Room:
    """A generated room: the exact scene and the robot's drive loop inside it."""

    scene: Scene
    drive: DriveSpec
    spec: RoomSpec
    placed: dict[str, int] = field(default_factory=dict)  # kind -> how many were placed


# ------------------------------------------------------------------------------ materials

_PALETTE = np.array([
    [0.62, 0.45, 0.30], [0.35, 0.40, 0.55], [0.70, 0.20, 0.18], [0.20, 0.45, 0.30],
    [0.85, 0.75, 0.35], [0.50, 0.50, 0.52], [0.15, 0.18, 0.22], [0.80, 0.55, 0.45],
    [0.30, 0.60, 0.70], [0.55, 0.30, 0.55], [0.90, 0.88, 0.82], [0.40, 0.28, 0.18],
])


class _Materials:
    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.n = 0

    def make(self, pattern: str | None = None, base: np.ndarray | None = None, scale: float | None = None,
             smooth: bool = True, ir: float | None = None, contrast: float = 0.35) -> Material:
        rng = self.rng
        self.n += 1
        if base is None:
            base = _PALETTE[rng.integers(len(_PALETTE))] * rng.uniform(0.85, 1.15, 3)
        base = np.clip(base, 0.03, 0.97)
        other = np.clip(base * (1 - contrast) + rng.uniform(0, 1, 3) * contrast * 0.6, 0.02, 0.98)
        if pattern is None:
            pattern = str(rng.choice(["plain", "stripes", "noise", "wood", "checker"]))
        if scale is None:
            scale = float(rng.uniform(0.08, 0.4))
        if ir is None:
            ir = float(np.clip(0.35 + 0.6 * base.mean() + rng.normal(0, 0.05), 0.1, 0.95))
        return Material(colour=tuple(np.round(base, 4)), colour2=tuple(np.round(other, 4)), pattern=pattern,
                        scale=round(scale, 4), smooth=smooth, ir_reflectance=round(ir, 3),
                        seed=int(rng.integers(1, 2**20)))


# ------------------------------------------------------------------------------ furniture


@dataclass(frozen=True)
class _Piece:
    """Furniture in its own frame: objects with primitives about (0, 0, floor), footprint half
    sizes (hx, hy) of the occupied rectangle in that frame, and whether it goes against a wall
    (its back, local -y side, to the wall)."""

    objects: list[tuple[str, list[Primitive], Material]]
    half: tuple[float, float]
    wall: bool = False


def _legs(hx: float, hy: float, h: float, r: float, inset: float) -> list[Primitive]:
    return [Cylinder((sx * (hx - inset), sy * (hy - inset), h / 2), r, h) for sx in (-1, 1) for sy in (-1, 1)]


def _chair(mats: _Materials, x: float, y: float, yaw: float) -> tuple[str, list[Primitive], Material]:
    """Chair at (x, y) in the piece frame facing direction yaw (its back behind)."""
    c, s = np.cos(yaw), np.sin(yaw)

    def at(lx: float, ly: float, z: float) -> tuple[float, float, float]:
        return (x + c * lx - s * ly, y + s * lx + c * ly, z)

    prims: list[Primitive] = [Box(at(0, 0, 0.45), (0.44, 0.44, 0.05), yaw),
                              Box(at(-0.2, 0, 0.72), (0.04, 0.42, 0.46), yaw)]
    prims += [Cylinder(at(sx * 0.19, sy * 0.19, 0.215), 0.015, 0.43) for sx in (-1, 1) for sy in (-1, 1)]
    return ("chair", prims, mats.make(pattern=str(mats.rng.choice(["stripes", "noise", "plain"])), smooth=False))


def make_piece(kind: str, mats: _Materials, spec: RoomSpec) -> _Piece:
    rng = mats.rng
    H = spec.height
    if kind == "desk":
        w, d, h = rng.uniform(1.2, 1.6), rng.uniform(0.7, 0.8), rng.uniform(0.72, 0.76)
        top = mats.make(pattern="wood", smooth=True)
        objs = [("desk", [Box((0, 0, h - 0.02), (w, d, 0.04))] + _legs(w / 2, d / 2, h - 0.04, 0.025, 0.06),
                 top)]
        n_ch = int(rng.integers(1, 3))
        for i in range(n_ch):
            cx = (i - (n_ch - 1) / 2) * w / 2
            objs.append(_chair(mats, cx, -d / 2 - 0.15, np.pi / 2 + rng.uniform(-0.4, 0.4)))
        # a monitor on top: a thin dark box
        objs.append(("monitor", [Box((rng.uniform(-0.2, 0.2) * w, 0.15, h + 0.25), (0.55, 0.03, 0.34)),
                                 Box((0, 0.2, h + 0.05), (0.2, 0.15, 0.1))],
                     mats.make(pattern="noise", base=np.array([0.12, 0.12, 0.14]), smooth=True)))
        return _Piece(objs, (w / 2 + 0.05, d / 2 + 0.5))
    if kind == "table":
        w, d, h = rng.uniform(1.4, 2.0), rng.uniform(0.8, 0.9), 0.75
        objs = [("table", [Box((0, 0, h - 0.02), (w, d, 0.04))] + _legs(w / 2, d / 2, h - 0.04, 0.03, 0.08),
                 mats.make(pattern="wood"))]
        n_side = int(rng.integers(1, 3))
        for i in range(n_side):
            cx = (i - (n_side - 1) / 2) * w / 2
            objs.append(_chair(mats, cx, -d / 2 - 0.15, np.pi / 2))
            objs.append(_chair(mats, cx, d / 2 + 0.15, -np.pi / 2))
        return _Piece(objs, (w / 2 + 0.05, d / 2 + 0.5))
    if kind == "round_table":
        r, h = rng.uniform(0.4, 0.55), 0.74
        objs = [("round_table", [Cylinder((0, 0, h - 0.02), r, 0.04), Cylinder((0, 0, (h - 0.04) / 2), 0.04, h - 0.04),
                                 Cylinder((0, 0, 0.015), 0.25, 0.03)], mats.make(pattern="noise"))]
        for k in range(int(rng.integers(2, 4))):
            a = 2 * np.pi * k / 3 + rng.uniform(-0.3, 0.3)
            objs.append(_chair(mats, (r + 0.15) * np.cos(a), (r + 0.15) * np.sin(a), a + np.pi))
        return _Piece(objs, (r + 0.45, r + 0.45))
    if kind == "couch":
        w, d = rng.uniform(1.8, 2.4), 0.9
        m = mats.make(pattern=str(rng.choice(["noise", "stripes"])), smooth=False, scale=rng.uniform(0.1, 0.3))
        prims: list[Primitive] = [Box((0, 0, 0.22), (w, d, 0.3)), Box((0, 0.05, 0.42), (w - 0.4, d - 0.2, 0.12)),
                                  Box((0, -d / 2 + 0.12, 0.6), (w, 0.24, 0.5)),
                                  Box((-w / 2 + 0.1, 0, 0.5), (0.2, d, 0.26)), Box((w / 2 - 0.1, 0, 0.5), (0.2, d, 0.26))]
        objs = [("couch", prims, m)]
        # coffee table in front
        objs.append(("coffee_table", [Box((0, d / 2 + 0.55, 0.4), (1.0, 0.55, 0.04))]
                     + [Cylinder((sx * 0.45, d / 2 + 0.55 + sy * 0.22, 0.19), 0.02, 0.38) for sx in (-1, 1) for sy in (-1, 1)],
                     mats.make(pattern="wood")))
        return _Piece([(n, [_shift(p, 0, -0.4) for p in ps], mm) for n, ps, mm in objs], (w / 2 + 0.05, d / 2 + 0.5), wall=True)
    if kind == "cupboard":
        w, d, h = rng.uniform(0.8, 1.4), rng.uniform(0.4, 0.5), rng.uniform(1.6, 2.1)
        m = mats.make(pattern=str(rng.choice(["wood", "plain", "noise"])))
        prims = [Box((0, 0, h / 2), (w, d, h))]
        handles = [Box((sx * 0.06, d / 2 + 0.01, h * 0.55), (0.02, 0.02, 0.18)) for sx in (-1, 1)]
        return _Piece([("cupboard", prims, m), ("handles", handles, mats.make(pattern="plain", base=np.array([0.7, 0.7, 0.72])))],
                      (w / 2, d / 2), wall=True)
    if kind == "shelf":
        w, d, h = rng.uniform(0.8, 1.2), 0.35, rng.uniform(1.5, 2.0)
        m = mats.make(pattern="wood")
        n_b = int(rng.integers(4, 6))
        prims = [Box((-w / 2 + 0.01, 0, h / 2), (0.02, d, h)), Box((w / 2 - 0.01, 0, h / 2), (0.02, d, h)),
                 Box((0, -d / 2 + 0.005, h / 2), (w, 0.01, h))]
        prims += [Box((0, 0, 0.02 + i * (h - 0.04) / (n_b - 1)), (w - 0.04, d, 0.02)) for i in range(n_b)]
        books: list[Primitive] = []
        for i in range(n_b - 1):
            z0 = 0.03 + i * (h - 0.04) / (n_b - 1)
            bh = rng.uniform(0.15, 0.28)
            bw = rng.uniform(0.3, w - 0.1)
            bx = rng.uniform(-w / 2 + 0.03 + bw / 2, w / 2 - 0.03 - bw / 2)
            books.append(Box((bx, 0.0, z0 + bh / 2 + 0.01), (bw, d - 0.08, bh)))
        return _Piece([("shelf", prims, m), ("books", books, mats.make(pattern="stripes", scale=0.05, contrast=0.8))],
                      (w / 2, d / 2), wall=True)
    if kind == "kitchen":
        w = rng.uniform(2.4, 3.5)
        counter = mats.make(pattern="plain")
        top = mats.make(pattern="noise", scale=0.05, base=np.array([0.3, 0.3, 0.32]))
        upper = mats.make(pattern="plain")
        objs = [("kitchen_counter", [Box((0, 0, 0.44), (w, 0.6, 0.88))], counter),
                ("countertop", [Box((0, 0.02, 0.9), (w + 0.02, 0.64, 0.04))], top),
                ("upper_cabinets", [Box((0, -0.12, 1.85), (w, 0.35, 0.7))], upper),
                ("fridge", [Box((w / 2 + 0.4, 0, 0.95), (0.7, 0.65, 1.9))],
                 mats.make(pattern="plain", base=np.array([0.88, 0.88, 0.9])))]
        return _Piece(objs, (w / 2 + 0.8, 0.33), wall=True)
    if kind == "plant":
        r = rng.uniform(0.15, 0.22)
        h = rng.uniform(0.9, 1.5)
        return _Piece([("pot", [Cylinder((0, 0, 0.2), r, 0.4)], mats.make(pattern="stripes", scale=0.1)),
                       ("foliage", [Cylinder((0, 0, 0.4 + (h - 0.4) / 2), r + 0.12, h - 0.4)],
                        mats.make(pattern="noise", scale=0.06, base=np.array([0.2, 0.45, 0.18]), smooth=False))],
                      (r + 0.12, r + 0.12))
    if kind == "bin":
        return _Piece([("bin", [Cylinder((0, 0, 0.2), 0.16, 0.4)], mats.make(pattern="plain"))], (0.16, 0.16))
    if kind == "pillar":
        return _Piece([("pillar", [Cylinder((0, 0, H / 2), 0.2, H - 0.002)], mats.make(pattern="noise",
                                                                                 base=np.array([0.8, 0.8, 0.78])))],
                      (0.2, 0.2))
    raise ValueError(f"unknown furniture kind {kind!r}")


def _shift(p: Primitive, dx: float, dy: float, dz: float = 0.0) -> Primitive:
    c = (p.center[0] + dx, p.center[1] + dy, p.center[2] + dz)
    if isinstance(p, Box):
        return Box(c, p.size, p.yaw)
    return Cylinder(c, p.radius, p.height)


def _place(p: Primitive, x: float, y: float, yaw: float, z0: float) -> Primitive:
    c, s = np.cos(yaw), np.sin(yaw)
    px, py, pz = p.center
    centre = (round(x + c * px - s * py, 6), round(y + s * px + c * py, 6), round(z0 + pz, 6))
    if isinstance(p, Box):
        return Box(centre, p.size, round(float((p.yaw + yaw + np.pi) % (2 * np.pi) - np.pi), 9))
    return Cylinder(centre, p.radius, p.height)


# ------------------------------------------------------------------------------ occupancy


class _FloorGrid:
    """A 5 cm raster of the floor marking what is taken (walls margin, drive corridor, furniture)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, path_pts: np.ndarray, corridor: float, res: float = 0.05):
        self.res = res
        xs = np.arange(lo[0] + res / 2, hi[0], res)
        ys = np.arange(lo[1] + res / 2, hi[1], res)
        self.gx, self.gy = np.meshgrid(xs, ys, indexing="ij")
        self.lo, self.hi = lo, hi
        from scipy.spatial import cKDTree

        d, _ = cKDTree(path_pts).query(np.stack([self.gx.ravel(), self.gy.ravel()], 1))
        self.taken = (d < corridor).reshape(self.gx.shape)

    def rect_mask(self, x: float, y: float, yaw: float, hx: float, hy: float) -> np.ndarray:
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy = self.gx - x, self.gy - y
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        return (np.abs(lx) <= hx) & (np.abs(ly) <= hy)

    def rect_inside(self, x: float, y: float, yaw: float, hx: float, hy: float, margin: float) -> bool:
        c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
        ex, ey = c * hx + s * hy, s * hx + c * hy
        return (x - ex >= self.lo[0] + margin and x + ex <= self.hi[0] - margin
                and y - ey >= self.lo[1] + margin and y + ey <= self.hi[1] - margin)


def build_room(name: str, rng: np.random.Generator, spec: RoomSpec | None = None) -> Room:
    """Generate the preset room `name` ('office' or 'common') with furniture placed by `rng`."""
    if spec is None:
        if name not in PRESETS:
            raise ValueError(f"unknown room preset {name!r}; choose one of {ROOM_NAMES}")
        spec = PRESETS[name]
    R = spec.turn_radius
    x0 = -spec.start_margin
    x1 = x0 + spec.length
    y0 = R - spec.width / 2
    y1 = y0 + spec.width
    zf = -LIDAR_HEIGHT_M
    zc = zf + spec.height
    straight = x1 - spec.end_margin - R
    drive = DriveSpec(straight=straight, radius=R)
    path = DrivePath(drive)
    mats = _Materials(rng)
    objects: list[SceneObject] = []

    def add(name_: str, kind: str, prims: list[Primitive], mat: Material) -> None:
        objects.append(SceneObject(name=f"{name_}_{len(objects)}", kind=kind, primitives=tuple(prims), material=mat))

    # shell: slabs 0.1 m thick outside the interior box
    th = 0.1
    L, W, H = spec.length, spec.width, spec.height
    cxm, cym = (x0 + x1) / 2, (y0 + y1) / 2
    wall_base = np.array(spec.wall_colours[rng.integers(len(spec.wall_colours))]) * rng.uniform(0.9, 1.05)
    floor_mat = mats.make(pattern=spec.floor_pattern, base=np.array([0.55, 0.5, 0.45]) * rng.uniform(0.8, 1.2, 3),
                          scale=0.5, smooth=True, contrast=0.3)
    add("floor", "floor", [Box((cxm, cym, zf - th / 2), (L + 2 * th, W + 2 * th, th))], floor_mat)
    add("ceiling", "ceiling", [Box((cxm, cym, zc + th / 2), (L + 2 * th, W + 2 * th, th))],
        mats.make(pattern="checker", base=np.array([0.92, 0.92, 0.9]), scale=0.6, contrast=0.1))
    walls = {
        "wall_back": Box((x0 - th / 2, cym, (zf + zc) / 2), (th, W, H)),
        "wall_front": Box((x1 + th / 2, cym, (zf + zc) / 2), (th, W, H)),
        "wall_right": Box((cxm, y0 - th / 2, (zf + zc) / 2), (L, th, H)),
        "wall_left": Box((cxm, y1 + th / 2, (zf + zc) / 2), (L, th, H)),
    }
    for wname, box in walls.items():
        add(wname, "wall", [box], mats.make(pattern=str(rng.choice(["noise", "stripes", "plain"])),
                                            base=wall_base * rng.uniform(0.92, 1.05, 3), scale=rng.uniform(0.3, 1.2),
                                            contrast=0.15))

    lo, hi = np.array([x0, y0]), np.array([x1, y1])
    grid = _FloorGrid(lo, hi, path.sample(0.05), spec.corridor)
    placed: dict[str, int] = {}
    # wall-hung flat items: posters, whiteboards, doors (do not take floor space except doors)
    wall_kinds = [k for k in ("door", "whiteboard", "poster") if k in spec.counts]
    free_kinds = [k for k in spec.counts if k not in wall_kinds]
    # big pieces first so they find room
    order = sorted(free_kinds, key=lambda k: -{"kitchen": 5, "couch": 4, "desk": 3, "table": 3, "cupboard": 2,
                                               "shelf": 2, "round_table": 2}.get(k, 0))
    walls_geo = [  # (x, y of the wall line start, direction along, inward normal yaw of the piece's +y)
        ("back", np.array([x0, y0]), np.array([0.0, 1.0]), W),
        ("front", np.array([x1, y1]), np.array([0.0, -1.0]), W),
        ("right", np.array([x1, y0]), np.array([-1.0, 0.0]), L),
        ("left", np.array([x0, y1]), np.array([1.0, 0.0]), L),
    ]
    for kind in order:
        for _ in range(spec.counts[kind]):
            piece = make_piece(kind, mats, spec)
            hx, hy = piece.half
            ok = False
            for _try in range(60):
                if piece.wall:
                    _, a, along, wlen = walls_geo[rng.integers(4)]
                    pos = rng.uniform(hx + 0.1, wlen - hx - 0.1) if wlen > 2 * hx + 0.2 else wlen / 2
                    inward = np.array([along[1], -along[0]])  # right of the walking direction = into the room
                    centre = a + along * pos + inward * (hy + 0.01)
                    yaw = float(np.arctan2(inward[1], inward[0]) - np.pi / 2)  # local +y -> inward
                    x, y = float(centre[0]), float(centre[1])
                else:
                    yaw = float(rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2]) + rng.uniform(-0.2, 0.2))
                    x, y = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
                if not grid.rect_inside(x, y, yaw, hx, hy, 0.0 if piece.wall else 0.15):
                    continue
                need = grid.rect_mask(x, y, yaw, hx, hy)
                if not need.any() or grid.taken[need].any():
                    continue
                ok = True
                break
            if not ok:
                continue
            grid.taken |= grid.rect_mask(x, y, yaw, hx + spec.gap, hy + spec.gap)
            placed[kind] = placed.get(kind, 0) + 1
            for oname, prims, mat in piece.objects:
                add(oname, kind, [_place(p, x, y, yaw, zf) for p in prims], mat)
    for kind in wall_kinds:
        for _ in range(spec.counts[kind]):
            _, a, along, wlen = walls_geo[rng.integers(4)]
            if kind == "door":
                w, h, z = 0.95, 2.05, 0.0
            elif kind == "whiteboard":
                w, h, z = rng.uniform(1.2, 1.8), rng.uniform(0.9, 1.2), 0.9
            else:
                w, h, z = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.9), rng.uniform(0.9, 1.4)
            if wlen < w + 0.4:
                continue
            pos = rng.uniform(w / 2 + 0.2, wlen - w / 2 - 0.2)
            inward = np.array([along[1], -along[0]])
            centre = a + along * pos + inward * 0.011
            yaw = float(np.arctan2(along[1], along[0]))
            box = Box((round(float(centre[0]), 6), round(float(centre[1]), 6), round(zf + z + h / 2, 6)), (w, 0.02, h),
                      round(yaw, 9))
            if kind == "door":
                mat = mats.make(pattern="wood", scale=0.3)
            elif kind == "whiteboard":
                mat = mats.make(pattern="noise", base=np.array([0.95, 0.95, 0.95]), scale=0.05, contrast=0.2)
            else:
                mat = mats.make(pattern=str(rng.choice(["checker", "stripes", "noise"])), contrast=0.9,
                                scale=rng.uniform(0.05, 0.2))
            placed[kind] = placed.get(kind, 0) + 1
            add(kind, kind, [box], mat)
    scene = Scene(objects=objects, name=spec.name, extent_lo=(x0, y0, zf), extent_hi=(x1, y1, zc),
                  meta={"preset": spec.name, "floor_z": zf, "ceiling_z": zc, "lidar_height": LIDAR_HEIGHT_M,
                        "area_m2": L * W, "placed": placed,
                        "drive": {"straight": drive.straight, "radius": drive.radius}})
    return Room(scene=scene, drive=drive, spec=spec, placed=placed)


RoomBuilder = Callable[[np.random.Generator], Room]
