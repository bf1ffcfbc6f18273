"""Pinhole camera (OpenCV axes: x right, y down, z forward; pixel centres at integer coords)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.sensors.rays import Rays, rays_to_world


def scaled_pixels(uv, scale) -> np.ndarray:
    """Pixel coordinates (any shape) in an image resized by `scale`, pixel centres at integers:
    (uv + 0.5) * scale - 0.5 (the principal point of `Intrinsics.scaled`, a stereo target's pixel)."""
    return (np.asarray(uv, dtype=np.float64) + 0.5) * scale - 0.5


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
            cx=float(scaled_pixels(self.cx, factor)),
            cy=float(scaled_pixels(self.cy, factor)),
            width=round(self.width * factor),
            height=round(self.height * factor),
        )

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


# Plausible pinhole intrinsics (checked where intrinsics are read from a file): a field of view
# 2 atan(size / (2 f)) of 1 to 170 degrees along each image axis, the principal point inside the
# image, sides of a whole number of pixels up to 100000 px. Anything else is a unit mix-up
# (metres, a normalised matrix) or garbage, and makes every ray degenerate.
FOV_RANGE_DEG = (1.0, 170.0)
MAX_IMAGE_SIDE_PX = 100_000


def focal_range_px(size_px: float) -> tuple[float, float]:
    """Focal lengths (px) that give a field of view within FOV_RANGE_DEG over `size_px` pixels."""
    lo_deg, hi_deg = FOV_RANGE_DEG
    return size_px / (2 * np.tan(np.radians(hi_deg) / 2)), size_px / (2 * np.tan(np.radians(lo_deg) / 2))


def image_side_problem(value: float, name: str) -> str | None:
    """Why `value` is no image width/height (name: 'width' or 'height'), or None."""
    if value != int(value):
        return f"image {name} {value:g} px is not a whole number of pixels"
    if not 1 <= value <= MAX_IMAGE_SIDE_PX:
        return f"image {name} {value:g} px; expected a size from 1 to {MAX_IMAGE_SIDE_PX} px"
    return None


def intrinsics_problem(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> tuple[str, str] | None:
    """(field, problem) of the first implausible value of finite pinhole intrinsics, or None."""
    for name, f, size in (("fx", fx, width), ("fy", fy, height)):
        lo, hi = focal_range_px(size)
        if not lo <= f <= hi:
            fov = float(np.degrees(2 * np.arctan2(size, 2 * f))) if f > 0 else 180.0
            return name, (f"focal length {f:g} px gives a {fov:.1f} degree field of view over {size} px; expected "
                          f"a field of view of {FOV_RANGE_DEG[0]:g} to {FOV_RANGE_DEG[1]:g} degrees "
                          f"({name} from {lo:.0f} to {hi:.0f} px)")
    for name, c, size in (("cx", cx, width), ("cy", cy, height)):
        if not 0 <= c <= size:
            return name, f"principal point {c:g} px lies outside the image (0 to {size} px)"
    return None


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
