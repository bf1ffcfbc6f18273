"""The robot's drive (docs/method.md 5): a smooth 2D loop at walking pace with low view variation.

The path is a "stadium" loop: forward along the room's x axis from the origin, a left U-turn,
a return leg on a parallel lane, a U-turn back to the start, repeated while time lasts. The
straight legs weave gently (a sin^2-tapered lateral offset) so the views vary a little. The
robot (= LiDAR frame) starts at the origin heading +x, so the world frame is the LiDAR pose at
the start (x forward, y left, z up). Speed slows in the turns and ramps up at the start.
Odometry poses (for the "poses not optimised" ablation) integrate the true motion with a
scale error, a yaw-rate bias and a random walk, i.e. with drift that accumulates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DriveSpec:
    """Loop geometry and speed. straight: length of the forward leg (m) from x = 0;
    radius: U-turn radius (m, lanes are 2 * radius apart, the return lane at y = +2 radius);
    weave: lateral amplitude (m) and wavelength (m) on straight legs; speeds in m/s."""

    straight: float
    radius: float = 0.9
    weave_amplitude: float = 0.12
    weave_wavelength: float = 5.0
    speed: float = 0.5
    turn_speed: float = 0.35
    ramp_s: float = 1.5


@dataclass(frozen=True)
class OdometryDrift:
    """Odometry error model: per-drive scale error of distance and yaw (std, unitless),
    yaw-rate bias (std, deg/s), yaw random walk (deg/sqrt(s)), height drift (m per m driven)."""

    scale_std: float = 0.01
    yaw_scale_std: float = 0.005
    yaw_bias_std_deg_s: float = 0.02
    yaw_walk_deg_sqrt_s: float = 0.05
    z_drift_per_m_std: float = 0.003


class DrivePath:
    """Centreline of the loop as a dense polyline parametrised by arc length."""

    def __init__(self, spec: DriveSpec, step: float = 0.01) -> None:
        self.spec = spec
        L, R = spec.straight, spec.radius
        n_s = max(2, int(np.ceil(L / step)))
        u = np.linspace(0.0, L, n_s, endpoint=False)
        taper = np.sin(np.pi * u / L) ** 2
        weave = spec.weave_amplitude * np.sin(2 * np.pi * u / spec.weave_wavelength) * taper
        n_a = max(2, int(np.ceil(np.pi * R / step)))
        a = np.linspace(0.0, np.pi, n_a, endpoint=False)
        legs = [
            np.stack([u, weave], 1),  # forward leg on y = 0
            np.stack([L + R * np.sin(a), R - R * np.cos(a)], 1),  # left U-turn at the far end
            np.stack([L - u, 2 * R - weave], 1),  # return leg on y = 2R
            np.stack([-R * np.sin(a), R + R * np.cos(a)], 1),  # U-turn back at the start
        ]
        pts = np.concatenate(legs + [legs[0][:1]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self.points = pts  # (M, 2) m, closed (last = first)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])  # (M,) arc length m
        self.length = float(self.s[-1])
        tang = np.gradient(pts, self.s, axis=0)
        heading = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
        heading[0], heading[-1] = 0.0, 2 * np.pi  # exact +x at the start (one-sided differences)
        self.heading = heading  # (M,) rad
        self.curvature = np.gradient(self.heading, self.s)  # (M,) 1/m

    def sample(self, step: float = 0.05) -> np.ndarray:
        """(K, 2) points every `step` metres along one loop (for keeping furniture off the path)."""
        s = np.arange(0.0, self.length, step)
        return np.stack([np.interp(s, self.s, self.points[:, 0]), np.interp(s, self.s, self.points[:, 1])], 1)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position x, y and heading (rad, unwrapped over loops) at arc lengths s (any shape)."""
        s = np.asarray(s, dtype=np.float64)
        loops = np.floor(s / self.length)
        sm = s - loops * self.length
        x = np.interp(sm, self.s, self.points[:, 0])
        y = np.interp(sm, self.s, self.points[:, 1])
        h = np.interp(sm, self.s, self.heading) + loops * (self.heading[-1] - self.heading[0])
        return x, y, h


class Trajectory:
    """Robot (LiDAR) poses over time: lidar_to_world(t) -> (..., 4, 4), z = 0 (floor level drive)."""

    def __init__(self, path: DrivePath, duration: float, dt: float = 0.005) -> None:
        self.path = path
        spec = path.spec
        n = int(np.ceil(duration / dt)) + 2
        t = np.arange(n) * dt
        s = np.zeros(n)
        for i in range(1, n):  # tiny ODE; n ~ 12k for 60 s
            k = abs(np.interp(s[i - 1] % path.length, path.s, path.curvature))
            turn = min(1.0, k * spec.radius)
            v = spec.speed - (spec.speed - spec.turn_speed) * turn
            v *= min(1.0, 0.5 - 0.5 * np.cos(np.pi * min(1.0, t[i - 1] / spec.ramp_s)))
            s[i] = s[i - 1] + v * dt
        self.t = t  # (n,) s
        self.s = s  # (n,) m driven
        self.duration = duration

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y (m) and yaw (rad) at times t (s)."""
        s = np.interp(np.asarray(t, dtype=np.float64), self.t, self.s)
        return self.path.at(s)

    def lidar_to_world(self, t: np.ndarray) -> np.ndarray:
        """(..., 4, 4) LiDAR-to-world poses at times t (s since the start)."""
        x, y, yaw = self.state(t)
        return planar_pose(x, y, yaw)

    def distance(self, t: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(t, dtype=np.float64), self.t, self.s)


def planar_pose(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, z: np.ndarray | float = 0.0) -> np.ndarray:
    x, y, yaw = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(yaw, float))
    out = np.zeros(x.shape + (4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    out[..., 0, 3], out[..., 1, 3], out[..., 2, 3] = x, y, z
    out[..., 3, 3] = 1.0
    return out


def odometry_poses(traj: Trajectory, times: np.ndarray, drift: OdometryDrift,
                   rng: np.random.Generator) -> np.ndarray:
    """LiDAR-to-world (K, 4, 4) as a drifting odometry would report them at `times` (s).

    Integrates the true body-frame increments on the trajectory's fine time grid with one
    scale error per drive, a yaw-rate bias and a yaw random walk, so the error grows along
    the drive; at t = 0 the odometry equals the truth (the world frame is the start).
    """
    x, y, yaw = traj.state(traj.t)
    dx, dy = np.diff(x), np.diff(y)
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    fwd, lat = c * dx + s * dy, -s * dx + c * dy  # body-frame increments
    dyaw = np.diff(yaw)
    dt = np.diff(traj.t)
    scale = 1.0 + drift.scale_std * rng.standard_normal()
    yaw_scale = 1.0 + drift.yaw_scale_std * rng.standard_normal()
    bias = np.deg2rad(drift.yaw_bias_std_deg_s) * rng.standard_normal()
    walk = np.deg2rad(drift.yaw_walk_deg_sqrt_s) * np.sqrt(dt) * rng.standard_normal(len(dt))
    z_rate = drift.z_drift_per_m_std * rng.standard_normal()
    moving = (np.abs(fwd) + np.abs(dyaw)) > 0  # no drift while standing still
    yaw_o = yaw[0] + np.concatenate([[0.0], np.cumsum(dyaw * yaw_scale + (bias * dt + walk) * moving)])
    co, so = np.cos(yaw_o[:-1]), np.sin(yaw_o[:-1])
    xo = x[0] + np.concatenate([[0.0], np.cumsum(scale * (co * fwd - so * lat))])
    yo = y[0] + np.concatenate([[0.0], np.cumsum(scale * (so * fwd + co * lat))])
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(dx, dy))])
    zo = z_rate * dist
    times = np.asarray(times, dtype=np.float64)
    return planar_pose(np.interp(times, traj.t, xo), np.interp(times, traj.t, yo),
                       np.interp(times, traj.t, yaw_o), np.interp(times, traj.t, zo))
