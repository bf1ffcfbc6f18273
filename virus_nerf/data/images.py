"""Colour images and aligned depth maps of the ETHZ layout, read one at a time (docs/method.md 4).

Colour: any image PIL reads, returned as RGB uint8 (H, W, 3). Depth: .npy of unsigned 16-bit
millimetres (0 and 65535 invalid), returned in metres with NaN where invalid. Every problem is
a DataFormatError naming the file.
"""

from __future__ import annotations

import struct
import tokenize
import zlib
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError, one_line
from virus_nerf.sensors.camera import Intrinsics

DEPTH_INVALID_MM = (0, 65535)
# PIL's modes of more than 8 bits a pixel, which a colour image of the layout never has
WIDE_MODES = {"I": "32-bit integer grey", "F": "32-bit float grey", "I;16": "16-bit grey", "I;16B": "16-bit grey",
              "I;16L": "16-bit grey", "I;16N": "16-bit grey"}
# What PIL raises on a damaged image file besides DecompressionBombError: OSError (unidentified,
# truncated), and from deep inside its decoders SyntaxError, ValueError, EOFError, struct/zlib errors.
IMAGE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, IndexError, struct.error, zlib.error)
# What numpy raises on a damaged .npy header (it parses the header dict with ast.literal_eval) or body.
NPY_ERRORS = (OSError, ValueError, EOFError, SyntaxError, TypeError, KeyError, OverflowError, MemoryError,
              tokenize.TokenError)


def read_rgb(path: Path, intr: Intrinsics) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            mode = im.mode
            wide = mode in ("I", "F") or mode.startswith("I;")  # convert("RGB") would clip them to white
            arr = None if wide else np.asarray(im.convert("RGB"))
    except FileNotFoundError:
        raise DataFormatError(path, "image file not found") from None
    except Image.DecompressionBombError as exc:
        raise huge_image_error(path, exc) from None
    except IMAGE_ERRORS as exc:
        raise DataFormatError(path, f"not a readable image: {one_line(exc, 200)}") from None
    if arr is None:
        raise DataFormatError(path, f"image mode {mode} ({WIDE_MODES.get(mode, 'more than 8 bits a pixel')}); "
                                    "expected 8-bit colour or grey (RGB, RGBA, P, L)")
    if arr.shape[:2] != (intr.height, intr.width):
        raise DataFormatError(
            path, f"image is {arr.shape[1]}x{arr.shape[0]}; the intrinsics expect {intr.width}x{intr.height}"
        )
    return arr


def read_depth(path: Path, intr: Intrinsics) -> np.ndarray:
    """An aligned depth map: .npy of unsigned 16-bit integers in millimetres (0 and 65535 invalid).

    Other integer types are accepted if every value fits 0..65535; floating-point maps are
    refused (a float map is usually in metres, and reading it as millimetres would shrink the
    scene 1000 times).
    """
    shape, _ = _npy_header(path)  # the shape before the pixels: a corrupt header must not allocate
    if shape != (intr.height, intr.width):
        raise DataFormatError(path, f"depth map has shape {shape}; expected ({intr.height}, {intr.width})")
    try:
        raw = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DataFormatError(path, "depth file not found") from None
    except NPY_ERRORS as exc:
        raise DataFormatError(path, f"not a readable .npy depth map: {one_line(exc, 200)}") from None
    if not isinstance(raw, np.ndarray):
        raise DataFormatError(path, "not a .npy array; expected a uint16 depth map in millimetres")
    if raw.shape != (intr.height, intr.width):
        raise DataFormatError(path, f"depth map has shape {raw.shape}; expected ({intr.height}, {intr.width})")
    if raw.dtype.kind == "f":
        finite = raw[np.isfinite(raw)]
        top = float(finite.max()) if finite.size else float("nan")
        hint = f" (values up to {top:.3g} look like metres)" if finite.size and top < 100 else ""
        raise DataFormatError(
            path, f"depth map is {raw.dtype}{hint}; expected uint16 millimetres (e.g. (metres * 1000).astype(np.uint16))"
        )
    if raw.dtype.kind not in "ui":
        raise DataFormatError(path, f"depth map is {raw.dtype}; expected uint16 millimetres")
    if raw.dtype != np.uint16 and raw.size and (raw.min() < 0 or raw.max() > 65535):
        raise DataFormatError(
            path, f"depth map ({raw.dtype}) has values {raw.min()}..{raw.max()}; expected uint16 millimetres 0..65535"
        )
    return depth_from_mm(raw)


DEPTH_MAX_MM = 65534  # the largest valid reading of a uint16 depth map (65535 and 0 are invalid)


def depth_to_mm(metres: np.ndarray) -> np.ndarray:
    """z-depth in metres -> uint16 millimetres, 0 (invalid) where not finite, not positive once
    rounded, or beyond DEPTH_MAX_MM (a reading out of the map's range is no reading, not one at its
    end): the inverse of `depth_from_mm`, for the frame store, the exports and depth messages."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.round(np.asarray(metres, dtype=np.float64) * 1000.0)
        ok = np.isfinite(mm) & (mm > 0) & (mm <= DEPTH_MAX_MM)
    return np.where(ok, mm, 0.0).astype(np.uint16)


def depth_from_mm(mm: np.ndarray) -> np.ndarray:
    """Depth in integer millimetres -> float32 metres, NaN where invalid (DEPTH_INVALID_MM): the one
    rule for a .npy map here and for a depth message (data/bags/messages.py)."""
    depth = mm.astype(np.float32) / 1000.0
    depth[np.isin(mm, DEPTH_INVALID_MM)] = np.nan
    return depth


def check_depth_header(path: Path, intr: Intrinsics) -> None:
    """Shape and type of a depth map from its .npy header alone (no pixels are read)."""
    shape, dtype = _npy_header(path)
    if shape != (intr.height, intr.width):
        raise DataFormatError(path, f"depth map has shape {shape}; expected ({intr.height}, {intr.width})")
    if dtype.kind == "f":
        raise DataFormatError(
            path, f"depth map is {dtype} (metres?); expected uint16 millimetres (e.g. (metres * 1000).astype(np.uint16))"
        )
    if dtype.kind not in "ui":
        raise DataFormatError(path, f"depth map is {dtype}; expected uint16 millimetres")


def _npy_header(path: Path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) from a .npy file's header; a damaged header is a DataFormatError."""
    try:
        with path.open("rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            shape, _, dtype = read_header(fh)
    except FileNotFoundError:
        raise DataFormatError(path, "depth file not found") from None
    except NPY_ERRORS as exc:
        raise DataFormatError(path, f"not a readable .npy depth map: {one_line(exc, 200)}") from None
    return shape, dtype


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataFormatError(path, "image file not found") from None
    except Image.DecompressionBombError as exc:
        raise huge_image_error(path, exc) from None
    except IMAGE_ERRORS as exc:
        raise DataFormatError(path, f"not a readable image: {one_line(exc, 200)}") from None


def huge_image_error(path: Path, exc: Exception) -> DataFormatError:
    """The error for an image whose header claims more pixels than PIL will decode (a corrupt
    header, or a decompression bomb): names the size the header claims where it can be read."""
    from PIL import Image

    limit = 2 * (Image.MAX_IMAGE_PIXELS or 0)  # PIL refuses above twice its warning threshold
    size = _png_header_size(path)
    claim = f"{size[0]}x{size[1]} px ({size[0] * size[1] / 1e6:.0f} Mpx)" if size else one_line(exc, 120)
    return DataFormatError(path, f"image header claims {claim}, beyond the {limit / 1e6:.0f} Mpx an image may "
                                 "have; corrupt file?")


def _png_header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if `path` is no PNG."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if len(head) < 24 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])
