"""Ray marching: packed samples only where the occupancy grid says "occupied" (docs/method.md 2, 3.3, 3.4).

Each ray is clipped to the scene box (slab test) and to [near, far]; it is then walked from a start
jittered by one random fraction of the first step, and a sample [t_start, t_end] is kept where the
cell of its midpoint is occupied. Cells are looked up with THE shared cell-index formula
(`cell_index` in torch, `cell_index_scalar` in numba; docs/method.md 9.5), evaluated in float64 so that the
two backends agree bit for bit.

Step rules (both backends, identical arithmetic):
- constant: t_start_k = t0 + k * step_size;
- cone (cone_angle > 0): dt_k = clamp(t_k * cone_angle, step_size, max_step), t_{k+1} = t_k + dt_k,
  so far-away samples are coarser (Instant-NGP's cone-angle marching).
The last interval is clipped at the exit distance t_max; intervals that collapse to zero length in
float32 are dropped. A ray stops after `max_samples_per_ray` kept samples.

The numba backend works in two passes parallel over rays (count, prefix sum, fill) and, with the
constant step, can jump over empty cells (`skip_empty`): from a step in an empty cell it skips
every following step whose midpoint is provably in the same cell (a safety margin of 1e-5 cell
keeps rounding out of the decision), so its output is identical to the torch twin, which
evaluates every step. (With cone steps the recurrence must be walked anyway, and skipping was
measured to cost more than the lookups it saves, so it is not done there.)
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import prange

from virus_nerf.grid.base import GridSpec, cell_index, cell_index_scalar
from virus_nerf.render.samples import PackedSamples
from virus_nerf.utils.backend import Backend, resolve_backend

_SKIP_MARGIN = 1e-5  # cells: a step is skipped only if its midpoint is this far inside the cell
_TORCH_CHUNK = 1 << 21  # candidate steps per torch chunk (memory: ~100 MB of float64 points)


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
    the first step per ray (None: start at the box entry). skip_empty: numba, constant step only;
    same output either way.
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
            o64,
            d64,
            t0,
            t_end,
            occupied,
            spec,
            step_size,
            cone_angle,
            max_step,
            max_samples_per_ray,
            skip_empty,
        )
    return _march_torch(
        o64, d64, t0, t_end, occupied, spec, step_size, cone_angle, max_step, max_samples_per_ray
    )


# ----------------------------------------------------------------------------- torch twin


def _march_torch(o, d, t0, t_max, occ_grid, spec, step, cone, max_step, max_samples):
    """Candidate steps as (rays x steps) matrices in chunks of rays; float64 throughout."""
    occ = occ_grid.reshape(-1)
    n = o.shape[0]
    out_r, out_s, out_e = [], [], []
    for start, stop, ts in _candidate_chunks(t0, t_max, step, cone, max_step):
        tmax = t_max[start:stop, None]
        dt = torch.clamp(ts * cone, min=step, max=max_step) if cone > 0 else step
        te = torch.minimum(ts + dt, tmax)
        tm = (ts + te) * 0.5
        pts = o[start:stop, None, :] + tm[..., None] * d[start:stop, None, :]  # (Rc, K, 3)
        cid = cell_index(pts.reshape(-1, 3), spec).reshape(tm.shape)
        keep = (ts < tmax) & (cid >= 0) & occ[cid.clamp(min=0)] & (ts.float() < te.float())
        keep &= torch.cumsum(keep, dim=1) <= max_samples
        rows, cols = keep.nonzero(as_tuple=True)  # row-major: sorted by ray, then by t
        out_r.append(rows + start)
        out_s.append(ts[rows, cols])
        out_e.append(te[rows, cols])
    rays, ts, te = _cat(out_r, out_s, out_e, o.device)
    return PackedSamples.from_counts(torch.bincount(rays, minlength=n), ts, te)


def _candidate_chunks(t0, t_max, step, cone, max_step):
    """Yield (start, stop, ts (Rc, K)): every step start of rays start:stop (padded past t_max)."""
    n = t0.shape[0]
    if cone > 0:
        rows = max(1, _TORCH_CHUNK // 2048)
        for start in range(0, n, rows):
            stop = min(n, start + rows)
            t = t0[start:stop].clone()
            tmax = t_max[start:stop]
            cols = []
            while True:  # the recurrence t_{k+1} = t_k + clamp(t_k cone, step, max_step)
                cols.append(t)
                if not bool((t < tmax).any()):
                    break
                t = t + torch.clamp(t * cone, min=step, max=max_step)
            yield start, stop, torch.stack(cols, dim=1)
        return
    n_steps = (torch.ceil((t_max - t0).clamp(min=0) / step).to(torch.int64) + 1).tolist()
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
        k = torch.arange(k_max, dtype=torch.float64, device=t0.device)
        yield start, stop, t0[start:stop, None] + k * step
        start = stop


def _cat(out_r, out_s, out_e, device):
    if not out_r:
        z = torch.zeros(0, dtype=torch.float32, device=device)
        return torch.zeros(0, dtype=torch.int64, device=device), z, z.clone()
    return torch.cat(out_r), torch.cat(out_s).float(), torch.cat(out_e).float()


# ----------------------------------------------------------------------------- numba kernels


def _march_numba(o, d, t0, t_max, occupied, spec, step, cone, max_step, max_samples, skip):
    n = o.shape[0]
    geometry = (
        o.contiguous().numpy(),
        d.contiguous().numpy(),
        t0.contiguous().numpy(),
        t_max.contiguous().numpy(),
        occupied.reshape(-1).contiguous().numpy().astype(np.bool_, copy=False),
        np.asarray(spec.box.lo, dtype=np.float64),
        np.asarray(spec.box.size, dtype=np.float64),
        np.asarray(spec.resolution, dtype=np.int64),
        float(step),
        float(cone),
        float(max_step),
        bool(skip),
    )
    # Pass 1: count per ray, and where its first kept sample is (step index k, distance t).
    counts = np.full(n, int(max_samples), dtype=np.int64)  # in: the cap; out: the count
    first_k = np.zeros(n, dtype=np.int64)
    first_t = np.zeros(n, dtype=np.float64)
    none_i = np.zeros(0, dtype=np.int64)
    none_f = np.zeros(0, dtype=np.float32)
    _march_kernel(*geometry, counts, first_k, first_t, none_i, none_i, none_f, none_f, False)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    s = int(offsets[-1])
    rays = np.empty(s, dtype=np.int64)
    ts = np.empty(s, dtype=np.float32)
    te = np.empty(s, dtype=np.float32)
    # Pass 2: walk again from the first kept sample until the count is reached; fill.
    _march_kernel(*geometry, counts, first_k, first_t, offsets, rays, ts, te, True)
    return PackedSamples(
        torch.from_numpy(rays),
        torch.from_numpy(ts),
        torch.from_numpy(te),
        torch.from_numpy(offsets),
    )


@numba.njit(cache=True, inline="always")
def _axis_room(p, lo, size, res, inv_rate):  # pragma: no cover - compiled
    """Metres the ray may go from coordinate p before its cell coordinate comes within
    _SKIP_MARGIN of the next face on this axis; -1 if it is already that close to a face."""
    u = (p - lo) / size * res  # the cell_index arithmetic
    f = u - math.floor(u)
    if f < _SKIP_MARGIN or f > 1.0 - _SKIP_MARGIN:
        return -1.0
    if inv_rate > 0.0:
        return (1.0 - _SKIP_MARGIN - f) * inv_rate
    if inv_rate < 0.0:
        return (_SKIP_MARGIN - f) * inv_rate
    return np.inf


@numba.njit(cache=True, parallel=True)
def _march_kernel(
    o,
    d,
    t0,
    t_max,
    occ,
    lo,
    size,
    res,
    step,
    cone,
    max_step,
    skip,
    counts,
    first_k,
    first_t,
    offsets,
    rays,
    out_s,
    out_e,
    write,
):  # pragma: no cover - compiled
    """Walk every ray. Pass 1 (write=False): counts[r] = kept samples (at most counts[r] on
    entry), first_k/first_t[r] = the step of the first one. Pass 2: start there, stop after
    counts[r] samples, and write them from offsets[r]; the same steps, so the same samples."""
    for r in prange(o.shape[0]):
        ox, oy, oz = o[r, 0], o[r, 1], o[r, 2]
        dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
        # metres per cell along the ray on each axis (sign = direction); 0 = parallel, no limit
        ix = size[0] / (dx * res[0]) if dx != 0.0 else 0.0
        iy = size[1] / (dy * res[1]) if dy != 0.0 else 0.0
        iz = size[2] / (dz * res[2]) if dz != 0.0 else 0.0
        start = t0[r]
        tmax = t_max[r]
        limit = counts[r]
        if write:
            k = first_k[r]
            t = first_t[r]
            base = offsets[r]
        else:
            k = 0
            t = start
            base = 0
        n = 0
        while n < limit:
            if cone > 0.0:
                ts = t
                dt = min(max(ts * cone, step), max_step)
            else:
                ts = start + k * step
                dt = step
            if not ts < tmax:
                break
            te = min(ts + dt, tmax)
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
                    elif n == 0:
                        first_k[r] = k
                        first_t[r] = ts
                    n += 1
            elif skip and cone == 0.0 and c >= 0:
                # Every later midpoint up to t_lim lies >= _SKIP_MARGIN cells inside this cell.
                room = min(
                    _axis_room(x, lo[0], size[0], res[0], ix),
                    _axis_room(y, lo[1], size[1], res[1], iy),
                    _axis_room(z, lo[2], size[2], res[2], iz),
                )
                if room > 0.0:
                    # Unclipped midpoints start + (j + 1/2) step <= t_lim are in this empty cell.
                    t_lim = min(tm + room, tmax)
                    k = max(k + 1, math.floor((t_lim - start) / step - 0.5) + 1)
                    continue
            k += 1
            t = ts + dt
        if not write:
            counts[r] = n
