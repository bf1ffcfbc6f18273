"""Decoded frames are reused across runs, keyed by the image bytes, and never inside the input."""

import numpy as np
import pytest

from virus_nerf.data.ethz import load_recording
from virus_nerf.sampler import frame_cache
from virus_nerf.sampler.frames import build_frame_store


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from virus_nerf.sim.command import simulate

    out = tmp_path_factory.mktemp("sim") / "data"
    simulate(scene="office", out=out, seed=4, duration=2.0, resolution_scale=0.25)
    return out


def test_second_build_reads_the_cache_and_a_changed_image_is_decoded_again(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("VIRUS_NERF_CACHE_DIR", str(tmp_path / "cache"))
    before = sorted(p.relative_to(tiny) for p in tiny.rglob("*"))
    rec = load_recording(tiny, "office")
    first = build_frame_store(rec, ("train",), 0.5, with_depth=True)
    entries = list((tmp_path / "cache" / "frames").iterdir())
    assert len(entries) == 1 and (entries[0] / "images.npy").is_file() and (entries[0] / "depths.npy").is_file()
    # a second build decodes nothing: every image read would fail
    for stack in rec.stacks.values():
        monkeypatch.setattr(stack, "image", lambda i: (_ for _ in ()).throw(AssertionError("decoded")))
        monkeypatch.setattr(stack, "depth", lambda i: (_ for _ in ()).throw(AssertionError("decoded")))
    again = build_frame_store(rec, ("train",), 0.5, with_depth=True)
    np.testing.assert_array_equal(again.images, first.images)
    np.testing.assert_array_equal(again.depths_mm, first.depths_mm)
    monkeypatch.undo()
    monkeypatch.setenv("VIRUS_NERF_CACHE_DIR", str(tmp_path / "cache"))
    # another resolution or one changed image file: a new entry
    build_frame_store(load_recording(tiny, "office"), ("train",), 0.25)
    stack = next(iter(rec.stacks.values()))
    path = stack.image_paths[int(np.flatnonzero(stack.split == "train")[0])]
    path.write_bytes(path.read_bytes())  # same bytes: same key
    build_frame_store(load_recording(tiny, "office"), ("train",), 0.5, with_depth=True)
    assert len(list((tmp_path / "cache" / "frames").iterdir())) == 2
    from PIL import Image

    img = np.asarray(Image.open(path)).copy()
    img[0, 0] = 255 - img[0, 0]
    Image.fromarray(img).save(path)
    changed = build_frame_store(load_recording(tiny, "office"), ("train",), 0.5, with_depth=True)
    assert len(list((tmp_path / "cache" / "frames").iterdir())) == 3
    assert not np.array_equal(changed.images, first.images)
    assert sorted(p.relative_to(tiny) for p in tiny.rglob("*")) == before, "nothing written into the input"


def test_cache_can_be_switched_off(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("VIRUS_NERF_CACHE_DIR", "off")
    assert frame_cache.cache_root() is None
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    build_frame_store(load_recording(tiny, "office"), ("train",), 0.5)
    assert not (tmp_path / ".cache").exists()
