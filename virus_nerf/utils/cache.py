"""The user cache folder shared by the decoded frames (sampler.frame_cache) and the stereo pass
(stereo.build): never inside an input folder, keyed by content, safe to delete at any time.

Folder: $VIRUS_NERF_CACHE_DIR, else $XDG_CACHE_HOME/virus-nerf, else ~/.cache/virus-nerf.
Set VIRUS_NERF_CACHE_DIR=off to disable it.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path | None:
    """The cache folder, or None when disabled."""
    env = os.environ.get("VIRUS_NERF_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "virus-nerf"
