"""The topics file of `import-bag`: which topics hold which sensor, the rig, sync tolerances.

Defaults are the ETHZ robot as the simulator models it (virus_nerf/sensors/rig.py): stacks 1 and 3,
their cameras in the LiDAR frame. USS and IRS share their camera's origin and axes in the ETHZ
layout (docs/method.md 4), so the file has no USS/IRS extrinsics: mount them next to the camera,
looking along its optical axis. A TOML file replaces the defaults (read with tomllib); every key
is checked and an unknown key is refused naming the file and the dotted key.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from virus_nerf.data.bags.odometry import KissIcpSettings
from virus_nerf.errors import ConfigError
from virus_nerf.sensors.geometry import QUATERNION_NORM_TOLERANCE, pose_matrix

MAX_MOUNT_M = 5.0  # a camera farther from its LiDAR is a unit mistake (a translation in millimetres)


@dataclass(frozen=True)
class StackTopics:
    """Topics of one sensor stack; None = the robot has no such sensor (readings written invalid)."""

    color: str
    depth: str | None = None
    camera_info: str | None = None
    uss: str | None = None
    tof: str | None = None
    # camera in the LiDAR frame: translation (m) and quaternion x y z w
    camera_in_lidar_translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    camera_in_lidar_rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def camera_in_lidar(self) -> np.ndarray:
        """(4, 4) camera-to-LiDAR transform."""
        return pose_matrix(np.array(self.camera_in_lidar_translation), np.array(self.camera_in_lidar_rotation_xyzw))

    def roles(self) -> dict[str, str]:
        """role -> topic for the topics this stack names."""
        out = {"color": self.color, "depth": self.depth, "camera_info": self.camera_info,
               "uss": self.uss, "tof": self.tof}
        return {k: v for k, v in out.items() if v}


@dataclass(frozen=True)
class SyncConfig:
    """Nearest-timestamp matching to each colour frame (s); a frame without a partner within the
    tolerance is dropped. camera_rate_hz thins the colour frames to at most this rate (0 = all)."""

    depth_tolerance_s: float = 0.02
    uss_tolerance_s: float = 0.15
    tof_tolerance_s: float = 0.15
    pose_tolerance_s: float = 0.1
    camera_rate_hz: float = 0.0


@dataclass(frozen=True)
class LidarConfig:
    """LiDAR topic and the range filter of the written scans (m; the RS-16's 0.3-30 m).

    flat_floor: the robot drives on one flat floor, so KISS-ICP registers the motion along it
    only (odometry.KissIcpSettings `planar`); false registers in 6 degrees of freedom, for a floor
    that is no plane at all (not measured; on a ramp it does no better, D119)."""

    topic: str | None = "/rslidar_points"
    min_range_m: float = 0.3
    max_range_m: float = 30.0
    flat_floor: bool = True

    def kiss_settings(self, settings: KissIcpSettings | None = None) -> KissIcpSettings:
        """KISS-ICP's settings for this LiDAR: `settings` (default KissIcpSettings()), planar only
        on a flat floor."""
        s = settings or KissIcpSettings()
        return s if self.flat_floor or not s.planar else dataclasses.replace(s, planar=False)


@dataclass(frozen=True)
class TopicsConfig:
    """Everything `import-bag` needs to know about a robot besides the bag itself."""

    stacks: dict[int, StackTopics]
    lidar: LidarConfig = field(default_factory=LidarConfig)
    sync: SyncConfig = field(default_factory=SyncConfig)
    tf_topics: tuple[str, ...] = ("/tf", "/tf_static")
    intrinsics_csv: Path | None = None  # used for stacks without a camera_info topic
    source: Path | None = None  # the file read (None = built-in defaults)
    notes: tuple[str, ...] = ()  # what the import report should say about the file (e.g. defaults used)
    lidar_named: bool = False  # the file names lidar.topic: a bag without it is refused, not taken as LiDAR-less

    def for_sensors(self, sensors) -> TopicsConfig:
        """The topics a stream that trains `sensors` needs: without the depth images unless `rgbd`
        is trained (map-bag's stream and the ROS 2 node neither require, read nor wait for them)."""
        if "rgbd" in sensors:
            return self
        return dataclasses.replace(self, stacks={s: dataclasses.replace(st, depth=None) for s, st in self.stacks.items()})


def ethz_stack(s: int) -> StackTopics:
    """Topics of ETHZ stack s with the simulator's camera-in-LiDAR mounting."""
    from virus_nerf.sensors.rig import CAMERA_IN_LIDAR

    t, q = CAMERA_IN_LIDAR[s]
    return StackTopics(
        color=f"/CAM{s}/color/image_raw", depth=f"/CAM{s}/aligned_depth_to_color/image_raw",
        camera_info=f"/CAM{s}/color/camera_info", uss=f"/USS{s}", tof=f"/TOF{s}",
        camera_in_lidar_translation=t, camera_in_lidar_rotation_xyzw=q,
    )


def default_topics() -> TopicsConfig:
    """The ETHZ recording's topics (stacks 1 and 3)."""
    return TopicsConfig(stacks={1: ethz_stack(1), 3: ethz_stack(3)})


def read_topics(path: str | Path) -> TopicsConfig:
    """Read a topics TOML file; unknown keys and wrong types are refused naming the key."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError("topics file not found", file=path) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"not valid TOML: {exc}", file=path) from None
    r = _Reader(path)
    r.keys(doc, "", {"stacks", "lidar", "sync", "tf_topics", "intrinsics_csv"})
    stacks_doc = doc.get("stacks", None)
    notes: tuple[str, ...] = ()
    if stacks_doc is None:
        stacks = default_topics().stacks
        notes = (f"{path}: no [stacks] section: the ETHZ robot's stacks "
                 f"{' and '.join(str(s) for s in sorted(stacks))} are used "
                 f"({', '.join(stacks[s].color for s in sorted(stacks))}, ...)",)
    else:
        if not isinstance(stacks_doc, dict) or not stacks_doc:
            raise ConfigError("expected a table of stacks ([stacks.1], [stacks.3], ...)", file=path, key="stacks")
        stacks = {}
        for sid, table in stacks_doc.items():
            key = f"stacks.{sid}"
            if not (sid.isascii() and sid.isdigit()):  # not '¹' or '٣', which isdigit() accepts and int() not
                raise ConfigError(f"stack id {sid!r}: expected a non-negative integer (digits 0-9)", file=path, key=key)
            if int(sid) in stacks:  # [stacks.1] and [stacks.01]: the second would replace the first unsaid
                first = next(other for other in stacks_doc if other.isascii() and other.isdigit()
                             and int(other) == int(sid))
                raise ConfigError(f"stack {int(sid)} is given twice (stacks.{first} and stacks.{sid}); expected one "
                                  "table per stack", file=path, key=key)
            stacks[int(sid)] = r.stack(table, key)
    lidar = r.section(doc.get("lidar", {}), "lidar", LidarConfig, optional_str={"topic"})
    sync = r.section(doc.get("sync", {}), "sync", SyncConfig)
    for k in ("depth_tolerance_s", "uss_tolerance_s", "tof_tolerance_s", "pose_tolerance_s"):
        if getattr(sync, k) <= 0:
            raise ConfigError(f"{getattr(sync, k)}: expected a number > 0", file=path, key=f"sync.{k}")
    if sync.camera_rate_hz < 0:
        raise ConfigError(f"{sync.camera_rate_hz}: expected a number >= 0", file=path, key="sync.camera_rate_hz")
    if not 0 <= lidar.min_range_m < lidar.max_range_m:
        raise ConfigError("expected 0 <= min_range_m < max_range_m", file=path, key="lidar.max_range_m")
    tf = doc.get("tf_topics", ["/tf", "/tf_static"])
    if not isinstance(tf, list) or not all(isinstance(t, str) for t in tf):
        raise ConfigError(f"{tf!r}: expected a list of topic names", file=path, key="tf_topics")
    intr = doc.get("intrinsics_csv")
    if intr is not None and not isinstance(intr, str):
        raise ConfigError(f"{intr!r}: expected a path string", file=path, key="intrinsics_csv")
    intr_path = None if intr is None else (path.parent / intr if not Path(intr).is_absolute() else Path(intr))
    return TopicsConfig(stacks=stacks, lidar=lidar, sync=sync, tf_topics=tuple(tf),
                        intrinsics_csv=intr_path, source=path, notes=notes,
                        lidar_named=bool(lidar.topic) and "topic" in doc.get("lidar", {}))


class _Reader:
    """Typed reading of TOML tables with errors naming the file and dotted key."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def keys(self, table, key: str, allowed: set[str]) -> None:
        if not isinstance(table, dict):
            raise ConfigError(f"expected a table, got {table!r}", file=self.path, key=key)
        unknown = sorted(set(table) - allowed)
        if unknown:
            where = f"{key}.{unknown[0]}" if key else unknown[0]
            raise ConfigError(f"unknown key; expected one of {', '.join(sorted(allowed))}", file=self.path, key=where)

    def number(self, value, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise ConfigError(f"{value!r}: expected a number", file=self.path, key=key)
        return float(value)

    def vector(self, value, n: int, key: str) -> tuple[float, ...]:
        if not isinstance(value, list) or len(value) != n:
            raise ConfigError(f"{value!r}: expected a list of {n} numbers", file=self.path, key=key)
        return tuple(self.number(v, f"{key}[{i}]") for i, v in enumerate(value))

    def topic(self, value, key: str) -> str | None:
        if value in (None, ""):
            return None
        if not isinstance(value, str) or not value.startswith("/"):
            raise ConfigError(f"{value!r}: expected a topic name starting with '/'", file=self.path, key=key)
        return value

    def section(self, table, key: str, cls, optional_str: set[str] = frozenset()):
        names = {f.name for f in fields(cls)}
        self.keys(table, key, names)
        flags = {f.name for f in fields(cls) if f.type in (bool, "bool")}
        values = {}
        for k, v in table.items():
            if k in flags:
                if not isinstance(v, bool):
                    raise ConfigError(f"{v!r}: expected true or false", file=self.path, key=f"{key}.{k}")
                values[k] = v
            else:
                values[k] = self.topic(v, f"{key}.{k}") if k in optional_str else self.number(v, f"{key}.{k}")
        return cls(**values)

    def stack(self, table, key: str) -> StackTopics:
        roles = ("color", "depth", "camera_info", "uss", "tof")
        self.keys(table, key, set(roles) | {"camera_in_lidar"})
        if not table.get("color"):
            raise ConfigError("missing: every stack needs its colour image topic", file=self.path, key=f"{key}.color")
        values = {r: self.topic(table.get(r), f"{key}.{r}") for r in roles}
        ext = table.get("camera_in_lidar")
        if ext is None:
            raise ConfigError("missing: the camera's mounting in the LiDAR frame "
                              "({ translation = [x, y, z], rotation_xyzw = [qx, qy, qz, qw] })",
                              file=self.path, key=f"{key}.camera_in_lidar")
        self.keys(ext, f"{key}.camera_in_lidar", {"translation", "rotation_xyzw"})
        t = self.vector(ext.get("translation"), 3, f"{key}.camera_in_lidar.translation")
        if (reach := float(np.linalg.norm(t))) > MAX_MOUNT_M:
            raise ConfigError(f"{list(t)} puts the camera {reach:g} m from the LiDAR; expected metres (a robot's "
                              f"camera within {MAX_MOUNT_M:g} m of its LiDAR: millimetres?)", file=self.path,
                              key=f"{key}.camera_in_lidar.translation")
        q = self.vector(ext.get("rotation_xyzw"), 4, f"{key}.camera_in_lidar.rotation_xyzw")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise ConfigError(f"quaternion norm {norm:.6g}; expected a unit quaternion (x, y, z, w)",
                              file=self.path, key=f"{key}.camera_in_lidar.rotation_xyzw")
        return StackTopics(**values, camera_in_lidar_translation=t,  # type: ignore[arg-type]
                           camera_in_lidar_rotation_xyzw=tuple(v / norm for v in q))  # type: ignore[arg-type]
