"""Point clouds as PCD (pypcd4, binary) and PLY (binary little-endian, written by hand).

Both hold float32 x y z in metres in the world frame; with colours, PLY adds uchar red green
blue and PCD a packed float `rgb` field (the PCL convention, pypcd4's encode_rgb).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.utils.io import atomic_path


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> None:
    """(N, 3) points (+ (N, 3) uint8 colours) as a binary little-endian PLY, atomically."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    props = ["property float x", "property float y", "property float z"]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    rec = np.empty(len(xyz), dtype=fields)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = "\n".join(["ply", "format binary_little_endian 1.0", "comment virus-nerf export, metres, world frame",
                        f"element vertex {len(xyz)}", *props, "end_header"]) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_bytes(header.encode("ascii") + rec.tobytes())


def write_pcd(path: Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> None:
    """(N, 3) points (+ (N, 3) uint8 colours) as a binary PCD through pypcd4, atomically."""
    from pypcd4 import PointCloud

    from virus_nerf.data.pcd import write_pcd_xyz

    if rgb is None:
        write_pcd_xyz(path, xyz)
        return
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    packed = PointCloud.encode_rgb(np.asarray(rgb, dtype=np.uint8).reshape(-1, 3))
    cloud = PointCloud.from_xyzrgb_points(np.column_stack([xyz, packed.astype(np.float32)]))
    with atomic_path(path) as tmp:
        cloud.save(tmp)
