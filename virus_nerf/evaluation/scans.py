"""A model's 2D scan of a test point (docs/method.md 6.3): the same rays as the ground truth's,
from the camera-1 position. The scan geometry (Scan2D, FieldOfView, ...) is maps/scans.py."""

from __future__ import annotations

import numpy as np

from virus_nerf.evaluation.testpoints import TestPoint
from virus_nerf.maps.scans import (
    FieldOfView,
    RangeModel,
    Scan2D,
    points_from_ranges,
    scan_angles,
    scan_ranges,
)


def model_scan(model: RangeModel, test_point: TestPoint, n_rays: int = 512, name: str = "NeRF") -> Scan2D:
    """360 deg horizontal scan of `model` from the test point's scan origin (same rays as the GT)."""
    _, dirs, r = scan_ranges(model, test_point.origin, n_rays)  # (N, 3), (N,)
    if r.shape != (n_rays,):
        raise ValueError(f"model {name!r} returned {r.shape} ranges for {n_rays} rays")
    ok = np.isfinite(r) & (r > 0)
    return Scan2D(
        name=name,
        points=points_from_ranges(test_point.origin_xy, dirs, r),
        origin=test_point.origin_xy,
        fov=FieldOfView.full(test_point.origin_xy),
        extra={"angle": scan_angles(n_rays)[ok]},
    )
