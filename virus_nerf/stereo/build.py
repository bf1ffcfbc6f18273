"""The stereo pre-pass of a recording: every training frame through a StereoBuilder, cached.

Tracking reads the recording's full-resolution images (the decoded training store holds only the
training resolution). The result is kept in the user cache beside the decoded frames
(utils.cache), under a key of every image file's bytes, the poses, the settings and
the training resolution, so a second run on the same recording skips it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data.ethz import Recording
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.stereo.depth import StereoBuilder, StereoConfig, StereoDepth
from virus_nerf.utils.cache import cache_root
from virus_nerf.utils.io import atomic_path

FORMAT_VERSION = 1  # bump when tracking or triangulation change what a key means
_FIELDS = ("frames", "uv", "ranges", "sigmas", "points")


def _key(recording: Recording, frames: FrameList, cfg: StereoConfig) -> str:
    h = hashlib.blake2b(digest_size=20)
    sizes = {str(s): [i.width, i.height] for s, i in sorted(frames.train_intrinsics.items())}
    # the filters the pass ran with; the small room's alternatives are not the pass's settings (a pass
    # with 3 views and 5 % is one pass however it was asked for, and older caches keep their keys)
    settings = {"v": FORMAT_VERSION, "cfg": {k: v for k, v in dataclasses.asdict(cfg).items()
                                             if not k.startswith("small_room_")}, "sizes": sizes}
    h.update(json.dumps(settings, sort_keys=True).encode())
    h.update(np.ascontiguousarray(frames.stack_ids).tobytes() + np.ascontiguousarray(frames.rows).tobytes())
    h.update(np.ascontiguousarray(frames.cam_to_world, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(frames.times, dtype=np.float64).tobytes())
    for s, i in zip(frames.stack_ids, frames.rows, strict=True):
        h.update(Path(recording.stacks[int(s)].image_paths[int(i)]).read_bytes())
    return h.hexdigest()


def _load(path: Path) -> StereoDepth | None:
    try:
        with np.load(path) as z:
            return StereoDepth(**{name: z[name] for name in _FIELDS})
    except (OSError, ValueError, KeyError):
        return None  # missing or damaged: compute again


def _store(path: Path, depth: StereoDepth) -> None:
    """Atomic write; a cache that cannot be written is skipped, never an error."""
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:  # a file: given a name, savez adds .npz
            np.savez(f, **{name: getattr(depth, name) for name in _FIELDS})
    except OSError:
        return


@dataclass(frozen=True)
class FrameList:
    """Which frames of a recording, in which order (row r = the r-th target frame), and the
    training image size per stack: what a FrameStore holds, without its pixels."""

    stack_ids: np.ndarray  # (F,) int
    rows: np.ndarray  # (F,) sample index within the stack
    times: np.ndarray  # (F,) s
    cam_to_world: np.ndarray  # (F, 4, 4)
    train_intrinsics: dict[int, Intrinsics]  # per stack, at training resolution


def stereo_depth(recording: Recording, frames: FrameList, cfg: StereoConfig | None = None,
                 use_cache: bool = True, progress: bool = False) -> StereoDepth:
    """Triangulated depth targets for `frames` of `recording` (`FrameStore.frame_list()`: the
    targets' frame rows are the store's rows)."""
    cfg = StereoConfig() if cfg is None else cfg
    root = cache_root() if use_cache else None
    path = root / "stereo" / f"{_key(recording, frames, cfg)}.npz" if root is not None else None
    if path is not None and path.is_file():
        cached = _load(path)
        if cached is not None:
            return cached
    builder = StereoBuilder({s: st.intrinsics for s, st in recording.stacks.items()}, frames.train_intrinsics, cfg)
    order = np.argsort(frames.times, kind="stable")
    if progress:
        from tqdm import tqdm

        order = tqdm(order, desc="tracking (stereo)", unit="img", leave=False)
    for r in order:
        s, i = int(frames.stack_ids[r]), int(frames.rows[r])
        builder.add(int(r), s, float(frames.times[r]), frames.cam_to_world[r], recording.stacks[s].image(i))
    depth = builder.result()
    if path is not None:
        _store(path, depth)
    return depth
