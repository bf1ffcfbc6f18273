"""A map whose extent is not known in advance (issue 29, item 2; grid/extent.py): the box starts
around the first frame and grows by whole cells (to hold what the robot sensed, or the reach
around every camera), every cell keeping its place and value, and the field's frame never moves.
Hand-computed cases, then a Mapper on a simulated drive."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from virus_nerf.errors import UsageError
from virus_nerf.grid.base import GridSpec
from virus_nerf.grid.extent import (
    ExtentConfig,
    SensedSupport,
    camera_margin_m,
    field_config_for_frame,
    field_frame,
    first_box,
    fitted_field_frame,
    grows_from_sensors,
    holding_box,
    needed_box,
)
from virus_nerf.grid.ngp import NgpGrid
from virus_nerf.grid.virus import VirusGrid, VirusGridConfig
from virus_nerf.scene_box import SceneBox

EXT = ExtentConfig(mode="grow", reach_m=2.0, height_m=1.0, grow_step_m=1.0, grid_cell_m=0.5, frame_m=20.0)


def test_a_fitted_box_normalises_the_field_per_axis_or_over_its_cube():
    box = SceneBox((1.0, -2.0, 0.0), (9.0, 2.0, 3.0))  # 8 x 4 x 3 m
    assert fitted_field_frame(box, ExtentConfig(fitted_frame="box")) == box
    cube = fitted_field_frame(box, ExtentConfig())  # the default (D58)
    # the same centre (5, 0, 1.5), 8 m on every side
    assert cube == SceneBox((1.0, -4.0, -2.5), (9.0, 4.0, 5.5))
    # the mapper's extent: the grid keeps the box, the field takes the cube
    from virus_nerf.engine.extent import MapExtent

    extent = MapExtent(ExtentConfig(), ("camera",), box)
    assert extent.box == box and extent.frame == cube and extent.grid_spec() is None
    with pytest.raises(ValueError, match="extent.fitted_frame 'ball'"):
        ExtentConfig(fitted_frame="ball")


def test_first_box_is_the_reach_around_the_first_camera_in_whole_cells():
    box = first_box(np.array([1.0, 2.0, 0.5]), EXT)  # no sensors named: the reach
    np.testing.assert_allclose(box.lo, (-1.0, 0.0, -0.5))
    np.testing.assert_allclose(box.hi, (3.0, 4.0, 1.5))
    assert GridSpec.from_cell(box, 0.5).resolution == (8, 8, 4)
    frame = field_frame(box, EXT)
    np.testing.assert_allclose(frame.lo, (-9.0, -8.0, -9.5))
    from virus_nerf.field.field import FieldConfig

    cfg = field_config_for_frame(FieldConfig(), ExtentConfig(mode="grow"))  # 64 m cube, 1.14 m .. 3.6 cm cells
    assert (cfg.base_resolution, cfg.max_resolution) == (56, 1778)  # round(64 / 1.14), round(64 / 0.036)
    office = ExtentConfig(mode="grow", field_coarse_m=0.6, field_fine_m=0.02)  # the sizes before D46
    cfg = field_config_for_frame(FieldConfig(), office)
    assert (cfg.base_resolution, cfg.max_resolution) == (107, 3200)


def test_the_box_grows_by_whole_cells_and_at_least_the_step_and_stops_at_the_frame():
    box = first_box(np.array([1.0, 2.0, 0.5]), EXT)  # x -1..3, y 0..4
    frame = field_frame(box, EXT)  # x -9..11
    assert needed_box(box, np.array([1.0, 2.0, 0.5]), EXT, frame) is None  # reach 2 m fits
    grown = needed_box(box, np.array([0.7, 2.0, 0.5]), EXT, frame)  # short by 0.3 m on -x: grows 1 m (2 cells)
    np.testing.assert_allclose(grown.lo, (-2.0, 0.0, -0.5))
    np.testing.assert_allclose(grown.hi, (3.0, 4.0, 1.5))
    far = needed_box(box, np.array([4.6, 2.0, 0.5]), EXT, frame)  # short by 3.6 m on +x: 8 cells (4 m)
    np.testing.assert_allclose(far.hi, (7.0, 4.0, 1.5))
    edge = needed_box(box, np.array([10.0, 2.0, 0.5]), EXT, frame)  # wants x up to 12: the frame ends at 11
    np.testing.assert_allclose(edge.hi, (11.0, 4.0, 1.5))
    # an interval: each short side by whole cells, at least the step; a side already holding it stays
    both = holding_box(box, np.array([-1.2, 0.5]), np.array([3.7, 4.0]), EXT, frame)
    np.testing.assert_allclose(both.lo, (-2.0, 0.0, -0.5))  # short 0.2 m: the 1 m step
    np.testing.assert_allclose(both.hi, (4.0, 4.0, 1.5))  # short 0.7 m: the 1 m step
    assert holding_box(box, np.array([-1.0, 0.0]), np.array([3.0, 4.0]), EXT, frame) is None


def test_sensed_growth_needs_the_stereo_sensor_and_starts_from_the_margin():
    ext = dataclasses.replace(EXT, grow_from="sensed", margin_m=0.3)
    assert grows_from_sensors(ext, ("camera", "irs", "stereo"))
    assert not grows_from_sensors(ext, ("camera", "uss", "irs"))  # the IRS alone: the reach
    assert not grows_from_sensors(dataclasses.replace(ext, grow_from="reach"), ("camera", "stereo"))
    assert camera_margin_m(ext, ("stereo",)) == 0.3 and camera_margin_m(ext, ("irs",)) == 2.0
    box = first_box(np.array([1.0, 2.0, 0.5]), ext, ("camera", "stereo"))  # +-0.3 m: 2 cells of 0.5 m
    np.testing.assert_allclose(box.lo, (0.5, 1.5, -0.5))
    np.testing.assert_allclose(box.hi, (1.5, 2.5, 1.5))
    with pytest.raises(ValueError, match="grow_from"):
        ExtentConfig(grow_from="map")
    with pytest.raises(ValueError, match="support_points"):
        ExtentConfig(support_points=0)


def test_the_support_counts_points_per_cell_and_bounds_the_cells_with_enough():
    ext = ExtentConfig(mode="grow", grow_from="sensed", support_cell_m=0.5, support_points=2)
    frame = SceneBox((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0))  # 8 x 8 support cells
    sup = SensedSupport(ext, frame, (-0.5, 0.5))
    assert sup.counts.shape == (8, 8) and sup.bounds() is None
    assert not sup.add(np.array([[0.1, 0.1, 0.0]]))  # one point: its cell (4, 4) is not supported yet
    assert sup.add(np.array([[0.2, 0.3, 0.0], [1.7, -1.9, 0.0]]))  # (4, 4) has 2; (7, 0) has 1
    lo, hi = sup.bounds()
    np.testing.assert_allclose(lo, (0.0, 0.0))
    np.testing.assert_allclose(hi, (0.5, 0.5))
    # outside the height, outside the frame, not finite: not counted
    assert not sup.add(np.array([[1.8, -1.8, 0.9], [2.5, 0.0, 0.0], [np.nan, 0.0, 0.0]]))
    assert sup.counts.sum() == 3
    assert sup.add(np.array([[1.9, -1.6, 0.0]]))  # (7, 0) has 2: the bounds reach it
    lo, hi = sup.bounds()
    np.testing.assert_allclose(lo, (0.0, -2.0))
    np.testing.assert_allclose(hi, (2.0, 0.5))
    assert not sup.add(np.array([[0.3, 0.3, 0.0]]))  # inside the bounds: nothing grows


@pytest.mark.parametrize("kind", ["virus", "ngp"])
def test_growing_keeps_every_cell_and_fills_new_ones_as_untouched(kind):
    box = SceneBox((0.0, 0.0, 0.0), (1.0, 1.5, 0.5))
    spec = GridSpec.from_cell(box, 0.5)
    assert spec.resolution == (2, 3, 1)
    grid = VirusGrid(spec, VirusGridConfig()) if kind == "virus" else NgpGrid(spec)
    if kind == "virus":
        grid._logodds = torch.arange(6, dtype=torch.float32).reshape(2, 3, 1)
    else:
        grid.values = torch.arange(6, dtype=torch.float32).reshape(2, 3, 1)
        grid._occupied = grid.values > 2.5
    before = grid.occupied.clone()
    grid.grow(SceneBox((-1.0, 0.0, 0.0), (1.0, 2.5, 0.5)))  # 2 cells on -x, 2 on +y
    assert grid.spec.resolution == (4, 5, 1)
    values = grid.logodds if kind == "virus" else grid.values
    np.testing.assert_array_equal(values[2:4, 0:3, 0].numpy(), np.arange(6).reshape(2, 3))
    np.testing.assert_array_equal(grid.occupied[2:4, 0:3].numpy(), before.numpy())
    new = np.ones((4, 5), dtype=bool)
    new[2:4, 0:3] = False
    if kind == "virus":  # a cell nothing updated: p_init, occupied (the warm-up has not started)
        assert (values[..., 0].numpy()[new] == VirusGridConfig().logodds_init).all()
    else:  # density 0, occupied until an update evaluates it
        assert (values[..., 0].numpy()[new] == 0).all()
    assert grid.occupied[..., 0].numpy()[new].all()
    # the cell index of a point is the same cell as before
    from virus_nerf.grid.base import cell_index

    p = torch.tensor([[0.7, 1.2, 0.2]])
    assert int(cell_index(p, grid.spec)) == (3 * 5 + 2) * 1 + 0
    with pytest.raises(ValueError, match="does not contain"):
        grid.spec.grown(SceneBox((0.0, 0.0, 0.0), (1.0, 1.0, 0.5)))


@pytest.mark.parametrize("grow_from", ["reach", "sensed"])
def test_a_mapper_in_grow_mode_grows_as_it_drives_and_refuses_a_frame_outside_its_frame(tiny_office, grow_from):
    from helpers import tiny_train_config

    from virus_nerf.data.ethz import load_recording
    from virus_nerf.engine.mapper import Mapper
    from virus_nerf.sampler.sensor_rays import irs_zone_rays

    rec = load_recording(tiny_office, "office")
    ext = ExtentConfig(mode="grow", grow_from=grow_from, reach_m=1.0, grow_step_m=0.5, frame_m=30.0)
    cfg = tiny_train_config(extent=ext)
    assert "irs" in cfg.sensors and "stereo" in cfg.sensors
    mapper = Mapper.for_recording(rec, cfg)
    order = rec.frame_order(("train",))
    first = rec.stacks[order[0][0]].cam_to_world[order[0][1], :3, 3]
    np.testing.assert_allclose(mapper.box.center[:2], first[:2], atol=ext.grid_cell_m)
    frame_before = (mapper.frame.lo, mapper.frame.hi)
    positions = []
    for s, i in order:
        frame = rec.stacks[s].frame(i)
        mapper.add_frame(frame)
        positions.append(frame.cam_to_world[:3, 3])
        if len(positions) == 4:
            mapper.train(60.0, steps=2)
    positions = np.array(positions)
    lo, hi = np.asarray(mapper.box.lo), np.asarray(mapper.box.hi)
    m = 1.0 if grow_from == "reach" else ext.margin_m
    assert (positions[:, :2] - m >= lo[:2] - 1e-9).all() and (positions[:, :2] + m <= hi[:2] + 1e-9).all()
    if grow_from == "sensed":  # every supported IRS return and stereo point lies inside, margin_m from the sides
        rays = irs_zone_rays(mapper.store, np.arange(mapper.frames), 1).valid()
        pts = (rays.origins + rays.directions * rays.ranges[:, None]).double().numpy()
        if mapper.stereo is not None:
            pts = np.concatenate([pts, np.asarray(mapper.stereo.points, dtype=np.float64)])
        sup = SensedSupport(ext, mapper.frame, (lo[2], hi[2]))
        assert sup.add(pts)
        s_lo, s_hi = sup.bounds()
        assert (s_lo - ext.margin_m >= lo[:2] - 1e-9).all() and (s_hi + ext.margin_m <= hi[:2] + 1e-9).all()
        # the box is no larger than that (plus less than one grow step a side) nor than the reach
        want_lo = np.minimum(s_lo - ext.margin_m, positions[:, :2].min(axis=0) - m)
        want_hi = np.maximum(s_hi + ext.margin_m, positions[:, :2].max(axis=0) + m)
        assert (lo[:2] > want_lo - ext.grow_step_m - 1e-9).all() and (hi[:2] < want_hi + ext.grow_step_m + 1e-9).all()
    assert tuple(mapper.grid.spec.resolution[:2]) == tuple(np.rint((hi - lo)[:2] / ext.grid_cell_m).astype(int))
    assert (mapper.frame.lo, mapper.frame.hi) == frame_before
    mapper.train(60.0, steps=2)
    assert mapper.step == 4 and math.isfinite(mapper.last_loss)
    # a resumed mapper grows to the saved box before it loads the grid
    state = mapper.state()
    again = Mapper.for_recording(rec, cfg)
    again.load_state(state)
    assert again.box == mapper.box and torch.equal(again.grid.logodds, mapper.grid.logodds)
    far = rec.stacks[order[0][0]].frame(order[0][1])
    pose = far.cam_to_world.copy()
    pose[0, 3] += 100.0
    with pytest.raises(UsageError, match="outside the map's frame"):
        mapper.add_frame(dataclasses.replace(far, cam_to_world=pose, time=float(mapper.store.times.max()) + 1.0))
