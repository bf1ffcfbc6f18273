"""Room presets (docs/method.md 5): an office (~72 m^2), a common area (~216 m^2) and a
warehouse (~512 m^2) from primitives.

Each room is a box shell (4 walls, floor, ceiling as slabs) with furniture placed at random
(numpy Generator) outside a corridor around the robot's drive loop, so nothing ever blocks the
path. Wall items (cupboards, shelves, kitchen counter) stand against a wall; free items
(desks with chairs, tables, couches, plants, pillars, pallets) stand in the open. The warehouse
first fills its hall with rows of shelving racks (`racks.py`): the drive's two legs run down
two parallel aisles on either side of a rack row, and its U-turns lie in open cross-aisles at
the back and the front of the hall. Every surface carries a procedural texture (per-object
colours plus stripes / checker / noise / wood patterns).
The robot starts at the origin heading +x with its LiDAR `rig.LIDAR_HEIGHT_M` above the floor,
so the floor is at z = -LIDAR_HEIGHT_M.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from virus_nerf.sensors.rig import LIDAR_HEIGHT_M
from virus_nerf.sim.furniture import Materials, make_piece, place
from virus_nerf.sim.racks import RackSpec, build_racks
from virus_nerf.sim.scene import Box, Material, Primitive, Scene, SceneObject
from virus_nerf.sim.trajectory import DrivePath, DriveSpec

ROOM_NAMES: tuple[str, ...] = ("office", "common", "warehouse")


@dataclass(frozen=True)
class RoomSpec:
    """Preset parameters (metres). length along x (the drive direction), width along y.
    start_margin: start point to the back wall; end_margin: far U-turn apex to the front wall.
    corridor: clearance kept free around the drive centreline; gap: minimum free space between
    furniture groups (larger = more spread). counts: furniture kind -> how many to try to place.
    racks: shelving racks filling the hall before the furniture (the warehouse), None = none.
    wall_sides: walls ('back', 'front', 'right', 'left') carrying doors and posters, kept from
    overlapping each other; None = any wall, overlaps not checked (the office and common area)."""

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
    floor_colour: tuple[float, float, float] = (0.55, 0.5, 0.45)
    racks: RackSpec | None = None
    wall_sides: tuple[str, ...] | None = None


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
    # 32 x 16 x 6 m hall: the drive legs (y = 0 and y = 3) run down two aisles either side of
    # a rack row; the start U-turn lies in the back cross-aisle (x < 0.8), the far U-turn in
    # the front one (x > straight - 0.3 = 25.7); doors and signs on the back and front walls.
    "warehouse": RoomSpec(
        name="warehouse", length=32.0, width=16.0, height=6.0, turn_radius=1.5,
        start_margin=3.0, end_margin=1.5,
        counts={"pallet": 5, "dock_door": 2, "door": 2, "poster": 4},
        gap=0.6, corridor=0.7, floor_pattern="noise",
        wall_colours=((0.78, 0.79, 0.80), (0.72, 0.74, 0.76)), floor_colour=(0.52, 0.52, 0.5),
        racks=RackSpec(), wall_sides=("back", "front"),
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
    """Generate the preset room `name` (one of ROOM_NAMES) with furniture placed by `rng`."""
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
    mats = Materials(rng)
    objects: list[SceneObject] = []

    def add(name_: str, kind: str, prims: list[Primitive], mat: Material) -> None:
        objects.append(SceneObject(name=f"{name_}_{len(objects)}", kind=kind, primitives=tuple(prims), material=mat))

    # shell: slabs 0.1 m thick outside the interior box
    th = 0.1
    L, W, H = spec.length, spec.width, spec.height
    cxm, cym = (x0 + x1) / 2, (y0 + y1) / 2
    wall_base = np.array(spec.wall_colours[rng.integers(len(spec.wall_colours))]) * rng.uniform(0.9, 1.05)
    floor_mat = mats.make(pattern=spec.floor_pattern, base=np.array(spec.floor_colour) * rng.uniform(0.8, 1.2, 3),
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
    racks_meta: dict = {}
    if spec.racks is not None:
        # the centre row may be as deep as the lanes allow with the corridor (and the weave) kept
        centre_max = 2 * (R - drive.weave_amplitude - spec.corridor - 0.05)
        layout = build_racks(spec.racks, rng, mats, grid, y_mid=R, y_lo=y0, y_hi=y1, straight=straight,
                             centre_max=centre_max, zf=zf, gap=spec.gap)
        for oname, kind, prims, mat in layout.objects:
            add(oname, kind, prims, mat)
        placed.update(layout.counts)
        racks_meta = {"rows": layout.rows, "cross_aisles": layout.cross_aisles}
    # wall-hung flat items: posters, whiteboards, doors (do not take floor space except doors)
    wall_kinds = [k for k in ("dock_door", "door", "whiteboard", "poster") if k in spec.counts]  # big first
    free_kinds = [k for k in spec.counts if k not in wall_kinds]
    # big pieces first so they find room
    order = sorted(free_kinds, key=lambda k: -{"kitchen": 5, "couch": 4, "desk": 3, "table": 3, "cupboard": 2,
                                               "shelf": 2, "round_table": 2, "pallet": 1}.get(k, 0))
    walls_geo = [  # (x, y of the wall line start, direction along, inward normal yaw of the piece's +y)
        ("back", np.array([x0, y0]), np.array([0.0, 1.0]), W),
        ("front", np.array([x1, y1]), np.array([0.0, -1.0]), W),
        ("right", np.array([x1, y0]), np.array([-1.0, 0.0]), L),
        ("left", np.array([x0, y1]), np.array([1.0, 0.0]), L),
    ]
    for kind in order:
        for _ in range(spec.counts[kind]):
            piece = make_piece(kind, mats, spec.height)
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
                add(oname, kind, [place(p, x, y, yaw, zf) for p in prims], mat)
    walls_named = {g[0]: g for g in walls_geo}
    wall_used: dict[str, list[tuple[float, float]]] = {}  # wall -> occupied [lo, hi] along it (wall_sides)
    for kind in wall_kinds:
        for _ in range(spec.counts[kind]):
            if spec.wall_sides is None:
                wname, a, along, wlen = walls_geo[rng.integers(4)]
            else:
                wname, a, along, wlen = walls_named[spec.wall_sides[rng.integers(len(spec.wall_sides))]]
            if kind == "door":
                w, h, z = 0.95, 2.05, 0.0
            elif kind == "dock_door":  # a roller shutter of a loading dock
                w, h, z = rng.uniform(2.8, 3.6), rng.uniform(3.0, min(4.0, H - 0.5)), 0.0
            elif kind == "whiteboard":
                w, h, z = rng.uniform(1.2, 1.8), rng.uniform(0.9, 1.2), 0.9
            else:
                w, h, z = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.9), rng.uniform(0.9, 1.4)
            if wlen < w + 0.4:
                continue
            pos = rng.uniform(w / 2 + 0.2, wlen - w / 2 - 0.2)
            if spec.wall_sides is not None:
                for _try in range(30):
                    if all(pos + w / 2 + 0.3 <= lo_ or pos - w / 2 - 0.3 >= hi_ for lo_, hi_ in wall_used.get(wname, [])):
                        break
                    wname, a, along, wlen = walls_named[spec.wall_sides[rng.integers(len(spec.wall_sides))]]
                    pos = rng.uniform(w / 2 + 0.2, max(w / 2 + 0.2, wlen - w / 2 - 0.2))
                else:
                    continue
                wall_used.setdefault(wname, []).append((pos - w / 2, pos + w / 2))
            inward = np.array([along[1], -along[0]])
            centre = a + along * pos + inward * 0.011
            yaw = float(np.arctan2(along[1], along[0]))
            box = Box((round(float(centre[0]), 6), round(float(centre[1]), 6), round(zf + z + h / 2, 6)), (w, 0.02, h),
                      round(yaw, 9))
            if kind == "door":
                mat = mats.make(pattern="wood", scale=0.3)
            elif kind == "dock_door":
                mat = mats.make(pattern="stripes", base=np.array([0.6, 0.62, 0.65]) * rng.uniform(0.85, 1.1, 3),
                                scale=0.12, contrast=0.4)
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
                        "drive": {"straight": drive.straight, "radius": drive.radius}}
                  | ({"racks": racks_meta} if racks_meta else {}))
    return Room(scene=scene, drive=drive, spec=spec, placed=placed)
