"""Where the sensors have looked: the mask that keeps a 2D map honest for a planner (issue 29).

A NeRF answers a density everywhere in its box, also where no camera, IRS or USS ray ever went:
its 360 deg scans from a camera position run through the sides the cameras never faced, and a
map made from them is free there, a fan that a planner would drive into. So a map pixel counts
as observed only if some frame's sensors looked at it:

- the camera's horizontal field of view (half-angle atan(W / 2 fx) around its optical axis
  projected on the floor) up to `reach` metres from the camera. The IRS (45 deg, 4 m) and the
  USS (55 deg, 8 m) look along the camera's axis (sensors/rig.py) inside that wedge, so the
  camera wedge is the union of all three. `reach` defaults to 12 m, the stereo stage's
  farthest triangulated point (stereo/depth.py `max_range`): beyond it no sensor of the robot
  gives metric evidence, only the NeRF's guess.

The pixels that hold a camera position count as observed as well (`with_camera_pixels`, the
maps' mask, not the grid's warm-up): the robot stood there. Every map pixel outside the mask is written unknown (trinary map; 255, served as -1, in the
probability map), NaN (ESDF, which is NaN wherever the trinary map is unknown). The share of the map's pixels inside the mask is reported as
the map's `observed` figure in snapshot.json and export.json.

The wedge test is exact per pixel centre; frames are first thinned to distinct (position
rounded to `resolution`, heading rounded to 1 deg) so a robot standing still costs one frame.
"""

from __future__ import annotations

import math

import numpy as np

OBSERVE_REACH_M = 12.0  # the stereo stage's max_range: the farthest metric evidence
WINDOW_PIXELS_PER_CHUNK = 1 << 22  # a view wedge's pixels tested at once (~150 MB of float64 temporaries)


def camera_half_fov(width: int, fx: float) -> float:
    """Horizontal half field of view (rad) of a pinhole camera `width` px wide with focal `fx` px."""
    return math.atan(width / (2.0 * fx))


def observed_mask(
    cam_to_world: np.ndarray, half_fov: np.ndarray, lo: np.ndarray, shape: tuple[int, int], resolution: float,
    reach: float = OBSERVE_REACH_M,
) -> np.ndarray:
    """(nx, ny) bool indexed [ix, iy]: pixel centres inside some frame's horizontal view wedge.

    cam_to_world (N, 4, 4) camera poses (OpenCV axes: z = optical axis); half_fov (N,) rad;
    lo (2,) world x, y of the raster's lower-left corner; shape (nx, ny) pixels of `resolution` m
    (one size, or (2,) sizes along x and y: the grid's near-cubic cells).
    A camera looking straight up or down (axis with no horizontal part) observes nothing.
    """
    nx, ny = int(shape[0]), int(shape[1])
    mask = np.zeros((nx, ny), dtype=bool)
    poses = np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4)
    half = np.broadcast_to(np.asarray(half_fov, dtype=np.float64), (len(poses),))
    if not len(poses):
        return mask
    pos = poses[:, :2, 3]  # (N, 2)
    axis = poses[:, :2, 2]  # (N, 2) optical axis on the floor
    norm = np.linalg.norm(axis, axis=1)
    keep = norm > 1e-6
    heading = np.arctan2(axis[:, 1], axis[:, 0])
    res = np.broadcast_to(np.asarray(resolution, dtype=np.float64), (2,))
    key = np.column_stack([np.round(pos / res), np.round(np.degrees(heading)), np.round(np.degrees(half), 1)])
    _, first = np.unique(key[keep], axis=0, return_index=True)
    lo = np.asarray(lo, dtype=np.float64)[:2]
    for k in np.flatnonzero(keep)[first]:
        i0, j0 = np.floor((pos[k] - reach - lo) / res).astype(int)
        i1, j1 = np.ceil((pos[k] + reach - lo) / res).astype(int)
        i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1, nx), min(j1, ny)
        if i0 >= i1 or j0 >= j1:
            continue
        dy = lo[1] + (np.arange(j0, j1) + 0.5) * res[1] - pos[k, 1]  # (h,)
        rows = max(1, WINDOW_PIXELS_PER_CHUNK // (j1 - j0))  # bounded memory at any resolution
        for a in range(i0, i1, rows):
            b = min(a + rows, i1)
            dx = lo[0] + (np.arange(a, b) + 0.5) * res[0] - pos[k, 0]  # (w,)
            d2 = dx[:, None] ** 2 + dy[None, :] ** 2
            # inside the wedge: angle to the axis <= half, i.e. cos >= cos(half) (half < 90 deg)
            along = (dx[:, None] * axis[k, 0] + dy[None, :] * axis[k, 1]) / norm[k]
            mask[a:b, j0:j1] |= (d2 <= reach * reach) & (along >= np.sqrt(d2) * math.cos(half[k]))
    return mask


def frames_observed(cam_to_world: np.ndarray, stack_ids: np.ndarray, intrinsics, lo: np.ndarray,
                    shape: tuple[int, int], resolution: float, reach: float = OBSERVE_REACH_M) -> np.ndarray:
    """`observed_mask` of frames (N, 4, 4) whose cameras are `intrinsics[stack_ids[k]]` (any
    resolution: the field of view is W / fx)."""
    half = np.array([camera_half_fov(intrinsics[int(s)].width, intrinsics[int(s)].fx) for s in stack_ids])
    return observed_mask(cam_to_world, half, lo, shape, resolution, reach)


def with_camera_pixels(mask_xy: np.ndarray, positions: np.ndarray, lo: np.ndarray, resolution) -> np.ndarray:
    """`mask_xy` (nx, ny) [ix, iy] with the pixels that hold a camera position ((N, 2+) m, world)
    observed too (`resolution`: one pixel size, or (2,) sizes along x and y: the grid's cells): the robot's body stood there, while a view wedge starts at the lens, so the
    centre of the camera's own pixel may lie just behind it (at a drive's start, before the robot
    moves, no wedge covers it and the planner's own start pixel would be unknown). The input is
    not changed."""
    from virus_nerf.maps.occupancy import world_pixels

    out = np.array(mask_xy, dtype=bool, copy=True)
    xy = np.asarray(positions, dtype=np.float64)[..., :2].reshape(-1, 2)
    ij, inside = world_pixels(xy, np.asarray(lo, dtype=np.float64)[:2], resolution, out.shape)
    out[ij[inside, 0], ij[inside, 1]] = True
    return out


def apply_mask(image: np.ndarray, mask_xy: np.ndarray, unobserved_value: int) -> np.ndarray:
    """A map image (H, W) (row 0 = largest y) with every pixel outside `mask_xy` [ix, iy] set to
    `unobserved_value`; the input is not changed."""
    from virus_nerf.maps.occupancy import to_image

    out = np.array(image, copy=True)
    out[~to_image(mask_xy)] = unobserved_value
    return out


def observed_share(mask_xy: np.ndarray) -> float:
    """Share of the map's pixels that some sensor observed (the map's confidence figure)."""
    return float(mask_xy.mean()) if mask_xy.size else 0.0
