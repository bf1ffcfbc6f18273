"""One map extraction for every consumer: `virus-nerf export` (a trained run), the Mapper's
`map2d` / `probability_map` / snapshots (mapping while driving) and the planner-safety figure.

The 2D map of a trained model is its own 360 deg scans in the camera-height band from evenly
spread camera positions, rasterised (maps/occupancy.py: passed cells free, end cells occupied; a
scan that nothing stopped free up to the first surface a sensor touched; free too what the stereo
cameras looked through at camera height, maps/evidence.py), occupied where its scans just below
the band end (the scan rule; what the robot's body meets; they end where their opacity first
reaches MAP_LOW_FRONT_OPACITY once the field has trained MAP_LOW_FRONT_FROM_STEP steps) and unknown
up to 1 m behind what they met (0.5 m in a fitted box up to 12 m: an office's furniture, not a
warehouse's goods), where a camera measured a surface and none of them passed (what the body's
rays did not see), then unknown wherever no sensor looked (maps/observed.py), occupied
wherever the infrared or ultrasonic sensors touched an obstacle the scans called free
(maps/planner.py), and free where a camera stood. The probability map is the VIRUS grid's
occupancy probability at camera height, 0.5 where no sensor looked. The caller chooses the
positions and the observed mask (a run: the recording's frames; the Mapper: the frames it has).
"""

from __future__ import annotations

import numbers

import numpy as np
import torch

from virus_nerf.errors import UsageError
from virus_nerf.maps.evidence import Rays2D
from virus_nerf.maps.observed import apply_mask
from virus_nerf.maps.occupancy import (
    FREE,
    MAX_PIXELS,
    OCCUPIED,
    UNKNOWN,
    OccupancyMap2D,
    probability_slice,
    raster_shape,
    raw_map,
    ray_ends,
    ray_points,
    scan_counts,
    scan_rule_occupied,
    to_image,
    world_pixels,
)
from virus_nerf.maps.planner import (
    USS_EXPLAINED_M,
    RangeEvidence,
    near_surfaces,
    planner_image,
    track_free,
    uss_arcs,
)
from virus_nerf.maps.scans import scan_rays
from virus_nerf.sensors.rig import MAIN_STACK
from virus_nerf.utils.memory import require_memory

# working memory of the 2D rasters per pixel (scan counts, observed mask, planner votes, distance
# transforms, the probability slice, the ESDF): the slope of `export --what map,prob,esdf`'s peak
# RSS over pixels (office 81, D101): 4.7 M px 0.90 GB, 19.0 M px 1.75 GB, 75.8 M px 5.19 GB, 60
# bytes a pixel (D48: 53); the scans' pass points and the view wedges go in chunks, and the IRS
# hits' test for a scan end nearby is a distance transform, so nothing else grows with the raster
RASTER_BYTES_PER_PIXEL = 64
# the map's scan rays start at these heights (m) above the camera, in turn: the +-5 cm band that
# the 2D map and its ground truth stand for (evaluation.height_band_m), sampled at the cost of one
# plane (D56: office free recall 83.3 -> 85.7 %, warehouse obstacles marked free 16.7 -> 16.4 %)
MAP_SCAN_HEIGHTS_M = (-0.05, 0.0, 0.05)
# and rays cast below the band, half as many, at these heights in turn: the robot's body below its
# cameras meets what they hit (the 0.3 m of the IRS hits and stereo points, maps/planner.py), so a
# pixel they call occupied by the scan rule (ends >= half the passes: a floater near the floor that
# most rays pass is not one) is occupied where the band said free, and their passes claim nothing;
# they point between the band's rays (D60: goods and pallet tops just below camera height)
MAP_LOW_HEIGHTS_M = (-0.15, -0.3)
MAP_LOW_RAYS_SHARE = 0.5  # low rays per band ray
# behind what the low rays met (a pixel they call occupied), the band's free pixels that no low ray
# passed are unknown up to this far (m): the band passes over a box whose top is at camera height,
# and the robot's body cannot see past its front (D64: the warehouse's goods tops)
MAP_LOW_SHADOW_M = 1.0
# ... and this far in a fitted box whose longest horizontal side is at most MAP_SMALL_ROOM_M (an
# office; `low_shadow_depth`): what the band passes over there is furniture, not rows of goods
# a metre deep. On rooms 81-86 offline the offices' free recall rose 88.41 -> 89.31 % with every
# obstacle figure within 2 m the same; in the warehouses 0.5 m everywhere marked 1.24 / 2.13 /
# 5.13 % of the obstacles free (D95, D111). 12 m is D77's boundary between the simulated offices'
# 9.2 m boxes and the common areas' 18.2 m, a constant of the map's own (weights.free_stereo_room_m, the
# same 12 m, is the training's knob). A grown box's room is not known while it grows: 1 m
MAP_LOW_SHADOW_SMALL_ROOM_M = 0.5
MAP_SMALL_ROOM_M = 12.0
# the low rays march over the grid's occupied cells grown by this many cells up and down: the
# fitted warehouse's 25 cm cells beside a box whose top is at camera height are empty though the
# field holds the box, and a low ray skipped it (D66); the band's rays march the grid as trained
MAP_LOW_GRID_GROW_Z = 1
# and the low rays at these heights march the occupied cells grown by one cell in x and y as well
# (`grown_around`): goods on a rack whose tops stand at camera height fill too little of the
# fitted warehouse's 25 cm cells to keep them, and the rays 15 cm below the cameras passed them;
# the 30 cm rays keep D66's cells, near the floor's haze that grown cells would make ends (D73)
MAP_LOW_AROUND_HEIGHTS_M = (-0.15,)
# a low ray ends where its opacity first reaches this level (render/compositing.opacity_front), not
# at D / A like the band's: a round object or a pillar that the cameras saw from one side is soft
# density, and D / A lies 0.15-0.2 m inside its rim, where the band's passes made the rim free
# (D90, D93, D94: on rooms 81-86 offline and driving every obstacle target met and no planner path
# through an obstacle, for 0.5-1.9 points of free recall: the front also lies in the haze before walls)
MAP_LOW_FRONT_OPACITY = 0.1
# ... once the field has trained this many steps; before, they end at D / A as the band's rays do. A
# field of a few steps holds a thin haze everywhere (about 1 /m), whose front lies 0.1 m from the
# cameras: a ring of occupied pixels around the robot. The test drive's office (3 s, 90 rays from 5
# positions) after 2 / 5 / 10 / 20 steps: its occupied pixels lie farther from the room's surfaces
# than its free ones (0.96 against 0.75 m at 10 steps) and it keeps a third of D / A's free pixels;
# from 40 steps both rules give sane maps (D94). Every map D94 measured had 241 steps or more
MAP_LOW_FRONT_FROM_STEP = 100
# a low ray's end casts that shadow only where the cameras measured a surface (a stereo point within
# 0.5 m of camera height) within this horizontal distance (m) of it: of the low ends the simulator
# says are real 93-99 % have one, of the false ones (the field's haze near the floor, which casts two
# thirds of the offices' shadow over free floor) 40-68 % (D80; at 0.1 m 78-92 % and 16-36 %, and the
# warehouse's goods, whose fronts the cameras see at grazing angles, lose their shadow). A run without
# stereo points keeps D64's rule (every end casts)
MAP_LOW_SUPPORT_M = 0.2
# and a low ray's end pixel is occupied only where a sensor backs it when it is a lone one: no other
# pixel the low rays call occupied among its 8 neighbours and one low ray ended there; backed by a
# stereo point within 0.5 m of camera height or an IRS hit within MAP_LOW_SUPPORT_M of its centre, or
# by a USS echo's arc that it would explain (maps/planner.py). Such a pixel is a 0.6 m disk to a
# planner with a 0.3 m robot, and 1.5 % of the warehouses' aisles were specks, half of them these
# (D86, D87); a real edge of a pallet or goods is met by more rays or measured (dropping every lone
# end: within 1 m of the path 0.41 -> 1.09 % marked free). A run without stereo points or IRS hits
# keeps every end
MAP_LOW_LONE_HITS = 1
# a band ray that nothing in the box stops (its opacity never reaches the scan's 0.5: the grid
# emptied the cells of a wall the field still holds) passed free space as far as it goes, but not
# where it ends; it marks free what it passed up to this distance (m) from the first IRS hit or
# stereo point at camera height that it meets, and no closer than MAP_THROUGH_MARGIN_M to the box's
# side (the fitted box's walls, and the counters and cupboards against them), D80
MAP_THROUGH_STOP_M = 0.1
MAP_THROUGH_MARGIN_M = 1.0


def check_raster(what: str, lo: np.ndarray, hi: np.ndarray, resolution, limit: int | None = None) -> tuple[int, int]:
    """(nx, ny) of the (x, y) box [lo, hi] at `resolution`; a one-line UsageError naming `what`
    (the flag or argument) before anything is allocated for a resolution that is not a positive
    number, makes the map larger than maps.occupancy.MAX_PIXELS, or whose rasters' working memory
    (RASTER_BYTES_PER_PIXEL) would not fit in half the memory this process may use (`limit`
    bytes; None: utils.memory's)."""
    if isinstance(resolution, bool) or not isinstance(resolution, numbers.Real) or not np.isfinite(resolution) \
            or resolution <= 0:
        raise UsageError(f"{what} {resolution!r}: expected a positive number of metres per pixel")
    nx, ny = raster_shape(lo, hi, resolution)
    if nx * ny > MAX_PIXELS:
        raise UsageError(f"{what} {resolution!r}: the {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m box would be a "
                         f"{nx}x{ny} px map; expected at most {MAX_PIXELS // 1_000_000} M px (a coarser resolution)")
    require_memory(f"{what} {resolution!r}: the {nx}x{ny} px map's rasters", nx * ny * RASTER_BYTES_PER_PIXEL,
                   "a coarser resolution", limit)
    return nx, ny


def spread_rows(n: int, max_poses: int) -> np.ndarray:
    """(M,) int: at most `max_poses` of the rows 0..n-1, evenly spread (the first and the last
    always among them); none for n = 0."""
    return np.linspace(0, n - 1, min(max_poses, n)).astype(int) if n else np.zeros(0, dtype=int)


def spread_positions(positions: np.ndarray, max_poses: int) -> np.ndarray:
    """(N, 3) camera positions -> at most `max_poses` of them (`spread_rows`)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return positions[spread_rows(len(positions), max_poses)]


def camera_height(cam_to_world: np.ndarray, stack_ids: np.ndarray, default: float = 0.0) -> float:
    """Median height (m) of the main stack's cameras (every stack's without it): the height of
    the 2D maps (docs/method.md 6.3). cam_to_world (N, 4, 4), stack_ids (N,)."""
    z = np.asarray(cam_to_world)[:, 2, 3]
    main = np.asarray(stack_ids) == MAIN_STACK
    z = z[main] if main.any() else z
    return float(np.median(z)) if len(z) else float(default)


def low_shadow_depth(box_lo, box_hi, growing: bool) -> float:
    """How far (m) the map's shadow reaches behind the low rays' ends in the box [box_lo, box_hi]
    (x, y first, metres): MAP_LOW_SHADOW_SMALL_ROOM_M in a fitted box whose longest horizontal
    side is at most MAP_SMALL_ROOM_M, MAP_LOW_SHADOW_M in a larger or a `growing` one (D111)."""
    side = max(float(box_hi[0]) - float(box_lo[0]), float(box_hi[1]) - float(box_lo[1]))
    return MAP_LOW_SHADOW_SMALL_ROOM_M if not growing and side <= MAP_SMALL_ROOM_M else MAP_LOW_SHADOW_M


def scan_map(model, positions: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution: float, n_rays: int,
             evidence: RangeEvidence | None = None, low_front: float | None = MAP_LOW_FRONT_OPACITY,
             shadow: float = MAP_LOW_SHADOW_M):
    """360 deg model scans from camera `positions` (N, 3) -> a trinary OccupancyMap2D over the
    (x, y) box [lo, hi]: the band's `n_rays` rays a position, whose heights take turns over
    MAP_SCAN_HEIGHTS_M (maps.occupancy.scan_occupancy: passed cells free, end cells occupied; the
    map stands for the camera-height band, not one plane, D56; the scan rule height by height,
    `band_counts`, D97), then occupied where the band's
    rays said free and the low rays (MAP_LOW_HEIGHTS_M, half a band ray's angle apart from them)
    by the same rule said occupied (D60), and unknown where the band said free up to
    `shadow` m (MAP_LOW_SHADOW_M; `low_shadow_depth`) behind the low rays' occupied ends and no
    low ray passed (D64). The band's
    rays march the grid as trained, the low rays the grid grown in z (`low_ranges`, D66), those
    at MAP_LOW_AROUND_HEIGHTS_M the grid grown in x and y as well (D73). With the robot's
    `evidence` (maps/planner.py), only low ends near a measured surface cast the shadow, the
    band rays nothing stopped mark free what they passed up to the first surface a sensor
    touched (`through_lengths`, D80), and what the stereo cameras looked through at camera height
    is free where the band left it unknown (`evidence.sight_lines`; the scan rule's ends, the low
    rays and the shadow still apply, D81), and a lone low end that no sensor backs occupies nothing
    (`lone_unsupported`, D87). The low rays end where their opacity first reaches `low_front`
    (None: at D / A; `low_front_level`)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    band_o, band_d = scan_rays(positions, n_rays, MAP_SCAN_HEIGHTS_M)  # (N n_rays, 3) each
    n_low = max(1, round(n_rays * MAP_LOW_RAYS_SHARE))
    low_o, low_d = scan_rays(positions, n_low, MAP_LOW_HEIGHTS_M,
                             first_angle=np.pi / n_rays)  # between the band's rays: a leg they pass between
    band_r = np.asarray(model.ranges(band_o, band_d), dtype=np.float64).reshape(-1) if len(positions) \
        else np.zeros(0)
    below = low_o[:, 2] - np.repeat(positions[:, 2], n_low)  # (N n_low,) m, each low ray's height
    around = np.isclose(below[:, None], np.asarray(MAP_LOW_AROUND_HEIGHTS_M)[None, :]).any(axis=1)
    low_r = low_ranges(model, low_o, low_d, around, low_front) if len(positions) else np.zeros(0)
    passes, hits, occupied = band_counts(band_o, band_d, band_r, n_rays, lo, hi, resolution)
    grid = np.full(passes.shape, UNKNOWN, dtype=np.uint8)  # [ix, iy]
    grid[passes > 0] = FREE
    if evidence is not None:  # free space without an end: the rays nothing stopped, up to the first
        # surface a sensor touched (D80), and what the stereo cameras looked through (D81)
        through = ~np.isfinite(band_r)
        o, d = band_o[through, :2], band_d[through, :2]  # level unit directions (maps/scans.py)
        free = Rays2D(o, d, through_lengths(o, d, evidence.touched(), lo, hi, resolution)).concat(evidence.sight_lines)
        grid[scan_counts(free.origins, free.directions, free.ranges + resolution, lo, hi, resolution)[0] > 0] = FREE
    grid[occupied] = OCCUPIED  # the ends by the rays that met them, height by height (D97)
    low_passes, low_hits = scan_counts(low_o[:, :2], low_d[:, :2], low_r, lo, hi, resolution)
    low_occupied = scan_rule_occupied(low_passes, low_hits)  # the same scan rule as the band's
    if evidence is not None:  # a lone end no sensor backs is the field's haze near the floor (D87)
        low_occupied &= ~lone_unsupported(low_occupied, low_hits, evidence, lo, resolution)
    grid[low_occupied & (grid == FREE)] = OCCUPIED
    if evidence is not None and len(evidence.surfaces):
        ends = low_o[:, :2] + low_d[:, :2] * low_r[:, None]  # (N n_low, 2), NaN where a low ray ended nowhere
        low_r = np.where(near_surfaces(ends, evidence.surfaces, MAP_LOW_SUPPORT_M), low_r, np.nan)  # the rest cast none
    behind = behind_ends(low_o[:, :2], low_d[:, :2], low_r, low_occupied, shadow, lo, hi, resolution)
    grid[behind & (low_passes == 0) & (grid == FREE)] = UNKNOWN
    return OccupancyMap2D(image=to_image(grid), resolution=resolution, origin=(float(lo[0]), float(lo[1])))


def band_counts(origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, n_rays: int, lo: np.ndarray,
                hi: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The band's scans (`scan_rays` with MAP_SCAN_HEIGHTS_M: origins (N n_rays, 3), directions
    (N n_rays, 3), ranges (N n_rays,) m) -> passes and ends ((nx, ny) counts, all heights) and the
    occupied pixels ((nx, ny) bool): the scan rule height by height, occupied where the rays of any
    one height ended at least half as often as they passed. A thin obstacle stops the rays of one
    height while the others pass: a table top 4 cm thick at camera height, or a 5 cm leg whose
    one ray ends on it while the next rays, at the other heights, pass through its pixel beside
    it. Counted together, their passes outvoted its ends and a planner drove through a desk's leg
    (D96, D97; corrected in D99)."""
    heights = np.arange(len(ranges)) % n_rays % len(MAP_SCAN_HEIGHTS_M)  # ray i at heights[i % 3]
    passes = hits = occupied = None
    for h in range(len(MAP_SCAN_HEIGHTS_M)):
        one = heights == h
        p, e = scan_counts(origins[one, :2], directions[one, :2], ranges[one], lo, hi, resolution)
        if passes is None:  # the first height's rasters hold the sums (no copy of a raster a height)
            passes, hits, occupied = p, e, scan_rule_occupied(p, e)
        else:
            passes += p
            hits += e
            occupied |= scan_rule_occupied(p, e)
    return passes, hits, occupied


def lone_unsupported(occupied: np.ndarray, hits: np.ndarray, evidence: RangeEvidence, lo: np.ndarray,
                     resolution: float) -> np.ndarray:
    """(nx, ny) bool: the pixels of `occupied` ((nx, ny) bool [ix, iy]) with no other occupied pixel
    among their 8 neighbours and at most MAP_LOW_LONE_HITS ray ends (`hits`, (nx, ny) counts) that
    no sensor backs: no IRS hit or stereo surface point (`evidence.support()`) within
    MAP_LOW_SUPPORT_M of their centre, and no USS echo's arc within USS_EXPLAINED_M (the closeness
    at which such a pixel explains the echo, maps/planner.py). No pixel without IRS hits and
    stereo points (nothing to tell a lone end by)."""
    from scipy.ndimage import convolve, maximum_filter

    out = np.zeros(occupied.shape, dtype=bool)
    support = evidence.support()  # (K, 2)
    if not len(support):
        return out
    neighbours = convolve(occupied.astype(np.int32), np.ones((3, 3), dtype=np.int32), mode="constant") - occupied
    lone_mask = occupied & (neighbours == 0) & (hits <= MAP_LOW_LONE_HITS)
    if not lone_mask.any():
        return out
    lo = np.asarray(lo, dtype=np.float64)[:2]
    # only the points in pixels near a lone one can back it (tens of thousands of IRS hits: a tree
    # over the few is what costs nothing); a point off the raster counts at its nearest border pixel
    reach = maximum_filter(lone_mask, size=2 * (int(np.ceil(MAP_LOW_SUPPORT_M / resolution)) + 1) + 1)

    def nearby(points: np.ndarray) -> np.ndarray:
        points = points[np.isfinite(points).all(axis=1)]
        ij = np.clip(np.floor((points - lo) / resolution), 0, np.array(occupied.shape) - 1).astype(np.int64)
        return points[reach[ij[:, 0], ij[:, 1]]]

    lone = np.argwhere(lone_mask)  # (M, 2) [ix, iy]
    centres = lo + (lone + 0.5) * resolution
    backed = near_surfaces(centres, nearby(support), MAP_LOW_SUPPORT_M)
    if len(evidence.uss_range):
        backed |= near_surfaces(centres, nearby(uss_arcs(evidence).reshape(-1, 2)), USS_EXPLAINED_M)
    out[lone[~backed, 0], lone[~backed, 1]] = True
    return out


def through_lengths(origins: np.ndarray, directions: np.ndarray, touched: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray, resolution: float) -> np.ndarray:
    """(N,) m: how far the free space of 2D rays (origins (N, 2), directions (N, 2) unit) that no
    surface stopped reaches: to the first pixel within MAP_THROUGH_STOP_M of a `touched` point
    (K, 2), and no further than MAP_THROUGH_MARGIN_M before the side of the box [lo, hi]."""
    from scipy.ndimage import distance_transform_edt

    with np.errstate(divide="ignore", invalid="ignore"):
        side = np.where(directions > 0, (hi[:2] - origins) / directions,
                        np.where(directions < 0, (lo[:2] - origins) / directions, np.inf)).min(axis=1)
    length = np.maximum(side - MAP_THROUGH_MARGIN_M, 0.0)
    shape = raster_shape(lo, hi, resolution)
    ij, inside = world_pixels(np.asarray(touched, dtype=np.float64).reshape(-1, 2), lo[:2], resolution, shape)
    ij = ij[inside]
    if not len(ij) or not len(origins):
        return length
    near = np.ones(shape, dtype=bool)
    near[ij[:, 0], ij[:, 1]] = False
    near = distance_transform_edt(near) * resolution <= MAP_THROUGH_STOP_M  # (nx, ny) the touched pixels, grown
    return np.minimum(length, first_pixel(origins, directions, length, near, lo, resolution))


def first_pixel(origins: np.ndarray, directions: np.ndarray, lengths: np.ndarray, mask: np.ndarray, lo: np.ndarray,
                resolution: float) -> np.ndarray:
    """(N,) m: the distance along each 2D ray (origins (N, 2), directions (N, 2) unit) to the
    first of its points, every half pixel, that lies in a pixel of `mask` ((nx, ny) bool [ix, iy]);
    `lengths` (N,) m where none does before it."""
    out = np.asarray(lengths, dtype=np.float64).copy()
    k = np.floor(np.maximum(out, 0) / (resolution / 2)).astype(np.int64) + 1  # (N,) points a ray, from its origin
    for rows, kk, t, ix, iy, inside in ray_points(origins, directions, k, lo, resolution, mask.shape):
        hit = np.zeros(len(t), dtype=bool)
        hit[inside] = mask[ix[inside], iy[inside]]
        first = np.full(len(rows), np.inf)
        np.minimum.at(first, np.repeat(np.arange(len(rows)), kk)[hit], t[hit])
        out[rows] = np.minimum(out[rows], first)
    return out


def low_front_level(step: int) -> float | None:
    """The opacity at which the map's low rays end for a field trained `step` steps: None (D / A)
    before MAP_LOW_FRONT_FROM_STEP, MAP_LOW_FRONT_OPACITY from then on."""
    return MAP_LOW_FRONT_OPACITY if step >= MAP_LOW_FRONT_FROM_STEP else None


def low_ranges(model, origins: np.ndarray, directions: np.ndarray, around: np.ndarray | None = None,
               front: float | None = MAP_LOW_FRONT_OPACITY) -> np.ndarray:
    """(N,) ranges (m) of the low rays (origins, directions (N, 3)): a model with an occupancy
    grid marches them over its occupied cells grown by MAP_LOW_GRID_GROW_Z cells up and down
    (`grown_in_z`), the rays flagged in `around` ((N,) bool; None: none) over the cells grown by
    one in every direction (`grown_around`), and ends them where their opacity first reaches
    `front` (None: at D / A); any other range model (an analytic scene) answers as for every ray."""
    grid = getattr(model, "grid", None)
    if grid is None:
        return np.asarray(model.ranges(origins, directions), dtype=np.float64).reshape(-1)
    around = np.zeros(len(origins), dtype=bool) if around is None else np.asarray(around, dtype=bool)
    out = np.full(len(origins), np.nan)
    for rays, grow in ((~around, lambda occ: grown_in_z(occ, MAP_LOW_GRID_GROW_Z)), (around, grown_around)):
        if rays.any():
            cells = grow(grid.occupied)
            out[rays] = np.asarray(model.ranges(origins[rays], directions[rays], occupied=cells, front=front),
                                   dtype=np.float64).reshape(-1)
    return out


def grown_in_z(occupied: torch.Tensor, cells: int) -> torch.Tensor:
    """(rx, ry, rz) bool cells -> the same with every occupied cell's `cells` neighbours above
    and below occupied too (on the grid's own device)."""
    out = occupied.clone()
    for k in range(1, cells + 1):
        if k >= occupied.shape[2]:
            break
        out[:, :, k:] |= occupied[:, :, :-k]
        out[:, :, :-k] |= occupied[:, :, k:]
    return out


def grown_around(occupied: torch.Tensor) -> torch.Tensor:
    """(rx, ry, rz) bool cells -> the same with the 26 neighbours of every occupied cell occupied
    too (on the grid's own device)."""
    cells = occupied[None, None].to(torch.float32)  # (1, 1, rx, ry, rz)
    return torch.nn.functional.max_pool3d(cells, kernel_size=3, stride=1, padding=1)[0, 0] > 0


def behind_ends(origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, occupied: np.ndarray,
                depth: float, lo: np.ndarray, hi: np.ndarray, resolution: float) -> np.ndarray:
    """(nx, ny) bool [ix, iy]: the pixels up to `depth` m beyond the ends of the 2D rays (origins
    (N, 2), directions (N, 2) unit, ranges (N,) m) that ended in an `occupied` pixel ((nx, ny) bool):
    what those rays did not see behind the surface they met."""
    ok, ends, ij, inside = ray_ends(origins, directions, ranges, lo[:2], resolution, occupied.shape)
    if depth <= 0 or not ok.any():
        return np.zeros(occupied.shape, dtype=bool)
    d = np.asarray(directions, dtype=np.float64)[ok]
    stopped = np.zeros(len(ends), dtype=bool)
    stopped[inside] = occupied[ij[inside, 0], ij[inside, 1]]
    # a ray from each end whose pass points (every half pixel, stopping a pixel short of its end:
    # scan_counts) reach `depth` m
    passes, _ = scan_counts(ends[stopped], d[stopped], np.full(int(stopped.sum()), depth + 1.5 * resolution), lo,
                            hi, resolution)
    return passes > 0


def occupancy_map(model, positions: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution: float, n_rays: int,
                  max_poses: int, observed: np.ndarray, evidence: RangeEvidence | None = None,
                  low_front: float | None = MAP_LOW_FRONT_OPACITY, stack_ids: np.ndarray | None = None,
                  times: np.ndarray | None = None, shadow: float = MAP_LOW_SHADOW_M, scan: bool = True) -> OccupancyMap2D:
    """The trinary 2D map a planner reads: scans from up to `max_poses` of the camera `positions`
    (N, 3), unknown outside `observed` ((nx, ny) bool [ix, iy], maps/observed.py) whatever the
    model says, then occupied where the IRS and USS `evidence` touched what the scans called free
    (maps/planner.py; None: the scans alone), and free where a camera stood within `observed` (and,
    given the positions' `stack_ids` and `times` (N,), on the way between a stack's consecutive
    positions, maps/planner.track_free). The low rays end at the opacity `low_front` (`scan_map`;
    the Mapper's: `low_front_level` of its step) and the shadow behind them reaches `shadow` m (the
    Mapper's: `low_shadow_depth` of its box). `scan` False: no model scans (a field not trained yet
    says nothing: its haze would read as walls about 1 m around the cameras), the sensors' own
    evidence and the cameras' pixels alone."""
    scanned = spread_positions(positions, max_poses) if scan else np.zeros((0, 3))
    m = scan_map(model, scanned, lo, hi, resolution, n_rays, evidence, low_front, shadow)
    m.image = apply_mask(m.image, observed, UNKNOWN)  # free only where a sensor looked
    if evidence is not None:
        m.image = planner_image(m.image, lo, resolution, evidence)
    m.image = track_free(m.image, lo, resolution, positions, observed, stack_ids, times)  # the robot stood there
    return m


def probability_map(probability: np.ndarray, box_lo, box_hi, height: float, band: float, lo: np.ndarray,
                    hi: np.ndarray, resolution: float, observed: np.ndarray) -> OccupancyMap2D:
    """The VIRUS grid's occupancy probability (rx, ry, rz) over the 3D box [box_lo, box_hi] as a
    `mode: raw` map of the (x, y) box [lo, hi] at `height` +- `band` m (maximum over the layers):
    round(100 p), unknown (maps.occupancy.RAW_UNKNOWN, -1 to map_server) outside `observed`, where
    no sensor looked (the grid's prior there is no knowledge, and never free)."""
    p = probability_slice(probability, box_lo, box_hi, height, band, lo, hi, resolution)
    return raw_map(p, lo, resolution, observed)
