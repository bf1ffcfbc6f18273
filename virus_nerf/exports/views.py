"""What the trained model renders at poses: 360 deg scans, a dense surface cloud, images.

Poses are camera-to-world transforms in OpenCV camera axes (x right, y down, z forward), the
same as the recording's `poses/*cam*` files: a CSV with columns time,x,y,z,qx,qy,qz,qw (seconds,
metres, unit quaternion), read by the recording's own pose reader (every bad row named).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from virus_nerf.data.images import depth_to_mm


@dataclass
class PoseSet:
    """Camera poses at which to render; times in seconds, cam_to_world (N, 4, 4) in metres."""

    times: np.ndarray
    cam_to_world: np.ndarray
    source: str  # the CSV path, or "test split" for the recording's test poses

    def __len__(self) -> int:
        return len(self.times)

    def subsample(self, max_poses: int) -> PoseSet:
        """At most `max_poses`, evenly spread (first and last kept)."""
        if len(self) <= max_poses:
            return self
        keep = np.unique(np.linspace(0, len(self) - 1, max_poses).round().astype(int))
        return PoseSet(self.times[keep], self.cam_to_world[keep], self.source)

    def csv(self) -> str:
        """index,time,x,y,z,qx,qy,qz,qw lines (the poses as rendered)."""
        from virus_nerf.sensors.geometry import matrix_to_quat

        q = matrix_to_quat(self.cam_to_world[:, :3, :3])  # w >= 0, as the recording's pose files
        rows = ["index,time,x,y,z,qx,qy,qz,qw"]
        for i, (t, m) in enumerate(zip(self.times, self.cam_to_world, strict=True)):
            # time to the microsecond (a float64 epoch stamp holds no finer): 9 significant digits kept whole seconds only
            rows.append(f"{i},{t:.6f}," + ",".join(f"{v:.9g}" for v in (*m[:3, 3], *q[i])))
        return "\n".join(rows) + "\n"


def read_pose_csv(path: Path) -> PoseSet:
    """A user's pose CSV (time,x,y,z,qx,qy,qz,qw); bad files fail with file, row and field."""
    from virus_nerf.data.ethz import read_poses
    from virus_nerf.errors import DataFormatError

    times, poses = read_poses(Path(path))
    if len(times) == 0:
        raise DataFormatError(path, "no poses; expected at least one row time,x,y,z,qx,qy,qz,qw")
    return PoseSet(times, poses, str(path))


def recording_test_poses(recording) -> PoseSet:
    """The recording's evaluation test poses (camera 1 at the test frames, docs/method.md 6.1)."""
    from virus_nerf.evaluation.testpoints import make_test_points

    pts = make_test_points(recording)
    return PoseSet(np.array([p.time for p in pts]), np.array([p.pose1 for p in pts]).reshape(-1, 4, 4),
                   "test split")


@torch.no_grad()
def render_rays(model, origins: np.ndarray, directions: np.ndarray, chunk: int = 8192):
    """-> (depth (N,) metres along the ray, NaN where the model sees nothing, as
    `SceneModel.ranges`; rgb (N, 3) uint8, black where nothing is seen)."""
    from virus_nerf.render.compositing import scan_depth

    n = len(origins)
    depth, rgb = np.full(n, np.nan), np.zeros((n, 3), dtype=np.uint8)
    o_all = torch.as_tensor(np.asarray(origins, dtype=np.float32), device=model.device)
    d_all = torch.as_tensor(np.asarray(directions, dtype=np.float32), device=model.device)
    for s in range(0, n, chunk):
        out, _ = model.render(o_all[s : s + chunk], d_all[s : s + chunk], generator=None)
        depth[s : s + chunk] = scan_depth(out, model.min_opacity).double().cpu().numpy()
        rgb[s : s + chunk] = (out.rgb.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
    return depth, rgb


def scan_points(model, position: np.ndarray, n_rays: int) -> np.ndarray:
    """A 360 deg horizontal scan at `position` (3,) -> hit points (M, 3), world frame (docs/method.md 6.3)."""
    from virus_nerf.maps.scans import scan_ranges

    origins, dirs, r = scan_ranges(model, position, n_rays)
    ok = np.isfinite(r) & (r > 0)
    return origins[ok] + dirs[ok] * r[ok, None]


def observed_points(points: np.ndarray, seen: np.ndarray, lo: np.ndarray, resolution: float) -> np.ndarray:
    """(M,) bool: the points (M, 3+) whose x, y lie in an observed pixel of `seen` ((nx, ny) [ix,
    iy] over the raster from `lo` at `resolution`, Mapper.observed). A 360 deg scan also runs
    through the sides no camera faced, where the field holds what it was initialised to: every
    2D map calls that unknown, and a scan keeps no point there."""
    from virus_nerf.maps.occupancy import world_pixels

    ij, inside = world_pixels(np.asarray(points, dtype=np.float64)[:, :2], np.asarray(lo, dtype=np.float64)[:2],
                              resolution, seen.shape)
    keep = np.zeros(len(ij), dtype=bool)
    keep[inside] = seen[ij[inside, 0], ij[inside, 1]]
    return keep


def surface_cloud(model, recording, max_points: int, image_scale: float):
    """Dense surface points (M, 3) and colours (M, 3) uint8, M <= max_points.

    Why rendered depth from the training cameras and not occupied grid cells: the grid's cells
    are ~8 cm and include haze the marcher still samples, while the expected ray termination
    (depth / opacity where opacity >= min_opacity, exactly the scans' rule) lies on the surface
    the NeRF reconstructs, and only surfaces a camera saw are claimed. Pixels are taken on a
    regular stride over every training frame of every stack, the stride chosen so the total
    number of rays is at most `max_points` (frames are thinned if even one pixel each is too many).
    """
    from virus_nerf.sensors.camera import pixel_rays

    frames = [(s, i) for s in recording.stacks.values() for i in s.indices("train")]
    if not frames:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    if len(frames) > max_points:
        frames = [frames[k] for k in np.linspace(0, len(frames) - 1, max_points).round().astype(int)]
    per_frame = max_points // len(frames)
    origins, dirs = [], []
    for stack, i in frames:
        intr = stack.intrinsics.scaled(image_scale)
        stride = max(1, int(np.ceil(np.sqrt(intr.width * intr.height / per_frame))))
        v, u = np.mgrid[stride // 2 : intr.height : stride, stride // 2 : intr.width : stride]
        u, v = u.ravel()[:per_frame], v.ravel()[:per_frame]
        rays = pixel_rays(intr, stack.cam_to_world[i], u, v)
        origins.append(rays.origins)
        dirs.append(rays.directions)
    o, d = np.concatenate(origins), np.concatenate(dirs)
    depth, rgb = render_rays(model, o, d)
    ok = np.isfinite(depth) & (depth > 0)
    return (o[ok] + d[ok] * depth[ok, None]).astype(np.float32), rgb[ok]


def render_image(model, intr, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """-> colour (H, W, 3) uint8 and z-depth (H, W) uint16 millimetres, 0 = no hit (the
    recording's depth convention: z along the optical axis, not the ray length)."""
    from virus_nerf.sensors.camera import pixel_directions

    v, u = np.mgrid[0 : intr.height, 0 : intr.width]
    dirs_cam = pixel_directions(intr, u.ravel(), v.ravel())
    dirs = dirs_cam @ np.asarray(cam_to_world)[:3, :3].T
    origins = np.broadcast_to(np.asarray(cam_to_world)[:3, 3], dirs.shape).copy()
    depth, rgb = render_rays(model, origins, dirs)
    z = depth * dirs_cam[:, 2]
    return rgb.reshape(intr.height, intr.width, 3), depth_to_mm(z).reshape(intr.height, intr.width)
