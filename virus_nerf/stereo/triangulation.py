"""Points from rays of known cameras: multi-view triangulation with its uncertainty (pure numpy).

Every function works on many tracks at once. A track is a set of views of one 3D point; a view
is a camera centre c (3,), a world-frame unit ray d (3,) through the observed pixel, and the
camera's rotation and intrinsics for the reprojection. The point minimises the summed squared
distances to the view rays (the multi-view midpoint, closed form); its covariance is the inverse
of the reprojection information sum_v J_v^T J_v / sigma_px^2 (J_v the 2x3 Jacobian of the
pixel coordinates in view v), so a short baseline gives a long, thin ellipsoid along the rays.
"""

from __future__ import annotations

import numpy as np


def midpoint(track: np.ndarray, centres: np.ndarray, rays: np.ndarray, n_tracks: int) -> np.ndarray:
    """Least-squares intersection of each track's rays: track (V,) int ids in [0, n_tracks),
    centres (V, 3) m, rays (V, 3) unit -> points (n_tracks, 3); NaN where the rays are parallel
    (or the track has fewer than two views)."""
    proj = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # (V, 3, 3) I - d d^T
    a = np.zeros((n_tracks, 3, 3))
    b = np.zeros((n_tracks, 3))
    np.add.at(a, track, proj)
    np.add.at(b, track, np.einsum("vij,vj->vi", proj, centres))
    points = np.full((n_tracks, 3), np.nan)
    ok = np.linalg.cond(a) < 1e8  # parallel rays leave a singular normal matrix
    if ok.any():
        points[ok] = np.linalg.solve(a[ok], b[ok][:, :, None])[:, :, 0]
    return points


def project_views(points: np.ndarray, world_to_cam: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (V, 2) and camera-frame points (V, 3) of points (V, 3) in views with
    world_to_cam (V, 4, 4) and intrinsic matrices k (V, 3, 3)."""
    p_cam = np.einsum("vij,vj->vi", world_to_cam[:, :3, :3], points) + world_to_cam[:, :3, 3]
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([k[:, 0, 0] * p_cam[:, 0] / z + k[:, 0, 2], k[:, 1, 1] * p_cam[:, 1] / z + k[:, 1, 2]], axis=1)
    return uv, p_cam


def covariance(track: np.ndarray, points: np.ndarray, world_to_cam: np.ndarray, k: np.ndarray,
               sigma_px: float, n_tracks: int) -> np.ndarray:
    """(n_tracks, 3, 3) m^2 covariance of each point from its views' reprojection Jacobians with
    isotropic pixel noise sigma_px; inf where the information is singular."""
    _, p_cam = project_views(points[track], world_to_cam, k)
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    zero = np.zeros_like(z)
    j_cam = np.stack([
        np.stack([k[:, 0, 0] / z, zero, -k[:, 0, 0] * x / z**2], axis=1),
        np.stack([zero, k[:, 1, 1] / z, -k[:, 1, 1] * y / z**2], axis=1),
    ], axis=1)  # (V, 2, 3) d(u, v) / d(point in camera)
    j = j_cam @ world_to_cam[:, :3, :3]  # (V, 2, 3) d(u, v) / d(point in world)
    info = np.zeros((n_tracks, 3, 3))
    np.add.at(info, track, np.einsum("vai,vaj->vij", j, j) / sigma_px**2)
    cov = np.full((n_tracks, 3, 3), np.inf)
    ok = np.linalg.cond(info) < 1e12
    if ok.any():
        cov[ok] = np.linalg.inv(info[ok])
    return cov


def max_parallax_deg(track: np.ndarray, points: np.ndarray, centres: np.ndarray, n_tracks: int) -> np.ndarray:
    """(n_tracks,) largest angle (deg) between a track's viewing rays towards its point, taken
    against the ray of the track's first and of its last view (a lower bound of the pairwise
    maximum that equals it for views along a line)."""
    u = points[track] - centres
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    first = np.full(n_tracks, -1, dtype=np.int64)
    last = np.full(n_tracks, -1, dtype=np.int64)
    order = np.arange(len(track))
    np.maximum.at(last, track, order)
    first_rev = np.full(n_tracks, len(track), dtype=np.int64)
    np.minimum.at(first_rev, track, order)
    first = np.where(first_rev < len(track), first_rev, 0)
    last = np.maximum(last, 0)
    cos_first = np.clip(np.einsum("vi,vi->v", u, u[first[track]]), -1.0, 1.0)
    cos_last = np.clip(np.einsum("vi,vi->v", u, u[last[track]]), -1.0, 1.0)
    angle = np.degrees(np.arccos(np.minimum(cos_first, cos_last)))
    out = np.zeros(n_tracks)
    np.maximum.at(out, track, angle)
    return out
