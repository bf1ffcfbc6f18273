"""Test oracle for the simulator's numba ray caster: exact casting in plain numpy, vectorised
over rays x primitives. Lives with the tests: the package never needs it."""

from __future__ import annotations

import numpy as np

from virus_nerf.sim.kernels import EPS, T_MIN
from virus_nerf.sim.scene import Scene


def cast_reference(scene: Scene, origins: np.ndarray, dirs: np.ndarray, max_range: float = np.inf,
                   chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pure-numpy exact casting, vectorised over rays x primitives (chunked): the test oracle
    for the numba kernel. Returns t (N,) inf = no hit, normal (N, 3), prim_id (N,)."""
    pk = scene.packed
    o_all = np.asarray(origins, dtype=np.float64)
    d_all = np.asarray(dirs, dtype=np.float64)
    n = o_all.shape[0]
    t_out = np.full(n, np.inf)
    n_out = np.zeros((n, 3))
    k_out = np.full(n, -1, dtype=np.int64)
    c, s = pk.prot[:, 0], pk.prot[:, 1]  # (P,)
    box = pk.ptype == 0
    h = pk.phalf  # (P, 3)
    for st in range(0, n, chunk):
        o = o_all[st:st + chunk, None, :] - pk.pcen[None]  # (n, P, 3)
        d = np.broadcast_to(d_all[st:st + chunk, None, :], o.shape)
        lo = np.stack([c * o[..., 0] + s * o[..., 1], -s * o[..., 0] + c * o[..., 1], o[..., 2]], -1)
        ld = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            # boxes: slab test
            ta = (-h[None] - lo) / ld
            tb = (h[None] - lo) / ld
            par = np.abs(ld) < EPS
            inside_slab = np.abs(lo) <= h[None]
            ta = np.where(par, np.where(inside_slab, -np.inf, np.inf), ta)
            tb = np.where(par, np.where(inside_slab, np.inf, -np.inf), tb)
            tn, tf = np.minimum(ta, tb), np.maximum(ta, tb)
            t_enter = tn.max(-1)
            axis = tn.argmax(-1)
            t_box = np.where((t_enter <= tf.min(-1)) & (t_enter >= T_MIN), t_enter, np.inf)
            ld_ax = np.take_along_axis(ld, axis[..., None], -1)[..., 0]
            nb = np.zeros(lo.shape)
            np.put_along_axis(nb, axis[..., None], -np.sign(ld_ax)[..., None], -1)
            # cylinders: side and caps
            r = h[None, :, 0]
            hz = h[None, :, 2]
            a2 = ld[..., 0] ** 2 + ld[..., 1] ** 2
            b = lo[..., 0] * ld[..., 0] + lo[..., 1] * ld[..., 1]
            cc = lo[..., 0] ** 2 + lo[..., 1] ** 2 - r ** 2
            disc = b * b - a2 * cc
            ts = (-b - np.sqrt(np.maximum(disc, 0))) / a2
            zs = lo[..., 2] + ts * ld[..., 2]
            ok_s = (a2 > EPS) & (disc >= 0) & (cc > 0) & (ts >= T_MIN) & (np.abs(zs) <= hz)
            t_side = np.where(ok_s, ts, np.inf)
            zc = np.where(ld[..., 2] < 0, hz, -hz)
            outside_z = np.where(ld[..., 2] < 0, lo[..., 2] > hz, lo[..., 2] < -hz)
            tc = (zc - lo[..., 2]) / ld[..., 2]
            xc = lo[..., 0] + tc * ld[..., 0]
            yc = lo[..., 1] + tc * ld[..., 1]
            ok_c = (np.abs(ld[..., 2]) > EPS) & outside_z & (tc >= T_MIN) & (xc**2 + yc**2 <= r**2)
            t_cap = np.where(ok_c, tc, np.inf)
            t_cyl = np.minimum(t_side, t_cap)
            p_side = lo + ts[..., None] * ld
            n_side = np.stack([p_side[..., 0] / r, p_side[..., 1] / r, np.zeros_like(r * ts)], -1)
            n_cap = np.stack([np.zeros_like(tc), np.zeros_like(tc), np.where(ld[..., 2] < 0, 1.0, -1.0)], -1)
            nc = np.where((t_cap < t_side)[..., None], n_cap, n_side)
        t_all = np.where(box[None], t_box, t_cyl)
        nl = np.where(box[None, :, None], nb, nc)
        t_all = np.where(t_all <= max_range, t_all, np.inf)
        k = t_all.argmin(-1)
        tk = t_all[np.arange(len(k)), k]
        nlk = nl[np.arange(len(k)), k]
        ck, sk = c[k], s[k]
        nw = np.stack([ck * nlk[:, 0] - sk * nlk[:, 1], sk * nlk[:, 0] + ck * nlk[:, 1], nlk[:, 2]], -1)
        hit = np.isfinite(tk)
        t_out[st:st + chunk] = tk
        n_out[st:st + chunk] = np.where(hit[:, None], nw, 0.0)
        k_out[st:st + chunk] = np.where(hit, k, -1)
    return t_out, n_out, k_out
