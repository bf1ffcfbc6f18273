"""Can a planner trust the map? The share of real obstacles that the exported 2D map marks free.

The paper's accuracy and coverage judge the NeRF's scans; a planner reads the map instead, and
what hurts it is an obstacle the map calls free. For every ground-truth obstacle pixel (the
LiDAR map's points within +-band of the camera height, drawn into the map's own raster) the map
is asked whether it marks that pixel free with no occupied or unknown pixel within `tolerance`
metres (so a wall placed a pixel or two off, inside the paper's 10 cm inlier distance, is not a
miss). Obstacle pixels are grouped by their distance to the robot's path (the training cameras'
positions): within 1 m, within 2 m, and all. Lower is safer; 0 means no known obstacle is free.

A map that marks nothing free is safe and useless, so beside it stands the map's free recall
(issue 42): of the true free pixels within 3 m of the path, more than 0.15 m from every obstacle,
connected to the path and inside the ground truth's own extent (the LiDAR map's box: beyond it the
ground truth knows nothing, and a grown map's raster reaches there through the gaps that
furniture leaves in a wall's camera-height slice), the share the map marks free. Both figures are also given for two
anchors on the same raster: the classic inverse-sensor map of the robot's USS and IRS alone
(maps/evidence.py, no NeRF) and the 2D map a LiDAR robot has, carved by the LiDAR's own scans at
camera height at the same positions as the map's scans.

The free recall's ground truth is the camera-height slice, so the space over a pallet or a low
shelf counts free there, though the robot's body would meet it and the map rightly keeps it out.
Beside it stands the drivable free recall: the same share of the true free space less what the
LiDAR map holds from 0.1 m above the floor up to the camera band (evaluation/gt.py `body_slice`),
the space the robot can actually cross. And the obstacles the band does not hold but the body
meets (those same points: a pallet, a rack's lowest shelf, a chair's seat) stand beside the band's
own, by the same zones (`below_band`): the band's ground truth does not count a map that marks
them free, a robot does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SAFETY_ZONES_M = (1.0, 2.0, math.inf)  # obstacle distance to the robot's path
SAFETY_TOLERANCE_M = 0.1  # the paper's inlier distance
FREE_NEAR_PATH_M = 3.0  # free recall: true free space this close to the path ...
FREE_CLEARANCE_M = 0.15  # ... and more than this far from every obstacle
PLANNER_RADIUS_M = 0.3  # the robot's radius for the planner's check
# distances between pixel centres are compared in pixels, with this slack: at 0.05 m a pixel 0.2 m
# away is 4 px, where 4 * 0.05 = 0.2 but 0.3 - 0.1 = 0.19999999999999998 (floating point would
# otherwise decide the boundary pixels of every radius, clearance and tolerance)
PIXEL_EPS = 1e-9
# `safety_picture`'s colours: the map (free, unknown, occupied), the ground truth's obstacles (held
# or unknown, marked free), the path, what the body meets below the band (held or unknown, marked free)
MAP_FREE_RGB, MAP_UNKNOWN_RGB, MAP_OCCUPIED_RGB = (255, 255, 255), (190, 190, 190), (0, 0, 0)
OBSTACLE_RGB, MISSED_RGB, PATH_RGB = (40, 80, 255), (255, 0, 0), (0, 160, 0)
BODY_RGB, BODY_MISSED_RGB = (150, 110, 60), (255, 150, 0)


@dataclass(frozen=True)
class SafetyZone:
    within_m: float  # obstacle pixels at most this far from the path (inf = all)
    obstacles: int  # ground-truth obstacle pixels in the zone
    marked_free: int  # of them, free in the map with nothing but free within the tolerance

    @property
    def free_share(self) -> float | None:
        return self.marked_free / self.obstacles if self.obstacles else None


def obstacle_pixels(points_xy: np.ndarray, origin: tuple[float, float], resolution: float,
                    shape_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) bool image (row 0 = largest y, the maps.occupancy raster): pixels holding a point."""
    h, w = shape_hw
    out = np.zeros((h, w), dtype=bool)
    ij = np.floor((np.asarray(points_xy, dtype=np.float64).reshape(-1, 2) - np.asarray(origin)) / resolution).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out[h - 1 - ij[ok, 1], ij[ok, 0]] = True
    return out


def free_for_sure(image: np.ndarray, free_value: int, resolution: float, tolerance: float) -> np.ndarray:
    """(H, W) bool: free pixels whose every pixel within `tolerance` metres is free too."""
    from scipy.ndimage import binary_erosion

    free = np.asarray(image) == free_value
    r = int(math.floor(tolerance / resolution + PIXEL_EPS))
    if r <= 0:
        return free
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (xx * xx + yy * yy) <= r * r
    return binary_erosion(free, structure=disk, border_value=1)


def true_free_near_path(obstacles: np.ndarray, origin: tuple[float, float], resolution: float,
                        path_xy: np.ndarray, within: float = FREE_NEAR_PATH_M,
                        clearance: float = FREE_CLEARANCE_M, extent: tuple | None = None) -> np.ndarray:
    """(H, W) bool: the free space a planner needs from the map, from the ground truth alone.

    Pixels more than `clearance` m from every ground-truth obstacle pixel (`obstacles`, (H, W)
    bool), within `within` m of the path (P, 2), connected (4-neighbours) to a pixel the path
    passes through, and with their centre inside `extent` ((x, y) lo, (x, y) hi in metres: the
    ground truth's own box; None: the whole raster). The connection keeps out the space behind
    walls, the clearance closes the gaps between a wall's LiDAR points; the extent keeps out the
    space beyond the ground truth, which a wall's slice does not close where furniture hid it
    from the LiDAR.
    """
    from scipy.ndimage import label

    h, w = obstacles.shape
    clear = ~pixels_within(obstacles, resolution, clearance)
    path = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    on_path = obstacle_pixels(path, origin, resolution, (h, w))  # pixels the path passes through
    if not on_path.any():
        return np.zeros((h, w), dtype=bool)
    near = pixels_within(on_path, resolution, within)
    labels, _ = label(clear)
    keep = np.unique(labels[on_path & clear])
    keep = keep[keep > 0]
    free = near & clear & np.isin(labels, keep)
    if extent is not None:
        lo, hi = np.asarray(extent[0], dtype=np.float64), np.asarray(extent[1], dtype=np.float64)
        x = origin[0] + (np.arange(w) + 0.5) * resolution  # (W,) pixel centres
        y = origin[1] + (h - np.arange(h) - 0.5) * resolution  # (H,) row 0 = largest y
        free &= ((y >= lo[1]) & (y <= hi[1]))[:, None] & ((x >= lo[0]) & (x <= hi[0]))[None, :]
    return free


def free_recall(image: np.ndarray, free_value: int, true_free: np.ndarray) -> float | None:
    """Share of the true free pixels (`true_free_near_path`) that the map marks free; None if none."""
    n = int(true_free.sum())
    return float((np.asarray(image)[true_free] == free_value).sum() / n) if n else None


def map_safety(image: np.ndarray, origin: tuple[float, float], resolution: float, obstacles_xy: np.ndarray,
               path_xy: np.ndarray, free_value: int = 254, zones: tuple[float, ...] = SAFETY_ZONES_M,
               tolerance: float = SAFETY_TOLERANCE_M) -> list[SafetyZone]:
    """Per zone, the ground-truth obstacle pixels and how many the map `image` marks free for sure.

    image (H, W) trinary map (maps.occupancy raster); obstacles_xy (K, 2) ground-truth points at
    camera height (m); path_xy (P, 2) the robot's camera positions (m).
    """
    obst = obstacle_pixels(obstacles_xy, origin, resolution, np.asarray(image).shape)
    return pixels_marked_free(image, obst, origin, resolution, path_xy, free_value, zones, tolerance)


def pixels_marked_free(image: np.ndarray, obstacles: np.ndarray, origin: tuple[float, float], resolution: float,
                       path_xy: np.ndarray, free_value: int = 254, zones: tuple[float, ...] = SAFETY_ZONES_M,
                       tolerance: float = SAFETY_TOLERANCE_M) -> list[SafetyZone]:
    """`map_safety` of obstacle pixels given as a mask ((H, W) bool, the map's raster)."""
    rows, cols, dist = path_distances(obstacles, origin, resolution, path_xy)
    missed = free_for_sure(image, free_value, resolution, tolerance)[rows, cols]
    return [SafetyZone(float(z), int((dist <= z).sum()), int((missed & (dist <= z)).sum())) for z in zones]


def path_distances(mask: np.ndarray, origin: tuple[float, float], resolution: float,
                   path_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of `mask` ((H, W) bool, the maps.occupancy raster) as rows (K,), cols (K,) and
    the distance (K,) m from each one's centre to the nearest point of the path (P, 2 m; inf
    without one)."""
    from scipy.spatial import cKDTree

    rows, cols = np.nonzero(mask)
    h = mask.shape[0]
    centres = np.column_stack([origin[0] + (cols + 0.5) * resolution, origin[1] + (h - rows - 0.5) * resolution])
    path = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    dist = cKDTree(path).query(centres)[0] if len(path) and len(centres) else np.full(len(centres), np.inf)
    return rows, cols, dist


@dataclass(frozen=True)
class MapJudgement:
    """A map's safety figures: obstacles marked free per zone and the free space it keeps."""

    zones: list[SafetyZone]
    free_recall: float | None  # share of the true free space near the path the map marks free
    # the same share of the drivable free space (less what the body meets below the band); None
    # without the body's ground truth (a map without its floor)
    free_recall_drivable: float | None = None
    # the share of the drivable space a PLANNER_RADIUS_M robot can stand in (near the path) that a
    # planner on the map reaches from where the robot drove (`planner_reach`); None as above
    planner_reach: float | None = None
    # `zones` for what the body meets below the band (gt.body_slice's pixels that hold no band
    # obstacle): a pallet or a rack's lowest shelf the map marks free; None as above
    below_band: list[SafetyZone] | None = None

    def block(self) -> dict:
        return {"zones": _zones_block(self.zones),
                "free_recall": _round(self.free_recall), "free_recall_drivable": _round(self.free_recall_drivable),
                "planner_reach": _round(self.planner_reach),
                "below_band": None if self.below_band is None else _zones_block(self.below_band)}


def _zones_block(zones: list[SafetyZone]) -> dict:
    return {_zone_name(z.within_m): {"obstacles": z.obstacles, "marked_free": z.marked_free,
                                     "free_share": None if z.free_share is None else round(z.free_share, 4)}
            for z in zones}


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


def _zone_name(within_m: float) -> str:
    return "all" if math.isinf(within_m) else f"{within_m:g}m"


def judge_map(image: np.ndarray, origin: tuple[float, float], resolution: float, obstacles_xy: np.ndarray,
              path_xy: np.ndarray, free_value: int = 254, extent: tuple | None = None,
              body_xy: np.ndarray | None = None) -> MapJudgement:
    """`map_safety` and `free_recall` of a trinary map `image` (H, W) against ground-truth
    obstacle points (K, 2) at camera height and the robot's path (P, 2), metres; the true free
    space lies inside `extent` ((x, y) lo, hi m, the ground truth's box; None: the raster). With
    `body_xy` (B, 2), the points the body meets below the band (gt.body_slice), the drivable free
    recall too: the true free space taken as free of those as well; and those points' own pixels
    (the ones without a band obstacle) that the map marks free, by zone."""
    obst = obstacle_pixels(obstacles_xy, origin, resolution, np.asarray(image).shape)
    free = true_free_near_path(obst, origin, resolution, path_xy, extent=extent)
    drivable = reach = below = None
    if body_xy is not None:
        body = obstacle_pixels(body_xy, origin, resolution, obst.shape)
        below = pixels_marked_free(image, body & ~obst, origin, resolution, path_xy, free_value)
        drivable = free_recall(image, free_value, true_free_near_path(obst | body, origin, resolution, path_xy,
                                                                      extent=extent))
        stand = true_free_near_path(obst | body, origin, resolution, path_xy, clearance=PLANNER_RADIUS_M,
                                    extent=extent)  # where the robot's centre may truly be
        reach = planner_reach(image, origin, resolution, stand, path_xy, free_value=free_value)
    return MapJudgement(pixels_marked_free(image, obst, origin, resolution, path_xy, free_value),
                        free_recall(image, free_value, free), drivable, reach, below)


def configuration_space(image: np.ndarray, resolution: float, radius: float, free_value: int = 254) -> np.ndarray:
    """(H, W) bool: where the centre of a robot of `radius` m may be on the map (H, W): free pixels
    farther than `radius` from every pixel that is not free (occupied or unknown alike)."""
    from scipy.ndimage import distance_transform_edt

    return distance_transform_edt(np.asarray(image) == free_value) > radius / resolution + PIXEL_EPS


def planner_reach(image: np.ndarray, origin: tuple[float, float], resolution: float, true_space: np.ndarray,
                  path_xy: np.ndarray, radius: float = PLANNER_RADIUS_M, free_value: int = 254) -> float | None:
    """Share of `true_space` ((H, W) bool: where a robot of `radius` m may truly stand) that lies in
    the map's configuration space (free pixels farther than `radius` from every pixel that is not
    free, as `planner_check` plans) connected, 8 ways, to the component holding most of the path's
    pixels (P, 2 m): what a planner starting where the robot drove can reach. A lone occupied pixel
    in an aisle cuts it, though the free recall counts it once. None without true space."""
    from scipy.ndimage import label

    n = int(true_space.sum())
    if not n:
        return None
    image = np.asarray(image)
    labels, _ = label(configuration_space(image, resolution, radius, free_value), structure=np.ones((3, 3), dtype=bool))
    on_path = labels[obstacle_pixels(np.asarray(path_xy, dtype=np.float64).reshape(-1, 2), origin, resolution,
                                     image.shape)]
    on_path = on_path[on_path > 0]
    if not len(on_path):
        return 0.0
    main = np.bincount(on_path).argmax()
    return float((true_space & (labels == main)).sum() / n)


def safety_document(judgement: MapJudgement, observed: float, gt: str, resolution: float,
                    anchors: dict[str, MapJudgement] | None = None) -> dict:
    """metrics.json's "safety" block: the map's figures, and the same figures of the anchors
    (the maps the robot's range sensors alone and a LiDAR give, judged on the same raster)."""
    from virus_nerf.evaluation.gt import BODY_FLOOR_CLEARANCE_M

    doc = {"gt": gt, "resolution": resolution, "tolerance_m": SAFETY_TOLERANCE_M,
           "free_near_path_m": FREE_NEAR_PATH_M, "free_clearance_m": FREE_CLEARANCE_M,
           "drivable_from_floor_m": BODY_FLOOR_CLEARANCE_M, "observed": round(float(observed), 4), **judgement.block()}
    if anchors:
        doc["anchors"] = {name: j.block() for name, j in anchors.items()}
    return doc


ANCHOR_LABELS = {"sensors": "USS + IRS alone", "lidar": "LiDAR 2D map"}


def _figures(block: dict) -> str:
    recall, drivable, below = block.get("free_recall"), block.get("free_recall_drivable"), block.get("below_band")
    return (_shares(block["zones"]) + "; free space kept " + ("-" if recall is None else f"{recall:.1%}")
            + ("" if drivable is None else f" ({drivable:.1%} of the drivable)")
            + (f"; what the body meets below the band marked free: {_shares(below)}" if below else ""))


def _shares(zones: dict) -> str:
    """A zones block in words: "1m 0.5%, 2m -, all 1.0%"."""
    return ", ".join(f"{name} " + ("-" if b["free_share"] is None else f"{b['free_share']:.1%}")
                     for name, b in zones.items())


def safety_line(doc: dict) -> str:
    """One line for the table: obstacles marked free per zone, free recall, observed share, anchors."""
    line = (f"map safety ({doc['gt']} ground truth; shares of the obstacles within that distance of the path, "
            f"free space within {doc.get('free_near_path_m', 3):g} m of it): obstacles the map marks free: "
            f"{_figures(doc)}; map observed {doc['observed']:.1%}")
    for name, block in doc.get("anchors", {}).items():
        line += f"\n  beside it, {ANCHOR_LABELS.get(name, name)}: {_figures(block)}"
    if "planner" in doc:
        p = doc["planner"]
        line += (f"\n  a planner (robot radius {p['radius_m']:g} m) on the map: {p['crossing']} of {p['paths']} "
                 "paths between random free points pass a real obstacle" + below_words(p) + unsafe_words(p))
    return line


def below_words(planner: dict) -> str:
    """The planner block's paths past what the body meets below the band, in words ("" without them)."""
    if planner.get("crossing_below") is None:
        return ""
    return (f", {planner['crossing_below']} more pass only what the body meets below the band "
            f"({planner['unsafe_below_m2']:.4g} m^2 where its centre may touch that)")


def unsafe_words(planner: dict) -> str:
    """The planner block's unsafe space in words ("" for a block written before D99)."""
    if planner.get("unsafe_m2") is None:
        return ""
    share, near = planner.get("unsafe_share"), planner.get("unsafe_near_m2") or {}
    return (f"; it may put the robot's centre where it touches a real obstacle in {planner['unsafe_m2']:.4g} m^2"
            + ("" if share is None else f" ({share:.2%} of where it may put it)")
            + "".join(f", {a:.4g} m^2 within {z[:-1]} m of the path" for z, a in near.items()))


def safety_picture(image: np.ndarray, origin: tuple[float, float], resolution: float, obstacles_xy: np.ndarray,
                   path_xy: np.ndarray, tolerance: float = SAFETY_TOLERANCE_M,
                   body_xy: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB: the map (free white, unknown grey, occupied black), the ground-truth
    obstacles over it in blue, the ones it marks free in red, the path in green; with the points
    the body meets below the band (B, 2 m, gt.body_slice), their pixels that hold no band obstacle
    in brown, the ones the map marks free in orange (`below_band`'s pixels)."""
    from virus_nerf.maps.occupancy import FREE, OCCUPIED

    image = np.asarray(image)
    rgb = np.empty(image.shape + (3,), dtype=np.uint8)
    rgb[:] = MAP_UNKNOWN_RGB
    rgb[image == FREE] = MAP_FREE_RGB
    rgb[image == OCCUPIED] = MAP_OCCUPIED_RGB
    obst = obstacle_pixels(obstacles_xy, origin, resolution, image.shape)
    sure_free = free_for_sure(image, FREE, resolution, tolerance)
    missed = obst & sure_free
    if body_xy is not None:
        body = obstacle_pixels(body_xy, origin, resolution, image.shape) & ~obst
        rgb[body] = BODY_RGB
        rgb[body & sure_free] = BODY_MISSED_RGB
    rgb[obst] = OBSTACLE_RGB
    rgb[missed] = MISSED_RGB
    rgb[obstacle_pixels(path_xy, origin, resolution, image.shape)] = PATH_RGB
    return rgb


def lidar_rays_2d(recording, times: np.ndarray, height: float, band: float):
    """The reference a LiDAR robot has (issue 42): for each time (s), the LiDAR scan taken then (the
    nearest within SYNC_TOLERANCE_S; none: no rays), its points within +-band of `height` as 2D
    rays from the LiDAR (maps.evidence.Rays2D)."""
    from virus_nerf.evaluation.testpoints import lidar_scan_index
    from virus_nerf.maps.evidence import Rays2D
    from virus_nerf.sensors.geometry import transform_points

    out = Rays2D.empty()
    scans = {lidar_scan_index(recording, float(t)) for t in np.asarray(times).reshape(-1)}
    for k in sorted(scans - {None}):
        pose = recording.lidar_pose_at(float(recording.lidar_times[k]))  # (4, 4) LiDAR to world
        pts = transform_points(pose, recording.lidar_scan(k).astype(np.float64))  # (M, 3) world
        xy = pts[np.abs(pts[:, 2] - height) <= band, :2] - pose[None, :2, 3]
        r = np.linalg.norm(xy, axis=1)
        ok = r > 1e-6
        out = out.concat(Rays2D(np.broadcast_to(pose[:2, 3], (int(ok.sum()), 2)).copy(), xy[ok] / r[ok, None], r[ok]))
    return out


@dataclass
class RunSafety:
    """A trained mapper's safety block (metrics.json) and its picture (`safety_picture`) on the
    map's raster (its lower left corner `origin`, m, and `resolution`, m a pixel)."""

    document: dict
    picture: np.ndarray  # (H, W, 3) uint8, row 0 = largest y
    origin: tuple[float, float] = (0.0, 0.0)
    resolution: float = 0.05


def mapper_safety(mapper, recording, band: float, resolution: float = 0.05) -> RunSafety | None:
    """The safety of the mapper's 2D map (as its snapshots write it) against the recording's
    LiDAR map at camera height (+-band m), beside its anchors; None without a LiDAR map or frames."""
    from virus_nerf.data.room_box import fit_scene_box
    from virus_nerf.evaluation.gt import body_slice, height_slice
    from virus_nerf.maps.evidence import sensor_rays_2d
    from virus_nerf.maps.extract import spread_rows
    from virus_nerf.maps.observed import apply_mask, observed_share
    from virus_nerf.maps.occupancy import MAP_POSES, UNKNOWN, scan_occupancy

    if recording.map_path is None or not mapper.frames:
        return None
    m = mapper.map2d(resolution, max_poses=MAP_POSES)
    height = mapper.camera_height()
    obstacles = height_slice(recording.lidar_map(), height, band)
    body = body_slice(recording.lidar_map(), height, band)  # (B, 2) what the body meets below the band
    store = mapper.store
    path = store.cam_to_world[:, :2, 3]
    lo, hi = np.asarray(mapper.box.lo[:2]), np.asarray(mapper.box.hi[:2])
    seen = mapper.observed(resolution)
    sensors = sensor_rays_2d(store.cam_to_world, store.uss_range, store.irs_range, height,
                             tuple(mapper.config.sensors))
    sensor_map = scan_occupancy(sensors.origins, sensors.directions, sensors.ranges, lo, hi, resolution)
    rows = spread_rows(len(store), MAP_POSES)  # the map's scan positions
    lidar = lidar_rays_2d(recording, store.times[rows], height, band)
    lidar_map = scan_occupancy(lidar.origins, lidar.directions, lidar.ranges, lo, hi, resolution)
    gt_box = fit_scene_box(recording)  # the LiDAR map's extent: true free space lies inside it
    extent = (gt_box.lo[:2], gt_box.hi[:2])
    anchors = {"sensors": judge_map(apply_mask(sensor_map.image, seen, UNKNOWN), m.origin, resolution,
                                    obstacles, path, extent=extent, body_xy=body),
               "lidar": judge_map(lidar_map.image, m.origin, resolution, obstacles, path, extent=extent,
                                  body_xy=body)}
    doc = safety_document(judge_map(m.image, m.origin, resolution, obstacles, path, extent=extent, body_xy=body),
                          observed_share(seen), "map", resolution, anchors)
    doc["planner"] = planner_check(m.image, m.origin, resolution, obstacles, path_xy=path, body_xy=body).block()
    return RunSafety(doc, safety_picture(m.image, m.origin, resolution, obstacles, path, body_xy=body),
                     (float(m.origin[0]), float(m.origin[1])), resolution)


# 100 starts, 10 goals each: up to 1000 paths. A thin obstacle the map lost lies on a few paths
# in a thousand: 50 paths told a safe map from one with a hole by where their ends fell (D96)
PLANNER_STARTS, PLANNER_GOALS = 100, 10


@dataclass(frozen=True)
class PlannerCheck:
    """Paths a planner finds on the map between random free points, and how many hit a real obstacle."""

    paths: int  # paths found (start and goal connected in the map's free space)
    crossing: int  # of them, paths passing closer than radius - tolerance to a ground-truth obstacle
    radius_m: float
    # where the planner may put the robot's centre though a real obstacle lies closer than radius -
    # tolerance (m^2; every path through it crosses one): the check's figure without its random ends
    unsafe_m2: float = 0.0
    space_m2: float = 0.0  # the whole configuration space (m^2)
    # of unsafe_m2, the part within each of SAFETY_ZONES_M's finite distances of the path (m^2, by
    # zone name; empty without the path): where the robot drives next, not across the room (D102)
    unsafe_near_m2: dict[str, float] = field(default_factory=dict)
    # with the body's ground truth (gt.body_slice): the paths that pass no band obstacle but come
    # as close to one the body meets below the band (a pallet, a rack's lowest shelf, a seat), and
    # the configuration space's area where that may happen (m^2); None without it
    crossing_below: int | None = None
    unsafe_below_m2: float | None = None

    @property
    def unsafe_share(self) -> float | None:
        return self.unsafe_m2 / self.space_m2 if self.space_m2 else None

    def block(self) -> dict:
        share = self.unsafe_share
        return {"paths": self.paths, "crossing": self.crossing, "radius_m": self.radius_m,
                "unsafe_m2": round(self.unsafe_m2, 4), "unsafe_share": None if share is None else round(share, 6),
                **({"unsafe_near_m2": {z: round(a, 4) for z, a in self.unsafe_near_m2.items()}}
                   if self.unsafe_near_m2 else {}),
                **({} if self.crossing_below is None else
                   {"crossing_below": self.crossing_below, "unsafe_below_m2": round(self.unsafe_below_m2, 4)})}


def planner_check(image: np.ndarray, origin: tuple[float, float], resolution: float, obstacles_xy: np.ndarray,
                  seed: int = 0, radius: float = PLANNER_RADIUS_M, tolerance: float = SAFETY_TOLERANCE_M,
                  free_value: int = 254, path_xy: np.ndarray | None = None,
                  body_xy: np.ndarray | None = None) -> PlannerCheck:
    """Plan as a robot of `radius` m would on the map (H, W): its configuration space is the free
    pixels farther than `radius` from every pixel that is not free (occupied or unknown alike).
    Shortest 8-connected paths (Dijkstra, scipy.sparse.csgraph) from PLANNER_STARTS random
    configuration-space pixels to PLANNER_GOALS random others each (seeded); a path crosses a
    ground-truth obstacle (points (K, 2) m) when one of its pixels lies within radius - tolerance
    of an obstacle pixel (the tolerance forgives a wall drawn a pixel or two off, as `map_safety`).
    Beside the paths, the configuration space's pixels within that distance of an obstacle pixel,
    as an area: a path crosses an obstacle only through them, and unlike the paths they do not
    depend on where random ends fell (D99); with the robot's path (P, 2 m), also the part of that
    area within 1 m and 2 m of it (D102). With the points the body meets below the band (B, 2 m,
    gt.body_slice), the same count and area for them where no band obstacle is that close: the band's
    ground truth does not see a pallet, the robot's body meets it."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    image = np.asarray(image)
    h, w = image.shape
    space = configuration_space(image, resolution, radius, free_value)  # (H, W) robot centre may be here
    obst = obstacle_pixels(obstacles_xy, origin, resolution, (h, w))
    danger = pixels_within(obst, resolution, radius - tolerance)  # (H, W) a centre here touches a band obstacle
    below = None  # (H, W) a centre here touches only what the body meets below the band
    if body_xy is not None:
        body = obstacle_pixels(body_xy, origin, resolution, (h, w)) & ~obst
        below = pixels_within(body, resolution, radius - tolerance) & ~danger
    area = resolution * resolution
    unsafe_m2, space_m2 = float((space & danger).sum()) * area, float(space.sum()) * area
    near = unsafe_near_path(space & danger, origin, resolution, path_xy) if path_xy is not None else {}
    unsafe_below = None if below is None else float((space & below).sum()) * area
    nodes = np.flatnonzero(space.ravel())
    if len(nodes) < 2:
        return PlannerCheck(0, 0, radius, unsafe_m2, space_m2, near, None if below is None else 0, unsafe_below)
    index = np.full(h * w, -1, dtype=np.int64)
    index[nodes] = np.arange(len(nodes))
    r, c = np.divmod(nodes, w)
    src, dst, cost = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        rr, cc = r + dr, c + dc
        ok = (rr < h) & (cc >= 0) & (cc < w)
        ok[ok] = space[rr[ok], cc[ok]]
        src.append(index[nodes[ok]])
        dst.append(index[rr[ok] * w + cc[ok]])
        cost.append(np.full(int(ok.sum()), float(np.hypot(dr, dc))))
    n = len(nodes)
    graph = coo_matrix((np.concatenate(cost), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)).tocsr()
    rng = np.random.default_rng(seed)
    starts = rng.choice(n, size=min(PLANNER_STARTS, n), replace=False)
    dist, pred = dijkstra(graph, directed=False, indices=starts, return_predecessors=True)
    paths = crossing = crossing_below = 0
    for k in range(len(starts)):
        goals = rng.choice(n - 1, size=min(PLANNER_GOALS, n - 1), replace=False)
        for goal in goals + (goals >= starts[k]):  # any node but the start
            if not np.isfinite(dist[k, goal]):
                continue
            paths += 1
            v, hit, hit_below = goal, False, False
            while v >= 0 and not hit:
                hit = bool(danger.flat[nodes[v]])
                hit_below |= below is not None and bool(below.flat[nodes[v]])
                v = pred[k, v]
            crossing += hit
            crossing_below += hit_below and not hit
    return PlannerCheck(paths, crossing, radius, unsafe_m2, space_m2, near,
                        None if below is None else crossing_below, unsafe_below)


def pixels_within(mask: np.ndarray, resolution: float, distance: float) -> np.ndarray:
    """(H, W) bool: the pixels whose centre lies within `distance` m of a pixel of `mask` (H, W)."""
    from scipy.ndimage import distance_transform_edt

    if not mask.any():
        return np.zeros(mask.shape, dtype=bool)
    return distance_transform_edt(~mask) <= distance / resolution + PIXEL_EPS


def unsafe_near_path(unsafe: np.ndarray, origin: tuple[float, float], resolution: float,
                     path_xy: np.ndarray) -> dict[str, float]:
    """{zone name: m^2} of the unsafe pixels ((H, W) bool, the map's raster) whose centre lies
    within each finite distance of SAFETY_ZONES_M of the path (P, 2 m)."""
    dist = path_distances(unsafe, origin, resolution, path_xy)[2]
    return {_zone_name(z): float((dist <= z).sum()) * resolution * resolution for z in SAFETY_ZONES_M
            if math.isfinite(z)}
