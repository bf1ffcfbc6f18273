"""PCD point clouds (LiDAR scans and the global map) through pypcd4, with clear errors."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError, one_line
from virus_nerf.utils.io import atomic_path

# Points of a PCD (LiDAR scan or map, metres) lie within this distance of the origin on every axis;
# a coordinate beyond it is a garbage body (random bytes read as floats) or wrong units (mm).
MAX_ABS_COORD_M = 10_000.0


def _header_problem(exc: Exception) -> str:
    """pypcd4's refusal in one short line: its header model's (pydantic) first error as the PCD
    header line it concerns ("header line SIZE missing", "header TYPE, value 1: ..."), else the
    exception's own text."""
    errors = getattr(exc, "errors", None)
    try:
        first = errors()[0] if callable(errors) else None
    except Exception:  # noqa: BLE001 - not pydantic's: its own text below
        first = None
    if not isinstance(first, dict) or not first.get("loc"):
        return one_line(exc, 200)
    line, *index = (str(v) for v in first["loc"])
    where = f"header {line.upper()}" + (f", value {int(index[0]) + 1}" if index and index[0].isdigit() else "")
    if first.get("type") == "missing":
        return f"header line {line.upper()} missing"
    return f"{where}: {one_line(first.get('msg', ''), 120)} (got {one_line(repr(first.get('input')), 40)})"


def read_pcd_xyz(path: str | Path, *, nonempty: str | None = None) -> np.ndarray:
    """Read the x, y, z fields of a PCD file -> (N, 3) float32 (NaN and infinite points removed).

    Refused with a DataFormatError naming the file: an unreadable header, a body shorter than the
    header's POINTS, a coordinate beyond MAX_ABS_COORD_M and, if `nonempty` names what the file is
    (e.g. "the LiDAR map"), a file without a single finite point.
    """
    from pypcd4 import PointCloud

    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "PCD file not found")
    raw = path.read_bytes()
    if not raw.strip():
        raise DataFormatError(path, "empty file; expected a PCD file (a VERSION .. DATA header, then the points)")
    npoints = _check_body_size(path, raw)
    try:
        cloud = PointCloud.from_fileobj(io.BytesIO(raw))  # type: ignore[arg-type]
    except Exception as exc:  # pypcd4 raises several types for bad headers/encodings
        raise DataFormatError(
            path, f"not a readable PCD file (expected ascii/binary/binary_compressed): {_header_problem(exc)}"
        ) from None
    missing = [f for f in ("x", "y", "z") if f not in cloud.fields]
    if missing:
        raise DataFormatError(
            path, f"PCD has fields {list(cloud.fields)}; expected x, y, z", field=",".join(missing)
        )
    data = np.atleast_1d(cloud.pc_data)
    if npoints is not None and len(data) != npoints:
        raise DataFormatError(path, f"header says {npoints} points, body holds {len(data)}")
    try:
        with np.errstate(invalid="ignore", over="ignore"):  # signalling NaNs of a garbage body
            xyz = np.stack([np.asarray(data[f], dtype=np.float64).reshape(len(data)) for f in ("x", "y", "z")],
                           axis=1)
    except (ValueError, TypeError, KeyError) as exc:  # e.g. COUNT 2 for x
        raise DataFormatError(path, f"fields x, y, z are not one number each per point: {one_line(exc, 200)}") from None
    finite = np.isfinite(xyz).all(axis=1)
    far = np.flatnonzero(finite & (np.abs(xyz).max(axis=1) > MAX_ABS_COORD_M))
    if far.size:
        k = int(far[0])
        x, y, z = xyz[k]
        raise DataFormatError(path, f"point {k} of {len(xyz)} ({x:.3g}, {y:.3g}, {z:.3g}) lies beyond "
                                    f"{MAX_ABS_COORD_M / 1000:g} km of the origin; expected metres (a garbage "
                                    "body or wrong units?)")
    if nonempty is not None and not finite.any():
        detail = f" (all {len(xyz)} points are NaN or infinite)" if len(xyz) else ""
        raise DataFormatError(path, f"{nonempty} has no points{detail}; expected the room's map as x y z points "
                                    "in metres")
    return xyz[finite].astype(np.float32)


def _check_body_size(path: Path, raw: bytes) -> int | None:
    """POINTS of the header, after checking that a binary body holds that many points.

    Reads the header as pypcd4 does (up to the DATA line, at most 10 lines). None where the header
    cannot be parsed here: pypcd4 then reports it."""
    from pypcd4.pypcd4 import MetaData

    lines: list[str] = []
    offset = 0
    for bline in raw.splitlines(keepends=True):
        offset += len(bline)
        try:
            line = bline.decode("utf-8").strip()
        except UnicodeDecodeError:
            raise DataFormatError(path, "PCD header is not text (a byte that is not UTF-8 in line "
                                        f"{len(lines) + 1}); expected a PCD file") from None
        if line.startswith("#") or not line:
            continue
        lines.append(line)
        if line.startswith("DATA") or len(lines) >= 10:
            break
    if lines and not lines[-1].startswith("DATA"):  # pypcd4 would read on as binary_compressed
        raise DataFormatError(path, "not a readable PCD file: no DATA line in the header's first 10 lines; "
                                    "expected DATA ascii, binary or binary_compressed after POINTS")
    try:
        meta = MetaData.parse_header(lines)
        itemsize = meta.build_dtype().itemsize
    except Exception:  # noqa: BLE001 - reported by pypcd4's own reading below
        return None
    points, body = meta.points, len(raw) - offset
    need = points * itemsize
    if meta.data.value == "binary" and body < need:
        part = body % itemsize
        tail = f" (and {part} bytes of a partial point)" if part else ""
        raise DataFormatError(path, f"header says {points} points, body holds {body // itemsize}{tail}; "
                                    "truncated file?")
    if meta.data.value == "binary_compressed" and points > 0:
        if body < 8:
            raise DataFormatError(path, f"header says {points} points, the compressed body has no size fields; "
                                        "truncated file?")
        packed, unpacked = struct.unpack("<II", raw[offset:offset + 8])
        if unpacked != need:
            raise DataFormatError(path, f"header says {points} points ({need} bytes), the compressed body "
                                        f"unpacks to {unpacked} bytes")
        if packed > body - 8:
            raise DataFormatError(path, f"header says {points} points, the compressed body holds {body - 8} of "
                                        f"{packed} bytes; truncated file?")
    return points


def write_pcd_xyz(path: str | Path, xyz: np.ndarray) -> None:
    """Write (N, 3) points as a binary PCD with float32 x y z (atomically)."""
    from pypcd4 import PointCloud

    xyz = np.ascontiguousarray(np.asarray(xyz, dtype=np.float32).reshape(-1, 3))
    cloud = PointCloud.from_xyz_points(xyz)
    with atomic_path(path) as tmp:
        cloud.save(tmp)
