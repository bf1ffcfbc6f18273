"""Test points of the evaluation (docs/method.md 6.1): the test frames of stack 1 and the stack-3 frame
taken at (nearly) the same time. One test point = one scan origin shared by every scan.

"The same time" is within `SYNC_TOLERANCE_S` (0.15 s): a stack-3 frame or LiDAR scan farther
from the test point's time was taken elsewhere, so the test point goes without it (stack 1's
sensors alone; no LiDAR scan), and `pairing_warnings` says how many did."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.data.bags.sync import match_nearest
from virus_nerf.data.ethz import SYNC_TOLERANCE_S, Recording
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.rig import MAIN_STACK

PARTNER_STACK = 3


@dataclass(frozen=True, eq=False)
class TestPoint:
    """Where and when a 2D scan is taken; the scan origin is the camera-1 position (docs/method.md 9.9)."""

    __test__ = False  # not a pytest test class

    index1: int  # frame index in stack 1
    index3: int | None  # synchronous frame index in stack 3 (None: no stack 3, or none within SYNC_TOLERANCE_S)
    time: float  # s, stack-1 camera timestamp
    time3: float | None  # s, stack-3 camera timestamp
    pose1: np.ndarray  # (4, 4) camera-1 to world
    pose3: np.ndarray | None  # (4, 4) camera-3 to world

    @property
    def origin(self) -> np.ndarray:
        """(3,) scan origin in the world frame, metres (camera-1 position)."""
        return self.pose1[:3, 3].copy()

    @property
    def origin_xy(self) -> np.ndarray:
        """(2,) scan origin in the horizontal plane."""
        return self.pose1[:2, 3].copy()

    @property
    def height(self) -> float:
        """Camera-1 height z (m), the height of the 2D slice."""
        return float(self.pose1[2, 3])

    def camera_poses(self) -> dict[int, tuple[int, np.ndarray]]:
        """Stack id -> (frame index, camera-to-world pose) for the stacks present."""
        out = {MAIN_STACK: (self.index1, self.pose1)}
        if self.index3 is not None and self.pose3 is not None:
            out[PARTNER_STACK] = (self.index3, self.pose3)
        return out


def synchronous_index(times: np.ndarray, t: float, tolerance_s: float = SYNC_TOLERANCE_S) -> int | None:
    """Index of the entry of `times` nearest to t if it lies within `tolerance_s`, else None: the
    importer's pairing rule (data/bags/sync.match_nearest; a tie goes to the earlier stamp)."""
    k = int(match_nearest(np.array([t]), times, tolerance_s)[0])
    return None if k < 0 else k


def lidar_scan_index(recording: Recording, t: float) -> int | None:
    """The LiDAR scan taken at time t (s): the nearest within SYNC_TOLERANCE_S, else None."""
    return synchronous_index(recording.lidar_times, t)


def make_test_points(recording: Recording, split: str = "test") -> list[TestPoint]:
    """One TestPoint per stack-1 frame labelled `split`, paired with the stack-3 frame taken at the
    same time (the nearest, within SYNC_TOLERANCE_S)."""
    if MAIN_STACK not in recording.stacks:
        raise DataFormatError(recording.room_dir / "measurements", f"stack {MAIN_STACK} (USS{MAIN_STACK}.csv, "
                              f"CAM{MAIN_STACK}) is needed for the test points; train --gt none maps the recording "
                              f"without scoring it, or number the main stack's files {MAIN_STACK}")
    s1 = recording.stacks[MAIN_STACK]
    s3 = recording.stacks.get(PARTNER_STACK)
    points = []
    for i in s1.indices(split):
        t = float(s1.times[i])
        j = synchronous_index(s3.times, t) if s3 is not None else None
        points.append(
            TestPoint(
                index1=int(i),
                index3=j,
                time=t,
                time3=float(s3.times[j]) if j is not None else None,
                pose1=np.array(s1.cam_to_world[i], dtype=np.float64),
                pose3=np.array(s3.cam_to_world[j], dtype=np.float64) if j is not None else None,
            )
        )
    return points


def recording_warnings(recording: Recording, scored: bool = True) -> list[str]:
    """What `train`, `evaluate` and `sensors` say of a recording whose numbers may mislead: LiDAR
    poses upside down (quaternions written w,x,y,z?), and when it is `scored`, test points that
    went without their stack-3 frame or LiDAR scan."""
    from virus_nerf.sensors.geometry import upside_down_words

    out = []
    lidar_poses = {s: st.lidar_to_world for s, st in recording.stacks.items()}
    if lidar_poses and (note := upside_down_words(np.concatenate(list(lidar_poses.values())),
                                                  "the LiDAR poses (poses/poses_lidar_*)")):
        out.append(note)
    elif len(lidar_poses) > 1:  # one stack's file alone written w,x,y,z: half of all, said per file
        out += [note for s, poses in lidar_poses.items()
                if (note := upside_down_words(poses, f"stack {s}'s LiDAR poses (poses/poses_lidar_*sync{s}.csv)"))]
    out += stacks_apart_warnings(recording)
    if scored and not recording.lidar_paths and recording.map_path is not None:
        out.append(f"{recording.room_dir / 'lidars' / 'filtered'}: no LiDAR scans, though the recording has a LiDAR "
                   "map: the LiDAR's row stays empty (scans named <seconds>.<nanoseconds>.pcd)")
    if scored and MAIN_STACK in recording.stacks:
        out += pairing_warnings(recording, make_test_points(recording))
    return out


# Both stacks' pose files hold the one LiDAR's poses: in the real recording they agree to 0.08 mm,
# in the simulated ones to 3 mm at most. A stack on another clock or in another frame is metres off.
STACKS_APART_M = 0.05


def stacks_apart_warnings(recording: Recording) -> list[str]:
    """One line for each stack whose LiDAR poses lie a median of more than STACKS_APART_M from the
    main stack's at the same times (interpolated; only the times both cover)."""
    from virus_nerf.sensors.geometry import interpolate_poses

    main = recording.stacks.get(MAIN_STACK)
    if main is None or len(main) < 2 or not np.isfinite(main.lidar_to_world).all():
        return []
    out = []
    for s, st in recording.stacks.items():
        inside = (st.times >= main.times[0]) & (st.times <= main.times[-1]) & np.isfinite(st.lidar_to_world).all(axis=(1, 2))
        if s == MAIN_STACK or not inside.any():
            continue
        there = interpolate_poses(main.times, main.lidar_to_world, st.times[inside])  # (M, 4, 4)
        apart = float(np.median(np.linalg.norm(there[:, :3, 3] - st.lidar_to_world[inside, :3, 3], axis=1)))
        if apart > STACKS_APART_M:
            out.append(f"stack {s}'s LiDAR poses lie a median {apart:.2f} m from stack {MAIN_STACK}'s at the same "
                       "times (one LiDAR: they should agree): are the stacks' files on different clocks or in "
                       "different frames?")
    return out


def pairing_warnings(recording: Recording, points: list[TestPoint]) -> list[str]:
    """One line each for the test points that went without their stack-3 frame or LiDAR scan (none
    taken within SYNC_TOLERANCE_S of them: a stream that starts late, ends early or pauses)."""
    out = []
    if PARTNER_STACK in recording.stacks:
        alone = sum(p.index3 is None for p in points)
        if alone:
            out.append(f"{alone} of {len(points)} test points have no stack-{PARTNER_STACK} frame within "
                       f"{SYNC_TOLERANCE_S:g} s: they are scored with stack {MAIN_STACK}'s cameras, USS and IRS alone")
    if len(recording.lidar_times):
        unscanned = sum(lidar_scan_index(recording, p.time) is None for p in points)
        if unscanned:
            out.append(f"{unscanned} of {len(points)} test points have no LiDAR scan within {SYNC_TOLERANCE_S:g} s: "
                       "the LiDAR row leaves them out")
    return out


def split_file(recording: Recording) -> str:
    """The split file a refusal names (the default split when the recording has none)."""
    path = recording.room_dir / "split" / "split.csv"
    if path.is_file():
        return str(path)
    ratios = path.with_name("split_description.csv")
    if ratios.is_file():  # its ratios made the split: the file to change
        return f"{ratios} (the ratios the split was made from; split.csv absent)"
    return f"{path} (absent: the default split made in memory)"


def require_test_points(recording: Recording) -> None:
    """A one-line DataFormatError naming the split file when the recording has no test frame of
    the main stack: there is nothing to score (`train` and `sensors` refuse it before any work)."""
    if not make_test_points(recording):
        raise DataFormatError(split_file(recording), f"no CAM{MAIN_STACK} rows labelled 'test'; the evaluation "
                              f"scores the test frames of stack {MAIN_STACK}", field=f"CAM{MAIN_STACK}")
