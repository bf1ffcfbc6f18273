"""PCD point clouds (LiDAR scans and the global map) through pypcd4, with clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError
from virus_nerf.utils.io import atomic_path


def read_pcd_xyz(path: str | Path) -> np.ndarray:
    """Read the x, y, z fields of a PCD file -> (N, 3) float32 (NaN points removed)."""
    from pypcd4 import PointCloud

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "PCD file not found")
    try:
        cloud = PointCloud.from_path(path)
    except Exception as exc:  # pypcd4 raises several types for bad headers/encodings
        raise DataFormatError(
            path, f"not a readable PCD file (expected ascii/binary/binary_compressed): {exc}"
        ) from exc
    missing = [f for f in ("x", "y", "z") if f not in cloud.fields]
    if missing:
        raise DataFormatError(
            path, f"PCD has fields {list(cloud.fields)}; expected x, y, z", field=",".join(missing)
        )
    xyz = np.asarray(cloud.numpy(("x", "y", "z")), dtype=np.float32)
    return xyz[np.isfinite(xyz).all(axis=1)]


def write_pcd_xyz(path: str | Path, xyz: np.ndarray) -> None:
    """Write (N, 3) points as a binary PCD with float32 x y z (atomically)."""
    from pypcd4 import PointCloud

    xyz = np.ascontiguousarray(np.asarray(xyz, dtype=np.float32).reshape(-1, 3))
    cloud = PointCloud.from_xyz_points(xyz)
    with atomic_path(path) as tmp:
        cloud.save(tmp)
