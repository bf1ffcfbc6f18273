"""The slab test of a ray against an axis-aligned box, for numba kernels (inlined where called).

One definition for every kernel that clips a ray to a box: the grid's Depth-Update traversal
(grid/sensor_model.py) and the simulator's object bounding boxes (sim/kernels.py). The PyTorch
twin for batches of rays is `render.marching.ray_box_interval`.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def slab_clip(ox, oy, oz, dx, dy, dz, lo, hi, t0, t1, parallel_eps):  # pragma: no cover - compiled
    """Clip the parameter interval [t0, t1] of the ray o + t d to the box [lo, hi] (metres).

    An axis with |d| < parallel_eps is parallel: inside its slab for every t if lo <= o <= hi
    (faces included), else the ray misses. Returns (t0, t1); the ray misses where t1 < t0
    (a miss on a parallel axis returns (inf, -inf)).
    """
    for ax in range(3):
        o = ox if ax == 0 else (oy if ax == 1 else oz)
        d = dx if ax == 0 else (dy if ax == 1 else dz)
        if abs(d) < parallel_eps:
            if o < lo[ax] or o > hi[ax]:
                return float("inf"), float("-inf")
        else:
            ta = (lo[ax] - o) / d
            tb = (hi[ax] - o) / d
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0 = ta
            if tb < t1:
                t1 = tb
    return t0, t1
