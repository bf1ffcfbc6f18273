"""Feature tracks from images with known poses: KLT across time in one camera, and between cameras.

OpenCV's pyramidal Lucas-Kanade tracker follows corners (Shi-Tomasi) from frame to frame. Known
poses do two things a pose-free tracker cannot: each corner's search starts where a point at
infinity would land (the rotation-only homography K R_b^T R_a K^-1, so turning in place or the
two cameras' 29 deg toe-out costs no search range), and a match must lie within
`epipolar_max_px` of its epipolar line. A forward-backward check (track back and land within
`fb_max_px` of the start) drops drifting tracks. Frames are fed one at a time in time order,
offline and while driving alike.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from virus_nerf.checks import Checks
from virus_nerf.sensors.camera import Intrinsics


def _cv2():
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - the dependency is declared
        raise ImportError("the stereo sensor needs OpenCV: pip install opencv-python-headless") from exc
    return cv2


def rotation_homography(k_a: np.ndarray, k_b: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """3x3 homography mapping pixels of camera a to camera b for points at infinity
    (poses cam_to_world (4, 4), OpenCV axes)."""
    rel = pose_b[:3, :3].T @ pose_a[:3, :3]  # a's camera frame -> b's
    return k_b @ rel @ np.linalg.inv(k_a)


def fundamental(k_a: np.ndarray, k_b: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray | None:
    """F with x_b^T F x_a = 0 for pixels of cameras a and b; None when the centres coincide
    (below 1 mm apart: no epipolar geometry)."""
    rel = np.linalg.inv(pose_b) @ pose_a  # a's camera frame -> b's
    r, t = rel[:3, :3], rel[:3, 3]
    if np.linalg.norm(t) < 1e-3:
        return None
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(k_b).T @ tx @ r @ np.linalg.inv(k_a)


def epipolar_distance(f: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(N,) px distance of each uv_b (N, 2) from the epipolar line of uv_a (N, 2) in image b."""
    xa = np.concatenate([uv_a, np.ones((len(uv_a), 1))], axis=1)
    lines = xa @ f.T  # (N, 3) lines in image b
    xb = np.concatenate([uv_b, np.ones((len(uv_b), 1))], axis=1)
    return np.abs(np.einsum("ni,ni->n", lines, xb)) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)


# the narrowest window the angle may give: fewer pixels average less of the images' noise in LK's
# gradient sums, and 7 px is the narrowest measured (D78: on the simulator's 320 x 240 images; a
# 160 x 120 image would get 3 px from the angle)
MIN_WINDOW_PX = 7


@dataclass(frozen=True)
class TrackerConfig:
    """Corner detection and KLT settings (pixels at the recording's resolution)."""

    max_corners: int = 800  # per image
    quality: float = 0.001  # Shi-Tomasi quality level (share of the image's strongest corner)
    min_distance: float = 4.0  # px between corners
    # LK window side as an angle, the same part of the view at any image size: 15 px on the ETHZ
    # recordings' 640 x 480 images (fx 388 px), 7 px on the simulator's 320 x 240 ones. A window
    # across a depth edge follows the foreground and the background at once, and its track
    # triangulates a point between them (docs/decisions.md D78)
    window_deg: float = 2.2
    window: int | None = None  # LK window side in px instead (a run saved before D78: 15)
    levels: int = 3  # LK pyramid levels
    fb_max_px: float = 0.5  # forward-backward error bound
    epipolar_max_px: float = 1.0  # distance from the epipolar line

    def __post_init__(self) -> None:
        check = Checks(self, "stereo.tracker.")
        check.number("window_deg", 0.0)
        check.integer("window", 3, optional=True)

    def window_px(self, fx: float) -> int:
        """The LK window side in pixels of an image with focal length `fx` px: `window` when set,
        else `window_deg` rounded to the nearest odd number of pixels, at least MIN_WINDOW_PX."""
        if self.window is not None:
            return self.window
        return max(MIN_WINDOW_PX, 2 * round((math.radians(self.window_deg) * fx - 1.0) / 2.0) + 1)


@dataclass
class Views:
    """Observations of tracks: view i saw track `track[i]` in frame `frame[i]` at pixel uv[i]."""

    track: list[np.ndarray] = field(default_factory=list)
    frame: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)

    def add(self, track: np.ndarray, frame: int | np.ndarray, uv: np.ndarray) -> None:
        """Views of tracks `track` (N,) in one frame (an int) or in frames (N,), at uv (N, 2)."""
        self.track.append(np.asarray(track, dtype=np.int64))
        self.frame.append(np.broadcast_to(np.asarray(frame, dtype=np.int64), (len(track),)).copy())
        self.uv.append(np.asarray(uv, dtype=np.float64).reshape(-1, 2))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(track (V,), frame (V,), uv (V, 2)) of every view so far."""
        if not self.track:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
        return np.concatenate(self.track), np.concatenate(self.frame), np.concatenate(self.uv)


def track_points(gray_a: np.ndarray, gray_b: np.ndarray, uv_a: np.ndarray, k_a: np.ndarray, k_b: np.ndarray,
                 pose_a: np.ndarray, pose_b: np.ndarray, cfg: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Follow pixels uv_a (N, 2) of image a into image b: (uv_b (N, 2), ok (N,) bool), checked
    forward-backward and against the epipolar line."""
    cv2 = _cv2()
    n = len(uv_a)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    h = rotation_homography(k_a, k_b, pose_a, pose_b)
    start = cv2.perspectiveTransform(uv_a.reshape(-1, 1, 2).astype(np.float32), h).reshape(-1, 2)
    side = cfg.window_px(float(k_a[0, 0]))
    lk = dict(winSize=(side, side), maxLevel=cfg.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p0 = uv_a.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, p0, start.reshape(-1, 1, 2).copy(),
                                          flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(gray_b, gray_a, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    uv_b = p1.reshape(-1, 2).astype(np.float64)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1)
    ok &= np.linalg.norm(back.reshape(-1, 2) - uv_a, axis=1) < cfg.fb_max_px
    hb, wb = gray_b.shape
    ok &= (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= wb - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= hb - 1)
    f = fundamental(k_a, k_b, pose_a, pose_b)
    if f is not None:
        ok &= epipolar_distance(f, uv_a, uv_b) < cfg.epipolar_max_px
    return uv_b, ok


@functools.lru_cache(maxsize=8)
def _disk(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(dy, dx) pixel offsets of OpenCV's filled circle of `radius` px around an integer centre."""
    cv2 = _cv2()
    canvas = np.zeros((2 * radius + 3, 2 * radius + 3), dtype=np.uint8)
    cv2.circle(canvas, (radius + 1, radius + 1), radius, 255, -1)
    dy, dx = np.nonzero(canvas)
    return dy - (radius + 1), dx - (radius + 1)


def corner_mask(shape: tuple[int, int], uv: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) uint8: 255, and 0 within `radius` px of the pixels uv (N, 2) (rounded): where new
    corners may not start. The same pixels as a filled cv2.circle at each point, in one pass
    (a drive's frames have ~600 tracks each)."""
    mask = np.full(shape, 255, dtype=np.uint8)
    if len(uv) == 0:
        return mask
    dy, dx = _disk(int(radius))
    centres = np.round(np.asarray(uv, dtype=np.float64)).astype(np.int64)  # (N, 2) u, v
    rows = (centres[:, 1, None] + dy[None, :]).ravel()
    cols = (centres[:, 0, None] + dx[None, :]).ravel()
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    mask[rows[inside], cols[inside]] = 0
    return mask


class StackTracker:
    """Tracks corners through one camera's frames, fed in time order (`add`)."""

    def __init__(self, intrinsics: Intrinsics, cfg: TrackerConfig, views: Views, next_id: list[int]):
        self.k = intrinsics.matrix
        self.cfg = cfg
        self.views = views
        self._next_id = next_id  # shared counter: track ids are unique across trackers
        self.last_gray: np.ndarray | None = None  # the newest frame (cross-camera matching reads it)
        self.last_pose: np.ndarray | None = None
        self.active_ids = np.zeros(0, dtype=np.int64)  # tracks seen in the last frame
        self.active_uv = np.zeros((0, 2))

    def add(self, frame: int, gray: np.ndarray, cam_to_world: np.ndarray) -> None:
        """Continue the active tracks into this frame and start new ones where none are."""
        cv2 = _cv2()
        if self.last_gray is not None and len(self.active_ids):
            uv, ok = track_points(self.last_gray, gray, self.active_uv, self.k, self.k, self.last_pose, cam_to_world, self.cfg)
            self.active_ids, self.active_uv = self.active_ids[ok], uv[ok]
            self.views.add(self.active_ids, frame, self.active_uv)
        room = self.cfg.max_corners - len(self.active_ids)
        if room > 0:
            mask = corner_mask(gray.shape, self.active_uv, int(self.cfg.min_distance))
            corners = cv2.goodFeaturesToTrack(gray, room, self.cfg.quality, self.cfg.min_distance, mask=mask)
            if corners is not None:
                uv = corners.reshape(-1, 2).astype(np.float64)
                ids = np.arange(self._next_id[0], self._next_id[0] + len(uv))
                self._next_id[0] += len(uv)
                self.views.add(ids, frame, uv)
                self.active_ids = np.concatenate([self.active_ids, ids])
                self.active_uv = np.concatenate([self.active_uv, uv])
        self.last_gray, self.last_pose = gray, np.asarray(cam_to_world, dtype=np.float64)
