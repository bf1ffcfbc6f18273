"""LiDAR poses for an imported bag: KISS-ICP odometry, a /tf chain, or a CSV/TUM trajectory.

All three give a `PoseTrack` of LiDAR-to-world poses; camera poses are the LiDAR pose
interpolated at the camera stamp times the camera-in-LiDAR mounting (docs/method.md 4).

KISS-ICP (Vizzo et al. 2023) ships outdoor defaults: max_range 100 m, from which its map voxel
is max_range / 100 = 1 m, too coarse for a room. `KissIcpSettings()` are indoor settings for a
robot on one flat floor, measured on simulated offices, common areas and warehouses (D118,
docs/usage.md "KISS-ICP indoors", benchmarks/bench_bag_odometry.py).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data.csvtable import MAX_TIME_S, time_unit_problem
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.geometry import QUATERNION_NORM_TOLERANCE, interpolate_poses, pose_matrix


@dataclass
class PoseTrack:
    """LiDAR-to-world poses at increasing times."""

    times_s: np.ndarray  # (K,) s
    poses: np.ndarray  # (K, 4, 4)

    def at(self, t_s: np.ndarray, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Poses (N, 4, 4) at times (N,): slerp/lerp between the neighbours; a time outside the
        track by more than `tolerance_s` (or any time when the track is empty) is invalid (N,) bool."""
        t_s = np.asarray(t_s, dtype=np.float64)
        if len(self.times_s) == 0:
            return np.tile(np.eye(4), (len(t_s), 1, 1)), np.zeros(len(t_s), dtype=bool)
        ok = (t_s >= self.times_s[0] - tolerance_s) & (t_s <= self.times_s[-1] + tolerance_s)
        return interpolate_poses(self.times_s, self.poses, t_s), ok


@dataclass(frozen=True)
class KissIcpSettings:
    """KISS-ICP parameters (metres). deskew needs per-point times, which the ETHZ-style filtered
    scans do not carry; refine_start_s re-registers the scans of the first seconds, taken while the
    constant-velocity prediction of KISS-ICP is still wrong, against the map of the next seconds,
    and moves the whole track so that the first scan stays the world frame. 8 s, not 2: in a
    warehouse KISS-ICP lags the robot from about 1 to 5 s (0.47 for 0.50 m/s), and the lag then
    shifts every later pose by 6-7 cm from the first scan's frame (D120).

    drop_floor_ceiling_m: registration ignores points within this distance of the floor and the
    ceiling (found in the first scan, `find_floor`; 0 = keep all). A 16-beam LiDAR draws
    the floor as rings centred on itself that move with it; matched point to point they pull the
    estimate back towards standstill: in a common area, whose walls are far and few, KISS-ICP
    registered 0.3 m/s for 0.5 m/s and ended 1.4 m behind after 20 s (D118).

    planar: the robot drives on one flat floor. Each pose keeps the first scan's height, roll and
    pitch over the floor (found in the first scan, `find_floor`; where none is found the scans
    register in 6 degrees of freedom): only the yaw and the translation along the floor
    are registered, projected before the scan enters KISS-ICP's map. Without the floor the 16
    beams constrain pitch and roll poorly (1.1-1.6 deg median rotation error); on the floor they
    need not be registered. On a ramp the poses keep the first floor's height; turned off (the
    topics file's `[lidar] flat_floor = false`) they follow it only in part and drift in height
    on a flat floor (D119, benchmarks/bench_ramp_odometry.py)."""

    max_range_m: float = 30.0
    min_range_m: float = 0.3
    voxel_size_m: float = 0.2
    deskew: bool = False
    initial_threshold_m: float = 2.0
    min_motion_m: float = 0.1
    refine_start_s: float = 8.0
    refine_window_s: float = 3.0
    drop_floor_ceiling_m: float = 0.2
    planar: bool = True


    @classmethod
    def library_defaults(cls) -> KissIcpSettings:
        """KISS-ICP 1.x's own (outdoor) defaults, for comparison."""
        return cls(max_range_m=100.0, min_range_m=0.0, voxel_size_m=1.0, deskew=True,
                   initial_threshold_m=2.0, min_motion_m=0.1, refine_start_s=0.0, drop_floor_ceiling_m=0.0,
                   planar=False)


def scale_motion(delta: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion `delta` (4, 4) stretched in time by `factor`: its rotation vector and its
    translation times `factor` (constant velocity over a longer or shorter interval)."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(delta[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = np.asarray(delta[:3, 3]) * factor
    return out


def planar_pose(pose: np.ndarray, level: np.ndarray) -> np.ndarray:
    """`pose` (4, 4, in the first scan's frame) made a motion along the floor: in the frame
    `level` (3, 3) takes it to (z up from the floor), the rotation about z and the x, y
    translation kept, the height, roll and pitch of the first scan."""
    a = np.eye(4)
    a[:3, :3] = level
    q = a @ pose @ a.T
    yaw = np.arctan2(q[1, 0], q[0, 0])
    flat = np.eye(4)
    flat[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    flat[:2, 3] = q[:2, 3]
    return a.T @ flat @ a


@dataclass(frozen=True)
class FloorFrame:
    """The floor and the ceiling of a scan: heights are measured along `normal` (the floor's
    upward normal in sensor coordinates; z for a LiDAR mounted level)."""

    normal: np.ndarray  # (3,) unit
    floor_m: float  # height of the floor below the sensor (negative; -inf: none found)
    ceiling_m: float  # height of the ceiling (+inf: none found)

    def heights(self, points: np.ndarray) -> np.ndarray:
        """(M,) m along the normal, from the sensor."""
        return np.asarray(points, dtype=np.float64) @ self.normal

    def level(self) -> np.ndarray:
        """Rotation (3, 3) taking sensor coordinates to ones whose z axis is the normal."""
        from scipy.spatial.transform import Rotation

        return Rotation.align_vectors([[0.0, 0.0, 1.0]], [self.normal])[0].as_matrix()


def _bottom_bin(h: np.ndarray, bin_m: float, max_below: float, n: int) -> tuple[int, float]:
    """(points, centre height) of the densest `bin_m` bin of heights `h` (M,) below -0.1 m with at
    most `max_below` x `n` of the heights under it (the floor is the bottom: a table top or a shelf
    has the floor under it, however dense); (0, nan) when no bin qualifies. The ceiling is the
    bottom of -h."""
    values, counts = np.unique(np.floor(h[h < -0.1] / bin_m).astype(np.int64), return_counts=True)
    bottom = np.flatnonzero(np.cumsum(counts) - counts <= max_below * n)
    if len(bottom) == 0:
        return 0, math.nan
    k = int(bottom[np.argmax(counts[bottom])])
    return int(counts[k]), float((values[k] + 0.5) * bin_m)


def _bottom_planes(sample: np.ndarray, roll_pitch: np.ndarray, bin_m: float, max_below: float) -> list:
    """Of the normals tilted by (C, 2) roll and pitch (rad): (points, normal (3,), height) of each
    one's `_bottom_bin`, those that have one, the most points first."""
    from scipy.spatial.transform import Rotation

    normals = Rotation.from_euler("xy", roll_pitch).apply([0.0, 0.0, 1.0])  # (C, 3)
    out = []
    for c, h in enumerate((sample @ normals.T).T):  # heights along each candidate normal
        count, height = _bottom_bin(h, bin_m, max_below, len(sample))
        if count > 0:
            out.append((count, normals[c], height))
    return sorted(out, key=lambda row: -row[0])  # stable: of equals, the first normal


def _refined_floor(p: np.ndarray, normal: np.ndarray, floor: float, bin_m: float) -> tuple[np.ndarray, float, int]:
    """The least-squares plane through the points (M, 3) ever nearer to the plane (`normal`,
    height `floor`): its upward normal, its height and the points within bin_m / 4 of it."""
    for window in (bin_m, bin_m / 2, bin_m / 4):
        near = p[np.abs(p @ normal - floor) < window]
        if len(near) < 3:
            return normal, floor, 0
        normal = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)[2][2]
        normal = normal if normal[2] > 0 else -normal
        floor = float(np.median(near @ normal))
    return normal, floor, len(near)


def find_floor(points: np.ndarray, max_tilt_deg: float = 15.0, step_deg: float = 1.0, bin_m: float = 0.1,
               min_share: float = 0.03, max_below: float = 0.02, search_points: int = 4000,
               candidates: int = 6, apart_steps: float = 2.0, max_under: float = 0.005) -> FloorFrame:
    """The floor and ceiling of a LiDAR scan (M, 3), the LiDAR mounted up to `max_tilt_deg` off
    level. The normals (roll and pitch in `step_deg` steps) whose densest `bin_m` height bin at the
    bottom holds the most points (`_bottom_bin`) are the `candidates`, at least `apart_steps`
    steps apart; each is searched in quarter steps around it and refined by least-squares planes
    through the points ever nearer to it (`_refined_floor`), and the plane that holds the most
    points within bin_m / 4 with at most `max_under` of the points more than bin_m / 2 under it
    is the floor (none when it is tilted more than max_tilt_deg + step_deg: a steep slope ahead
    that outnumbers the floor leaves the floor unknown rather than wrong).
    The floor needs `min_share` of the points in its bin and within bin_m / 4 of its plane; the
    ceiling (the densest bin above +0.1 m along the same normal with at most `max_below` of the
    points over it) `min_share` too. Measured on the ETHZ office recording: its RS-16 is tilted
    about 2 deg, and a height bin of the sensor's own z axis holds too few floor points to find
    it; its floor holds 7 % of a scan's points, and other points along a 10 deg normal held as
    many in one bin in 6 of its 11 scans when the densest bin alone chose (the thin plane's count
    decides). The real floor has no point more than 5 cm under it, such a tilted plane 1-2 % (the
    sample's rear half cut away, D119), hence `max_under` 0.5 %."""
    p = np.asarray(points, dtype=np.float64)
    none = FloorFrame(np.array([0.0, 0.0, 1.0]), -np.inf, np.inf)
    if len(p) == 0:
        return none
    sample = p[:: max(1, len(p) // search_points)]
    angles = np.radians(np.arange(-max_tilt_deg, max_tilt_deg + 1e-9, step_deg))
    grid = np.stack([a.ravel() for a in np.meshgrid(angles, angles, indexing="ij")], axis=1)
    apart = math.cos(np.radians(apart_steps * step_deg))
    starts: list[np.ndarray] = []
    for _, normal, _ in _bottom_planes(sample, grid, bin_m, max_below):
        if all(normal @ other < apart for other in starts):
            starts.append(normal)
            if len(starts) == candidates:
                break
    fine = np.radians(np.arange(-step_deg, step_deg + 1e-9, step_deg / 4))
    best = (0, None, None)
    for start in starts:
        roll, pitch = np.arcsin(-start[1]), np.arctan2(start[0], start[2])  # of Rotation.from_euler("xy")
        near_grid = np.stack([a.ravel() for a in np.meshgrid(roll + fine, pitch + fine, indexing="ij")], axis=1)
        rows = _bottom_planes(sample, near_grid, bin_m, max_below)
        if not rows or rows[0][0] < min_share * len(sample):
            continue
        _, normal, floor = rows[0]
        normal, floor, thin = _refined_floor(p, normal, floor, bin_m)
        if thin > best[0] and np.sum(p @ normal < floor - bin_m / 2) <= max_under * len(p):
            best = (thin, normal, floor)
    thin, normal, floor = best
    if (normal is None or thin < min_share * len(p)  # a floor is a thin plane: not the bottom of the walls
            or np.degrees(np.arccos(min(normal[2], 1.0))) > max_tilt_deg + step_deg):
        return none  # none, or one tilted more than the search covers
    h = p @ normal
    count, top = _bottom_bin(-h, bin_m, max_below, len(p))
    ceiling = float(np.median(h[np.abs(h + top) < bin_m])) if count >= min_share * len(p) else np.inf
    return FloorFrame(normal, floor, ceiling)


def _kiss_config(s: KissIcpSettings):
    from kiss_icp.config import KISSConfig

    cfg = KISSConfig()
    cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = s.max_range_m, s.min_range_m, s.deskew
    cfg.mapping.voxel_size = s.voxel_size_m
    cfg.adaptive_threshold.initial_threshold = s.initial_threshold_m
    cfg.adaptive_threshold.min_motion_th = s.min_motion_m
    cfg.registration.max_num_threads = 1  # the machine is shared; a room's scans are small
    return cfg


class ScanRegistration:
    """KISS-ICP over scans in time order, one `register` call a scan -> its pose (4, 4).

    stretch: scans may be skipped (a stream keeping up, kiss_worker.py): KISS-ICP predicts each
    pose by repeating the last motion, scan to scan; it is stretched to the interval actually
    registered (`scale_motion`) when that differs from the last one by more than 1 %. Without it
    the registration is KISS-ICP's own (the importer's poses)."""

    def __init__(self, settings: KissIcpSettings, stretch: bool = False) -> None:
        from kiss_icp.kiss_icp import KissICP

        self.settings = settings
        self.icp, self.stretch = KissICP(_kiss_config(settings)), stretch
        self.last_t: float | None = None  # the last registered scan's time
        self.last_dt: float | None = None  # the interval icp.last_delta spans
        self.started = False
        self.floor: FloorFrame | None = None  # the first scan's (drop_floor_ceiling_m, planar)
        self.band: tuple[float, float] | None = None  # heights kept along floor.normal (drop_floor_ceiling_m)
        self.level: np.ndarray | None = None  # (3, 3) first scan's frame -> the floor's (planar)

    def start(self, points: np.ndarray) -> None:
        """The first scan's floor and ceiling: the heights kept, the floor's plane."""
        self.started = True
        s = self.settings
        if s.drop_floor_ceiling_m <= 0 and not s.planar:
            return
        self.floor = find_floor(points)
        if s.drop_floor_ceiling_m > 0:
            self.band = (self.floor.floor_m + s.drop_floor_ceiling_m, self.floor.ceiling_m - s.drop_floor_ceiling_m)
        if s.planar and math.isfinite(self.floor.floor_m):
            self.level = self.floor.level()

    def describe(self) -> dict:
        """The first scan's floor as the registration used it (JSON-ready; `note` says when the
        motion could not be kept along the floor it was asked to keep it along)."""
        if self.floor is None:
            return {"floor_searched": False}
        f = self.floor
        found = math.isfinite(f.floor_m)
        out = {"floor_found": found,
               "tilt_deg": round(math.degrees(math.acos(min(float(f.normal[2]), 1.0))), 2) if found else None,
               "floor_m": round(f.floor_m, 3) if found else None,
               "ceiling_m": round(f.ceiling_m, 3) if math.isfinite(f.ceiling_m) else None,
               "motion": "along the floor" if self.level is not None else "6 degrees of freedom"}
        if self.settings.planar and self.level is None:
            out["note"] = ("KISS-ICP found no floor in the first LiDAR scan (a LiDAR tilted more than 15 deg, or one "
                           "that does not see the floor): the scans were registered in 6 degrees of freedom with the "
                           "floor kept, which lags in large rooms (docs/usage.md, KISS-ICP indoors)")
        return out

    def crop(self, points: np.ndarray) -> np.ndarray:
        """The points registration uses (M', 3) float64: without the floor and ceiling's bands."""
        p = np.asarray(points, dtype=np.float64)
        if self.band is None:
            return p
        h = self.floor.heights(p)
        return p[(h > self.band[0]) & (h < self.band[1])]

    def project(self, pose: np.ndarray) -> np.ndarray:
        """A registered pose as the robot can move (planar: along the floor)."""
        return pose if self.level is None else planar_pose(pose, self.level)

    def register(self, t: float, points: np.ndarray) -> np.ndarray:
        """points (M, 3), sensor frame -> the scan's pose in the first scan's frame (4, 4)."""
        if not self.started:
            self.start(points)
        points = self.crop(points)
        if self.stretch and self.last_dt:
            ratio = (t - self.last_t) / self.last_dt
            if abs(ratio - 1.0) > 0.01:
                self.icp.last_delta = scale_motion(self.icp.last_delta, ratio)
        if self.level is None or self.last_t is None:  # (the first scan is the world frame, as it is)
            self.icp.register_frame(points, np.empty(0))
        else:
            self._register_planar(points)
        self.last_t, self.last_dt = t, (None if self.last_t is None else t - self.last_t)
        return np.array(self.icp.last_pose, dtype=np.float64)

    def _register_planar(self, points: np.ndarray) -> None:
        """KissICP.register_frame's steps (kiss_icp 1.x) with the registered pose projected
        along the floor before the map, the threshold and the motion model take it."""
        icp = self.icp
        frame = icp.preprocessor.preprocess(points, np.empty(0), icp.last_delta)
        source, frame_downsample = icp.voxelize(frame)
        sigma = icp.adaptive_threshold.get_threshold()
        guess = icp.last_pose @ icp.last_delta
        pose = self.project(icp.registration.align_points_to_map(
            points=source, voxel_map=icp.local_map, initial_guess=guess,
            max_correspondance_distance=3 * sigma, kernel=sigma))
        icp.adaptive_threshold.update_model_deviation(np.linalg.inv(guess) @ pose)
        icp.local_map.update(frame_downsample, pose)
        icp.last_delta = np.linalg.inv(icp.last_pose) @ pose
        icp.last_pose = pose


def kiss_icp_track(times_s: np.ndarray, load_scan: Callable[[int], np.ndarray],
                   settings: KissIcpSettings | None = None,
                   registration: ScanRegistration | None = None) -> PoseTrack:
    """Register the scans (k -> (M, 3) points, sensor frame, in time order) with KISS-ICP
    (`registration`, a new ScanRegistration of `settings` by default: pass one to read its
    `describe()` after).

    The first scan's pose is the world frame (as in the ETHZ recordings)."""
    s = registration.settings if registration is not None else (settings or KissIcpSettings())
    cfg = _kiss_config(s)
    registration = registration or ScanRegistration(s)
    poses = np.empty((len(times_s), 4, 4))
    for k in range(len(times_s)):
        poses[k] = registration.register(float(times_s[k]), load_scan(k))
    track = PoseTrack(np.asarray(times_s, dtype=np.float64), poses)
    if s.refine_start_s > 0 and len(times_s) > 1:
        _refine_start(track, lambda k: registration.crop(load_scan(k)), cfg, s, registration.project)
    return track


def _refine_start(track: PoseTrack, load_scan, cfg, s: KissIcpSettings, project=lambda pose: pose) -> None:
    """Re-register the scans of the first refine_start_s seconds, newest first, against a map of
    the scans of the following refine_window_s seconds placed by their (settled) poses. A
    recording shorter than both re-registers its first part against the rest (at least half)."""
    from kiss_icp.mapping import get_voxel_hash_map
    from kiss_icp.registration import get_registration
    from kiss_icp.voxelization import voxel_down_sample

    t0, span = track.times_s[0], track.times_s[-1] - track.times_s[0]
    start_s = min(s.refine_start_s, max(span - s.refine_window_s, span / 2))
    early = np.flatnonzero(track.times_s < t0 + start_s)
    later = np.flatnonzero((track.times_s >= t0 + start_s) & (track.times_s < t0 + start_s + s.refine_window_s))
    if len(later) == 0 or len(early) == 0:
        return
    vmap = get_voxel_hash_map(cfg)
    for k in later:
        pts = voxel_down_sample(np.asarray(load_scan(k), dtype=np.float64), s.voxel_size_m * 0.5)
        vmap.add_points(pts @ track.poses[k, :3, :3].T + track.poses[k, :3, 3])
    reg = get_registration(cfg)
    sigma = 0.1  # the map is settled: a tight correspondence threshold (3 sigma) and kernel
    guess = track.poses[later[0]]
    first = track.poses[0].copy()
    for k in early[::-1]:
        pts = voxel_down_sample(np.asarray(load_scan(k), dtype=np.float64), s.voxel_size_m * 0.5)
        src = voxel_down_sample(pts, s.voxel_size_m * 1.5)
        guess = project(reg.align_points_to_map(src, vmap, guess, 3 * sigma, sigma))
        track.poses[k] = guess
        vmap.add_points(pts @ guess[:3, :3].T + guess[:3, 3])
    # keep the first scan as the world frame
    fix = first @ np.linalg.inv(track.poses[0])
    track.poses[:] = fix @ track.poses


def csv_track(path: str | Path) -> PoseTrack:
    """LiDAR poses from `time,x,y,z,qx,qy,qz,qw` CSV (header row) or a TUM file
    (`t x y z qx qy qz qw` separated by spaces, `#` comments)."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "is a directory; expected a pose file (--poses-file)" if path.is_dir()
                              else "pose file not found (--poses-file)")
    rows: list[tuple[int, list[str]]] = []
    with path.open(newline="") as fh:
        for n, line in enumerate(fh, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            parts = next(csv.reader([text])) if "," in text else text.split()
            rows.append((n, [p.strip() for p in parts]))
    if rows and rows[0][1][:1] == ["time"]:
        if rows[0][1] != ["time", "x", "y", "z", "qx", "qy", "qz", "qw"]:
            raise DataFormatError(path, "header must be time,x,y,z,qx,qy,qz,qw", row=rows[0][0])
        rows = rows[1:]
    if not rows:
        raise DataFormatError(path, "no poses; expected rows of time,x,y,z,qx,qy,qz,qw (CSV) or a TUM file")
    values = np.empty((len(rows), 8))
    for i, (n, parts) in enumerate(rows):
        if len(parts) != 8:
            raise DataFormatError(path, f"has {len(parts)} values; expected 8 (time x y z qx qy qz qw)", row=n)
        try:
            values[i] = [float(p) for p in parts]
        except ValueError:
            raise DataFormatError(path, f"values {parts} are not all numbers", row=n) from None
    names = ("time", "x", "y", "z", "qx", "qy", "qz", "qw")
    for i, j in zip(*np.nonzero(~np.isfinite(values)), strict=True):
        raise DataFormatError(path, f"{values[i, j]} is not a finite number", row=rows[int(i)][0], field=names[j])
    norms = np.linalg.norm(values[:, 4:], axis=1)
    for i in np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE):
        raise DataFormatError(path, f"quaternion {tuple(float(q) for q in values[i, 4:])} has norm {norms[i]:.6g}; "
                                    "expected a unit quaternion", row=rows[int(i)][0], field="qx/qy/qz/qw")
    for i in np.flatnonzero(np.abs(values[:, 0]) > MAX_TIME_S):
        raise DataFormatError(path, time_unit_problem(values[i, 0]), row=rows[int(i)][0], field="time")
    if np.any(np.diff(values[:, 0]) <= 0):
        k = int(np.flatnonzero(np.diff(values[:, 0]) <= 0)[0]) + 1
        raise DataFormatError(path, "times must increase", row=rows[k][0], field="time")
    return PoseTrack(values[:, 0], pose_matrix(values[:, 1:4], values[:, 4:] / norms[:, None]))


@dataclass(frozen=True)
class Transform:
    """One /tf or /tf_static entry: pose of `child` in `parent` at time_s."""

    time_s: float
    parent: str
    child: str
    pose: np.ndarray  # (4, 4)
    static: bool


def tf_track(transforms: list[Transform], parent: str, child: str, where: str) -> PoseTrack:
    """Pose of frame `child` in frame `parent` over time, composed along the tf tree (child up to
    parent; dynamic links interpolated at the union of their stamps, static links constant)."""
    links: dict[str, tuple[str, bool, list[Transform]]] = {}
    for tr in transforms:
        p, static, items = links.setdefault(tr.child, (tr.parent, tr.static, []))
        if p != tr.parent:
            raise DataFormatError(where, f"frame {tr.child!r} has two parents in tf ({p!r} and {tr.parent!r})")
        items.append(tr)
    frames = sorted(set(links) | {p for p, _, _ in links.values()})
    for flag, name in (("--tf-parent", parent), ("--tf-child", child)):
        if name not in frames:
            raise DataFormatError(where, f"{flag} {name!r}: frame not in tf; frames: {', '.join(frames) or 'none'}")
    chain, f = [], child
    while f != parent:
        if f not in links:
            raise DataFormatError(where, f"--tf-child {child!r} is not below --tf-parent {parent!r} in the tf tree")
        chain.append(links[f])
        f = links[f][0]
        if len(chain) > len(links):
            raise DataFormatError(where, "the tf tree has a cycle")
    tracks = []
    for _, static, items in chain:
        items = sorted(items, key=lambda x: x.time_s)
        t = np.array([x.time_s for x in items])
        keep = np.concatenate([[True], np.diff(t) > 0])
        tracks.append((static, PoseTrack(t[keep], np.stack([x.pose for x in items])[keep])))
    stamps = [tr.times_s for static, tr in tracks if not static]
    times = np.unique(np.concatenate(stamps)) if stamps else np.zeros(1)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    for static, tr in tracks:  # chain runs child -> parent: parent_T_child = ... @ link2 @ link1
        link = np.broadcast_to(tr.poses[-1], poses.shape) if static else tr.at(times, np.inf)[0]
        poses = link @ poses
    return PoseTrack(times, poses)
