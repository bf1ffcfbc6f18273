"""What memory this process may use, and a one-line refusal of a size that cannot fit (issue 30)."""

from __future__ import annotations

import os
from pathlib import Path

from virus_nerf.errors import UsageError


def memory_limit() -> int | None:
    """Bytes of memory this process may use: the machine's RAM, or a smaller cgroup limit or
    address-space limit (`ulimit -v`, systemd's LimitAS=)."""
    import resource

    limits = []
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        limits.append(int(soft))
    try:
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 1 << 60:
            limits.append(int(text))
    return min(limits) if limits else None


def require_memory(what: str, nbytes: float, expected: str, limit: int | None = None) -> None:
    """A UsageError naming `what` when `nbytes` is more than half the memory this process may use
    (the rest holds the frames, the network and its optimiser); `expected` says what to change."""
    limit = memory_limit() if limit is None else limit
    if limit is not None and nbytes > limit / 2:
        raise UsageError(f"{what}: would need {nbytes / 2**30:.1f} GiB and this machine has "
                         f"{limit / 2**30:.1f} GiB; expected {expected}")
