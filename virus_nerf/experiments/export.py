"""Former home of `virus-nerf export`; the command now lives in `virus_nerf.exports`."""

from virus_nerf.exports.command import export
from virus_nerf.exports.maps import (
           FREE,
           MAX_PIXELS,
           OCCUPIED,
           UNKNOWN,
           OccupancyMap2D,
           scan_occupancy,
           write_map_server,
)

__all__ = ["FREE", "MAX_PIXELS", "OCCUPIED", "UNKNOWN", "OccupancyMap2D", "export", "scan_occupancy",
           "write_map_server"]
