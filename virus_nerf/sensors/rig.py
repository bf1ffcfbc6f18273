"""The robot's sensor rig: where the two sensor stacks sit relative to the LiDAR (docs/method.md 4).

The camera-to-LiDAR transforms were derived from the real sample recording
(../shared/data/sample_dataset/office/poses): T_lidar_cam = inv(lidar_to_world) @ cam_to_world
with both poses read by `virus_nerf.data.ethz.load_recording` at the same camera timestamps
(poses_cam_balm_sync{1,3}.csv and poses_lidar_balm_sync{1,3}.csv; the 5 samples agree to 1e-15).
The numbers are hard-coded here (rounded to um / 1e-8) so the simulator needs no sample;
`tests/test_sim_sensors.py` (`test_mounting_matches_the_sample`) recomputes them from the sample and compares.

What the numbers say: the cameras are mounted upside down (camera y axis ~ +z of the LiDAR),
stack 1 looks ~14.7 deg to the right and stack 3 ~14.4 deg to the left, both pitched up ~5 deg,
~0.28 m apart and ~0.14-0.15 m below the LiDAR. USS and IRS share their camera's origin and axes.
"""

from __future__ import annotations

import numpy as np

from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.geometry import pose_matrix

# stack id -> (translation x y z in m, quaternion x y z w) of the camera in the LiDAR frame
CAMERA_IN_LIDAR: dict[int, tuple[tuple[float, float, float], tuple[float, float, float, float]]] = {
    1: ((0.36199, -0.15161, -0.15014), (0.54758683, 0.39549049, 0.46878873, 0.56918631)),
    3: ((0.354917, 0.129445, -0.137696), (0.42124637, 0.52122863, 0.5954544, 0.44306464)),
}

STACK_IDS = (1, 3)
# the stack whose camera is the scan origin of the evaluation and the height of the 2D maps
# (docs/method.md 6.1, 6.3)
MAIN_STACK = 1

# Pinhole intrinsics of the real cameras at 640x480 (the sample's camera_intrinsics.CSV).
CAMERA_INTRINSICS: dict[int, Intrinsics] = {
    1: Intrinsics(fx=388.0472148, fy=388.3651136, cx=327.5759548, cy=244.2966786),
    3: Intrinsics(fx=387.5046303, fy=387.6923004, cx=334.4870078, cy=241.9182859),
}

# LiDAR height above the floor (m): the sample's map has its floor at z ~ -0.72 m in the world
# frame (= the LiDAR at the start), so the RS-16 sits ~0.72 m above the floor.
LIDAR_HEIGHT_M = 0.72

# Stack 3 samples ~27 ms after stack 1 in the sample (0.0264-0.0273 s).
STACK_TIME_OFFSET_S = {1: 0.0, 3: 0.027}


def camera_in_lidar(stack: int) -> np.ndarray:
    """(4, 4) camera-to-LiDAR transform of sensor stack `stack` (1 or 3)."""
    if stack not in CAMERA_IN_LIDAR:
        raise ValueError(f"unknown sensor stack {stack}; the rig has stacks {STACK_IDS}")
    t, q = CAMERA_IN_LIDAR[stack]
    return pose_matrix(np.array(t), np.array(q))
