"""The report of one `import_bag`: what was written and what was dropped, per topic and reason."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from virus_nerf.data.bags.sync import TopicReport

REPORT_NAME = "import_report.json"


@dataclass
class ImportReport:
    """What an import wrote and dropped (also saved as DATA/import_report.json)."""

    bag: str
    data_dir: str  # the ETHZ data folder: pass it as --data, with --room `room`
    room: str
    ros_version: int
    poses: str
    samples: dict[int, int]  # stack -> samples written
    lidar_scans: int
    map_points: int
    topics: list[TopicReport]
    dropped_frames: dict[int, dict[str, int]]  # stack -> reason -> colour frames dropped
    pose_settings: dict | None = None
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for t, rep in zip(d["topics"], self.topics, strict=True):
            t["dropped"] = rep.dropped
        return d

    def summary(self) -> str:
        lines = [f"imported {self.bag} (ROS {self.ros_version}) -> {self.data_dir}, room {self.room!r}",
                 f"  poses: {self.poses}; samples per stack: "
                 + ", ".join(f"{s}: {n}" for s, n in self.samples.items())
                 + f"; LiDAR scans: {self.lidar_scans}; map points: {self.map_points}"]
        for t in self.topics:
            lines.append(f"  {t.topic:<45} {t.role:<11} {t.messages:>6} messages, {t.used:>6} used, "
                         f"{t.dropped:>6} dropped")
        for s, reasons in self.dropped_frames.items():
            for why, n in reasons.items():
                lines.append(f"  stack {s}: {n} colour frames dropped ({why})")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)
