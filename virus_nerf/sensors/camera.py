"""Pinhole camera (OpenCV axes: x right, y down, z forward; pixel centres at integer coords)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.sensors.rays import Rays, rays_to_world


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; no distortion (the ETHZ recordings are rectified)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics for an image resized by `factor` (e.g. 0.5 for 320x240)."""
        return Intrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=round(self.width * factor),
            height=round(self.height * factor),
        )

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


def pixel_directions(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame unit directions (N, 3) through pixel coordinates u (column), v (row)."""
    x = (np.asarray(u, dtype=np.float64) - intr.cx) / intr.fx
    y = (np.asarray(v, dtype=np.float64) - intr.cy) / intr.fy
    d = np.stack([x, y, np.ones_like(x)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def pixel_rays(intr: Intrinsics, cam_to_world: np.ndarray, u: np.ndarray, v: np.ndarray) -> Rays:
    """World-frame rays through pixels (u, v) of a camera at `cam_to_world` (4, 4)."""
    return rays_to_world(cam_to_world, pixel_directions(intr, u, v))


def project(intr: Intrinsics, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> pixel coords u, v and z-depth (N,)."""
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * points_cam[:, 0] / z + intr.cx
        v = intr.fy * points_cam[:, 1] / z + intr.cy
    return u, v, z


def z_depth_to_ray_length(z: np.ndarray, dirs_cam: np.ndarray) -> np.ndarray:
    """A z-depth along camera-frame unit directions (N, 3) -> distance along each ray (m)."""
    return np.asarray(z) / dirs_cam[..., 2]
