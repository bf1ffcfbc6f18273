"""Mapping while driving (issue 12): the Mapper on frames added one by one, its snapshots, its
input checks, the real-time replay and `map-bag`."""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_cli, tiny_train_config

from virus_nerf.data.ethz import load_recording
from virus_nerf.data.frame import SyncFrame
from virus_nerf.engine.config import MarchConfig
from virus_nerf.engine.mapper import Mapper
from virus_nerf.errors import OutputExistsError, UsageError
from virus_nerf.grid.virus import VirusGridConfig
from virus_nerf.sampler.frames import FrameStore
from virus_nerf.scene_box import SceneBox
from virus_nerf.sensors.camera import Intrinsics

INTR = Intrinsics(fx=20.0, fy=20.0, cx=16.0, cy=12.0, width=32, height=24)
BOX = SceneBox((-3.0, -3.0, -1.0), (3.0, 3.0, 2.0))


def _frame(t: float = 0.0, stack: int = 1, **changes) -> SyncFrame:
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]]  # looking along +x, level
    pose[:3, 3] = (0.1 * t, 0.0, 0.5)
    rgb = np.full((INTR.height, INTR.width, 3), 120, dtype=np.uint8)
    base = SyncFrame(time=t, stack_id=stack, rgb=rgb, cam_to_world=pose, uss_range=1.5,
                     irs_range=np.full((8, 8), 2.0))
    return dataclasses.replace(base, **changes)


def _mapper(**changes) -> Mapper:
    return Mapper(tiny_train_config(**changes), {1: INTR, 3: INTR}, BOX)


def test_frame_store_grows_without_losing_frames():
    store = FrameStore.empty({1: INTR, 3: INTR})
    images = []
    for k in range(40):  # past several reallocations (capacity 16, 34, 70)
        img = np.full((INTR.height, INTR.width, 3), k, dtype=np.uint8)
        images.append(img)
        assert store.append(1 + 2 * (k % 2), k, float(k), np.eye(4), img, None, float(k), np.full((8, 8), k)) == k
    assert len(store) == 40 and store.images.shape == (40, INTR.height, INTR.width, 3)
    assert np.array_equal(store.images, np.stack(images))
    assert np.array_equal(store.times, np.arange(40.0)) and np.array_equal(store.stack_ids[:3], [1, 3, 1])
    with pytest.raises(ValueError, match="stack 2 is not one of"):
        store.append(2, 0, 0.0, np.eye(4), images[0], None, 1.0, np.zeros((8, 8)))


def test_a_spilled_store_keeps_its_frames_in_an_unlinked_file_and_trains_the_same(tmp_path):
    """Issue 39: past the budget, a growing store's images live in a memory-mapped file, not in
    anonymous memory; the file's name is gone at once (nothing left after a kill), the frames
    read back bit-identically, and a mapper on a spilled store trains exactly as one without."""
    frame_bytes = INTR.height * INTR.width * 3  # 2304
    store = FrameStore.empty({1: INTR, 3: INTR})
    store.spill_to(tmp_path / "spill", above_bytes=40 * frame_bytes)
    images = []
    for k in range(40):  # capacity 16 (in memory), 34 (in memory: 34 * 2304 <= the budget), 70 (spilled)
        images.append(np.full((INTR.height, INTR.width, 3), 3 * k, dtype=np.uint8))
        store.append(1 + 2 * (k % 2), k, float(k), np.eye(4), images[-1], None, float(k), np.full((8, 8), k))
        spilled = isinstance(store._capacity["images"], np.memmap)
        assert spilled == (k >= 34) and store.spilled == (("images",) if spilled else ()), k
    file = store._spill_files["images"]
    for k in range(40, 80):  # capacity 70 -> 142: the file grows in place
        images.append(np.full((INTR.height, INTR.width, 3), k, dtype=np.uint8))
        images[-1][1, 2] = (k, 7, 200)  # one pixel unlike the rest: pixel 1 * W + 2
        store.append(1, k, float(k), np.eye(4), images[-1], None, float(k), np.full((8, 8), k))
    assert store._spill_files["images"] is file and len(store._capacity["images"]) == 142
    assert not isinstance(store._capacity["times"], np.memmap)  # only the pixels are spilled
    assert list((tmp_path / "spill").iterdir()) == []
    rows, pix = np.array([0, 33, 34, 41, 79, 41]), np.array([0, 5, 9, INTR.width + 2, INTR.width + 2, 3])
    want = [(0, 0, 0), (99, 99, 99), (102, 102, 102), (41, 7, 200), (79, 7, 200), (41, 41, 41)]
    assert store.pixels("images", rows, pix).tolist() == [list(w) for w in want]

    def mapped_kb() -> int:  # the spilled file's pages this process maps (/proc/self/smaps)
        total, inside = 0, False
        for line in Path("/proc/self/smaps").read_text().splitlines():
            if line[:1].isdigit() or line[:1] in "abcdef":
                inside = ".frames-images-" in line
            elif inside and line.startswith("Rss:"):
                total += int(line.split()[1])
        return total

    if Path("/proc/self/smaps").exists():  # written with pwrite, read with pread: nothing mapped
        assert mapped_kb() == 0
    assert np.array_equal(store.images, np.stack(images)) and np.array_equal(store.times, np.arange(80.0))

    def trained(spill: bool) -> list[float]:
        torch.manual_seed(0)
        mapper = _mapper(device="cpu")  # bit-for-bit is the CPU promise (CUDA adds with atomics)
        if spill:
            mapper.spill_frames(tmp_path / "spill2", above_bytes=0)  # every buffer in a file
        losses = []
        for k in range(3):  # 6 steps
            mapper.add_frame(_frame(float(k), stack=1 + 2 * (k % 2)))
            losses.append(mapper.train(600.0, steps=2).loss)
        assert isinstance(mapper.store._capacity["images"], np.memmap) == spill
        return losses

    assert trained(True) == trained(False)


def test_frames_not_added_are_never_sampled_and_each_gets_the_prior_once():
    mapper = _mapper()
    seen = []
    sample = mapper.sampler.sample

    def recording_sample(rng, n, frames=None, frame_p=None):
        batch = sample(rng, n, frames, frame_p)
        seen.append((mapper.frames, batch))
        return batch

    mapper.sampler.sample = recording_sample
    for k in range(3):
        mapper.add_frame(_frame(float(k)))
        report = mapper.train(600.0, steps=2)
        assert report.steps == 2 and report.frames == k + 1 and np.isfinite(report.loss)
        assert mapper.state()["prior_frames"] == k + 1  # the new frame's sensor prior is in the grid
    for n_added, batch in seen:
        assert int(batch.frames.max()) < n_added
        # every ray starts at the camera of one of the frames added so far
        xs = np.round(batch.origins[:, 0].numpy() / 0.1).astype(int)
        assert set(xs.tolist()) <= set(range(n_added))
    assert mapper.train(0.0).steps == 0


def test_bad_frames_and_arguments_give_one_line_errors(tmp_path):
    mapper = _mapper()
    with pytest.raises(UsageError, match=r"Mapper.train: no frames yet"):
        mapper.train(1.0)
    cases = [
        (dict(rgb=np.zeros((10, 10, 3), np.uint8)), r"SyncFrame.rgb \(stack 1\): got a uint8 array of shape \(10, 10, 3\); "
                                                     r"expected uint8 of shape \(24, 32, 3\)"),
        (dict(rgb=np.zeros((24, 32, 3), np.float32)), r"got a float32 array"),
        (dict(stack_id=2), r"SyncFrame.stack_id 2: unknown stack; expected one of \[1, 3\]"),
        (dict(irs_range=np.zeros(64)), r"SyncFrame.irs_range \(stack 1\): shape \(64,\); expected \(8, 8\)"),
        (dict(cam_to_world=np.eye(4) * 2), r"SyncFrame.cam_to_world .*: last row \[0.0, 0.0, 0.0, 2.0\]; expected a "
                                            r"finite \(4, 4\) rigid transform"),
        (dict(uss_range=-1.0), r"SyncFrame.uss_range \(stack 1\) -1.0: expected a range >= 0 m or NaN"),
        (dict(depth=np.zeros((3, 3))), r"SyncFrame.depth \(stack 1\): shape \(3, 3\); expected \(24, 32\)"),
        (dict(time=float("nan")), r"SyncFrame.time nan: expected a finite number"),
        (dict(time=True), r"SyncFrame.time True: expected a finite number of seconds"),
        (dict(time=1.7e18), r"SyncFrame.time 1.7e\+18: beyond 1e\+11 s .*expected seconds, not milli-, micro- or nano"),
        (dict(depth=np.full((24, 32), 2500, np.uint16)),
         r"SyncFrame.depth \(stack 1\): uint16 values; expected floating-point metres .*divided by 1000"),
        (dict(depth=np.full((24, 32), 2500.0)), r"SyncFrame.depth \(stack 1\): 2500 is beyond 100 m; expected metres"),
        (dict(irs_range=np.full((8, 8), 2582.0)), r"SyncFrame.irs_range \(stack 1\): 2582 is beyond 100 m; expected metres"),
        (dict(irs_range=np.full((8, 8), "x")), r"SyncFrame.irs_range \(stack 1\): not numbers; expected \(8, 8\)"),
        (dict(uss_range=1500.0), r"SyncFrame.uss_range \(stack 1\) 1500.0: beyond 100 m; expected metres"),
        (dict(uss_range=True), r"SyncFrame.uss_range \(stack 1\) True: expected a range >= 0 m"),
    ]
    for changes, message in cases:
        with pytest.raises(UsageError, match=message) as exc:
            mapper.add_frame(_frame(**changes))
        assert "\n" not in str(exc.value)
    assert mapper.frames == 0, "a refused frame is not added"
    mapper.add_frame(_frame(uss_range=float("nan")))  # no echo is fine
    mapper.add_frame(_frame(np.float32(0.5), uss_range=np.float32(1.5)))  # numpy scalars are numbers too
    mapper.add_frame(_frame(np.int64(1)))
    for t in (1.0, 0.5):  # the same time again, an earlier one
        with pytest.raises(UsageError, match=rf"SyncFrame.time {t} \(stack 1\): not after the stack's previous "
                                             r"frame at 1.0 s; expected each stack's frames in time order"):
            mapper.add_frame(_frame(t))
    mapper.add_frame(_frame(0.5, stack=3))  # the order is per stack
    for seconds in (-1.0, float("inf"), "1"):
        with pytest.raises(UsageError, match=r"Mapper.train seconds .*: expected a finite number >= 0"):
            mapper.train(seconds)
    with pytest.raises(UsageError, match=r"Mapper.scans poses of shape \(2, 2\)"):
        mapper.scans(np.zeros((2, 2)))
    with pytest.raises(UsageError, match=r"Mapper.map2d resolution 0: expected a positive number"):
        mapper.map2d(resolution=0)
    for call, message in ((lambda: mapper.map2d(n_rays=2.5), r"Mapper.map2d n_rays 2.5: expected an integer >= 1"),
                          (lambda: mapper.map2d(max_poses=0), r"Mapper.map2d max_poses 0: expected an integer >= 1"),
                          (lambda: mapper.scans(np.zeros((1, 3)), n_rays=0), r"Mapper.scans n_rays 0: expected an integer >= 1"),
                          (lambda: mapper.probability_map(band=-1.0), r"Mapper.probability_map band -1.0: expected"),
                          (lambda: mapper.probability_map(band=float("nan")), r"Mapper.probability_map band nan")):
        with pytest.raises(UsageError, match=message):
            call()
    with pytest.raises(UsageError, match=r"Mapper intrinsics"):
        Mapper(tiny_train_config(), {}, BOX)
    for changes, message in ((dict(fx=float("nan")), r"intrinsics\[1\].fx nan: expected a finite number of pixels"),
                             (dict(fx=-20.0), r"intrinsics\[1\].fx: focal length -20 px"),
                             (dict(width=0), r"intrinsics\[1\].width: image width 0 px; expected a size from 1"),
                             (dict(width=32.5), r"intrinsics\[1\].width: image width 32.5 px is not a whole number"),
                             (dict(cx=99.0), r"intrinsics\[1\].cx: principal point 99 px lies outside the image")):
        with pytest.raises(UsageError, match=r"Mapper " + message):
            Mapper(tiny_train_config(), {1: dataclasses.replace(INTR, **changes)}, BOX)
    half = Intrinsics(fx=10.0, fy=10.0, cx=8.0, cy=6.0, width=16, height=12)
    with pytest.raises(UsageError, match=r"the stacks' images differ in size \(stack 1 32x24, stack 3 16x12\)"):
        Mapper(tiny_train_config(), {1: INTR, 3: half}, BOX)
    with pytest.raises(UsageError, match=r"Mapper box: got a tuple; expected a virus_nerf.scene_box.SceneBox"):
        Mapper(tiny_train_config(), {1: INTR}, ((-3.0, -3.0, -1.0), (3.0, 3.0, 2.0)))


def test_a_stack_that_joins_after_the_first_frames_is_mapped_from_then_on():
    """Live, a camera driver that starts late (its camera_info after the map was started) joins
    with `add_stack`: its frames are taken, sampled and tracked by the stereo sensor from then on.
    A stack already mapped, or of another image size, is refused in one line, nothing changed."""
    mapper = Mapper(tiny_train_config(sensors=("camera", "uss", "irs", "stereo")), {1: INTR}, BOX)
    with pytest.raises(UsageError, match=r"SyncFrame.stack_id 3: unknown stack; expected one of \[1\] .*Mapper.add_stack"):
        mapper.add_frame(_frame(0.0, stack=3))
    mapper.add_frame(_frame(0.0))
    assert mapper.train(600.0, steps=1).steps == 1  # the sampler and the stereo feed are made
    with pytest.raises(UsageError, match=r"^Mapper.add_stack stack_id 1: already mapped; expected a new stack id$"):
        mapper.add_stack(1, INTR)
    for sid in (True, "3", 3.0, None):  # a review: the constructor's argument was named, True "already mapped"
        with pytest.raises(UsageError, match=rf"^Mapper.add_stack stack_id {re.escape(repr(sid))}: a "
                                             rf"{type(sid).__name__}; expected the stack id as an int"):
            mapper.add_stack(sid, INTR)
    with pytest.raises(UsageError, match=r"^Mapper.add_stack intrinsics\[3\]: got a tuple; expected a "):
        mapper.add_stack(3, (20.0, 20.0, 16.0, 12.0))
    with pytest.raises(UsageError, match=r"^Mapper.add_stack intrinsics: the stacks' images differ in size "
                                         r"\(stack 1 32x24, stack 3 64x48\)"):
        mapper.add_stack(3, dataclasses.replace(INTR, width=64, height=48, cx=32.0, cy=24.0))
    assert set(mapper.intrinsics) == set(mapper.store.intrinsics) == {1}
    mapper.add_stack(3, INTR)
    assert mapper.store.intrinsics[3] == INTR.scaled(mapper.config.image_scale) and 3 in mapper.store.footprints
    for k in range(1, 4):
        mapper.add_frame(_frame(float(k), stack=3))
    assert mapper.store.stack_ids.tolist() == [1, 3, 3, 3]
    batch = mapper.sampler.sample(np.random.default_rng(0), 256)
    assert {int(mapper.store.stack_ids[f]) for f in batch.frames.numpy()} == {1, 3}  # both cameras' rays
    assert mapper.train(600.0, steps=2).steps == 2 and np.isfinite(mapper.train(600.0, steps=1).loss)
    assert 3 in mapper._stereo_feed.builder.trackers  # its images are tracked too


def test_a_restarted_clock_continues_after_the_newest_frame():
    """Mapper.restart_clock: the next frames (stamped from 0 again) follow the newest frame in the
    store, 1 s on, each stack in time order; without it an earlier stamp is refused."""
    mapper = _mapper()
    mapper.restart_clock()  # before any frame: nothing to follow, no gap
    for t in (10.0, 10.5):
        mapper.add_frame(_frame(t))
    mapper.add_frame(_frame(10.2, stack=3))
    with pytest.raises(UsageError, match=r"call Mapper.restart_clock\(\) first"):
        mapper.add_frame(_frame(0.0, stack=3))
    mapper.restart_clock()
    for t, stack in ((0.0, 3), (0.1, 1), (0.5, 3)):
        mapper.add_frame(_frame(t, stack=stack))
    np.testing.assert_allclose(mapper.store.times, [10.0, 10.5, 10.2, 11.5, 11.6, 12.0])


def test_the_frame_clock_by_hand():
    """engine/clock.FrameClock alone: a restart's first frame (stamped back) continues 1 s after the
    store's newest time; a stack's late frame of the old clock keeps the old shift; a frame the
    store refused (not kept) changes nothing."""
    from virus_nerf.engine.clock import FrameClock

    clock = FrameClock()
    for stack, stamp in ((1, 100.0), (3, 100.1)):
        clock.keep(clock.place(stack, stamp, None))
    clock.restart()
    late = clock.place(3, 100.15, 100.1)  # after stack 3's previous: still the old clock
    assert (late.time, late.starts_clock) == (100.15, False)
    first = clock.place(1, 0.0, 100.1)  # stack 1 went back: the new clock, 100.1 + 1 s
    assert first.starts_clock and first.time == pytest.approx(101.1)
    assert clock.shift == 0.0 and clock.restarted  # placed, not kept
    clock.keep(first)
    assert clock.shift == pytest.approx(101.1) and not clock.restarted
    assert clock.place(3, 100.2, 101.1).time == pytest.approx(100.2)  # nearer 100.1 than 0.0
    assert clock.place(3, 0.05, 101.1).time == pytest.approx(101.15)  # nearer the new clock's 0.0
    assert clock.newest_stamp == 0.0 and clock.previous_stamp(3) == 100.1 and clock.previous_stamp(2) is None


def test_a_restarted_clock_leaves_the_snapshot_the_newest_frames_own_stamp(tmp_path):
    """snapshot.json's last_frame_time is the newest frame's stamp as the robot sent it, not the
    store's time that runs on past a restart (the first frame after it at 10.5 + 1 s gap = 11.5)."""
    mapper = _mapper()
    for t in (10.0, 10.5):
        mapper.add_frame(_frame(t))
    mapper.restart_clock()
    mapper.add_frame(_frame(0.3))
    assert mapper.store.times[-1] == pytest.approx(11.5)
    info = mapper.snapshot(tmp_path / "s", n_rays=8, max_poses=1)
    assert info.last_frame_time == pytest.approx(0.3)
    assert json.loads((tmp_path / "s" / "snapshot.json").read_text())["last_frame_time"] == pytest.approx(0.3)


def test_a_frame_of_the_old_clock_arriving_after_a_restart_keeps_the_old_clock():
    """A library user's review: after restart_clock, a stack-3 frame still stamped on the old clock
    (its driver's queue) took the new shift, landed 100 s ahead and shut out every later stack-3
    frame. Nearer the old clock's newest stamp than the new one's, it keeps the old shift; by hand:
    newest 100.1, the new clock's first frame at 0.0 -> 101.1, the late 100.2 -> 100.2, then 0.05
    -> 101.15 and 0.1 -> 101.2. A second review's cases: a stack silent for 30 s that comes back
    on a clock reset 10 s back takes the new clock (not the old one, 11 s behind), and a restart
    whose frames go on forward keeps one clock for every stack."""
    pose = _frame(0.0).cam_to_world

    def times(before, after):
        """The store's times after frames (stamp, stack) `before`, restart_clock, then `after`."""
        mapper = _mapper()
        for i, frames in enumerate((before, after)):
            if i:
                mapper.restart_clock()
            for t, stack in frames:
                mapper.add_frame(_frame(t, stack=stack, cam_to_world=pose))
        return mapper.store.times

    np.testing.assert_allclose(times([(100.0, 1), (100.1, 3)], [(0.0, 1), (100.2, 3), (0.05, 3), (0.1, 1)]),
                               [100.0, 100.1, 101.1, 100.2, 101.15, 101.2])
    # the late frame may also come first: the restart waits for the new clock's first frame
    np.testing.assert_allclose(times([(100.0, 1), (100.1, 3)], [(100.2, 3), (0.0, 1), (0.05, 3)]),
                               [100.0, 100.1, 100.2, 101.2, 101.25])
    # stack 3 last at 100, stack 1 on to 130; reset to 120: shift 130 + 1 - 120 = 11
    np.testing.assert_allclose(times([(100.0, 3), (130.0, 1)], [(120.0, 1), (120.05, 3), (120.5, 1), (120.55, 3)]),
                               [100.0, 130.0, 131.0, 131.05, 131.5, 131.55])
    # restart_clock, but the clock never goes back: one clock, no shift
    np.testing.assert_allclose(times([(10.0, 1), (10.05, 3)], [(20.0, 1), (20.05, 3), (61.55, 3), (62.0, 1)]),
                               [10.0, 10.05, 20.0, 20.05, 61.55, 62.0])


def test_a_refused_frame_leaves_the_clock_as_it_was(tmp_path):
    """The first frame after restart_clock refused (its camera 50 m outside the box): the clock is
    not restarted by it, so the next good frame follows the newest 1 s on (before: the refused
    frame's stamp set the shift and the good frames were refused as out of order)."""
    mapper = _mapper()
    for t in (10.0, 10.5):
        mapper.add_frame(_frame(t))
    mapper.restart_clock()
    far = _frame(5000.0)  # the pose moves 0.1 m a second: x = 500 m
    with pytest.raises(UsageError, match="lies outside the Mapper's box"):
        mapper.add_frame(far)
    mapper.add_frame(_frame(0.2))
    mapper.add_frame(_frame(0.3, stack=3))
    np.testing.assert_allclose(mapper.store.times, [10.0, 10.5, 11.5, 11.6])
    assert mapper.snapshot(tmp_path / "s", n_rays=8, max_poses=1).last_frame_time == pytest.approx(0.3)


def test_a_float32_epoch_stamp_and_a_depth_the_store_cannot_hold_are_refused():
    """np.float32(1700000070.0) is 1700000128.0 (float32 holds such a time only to 128 s): refused
    in one line, not stored 58 s late; a float32 stamp fine to the millisecond is taken. A depth of
    70 m (over the store's uint16 millimetres, 65.534 m) is refused, not stored as 65.534 m."""
    mapper = _mapper()
    with pytest.raises(UsageError, match=r"SyncFrame.time 1700000128.0: a float32 holds a time this large only to "
                                         r"128 s; expected seconds as a Python float or float64"):
        mapper.add_frame(_frame(np.float32(1700000070.0)))
    assert mapper.frames == 0
    with pytest.raises(UsageError, match=r"SyncFrame.time -20000.0: a float32 holds"):  # negative alike
        mapper.add_frame(_frame(np.float32(-20000.0)))
    mapper.add_frame(_frame(np.float32(12.5)))
    depth = np.full((INTR.height, INTR.width), 70.0, dtype=np.float32)
    rgbd = Mapper(tiny_train_config(sensors=("camera", "rgbd")), {1: INTR}, BOX)
    with pytest.raises(UsageError, match=r"SyncFrame.depth \(stack 1\): 70 m is beyond 65.534 m"):
        rgbd.add_frame(_frame(0.0, depth=depth))
    rgbd.add_frame(_frame(0.0, depth=np.full_like(depth, np.nan)))  # no valid pixel: nothing to bound


def test_the_state_is_a_copy_and_train_counts_its_own_steps():
    """state() is the state of its moment while training goes on (a timer thread trains while
    another writes it out; before: the live tensors, saved a step later); train(steps=3) runs and
    reports 3 steps when a load_state lands between two of them (before: counted from the step
    counter that load_state set back, 4 steps run)."""
    mapper = _mapper(device="cpu")
    mapper.add_frame(_frame(0.0))
    mapper.add_frame(_frame(1.0))
    mapper.train(600.0, steps=2)
    saved = mapper.state()
    at_save = [p.detach().clone() for p in mapper.field.parameters()]
    mapper.train(600.0, steps=1)
    assert all(torch.equal(a, b) for a, b in zip(saved["field"].values(), at_save, strict=True))
    assert not torch.equal(next(iter(saved["field"].values())), next(mapper.field.parameters()).detach())
    real = Mapper._timed_step
    calls = []

    def then_load(self, progress=None):
        out = real(self, progress)
        calls.append(self.step)
        if len(calls) == 1:
            self.load_state(saved)  # as another thread would, between two steps (step 4 -> 2)
        return out

    Mapper._timed_step = then_load
    try:
        report = mapper.train(600.0, steps=3)
    finally:
        Mapper._timed_step = real
    assert (report.steps, calls, report.total_steps) == (3, [4, 3, 4], 4)


def test_small_public_inputs_named_as_the_others(tmp_path):
    """write_map_server takes a str folder as snapshot does; a SceneBox of NaN is one line naming it."""
    from virus_nerf import warm_up
    from virus_nerf.maps.occupancy import read_map_server, write_map_server

    assert callable(warm_up)  # the start-up the live commands run, public for a robot's program
    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    grid_map = mapper.update_map()
    pgm, yaml = write_map_server(grid_map, str(tmp_path), "map")
    back = read_map_server(yaml)
    assert pgm == tmp_path / "map.pgm" and np.array_equal(back.image, grid_map.image) and back.origin == grid_map.origin
    with pytest.raises(ValueError, match=r"SceneBox lo=\(nan, 0.0, 0.0\) hi=\(1.0, 1.0, 1.0\): expected finite metres"):
        SceneBox((float("nan"), 0, 0), (1, 1, 1))


def test_a_loaded_state_takes_only_the_frames_it_was_trained_on_in_their_order():
    """Mapper.state() names its frames (stack, time); frames added again, before or after
    load_state, must be those in that order: a robot program that restarts its reader one frame
    late would train on with a field fitted to other frames. Refused in one line, nothing added;
    frames beyond the state's go on as new ones; a state from before the list loads as before."""
    a = _mapper()
    for t, stack in ((0.0, 1), (0.2, 3), (1.0, 1)):
        a.add_frame(_frame(t, stack=stack))
    a.train(600.0, steps=1)
    state = a.state()
    assert state["frame_stacks"].tolist() == [1, 3, 1] and state["frame_times"].tolist() == [0.0, 0.2, 1.0]
    b = _mapper()
    b.load_state(state)
    b.add_frame(_frame(0.0))
    with pytest.raises(UsageError, match=r"^Mapper.add_frame: SyncFrame \(time 1.0\): frame 1 is stack 1 at 1.0 s, the "
                                         r"loaded state's frame 1 was stack 3 at 0.2 s; expected the frames the state "
                                         r"was trained on, in the same order$"):
        b.add_frame(_frame(1.0))
    assert b.frames == 1
    b.add_frame(_frame(0.2, stack=3))
    b.add_frame(_frame(1.0))
    b.add_frame(_frame(1.5))  # the drive goes on: a new frame
    assert b.frames == 4
    c = _mapper()  # frames first, then the state: checked as the state loads, the mapper unchanged
    c.add_frame(_frame(0.5))
    with pytest.raises(UsageError, match=r"^Mapper.load_state state\['frame_times'\]: frame 0 is stack 1 at 0.5 s, "
                                         r"the loaded state's frame 0 was stack 1 at 0.0 s"):
        c.load_state(state)
    assert c.step == 0
    store = a.store  # add_store is checked alike
    d = _mapper()
    d.load_state(state)
    with pytest.raises(UsageError, match=r"^Mapper.add_store: rows \[1, 0, 2\]: frame 0 is stack 3 at 0.2 s"):
        d.add_store(store, rows=np.array([1, 0, 2]))
    d.add_store(store, rows=np.array([0, 1, 2]))
    legacy = {k: v for k, v in state.items() if k not in ("frame_stacks", "frame_times")}
    e = _mapper()
    e.add_frame(_frame(0.5))
    e.load_state(legacy)  # nothing to check against
    for broken, message in (({**state, "frame_times": state["frame_times"].float()}, "expected frame_stacks"),
                            ({**state, "frames": 2}, "holds 3 frames, the state's 'frames' says 2")):
        with pytest.raises(UsageError, match=r"^Mapper.load_state state\['frame_times'\]: " + message):
            _mapper().load_state(broken)


def test_snapshots_are_written_whole_and_never_overwritten(tmp_path, monkeypatch):
    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    mapper.train(600.0, steps=2)
    scans = mapper.scans(np.stack([_frame(0.0).cam_to_world, _frame(1.0).cam_to_world]), n_rays=16)
    assert [s.name for s in scans] == ["NeRF", "NeRF"] and np.allclose(scans[1].origin, (0.1, 0.0))
    info = mapper.snapshot(tmp_path / "s1", n_rays=16, max_poses=2, with_state=True)
    names = sorted(p.name for p in (tmp_path / "s1").iterdir())
    assert names == ["map.pgm", "map.png", "map.yaml", "mapper.pt", "prob.pgm", "prob.png", "prob.yaml",
                     "snapshot.json"]
    assert (tmp_path / "s1" / "map.pgm").read_bytes().startswith(b"P5\n120 120\n255\n")  # 6 m / 0.05 m
    assert "image: map.pgm" in (tmp_path / "s1" / "map.yaml").read_text()
    doc = json.loads((tmp_path / "s1" / "snapshot.json").read_text())
    assert doc["frames"] == 1 and doc["steps"] == 2 == info.steps and 0.0 <= doc["map_known"] <= 1.0
    before = {p.name: p.read_bytes() for p in (tmp_path / "s1").iterdir()}
    with pytest.raises(OutputExistsError):
        mapper.snapshot(tmp_path / "s1")
    assert before == {p.name: p.read_bytes() for p in (tmp_path / "s1").iterdir()}

    import virus_nerf.maps.occupancy as maps

    def broken_png(path, image):
        raise OSError("disk full")

    monkeypatch.setattr(maps, "write_png", broken_png)
    with pytest.raises(OSError, match="disk full"):
        mapper.snapshot(tmp_path / "s2")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s1"], "no half-written snapshot or temporary left"


def test_mapper_on_a_drive_improves_the_map(tiny_office):
    """Frames of the simulated office arrive six at a time with 16 steps between: the NeRF's
    zone-3 accuracy against the LiDAR map (the evaluation's own metric) gets better."""
    from virus_nerf.evaluation.evaluate import build_ground_truth, evaluate

    rec = load_recording(tiny_office, "office")
    cfg = tiny_train_config(max_steps=80, batch_size=512, march=MarchConfig(step_size=0.04, max_samples=64),
                            virus_grid=VirusGridConfig(warmup_steps=40, update_interval=4, rays_per_update=256))
    cfg.evaluation = dataclasses.replace(cfg.evaluation, n_rays=128, sensors=())
    mapper = Mapper.for_recording(rec, cfg)
    gts = build_ground_truth(rec, cfg.evaluation)

    def zone3_accuracy() -> float:
        result = evaluate(rec, {"NeRF": mapper.model}, cfg.evaluation, ground_truth=gts)
        return result.metrics["NeRF"].zones["zone3"].acc_mean

    order = rec.frame_order(("train",))
    start = zone3_accuracy()
    for k in range(0, len(order), 6):
        for s, i in order[k:k + 6]:
            mapper.add_frame(rec.stacks[s].frame(i))
        mapper.train(600.0, steps=16)
    mapper.train(600.0, steps=80 - mapper.step)
    assert mapper.frames == len(order) and mapper.step == 80
    end = zone3_accuracy()
    assert end < start - 0.05, (start, end)
    m = mapper.map2d(resolution=0.1, n_rays=64, max_poses=4)
    assert (m.image == 0).any() and (m.image == 254).any(), "the map has occupied and free cells"


def test_online_trainer_gives_the_mapper_only_frames_the_clock_passed(tiny_office, tmp_path):
    from virus_nerf.trainer.loop import Trainer

    rec = load_recording(tiny_office, "office")
    trainer = Trainer(rec, tiny_train_config(online=True, max_steps=None, max_time=5.0), tmp_path, quiet=True)
    trainer.train_step()
    # the first step fed the frames its clock (0 s) had passed: the first one; the clock has moved
    # on during the step (how far depends on the machine's load), so more may be available now
    assert trainer.mapper.frames == 1 <= len(trainer.available_frames())
    times = np.sort(trainer.store.times)
    trainer.mapper.seconds = (times[5] - times[0]) / trainer.config.playback_speed + 1e-6
    trainer.train_step()
    assert 6 <= trainer.mapper.frames <= len(trainer.available_frames())
    assert np.all(np.diff(trainer.mapper.store.times) >= 0), "frames arrive in time order"


def test_replay_and_map_bag_write_snapshots_with_progress_lines(tiny_office, tmp_path, capsys, monkeypatch):
    """map-bag --import-first on a real ROS 1 bag of the simulated office (imported with LiDAR
    odometry, then replayed): the 3 s drive at playback x1 gives snapshots every 0.4 s, each a
    complete folder with one progress line (the streaming default: test_map_stream.py); its frames
    spill to OUT beyond the budget, as the stream's do (an hour's drive stays out of memory)."""
    pytest.importorskip("rosbags")
    pytest.importorskip("kiss_icp")
    from virus_nerf.data.bags.writer import write_bag

    spills = []
    original_spill = Mapper.spill_frames
    monkeypatch.setattr(Mapper, "spill_frames", lambda self, folder, *a: (spills.append(Path(folder)),
                                                                        original_spill(self, folder, *a)))

    bag = write_bag(tiny_office, tmp_path / "drive.bag", ros_version=1)
    cfg = tmp_path / "cfg.json"
    from virus_nerf.config_io import to_dict

    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    out = tmp_path / "out"
    have_sinks = importlib.util.find_spec("rerun") and importlib.util.find_spec("mcap_ros2")
    sinks = ["--rerun-save", tmp_path / "live.rrd", "--out-bag", tmp_path / "maps_bag"] if have_sinks else []
    code, stdout, stderr = run_cli(["map-bag", bag, "--out", out, "--playback", "1", "--snapshot-every", "0.4",
                                    "--config", cfg, "--n-rays", "32", "--max-poses", "3", "--import-first", *sinks])
    assert code == 0, stderr
    assert (out / "recording" / "import_report.json").is_file()
    assert spills == [out]
    lines = [ln for ln in stdout.splitlines() if ln.startswith(("snapshot", "final map"))]
    snaps = sorted(p for p in (out / "snapshots").iterdir() if p.is_dir())
    assert len(snaps) >= 1 and len(lines) == len(snaps) + 1
    for k, (line, folder) in enumerate(zip(lines, snaps, strict=False), start=1):
        assert folder.name.startswith(f"{k:04d}_") and line.startswith(f"snapshot {k} at ") and str(folder) in line
        assert {"map.pgm", "map.yaml", "map.png", "snapshot.json"} <= {p.name for p in folder.iterdir()}
    n_frames = sum(len(s) for s in load_recording(out / "recording", "drive").stacks.values())
    final = json.loads((out / "map" / "snapshot.json").read_text())
    assert final["frames"] == n_frames and final["steps"] > 0 and lines[-1].startswith("final map")
    assert (out / "map" / "mapper.pt").is_file() and not list(out.glob(".*"))
    if have_sinks:  # every snapshot's maps and every frame's pose went to the live view and the ROS bag
        _check_map_bag_sinks(tmp_path / "live.rrd", tmp_path / "maps_bag", out, len(snaps), n_frames)
    # never overwritten: map-bag refuses OUT, replay refuses OUT/snapshots
    code, _, stderr = run_cli(["map-bag", bag, "--out", out])
    assert code == 2 and "already exists" in stderr
    from virus_nerf.mapping.replay import replay

    with pytest.raises(OutputExistsError):
        replay(out / "recording", out, 2.0, 0.4)


def test_map_bag_without_the_ros_extra_is_one_clear_line(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "rosbags" else real(n, *a))
    bag = tmp_path / "drive.bag"
    bag.write_bytes(b"")
    code, _, stderr = run_cli(["map-bag", bag, "--out", tmp_path / "out"])
    assert code == 2 and not (tmp_path / "out").exists()
    assert stderr.startswith("virus-nerf: error: ") and "pip install -e '.[ros]' in the virus-nerf repository" in stderr
    assert stderr.count("\n") == 1
    for argv, message in ((["map-bag", tmp_path / "none.bag", "--out", tmp_path / "o"], "BAG"),
                          (["map-bag", bag, "--out", tmp_path / "o", "--playback", "0"], "--playback 0.0"),
                          (["map-bag", bag, "--out", tmp_path / "o", "--snapshot-every", "0"], "--snapshot-every 0.0")):
        code, _, stderr = run_cli(argv)
        assert code == 2 and message in stderr, stderr


def test_mapper_state_round_trip_continues_identically():
    a = _mapper(device="cpu")  # bit-for-bit is the CPU promise (CUDA adds with atomics, in no fixed order)
    a.add_frame(_frame(0.0))
    a.add_frame(_frame(1.0))
    a.train(600.0, steps=3)
    buffer = io.BytesIO()
    torch.save(a.state(), buffer)  # as a checkpoint file: state() holds the live tensors
    buffer.seek(0)
    c = _mapper(device="cpu")
    c.load_state(torch.load(buffer, weights_only=False))
    c.add_frame(_frame(0.0))
    c.add_frame(_frame(1.0))
    # a loaded mapper builds Adam at its first step (mapping or exporting a run never needs it),
    # and until then hands its checkpoint's Adam state on unchanged
    assert c._optimizer is None
    moments = c.state()["optimizer"]["state"][0]["exp_avg"]
    assert torch.equal(moments, a.optimizer.state_dict()["state"][0]["exp_avg"]) and moments.abs().sum() > 0
    d = _mapper(device="cpu")  # the still-pending state saved again reads as the first
    d.load_state(c.state())
    assert torch.equal(d.state()["optimizer"]["state"][0]["exp_avg"], moments)
    for m in (a, c):
        m.train(600.0, steps=2)
    assert c._optimizer is not None and c._optimizer_state is None
    assert c.state()["prior_frames"] == 2
    for x, y in zip(a.field.parameters(), c.field.parameters(), strict=True):
        assert np.array_equal(x.detach().numpy(), y.detach().numpy())
    assert np.array_equal(a.grid.logodds.numpy(), c.grid.logodds.numpy())


def test_building_adam_is_not_on_the_training_clock(monkeypatch):
    """Adam is built at the first training step, before the step's clock starts (torch's own
    optimiser class took seconds to build: it imports torch._dynamo), which a --max-time budget
    must not pay. Here it takes 1000 s by the training clock's own reading (the clock jumps while
    Adam is built), so no real time is measured and a busy machine cannot fail it."""
    import time
    import types

    import virus_nerf.engine.mapper as mapper_module

    built, jump = [], [0.0]

    class SlowAdam(mapper_module.Adam):
        def __init__(self, *args, **kwargs):
            jump[0] += 1000.0
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(mapper_module, "time", types.SimpleNamespace(perf_counter=lambda: time.perf_counter() + jump[0]))
    monkeypatch.setattr(mapper_module, "Adam", SlowAdam)
    mapper = _mapper(device="cpu")
    mapper.add_frame(_frame(0.0))
    mapper.prepare()  # off the clock, as a Trainer does
    assert not built  # adding frames and preparing build none
    mapper.train(600.0, steps=2)
    assert built == [1] and mapper.step == 2 and mapper.seconds < 1000.0


def test_a_resumed_mapper_keeps_the_restored_render_path_statistic():
    """The start-up kernel warm-up renders 8 rays; it must not replace the visible share restored
    from a checkpoint, which picks the next step's render path (issue 30: a resume from step 52
    of a 200-step run differed from the uninterrupted run)."""
    a = _mapper(device="cpu")
    a.add_frame(_frame(0.0))
    state = a.state()
    state["visible_share"] = 0.123
    c = _mapper(device="cpu")
    c.load_state(state)
    c.add_frame(_frame(0.0))
    c.prepare()
    assert c.visible_share == 0.123


def test_rgbd_frames_with_and_without_depth_and_an_instant_ngp_snapshot(tmp_path):
    rgbd = _mapper(sensors=("camera", "rgbd"))
    rgbd.add_frame(_frame(0.0, depth=np.full((INTR.height, INTR.width), 1.5, dtype=np.float32)))
    rgbd.add_frame(_frame(1.0))  # no depth image: every pixel invalid
    assert rgbd.store.depths_mm[0].min() == 1500 and rgbd.store.depths_mm[1].max() == 0
    assert rgbd.train(600.0, steps=1).steps == 1
    ngp = _mapper(grid="ngp")
    ngp.add_frame(_frame(0.0))
    ngp.train(600.0, steps=1)
    assert ngp.probability_map() is None
    ngp.snapshot(tmp_path / "ngp", n_rays=8, max_poses=1)
    assert sorted(p.name for p in (tmp_path / "ngp").iterdir()) == ["map.pgm", "map.png", "map.yaml",
                                                                    "snapshot.json"]


def test_newest_frames_get_their_share_of_the_batch_only_while_driving():
    # share 0.5 over the last 5 s: with frames at t = 0..9 and one at t = 20, the frame at 20 is
    # the only recent one, so it gets 0.5 + 0.5 / 11 of the rays (hand-computed: 0.5455)
    recent = dataclasses.replace(tiny_train_config().recent, share=0.5, window=5.0)
    mapper = _mapper(recent=recent)
    for k in range(10):
        mapper.add_frame(_frame(float(k)))
    mapper.train(600.0, steps=1)
    assert mapper._frame_odds(mapper.schedule) is None  # every frame was there at the first step: offline, uniform
    mapper.add_frame(_frame(20.0))
    odds = mapper._frame_odds(mapper.schedule)
    np.testing.assert_allclose(odds, [0.5 / 11] * 10 + [0.5 + 0.5 / 11])
    batch = mapper.sampler.sample(np.random.default_rng(0), 20000, np.arange(11), odds)
    assert abs(float((batch.frames == 10).float().mean()) - (0.5 + 0.5 / 11)) < 0.015
    assert mapper.train(600.0, steps=2).steps == 2
    told = []
    update = mapper.grid.update
    mapper.grid.update = lambda *a, **k: told.append(k["driving"]) or update(*a, **k)
    mapper.train(600.0, steps=mapper.grid.update_interval)  # a grid update while driving
    assert told == [True]  # its warm-up now runs over virus_grid.warmup_steps_driving
    assert mapper.schedule.driving and mapper.schedule.lr_decay_to == mapper.config.optim.lr_decay_driving
    again = Mapper(mapper.config, mapper.intrinsics, mapper.box)
    again.load_state(mapper.state())  # a resumed mapper knows the frames it started with
    for k in range(10):
        again.add_frame(_frame(float(k)))
    assert again._frame_odds(again.schedule) is None
    again.add_frame(_frame(20.0))
    np.testing.assert_allclose(again._frame_odds(again.schedule), odds)


def test_a_camera_turning_to_new_space_while_driving_restarts_those_columns_warmup():
    # warmup_restart "view": frames at the first step look along +x; a frame added while driving
    # looks along -x, so the columns behind the start get their warm-up back (p_init), and the
    # columns seen from the start keep the run's clock
    grid_cfg = dataclasses.replace(tiny_train_config().virus_grid, warmup_restart="view", warmup_steps_driving=4,
                                   update_interval=2)
    mapper = _mapper(virus_grid=grid_cfg)
    mapper.add_frame(_frame(0.0))
    mapper.train(600.0, steps=1)
    mapper.add_frame(_frame(1.0))  # driving from here
    mapper.train(600.0, steps=5)  # past the driving warm-up: untouched cells at the prior
    grid = mapper.grid
    spec = grid.spec
    centre_x = spec.box.lo[0] + (np.arange(spec.resolution[0]) + 0.5) * spec.cell_size[0]
    behind = int(np.flatnonzero(centre_x < -0.5)[0])  # a column behind the start, never looked at
    ahead = int(np.flatnonzero(centre_x > 0.5)[0])
    iy = spec.resolution[1] // 2
    prior = math.log(0.49 / 0.51)
    assert grid.logodds[behind, iy, 0] == pytest.approx(prior, abs=1e-5)
    turned = _frame(2.0)
    turned.cam_to_world[:3, :3] = [[0, 0, -1.0], [1.0, 0, 0], [0, -1.0, 0]]  # looking along -x
    mapper.add_frame(turned)
    told = []
    restart = grid.restart_warmup_in_view
    grid.restart_warmup_in_view = lambda viewed, step: told.append((viewed.copy(), step)) or restart(viewed, step)
    mapper.train(600.0, steps=2)  # one grid update
    viewed, step = told[-1]
    assert step == mapper.step and viewed[behind, iy] and not viewed[ahead, iy]
    # two steps into its own 4-step warm-up: p_init moved half-way (one update at the restart step)
    assert grid.logodds[behind, iy, 0] > prior + 0.1
    assert grid._restart_step[behind, iy] == step and grid._restart_step[ahead, iy] == -1
    again = Mapper(mapper.config, mapper.intrinsics, mapper.box)
    again.load_state(mapper.state())
    assert again._viewed_frames == mapper.frames
    # a state written before the restart existed: its frames count as seen at step 0, so a frame
    # looking where they looked restarts nothing
    legacy_state = mapper.state()
    legacy_state.pop("viewed_frames")
    legacy_state["grid"] = {k: v for k, v in legacy_state["grid"].items()
                            if k not in ("viewed", "restart_step", "column_applied")}
    legacy = Mapper(mapper.config, mapper.intrinsics, mapper.box)
    legacy.load_state(legacy_state)
    for f in (_frame(0.0), _frame(1.0), turned):
        legacy.add_frame(f)
    legacy.add_frame(dataclasses.replace(_frame(3.0), cam_to_world=_frame(0.0).cam_to_world))
    legacy.train(600.0, steps=2)
    assert legacy.grid._restart_step is None or (legacy.grid._restart_step == -1).all()


def test_learning_rate_decays_offline_and_stays_while_driving():
    # tiny config: max_steps 5, so step k (counted before it runs) uses lr * decay ** (k / 5)
    optim = dataclasses.replace(tiny_train_config().optim, lr=0.01, lr_decay_to=0.1, lr_decay_driving=0.5)
    offline, driving = _mapper(optim=optim), _mapper(optim=optim)
    for k in range(3):
        offline.add_frame(_frame(float(k)))
    offline.train(600.0, steps=3)
    assert not offline.driving
    assert offline.optimizer.param_groups[0]["lr"] == pytest.approx(0.01 * 0.1 ** (2 / 5))
    driving.add_frame(_frame(0.0))
    driving.train(600.0, steps=1)
    assert not driving.driving
    driving.add_frame(_frame(1.0))
    driving.train(600.0, steps=2)
    assert driving.driving
    assert driving.optimizer.param_groups[0]["lr"] == pytest.approx(0.01 * 0.5 ** (2 / 5))


def test_rays_for_step_keeps_the_sample_budget_by_hand():
    from virus_nerf.engine.schedule import rays_for_step

    assert rays_for_step(2048, None, 177.0) == 2048  # no budget: always the batch
    assert rays_for_step(2048, 65536, 0.0) == 2048  # first step: nothing measured yet
    assert rays_for_step(2048, 65536, 16.0) == 2048  # 2048 x 16 = 32768 samples, under the cap
    assert rays_for_step(2048, 65536, 32.0) == 2048  # exactly the cap
    assert rays_for_step(2048, 65536, 64.0) == 1024  # 65536 / 64
    assert rays_for_step(2048, 65536, 100.0) == 655  # floor(65536 / 100)
    assert rays_for_step(2048, 65536, 1000.0) == 256  # never below batch / 8
    assert rays_for_step(4, 10, 1000.0) == 1  # and never below one ray


def _record_ray_counts(mapper: Mapper) -> list[tuple[int, float, bool]]:
    """Wraps the mapper's sampler: the list grows by (rays asked for, last step's samples per
    ray, driving) at every step."""
    taken: list[tuple[int, float, bool]] = []
    sample = mapper.sampler.sample

    def recording_sample(rng, n, frames=None, frame_p=None):
        taken.append((n, mapper.last_samples_per_ray, mapper.driving))
        return sample(rng, n, frames, frame_p)

    mapper.sampler.sample = recording_sample
    return taken


def test_a_sample_budget_shrinks_long_ray_steps_and_resumes_identically():
    """With max_samples_per_step each step takes cap / (last step's samples per ray) rays (at
    most the batch); the measure travels in the state, so a resumed mapper takes the same."""
    a = _mapper(max_samples_per_step=640, device="cpu")  # 128 rays x 5 samples; bit-for-bit: CPU
    a.add_frame(_frame(0.0))
    taken = _record_ray_counts(a)
    a.train(600.0, steps=3)
    assert taken[0] == (128, 0.0, False)
    assert any(spr > 5.0 for _, spr, _ in taken[1:])  # the budget did bite on this scene
    for n, spr, _ in taken[1:]:
        assert n == (128 if spr <= 0 else max(16, min(128, int(640 // spr))))
    assert a.rays == sum(n for n, _, _ in taken)
    buffer = io.BytesIO()
    torch.save(a.state(), buffer)
    buffer.seek(0)
    c = _mapper(max_samples_per_step=640, device="cpu")
    c.load_state(torch.load(buffer, weights_only=False))
    c.add_frame(_frame(0.0))
    assert c.last_samples_per_ray == a.last_samples_per_ray and c.rays == a.rays
    for m in (a, c):
        m.train(600.0, steps=2)
    for x, y in zip(a.field.parameters(), c.field.parameters(), strict=True):
        assert np.array_equal(x.detach().numpy(), y.detach().numpy())


def test_the_driving_sample_budget_bites_only_once_frames_arrive_after_training_began():
    """max_samples_per_step_driving caps a step only while driving: before the second frame
    arrives every step takes the whole batch, afterwards cap / (last samples per ray) rays."""
    m = _mapper(max_samples_per_step=None, max_samples_per_step_driving=640)  # 128 rays x 5 samples
    m.add_frame(_frame(0.0))
    taken = _record_ray_counts(m)
    m.train(600.0, steps=2)
    m.add_frame(_frame(1.0))
    m.train(600.0, steps=3)
    assert [d for _, _, d in taken] == [False, False, True, True, True]
    assert [n for n, _, _ in taken[:2]] == [128, 128]  # offline: no budget
    assert any(spr > 5.0 for _, spr, _ in taken[2:])  # the budget did bite on this scene
    for n, spr, _ in taken[2:]:
        assert n == max(16, min(128, int(640 // spr)))


def _check_map_bag_sinks(rrd, bag_dir, out, n_snapshots: int, n_frames: int,
                         frames: tuple[str, str] = ("map", "base_link")) -> None:
    """The .rrd (read by rerun's own reader) and the MCAP (read by mcap + mcap_ros2) of a map-bag
    run; `frames`: the maps' frame and /tf parent, the /tf child."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from PIL import Image
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        if "drive_time" in chunk.timeline_names:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows["/map/trinary"] == n_snapshots + 1 and rows["/map/probability"] == n_snapshots + 1
    assert rows["/world/camera_1/image"] + rows.get("/world/camera_3/image", 0) == n_frames
    maps, tfs = [], []
    with open(bag_dir / f"{bag_dir.name}.mcap", "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            if channel.topic == "/map":
                maps.append(msg)
                assert msg.header.frame_id == frames[0]
            if channel.topic == "/tf":
                assert (msg.transforms[0].header.frame_id, msg.transforms[0].child_frame_id) == frames
                v = msg.transforms[0].transform.translation
                tfs.append((v.x, v.y))
    # base_link is the LiDAR's frame (map-bag mounts the cameras by the topics file's camera_in_lidar):
    # one /tf per frame of either stack, and the robot never jumps between the two cameras (0.28 m
    # across the rig) from one frame to the next
    assert len(maps) == n_snapshots + 1 and len(tfs) == n_frames
    assert np.linalg.norm(np.diff(np.asarray(tfs), axis=0), axis=1).max() < 0.2
    final = np.asarray(Image.open(out / "map" / "map.pgm"))
    expected = np.where(final == 0, 100, np.where(final == 254, 0, -1))[::-1]  # OccupancyGrid row 0 = smallest y
    last = maps[-1]
    assert (last.info.height, last.info.width) == final.shape
    np.testing.assert_array_equal(np.asarray(last.data, dtype=np.int8).reshape(final.shape), expected)


def test_mapper_api_bad_input_round_two():
    """Issue 30: a mirror-image pose, a negative depth, a map resolution that cannot fit, and a
    step in which no ray marches anything (every ray looks out of the box)."""
    mapper = _mapper(sensors=("camera", "rgbd"))
    mirror = _frame()
    pose = mirror.cam_to_world.copy()
    pose[:3, 0] *= -1  # det -1: orthonormal, but a reflection
    with pytest.raises(UsageError, match=r"cam_to_world .*: rotation with det -1 \(a mirror image\); .*det \+1"):
        mapper.add_frame(dataclasses.replace(mirror, cam_to_world=pose))
    depth = np.full((INTR.height, INTR.width), 2.0)
    depth[3, 4] = -2.0
    with pytest.raises(UsageError, match=r"SyncFrame.depth .*negative .*min -2"):
        mapper.add_frame(_frame(depth=depth))
    mapper.add_frame(_frame(depth=np.full((INTR.height, INTR.width), 2.0)))
    for resolution, what in ((1e-5, "would be a 600000x600000 px map"), (0.0, "expected a positive number")):
        with pytest.raises(UsageError, match=what):
            mapper.map2d(resolution)
        with pytest.raises(UsageError, match=what):
            mapper.probability_map(resolution)
    outward = _mapper()
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]]
    pose[:3, 3] = (2.999, 0.0, 0.5)  # at the box edge looking out: no ray has a sample
    outward.add_frame(_frame(cam_to_world=pose))
    before = [p.detach().clone() for p in outward.field.parameters()]
    outward.train(60.0, steps=2)
    assert outward.step == 2
    assert all(torch.equal(a, b.detach()) for a, b in zip(before, outward.field.parameters(), strict=True))


def test_mapper_api_bad_input_round_three(tmp_path):
    """A user's review of the API (thirty-seventh session): what a robot program gets wrong."""
    from virus_nerf.mapping.ros_maps import stamp_ns
    from virus_nerf.maps.occupancy import OCCUPIED, UNKNOWN

    # string stack keys (a KeyError after the frame was half added), bool and float stack ids
    with pytest.raises(UsageError, match=r"^Mapper intrinsics\['1'\]: the key '1' is a str; expected the stack id as an int"):
        Mapper(tiny_train_config(), {"1": INTR}, BOX)
    with pytest.raises(UsageError, match=r"^Mapper intrinsics: got a list; expected a dict stack id -> "):
        Mapper(tiny_train_config(), [INTR], BOX)  # a review: a bare AttributeError
    mapper = _mapper()
    for sid in (True, 1.0):
        with pytest.raises(UsageError, match=rf"^SyncFrame.stack_id {sid!r}: a {type(sid).__name__}; expected an int"):
            mapper.add_frame(_frame(stack=sid))
    # a pose in a ROS body frame (x forward, z up): the camera would look straight up
    with pytest.raises(UsageError, match=r"the camera looks straight up \(0.0 deg from vertical\); expected OpenCV "):
        mapper.add_frame(_frame(cam_to_world=np.eye(4)))
    # a bool mask or complex values for the IRS zones
    for bad in (np.ones((8, 8), bool), np.full((8, 8), 2.0 + 0j)):
        with pytest.raises(UsageError, match=rf"SyncFrame.irs_range \(stack 1\): {bad.dtype} values; expected real"):
            mapper.add_frame(_frame(irs_range=bad))
    assert mapper.frames == 0  # nothing half added
    # 0 is the VL53L5CX's "no target" (as in a TOF file: <= 0.1 m invalid), USS 0 no echo
    zones = np.full((8, 8), 2.0)
    zones[0, :3] = (0.0, 0.05, 0.1)
    mapper.add_frame(_frame(irs_range=zones, uss_range=0.0))
    kept = mapper.store.irs_range[0]
    assert np.isnan(kept[0, :3]).all() and (kept[np.isfinite(kept)] == 2.0).all() and np.isfinite(kept).sum() == 61
    assert np.isnan(mapper.store.uss_range[0]) and zones[0, 0] == 0.0  # the caller's array is not changed
    # before the first step the field is haze: no walls from it, only the robot's own pixels free
    m = mapper.map2d()
    assert (m.image == OCCUPIED).sum() == 0 and (m.image != UNKNOWN).sum() <= 4, np.unique(m.image, return_counts=True)
    # a snapshot handed maps of another resolution
    with pytest.raises(UsageError, match=r"Mapper.snapshot maps: computed at resolution 0.1 m; expected the "
                                         r"snapshot's resolution 0.05 m"):
        mapper.snapshot(tmp_path / "s", resolution=0.05, maps=(mapper.map2d(resolution=0.1), None))
    assert not (tmp_path / "s").exists()
    # a box in millimetres
    with pytest.raises(UsageError, match=r"^Mapper box: a side of 6000 m; expected metres, a box of at most 1000 m"):
        Mapper(tiny_train_config(), {1: INTR}, SceneBox((-3000.0, -3000.0, -1000.0), (3000.0, 3000.0, 2000.0)))
    # a ROS stamp in nanoseconds: one line, not a struct.error from deep inside rosbags
    assert stamp_ns(2**31 - 1) == (2**31 - 1) * 10**9
    with pytest.raises(UsageError, match=r"beyond a ROS stamp's 2147483647 s \(the year 2038\); expected seconds"):
        stamp_ns(1.7e18)


def test_the_learning_rate_decays_over_the_horizon_the_caller_hands_in():
    """One horizon for every caller (engine/schedule.py): a drive of 30 s of recording at playback
    2 is 15 s of training; the lr after a step is lr * decay ** (share of that horizon), whatever
    the config's own max_steps / max_time say."""
    from virus_nerf.engine.schedule import Horizon, Schedules

    horizon = Horizon.drive(30.0, 2.0)
    assert horizon == Horizon(None, 15.0)
    assert horizon.share(10**6, 7.5) == 0.5  # no step bound: the clock alone
    assert Horizon(100, 10.0).share(50, 8.0) == 0.8  # the larger share counts
    assert Horizon(100, 10.0).share(500, 1.0) == 1.0  # never past the end
    assert Horizon.drive(0.0, 1.0).max_time == 1e-3  # a one-frame drive is not a division by zero

    config = tiny_train_config(max_steps=3, max_time=None)
    mapper = Mapper(config, {1: INTR, 3: INTR}, BOX, Schedules.of(config, Horizon(None, 1000.0)))
    mapper.add_frame(_frame(0.0))
    mapper.train_step()
    clock = mapper.seconds  # the second step's lr comes from the horizon's share after the first
    assert mapper.progress() == pytest.approx(clock / 1000.0)  # the config's max_steps 3 would say 1/3
    mapper.train_step()
    lr = mapper.optimizer.param_groups[0]["lr"]
    assert lr == pytest.approx(config.optim.lr * config.optim.lr_decay_to ** (clock / 1000.0), rel=1e-12)
    assert lr > config.optim.lr * config.optim.lr_decay_to ** 0.1


@pytest.mark.skipif(sys.platform != "linux", reason="RssFile and madvise are Linux's")
def test_a_source_read_once_gives_its_pages_back_and_keeps_its_data(tmp_path):
    """Issue 39: `train --online` copies each recorded frame into the mapper once; the source's
    file pages then leave the process (its RSS) and the data stays readable from the file."""
    from virus_nerf.sampler.frames import release_pages

    def rss_file_kb() -> int:
        return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("RssFile"))

    frames = np.random.default_rng(0).integers(0, 256, size=(200, 120, 160, 3), dtype=np.uint8)  # 11.5 MB
    np.save(tmp_path / "images.npy", frames)
    source = np.load(tmp_path / "images.npy", mmap_mode="r")
    before = rss_file_kb()
    assert np.array_equal(np.asarray(source), frames)  # every page read: mapped into the process
    read = rss_file_kb() - before
    release_pages(source, np.arange(200))
    released = read - (rss_file_kb() - before)
    assert read > 10_000 and released > 0.9 * frames.nbytes / 1024  # KB
    assert np.array_equal(np.asarray(source[::7]), frames[::7])  # read back from the file
    in_memory = frames.copy()
    release_pages(in_memory, np.arange(200))  # an array in memory is left alone
    assert np.array_equal(in_memory, frames)


def test_map_queries_are_cheap_until_the_mapper_changes(monkeypatch):
    """Issue 38 item 4: `map2d` answers from the map `update_map` made last while nothing it
    depends on changed; a step, a frame or other settings render it again; a caller's copy is its own."""
    import virus_nerf.engine.views as views

    renders = []
    real = views.occupancy_map
    monkeypatch.setattr(views, "occupancy_map", lambda *a, **k: renders.append(1) or real(*a, **k))
    mapper = _mapper()
    for t in range(4):
        mapper.add_frame(_frame(float(t)))
    mapper.train(60.0, steps=2)
    first = mapper.map2d(0.1, n_rays=32, max_poses=4)
    first.image[:] = 7  # the caller's copy, not the mapper's
    again = mapper.map2d(0.1, n_rays=32, max_poses=4)
    assert len(renders) == 1 and not (again.image == 7).any()
    assert np.array_equal(again.image, mapper.update_map(0.1, n_rays=32, max_poses=4).image)  # the same state
    assert len(renders) == 2
    mapper.map2d(0.1, n_rays=64, max_poses=4)  # other settings
    assert len(renders) == 3
    mapper.train(60.0, steps=1)
    mapper.map2d(0.1, n_rays=64, max_poses=4)  # a step later
    mapper.add_frame(_frame(4.0))
    mapper.map2d(0.1, n_rays=64, max_poses=4)  # a frame later
    assert len(renders) == 5


def test_the_mappers_map_ends_the_low_rays_at_d_over_a_until_the_field_has_trained_100_steps(monkeypatch):
    """D94: a field of a few steps is haze everywhere, and its opacity front lies at the cameras;
    the Mapper asks for the front from MAP_LOW_FRONT_FROM_STEP on."""
    import virus_nerf.engine.views as views
    from virus_nerf.maps.extract import MAP_LOW_FRONT_FROM_STEP, MAP_LOW_FRONT_OPACITY

    asked = []
    real = views.occupancy_map
    monkeypatch.setattr(views, "occupancy_map", lambda *a, **k: asked.append(a[9]) or real(*a, **k))
    mapper = _mapper()
    for t in range(4):
        mapper.add_frame(_frame(float(t)))
    mapper.train(60.0, steps=2)
    mapper.update_map(0.1, n_rays=32, max_poses=4)
    mapper.step = MAP_LOW_FRONT_FROM_STEP  # as after that many steps (the map reads only the count)
    mapper.update_map(0.1, n_rays=32, max_poses=4)
    assert asked == [None, MAP_LOW_FRONT_OPACITY]


def test_the_mappers_shadow_is_half_a_metre_in_a_small_fitted_room_and_a_metre_in_a_grown_box(monkeypatch):
    """D111: the shadow behind the low rays' ends reaches 0.5 m in a fitted box up to 12 m (this
    6 x 6 m one) and 1 m in a grown box, whose room is not known while it grows."""
    import virus_nerf.engine.views as views
    from virus_nerf.grid.extent import ExtentConfig

    asked = []
    real = views.occupancy_map
    monkeypatch.setattr(views, "occupancy_map", lambda *a, **k: asked.append(a[12]) or real(*a, **k))
    for mode in ("fitted", "grow"):
        mapper = _mapper(extent=ExtentConfig(mode=mode))
        for t in range(4):
            mapper.add_frame(_frame(float(t)))
        mapper.update_map(0.1, n_rays=32, max_poses=4)
    assert asked == [0.5, 1.0]


def test_a_refused_state_leaves_the_mapper_as_it_was():
    """A damaged, edited or foreign state is refused whole, with the key that is wrong, before
    `load_state` touches the mapper: its field, grid and step stay, and it goes on training."""
    from virus_nerf.engine.config import MapperConfig

    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    mapper.train(60.0, steps=1)
    good = mapper.state()

    def field_now():
        return {k: v.clone() for k, v in mapper.field.state_dict().items()}

    before, grid_before = field_now(), mapper.grid.state_dict()["logodds"].clone()
    broken_grid = {**good, "grid": {k: v for k, v in good["grid"].items() if k != "logodds"}, "step": 7}
    no_rng = {k: v for k, v in good.items() if k != "numpy_rng"}
    other_box = {**good, "box": {"lo": [-4.0, -3.0, -1.0], "hi": [3.0, 3.0, 2.0]}}
    ngp = Mapper(dataclasses.replace(tiny_train_config(), grid="ngp"), {1: INTR, 3: INTR}, BOX)
    bad_field = {**good, "field": {**good["field"], next(iter(good["field"])): torch.zeros(3)}}
    bad_rng = {**good, "torch_generator": torch.zeros(3)}
    for state, message in ((broken_grid, r"state\['grid'\]: lacks tensor\(s\) \['logodds'\]"),
                           (no_rng, r"state\['state'\]: lacks \['numpy_rng'\]"),
                           (other_box, r"state\['box'\]: lo=\[-4.0, .* does not match this mapper's lo=\[-3.0"),
                           (ngp.state(), r"state\['grid'\]: lacks tensor\(s\) \['logodds'"),
                           (bad_field, r"state\['field\..*'\]: tensor of shape \(3,\)"),
                           (bad_rng, r"state\['torch_generator'\]: not a torch CPU generator state"),
                           ({"weights": 1}, r"state\['state'\]: lacks \['field'"),
                           ([1, 2], r"state\['state'\]: expected the dict of Mapper.state\(\), got a list")):
        with pytest.raises(UsageError, match=r"^Mapper.load_state " + message):
            mapper.load_state(state)
        after = field_now()
        assert mapper.step == 1 and all(torch.equal(before[k], after[k]) for k in before)
        assert torch.equal(mapper.grid.state_dict()["logodds"], grid_before)
    mapper.train(60.0, steps=1)  # still trains
    assert mapper.step == 2
    assert isinstance(MapperConfig(), MapperConfig)


def test_numpy_numbers_are_numbers_and_a_pose_far_outside_a_fitted_box_is_refused(tmp_path):
    """Robot code hands numpy scalars in (np.float32 from a message, np.int64 from an array): the
    Mapper takes them as the Python numbers they are. A camera far outside a fitted box is a pose
    in another unit or frame (millimetres: hundreds of metres away), refused as in grow mode; one
    just outside the box (within extent.FITTED_SLACK_M) is not."""
    from virus_nerf.engine.extent import FITTED_SLACK_M

    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    assert mapper.train(np.float32(60.0), steps=np.int64(1)).steps == 1
    assert mapper.map2d(resolution=np.float32(0.25), n_rays=np.int64(16), max_poses=np.int32(2)).resolution == 0.25
    assert mapper.probability_map(np.float64(0.25), band=np.float32(0.1)).resolution == 0.25
    mapper.snapshot(tmp_path / "snap", resolution=np.float32(0.1), n_rays=16, max_poses=2)
    for name in ("map.yaml", "prob.yaml"):  # numbers to a YAML reader (map_server), not "np.float32(0.1)"
        doc = (tmp_path / "snap" / name).read_text()
        assert "resolution: 0.10000000149011612\n" in doc and "np." not in doc, doc
    far = _frame(1.0)
    far.cam_to_world[:3, 3] = (362.0, -151.6, -150.1)  # the rig's camera offset in millimetres / 1000 wrong way
    with pytest.raises(UsageError, match=r"frame at time 1.000 s \(its pose, SyncFrame.cam_to_world\): camera at "
                                         r"\(362.00, -151.60, -150.10\) m lies outside the Mapper's box \[-3.0, -3.0, "
                                         r"-1.0\]..\[3.0, 3.0, 2.0\] m \(extent.mode fitted\); expected a pose in "
                                         r"metres \(one in millimetres lands far outside\)"):
        mapper.add_frame(far)
    near = _frame(2.0)
    near.cam_to_world[:3, 3] = (3.0 + FITTED_SLACK_M - 0.1, 0.0, 0.5)
    mapper.add_frame(near)
    assert mapper.frames == 2


@pytest.mark.slow
def test_threads_may_add_frames_while_another_trains_and_reads_the_map():
    """A sensor callback adds frames on its thread while a timer's thread trains and reads the
    map (rospy, an rclpy MultiThreadedExecutor): the calls take turns, none sees a half-added
    frame, and every frame is in. (Without the turns, about one run in five read the store's arrays
    at different lengths: an IndexError in the map's track_free.)"""
    import threading

    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    errors: list[BaseException] = []
    done = threading.Event()

    def feed():
        try:
            for k in range(1, 301):
                mapper.add_frame(_frame(0.01 * k))
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)
        finally:
            done.set()

    thread = threading.Thread(target=feed)
    thread.start()
    rounds = 0
    while not done.is_set() or rounds < 2:
        mapper.train(60.0, steps=1)
        mapper.map2d(resolution=0.25, n_rays=16, max_poses=30)
        mapper.observed(0.25)
        rounds += 1
    thread.join()
    assert not errors and mapper.frames == 301
    assert np.array_equal(mapper.store.times, 0.01 * np.arange(301))


def test_a_growing_mapper_starts_around_its_first_camera_and_sections_may_be_dicts(tmp_path):
    """`Mapper.growing` puts the first box around the first camera (grid/extent.py first_box, by
    hand: +-margin_m 0.1 m in x, y rounded up to whole 0.11 m cells, +-height_m 1.5 m in z: 2 and
    28 cells); a config section given as a dict keeps the defaults of the keys it lacks and names
    a mistyped one; a snapshot into an existing folder says which folder."""
    from virus_nerf.engine.config import MapperConfig

    config = MapperConfig(extent={"mode": "grow"}, max_steps=10, max_time=None)
    assert config.extent.mode == "grow" and config.extent.grid_cell_m == 0.11
    with pytest.raises(ValueError, match=r"extent \{'mdoe': 'grow'\}: unknown key\(s\) \['mdoe'\]; expected keys of "
                                         r"ExtentConfig: \['mode', "):
        MapperConfig(extent={"mdoe": "grow"})
    with pytest.raises(ValueError, match=r"extent 3: expected ExtentConfig or a dict of its keys"):
        MapperConfig(extent=3)
    mapper = Mapper.growing(MapperConfig(), {1: INTR, 3: INTR}, np.array([10.0, 5.0, 0.5]))
    assert mapper.config.extent.mode == "grow"
    np.testing.assert_allclose(mapper.box.lo, (10.0 - 0.11, 5.0 - 0.11, 0.5 - 14 * 0.11), atol=1e-12)
    np.testing.assert_allclose(mapper.box.hi, (10.0 + 0.11, 5.0 + 0.11, 0.5 + 14 * 0.11), atol=1e-12)
    with pytest.raises(UsageError, match=r"Mapper.growing first_position of shape \(2,\)"):
        Mapper.growing(MapperConfig(), {1: INTR}, [1.0, 2.0])
    far = _frame(1.0)
    far.cam_to_world[:3, 3] = (10.0 + 362.0, 5.0, 0.5)  # a pose in millimetres beside ones in metres
    with pytest.raises(UsageError, match=r"^frame at time 1.000 s \(its pose, SyncFrame.cam_to_world\): camera at "
                                         r"\(372.00, 5.00, 0.50\) m lies outside the map's frame .*; expected a drive "
                                         r"within it .* and poses in metres \(one in millimetres lands far outside\)"):
        mapper.add_frame(far)
    (tmp_path / "snap").mkdir()
    with pytest.raises(OutputExistsError, match=r"snap: output folder already exists; choose a new snapshot folder"):
        _mapper().snapshot(tmp_path / "snap")


def test_a_bad_optional_counter_of_a_state_is_refused_before_anything_loads():
    """rays, visible_share, prior_frames, ... were converted after the field, Adam and the counters
    had been loaded: a bad one left a half-loaded mapper behind a raw ValueError."""
    a = _mapper()
    for t in (0.0, 0.5, 1.0):
        a.add_frame(_frame(t))
    a.train(600.0, steps=3)
    state = a.state()
    for key, value, problem in (("rays", "x", "expected an integer >= 0, got 'x'"),
                                ("prior_frames", -1, "expected an integer >= 0, got -1"),
                                ("frames_at_start", 99, "99 is more than the state's 3 frames"),
                                ("visible_share", 1.5, r"expected a number in \[0, 1\], got 1.5"),
                                ("last_samples_per_ray", None, r"expected a number in \[0, inf\], got None")):
        b = _mapper()
        with pytest.raises(UsageError, match=rf"^Mapper.load_state state\['{key}'\]: {problem}$"):
            b.load_state({**state, key: value})
        assert b.step == 0 and b.seconds == 0.0 and b.samples == 0
    b = _mapper()
    b.load_state({**state, "frames_at_start": None})  # as a state saved before the first step
    assert b.step == 3


def test_a_bad_learning_rate_progress_or_a_non_finite_loss_changes_no_weight(tmp_path):
    """train_step(progress=nan) made every weight NaN (lr nan), and a NaN field maps everything
    free; a non-finite loss is skipped and counted, and the snapshot still writes."""
    mapper = _mapper()
    mapper.add_frame(_frame(0.0))
    mapper.train(600.0, steps=2)
    for bad in (float("nan"), -50.0, 1.5, "0.5", True):
        with pytest.raises(UsageError, match=r"^Mapper.train_step progress .*: expected a number in \[0, 1\] or None$"):
            mapper.train_step(progress=bad)
    before = {k: v.clone() for k, v in mapper.field.state_dict().items()}
    import virus_nerf.engine.mapper as engine

    real = engine.step_loss

    def nan_loss(*args, **kwargs):
        terms = real(*args, **kwargs)
        return dataclasses.replace(terms, total=terms.total * float("nan"))

    engine.step_loss = nan_loss
    try:
        mapper.train(600.0, steps=2)
    finally:
        engine.step_loss = real
    assert mapper.skipped_steps == 2 and mapper.step == 4 and mapper.last_loss is None
    assert all(torch.equal(before[k], v) for k, v in mapper.field.state_dict().items())
    info = mapper.snapshot(tmp_path / "s", n_rays=16, max_poses=1)
    assert info.loss is None
    mapper.train(600.0, steps=1)
    assert mapper.skipped_steps == 2 and mapper.last_loss is not None


def test_a_mapper_config_that_is_no_config_is_named():
    with pytest.raises(UsageError, match=r"^Mapper config: got a dict; expected a MapperConfig \(or a TrainConfig\)"):
        Mapper({"batch_size": 256}, {1: INTR}, BOX)


def test_optional_counters_held_as_numpy_numbers_load():
    """A state whose counters are numpy numbers (as code computing them with numpy would keep them)
    loads as one with Python numbers."""
    a = _mapper()
    for t in (0.0, 0.5):
        a.add_frame(_frame(t))
    a.train(600.0, steps=2)
    state = a.state()
    numpy_state = {**state, "rays": np.int64(state["rays"]), "prior_frames": np.int32(state["prior_frames"]),
                   "visible_share": np.float32(state["visible_share"])}
    b = _mapper()
    b.load_state(numpy_state)
    assert b.step == 2 and b.rays == state["rays"]
