"""Sparse camera depth: triangulated tracks turned into depth targets on training pixels.

The pipeline, frame by frame in time order (`StereoBuilder.add`), then once (`result`):
1. track corners through each camera (tracking.StackTracker);
2. follow every active track into the other camera's frame taken within `pair_max_dt`;
3. triangulate each track with at least `min_views` views from the known poses, drop views that
   reproject further than `max_reproj_px`, and triangulate again;
4. keep points with a parallax of `min_parallax_deg`, a range in [min_range, max_range] and a
   range uncertainty below `max_rel_sigma` of the range;
5. every view of a kept point becomes a depth target along the ray through the pixel it was
   tracked at: the distance from that camera to the point, and its standard deviation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from virus_nerf.checks import Checks
from virus_nerf.sensors.camera import Intrinsics, scaled_pixels
from virus_nerf.stereo import triangulation as tri
from virus_nerf.stereo.tracking import StackTracker, TrackerConfig, Views, track_points


@dataclass(frozen=True)
class StereoConfig:
    """Camera depth from tracks: tracking, triangulation and filters (metres, pixels of the
    recording's images)."""

    tracker: TrackerConfig = TrackerConfig()
    pair_max_dt: float = 0.1  # s: two cameras' frames closer than this are matched
    min_views: int = 4  # views per track (frames it was seen in); small_room_min_views where it applies
    sigma_px: float = 0.5  # pixel noise behind each point's covariance
    max_reproj_px: float = 0.5  # a view further than this from its point's projection is dropped
    min_parallax_deg: float = 1.0  # largest angle between a point's viewing rays
    min_range: float = 0.3  # m from the camera
    max_range: float = 12.0  # m from the camera
    max_rel_sigma: float = 0.03  # range standard deviation / range; small_room_max_rel_sigma where it applies
    # offline in a fitted room small enough for the stereo targets' line-of-sight term
    # (weights.free_stereo_room_m, engine/step_loss.stereo_line_of_sight) these two filters instead
    # (`small_room_config`): 29 % more points (office 84), and the term empties more of the density sheets
    # the colour leaves beside the path (offices 81-86: free recall 89.31 -> 90.12 %, fewer
    # obstacles marked free; docs/decisions.md D112); the larger rooms and every drive keep the above
    small_room_min_views: int = 3
    small_room_max_rel_sigma: float = 0.05
    # while driving (frames added one by one), the tracks that ended become targets every this
    # many frames (10: about one second of two cameras at 4.8 Hz)
    refresh_frames: int = 10

    def __post_init__(self) -> None:
        check = Checks(self, "stereo.")
        check.number("pair_max_dt", 0.0, lo_open=False)
        check.integer("min_views", 2)
        check.number("sigma_px", 0.0)
        check.number("max_reproj_px", 0.0)
        check.number("min_parallax_deg", 0.0, lo_open=False)
        check.number("min_range", 0.0, lo_open=False)
        check.number("max_range", self.min_range)
        check.number("max_rel_sigma", 0.0)
        check.integer("small_room_min_views", 2)
        check.number("small_room_max_rel_sigma", 0.0)
        check.integer("refresh_frames", 1)


def small_room_config(cfg: StereoConfig) -> StereoConfig:
    """`cfg` with the small room's filters (`small_room_min_views`, `small_room_max_rel_sigma`) as
    its `min_views` and `max_rel_sigma`: the stereo pass of an offline run in a fitted room where
    the line-of-sight term trains (trainer/loop.py)."""
    return dataclasses.replace(cfg, min_views=cfg.small_room_min_views, max_rel_sigma=cfg.small_room_max_rel_sigma)


@dataclass
class StereoDepth:
    """Depth targets along the exact rays of tracked pixels, sorted by frame row.

    Each target is a view of a triangulated point: the pixel it was tracked at (sub-pixel, in
    the training image's pixel coordinates) and the distance from that frame's camera centre to
    the point along the pixel's ray, with its standard deviation.
    """

    frames: np.ndarray  # (M,) int64 frame rows, ascending
    uv: np.ndarray  # (M, 2) float32 pixel coordinates (u column, v row) at training resolution
    ranges: np.ndarray  # (M,) float32 m along the ray through uv
    sigmas: np.ndarray  # (M,) float32 m, standard deviation of the range
    points: np.ndarray  # (N, 3) float32 world points behind them

    @staticmethod
    def empty() -> StereoDepth:
        return StereoDepth(np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                           np.zeros(0, np.float32), np.zeros((0, 3), np.float32))

    def __len__(self) -> int:
        return len(self.frames)

    def frame_slices(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(start, count) (N,) of each frame row's targets in the arrays."""
        frames = np.asarray(frames, np.int64)
        lo = np.searchsorted(self.frames, frames, side="left")
        hi = np.searchsorted(self.frames, frames, side="right")
        return lo, hi - lo


def whole_tracks(track: np.ndarray, view_ok: np.ndarray, n_tracks: int) -> np.ndarray:
    """(V,) bool: the views whose track passed in every view (track (V,) ids < n_tracks, view_ok
    (V,) bool). A point is kept whole or not at all: a view that failed the range or sigma test
    says the point is doubtful for its other views too."""
    failed = np.bincount(track, weights=~np.asarray(view_ok, dtype=bool), minlength=n_tracks)  # (n_tracks,)
    return (failed == 0)[track]


def _extend(old: StereoDepth, new: StereoDepth) -> StereoDepth:
    """`old`'s targets with `new`'s, sorted by frame; with equal frames `old`'s come first and each
    keeps its order (a stable sort of the two joined). Merged by insertion, so a long drive's
    millions of targets are held twice at a flush, not four times (joined, then sorted, D63)."""
    if not len(new):
        return StereoDepth(old.frames, old.uv, old.ranges, old.sigmas, np.concatenate([old.points, new.points]))
    order = np.argsort(new.frames, kind="stable")
    at = np.searchsorted(old.frames, new.frames[order], side="right")  # (K,) after old's equal frames
    return StereoDepth(frames=np.insert(old.frames, at, new.frames[order]),
                       uv=np.insert(old.uv, at, new.uv[order], axis=0),
                       ranges=np.insert(old.ranges, at, new.ranges[order]),
                       sigmas=np.insert(old.sigmas, at, new.sigmas[order]),
                       points=np.concatenate([old.points, new.points]))


class StereoFeed:
    """A StereoBuilder fed frame by frame while driving: every `refresh_frames` frames, the
    targets of the tracks that ended so far (None between refreshes)."""

    def __init__(self, intrinsics: dict[int, Intrinsics], train_intrinsics: dict[int, Intrinsics],
                 cfg: StereoConfig):
        self.builder = StereoBuilder(intrinsics, train_intrinsics, cfg)
        self.frames = 0

    def add(self, frame: int, stack: int, time: float, cam_to_world: np.ndarray, rgb: np.ndarray) -> StereoDepth | None:
        self.builder.add(frame, stack, time, cam_to_world, rgb)
        self.frames += 1
        return self.builder.flush() if self.frames % self.builder.cfg.refresh_frames == 0 else None


class StereoBuilder:
    """Feeds frames in time order into per-camera trackers and cross-camera matching."""

    def __init__(self, intrinsics: dict[int, Intrinsics], train_intrinsics: dict[int, Intrinsics],
                 cfg: StereoConfig = StereoConfig()):
        self.cfg = cfg
        self.intrinsics = dict(intrinsics)
        self.train_intrinsics = dict(train_intrinsics)
        self.views = Views()
        self._next_id = [0]
        self.trackers = {s: StackTracker(intr, cfg.tracker, self.views, self._next_id) for s, intr in intrinsics.items()}
        self._last: dict[int, tuple[int, float]] = {}  # stack -> (frame row, time) of its newest frame
        self.frame_stack: dict[int, int] = {}
        self.frame_pose: dict[int, np.ndarray] = {}
        # targets of the tracks triangulated so far, sorted by frame: one copy, extended by each
        # flush (a list of parts merged anew at every flush held the drive's targets twice)
        self._targets = StereoDepth.empty()

    def add_stack(self, stack: int, intrinsics: Intrinsics, train_intrinsics: Intrinsics) -> None:
        """A camera that joined after the first frames (Mapper.add_stack): tracked from its first frame."""
        self.intrinsics[stack], self.train_intrinsics[stack] = intrinsics, train_intrinsics
        self.trackers[stack] = StackTracker(intrinsics, self.cfg.tracker, self.views, self._next_id)

    def add(self, frame: int, stack: int, time: float, cam_to_world: np.ndarray, rgb: np.ndarray) -> None:
        """One frame (store row `frame`, full-resolution RGB uint8) of camera `stack`."""
        import cv2

        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        pose = np.asarray(cam_to_world, dtype=np.float64)
        self.frame_stack[frame], self.frame_pose[frame] = stack, pose
        tracker = self.trackers[stack]
        tracker.add(frame, gray, pose)
        for other, (other_frame, other_time) in self._last.items():
            if other == stack or abs(other_time - time) > self.cfg.pair_max_dt:
                continue
            peer = self.trackers[other]
            if peer.last_gray is None:
                continue
            for src, dst, dst_frame in ((tracker, peer, other_frame), (peer, tracker, frame)):
                uv, ok = track_points(src.last_gray, dst.last_gray, src.active_uv, src.k, dst.k, src.last_pose, dst.last_pose,
                                      self.cfg.tracker)
                self.views.add(src.active_ids[ok], dst_frame, uv[ok])
        self._last[stack] = (frame, time)

    def flush(self) -> StereoDepth:
        """The targets of every track that has ended so far (no tracker follows it any more):
        those tracks are triangulated now, once, and their views dropped; tracks still followed
        wait for a later call. Returns all targets so far, sorted by frame."""
        track, frame, uv = self.views.arrays()
        open_ids = np.concatenate([t.active_ids for t in self.trackers.values()])
        still_open = np.isin(track, open_ids)
        self.views = Views()
        self.views.add(track[still_open], frame[still_open], uv[still_open])
        for t in self.trackers.values():
            t.views = self.views
        done = ~still_open
        if done.any():
            self._targets = _extend(self._targets, self._triangulate(track[done], frame[done], uv[done]))
        return self._targets

    def result(self) -> StereoDepth:
        """Triangulate every track, followed or not (the end of a recording)."""
        for t in self.trackers.values():
            t.active_ids, t.active_uv = np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        return self.flush()

    def _triangulate(self, track: np.ndarray, frame: np.ndarray, uv: np.ndarray) -> StereoDepth:
        """Targets of the tracks among these views (track (V,), frame (V,), uv (V, 2) px)."""
        if len(track) == 0:
            return StereoDepth.empty()
        # tracks with enough views, renumbered 0..T-1
        counts = np.bincount(track)
        keep = counts[track] >= self.cfg.min_views
        track, frame, uv = track[keep], frame[keep], uv[keep]
        if len(track) == 0:
            return StereoDepth.empty()
        ids, track = np.unique(track, return_inverse=True)
        n_tracks = len(ids)
        # each frame's pose, camera and inverse once, then gathered per view (a drive's flush has
        # ~10^5 views over ~10^2 frames)
        rows, at = np.unique(frame, return_inverse=True)  # (F,), (V,) the views' frames
        row_poses = np.stack([self.frame_pose[int(f)] for f in rows])  # (F, 4, 4)
        row_stacks = np.array([self.frame_stack[int(f)] for f in rows])  # (F,)
        poses, stacks = row_poses[at], row_stacks[at]  # (V, 4, 4), (V,)
        k = np.stack([self.intrinsics[int(s)].matrix for s in row_stacks])[at]  # (V, 3, 3)
        world_to_cam = np.linalg.inv(row_poses)[at]
        centres = poses[:, :3, 3]
        d_cam = np.stack([(uv[:, 0] - k[:, 0, 2]) / k[:, 0, 0], (uv[:, 1] - k[:, 1, 2]) / k[:, 1, 1],
                          np.ones(len(uv))], axis=1)
        rays = np.einsum("vij,vj->vi", poses[:, :3, :3], d_cam / np.linalg.norm(d_cam, axis=1, keepdims=True))
        points = tri.midpoint(track, centres, rays, n_tracks)
        for _ in range(2):  # drop views far from the point, then triangulate again
            proj, p_cam = tri.project_views(points[track], world_to_cam, k)
            err = np.linalg.norm(proj - uv, axis=1)
            good = np.isfinite(err) & (err < self.cfg.max_reproj_px) & (p_cam[:, 2] > 0)
            n_good = np.bincount(track[good], minlength=n_tracks)
            good &= n_good[track] >= self.cfg.min_views
            track_g, centres_g, rays_g = track[good], centres[good], rays[good]
            points = tri.midpoint(track_g, centres_g, rays_g, n_tracks)
            points[n_good < self.cfg.min_views] = np.nan
        view_ok = good & np.isfinite(points[track]).all(axis=1)
        track, frame, uv, poses, world_to_cam, k, centres, stacks = (
            a[view_ok] for a in (track, frame, uv, poses, world_to_cam, k, centres, stacks))
        if len(track) == 0:
            return StereoDepth.empty()
        cov = tri.covariance(track, points, world_to_cam, k, self.cfg.sigma_px, n_tracks)
        parallax = tri.max_parallax_deg(track, points, centres, n_tracks)
        offset = points[track] - centres  # (V, 3)
        dist = np.linalg.norm(offset, axis=1)
        u_dir = offset / dist[:, None]
        with np.errstate(invalid="ignore"):
            sigma = np.sqrt(np.einsum("vi,vij,vj->v", u_dir, cov[track], u_dir))
        ok = (parallax[track] >= self.cfg.min_parallax_deg) & (dist >= self.cfg.min_range) & \
             (dist <= self.cfg.max_range) & np.isfinite(sigma) & (sigma <= self.cfg.max_rel_sigma * dist)
        ok = whole_tracks(track, ok, n_tracks)
        track, frame, uv, stacks, sigma, dist = (a[ok] for a in (track, frame, uv, stacks, sigma, dist))
        # each view -> a target along its own ray, in the training image's pixel coordinates
        cams, cam_of = np.unique(stacks, return_inverse=True)
        scale = np.array([self.train_intrinsics[int(c)].width / self.intrinsics[int(c)].width for c in cams])[cam_of]
        uv_train = scaled_pixels(uv, scale[:, None])
        order = np.argsort(frame, kind="stable")
        used = np.unique(track)
        return StereoDepth(frames=frame[order], uv=uv_train[order].astype(np.float32),
                           ranges=dist[order].astype(np.float32), sigmas=sigma[order].astype(np.float32),
                           points=points[used].astype(np.float32))
