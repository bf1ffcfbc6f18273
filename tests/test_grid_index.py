"""The one cell-index formula (docs/method.md 9.5): torch `cell_index` and numba `cell_index_scalar` agree."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from virus_nerf.grid.base import GridSpec, cell_index, cell_index_scalar
from virus_nerf.scene_box import SceneBox

BOX = SceneBox((-4.5, -4.1, -0.3), (4.7, 3.9, 2.6))  # anisotropic, off-centre, odd sizes


@numba.njit
def _numba_indices(p, lo, size, res):
    out = np.empty(p.shape[0], np.int64)
    for i in range(p.shape[0]):
        out[i] = cell_index_scalar(p[i, 0], p[i, 1], p[i, 2], lo, size, res)
    return out


def _numba(points: np.ndarray, spec: GridSpec) -> np.ndarray:
    return _numba_indices(
        points.astype(np.float64),
        np.asarray(spec.box.lo, dtype=np.float64),
        np.asarray(spec.box.size, dtype=np.float64),
        np.asarray(spec.resolution, dtype=np.int64),
    )


def _torch(points: np.ndarray, spec: GridSpec) -> np.ndarray:
    return cell_index(torch.from_numpy(points.astype(np.float64)), spec).numpy()


@pytest.mark.parametrize("max_res", [7, 64, 128])
def test_torch_and_numba_agree_on_random_border_and_face_points(max_res):
    spec = GridSpec.from_box(BOX, max_res)
    rng = np.random.default_rng(max_res)
    res = np.asarray(spec.resolution)
    lo = np.asarray(BOX.lo)
    uniform = lo + rng.random((20000, 3)) * BOX.size
    # exact cell borders (including both box faces), some nudged by +-1e-12 m
    ijk = rng.integers(0, res + 1, size=(20000, 3))
    borders = lo + ijk * spec.cell_size
    borders += rng.choice([-1e-12, 0.0, 1e-12], size=borders.shape)
    faces = np.concatenate([np.broadcast_to(lo, (1, 3)), np.broadcast_to(BOX.hi, (1, 3))])
    outside = lo + (rng.random((2000, 3)) * 3 - 1) * BOX.size
    pts = np.concatenate([uniform, borders, faces, outside])
    a, b = _torch(pts, spec), _numba(pts, spec)
    np.testing.assert_array_equal(a, b)
    # exactly one of both sides of a border is -1 only at the box faces
    assert (a >= -1).all() and (a < spec.n_cells).all()


def test_float32_points_agree_when_cast_to_float64_on_both_sides():
    """The marcher and grids call both twins with float64 points: float32 inputs are exact there."""
    spec = GridSpec.from_box(BOX, 128)
    rng = np.random.default_rng(1)
    ijk = rng.integers(0, np.asarray(spec.resolution) + 1, size=(20000, 3))
    pts = (np.asarray(BOX.lo) + ijk * spec.cell_size).astype(np.float32)
    np.testing.assert_array_equal(_torch(pts, spec), _numba(pts, spec))


def test_points_outside_give_minus_one_and_hi_face_is_outside():
    spec = GridSpec.from_box(BOX, 32)
    lo, hi = np.asarray(BOX.lo), np.asarray(BOX.hi)
    c = BOX.center
    pts = []
    for axis in range(3):
        for v in (lo[axis] - 1e-6, hi[axis], hi[axis] + 0.5, lo[axis] - 10.0):
            p = c.copy()
            p[axis] = v
            pts.append(p)
    pts = np.asarray(pts)
    np.testing.assert_array_equal(_torch(pts, spec), -1)
    np.testing.assert_array_equal(_numba(pts, spec), -1)
    # the lo corner is cell 0, the cell just inside the hi corner is the last cell
    inner = np.stack([lo, hi - 1e-9])
    np.testing.assert_array_equal(_torch(inner, spec), [0, spec.n_cells - 1])
    np.testing.assert_array_equal(_numba(inner, spec), [0, spec.n_cells - 1])


def test_cell_centres_round_trip_and_flat_order():
    spec = GridSpec.from_box(BOX, 48)
    centres = spec.cell_centers()  # (n, 3) float32
    expect = np.arange(spec.n_cells)
    np.testing.assert_array_equal(cell_index(centres, spec).numpy(), expect)
    np.testing.assert_array_equal(_numba(centres.numpy(), spec), expect)
    # flat = (ix * ry + iy) * rz + iz: stepping one cell in z adds 1, in y adds rz, in x ry * rz
    _, ry, rz = spec.resolution
    cs = spec.cell_size
    p0 = centres[0].numpy().astype(np.float64)
    steps = np.stack([p0, p0 + [0, 0, cs[2]], p0 + [0, cs[1], 0], p0 + [cs[0], 0, 0]])
    np.testing.assert_array_equal(_torch(steps, spec), [0, 1, rz, ry * rz])
