"""Numba kernels of the simulator: exact ray casting against boxes and vertical cylinders,
and the camera renderer (ray casting + procedural texture + Lambertian shading).

Primitives are packed into flat arrays by `scene.Scene` (docs/method.md 5):
  ptype (P,) int64       0 = box (yawed about z), 1 = vertical cylinder
  pcen (P, 3) m          centre
  phalf (P, 3) m         box half sizes (local x, y, z); cylinder (radius, radius, half height)
  prot (P, 2)            cos(yaw), sin(yaw) of the local frame (cylinders: 1, 0)
Primitives are grouped by object (objects are contiguous runs [ostart, oend) with a world AABB
olo/ohi), so a ray tests an object's box first and its parts only on a hit (a two-level BVH).

Hits are "entering" hits only: a ray starting inside a primitive does not hit that primitive
(the sensors are always in free space). Normals are the outward normals of the hit face.
All kernels are per-ray independent, hence bit-identical whatever the thread count.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from virus_nerf.utils.slab import slab_clip

EPS = 1e-9
T_MIN = 1e-6  # hits closer than this (m) are ignored

PATTERN_CODES = {"plain": 0, "stripes": 1, "checker": 2, "noise": 3, "wood": 4}


@njit(cache=True, inline="always")
def _aabb_hit(ox, oy, oz, dx, dy, dz, lo, hi, tmax):
    """Does the ray hit the world AABB [lo, hi] within (0, tmax)? (the shared slab test)"""
    t0, t1 = slab_clip(ox, oy, oz, dx, dy, dz, lo, hi, 0.0, tmax, EPS)
    return not t0 > t1


@njit(cache=True)
def _prim_hit(k, ox, oy, oz, dx, dy, dz, ptype, pcen, phalf, prot, out_n):
    """Entering hit distance of ray with primitive k (inf if none); writes the world normal."""
    c = prot[k, 0]
    s = prot[k, 1]
    px = ox - pcen[k, 0]
    py = oy - pcen[k, 1]
    pz = oz - pcen[k, 2]
    # world -> local: rotate by -yaw
    lx = c * px + s * py
    ly = -s * px + c * py
    lz = pz
    ux = c * dx + s * dy
    uy = -s * dx + c * dy
    uz = dz
    hx = phalf[k, 0]
    hy = phalf[k, 1]
    hz = phalf[k, 2]
    nlx = 0.0
    nly = 0.0
    nlz = 0.0
    if ptype[k] == 0:
        t0 = -np.inf
        t1 = np.inf
        ax = -1
        for a in range(3):
            o = lx if a == 0 else (ly if a == 1 else lz)
            d = ux if a == 0 else (uy if a == 1 else uz)
            h = hx if a == 0 else (hy if a == 1 else hz)
            if abs(d) < EPS:
                if o < -h or o > h:
                    return np.inf
            else:
                inv = 1.0 / d
                ta = (-h - o) * inv
                tb = (h - o) * inv
                if ta > tb:
                    ta, tb = tb, ta
                if ta > t0:
                    t0 = ta
                    ax = a
                if tb < t1:
                    t1 = tb
        if t0 > t1 or t0 < T_MIN or ax < 0:
            return np.inf
        d = ux if ax == 0 else (uy if ax == 1 else uz)
        sg = -1.0 if d > 0 else 1.0
        if ax == 0:
            nlx = sg
        elif ax == 1:
            nly = sg
        else:
            nlz = sg
        t = t0
    else:
        r = hx
        best = np.inf
        # side
        a2 = ux * ux + uy * uy
        if a2 > EPS:
            b = lx * ux + ly * uy
            cc = lx * lx + ly * ly - r * r
            disc = b * b - a2 * cc
            if disc >= 0.0 and cc > 0.0:
                ts = (-b - math.sqrt(disc)) / a2
                if ts >= T_MIN:
                    z = lz + ts * uz
                    if -hz <= z <= hz:
                        best = ts
                        nlx = (lx + ts * ux) / r
                        nly = (ly + ts * uy) / r
                        nlz = 0.0
        # caps
        if abs(uz) > EPS:
            zc = hz if uz < 0 else -hz
            if (uz < 0 and lz > hz) or (uz > 0 and lz < -hz):
                tc = (zc - lz) / uz
                if T_MIN <= tc < best:
                    x = lx + tc * ux
                    y = ly + tc * uy
                    if x * x + y * y <= r * r:
                        best = tc
                        nlx = 0.0
                        nly = 0.0
                        nlz = 1.0 if uz < 0 else -1.0
        if best == np.inf:
            return np.inf
        t = best
    # local -> world normal: rotate by +yaw
    out_n[0] = c * nlx - s * nly
    out_n[1] = s * nlx + c * nly
    out_n[2] = nlz
    return t


@njit(cache=True, inline="always")
def _first_hit(ox, oy, oz, dx, dy, dz, tmax, olo, ohi, ostart, oend, ptype, pcen, phalf, prot, nbuf, nbest):
    """Closest entering hit over all objects within tmax -> (t, prim) and normal in nbest."""
    best = tmax
    bestk = -1
    for o in range(olo.shape[0]):
        if not _aabb_hit(ox, oy, oz, dx, dy, dz, olo[o], ohi[o], best):
            continue
        for k in range(ostart[o], oend[o]):
            t = _prim_hit(k, ox, oy, oz, dx, dy, dz, ptype, pcen, phalf, prot, nbuf)
            if t < best:
                best = t
                bestk = k
                nbest[0] = nbuf[0]
                nbest[1] = nbuf[1]
                nbest[2] = nbuf[2]
    return best, bestk


@njit(cache=True, parallel=True)
def cast_kernel(orig, dirs, tmax, olo, ohi, ostart, oend, ptype, pcen, phalf, prot, out_t, out_n, out_k):
    """Cast N rays (orig/dirs (N, 3), tmax (N,)) -> out_t (N,) inf=no hit, out_n, out_k."""
    n = orig.shape[0]
    for i in prange(n):
        nbuf = np.empty(3)
        nbest = np.zeros(3)
        t, k = _first_hit(orig[i, 0], orig[i, 1], orig[i, 2], dirs[i, 0], dirs[i, 1], dirs[i, 2],
                          tmax[i], olo, ohi, ostart, oend, ptype, pcen, phalf, prot, nbuf, nbest)
        if k < 0:
            out_t[i] = np.inf
            out_k[i] = -1
            out_n[i, 0] = 0.0
            out_n[i, 1] = 0.0
            out_n[i, 2] = 0.0
        else:
            out_t[i] = t
            out_k[i] = k
            out_n[i, 0] = nbest[0]
            out_n[i, 1] = nbest[1]
            out_n[i, 2] = nbest[2]


# ---------------------------------------------------------------- procedural texture


@njit(cache=True, inline="always")
def _hash2(ix, iy, seed):
    """2D integer lattice hash -> [0, 1) (one multiply round: cheap, good enough for texture)."""
    h = ((ix * 73856093) ^ (iy * 19349663) ^ (seed * 83492791)) & 0xFFFFFFFF
    h = ((h ^ (h >> 15)) * 0x2C1B3C6D) & 0xFFFFFFFF
    h = h ^ (h >> 13)
    return (h & 0xFFFFFF) / 16777216.0


@njit(cache=True, inline="always")
def _value_noise(x, y, seed):
    """Smooth 2D value noise in [0, 1) on a unit lattice (bilinear, smoothstep weights)."""
    fx = math.floor(x)
    fy = math.floor(y)
    ix = int(fx)
    iy = int(fy)
    tx = x - fx
    ty = y - fy
    tx = tx * tx * (3 - 2 * tx)
    ty = ty * ty * (3 - 2 * ty)
    a = _hash2(ix, iy, seed)
    b = _hash2(ix + 1, iy, seed)
    c = _hash2(ix, iy + 1, seed)
    d = _hash2(ix + 1, iy + 1, seed)
    return (a * (1 - tx) + b * tx) * (1 - ty) + (c * (1 - tx) + d * tx) * ty


@njit(cache=True, inline="always")
def _surface_uv(x, y, z, nx, ny, nz):
    """2D texture coordinates of a surface point: the plane most orthogonal to the normal."""
    ax = abs(nx)
    ay = abs(ny)
    az = abs(nz)
    if az >= ax and az >= ay:
        return x, y
    if ax >= ay:
        return y, z
    return x, z


@njit(cache=True)
def albedo(k, hx, hy, hz, nx, ny, nz, pcen, prot, mcol, mpat, mscale, mseed, out):
    """RGB albedo in [0, 1] of primitive k at world point (hx, hy, hz) with normal n.

    Patterns are computed from the hit point in the primitive's local frame (so stripes follow
    a yawed object); a two-octave grain of value noise on every surface adds photometric detail.
    """
    c = prot[k, 0]
    s = prot[k, 1]
    px = hx - pcen[k, 0]
    py = hy - pcen[k, 1]
    lz = hz - pcen[k, 2]
    lx = c * px + s * py
    ly = -s * px + c * py
    lnx = c * nx + s * ny
    lny = -s * nx + c * ny
    sc = mscale[k]
    seed = mseed[k]
    pat = mpat[k]
    u, v = _surface_uv(lx, ly, lz, lnx, lny, nz)
    m = 0.0
    if pat == 1:  # stripes along the surface (wallpaper / fabric / book spines)
        m = 0.5 + 0.5 * math.sin(2 * math.pi * (u + 0.35 * v) / sc)
        m = 1.0 if m > 0.55 else (0.0 if m < 0.45 else (m - 0.45) * 10.0)
    elif pat == 2:  # checker (floor / ceiling tiles), world aligned
        q = math.floor(hx / sc + 1e-9) + math.floor(hy / sc + 1e-9) + math.floor(hz / sc + 1e-9)
        m = 1.0 if (int(q) & 1) else 0.0
    elif pat == 3:  # blotchy noise
        m = _value_noise(u / sc, v / sc, seed)
        m = min(1.0, max(0.0, (m - 0.3) * 2.5))
    elif pat == 4:  # wood grain: warped stripes
        w = _value_noise(u / sc * 0.5, v / sc * 4.0, seed)
        m = 0.5 + 0.5 * math.sin(2 * math.pi * (v / sc * 3.0 + 2.0 * w))
    g = 0.6 * _value_noise(u * 9.0, v * 9.0, seed + 17) + 0.4 * _value_noise(u * 31.0, v * 31.0, seed + 29)
    f = 0.82 + 0.36 * g
    for ch in range(3):
        val = (mcol[k, 0, ch] * (1 - m) + mcol[k, 1, ch] * m) * f
        out[ch] = min(1.0, max(0.0, val))


@njit(cache=True, parallel=True)
def shade_kernel(pts, normals, prim, dirs, pcen, prot, mcol, mpat, mscale, mseed, lights, ambient, out):
    """Lambertian + ambient colour (N, 3) in [0, 1] of hit points; background black. The camera
    renderer's shading, point by point: its reference in tests/test_sim_scene.py."""
    n = pts.shape[0]
    for i in prange(n):
        k = prim[i]
        if k < 0:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0
            continue
        alb = np.empty(3)
        albedo(k, pts[i, 0], pts[i, 1], pts[i, 2], normals[i, 0], normals[i, 1], normals[i, 2], pcen, prot, mcol, mpat, mscale, mseed, alb)
        light = ambient
        for j in range(lights.shape[0]):
            d = normals[i, 0] * lights[j, 0] + normals[i, 1] * lights[j, 1] + normals[i, 2] * lights[j, 2]
            if d > 0:
                light += lights[j, 3] * d
        for ch in range(3):
            out[i, ch] = min(1.0, alb[ch] * light)


# ---------------------------------------------------------------- camera renderer


@njit(cache=True)
def _object_rects(R, t, fx, fy, cx, cy, w, h, olo, ohi, rects):
    """Conservative pixel rectangle [u0, u1, v0, v1] of each object's AABB; u0 > u1 = culled."""
    for o in range(olo.shape[0]):
        umin = 1e18
        umax = -1e18
        vmin = 1e18
        vmax = -1e18
        n_front = 0
        for corner in range(8):
            x = olo[o, 0] if (corner & 1) == 0 else ohi[o, 0]
            y = olo[o, 1] if (corner & 2) == 0 else ohi[o, 1]
            z = olo[o, 2] if (corner & 4) == 0 else ohi[o, 2]
            # world -> camera: R^T (p - t)
            qx = x - t[0]
            qy = y - t[1]
            qz = z - t[2]
            xc = R[0, 0] * qx + R[1, 0] * qy + R[2, 0] * qz
            yc = R[0, 1] * qx + R[1, 1] * qy + R[2, 1] * qz
            zc = R[0, 2] * qx + R[1, 2] * qy + R[2, 2] * qz
            if zc > 1e-6:
                n_front += 1
                u = fx * xc / zc + cx
                v = fy * yc / zc + cy
                umin = min(umin, u)
                umax = max(umax, u)
                vmin = min(vmin, v)
                vmax = max(vmax, v)
        if n_front == 0:
            rects[o, 0] = 1
            rects[o, 1] = 0
            rects[o, 2] = 1
            rects[o, 3] = 0
        elif n_front < 8:
            rects[o, 0] = 0
            rects[o, 1] = w - 1
            rects[o, 2] = 0
            rects[o, 3] = h - 1
        else:
            rects[o, 0] = max(0, int(math.floor(umin)) - 1)
            rects[o, 1] = min(w - 1, int(math.ceil(umax)) + 1)
            rects[o, 2] = max(0, int(math.floor(vmin)) - 1)
            rects[o, 3] = min(h - 1, int(math.ceil(vmax)) + 1)


@njit(cache=True, parallel=True)
def render_kernel(R, t, fx, fy, cx, cy, w, h, tile, tmax, olo, ohi, ostart, oend, ptype, pcen, phalf, prot,
                  mcol, mpat, mscale, mseed, lights, ambient, noise_amp, frame_seed,
                  out_rgb, out_z, out_cos, out_k):
    """Render one pinhole frame (OpenCV axes, cam-to-world rotation R (3, 3), position t (3,)).

    Per tile of `tile` x `tile` pixels only the objects whose projected AABB overlaps the tile
    are tested (exact: the projection of a box lies inside its corners' pixel rectangle).
    out_rgb (h, w, 3) uint8, out_z (h, w) z-depth m (inf = no hit), out_cos (h, w) cosine of
    the incidence angle, out_k (h, w) primitive index (-1 = none).
    """
    n_obj = olo.shape[0]
    rects = np.empty((n_obj, 4), dtype=np.int64)
    _object_rects(R, t, fx, fy, cx, cy, w, h, olo, ohi, rects)
    ntx = (w + tile - 1) // tile
    nty = (h + tile - 1) // tile
    for ti in prange(ntx * nty):
        tyi = ti // ntx
        txi = ti % ntx
        u0 = txi * tile
        v0 = tyi * tile
        u1 = min(w, u0 + tile) - 1
        v1 = min(h, v0 + tile) - 1
        # objects overlapping this tile
        sel = np.empty(n_obj, dtype=np.int64)
        ns = 0
        for o in range(n_obj):
            if rects[o, 0] <= u1 and rects[o, 1] >= u0 and rects[o, 2] <= v1 and rects[o, 3] >= v0:
                sel[ns] = o
                ns += 1
        slo = np.empty((ns, 3))
        shi = np.empty((ns, 3))
        sst = np.empty(ns, dtype=np.int64)
        sen = np.empty(ns, dtype=np.int64)
        for j in range(ns):
            o = sel[j]
            for a in range(3):
                slo[j, a] = olo[o, a]
                shi[j, a] = ohi[o, a]
            sst[j] = ostart[o]
            sen[j] = oend[o]
        nbuf = np.empty(3)
        nb = np.zeros(3)
        alb = np.empty(3)
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                xc = (u - cx) / fx
                yc = (v - cy) / fy
                inv = 1.0 / math.sqrt(xc * xc + yc * yc + 1.0)
                xc *= inv
                yc *= inv
                zc = inv
                dx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2] * zc
                dy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2] * zc
                dz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2] * zc
                tt, k = _first_hit(t[0], t[1], t[2], dx, dy, dz, tmax, slo, shi, sst, sen,
                                   ptype, pcen, phalf, prot, nbuf, nb)
                out_k[v, u] = k
                if k < 0:
                    out_z[v, u] = np.inf
                    out_cos[v, u] = 0.0
                    for ch in range(3):
                        out_rgb[v, u, ch] = 0
                    continue
                out_z[v, u] = tt * zc
                out_cos[v, u] = -(nb[0] * dx + nb[1] * dy + nb[2] * dz)
                hx = t[0] + tt * dx
                hy = t[1] + tt * dy
                hz = t[2] + tt * dz
                albedo(k, hx, hy, hz, nb[0], nb[1], nb[2], pcen, prot, mcol, mpat, mscale, mseed, alb)
                light = ambient
                for j in range(lights.shape[0]):
                    d = nb[0] * lights[j, 0] + nb[1] * lights[j, 1] + nb[2] * lights[j, 2]
                    if d > 0:
                        light += lights[j, 3] * d
                if noise_amp > 0:
                    nz = (_hash2(u, v, frame_seed) - 0.5) * 2 * noise_amp
                else:
                    nz = 0.0
                for ch in range(3):
                    val = alb[ch] * light + nz
                    val = min(1.0, max(0.0, val))
                    out_rgb[v, u, ch] = np.uint8(int(val * 255.0 + 0.5))


@njit(cache=True, inline="always")
def _hash3u(a, b, c):
    """Hash of three integers -> uniform in (0, 1) (never 0, safe for log)."""
    h = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) & 0xFFFFFFFF
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return ((h & 0xFFFFFF) + 0.5) / 16777216.0


@njit(cache=True, parallel=True)
def depth_kernel(z, cos_inc, coarse, blob, hole_level, sigma0, k, zmin, zmax, min_cos, edge_jump, edge_drop,
                 seed, out):
    """RGB-D measurement model per pixel (see sensors.DepthModel): z (H, W) exact z-depth m
    (inf = none) -> out (H, W) uint16 mm, 0 = invalid. Per-pixel randomness comes from a
    counter-based hash of (pixel, seed), so results do not depend on the thread count."""
    h, w = z.shape
    for v in prange(h):
        for u in range(w):
            zz = z[v, u]
            bad = not (zz >= zmin and zz <= zmax) or cos_inc[v, u] < min_cos
            # blob holes: bilinear upsampling of a coarse uniform field
            fy = v / blob
            fx = u / blob
            y0 = int(fy)
            x0 = int(fx)
            ty = fy - y0
            tx = fx - x0
            up = ((coarse[y0, x0] * (1 - tx) + coarse[y0, x0 + 1] * tx) * (1 - ty)
                  + (coarse[y0 + 1, x0] * (1 - tx) + coarse[y0 + 1, x0 + 1] * tx) * ty)
            if up < hole_level:
                bad = True
            if not bad:
                # depth discontinuity to a 4-neighbour
                lim = edge_jump * max(zz, 0.1)
                jump = False
                if u > 0 and not abs(z[v, u - 1] - zz) <= lim:
                    jump = True
                if u < w - 1 and not abs(z[v, u + 1] - zz) <= lim:
                    jump = True
                if v > 0 and not abs(z[v - 1, u] - zz) <= lim:
                    jump = True
                if v < h - 1 and not abs(z[v + 1, u] - zz) <= lim:
                    jump = True
                if jump and _hash3u(u, v, seed * 3 + 1) < edge_drop:
                    bad = True
            if bad:
                out[v, u] = 0
                continue
            r1 = _hash3u(u, v, seed * 3)
            r2 = _hash3u(v, u, seed * 3 + 2)
            g = math.sqrt(-2.0 * math.log(r1)) * math.cos(2 * math.pi * r2)
            mm = round((zz + (sigma0 + k * zz * zz) * g) * 1000.0)
            out[v, u] = np.uint16(min(65534.0, max(1.0, mm)))
