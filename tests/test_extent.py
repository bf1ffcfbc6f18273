"""A map whose extent is not known in advance (issue 29, item 2; grid/extent.py): the box starts
around the first frame and grows by whole cells, every cell keeping its place and value, and the
field's frame never moves. Hand-computed cases, then a Mapper on a simulated drive."""

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
    field_config_for_frame,
    field_frame,
    first_box,
    needed_box,
)
from virus_nerf.grid.ngp import NgpGrid
from virus_nerf.grid.virus import VirusGrid, VirusGridConfig
from virus_nerf.scene_box import SceneBox

EXT = ExtentConfig(mode="grow", reach_m=2.0, height_m=1.0, grow_step_m=1.0, grid_cell_m=0.5, frame_m=20.0)


def test_first_box_is_the_reach_around_the_first_camera_in_whole_cells():
    box = first_box(np.array([1.0, 2.0, 0.5]), EXT)
    np.testing.assert_allclose(box.lo, (-1.0, 0.0, -0.5))
    np.testing.assert_allclose(box.hi, (3.0, 4.0, 1.5))
    assert GridSpec.from_cell(box, 0.5).resolution == (8, 8, 4)
    frame = field_frame(box, EXT)
    np.testing.assert_allclose(frame.lo, (-9.0, -8.0, -9.5))
    from virus_nerf.field.field import FieldConfig

    cfg = field_config_for_frame(FieldConfig(), ExtentConfig(mode="grow"))  # 64 m cube, 0.6 m .. 2 cm cells
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


def test_a_mapper_in_grow_mode_grows_as_it_drives_and_refuses_a_frame_outside_its_frame(tiny_office):
    from helpers import tiny_train_config

    from virus_nerf.data.ethz import load_recording
    from virus_nerf.engine.mapper import Mapper

    rec = load_recording(tiny_office, "office")
    cfg = tiny_train_config(extent=ExtentConfig(mode="grow", reach_m=1.0, grow_step_m=0.5, frame_m=30.0))
    mapper = Mapper.for_recording(rec, cfg)
    order = rec.frame_order(("train",))
    first = rec.stacks[order[0][0]].cam_to_world[order[0][1], :3, 3]
    np.testing.assert_allclose(mapper.box.center[:2], first[:2], atol=0.08)
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
    assert (positions[:, :2] - 1.0 >= lo[:2] - 1e-9).all() and (positions[:, :2] + 1.0 <= hi[:2] + 1e-9).all()
    assert tuple(mapper.grid.spec.resolution[:2]) == tuple(np.rint((hi - lo)[:2] / 0.08).astype(int))
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
        mapper.add_frame(dataclasses.replace(far, cam_to_world=pose))
