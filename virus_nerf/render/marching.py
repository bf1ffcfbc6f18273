"""Ray marching: packed samples only where the occupancy grid says "occupied" (design 2, 3.3, 3.4).

Each ray is clipped to the scene box (slab test) and to [near, far]; it is then walked from a start
jittered by one random fraction of the first step, and a sample [t_start, t_end] is kept where the
cell of its midpoint is occupied. Cells are looked up with THE shared cell-index formula
(`cell_index` in torch, `cell_index_scalar` in numba; design 9.5), evaluated in float64 so that the
two backends agree bit for bit.

Step rules (both backends, identical arithmetic):
- constant: t_start_k = t0 + k * step_size;
- cone (cone_angle > 0): dt_k = clamp(t_k * cone_angle, step_size, max_step), t_{k+1} = t_k + dt_k,
  so far-away samples are coarser (Instant-NGP's cone-angle marching).
The last interval is clipped at the exit distance t_max; intervals that collapse to zero length in
float32 are dropped. A ray stops after `max_samples_per_ray` kept samples.

The numba backend works in two passes parallel over rays (count, prefix sum, fill) and can jump
over empty cells (`skip_empty`): from a sample in an empty cell it skips every following step whose
midpoint is provably in the same cell (a safety margin of 1e-5 cell keeps rounding out of the
decision), so its output is identical to the torch twin, which evaluates every step.
"""

from __future__ import annotations

import math
from typing import Literal

import numba
import numpy as np
import torch
from numba import prange

from virus_nerf.grid.base import GridSpec, cell_index, cell_index_scalar
from virus_nerf.render.samples import PackedSamples

Backend = Literal["auto", "numba", "torch"]

_SKIP_MARGIN = 1e-5  # cells: a step is skipped only if its midpoint is this far inside the cell
_TORCH_CHUNK = 1 << 21  # candidate steps per torch chunk (memory: ~100 MB of float64 points)


def resolve_backend(backend: Backend, *tensors: torch.Tensor) -> Literal["numba", "torch"]:
    """`auto` -> numba when every tensor is on the CPU (the numba kernels are CPU-only)."""
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    on_cpu = all(t.device.type == "cpu" for t in tensors)
    if backend == "numba" and not on_cpu:
        raise ValueError("the numba backend needs CPU tensors; use backend='torch' on other devices")
    if backend == "auto":
        return "numba" if on_cpu else "torch"
    return backend


def ray_box_interval(
    origins: torch.Tensor,
    directions: torch.Tensor,
    spec: GridSpec,
    near: float | torch.Tensor,
    far: float | torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: (t_min, t_max) (R,) float64 metres of each ray inside box and [near, far].

    A ray misses where t_max <= t_min. Axis-parallel rays (a zero direction component) are
    inside the slab of that axis for all t if the origin is within it (faces included), else miss.
    """
    o = origins.to(torch.float64)
    d = directions.to(torch.float64)
    lo = torch.tensor(spec.box.lo, dtype=torch.float64, device=o.device)
    hi = torch.tensor(spec.box.hi, dtype=torch.float64, device=o.device)
    zero = d == 0
    safe = torch.where(zero, torch.ones_like(d), d)
    t1 = (lo - o) / safe  # (R, 3)
    t2 = (hi - o) / safe
    inside = (o >= lo) & (o <= hi)
    inf = torch.full_like(t1, math.inf)
    t_near = torch.where(zero, torch.where(inside, -inf, inf), torch.minimum(t1, t2))
    t_far = torch.where(zero, torch.where(inside, inf, -inf), torch.maximum(t1, t2))
    near_t = torch.as_tensor(near, dtype=torch.float64, device=o.device).expand(o.shape[0])
    far_t = torch.as_tensor(far, dtype=torch.float64, device=o.device).expand(o.shape[0])
    t_min = torch.maximum(t_near.amax(dim=-1), near_t)
    t_max = torch.minimum(t_far.amin(dim=-1), far_t)
    return t_min, t_max


def march_rays(
    origins: torch.Tensor,
    directions: torch.Tensor,
    occupied: torch.Tensor,
    spec: GridSpec,
    near: float | torch.Tensor = 0.0,
    far: float | torch.Tensor = math.inf,
    step_size: float = 0.01,
    max_samples_per_ray: int = 1024,
    jitter: torch.Generator | None = None,
    backend: Backend = "auto",
    cone_angle: float = 0.0,
    max_step: float | None = None,
    skip_empty: bool = True,
) -> PackedSamples:
    """Packed samples of rays origins (R, 3), unit directions (R, 3) in the occupied cells.

    occupied: (rx, ry, rz) bool over `spec`. near/far: metres, scalar or (R,). step_size: metres
    (the constant step, or the smallest step with cone_angle > 0). max_step: largest cone step,
    default the smallest cell edge (never step over a cell). jitter: draws one U[0, 1) fraction of
    the first step per ray (None: start at the box entry). skip_empty: numba only, same output.
    """
    r = origins.shape[0]
    if origins.shape != (r, 3) or directions.shape != (r, 3):
        raise ValueError(
            f"origins and directions must be (R, 3), got {tuple(origins.shape)} and "
            f"{tuple(directions.shape)}"
        )
    if tuple(occupied.shape) != tuple(spec.resolution):
        raise ValueError(
            f"occupied has shape {tuple(occupied.shape)}, grid resolution is {spec.resolution}"
        )
    if not step_size > 0 or max_samples_per_ray < 0 or cone_angle < 0:
        raise ValueError(
            f"need step_size > 0, max_samples_per_ray >= 0, cone_angle >= 0; got {step_size}, "
            f"{max_samples_per_ray}, {cone_angle}"
        )
    if max_step is None:
        max_step = max(step_size, float(spec.cell_size.min()))
    if max_step < step_size:
        raise ValueError(f"max_step {max_step} m is below step_size {step_size} m")
    which = resolve_backend(backend, origins, directions, occupied)
    device = origins.device

    t_min, t_max = ray_box_interval(origins, directions, spec, near, far)
    hit = t_max > t_min
    if cone_angle > 0:
        dt0 = torch.clamp(t_min * cone_angle, min=step_size, max=max_step)
    else:
        dt0 = torch.full_like(t_min, step_size)
    if jitter is not None:
        u = torch.rand(r, generator=jitter, dtype=torch.float64, device=jitter.device).to(device)
    else:
        u = torch.zeros(r, dtype=torch.float64, device=device)
    t0 = torch.where(hit, t_min + u * dt0, torch.zeros_like(t_min))  # (R,) jittered start
    t_end = torch.where(hit, t_max, torch.zeros_like(t_max))  # misses: t0 == t_end, no steps

    o64 = origins.to(torch.float64)
    d64 = directions.to(torch.float64)
    if which == "numba":
        return _march_numba(
            o64, d64, t0, t_end, occupied, spec, step_size, cone_angle, max_step,
            max_samples_per_ray, skip_empty,
        )
    return _march_torch(
        o64, d64, t0, t_end, occupied, spec, step_size, cone_angle, max_step, max_samples_per_ray
    )


# ----------------------------------------------------------------------------- torch twin


def _march_torch(o, d, t0, t_max, occupied, spec, step, cone, max_step, max_samples):
    """Vectorised over rays (and, for the constant step, over steps too); float64 throughout."""
    occ = occupied.reshape(-1)
    if cone > 0:
        rays, ts, te = _march_torch_cone(o, d, t0, t_max, occ, spec, step, cone, max_step, max_samples)
    else:
        rays, ts, te = _march_torch_const(o, d, t0, t_max, occ, spec, step, max_samples)
    counts = torch.bincount(rays, minlength=o.shape[0])
    return PackedSamples.from_counts(counts, ts, te)


def _keep(o, d, ts, te, occ, spec):
    """Bool mask: midpoint of [ts, te] in an occupied cell and a non-empty float32 interval."""
    tm = (ts + te) * 0.5
    pts = o + tm[..., None] * d  # (..., 3) float64
    cid = cell_index(pts.reshape(-1, 3), spec).reshape(tm.shape)
    return (cid >= 0) & occ[cid.clamp(min=0)] & (ts.float() < te.float())


def _march_torch_const(o, d, t0, t_max, occ, spec, step, max_samples):
    """All candidate steps t0 + k * step at once, in chunks of rays."""
    n = o.shape[0]
    n_steps = (torch.ceil((t_max - t0).clamp(min=0) / step).to(torch.int64) + 1).tolist()
    out_r, out_s, out_e = [], [], []
    start = 0
    while start < n:
        k_max = 1
        stop = start
        while stop < n:  # grow the chunk while its (rays x steps) box stays small
            k_new = max(k_max, n_steps[stop])
            if (stop - start + 1) * k_new > _TORCH_CHUNK and stop > start:
                break
            k_max = k_new
            stop += 1
        k = torch.arange(k_max, dtype=torch.float64, device=o.device)
        ts = t0[start:stop, None] + k * step  # (Rc, K)
        tmax = t_max[start:stop, None]
        te = torch.minimum(ts + step, tmax)
        keep = (ts < tmax) & _keep(o[start:stop, None, :], d[start:stop, None, :], ts, te, occ, spec)
        keep &= torch.cumsum(keep, dim=1) <= max_samples
        rows, cols = keep.nonzero(as_tuple=True)  # row-major: sorted by ray, then by t
        out_r.append(rows + start)
        out_s.append(ts[rows, cols])
        out_e.append(te[rows, cols])
        start = stop
    return _cat(out_r, out_s, out_e, o.device)


def _march_torch_cone(o, d, t0, t_max, occ, spec, step, cone, max_step, max_samples):
    """The cone recurrence t_{k+1} = t_k + dt_k, one step of all active rays per iteration."""
    n = o.shape[0]
    t = t0.clone()
    count = torch.zeros(n, dtype=torch.int64, device=o.device)
    active = torch.arange(n, device=o.device)
    out_r, out_s, out_e = [], [], []
    while True:
        ta = t[active]
        alive = (ta < t_max[active]) & (count[active] < max_samples)
        active = active[alive]
        if active.numel() == 0:
            break
        ts = t[active]
        dt = torch.clamp(ts * cone, min=step, max=max_step)
        te = torch.minimum(ts + dt, t_max[active])
        keep = _keep(o[active], d[active], ts, te, occ, spec)
        out_r.append(active[keep])
        out_s.append(ts[keep])
        out_e.append(te[keep])
        count[active[keep]] += 1
        t[active] = ts + dt
    rays, ts, te = _cat(out_r, out_s, out_e, o.device)
    order = torch.sort(rays, stable=True).indices  # iterations are in t order per ray
    return rays[order], ts[order], te[order]


def _cat(out_r, out_s, out_e, device):
    if not out_r:
        z = torch.zeros(0, dtype=torch.float32, device=device)
        return torch.zeros(0, dtype=torch.int64, device=device), z, z.clone()
    return torch.cat(out_r), torch.cat(out_s).float(), torch.cat(out_e).float()


# ----------------------------------------------------------------------------- numba kernels


def _march_numba(o, d, t0, t_max, occupied, spec, step, cone, max_step, max_samples, skip):
    o_np = o.contiguous().numpy()
    d_np = d.contiguous().numpy()
    t0_np = t0.contiguous().numpy()
    tmax_np = t_max.contiguous().numpy()
    occ = occupied.reshape(-1).contiguous().numpy().astype(np.bool_, copy=False)
    lo = np.asarray(spec.box.lo, dtype=np.float64)
    size = np.asarray(spec.box.size, dtype=np.float64)
    res = np.asarray(spec.resolution, dtype=np.int64)
    n = o_np.shape[0]
    counts = np.zeros(n, dtype=np.int64)
    dummy_f = np.zeros(0, dtype=np.float32)
    dummy_i = np.zeros(0, dtype=np.int64)
    args = (o_np, d_np, t0_np, tmax_np, occ, lo, size, res, float(step), float(cone),
            float(max_step), int(max_samples), bool(skip))
    _march_kernel(*args, counts, dummy_i, dummy_f, dummy_f, False)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    s = int(offsets[-1])
    rays = np.empty(s, dtype=np.int64)
    ts = np.empty(s, dtype=np.float32)
    te = np.empty(s, dtype=np.float32)
    _march_kernel(*args, offsets, rays, ts, te, True)
    return PackedSamples(
        torch.from_numpy(rays), torch.from_numpy(ts), torch.from_numpy(te), torch.from_numpy(offsets)
    )


@numba.njit(cache=True, inline="always")
def _safe_until(x, y, z, tm, dx, dy, dz, lo, size, res):  # pragma: no cover - compiled
    """Largest t such that the ray from midpoint tm up to t stays inside the current cell with a
    margin of _SKIP_MARGIN cells on every axis; tm itself if the midpoint is already too close to
    a face (then nothing is skipped)."""
    t_lim = np.inf
    for a in range(3):
        if a == 0:
            p = x
            da = dx
        elif a == 1:
            p = y
            da = dy
        else:
            p = z
            da = dz
        u = (p - lo[a]) / size[a] * res[a]  # the cell_index arithmetic
        i = math.floor(u)
        f = u - i
        if f < _SKIP_MARGIN or f > 1.0 - _SKIP_MARGIN:
            return tm
        rate = da * res[a] / size[a]  # cells per metre along the ray
        if rate > 0.0:
            t_lim = min(t_lim, tm + (i + 1.0 - _SKIP_MARGIN - u) / rate)
        elif rate < 0.0:
            t_lim = min(t_lim, tm + (i + _SKIP_MARGIN - u) / rate)
    return t_lim


@numba.njit(cache=True, inline="always")
def _march_one(o, d, t0, t_max, occ, lo, size, res, step, cone, max_step, max_samples, skip,
               r, base, rays, out_s, out_e, write):  # pragma: no cover - compiled
    """Walk one ray; return the number of kept samples (written from `base` when `write`)."""
    ox, oy, oz = o[0], o[1], o[2]
    dx, dy, dz = d[0], d[1], d[2]
    n = 0
    k = 0
    t = t0
    while n < max_samples:
        if cone > 0.0:
            ts = t
            dt = min(max(ts * cone, step), max_step)
        else:
            ts = t0 + k * step
            dt = step
        if not ts < t_max:
            break
        te = min(ts + dt, t_max)
        tm = (ts + te) * 0.5
        x = ox + tm * dx
        y = oy + tm * dy
        z = oz + tm * dz
        c = cell_index_scalar(x, y, z, lo, size, res)
        if c >= 0 and occ[c]:
            if np.float32(ts) < np.float32(te):
                if write:
                    rays[base + n] = r
                    out_s[base + n] = ts
                    out_e[base + n] = te
                n += 1
        elif skip and c >= 0:
            t_lim = min(_safe_until(x, y, z, tm, dx, dy, dz, lo, size, res), t_max)
            if cone > 0.0:
                # Same recurrence, no lookups, while the next midpoint is inside the safe part.
                tn = ts + dt
                while tn < t_max:
                    dtn = min(max(tn * cone, step), max_step)
                    if (tn + min(tn + dtn, t_max)) * 0.5 > t_lim:
                        break
                    tn = tn + dtn
                t = tn
                continue
            # Unclipped midpoints t0 + (j + 1/2) step <= t_lim are in this empty cell.
            kk = math.floor((t_lim - t0 - 0.5 * step) / step) + 1
            k = max(k + 1, kk)
            continue
        k += 1
        t = ts + dt
    return n


@numba.njit(cache=True, parallel=True)
def _march_kernel(o, d, t0, t_max, occ, lo, size, res, step, cone, max_step, max_samples, skip,
                  offsets, rays, out_s, out_e, write):  # pragma: no cover - compiled
    """Pass 1 (write=False): offsets[r] = count of ray r. Pass 2: fill from offsets[r]."""
    for r in prange(o.shape[0]):
        n = _march_one(o[r], d[r], t0[r], t_max[r], occ, lo, size, res, step, cone, max_step,
                       max_samples, skip, r, offsets[r], rays, out_s, out_e, write)
        if not write:
            offsets[r] = n
