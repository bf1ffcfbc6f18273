"""Nearest-timestamp matching of sensor streams to the colour frames (docs/method.md 4: row i of
every file of a stack is one sample), with a count of what was dropped and why."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def match_nearest(anchor_s: np.ndarray, times_s: np.ndarray, tolerance_s: float) -> np.ndarray:
    """For each anchor time (N,), the index into `times_s` (M,, any order) of the nearest stamp,
    or -1 where none lies within `tolerance_s` (ties go to the earlier stamp)."""
    anchor_s = np.asarray(anchor_s, dtype=np.float64)
    out = np.full(len(anchor_s), -1, dtype=np.int64)
    if len(times_s) == 0 or len(anchor_s) == 0:
        return out
    order = np.argsort(times_s, kind="stable")
    t = np.asarray(times_s, dtype=np.float64)[order]
    j = np.searchsorted(t, anchor_s)
    lo = np.clip(j - 1, 0, len(t) - 1)
    hi = np.clip(j, 0, len(t) - 1)
    pick = np.where(np.abs(t[hi] - anchor_s) < np.abs(anchor_s - t[lo]), hi, lo)
    ok = np.abs(t[pick] - anchor_s) <= tolerance_s
    out[ok] = order[pick[ok]]
    return out


def thin_to_rate(times_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """(N,) bool: keep frames at least 1 / rate_hz apart, greedily from the first (rate 0 = all)."""
    keep = np.ones(len(times_s), dtype=bool)
    if rate_hz <= 0 or len(times_s) == 0:
        return keep
    period = 1.0 / rate_hz
    last = -np.inf
    for i, t in enumerate(times_s):
        if t - last >= period - 1e-6:
            last = t
        else:
            keep[i] = False
    return keep


@dataclass
class TopicReport:
    """What became of one topic's messages: `used` went into at least one sample."""

    topic: str
    role: str  # color, depth, camera_info, uss, tof, lidar, tf
    stack: int | None
    messages: int
    used: int
    first_s: float | None = None
    last_s: float | None = None

    @property
    def dropped(self) -> int:
        return self.messages - self.used


@dataclass
class StackMatch:
    """The samples of one stack: colour frame k -> partner message indices (-1 = sensor absent)."""

    stack: int
    color_index: np.ndarray  # (N,) index of the colour message of sample i
    times_s: np.ndarray  # (N,) colour stamps = the sample times
    partner: dict[str, np.ndarray]  # role -> (N,) message index
    dropped_frames: dict[str, int] = field(default_factory=dict)  # reason -> colour frames


def match_stack(stack: int, color_s: np.ndarray, streams: dict[str, tuple[np.ndarray, float]],
                pose_ok: np.ndarray, rate_hz: float) -> StackMatch:
    """Keep the colour frames (thinned to `rate_hz`) that have every stream within its tolerance
    and a pose; of frames with one stamp (a driver that publishes a frame twice) the first in the
    bag. streams: role -> (stamps (M,), tolerance s). Reasons count the first missing partner."""
    order = np.argsort(color_s, kind="stable")
    sorted_s = np.asarray(color_s, dtype=np.float64)[order]
    repeated = np.r_[False, np.diff(sorted_s) == 0]  # (N,) in time order: a stamp kept already
    keep = np.zeros(len(color_s), dtype=bool)
    keep[order] = ~repeated
    dropped = {"repeated stamp": int(repeated.sum())}
    thinned = keep.copy()
    thinned[order[~repeated]] = thin_to_rate(sorted_s[~repeated], rate_hz)
    dropped["thinned to camera_rate_hz"] = int((keep & ~thinned).sum())
    keep = thinned
    partner = {}
    for role, (times, tol) in streams.items():
        idx = match_nearest(color_s, times, tol)
        lost = keep & (idx < 0)
        dropped[f"no {role} within {tol:g} s"] = int(lost.sum())
        keep &= idx >= 0
        partner[role] = idx
    lost = keep & ~pose_ok
    dropped["no pose"] = int(lost.sum())
    keep &= pose_ok
    sel = order[keep[order]]  # kept frames in time order
    return StackMatch(stack=stack, color_index=sel, times_s=np.asarray(color_s, dtype=np.float64)[sel],
                      partner={r: v[sel] for r, v in partner.items()},
                      dropped_frames={k: v for k, v in dropped.items() if v})
