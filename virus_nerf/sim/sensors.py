"""Sensor models of the simulator (docs/method.md 5); each has its parameters in a dataclass.

All models cast exact rays into a `Scene` and add documented noise with a numpy Generator, so a
seed fixes every reading. Distances are metres; ranges are z-depth for the camera depth and
the IRS and radial for the USS and LiDAR (as on the real robot, docs/method.md 4).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sim import kernels
from virus_nerf.sim.scene import Box, Material, Scene, SceneObject

# ------------------------------------------------------------------------------------ camera


@dataclass(frozen=True)
class CameraModel:
    """Pinhole colour camera: exact ray per pixel, procedural albedo, Lambertian + ambient.

    lights: directional lights (unit direction towards the light, intensity); no shadows.
    noise_amp: uniform per-pixel sensor noise amplitude (fraction of full scale).
    tile: pixels per tile side for per-tile object culling (speed only, results identical).
    """

    ambient: float = 0.38
    lights: tuple[tuple[float, float, float, float], ...] = (
        (0.30, 0.45, 0.84, 0.55),
        (-0.55, -0.35, 0.76, 0.30),
        (0.7, -0.6, 0.3, 0.12),
        (0.1, 0.2, -1.0, 0.25),  # light bounced off the floor, so the ceiling is not flat grey
    )
    noise_amp: float = 0.012
    tile: int = 16

    @cached_property
    def light_array(self) -> np.ndarray:
        a = np.array(self.lights, dtype=np.float64).reshape(-1, 4)
        a[:, :3] /= np.linalg.norm(a[:, :3], axis=1, keepdims=True)
        return np.ascontiguousarray(a)


@dataclass(frozen=True)
class CameraFrame:
    """One rendered frame: rgb (H, W, 3) uint8; z (H, W) exact z-depth m (inf = nothing);
    cos_incidence (H, W) cosine between the ray and the surface normal; prim (H, W) primitive."""

    rgb: np.ndarray
    z: np.ndarray
    cos_incidence: np.ndarray
    prim: np.ndarray


def render_camera(scene: Scene, intr: Intrinsics, cam_to_world: np.ndarray, model: CameraModel,
                  frame_seed: int, max_range: float = 100.0) -> CameraFrame:
    """Render the camera at `cam_to_world` (4, 4, OpenCV axes) exactly, one ray per pixel."""
    pk = scene.packed
    h, w = intr.height, intr.width
    rgb = np.empty((h, w, 3), dtype=np.uint8)
    z = np.empty((h, w))
    cos = np.empty((h, w))
    prim = np.empty((h, w), dtype=np.int64)
    R = np.ascontiguousarray(cam_to_world[:3, :3], dtype=np.float64)
    t = np.ascontiguousarray(cam_to_world[:3, 3], dtype=np.float64)
    kernels.render_kernel(R, t, float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), w, h, model.tile,
                          max_range, pk.olo, pk.ohi, pk.ostart, pk.oend, pk.ptype, pk.pcen, pk.phalf, pk.prot,
                          pk.mcol, pk.mpat, pk.mscale, pk.mseed, model.light_array, model.ambient,
                          model.noise_amp, int(frame_seed) & 0x7FFFFFFF, rgb, z, cos, prim)
    return CameraFrame(rgb=rgb, z=z, cos_incidence=cos, prim=prim)


# ------------------------------------------------------------------------------------ RGB-D


@dataclass(frozen=True)
class DepthModel:
    """Aligned depth of an active stereo camera (RealSense-like), uint16 mm, 0 = invalid.

    noise std sigma(z) = sigma0 + k * z^2 (grows quadratically with depth); readings outside
    [min_range, max_range] or at grazing incidence (cos < min_cos) are holes; blob-shaped
    random holes cover about hole_share of the image; pixels at depth discontinuities larger
    than edge_jump * z drop out with probability edge_drop.
    """

    sigma0: float = 0.001
    k: float = 0.0025
    min_range: float = 0.2
    max_range: float = 6.0
    min_cos: float = 0.12
    hole_share: float = 0.02
    hole_blob_px: int = 24
    edge_jump: float = 0.05
    edge_drop: float = 0.6

    def apply(self, z: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Exact z-depth (H, W) m -> measured depth (H, W) uint16 mm (0 invalid)."""
        h, w = z.shape
        b = max(2, self.hole_blob_px)
        coarse = rng.random((h // b + 2, w // b + 2))
        seed = int(rng.integers(0, 2**31 - 1))
        out = np.empty((h, w), dtype=np.uint16)
        # a bilinear mix of uniforms is ~triangular near 0: level 2.2 * share gives ~share holes
        kernels.depth_kernel(np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(cos_incidence, dtype=np.float64),
                             coarse, float(b), self.hole_share * 2.2, self.sigma0, self.k, self.min_range,
                             self.max_range, self.min_cos, self.edge_jump, self.edge_drop, seed, out)
        return out


# ------------------------------------------------------------------------------------ IRS


@dataclass(frozen=True)
class IrsModel:
    """VL53L5CX-like 8x8 time-of-flight: per-zone z-depth from samples_per_axis^2 rays.

    Zone z-depth = median over the zone's rays (no hit = infinitely far) + N(0, sigma0 +
    sigma_per_m * z). A zone is valid when that median is within max_range and the return
    signal ir_reflectance * cos(incidence) * (range_at_unit_signal / z)^2 (median over the
    zone's rays) is at least 1: far, dark or grazing targets give no reading (0 on disk).
    """

    samples_per_axis: int = 4
    max_range: float = 4.0
    range_at_unit_signal: float = 3.8
    sigma0: float = 0.01
    sigma_per_m: float = 0.008

    @cached_property
    def dirs_cam(self) -> np.ndarray:
        """(64 * s^2, 3) camera-frame directions, zone-major in image zone order."""
        return irs.zone_directions(self.samples_per_axis).reshape(-1, 3)

    def measure(self, scene: Scene, cam_to_world: np.ndarray, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
        """-> z-depth grid (8, 8) m in image zone order (NaN invalid) and its noise std (8, 8) m."""
        d_cam = self.dirs_cam
        d_w = d_cam @ cam_to_world[:3, :3].T
        o = np.broadcast_to(cam_to_world[:3, 3], d_w.shape)
        res = scene.cast(o, d_w)
        z = res.t * d_cam[:, 2]  # (64 s^2,) z-depth, inf where no hit
        refl = scene.packed.mir[np.maximum(res.prim_id, 0)]
        cos_inc = np.clip(-(res.normal * d_w).sum(1), 0.0, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            signal = np.where(np.isfinite(z), refl * cos_inc * (self.range_at_unit_signal / z) ** 2, 0.0)
        s2 = self.samples_per_axis**2
        # the zone's median over all its rays (like the median of the RGB-D pixels in the zone);
        # valid when the median target is within range (>= half the rays hit within max_range)
        zmed = np.median(z.reshape(irs.IRS_ZONE_COUNT, s2), axis=1)
        sig = np.median(signal.reshape(irs.IRS_ZONE_COUNT, s2), axis=1)
        valid = (zmed <= self.max_range) & (sig >= 1.0)
        zmed = np.where(valid, zmed, 0.0)
        std = self.sigma0 + self.sigma_per_m * zmed
        noisy = zmed + std * rng.standard_normal(irs.IRS_ZONE_COUNT)
        valid &= noisy > irs.IRS_MIN_VALID_M
        out = np.where(valid, noisy, np.nan).reshape(8, 8)
        return out, np.where(valid, std, np.nan).reshape(8, 8)


def irs_row_mm(grid: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image-order grid (8, 8) m -> sensor-order (64,) mm (0 = invalid) and stds (65535 = n/a)."""
    meas = irs.measurements_from_grid(grid)
    s = irs.measurements_from_grid(std)
    mm = np.where(np.isfinite(meas), np.round(meas * 1000.0), 0.0)
    smm = np.where(np.isfinite(s), np.round(s * 1000.0), 65535.0)
    return mm, smm


# ------------------------------------------------------------------------------------ USS


@dataclass(frozen=True)
class UssModel:
    """URM37 ultrasonic range: the first echo inside the 55x35 deg elliptic cone.

    Geometry: rays on a regular angular grid in the cone (virus_nerf.sensors.uss); a ray at
    normalised cone radius rho (0 axis, 1 edge) can echo up to max_range * (1 - edge_loss rho^2)
    (weaker off-axis). Incidence: one threshold per reading, uniform in
    [inc_smooth_deg, inc_smooth_deg + inc_spread_deg] for acoustically smooth materials and
    [inc_rough_deg, ...+spread] for rough ones; rays hitting at a larger incidence do not echo
    (so the floor, hit at 77+ deg, is silent). Reading = first echo distance + bias(d) +
    bearing_bias * rho^2 + N(0, sigma(d) + incidence_sigma * (inc / 67 deg)^2); a reading is
    lost with probability dropout (no echo = NaN, raw 50000).

    Calibration (bench data ../shared/data/uss_characterisation, URM37, reference offset 0.005 m
    subtracted, docs/method.md 5): second series and the third series' 0 deg columns, pooled over
    targets, give mean errors -0.015/-0.033/-0.022/-0.023 m at 0.25/0.5/1/2 m (a linear fit:
    -0.0230 - 0.0003 d) and std 0.000/0.004/0.004/0.011 m (fit 0.0054 d); the first
    series (readings long by an unknown offset, used only relative to 0 deg) shows +0.01 to
    +0.02 m at 30 deg bearing and targets lost beyond the cone at 2 m; the third series shows the
    plexiglas (smooth) target lost at 67 deg tilt at 2 m, partly at 45 deg, cardboard partly at
    67 deg, and a spread of ~0.02 m at 45-67 deg. `uss_bench_comparison` recomputes the table.
    """

    # reach: 8 m on the axis, the URM37 V5.0 datasheet's 2-800 cm (and the authors' firmware
    # header; 5 m was the older V3.2/V4.0 figure), 2 m at the cone's edge (8 * (1 - 0.75)), where
    # the bench's first series loses targets at 2 m (docs/uss-range.md)
    max_range: float = 8.0
    edge_loss: float = 0.75
    bias0: float = -0.0230
    bias_per_m: float = -0.0003
    sigma0: float = 0.0
    sigma_per_m: float = 0.0054
    bearing_bias: float = 0.013
    incidence_sigma: float = 0.02
    inc_smooth_deg: float = 40.0
    inc_rough_deg: float = 55.0
    inc_spread_deg: float = 27.0
    dropout: float = 0.02
    n_h: int = 56
    n_v: int = 36

    @cached_property
    def dirs_cam(self) -> np.ndarray:
        return uss.cone_directions(self.n_h, self.n_v)

    @cached_property
    def rho2(self) -> np.ndarray:
        d = self.dirs_cam
        ax = np.arctan2(d[:, 0], d[:, 2]) / np.deg2rad(uss.USS_FOV_H_DEG / 2)
        ay = np.arctan2(d[:, 1], d[:, 2]) / np.deg2rad(uss.USS_FOV_V_DEG / 2)
        return ax**2 + ay**2

    def measure(self, scene: Scene, cam_to_world: np.ndarray, rng: np.random.Generator) -> float:
        """One reading (m, radial) of a USS at `cam_to_world` (camera axes); NaN = no echo."""
        d_w = self.dirs_cam @ cam_to_world[:3, :3].T
        o = np.broadcast_to(cam_to_world[:3, 3], d_w.shape)
        res = scene.cast(o, d_w, self.max_range)
        u = rng.random(3)  # threshold draw, dropout draw, (normal below)
        noise = rng.standard_normal()
        cos_inc = np.clip(-(res.normal * d_w).sum(1), -1.0, 1.0)
        inc = np.degrees(np.arccos(np.clip(cos_inc, 0, 1)))
        smooth = scene.packed.msmooth[np.maximum(res.prim_id, 0)]
        thresh = np.where(smooth, self.inc_smooth_deg, self.inc_rough_deg) + self.inc_spread_deg * u[0]
        ok = np.isfinite(res.t) & (res.t <= self.max_range * (1 - self.edge_loss * self.rho2)) & (inc <= thresh)
        if not ok.any() or u[1] < self.dropout:
            return float("nan")
        j = np.flatnonzero(ok)[np.argmin(res.t[ok])]
        d = res.t[j]
        sigma = self.sigma0 + self.sigma_per_m * d + self.incidence_sigma * (inc[j] / 67.0) ** 2
        r = d + self.bias0 + self.bias_per_m * d + self.bearing_bias * self.rho2[j] + sigma * noise
        return float(r) if 0 < r <= self.max_range else float("nan")


@dataclass(frozen=True)
class UssBenchRow:
    """Range error of the URM37 at one target distance: bench vs model (metres)."""

    distance: float
    bench_mean: float
    bench_std: float
    model_mean: float
    model_std: float
    n_bench: int
    n_model: int


def _read_bench(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise DataFormatError(path, "empty bench file")
    try:
        data = np.array([[float(x) for x in r] for r in rows[1:] if r], dtype=np.float64)
    except ValueError as exc:
        raise DataFormatError(path, f"non-numeric reading: {exc}") from exc
    return rows[0], data


def uss_bench_comparison(bench_dir: str | Path, model: UssModel | None = None, n_model: int = 400,
                         seed: int = 0, offset_m: float = 0.005) -> list[UssBenchRow]:
    """Compare the model's range error with the URM37 bench readings on axis (0 deg).

    Bench: all URM37 targets of `secondMeasurement` and the 0 deg columns of
    `thirdMeasurement`, error = reading - offset_m - distance. Model: a 1 m x 1 m flat
    perpendicular target at the distance in front of a simulated USS, n_model readings.
    """
    bench_dir = Path(bench_dir)
    model = model or UssModel()
    pooled: dict[float, list[np.ndarray]] = {}
    files = sorted((bench_dir / "secondMeasurement").glob("URM37_*.csv")) + sorted(
        (bench_dir / "thirdMeasurement").glob("URM37_*.csv"))
    if not files:
        raise DataFormatError(bench_dir, "no URM37_*.csv in secondMeasurement/ or thirdMeasurement/")
    for f in files:
        header, data = _read_bench(f)
        for j, col in enumerate(header):
            try:
                dist_s, ang_s = col.split("m_")
                dist, ang = float(dist_s), float(ang_s.removesuffix("deg"))
            except ValueError:
                raise DataFormatError(f, f"column {col!r} is not <distance>m_<angle>deg", row=1, field=col) from None
            if ang == 0.0:
                pooled.setdefault(dist, []).append(data[:, j] - offset_m - dist)
    rng = np.random.default_rng(seed)
    pose = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])  # camera looking +x
    rows = []
    for dist in sorted(pooled):
        bench = np.concatenate(pooled[dist])
        target = Scene([SceneObject("target", "target", (Box((dist + 0.01, 0.0, 0.0), (0.02, 1.0, 1.0)),),
                                    Material((0.5, 0.5, 0.5), smooth=True))])
        readings = np.array([model.measure(target, pose, rng) for _ in range(n_model)])
        err = readings[np.isfinite(readings)] - dist
        rows.append(UssBenchRow(distance=dist, bench_mean=float(bench.mean()), bench_std=float(bench.std()),
                                model_mean=float(err.mean()), model_std=float(err.std()),
                                n_bench=int(bench.size), n_model=int(err.size)))
    return rows


def format_bench_table(rows: list[UssBenchRow]) -> str:
    lines = ["distance_m  bench_mean  bench_std  model_mean  model_std"]
    lines += [f"{r.distance:10.2f}  {r.bench_mean:+10.4f}  {r.bench_std:9.4f}  {r.model_mean:+10.4f}  {r.model_std:9.4f}"
              for r in rows]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ LiDAR


@dataclass(frozen=True)
class LidarModel:
    """RoboSense RS-16-like spinning LiDAR: beams elevations evenly over +-vfov_deg, azimuth
    steps of h_step_deg over 360 deg, radial noise N(0, sigma), returns within
    [min_range, max_range]; points in the sensor frame (x forward, y left, z up). A scan is
    taken at one pose (motion during the 0.1 s sweep is not modelled: "filtered" = deskewed).

    Range noise calibrated on the real sample (issue 11; was 0.025 m, the datasheet's accuracy
    bound): along each beam's ring of the 11 real scans, the second difference of consecutive
    ranges (0.18 deg apart) has a robust std of 7.3 mm, i.e. a per-point range noise of 3.0 mm
    (std / sqrt(6); the same estimator returns 3.0 mm on this model's scans at sigma 0.003).
    The real map agrees: a real scan point hit head-on on a plane lies a median 1.75 cm behind
    the front of the map's voxels along its ray (p25/p75 0.5/4.0 cm), the simulated map built
    the same way gives 2.5 cm at sigma 0.003 and 5.25 cm at the old 0.025, whose >= 2-hit voxel
    shell made map-based GT ~8 cm short of the true surfaces. The real scans' heavier tail
    (12.8 % vs 3.9 % of second differences above 2 cm) is taken for clutter edges and not modelled.
    """

    beams: int = 16
    vfov_deg: float = 15.0
    h_step_deg: float = 0.4
    sigma: float = 0.003
    min_range: float = 0.3
    max_range: float = 30.0

    @cached_property
    def dirs(self) -> np.ndarray:
        el = np.deg2rad(np.linspace(-self.vfov_deg, self.vfov_deg, self.beams))
        az = np.deg2rad(np.arange(0.0, 360.0, self.h_step_deg))
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)

    def scan(self, scene: Scene, lidar_to_world: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(M, 3) float32 points in the sensor frame."""
        d_w = self.dirs @ lidar_to_world[:3, :3].T
        o = np.broadcast_to(lidar_to_world[:3, 3], d_w.shape)
        t = scene.cast(o, d_w, self.max_range).t
        r = t + self.sigma * rng.standard_normal(t.shape)
        keep = np.isfinite(t) & (r >= self.min_range) & (r <= self.max_range)
        return (self.dirs[keep] * r[keep, None]).astype(np.float32)
