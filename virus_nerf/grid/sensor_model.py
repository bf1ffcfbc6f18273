"""Inverse sensor models of the VIRUS grid (docs/method.md 3.4): log-odds increments per cell.

Depth-Update (IRS rays): a MURIEL-style multiple-target model (Konolige 1997).
NeRF-Update: paper eq. 9.
Cell traversal: exact voxel traversal (Amanatides & Woo 1987), one segment per crossed cell, the
cell named by the shared `cell_index_scalar` at the segment midpoint (docs/method.md 9.4, 9.5).

Depth model, derivation. A beam leaves the sensor; the world along it is seen through the
"independent cell" lens: cell c (segment [a, b] along the beam, midpoint d, length s = b - a) is
either occupied or empty, everything else along the beam is empty apart from false detections,
a Poisson process of rate lambda per metre (short returns from dust, stray light, multipath).
The measurement is the first detection, read with Gaussian noise N(0, sigma^2) (sigma = sigma(m)).
- If c is empty, the return is the first false detection: p(m | emp) = lambda e^(-lambda m)
  (the Poisson process is memoryless, so this holds on either side of c).
- If c is occupied, three ways lead to a return at m: a false detection before the beam reaches c
  (weight 1 - Phi((m - d)/sigma) under the noise), the cell itself detected (probability p_det,
  the beam having reached c with probability e^(-lambda d); its surface lies anywhere in the
  segment, so the range density is the Gaussian averaged over the segment,
  N_bar = [Phi((b - m)/sigma) - Phi((a - m)/sigma)] / s), or the cell missed (1 - p_det) and a
  false detection after it (weight Phi((m - d)/sigma)):
      p(m | occ) = lambda e^(-lambda m) [1 - p_det Phi((m - d)/sigma)] + p_det e^(-lambda d) N_bar.
- Likelihood ratio, the log-odds increment of Bayes' rule (eq. 8):
      ln P(m|occ)/P(m|emp) = ln( 1 - p_det Phi((m - d)/sigma) + p_det e^(lambda (m - d)) N_bar / lambda ).
  Well before m: N_bar -> 0, Phi -> 1, increment -> ln(1 - p_det) < 0 (the beam passed through).
  Around m: the Gaussian term dominates, increment > 0 (peak ~ ln(p_det N_bar / lambda)); a
  larger false-detection rate explains more returns by chance and lowers the peak.
  Beyond m: Phi -> 0 and N_bar -> 0, increment -> 0 (nothing known); cells past m + 3 sigma are
  not visited at all. The profile is unimodal in d (rises up to the peak, decays after it) and
  bounded below by ln(1 - p_det), so it is always defined.
- p_det, the chance that an occupied cell stops the beam, grows with the length of beam inside the
  cell: p_det = p_hit (1 - e^(-s / stop_length)). A beam clipping a cell's corner for a few
  millimetres says little about that cell; one crossing it fully says a lot.
Increments are clamped to +-max_increment so one reading cannot saturate a cell on its own.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from virus_nerf.grid.base import GridSpec, cell_index_scalar
from virus_nerf.utils.slab import slab_clip

_SQRT_HALF = 1.0 / math.sqrt(2.0)


@numba.njit(cache=True, inline="always")
def _normal_cdf(x):  # pragma: no cover - compiled
    return 0.5 * math.erfc(-x * _SQRT_HALF)


@numba.njit(cache=True)
def depth_log_odds(a, b, m, sigma, false_rate, hit_probability, stop_length, max_increment):  # pragma: no cover - compiled
    """ln P(m|occ)/P(m|emp) for the cell whose beam segment is [a, b] metres (module docstring).

    m: measured range (m); sigma: range noise std at m (m); false_rate: lambda (1/m);
    hit_probability: p_hit; stop_length: metres of beam for p_det to reach 63 % of p_hit.
    """
    s = b - a
    if s <= 0.0:
        return 0.0
    d = 0.5 * (a + b)
    p_det = hit_probability * (1.0 - math.exp(-s / stop_length))
    # Gaussian mass of the return inside [a, b], taken on the side of m where it is accurate
    if a > m:
        mass = _normal_cdf((m - a) / sigma) - _normal_cdf((m - b) / sigma)
    else:
        mass = _normal_cdf((b - m) / sigma) - _normal_cdf((a - m) / sigma)
    n_bar = mass / s  # 1/m
    ratio = 1.0 - p_det * _normal_cdf((m - d) / sigma)
    ratio += p_det * math.exp(false_rate * (m - d)) * n_bar / false_rate
    inc = math.log(ratio)
    if inc > max_increment:
        inc = max_increment
    elif inc < -max_increment:
        inc = -max_increment
    return inc


@numba.njit(cache=True)
def traverse_ray(ox, oy, oz, dx, dy, dz, t_start, t_end, lo, size, res, cells, seg_a, seg_b):  # pragma: no cover - compiled
    """Cells crossed by the ray o + t d for t in [t_start, t_end] inside the box, in order.

    Writes one (cell, a, b) per crossed cell into cells/seg_a/seg_b (capacity >= sum(res) + 4) and
    returns how many. Boundary crossings come from a 3D DDA; each cell is named by
    `cell_index_scalar` at its segment midpoint, so the index is the one the ray marcher reads.
    Zero-length segments (exact edge/corner hits) are skipped; consecutive segments that land in
    the same cell are merged, so a cell appears at most once per ray.
    """
    o = (ox, oy, oz)
    dvec = (dx, dy, dz)
    hi = np.empty(3)
    for ax in range(3):
        hi[ax] = lo[ax] + size[ax]
    t0, t1 = slab_clip(ox, oy, oz, dx, dy, dz, lo, hi, t_start, t_end, 1e-15)
    if not t1 > t0:
        return 0
    # DDA state per axis: next integer boundary k (cell coordinates) and its t
    u0 = np.empty(3)
    du = np.empty(3)
    k = np.empty(3)
    stp = np.empty(3)
    t_next = np.empty(3)
    for ax in range(3):
        u0[ax] = (o[ax] - lo[ax]) / size[ax] * res[ax]
        du[ax] = dvec[ax] / size[ax] * res[ax]
        if du[ax] > 0.0:
            stp[ax] = 1.0
            k[ax] = math.floor(u0[ax] + du[ax] * t0) + 1.0
        elif du[ax] < 0.0:
            stp[ax] = -1.0
            k[ax] = math.ceil(u0[ax] + du[ax] * t0) - 1.0
        else:
            stp[ax] = 0.0
            t_next[ax] = np.inf
            continue
        t_next[ax] = (k[ax] - u0[ax]) / du[ax]
        while t_next[ax] <= t0:  # rounding guard: the next boundary must lie ahead
            k[ax] += stp[ax]
            t_next[ax] = (k[ax] - u0[ax]) / du[ax]
    cap = cells.shape[0]
    n = 0
    pending = -1
    pa = 0.0
    pb = 0.0
    t_cur = t0
    while t_cur < t1:
        tn = min(t_next[0], t_next[1], t_next[2], t1)
        if tn > t_cur:
            tm = 0.5 * (t_cur + tn)
            c = cell_index_scalar(ox + dx * tm, oy + dy * tm, oz + dz * tm, lo, size, res)
            if c == pending and c >= 0:
                pb = tn
            else:
                if pending >= 0 and n < cap:
                    cells[n] = pending
                    seg_a[n] = pa
                    seg_b[n] = pb
                    n += 1
                pending = c
                pa = t_cur
                pb = tn
        for ax in range(3):
            if t_next[ax] <= tn:
                k[ax] += stp[ax]
                t_next[ax] = (k[ax] - u0[ax]) / du[ax]
        t_cur = tn
    if pending >= 0 and n < cap:
        cells[n] = pending
        seg_a[n] = pa
        seg_b[n] = pb
        n += 1
    return n


@numba.njit(cache=True)
def depth_update_kernel(
    origins, directions, ranges, lo, size, res, logodds,
    std_per_m, std_floor, false_rate, hit_probability, stop_length, max_increment,
    l_min, l_max,
):  # pragma: no cover - compiled
    """Apply the Depth-Update of every ray, in ray order, to flat float32 `logodds` in place.

    origins/directions (K, 3) float64 (unit directions), ranges (K,) metres. Serial on purpose:
    the order of clamped additions is fixed, so the result is bit-reproducible. Returns the
    number of (cell, ray) increments applied.
    """
    cap = res[0] + res[1] + res[2] + 4
    cells = np.empty(cap, dtype=np.int64)
    seg_a = np.empty(cap)
    seg_b = np.empty(cap)
    total = 0
    for r in range(origins.shape[0]):
        m = ranges[r]
        if not (m > 0.0 and m < np.inf):
            continue
        sigma = std_per_m * m + std_floor
        t_end = m + 3.0 * sigma
        n = traverse_ray(
            origins[r, 0], origins[r, 1], origins[r, 2],
            directions[r, 0], directions[r, 1], directions[r, 2],
            0.0, t_end, lo, size, res, cells, seg_a, seg_b,
        )
        for j in range(n):
            inc = depth_log_odds(seg_a[j], seg_b[j], m, sigma, false_rate, hit_probability, stop_length, max_increment)
            c = cells[j]
            v = logodds[c] + inc
            if v > l_max:
                v = l_max
            elif v < l_min:
                v = l_min
            logodds[c] = v
        total += n
    return total


def spec_arrays(spec: GridSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo (3,) float64, size (3,) float64, res (3,) int64): what the numba kernels take."""
    lo = np.asarray(spec.box.lo, dtype=np.float64)
    size = np.asarray(spec.box.size, dtype=np.float64)
    res = np.asarray(spec.resolution, dtype=np.int64)
    return lo, size, res


def cells_along_ray(
    spec: GridSpec, origin, direction, t_end: float, t_start: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells a ray crosses between t_start and t_end metres: (cells (n,) int64, a (n,), b (n,)).

    `direction` is normalised here, so a and b are metres along the ray.
    """
    lo, size, res = spec_arrays(spec)
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    d = d / np.linalg.norm(d)
    cap = int(res.sum()) + 4
    cells = np.empty(cap, dtype=np.int64)
    seg_a = np.empty(cap)
    seg_b = np.empty(cap)
    n = traverse_ray(o[0], o[1], o[2], d[0], d[1], d[2], float(t_start), float(t_end), lo, size, res, cells, seg_a, seg_b)
    return cells[:n].copy(), seg_a[:n].copy(), seg_b[:n].copy()


@numba.njit(cache=True)
def points_to_cells(points, lo, size, res):  # pragma: no cover - compiled
    """Flat cell index (N,) int64 of points (N, 3), -1 outside: `cell_index_scalar` per point."""
    out = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        out[i] = cell_index_scalar(points[i, 0], points[i, 1], points[i, 2], lo, size, res)
    return out


def nerf_log_odds(
    sigma: np.ndarray, sigma_threshold: float, zeta: float, max_increment: float, sigma_floor: float
) -> np.ndarray:
    """Paper eq. 9: P(M=sigma|occ) = 1 / (1 + (sigma_T/sigma)^zeta), P(M|emp) = 1 - P(M|occ).

    The log-odds increment is ln P(M|occ)/P(M|emp) = zeta ln(sigma / sigma_T): zero at
    sigma = sigma_T, positive above, negative below (docs/method.md 9.3: not sigma * sigma_T). sigma (N,)
    in 1/m is floored at `sigma_floor` so ln never sees 0; result (N,) float64, clamped.
    """
    s = np.maximum(np.asarray(sigma, dtype=np.float64), sigma_floor)
    inc = zeta * np.log(s / max(float(sigma_threshold), sigma_floor))
    return np.clip(inc, -max_increment, max_increment)
