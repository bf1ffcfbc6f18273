"""`virus-nerf export`: the trained model as a top-down occupancy map for ROS map_server.

From every camera position of the recording (subsampled) the model renders a 360 deg scan at
camera height (design 6.3); cells a scan ray passes are free evidence, its end cell is
occupied evidence. A cell is occupied where occupied hits outweigh passes, free where only
passes were seen, unknown where no ray came. Written as PGM (0 occupied, 254 free, 205
unknown) + YAML in the map_server convention (origin = world pose of the lower-left pixel).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

OCCUPIED, FREE, UNKNOWN = 0, 254, 205
MAX_PIXELS = 100_000_000  # a finer --resolution is refused (memory) before anything is computed


@dataclass
class OccupancyMap2D:
    image: np.ndarray  # (H, W) uint8, row 0 = largest y (image top)
    resolution: float  # metres per pixel
    origin: tuple[float, float]  # world (x, y) of the lower-left pixel corner


def scan_occupancy(
    origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution: float
) -> OccupancyMap2D:
    """Occupancy raster from 2D scan rays. origins (N, 2), directions (N, 2) unit, ranges (N,) m."""
    shape = np.ceil((hi - lo) / resolution).astype(int)  # (nx, ny)
    passes = np.zeros(shape, dtype=np.int64)
    hits = np.zeros(shape, dtype=np.int64)
    ok = np.isfinite(ranges) & (ranges > 0)
    o, d, r = origins[ok], directions[ok], ranges[ok]
    end = o + d * r[:, None]
    ij = np.floor((end - lo) / resolution).astype(int)
    inside = np.all((ij >= 0) & (ij < shape), axis=1)
    np.add.at(hits, (ij[inside, 0], ij[inside, 1]), 1)
    step = resolution / 2
    n_steps = np.floor(np.maximum(r - resolution, 0) / step).astype(int)
    ray = np.repeat(np.arange(len(r)), n_steps)
    t = (np.arange(n_steps.sum()) - np.repeat(np.cumsum(n_steps) - n_steps, n_steps)) * step
    pts = o[ray] + d[ray] * t[:, None]
    ij = np.floor((pts - lo) / resolution).astype(int)
    inside = np.all((ij >= 0) & (ij < shape), axis=1)
    np.add.at(passes, (ij[inside, 0], ij[inside, 1]), 1)
    img = np.full(shape, UNKNOWN, dtype=np.uint8)
    img[passes > 0] = FREE
    img[(hits > 0) & (hits >= 0.5 * passes)] = OCCUPIED
    # x along image columns, y up the image rows
    return OccupancyMap2D(image=np.flipud(img.T).copy(), resolution=resolution, origin=(float(lo[0]), float(lo[1])))


def write_map_server(m: OccupancyMap2D, folder: Path, name: str = "map") -> tuple[Path, Path]:
    """PGM (binary P5) + YAML, atomically."""
    from virus_nerf.utils.io import atomic_path, write_text_atomic

    h, w = m.image.shape
    pgm = folder / f"{name}.pgm"
    with atomic_path(pgm) as tmp:
        tmp.write_bytes(f"P5\n{w} {h}\n255\n".encode() + m.image.tobytes())
    yaml = folder / f"{name}.yaml"
    write_text_atomic(
        yaml,
        f"image: {name}.pgm\nresolution: {m.resolution}\norigin: [{m.origin[0]:.4f}, {m.origin[1]:.4f}, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
    )
    return pgm, yaml


def export(run: Path, out: Path, resolution: float = 0.05, n_rays: int = 720, max_poses: int = 60) -> None:
    """Export a trained run's 2D occupancy map for ROS map_server (PGM + YAML).

    Args:
        run: A run folder written by `virus-nerf train`.
        out: New folder for map.pgm, map.yaml and map.png (checked before anything is computed).
        resolution: Metres per map pixel (> 0).
        n_rays: Rays per 360 deg scan.
        max_poses: At most this many camera positions (evenly spread over the recording).
    """
    from virus_nerf.errors import OutputExistsError, require_int, require_number
    from virus_nerf.trainer.command import load_trained, open_run
    from virus_nerf.utils.io import new_output_dir

    require_number("--resolution", resolution, 0.0)
    require_int("--n-rays", n_rays, 1, 1_000_000)
    require_int("--max-poses", max_poses, 1)
    out = Path(out)
    if out.exists():
        raise OutputExistsError(out)  # before any work
    cfg, _ = open_run(run, "--run")
    with new_output_dir(out) as tmp:  # made (and checked writable) before anything is computed
        trainer, cfg, _ = load_trained(run, "--run", poses="odometry" if cfg.odometry_poses else "optimised")
        m = _render_map(trainer, resolution, n_rays, max_poses)
        write_map_server(m, tmp)
        from PIL import Image

        Image.fromarray(m.image).save(tmp / "map.png")
    print(f"wrote {out}/map.pgm + map.yaml ({m.image.shape[1]}x{m.image.shape[0]} px at {resolution} m)")


def _render_map(trainer, resolution: float, n_rays: int, max_poses: int) -> OccupancyMap2D:
    """360 deg model scans from up to `max_poses` camera positions -> occupancy raster."""
    from virus_nerf.errors import UsageError
    from virus_nerf.evaluation.scans import horizontal_directions

    recording = trainer.recording
    lo, hi = np.asarray(trainer.box.lo[:2]), np.asarray(trainer.box.hi[:2])
    nx, ny = np.ceil((hi - lo) / resolution).astype(int)
    if int(nx) * int(ny) > MAX_PIXELS:
        raise UsageError(f"--resolution {resolution}: the {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m scene would be "
                         f"a {nx}x{ny} px map; expected at most {MAX_PIXELS // 1_000_000} M px (a coarser resolution)")
    positions = np.concatenate([s.cam_to_world[:, :3, 3] for s in recording.stacks.values()])
    positions = positions[np.linspace(0, len(positions) - 1, min(max_poses, len(positions))).astype(int)]
    dirs = horizontal_directions(n_rays)
    origins_all, dirs_all, ranges_all = [], [], []
    for p in positions:
        origins = np.broadcast_to(p, dirs.shape).copy()
        ranges_all.append(trainer.model.ranges(origins, dirs))
        origins_all.append(origins[:, :2])
        dirs_all.append(dirs[:, :2])
    return scan_occupancy(np.concatenate(origins_all), np.concatenate(dirs_all), np.concatenate(ranges_all),
                          lo, hi, resolution)
