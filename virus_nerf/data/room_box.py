"""The room's scene box from a recording (docs/method.md 3.5, 9.2): the field's and the grids'
frame when the room's extent is known before the first step (`extent.mode` fitted)."""

from __future__ import annotations

import numpy as np

from virus_nerf.data.ethz import Recording
from virus_nerf.scene_box import SceneBox
from virus_nerf.sensors import irs
from virus_nerf.sensors.uss import USS_MAX_RANGE_M


def fit_scene_box(recording: Recording, margin: float = 0.1) -> SceneBox:
    """Anisotropic box around the room (docs/method.md 3.5, 9.2), in metres.

    From the LiDAR map where there is one (robust 0.1/99.9 percentiles), otherwise from the
    camera positions grown by the longest sensor range.

    `train` (offline and --online) uses it, fitted before training from the whole map and drive:
    the room's extent taken as known in advance (as from a floor plan). It is the field's and the
    grids' coordinate frame and bounds the marching; no density, colour or occupancy comes from
    it. A room never seen grows its box instead (`extent.mode` grow, grid/extent.py).
    """
    cams = recording.camera_poses()[0][:, :3, 3]
    if recording.map_path is not None:
        pts = recording.lidar_map()
        lo = np.percentile(pts, 0.1, axis=0)
        hi = np.percentile(pts, 99.9, axis=0)
        lo, hi = np.minimum(lo, cams.min(axis=0)), np.maximum(hi, cams.max(axis=0))
        return SceneBox(tuple(lo - margin), tuple(hi + margin))
    reach = max(irs.IRS_MAX_RANGE_M, USS_MAX_RANGE_M)
    lo = cams.min(axis=0) - [reach, reach, 1.5]
    hi = cams.max(axis=0) + [reach, reach, 1.5]
    return SceneBox(tuple(lo), tuple(hi))
