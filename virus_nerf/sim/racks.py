"""Warehouse racking (docs/method.md 5): rows of shelving racks along the drive direction.

The warehouse preset (`rooms.PRESETS["warehouse"]`) fills its hall with rows of pallet /
shelving racks parallel to x: one row between the two legs of the drive loop (so the legs run
down two parallel aisles) and further rows on both sides, aisle after aisle, up to the side
walls (the outermost rows stand against the walls). The rows start after an open cross-aisle
at the back (the start U-turn), end before one at the front (the far U-turn) and are cut by an
open cross-aisle in the middle; each row is a sequence of bays 2.5-3 m long, grouped into runs
with occasional 1-2 m gaps between them. A run is one rack: upright posts at the bay ends,
3-4 shelf decks spanning the run and goods (boxes of varied sizes and materials) filling
the shelves in part, so some shelves can be seen through.

Every bay is checked against the floor raster (`rooms._FloorGrid`): a bay that would touch the
drive corridor is left out, so the path stays free whatever the parameters. Deterministic for
a given numpy Generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from virus_nerf.sim.furniture import Materials
from virus_nerf.sim.scene import Box, Material, Primitive

POST_M = 0.08  # upright post section, m
DECK_M = 0.05  # shelf deck thickness, m
FLOOR_DECK_M = 0.12  # top of the lowest deck above the floor, m
MIN_BAY_M = 1.2  # shortest bay (the one that fills the end of a block), m
RACK_KINDS = ("rack", "goods")  # SceneObject kinds of the racking


class _Grid(Protocol):
    taken: np.ndarray

    def rect_mask(self, x: float, y: float, yaw: float, hx: float, hy: float) -> np.ndarray: ...

    def rect_inside(self, x: float, y: float, yaw: float, hx: float, hy: float, margin: float) -> bool: ...


@dataclass(frozen=True)
class RackSpec:
    """Racking parameters (metres; (lo, hi) pairs are uniform ranges drawn per row / run / bay).

    depth: rack depth of the side rows; centre_depth: of the row between the drive legs (capped
    so the corridor stays free); aisle: free width between neighbouring rows; bay: bay length;
    height: rack (upright) height, per row; gap / gap_prob: length of and chance (after each
    bay) of a gap that ends a run; cross_aisle: width of the open cross-aisle across all rows
    near the middle of the hall; row_start: x where the rows begin (behind: the back
    cross-aisle with the start U-turn); row_end: how far before the far U-turn (x = straight)
    the rows end; wall_gap: space left between the outermost rows and the side walls;
    fill: probabilities of 0, 1, 2, 3 goods per bay and shelf level."""

    depth: tuple[float, float] = (1.0, 1.2)
    centre_depth: tuple[float, float] = (1.0, 1.1)
    aisle: tuple[float, float] = (2.5, 3.3)
    bay: tuple[float, float] = (2.5, 3.0)
    height: tuple[float, float] = (2.0, 4.0)
    gap: tuple[float, float] = (1.0, 2.0)
    gap_prob: float = 0.15
    cross_aisle: tuple[float, float] = (2.8, 3.4)
    row_start: float = 0.8
    row_end: float = 0.3
    wall_gap: float = 0.05
    fill: tuple[float, float, float, float] = (0.2, 0.35, 0.3, 0.15)


@dataclass
class RackLayout:
    """The generated racking: scene objects (name, kind, primitives, material) and facts for
    scene.meta (rows: y centre, depth, height, runs as [x_lo, x_hi]; cross_aisles: [x_lo, x_hi]
    of the open cross-aisle(s) between the back and the front one, free across all rows)."""

    objects: list[tuple[str, str, list[Primitive], Material]] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)
    cross_aisles: list[list[float]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)


def plan_rows(spec: RackSpec, rng: np.random.Generator, y_mid: float, y_lo: float, y_hi: float,
              centre_max: float) -> list[tuple[float, float]]:
    """Rows as (y centre, depth), sorted by y: the centre row at y_mid (depth <= centre_max),
    then rows outwards on both sides separated by aisles, the last ones close to the walls."""
    d0 = min(float(rng.uniform(*spec.centre_depth)), centre_max)
    rows = [(y_mid, d0)]
    a_lo, a_hi = spec.aisle
    d_lo, d_hi = spec.depth
    for side, wall in ((-1.0, y_lo), (1.0, y_hi)):
        edge = y_mid + side * d0 / 2
        space = abs(wall - edge) - spec.wall_gap
        n = int(space // (a_lo + d_lo))
        if n < 1:
            continue
        depths = rng.uniform(d_lo, d_hi, n)
        extra = max(0.0, space - depths.sum() - n * a_lo)
        aisles = np.minimum(a_lo + extra * rng.dirichlet(np.ones(n)), a_hi)  # leftover -> at the wall
        y = edge
        for a, d in zip(aisles, depths, strict=True):
            y += side * (a + d / 2)
            rows.append((float(y), float(d)))
            y += side * d / 2
    return sorted(rows)


def _bays(spec: RackSpec, rng: np.random.Generator, x0: float, x1: float) -> list[list[tuple[float, float]]]:
    """Runs of contiguous bays [(x_lo, x_hi), ...] laid from x0 towards x1 with random gaps; a
    last, shorter bay (>= MIN_BAY_M) fills the end, so less than MIN_BAY_M is left before x1."""
    runs: list[list[tuple[float, float]]] = []
    run: list[tuple[float, float]] = []
    pos = x0
    b_lo = spec.bay[0]
    while x1 - pos >= b_lo - 1e-9:
        b = min(float(rng.uniform(*spec.bay)), x1 - pos)
        run.append((pos, pos + b))
        pos += b
        if rng.random() < spec.gap_prob and x1 - pos >= spec.gap[1] + b_lo:
            runs.append(run)
            run = []
            pos += float(rng.uniform(*spec.gap))
    if x1 - pos >= MIN_BAY_M:
        run.append((pos, x1))
    if run:
        runs.append(run)
    return runs


def _goods_materials(mats: Materials, n: int) -> list[Material]:
    """Materials of the goods on one rack: cardboard first, then crates / wrapped pallets."""
    rng = mats.rng
    out = [mats.make(pattern=str(rng.choice(["noise", "stripes"])), smooth=False,
                     base=np.array([0.62, 0.47, 0.30]) * rng.uniform(0.85, 1.15, 3),
                     scale=float(rng.uniform(0.1, 0.3)), contrast=0.3)]
    for _ in range(n - 1):
        if rng.random() < 0.3:  # shrink-wrapped: light, glossy
            out.append(mats.make(pattern="noise", base=np.array([0.86, 0.87, 0.88]) * rng.uniform(0.9, 1.05, 3),
                                 scale=float(rng.uniform(0.05, 0.2)), contrast=0.25))
        else:  # plastic crates / printed boxes in palette colours
            out.append(mats.make(pattern=str(rng.choice(["stripes", "checker", "noise"])), contrast=0.6,
                                 scale=float(rng.uniform(0.08, 0.3))))
    return out


def build_racks(spec: RackSpec, rng: np.random.Generator, mats: Materials, grid: _Grid, *, y_mid: float,
                y_lo: float, y_hi: float, straight: float, centre_max: float, zf: float,
                gap: float) -> RackLayout:
    """Generate the racking of a hall whose interior spans y_lo..y_hi; the drive's straight legs
    run from x = 0 to x = straight on either side of y_mid. Bays touching grid.taken (the drive
    corridor) are left out; placed racks are marked taken with `gap` around them (m).
    zf: floor height (m)."""
    out = RackLayout()
    xs, xe = spec.row_start, straight - spec.row_end
    w = float(rng.uniform(*spec.cross_aisle))
    mid = (xs + xe) / 2 + float(rng.uniform(-0.1, 0.1)) * (xe - xs)
    blocks = [(xs, mid - w / 2), (mid + w / 2, xe)]
    n_runs = n_bays = n_goods = 0
    for ri, (yc, d) in enumerate(plan_rows(spec, rng, y_mid, y_lo, y_hi, centre_max)):
        h = float(rng.uniform(*spec.height))
        n_lev = 3 if h < 2.6 else int(rng.integers(3, 5))
        step = (h - FLOOR_DECK_M) / n_lev  # deck-to-deck spacing
        clear = step - DECK_M - 0.04  # free height for goods on a deck
        frame_mat = mats.make(pattern="noise", base=np.array([0.16, 0.30, 0.62]) * rng.uniform(0.8, 1.2, 3),
                              scale=0.15, contrast=0.25)
        deck_mat = mats.make(pattern="stripes", base=np.array([0.88, 0.45, 0.10]) * rng.uniform(0.85, 1.1, 3),
                             scale=0.1, contrast=0.45)
        row_runs: list[list[float]] = []
        for b0, b1 in blocks:
            for bays in _bays(spec, rng, b0, b1):
                # keep only bays clear of the corridor (splitting the run where one is dropped)
                pieces: list[list[tuple[float, float]]] = [[]]
                for lo_, hi_ in bays:
                    xc, hx = (lo_ + hi_) / 2, (hi_ - lo_) / 2
                    need = grid.rect_mask(xc, yc, 0.0, hx, d / 2)
                    if grid.rect_inside(xc, yc, 0.0, hx, d / 2, 0.0) and not grid.taken[need].any():
                        pieces[-1].append((lo_, hi_))
                    elif pieces[-1]:
                        pieces.append([])
                for run in (p for p in pieces if p):
                    n_goods += _add_run(out, rng, mats, run, yc, d, h, n_lev, step, clear, zf, frame_mat, deck_mat,
                                        spec.fill, f"r{ri}")
                    x_lo, x_hi = run[0][0], run[-1][1]
                    grid.taken |= grid.rect_mask((x_lo + x_hi) / 2, yc, 0.0, (x_hi - x_lo) / 2 + gap, d / 2 + gap)
                    row_runs.append([round(x_lo, 6), round(x_hi, 6)])
                    n_runs += 1
                    n_bays += len(run)
        out.rows.append({"y": round(yc, 6), "depth": round(d, 6), "height": round(h, 6), "levels": n_lev,
                         "runs": row_runs})
    # the open cross-aisle: from the last rack end before `mid` to the first start after it, in
    # all rows; kept free of the pallets placed later
    ends = [r[1] for row in out.rows for r in row["runs"] if r[1] <= mid]
    starts = [r[0] for row in out.rows for r in row["runs"] if r[0] >= mid]
    c0, c1 = max(ends, default=mid - w / 2), min(starts, default=mid + w / 2)
    out.cross_aisles = [[round(c0, 6), round(c1, 6)]]
    grid.taken |= grid.rect_mask((c0 + c1) / 2, (y_lo + y_hi) / 2, 0.0, (c1 - c0) / 2, (y_hi - y_lo) / 2)
    out.counts = {"rack_row": len(out.rows), "rack": n_runs, "rack_bay": n_bays, "goods": n_goods}
    return out


def _add_run(out: RackLayout, rng: np.random.Generator, mats: Materials, run: list[tuple[float, float]],
             yc: float, d: float, h: float, n_lev: int, step: float, clear: float, zf: float,
             frame_mat: Material, deck_mat: Material, fill: tuple[float, ...], tag: str) -> int:
    """Add one rack (contiguous bays) as objects: frame (posts), decks, goods by material."""
    x_lo, x_hi = run[0][0], run[-1][1]
    p = POST_M / 2
    ends = [x_lo] + [b[1] for b in run]
    posts: list[Primitive] = []
    for xb in ends:
        xp = min(max(xb, x_lo + p), x_hi - p)  # end posts inside the footprint
        for sy in (-1.0, 1.0):
            posts.append(Box(_r((xp, yc + sy * (d / 2 - p), zf + h / 2)), (POST_M, POST_M, round(h, 6))))
    decks: list[Primitive] = [
        Box(_r(((x_lo + x_hi) / 2, yc, zf + FLOOR_DECK_M + k * step - DECK_M / 2)), (round(x_hi - x_lo, 6), round(d, 6), DECK_M))
        for k in range(n_lev)
    ]
    n_mat = int(rng.integers(2, 4))
    goods_mats = _goods_materials(mats, n_mat)
    goods: list[list[Primitive]] = [[] for _ in range(n_mat)]
    p_fill = np.asarray(fill, dtype=np.float64) / np.sum(fill)
    for b0, b1 in run:
        inner = b1 - b0 - POST_M - 0.04
        for k in range(n_lev):
            z0 = zf + FLOOR_DECK_M + k * step
            n = int(rng.choice(len(p_fill), p=p_fill))
            if n == 0:
                continue
            slot = inner / n
            for j in range(n):
                gw = min(1.3, slot * float(rng.uniform(0.55, 0.95)))
                gd = d * float(rng.uniform(0.6, 0.95))
                gh = max(0.2, clear * float(rng.uniform(0.35, 0.95)))
                gx = b0 + POST_M / 2 + 0.02 + slot * (j + 0.5) + float(rng.uniform(-1, 1)) * (slot - gw) / 2
                gy = yc + float(rng.uniform(-1, 1)) * (d - gd) / 2
                goods[int(rng.integers(n_mat))].append(Box(_r((gx, gy, z0 + gh / 2)), _r((gw, gd, gh))))
    out.objects.append((f"rack_frame_{tag}", "rack", posts, frame_mat))
    out.objects.append((f"rack_decks_{tag}", "rack", decks, deck_mat))
    for m, g in zip(goods_mats, goods, strict=True):
        if g:
            out.objects.append((f"goods_{tag}", "goods", g, m))
    return sum(len(g) for g in goods)


def _r(v: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(round(float(a), 6) for a in v)
