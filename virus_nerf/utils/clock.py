"""Wall clock from the command's start: what a user waits for, not what a profiler sees.

Time to map is counted from the moment the process started (interpreter start-up, imports,
decoding and compilation included). On Linux the kernel knows that moment (/proc); elsewhere
the first import of this package stands in for it (a few hundred milliseconds later).
"""

from __future__ import annotations

import os
import time

_IMPORTED_AT = time.time()


def _linux_process_age() -> float | None:
    """Seconds since this process started, from /proc (10 ms resolution), or None."""
    try:
        with open("/proc/self/stat") as fh:
            stat = fh.read()
        with open("/proc/uptime") as fh:
            uptime = float(fh.read().split()[0])
        # field 22 (starttime, clock ticks since boot); the command name (field 2) may hold spaces
        start_ticks = int(stat.rsplit(")", 1)[1].split()[19])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def _process_start() -> float:
    age = _linux_process_age()
    return time.time() - age if age is not None else _IMPORTED_AT


PROCESS_START = _process_start()  # time.time() at which this process started


def since_process_start() -> float:
    """Seconds of wall clock since this process started."""
    return time.time() - PROCESS_START
