"""Check the two cameras' relative orientation against their own image matches.

Two-camera depth is only as good as the cameras' relative pose: at the robot's 0.27 m baseline a
relative yaw error of 0.2 deg moves a point at 4.4 m by about 0.25 m. Translation errors of a few
millimetres matter far less, so only the rotation is checked: corners of camera a are followed
into the simultaneous image of camera b (KLT from the rotation-only prediction, forward-backward
checked, without the epipolar gate the stereo tracker applies), and the small rotation of camera
b (about its own axes) that puts the matches closest to their epipolar lines (known baseline,
robust Huber loss) is estimated. A correction near zero means the poses agree with the images.

What the matches can tell: with the two cameras side by side, the epipolar lines run nearly
along the baseline, so a rotation about the cameras' vertical axis (yaw, y in OpenCV axes) moves
a match mostly along its line and is barely observable, although it is the rotation that biases
two-camera depth (a disparity offset). Pitch and roll move matches across their lines and are
well determined. `RotationCheck.std_deg` gives each axis's standard deviation from the fit, so a
caller can tell a measured correction from an unobservable one; a yaw error needs a metric
reference (motion parallax while driving, or the infrared zones).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from virus_nerf.stereo.tracking import TrackerConfig, epipolar_distance, fundamental, track_points


@dataclass(frozen=True)
class PairMatches:
    """Matched pixels of one simultaneous image pair (a: uv_a (N, 2), b: uv_b (N, 2)), with the
    cameras' intrinsic matrices and cam_to_world poses (4, 4) as recorded."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    k_a: np.ndarray
    k_b: np.ndarray
    pose_a: np.ndarray
    pose_b: np.ndarray


@dataclass(frozen=True)
class RotationCheck:
    """The rotation of camera b, about its own x, y, z axes (OpenCV: x right, y down, z forward;
    degrees), that best explains the matches, and the median epipolar distance (px) before and
    after applying it."""

    pairs: int
    matches: int
    correction_deg: tuple[float, float, float]
    std_deg: tuple[float, float, float]  # per axis, from the fit's Jacobian and its robust residual
    median_px_before: float
    median_px_after: float


def rotate_camera(pose: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """cam_to_world (4, 4) turned by the rotation vector `rotvec` (rad) about its own axes."""
    from scipy.spatial.transform import Rotation

    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ Rotation.from_rotvec(rotvec).as_matrix()
    return out


def match_pair(gray_a: np.ndarray, gray_b: np.ndarray, k_a: np.ndarray, k_b: np.ndarray, pose_a: np.ndarray,
               pose_b: np.ndarray, cfg: TrackerConfig | None = None, gate_px: float = 15.0) -> PairMatches:
    """Corners of image a followed into image b; matches further than `gate_px` from their
    epipolar line (gross mismatches, not pose error) are dropped."""
    import cv2

    cfg = cfg or TrackerConfig()
    corners = cv2.goodFeaturesToTrack(gray_a, cfg.max_corners, cfg.quality, cfg.min_distance)
    uv_a = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2).astype(np.float64)
    wide = dataclasses.replace(cfg, epipolar_max_px=gate_px)
    uv_b, ok = track_points(gray_a, gray_b, uv_a, k_a, k_b, pose_a, pose_b, wide)
    return PairMatches(uv_a[ok], uv_b[ok], k_a, k_b, np.asarray(pose_a, float), np.asarray(pose_b, float))


def _distances(pairs: list[PairMatches], rotvec: np.ndarray) -> np.ndarray:
    out = []
    for p in pairs:
        f = fundamental(p.k_a, p.k_b, p.pose_a, rotate_camera(p.pose_b, rotvec))
        if f is not None and len(p.uv_a):
            # signed distance: the sign tells the optimiser which side of the line
            xa = np.concatenate([p.uv_a, np.ones((len(p.uv_a), 1))], axis=1)
            lines = xa @ f.T
            xb = np.concatenate([p.uv_b, np.ones((len(p.uv_b), 1))], axis=1)
            out.append(np.einsum("ni,ni->n", lines, xb) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12))
    return np.concatenate(out) if out else np.zeros(0)


def check_rotation(pairs: list[PairMatches], huber_px: float = 1.0) -> RotationCheck:
    """The small rotation of camera b that minimises the matches' epipolar distances."""
    from scipy.optimize import least_squares

    n = sum(len(p.uv_a) for p in pairs)
    if n < 8:
        raise ValueError(f"{n} matches: expected at least 8 to check the cameras' relative rotation")
    fit = least_squares(lambda r: _distances(pairs, r), np.zeros(3), loss="huber", f_scale=huber_px,
                        x_scale=1e-3, xtol=1e-12)
    before = np.concatenate([epipolar_distance(fundamental(p.k_a, p.k_b, p.pose_a, p.pose_b), p.uv_a, p.uv_b)
                             for p in pairs if len(p.uv_a)])
    after = np.abs(_distances(pairs, fit.x))
    sigma = 1.4826 * float(np.median(after))  # robust residual scale, px
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * sigma**2
    return RotationCheck(pairs=len(pairs), matches=n, correction_deg=tuple(float(v) for v in np.degrees(fit.x)),
                         std_deg=tuple(float(v) for v in np.degrees(np.sqrt(np.maximum(np.diag(cov), 0.0)))),
                         median_px_before=float(np.median(before)), median_px_after=float(np.median(after)))


def check_recording(recording, max_pairs: int = 20, max_dt: float = 0.1, cfg: TrackerConfig | None = None,
                    stacks: tuple[int, int] = (1, 3)) -> RotationCheck:
    """The check on up to `max_pairs` simultaneous (within `max_dt` s) image pairs of a recording's
    two stacks, evenly spread over the drive."""
    import cv2

    a, b = recording.stacks[stacks[0]], recording.stacks[stacks[1]]
    j = np.searchsorted(b.times, a.times).clip(1, len(b.times) - 1)
    j = np.where(np.abs(b.times[j - 1] - a.times) < np.abs(b.times[j] - a.times), j - 1, j)
    good = np.flatnonzero(np.abs(b.times[j] - a.times) <= max_dt)
    if not len(good):
        raise ValueError(f"no image pairs of stacks {stacks} within {max_dt} s of each other")
    pick = good[np.unique(np.linspace(0, len(good) - 1, min(max_pairs, len(good))).round().astype(int))]
    pairs = []
    for i in pick:
        gray_a = cv2.cvtColor(np.ascontiguousarray(a.image(int(i))), cv2.COLOR_RGB2GRAY)
        gray_b = cv2.cvtColor(np.ascontiguousarray(b.image(int(j[i]))), cv2.COLOR_RGB2GRAY)
        pairs.append(match_pair(gray_a, gray_b, a.intrinsics.matrix, b.intrinsics.matrix, a.cam_to_world[i],
                                b.cam_to_world[j[i]], cfg))
    return check_rotation(pairs)
