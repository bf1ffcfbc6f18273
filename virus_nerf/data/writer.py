"""Writers for the ETHZ layout (docs/method.md 4), the exact inverse of virus_nerf.data.ethz's reader.

All writes are atomic (temporary file + rename); numbers are written with fixed formats so
that a seed gives byte-identical files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.sensors import uss
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.geometry import matrix_to_quat
from virus_nerf.sensors.irs import IRS_ZONE_COUNT
from virus_nerf.utils.io import atomic_path, write_text_atomic


def write_intrinsics(path: Path, intrinsics: dict[int, Intrinsics]) -> None:
    """The real format (cam_id,fx,fy,cx,cy: 640x480 implied); other sizes add width,height."""
    if all((i.width, i.height) == (640, 480) for i in intrinsics.values()):
        lines = ["cam_id,fx,fy,cx,cy"]
        lines += [f"CAM{s},{i.fx:.7f},{i.fy:.7f},{i.cx:.7f},{i.cy:.7f}" for s, i in sorted(intrinsics.items())]
    else:
        lines = ["cam_id,fx,fy,cx,cy,width,height"]
        lines += [
            f"CAM{s},{i.fx:.7f},{i.fy:.7f},{i.cx:.7f},{i.cy:.7f},{i.width},{i.height}"
            for s, i in sorted(intrinsics.items())
        ]
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_poses(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    """time,x,y,z,qx,qy,qz,qw rows; poses (N, 4, 4) sensor-to-world."""
    xyz, q = poses[:, :3, 3].copy(), matrix_to_quat(poses[:, :3, :3])  # x y z, quaternion x y z w
    lines = ["time,x,y,z,qx,qy,qz,qw"]
    for t, p, r in zip(times, xyz, q, strict=True):
        lines.append(f"{t:.6f}," + ",".join(f"{v:.9f}" for v in (*p, *r)))
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_uss(path: Path, times: np.ndarray, ranges_m: np.ndarray) -> None:
    """time,meas (echo time in us = m * 5000; no echo = 50000)."""
    raw = uss.raw_from_range(ranges_m)
    lines = ["time,meas"] + [f"{t:.6f},{v:.1f}" for t, v in zip(times, raw, strict=True)]
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_tof(path: Path, times: np.ndarray, meas_mm: np.ndarray, stds_mm: np.ndarray) -> None:
    """time, meas_0..63 (mm, sensor order, 0 = invalid), stds_0..63 (mm, 65535 = n/a)."""
    header = ["time"] + [f"meas_{k}" for k in range(IRS_ZONE_COUNT)] + [f"stds_{k}" for k in range(IRS_ZONE_COUNT)]
    lines = [",".join(header)]
    for t, m, s in zip(times, meas_mm, stds_mm, strict=True):
        lines.append(f"{t:.6f}," + ",".join(f"{v:.1f}" for v in m) + "," + ",".join(f"{v:.1f}" for v in s))
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8)).save(tmp, format="PNG", compress_level=1)


def write_depth(path: Path, depth_mm: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with tmp.open("wb") as fh:
            np.save(fh, depth_mm.astype(np.uint16))


def lidar_file_name(t: float) -> str:
    """<sec>.<nsec>.pcd with nanoseconds zero-padded to 9 digits (as the real recordings)."""
    ns = int(round(t * 1e9))
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}.pcd"


def write_split_description(path: Path, ratios: tuple[float, float, float]) -> None:
    write_text_atomic(
        path,
        "train,val,test,keep_N_observations,info\n"
        f"{ratios[0]},{ratios[1]},{ratios[2]},all,Split ratios of this simulated dataset (virus-nerf simulate).\n",
    )
