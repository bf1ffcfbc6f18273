"""Furniture of the simulated rooms (docs/method.md 5): desks, chairs, tables, couches, shelves,
plants, pillars and loaded pallets as primitives in a piece frame, with seeded procedural materials.

`make_piece` builds one piece at the origin; `place` moves a primitive of it into the room.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.sim.scene import Box, Cylinder, Material, Primitive

_PALETTE = np.array([
    [0.62, 0.45, 0.30], [0.35, 0.40, 0.55], [0.70, 0.20, 0.18], [0.20, 0.45, 0.30],
    [0.85, 0.75, 0.35], [0.50, 0.50, 0.52], [0.15, 0.18, 0.22], [0.80, 0.55, 0.45],
    [0.30, 0.60, 0.70], [0.55, 0.30, 0.55], [0.90, 0.88, 0.82], [0.40, 0.28, 0.18],
])


class Materials:
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


def _chair(mats: Materials, x: float, y: float, yaw: float) -> tuple[str, list[Primitive], Material]:
    """Chair at (x, y) in the piece frame facing direction yaw (its back behind)."""
    c, s = np.cos(yaw), np.sin(yaw)

    def at(lx: float, ly: float, z: float) -> tuple[float, float, float]:
        return (x + c * lx - s * ly, y + s * lx + c * ly, z)

    prims: list[Primitive] = [Box(at(0, 0, 0.45), (0.44, 0.44, 0.05), yaw),
                              Box(at(-0.2, 0, 0.72), (0.04, 0.42, 0.46), yaw)]
    prims += [Cylinder(at(sx * 0.19, sy * 0.19, 0.215), 0.015, 0.43) for sx in (-1, 1) for sy in (-1, 1)]
    return ("chair", prims, mats.make(pattern=str(mats.rng.choice(["stripes", "noise", "plain"])), smooth=False))


def make_piece(kind: str, mats: Materials, room_height: float) -> _Piece:
    rng = mats.rng
    H = room_height  # m, floor to ceiling
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
    if kind == "pallet":  # a loaded pallet standing on the floor (warehouse): 1-2 layers of goods
        w, d = (1.2, 0.8) if rng.random() < 0.7 else (1.2, 1.0)
        goods: list[Primitive] = []
        z = 0.144
        for _ in range(int(rng.integers(1, 3))):
            gw, gd, gh = w * rng.uniform(0.8, 1.0), d * rng.uniform(0.8, 1.0), rng.uniform(0.4, 0.8)
            goods.append(Box((rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), z + gh / 2), (gw, gd, gh)))
            z += gh
        return _Piece([("pallet", [Box((0, 0, 0.072), (w, d, 0.144))],
                        mats.make(pattern="wood", base=np.array([0.68, 0.55, 0.38]), scale=0.2, smooth=False)),
                       ("pallet_goods", goods, mats.make(pattern=str(rng.choice(["noise", "stripes", "checker"])),
                                                         scale=rng.uniform(0.08, 0.3)))],
                      (w / 2, d / 2))
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


def place(p: Primitive, x: float, y: float, yaw: float, z0: float) -> Primitive:
    c, s = np.cos(yaw), np.sin(yaw)
    px, py, pz = p.center
    centre = (round(x + c * px - s * py, 6), round(y + s * px + c * py, 6), round(z0 + pz, 6))
    if isinstance(p, Box):
        return Box(centre, p.size, round(float((p.yaw + yaw + np.pi) % (2 * np.pi) - np.pi), 9))
    return Cylinder(centre, p.radius, p.height)


# ------------------------------------------------------------------------------ occupancy
