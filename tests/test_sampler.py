"""Batch sampling on the real sample: shares, footprints and range conversion."""

from __future__ import annotations

import numpy as np
import pytest

from virus_nerf.sampler.batch import BatchSampler, BatchShares
from virus_nerf.sampler.frames import StackFootprints, build_frame_store
from virus_nerf.sensors import irs
from virus_nerf.sensors.camera import Intrinsics


@pytest.fixture(scope="module")
def store(sample_recording):
    return build_frame_store(sample_recording, ("train",), image_scale=0.25, with_depth=True)


def test_store_holds_train_frames_of_both_stacks(store, sample_recording):
    assert len(store) == 6  # 3 train frames per stack
    assert store.images.shape == (6, 120, 160, 3) and store.images.dtype == np.uint8
    assert list(store.stack_ids) == [1, 1, 1, 3, 3, 3]
    assert list(store.rows) == [0, 2, 4, 0, 2, 4]


def test_footprints_partition_pixels():
    fp = StackFootprints.of(Intrinsics(388.0, 388.0, 319.5, 239.5).scaled(0.25))
    assert fp.zone_start[-1] == (fp.irs_zone >= 0).sum()
    assert np.all(np.diff(fp.irs_zone[fp.zone_pixels]) >= 0)
    # 45 deg IRS field inside the ~78 deg camera; USS cone wider horizontally than IRS
    assert 0.2 < (fp.irs_zone >= 0).mean() < 0.45
    # the USS ellipse (55x35 deg) is wider than the IRS square (45x45 deg) but not as tall
    ax = np.degrees(np.arctan2(fp.dirs_cam[:, 0], fp.dirs_cam[:, 2]))
    ay = np.degrees(np.arctan2(fp.dirs_cam[:, 1], fp.dirs_cam[:, 2]))
    assert ax[fp.in_uss].max() > 25 > ax[fp.irs_zone >= 0].max() > 21
    assert ay[fp.in_uss].max() < 17.5 < ay[fp.irs_zone >= 0].max()


def test_shares_and_targets(store):
    sampler = BatchSampler(store, ("camera", "uss", "irs"), BatchShares(irs=0.4, uss=0.4))
    batch = sampler.sample(np.random.default_rng(0), 1000)
    assert len(batch) == 1000
    torch_norm = batch.directions.norm(dim=1)
    np.testing.assert_allclose(torch_norm.numpy(), 1.0, atol=1e-5)
    uss = batch.uss_range.numpy()
    # the first 400 rays are USS-cone rays: all carry their frame's (valid) echo range
    echo = store.uss_range[batch.frames.numpy()]
    np.testing.assert_allclose(uss[:400], echo[:400], rtol=1e-6)
    assert set(np.round(uss[:400].astype(float), 1)) == {0.8, 2.0}  # USS1 0.75 m, USS3 1.96 m
    # IRS rays: at least the valid-zone rays carry a range; ranges are >= the zone z-depth
    irs_r = batch.irs_range.numpy()[400:800]
    has_valid_zone = np.isfinite(store.irs_range[batch.frames.numpy()[400:800]]).any(axis=(1, 2))
    assert has_valid_zone.sum() > 100
    assert np.isfinite(irs_r[has_valid_zone]).all()  # IRS rays go to valid zones when there are any
    assert np.isnan(batch.rgbd_range.numpy()).all()  # rgbd not requested


def test_irs_range_is_z_depth_over_direction_z(store):
    sampler = BatchSampler(store, ("camera", "irs"))
    batch = sampler.sample(np.random.default_rng(1), 400)
    f = batch.frames.numpy()
    valid = np.isfinite(batch.irs_range.numpy())
    assert valid.any()
    pose = store.cam_to_world[f]
    dirs_cam = np.einsum("nji,nj->ni", pose[:, :3, :3], batch.directions.numpy().astype(np.float64))
    row, col = irs.zone_of_directions(dirs_cam)
    z = store.irs_range[f, row, col]
    np.testing.assert_allclose(batch.irs_range.numpy()[valid], (z / dirs_cam[:, 2])[valid], rtol=1e-4)


def test_camera_only_has_no_depth_targets_and_same_seed_same_batch(store):
    sampler = BatchSampler(store, ("camera",))
    a = sampler.sample(np.random.default_rng(5), 256)
    b = sampler.sample(np.random.default_rng(5), 256)
    assert np.isnan(a.irs_range.numpy()).all() and np.isnan(a.uss_range.numpy()).all()
    np.testing.assert_array_equal(a.rgb.numpy(), b.rgb.numpy())


def test_rgbd_range_matches_depth_map(store):
    sampler = BatchSampler(store, ("rgbd",))
    hw = store.height * store.width
    batch = sampler._rays(np.zeros(hw, dtype=np.int64), np.arange(hw, dtype=np.int64))  # every pixel of frame 0
    rng = batch.rgbd_range.numpy()
    mm = store.depths_mm[0].ravel()
    fp = store.footprints[1]
    ok = mm > 0
    np.testing.assert_allclose(rng[ok], mm[ok] / 1000.0 / fp.dirs_cam[ok, 2], rtol=1e-5)
    assert np.isnan(rng[~ok]).all()


def test_recent_frame_odds_by_hand():
    from virus_nerf.sampler.batch import recent_frame_odds

    # window 2 s from the newest (t = 10): frames at 8.5 and 10 are recent
    odds = recent_frame_odds(np.array([0.0, 3.0, 7.9, 8.5, 10.0]), share=0.6, window=2.0)
    np.testing.assert_allclose(odds, [0.08, 0.08, 0.08, 0.08 + 0.3, 0.08 + 0.3])
    np.testing.assert_allclose(recent_frame_odds(np.array([1.0, 2.0]), 0.0, 5.0), [0.5, 0.5])
