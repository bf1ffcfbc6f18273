"""LiDAR poses for an imported bag: KISS-ICP odometry, a /tf chain, or a CSV/TUM trajectory.

All three give a `PoseTrack` of LiDAR-to-world poses; camera poses are the LiDAR pose
interpolated at the camera stamp times the camera-in-LiDAR mounting (docs/method.md 4).

KISS-ICP (Vizzo et al. 2023) ships outdoor defaults: max_range 100 m, from which its map voxel
is max_range / 100 = 1 m, too coarse for a room. `KissIcpSettings()` are indoor settings measured
on simulated office drives (README "Your own robot", benchmarks/bench_bag_odometry.py).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data.csvtable import MAX_TIME_S, time_unit_problem
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.geometry import QUATERNION_NORM_TOLERANCE, pose_matrix


@dataclass
class PoseTrack:
    """LiDAR-to-world poses at increasing times."""

    times_s: np.ndarray  # (K,) s
    poses: np.ndarray  # (K, 4, 4)

    def at(self, t_s: np.ndarray, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Poses (N, 4, 4) at times (N,): slerp/lerp between the neighbours; a time outside the
        track by more than `tolerance_s` (or any time when the track is empty) is invalid (N,) bool."""
        from scipy.spatial.transform import Rotation, Slerp

        t_s = np.asarray(t_s, dtype=np.float64)
        out = np.tile(np.eye(4), (len(t_s), 1, 1))
        if len(self.times_s) == 0:
            return out, np.zeros(len(t_s), dtype=bool)
        ok = (t_s >= self.times_s[0] - tolerance_s) & (t_s <= self.times_s[-1] + tolerance_s)
        if len(self.times_s) == 1:
            out[:] = self.poses[0]
            return out, ok
        tc = np.clip(t_s, self.times_s[0], self.times_s[-1])
        out[:, :3, :3] = Slerp(self.times_s, Rotation.from_matrix(self.poses[:, :3, :3]))(tc).as_matrix()
        for k in range(3):
            out[:, k, 3] = np.interp(tc, self.times_s, self.poses[:, k, 3])
        return out, ok


@dataclass(frozen=True)
class KissIcpSettings:
    """KISS-ICP parameters (metres). deskew needs per-point times, which the ETHZ-style filtered
    scans do not carry; refine_start_s re-registers the scans of the first seconds, taken while the
    constant-velocity prediction of KISS-ICP is still wrong, against the map of the next seconds.

    drop_floor_ceiling_m: registration ignores points within this distance of the floor and the
    ceiling (found in the first scan, `horizontal_planes`; 0 = keep all). A 16-beam LiDAR draws
    the floor as rings centred on itself that move with it; matched point to point they pull the
    estimate back towards standstill (measured: 8 cm lag after 2.5 s of a simulated start, 1 cm
    without the rings). Off by default: without the floor the 16 beams constrain pitch and roll
    poorly (20 s office: 1.6 deg median rotation error against 0.26 deg with it); the re-registration
    of the start (refine_start_s) removes most of the lag instead."""

    max_range_m: float = 30.0
    min_range_m: float = 0.3
    voxel_size_m: float = 0.2
    deskew: bool = False
    initial_threshold_m: float = 2.0
    min_motion_m: float = 0.1
    refine_start_s: float = 2.0
    refine_window_s: float = 3.0
    drop_floor_ceiling_m: float = 0.0


    @classmethod
    def library_defaults(cls) -> KissIcpSettings:
        """KISS-ICP 1.x's own (outdoor) defaults, for comparison."""
        return cls(max_range_m=100.0, min_range_m=0.0, voxel_size_m=1.0, deskew=True,
                   initial_threshold_m=2.0, min_motion_m=0.1, refine_start_s=0.0, drop_floor_ceiling_m=0.0)


def scale_motion(delta: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion `delta` (4, 4) stretched in time by `factor`: its rotation vector and its
    translation times `factor` (constant velocity over a longer or shorter interval)."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(delta[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = np.asarray(delta[:3, 3]) * factor
    return out


def horizontal_planes(points: np.ndarray, bin_m: float = 0.02, min_share: float = 0.03) -> tuple[float, float]:
    """Heights (m, sensor frame) of the floor below and the ceiling above the sensor: the densest
    2 cm height bin below -0.1 m and above +0.1 m holding at least `min_share` of the points
    (-inf / +inf where none does: outdoors, or a LiDAR that does not see the floor)."""
    z = np.asarray(points)[:, 2]
    out = []
    for part, none in ((z[z < -0.1], -np.inf), (z[z > 0.1], np.inf)):
        if len(part) == 0:
            out.append(none)
            continue
        k = np.floor(part / bin_m).astype(np.int64)
        vals, counts = np.unique(k, return_counts=True)
        best = int(np.argmax(counts))
        out.append(float((vals[best] + 0.5) * bin_m) if counts[best] >= min_share * len(z) else none)
    return out[0], out[1]


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

        self.icp, self.stretch = KissICP(_kiss_config(settings)), stretch
        self.last_t: float | None = None  # the last registered scan's time
        self.last_dt: float | None = None  # the interval icp.last_delta spans

    def register(self, t: float, points: np.ndarray) -> np.ndarray:
        """points (M, 3), sensor frame -> the scan's pose in the first scan's frame (4, 4)."""
        if self.stretch and self.last_dt:
            ratio = (t - self.last_t) / self.last_dt
            if abs(ratio - 1.0) > 0.01:
                self.icp.last_delta = scale_motion(self.icp.last_delta, ratio)
        self.icp.register_frame(np.asarray(points, dtype=np.float64), np.empty(0))
        self.last_t, self.last_dt = t, (None if self.last_t is None else t - self.last_t)
        return np.array(self.icp.last_pose, dtype=np.float64)


def kiss_icp_track(times_s: np.ndarray, load_scan: Callable[[int], np.ndarray],
                   settings: KissIcpSettings | None = None) -> PoseTrack:
    """Register the scans (k -> (M, 3) points, sensor frame, in time order) with KISS-ICP.

    The first scan's pose is the world frame (as in the ETHZ recordings)."""
    s = settings or KissIcpSettings()
    cfg = _kiss_config(s)
    if s.drop_floor_ceiling_m > 0 and len(times_s):
        floor, ceiling = horizontal_planes(load_scan(0))
        lo, hi = floor + s.drop_floor_ceiling_m, ceiling - s.drop_floor_ceiling_m
        raw_scan = load_scan

        def load_scan(k: int) -> np.ndarray:  # noqa: F811 - the same scans without the rings
            p = raw_scan(k)
            return p[(p[:, 2] > lo) & (p[:, 2] < hi)]
    registration = ScanRegistration(s)
    poses = np.empty((len(times_s), 4, 4))
    for k in range(len(times_s)):
        poses[k] = registration.register(float(times_s[k]), load_scan(k))
    track = PoseTrack(np.asarray(times_s, dtype=np.float64), poses)
    if s.refine_start_s > 0 and len(times_s) > 1:
        _refine_start(track, load_scan, cfg, s)
    return track


def _refine_start(track: PoseTrack, load_scan, cfg, s: KissIcpSettings) -> None:
    """Re-register the scans of the first refine_start_s seconds, newest first, against a map of
    the scans of the following refine_window_s seconds placed by their (settled) poses."""
    from kiss_icp.mapping import get_voxel_hash_map
    from kiss_icp.registration import get_registration
    from kiss_icp.voxelization import voxel_down_sample

    t0 = track.times_s[0]
    early = np.flatnonzero(track.times_s < t0 + s.refine_start_s)
    later = np.flatnonzero((track.times_s >= t0 + s.refine_start_s)
                           & (track.times_s < t0 + s.refine_start_s + s.refine_window_s))
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
        guess = reg.align_points_to_map(src, vmap, guess, 3 * sigma, sigma)
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
