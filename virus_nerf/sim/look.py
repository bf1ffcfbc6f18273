"""Pictures of a simulated room for a person: a top-down view with the drive loop (docs/method.md 5)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.sim.scene import Scene
from virus_nerf.sim.trajectory import DrivePath, DriveSpec


def top_down_image(scene: Scene, resolution: float = 0.02) -> np.ndarray:
    """(H, W, 3) uint8 orthographic view from just below the ceiling, looking down; row 0 is
    the largest y (left wall), column 0 the smallest x (back wall). Surfaces are shaded by
    their height so tables and cupboards stand out from the floor."""
    lo, hi = np.array(scene.extent_lo), np.array(scene.extent_hi)
    xs = np.arange(lo[0] + resolution / 2, hi[0], resolution)
    ys = np.arange(hi[1] - resolution / 2, lo[1], -resolution)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    o = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, hi[2] - 0.01)], 1)
    d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
    res = scene.cast(o, d)
    pts = o + d * np.where(np.isfinite(res.t), res.t, 0.0)[:, None]
    alb = scene.albedo_at(pts, res.prim_id)
    height = np.clip((pts[:, 2] - lo[2]) / max(hi[2] - lo[2], 1e-6), 0, 1)
    rgb = alb * (0.55 + 0.45 * height[:, None])
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(gx.shape + (3,))


def save_top_down(scene: Scene, path: str | Path, drive: DriveSpec | None = None, resolution: float = 0.02) -> None:
    """Write the top-down view as PNG with axes in metres and, if given, the drive loop."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = top_down_image(scene, resolution)
    lo, hi = scene.extent_lo, scene.extent_hi
    fig, ax = plt.subplots(figsize=(8, 8 * (hi[1] - lo[1]) / (hi[0] - lo[0]) + 0.6))
    ax.imshow(img, extent=(lo[0], hi[0], lo[1], hi[1]))
    if drive is not None:
        p = DrivePath(drive).points
        ax.plot(p[:, 0], p[:, 1], "c-", lw=1.5, label="drive loop")
        ax.plot([0], [0], "r^", ms=10, label="start (world origin)")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{scene.name}: top-down view")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
