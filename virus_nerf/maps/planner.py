"""The map a planner reads (issue 42): the NeRF's scans, then what the robot's range sensors touched.

The NeRF's 360 deg scans (maps/extract.py: the camera-height band, and scans just below it) keep
the free space but miss what the colour loss does not hold at camera height: round objects in the
open floor, thin table and chair legs, furniture ends. The robot carries the sensors made for
exactly these, so two rules follow the scans, each only turning free pixels occupied (a planner's
map may lose free space, never gain it):

1. **IRS hits and stereo points.** Every infrared sub-ray whose end lies within
   `OBSTACLE_BAND_M` of camera height (maps/evidence.py) marks its end pixel occupied where
   something corroborates it (`corroborated_irs`: the scans' own ends, a stereo point or hits
   measured from elsewhere nearby): the sensor touched a surface there, one the robot's body
   (not only its cameras) would meet; so does every triangulated stereo point (issue 28's
   measured surfaces) within the same height band.
2. **Unexplained USS echoes.** An echo says "the nearest surface in this cone is at r". If the map
   holds an occupied pixel within `USS_EXPLAINED_M` of the echo's horizontal arc, the echo is
   explained and adds nothing; otherwise the obstacle lies somewhere on the arc and the map
   does not know it (a leg, a pole or glass that the cameras missed). Where on the arc is settled
   by the other echoes, as in sonar occupancy mapping (Elfes 1987): a pixel of an unexplained
   arc becomes occupied when the unexplained arcs through it are at least `USS_ARC_VOTE` times
   the cones that passed it as free space (closer than their echo by `USS_FREE_MARGIN_M`).
   An obstacle on the arc stops every cone that meets it, so its pixels keep their votes; the
   rest of a 55 deg arc lies in space other cones crossed, and stays free.

Last, the pixels holding a camera position are free (`track_free`, D92): the robot stood there,
whatever a half-trained field's scans or a stray measurement say; so are those on the way between a
stack's consecutive positions (D98: the frames a busy machine dropped while driving).

Measured and not kept (docs/decisions.md D47, D89, D91): the VIRUS grid's probability above 0.5
as obstacles, more scan positions and rays, a softer scan hit rule, every USS arc occupied, a
0.1 m or 0.2 m band for the IRS hits and stereo points, two other hits nearby as an IRS hit's
corroboration (a zone's stray sub-rays repeat while the robot stands), an echo explained by an
occupied pixel 0.1 m from its arc (a soft object's inner pixels explained its echoes).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from virus_nerf.maps.evidence import Rays2D, irs_rays_2d
from virus_nerf.maps.occupancy import FREE, OCCUPIED, from_image, to_image, world_pixels
from virus_nerf.sensors import uss
from virus_nerf.sensors.geometry import yaw_of

OBSTACLE_BAND_M = 0.3  # IRS hits and stereo points this close to camera height are obstacles of the map
# stereo points this close to camera height (m) are the measured surfaces the map's scan rules ask
# about (maps/extract.py, D80): the band and the map's low rays, 30 cm below it, with room to spare
SURFACE_BAND_M = 0.5
# an echo whose arc passes this close to an occupied pixel is explained: one pixel of the 0.05 m map,
# about the URM37's bias and spread at 4 m (sim/sensors.UssModel). At D47's 0.1 m, a round object
# whose front the scans miss but whose inside they end in explains its echoes and stays open to
# the planner (D91: common area 81's plant, 2 of 50 paths through it)
USS_EXPLAINED_M = 0.05
USS_ARC_STEP_DEG = 1.0  # points along an echo's arc
USS_ARC_VOTE = 0.25  # an arc pixel is occupied when unexplained arcs >= this share of the cones that passed it
USS_FREE_MARGIN_M = 0.1  # a cone passed a point this much closer than its echo
# consecutive camera positions of one stack at most this far apart (m) mark the way between them free
# (`track_free`): the recordings' frames lie 0.1 m apart, so up to four frames a busy machine dropped
# in a row; a straight chord of 0.5 m cuts a turn of 0.5 m radius by 6 cm, about a pixel, inside the
# 0.3 m robot's body
TRACK_GAP_M = 0.5
# an IRS hit marks its pixel occupied only when something corroborates it (D89): the NeRF's scans
# hold an occupied pixel within IRS_SCAN_NEAR_M of its pixel, a stereo point at camera height lies
# within IRS_STEREO_NEAR_M, or the hits in its pixel and the 8 around it were measured from sensor
# positions at least IRS_SEEN_APART_M apart (the diagonal of the box around them). A surface is met
# again as the robot moves; a zone's edge sub-ray ending short of the surface its zone measured
# lands in free space, moves with the robot and repeats only while it stands (office 81: the hits
# 0.3 m or more from every surface had sensor positions a median 0.00 m apart, those on a surface
# 1.0 m)
IRS_SCAN_NEAR_M = 0.1
IRS_STEREO_NEAR_M = 0.2
IRS_SEEN_APART_M = 0.2


@dataclass(frozen=True)
class RangeEvidence:
    """What the IRS and USS measured at camera height, in the world frame (metres)."""

    irs_hits: np.ndarray  # (K, 2) IRS ray ends at camera height
    uss_origins: np.ndarray  # (E, 2) USS positions of the echoes
    uss_yaw: np.ndarray  # (E,) rad, the cone's heading
    uss_range: np.ndarray  # (E,) m, radial echo range
    stereo_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))  # (S, 2) at camera height
    # (P, 2) the stereo points within SURFACE_BAND_M of camera height: where the cameras measured a
    # surface at the heights the map's scans look at (maps/extract.py)
    surfaces: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))
    # the free space the stereo cameras looked through at camera height (maps/evidence.stereo_sight_lines):
    # free where the map's scans left it unknown (maps/extract.py, D81)
    sight_lines: Rays2D = dataclasses.field(default_factory=Rays2D.empty)
    # (K, 2) where the IRS sensor stood for each hit (None: not known, every hit counts as seen apart)
    irs_origins: np.ndarray | None = None

    @staticmethod
    def empty() -> RangeEvidence:
        return RangeEvidence(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0))

    def support(self) -> np.ndarray:
        """(K + P, 2) world points where a sensor measured a surface at the heights the map's scans
        look at: the IRS hits and the stereo points within SURFACE_BAND_M of camera height."""
        return np.concatenate([self.irs_hits, self.surfaces])

    def touched(self) -> np.ndarray:
        """(K + S, 2) world points where a sensor touched a surface at camera height: the IRS hits
        and the stereo points."""
        return np.concatenate([self.irs_hits, self.stereo_points])

    @staticmethod
    def of_frames(cam_to_world: np.ndarray, uss_range: np.ndarray, irs_range: np.ndarray, height: float,
                  sensors: tuple[str, ...], band: float = OBSTACLE_BAND_M,
                  stereo_points: np.ndarray | None = None, sight_lines: Rays2D | None = None) -> RangeEvidence:
        """The evidence of frames (cam_to_world (F, 4, 4), uss_range (F,) m, irs_range (F, 8, 8)
        z-depth m), of the stereo's world points (P, 3) and of its views' `sight_lines` at camera
        height (maps/evidence.stereo_sight_lines) for the sensors in `sensors` (the ones the map
        was trained with; "irs", "uss" and "stereo" count) at camera `height` (m)."""
        poses = np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4)
        irs_rays = irs_rays_2d(poses, irs_range, height, band) if "irs" in sensors else Rays2D.empty()
        irs, irs_origins = irs_rays.ends(), irs_rays.origins
        stereo, surfaces, sight = np.zeros((0, 2)), np.zeros((0, 2)), Rays2D.empty()
        if "stereo" in sensors and stereo_points is not None:
            pts = np.asarray(stereo_points, dtype=np.float64).reshape(-1, 3)
            stereo = pts[np.abs(pts[:, 2] - height) <= band, :2]
            surfaces = pts[np.abs(pts[:, 2] - height) <= SURFACE_BAND_M, :2]
        if "stereo" in sensors and sight_lines is not None:
            sight = sight_lines
        if "uss" not in sensors:
            return RangeEvidence(irs, np.zeros((0, 2)), np.zeros(0), np.zeros(0), stereo, surfaces, sight, irs_origins)
        r = np.asarray(uss_range, dtype=np.float64).reshape(-1)
        ok = np.isfinite(r) & (r > 0)
        return RangeEvidence(irs, poses[ok, :2, 3].copy(), yaw_of(poses[ok]), r[ok], stereo, surfaces, sight,
                             irs_origins)


def uss_arcs(evidence: RangeEvidence, step_deg: float = USS_ARC_STEP_DEG) -> np.ndarray:
    """(E, A, 2) world points along each echo's horizontal arc (+-27.5 deg at its range)."""
    a = evidence.uss_yaw[:, None] + uss.fan_offsets(step_deg)[None]  # (E, A)
    return evidence.uss_origins[:, None, :] + evidence.uss_range[:, None, None] * np.stack([np.cos(a), np.sin(a)], -1)


def unexplained_echoes(occupied: np.ndarray, arcs: np.ndarray, lo: np.ndarray, resolution: float,
                       explained_m: float = USS_EXPLAINED_M) -> np.ndarray:
    """(E,) bool: echoes whose arc (E, A, 2) passes no pixel within `explained_m` of an
    occupied pixel of `occupied` ((nx, ny) bool [ix, iy])."""
    from scipy.ndimage import distance_transform_edt

    if not len(arcs):
        return np.zeros(0, dtype=bool)
    near = distance_transform_edt(~occupied) * resolution <= explained_m + 1e-9 if occupied.any() \
        else np.zeros(occupied.shape, dtype=bool)
    ij, inside = world_pixels(arcs, lo, resolution, occupied.shape)
    return ~(near[ij[..., 0], ij[..., 1]] & inside).any(axis=1)


def planner_image(image: np.ndarray, lo: np.ndarray, resolution: float, evidence: RangeEvidence,
                  explained_m: float = USS_EXPLAINED_M) -> np.ndarray:
    """The planner's trinary map (H, W) (row 0 = largest y) from the NeRF's scan map `image`
    (already unknown where no sensor looked) and the range evidence: IRS hits and stereo points,
    then the voted arcs of unexplained USS echoes, occupied where the scans said free. The input
    is not changed."""
    grid = from_image(image).copy()  # [ix, iy]
    lo = np.asarray(lo, dtype=np.float64)[:2]
    hit = corroborated_irs(grid == OCCUPIED, evidence, lo, resolution)
    ij, inside = world_pixels(evidence.stereo_points, lo, resolution, grid.shape)
    hit[ij[inside, 0], ij[inside, 1]] = True
    grid[hit & (grid == FREE)] = OCCUPIED
    arcs = uss_arcs(evidence)
    lost = unexplained_echoes(grid == OCCUPIED, arcs, lo, resolution, explained_m)
    votes = np.zeros(grid.shape, dtype=np.int64)  # unexplained arcs through each pixel
    for e in np.flatnonzero(lost):
        ij, inside = world_pixels(arcs[e], lo, resolution, grid.shape)
        ij = np.unique(ij[inside], axis=0)  # one vote a pixel and echo
        votes[ij[:, 0], ij[:, 1]] += 1
    cand = np.argwhere((votes > 0) & (grid == FREE))  # (M, 2) [ix, iy]
    centres = lo + (cand + 0.5) * resolution
    passed = cones_passing(centres, evidence)
    occ = votes[cand[:, 0], cand[:, 1]] >= USS_ARC_VOTE * passed
    grid[cand[occ, 0], cand[occ, 1]] = OCCUPIED
    return to_image(grid)


def track_free(image: np.ndarray, lo: np.ndarray, resolution: float, positions: np.ndarray,
               observed: np.ndarray | None = None, stack_ids: np.ndarray | None = None,
               times: np.ndarray | None = None) -> np.ndarray:
    """The trinary map (H, W) (row 0 = largest y) with the pixels that hold a camera position
    (positions (N, 2+) m, world frame) free: the robot's own body stood there, so whatever a
    rule or a half-trained field says, no obstacle does (D92). With `stack_ids` (N,), the
    pixels along the way between consecutive positions of one stack (in `times` (N,) s order;
    row order without) at most TRACK_GAP_M apart are free too: the camera passed there, in the
    frames the map was not given (a busy machine drops some while driving, D98). Only pixels a
    sensor looked at (`observed`, (nx, ny) bool [ix, iy]; None: all): the map stays unknown
    wherever its observed mask says so (maps/observed.py). The input is not changed."""
    out = np.array(image, copy=True)  # (H, W), row 0 = largest y
    xy = np.asarray(positions, dtype=np.float64)[..., :2].reshape(-1, 2)  # (N, 2)
    if stack_ids is not None:
        xy = np.concatenate([xy, track_points(xy, stack_ids, times, resolution / 2)])
    ij, inside = world_pixels(xy, np.asarray(lo, dtype=np.float64)[:2], resolution, out.shape[::-1])
    ij = ij[inside]  # (M, 2) [ix, iy]
    if observed is not None:
        ij = ij[np.asarray(observed, dtype=bool)[ij[:, 0], ij[:, 1]]]
    out[out.shape[0] - 1 - ij[:, 1], ij[:, 0]] = FREE
    return out


def track_points(positions: np.ndarray, stack_ids: np.ndarray, times: np.ndarray | None, step: float,
                 max_gap: float = TRACK_GAP_M) -> np.ndarray:
    """(M, 2) points every `step` m or closer along the straight segments between consecutive
    camera positions ((N, 2) m) of one stack (`stack_ids` (N,)), in `times` order ((N,) s; None:
    row order), for segments at most `max_gap` m long; both ends are included."""
    xy = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    stacks = np.asarray(stack_ids).reshape(-1)
    when = np.arange(len(xy)) if times is None else np.asarray(times, dtype=np.float64).reshape(-1)
    order = np.lexsort((when, stacks))  # by stack, then in time
    a, b = xy[order[:-1]], xy[order[1:]]  # (N - 1, 2) each segment's ends
    length = np.linalg.norm(b - a, axis=1)
    keep = (stacks[order[:-1]] == stacks[order[1:]]) & (length <= max_gap) & np.isfinite(length)
    a, b, length = a[keep], b[keep], length[keep]
    n = np.ceil(length / step).astype(np.int64) + 1  # (S,) points a segment, ends included
    seg = np.repeat(np.arange(len(n)), n)
    frac = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.maximum(np.repeat(n - 1, n), 1)
    return a[seg] + (b[seg] - a[seg]) * frac[:, None]


def corroborated_irs(occupied: np.ndarray, evidence: RangeEvidence, lo: np.ndarray, resolution: float) -> np.ndarray:
    """(nx, ny) bool [ix, iy]: the pixels of the IRS hits that something corroborates: an occupied
    pixel of the scans (`occupied`, (nx, ny) bool) within IRS_SCAN_NEAR_M, a stereo point at camera
    height within IRS_STEREO_NEAR_M of the pixel's centre, or hits in the pixel and its 8
    neighbours measured from sensor positions IRS_SEEN_APART_M apart (`evidence.irs_origins`; every
    hit pixel without them). The nearest occupied pixel comes from one distance transform of the
    raster (its memory is the raster's at any resolution, D101); the rest looks at the hits' own
    3 x 3 blocks."""
    out = np.zeros(occupied.shape, dtype=bool)
    ij, inside = world_pixels(evidence.irs_hits, lo, resolution, occupied.shape)
    if not inside.any():
        return out
    shape = np.array(occupied.shape)
    key_of_hit = ij[inside, 0] * shape[1] + ij[inside, 1]  # (K',) a hit's pixel, row by row
    key, which = np.unique(key_of_hit, return_inverse=True)  # (M,) sorted hit pixels, (K',) a hit's
    pix = np.stack([key // shape[1], key % shape[1]], axis=1)  # (M, 2) [ix, iy]
    if evidence.irs_origins is None:
        out[pix[:, 0], pix[:, 1]] = True
        return out

    kept = np.zeros(len(key), dtype=bool)
    if occupied.any():  # an occupied pixel within IRS_SCAN_NEAR_M: a distance transform, whose memory is the
        # raster's (a disk of pixels around each hit pixel took hits x (radius / resolution)^2, 10 GB at 2 mm)
        from scipy.ndimage import distance_transform_edt

        kept = distance_transform_edt(~occupied)[pix[:, 0], pix[:, 1]] ** 2 <= (IRS_SCAN_NEAR_M / resolution) ** 2 + 1e-9
    # the box around the sensor positions of each hit pixel, then of its 3 x 3 block
    origins = np.asarray(evidence.irs_origins, dtype=np.float64)[inside]  # (K', 2)
    order = np.argsort(which, kind="stable")
    starts = np.searchsorted(which[order], np.arange(len(key)))  # each pixel's first hit in `order`
    low = np.minimum.reduceat(origins[order], starts)  # (M, 2)
    high = np.maximum.reduceat(origins[order], starts)
    block = np.array([(x, y) for x in (-1, 0, 1) for y in (-1, 0, 1)])  # (9, 2)
    q = pix[:, None, :] + block[None]  # (M, 9, 2) each hit pixel's 3 x 3 block
    ok = ((q >= 0) & (q < shape)).all(axis=2)  # (M, 9) inside the raster
    q = np.clip(q, 0, shape - 1)
    at = np.clip(np.searchsorted(key, q[..., 0] * shape[1] + q[..., 1]), 0, len(key) - 1)  # (M, 9)
    ok &= key[at] == q[..., 0] * shape[1] + q[..., 1]  # a hit pixel
    block_low = np.where(ok[..., None], low[at], np.inf).min(axis=1)
    block_high = np.where(ok[..., None], high[at], -np.inf).max(axis=1)
    kept |= np.linalg.norm(block_high - block_low, axis=1) >= IRS_SEEN_APART_M
    rest = ~kept
    kept[rest] = near_surfaces(lo + (pix[rest] + 0.5) * resolution, evidence.stereo_points, IRS_STEREO_NEAR_M)
    out[pix[kept, 0], pix[kept, 1]] = True
    return out


def near_surfaces(points: np.ndarray, surfaces: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: the (N, D) points (NaN: never) with a point of `surfaces` (P, D) within `radius` m."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(points), dtype=bool)
    ok = np.isfinite(points).all(axis=1)
    if ok.any() and len(surfaces):
        dist, _ = cKDTree(surfaces).query(points[ok], distance_upper_bound=radius)
        out[ok] = np.isfinite(dist)
    return out


def cones_passing(points: np.ndarray, evidence: RangeEvidence, margin: float = USS_FREE_MARGIN_M,
                  pairs: int = 1 << 21) -> np.ndarray:
    """(M,) int: for each world point (M, 2), the echoes whose horizontal opening (+-27.5 deg)
    holds it closer than the echo's range minus `margin`: cones that passed it as free space.
    Points go in chunks of at most `pairs` point-echo pairs (bounded memory on long drives)."""
    half = np.deg2rad(uss.USS_FOV_H_DEG / 2)
    out = np.zeros(len(points), dtype=np.int64)
    chunk = max(1, pairs // max(1, len(evidence.uss_range)))
    for s in range(0, len(points), chunk):
        d = points[s : s + chunk, None, :] - evidence.uss_origins[None, :, :]  # (m, E, 2)
        dist = np.hypot(d[..., 0], d[..., 1])
        ang = np.arctan2(d[..., 1], d[..., 0]) - evidence.uss_yaw[None, :]
        ang = (ang + np.pi) % (2 * np.pi) - np.pi
        out[s : s + chunk] = ((np.abs(ang) <= half) & (dist < evidence.uss_range[None, :] - margin)).sum(axis=1)
    return out
