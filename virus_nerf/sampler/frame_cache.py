"""Decoded training frames kept between runs, so a second run on a recording starts at once.

Decoding and resizing every colour (and depth) image is the largest part of a run's start-up
on a real recording. The decoded arrays are stored in a user cache folder (never inside the
input folder), under a key made from the bytes of every image file used and the decoding
settings: a changed, added or removed image gives a new key, so a stale entry is never read.
Entries are written under a temporary name and renamed, so a killed run leaves no half entry.

Folder: $VIRUS_NERF_CACHE_DIR, else $XDG_CACHE_HOME/virus-nerf, else ~/.cache/virus-nerf;
`frames/<key>/{images,depths}.npy`. Set VIRUS_NERF_CACHE_DIR=off to disable it.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from virus_nerf.utils.cache import cache_root

FORMAT_VERSION = 1  # bump when the decoding (resize filter, depth encoding) changes


def frames_key(files: Sequence[Path], size: tuple[int, int], with_depth: bool) -> str:
    """Hex digest over the decoding settings and the bytes of every file, in order."""
    h = hashlib.blake2b(digest_size=20)
    h.update(f"v{FORMAT_VERSION};{size[0]}x{size[1]};depth={int(with_depth)};n={len(files)}".encode())
    for path in files:
        data = Path(path).read_bytes()
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)
    return h.hexdigest()


def load_frames(key: str) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(images (F, H, W, 3) uint8, depths (F, H, W) uint16 or None), memory-mapped; None on a miss."""
    root = cache_root()
    if root is None:
        return None
    entry = root / "frames" / key
    try:
        images = np.load(entry / "images.npy", mmap_mode="r")
        depth_file = entry / "depths.npy"
        depths = np.load(depth_file, mmap_mode="r") if depth_file.is_file() else None
    except (OSError, ValueError):
        return None  # missing or damaged: decode again
    return images, depths


def store_frames(key: str, images: np.ndarray, depths: np.ndarray | None) -> None:
    """Write an entry atomically; a cache that cannot be written is skipped, never an error."""
    root = cache_root()
    if root is None:
        return
    final = root / "frames" / key
    if final.exists():
        return
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}.partial-", dir=final.parent))
        try:
            np.save(tmp / "images.npy", images)
            if depths is not None:
                np.save(tmp / "depths.npy", depths)
            os.replace(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    except OSError:
        return
