"""Which sensors a run trains and how the batch is shared among them (`SENSORS`, `BatchShares`),
apart from the sampler so that a config, a flag or `--help` reads them without loading torch."""

from __future__ import annotations

from dataclasses import dataclass

SENSORS = ("camera", "uss", "irs", "rgbd", "stereo")


@dataclass(frozen=True)
class BatchShares:
    """Shares of the batch drawn from IRS-zone pixels, USS-cone pixels and tracked pixels with a
    triangulated depth (the `stereo` sensor); the rest are random pixels."""

    irs: float = 0.4  # of the batch, from IRS-zone pixels
    uss: float = 0.4  # from USS-cone pixels
    stereo: float = 0.1  # from tracked pixels with a triangulated depth
