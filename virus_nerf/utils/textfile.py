"""Text input files read as UTF-8, with bytes that are not UTF-8 reported by row and column.

`decode_lenient` keeps such bytes (as surrogate escapes, so free-text cells such as a comment in
Latin-1 still read); a reader then refuses them only where the value matters, showing them as
`\\xNN` with `quoted`. `decode_strict` refuses them at once (JSON, whose text must be UTF-8).
"""

from __future__ import annotations

import codecs
from pathlib import Path

from virus_nerf.errors import DataFormatError

BOM = codecs.BOM_UTF8  # spreadsheets saving "CSV UTF-8" put it first; it is not part of the header


def read_bytes(path: Path, what: str = "file") -> bytes:
    """The bytes of `path`; a missing or unreadable file is a DataFormatError naming it."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise DataFormatError(path, f"{what} not found") from None
    except IsADirectoryError:
        raise DataFormatError(path, f"is a folder; expected a {what}") from None
    except OSError as exc:
        raise DataFormatError(path, f"cannot be read: {exc.strerror or exc}") from None


def utf8_error(path: Path, data: bytes, start: int) -> DataFormatError:
    """The error for the byte at offset `start` of `data`, which does not decode as UTF-8."""
    row = data.count(b"\n", 0, start) + 1
    column = start - (data.rfind(b"\n", 0, start) + 1) + 1
    return DataFormatError(path, f"byte 0x{data[start]:02x} at column {column} is not UTF-8 text; "
                                 "expected a UTF-8 (or ASCII) text file", row=row)


def first_bad_byte(data: bytes) -> int | None:
    """Offset of the first byte of `data` that is not valid UTF-8 (None: all valid)."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start
    return None


def decode_strict(path: Path, data: bytes) -> str:
    """`data` as UTF-8 text (a leading BOM dropped); any other byte is refused naming its row."""
    data = data.removeprefix(BOM)
    bad = first_bad_byte(data)
    if bad is not None:
        raise utf8_error(path, data, bad)
    return data.decode("utf-8")


def decode_lenient(data: bytes) -> str:
    """`data` as UTF-8 text (a leading BOM dropped); bytes that are not UTF-8 are kept as surrogate
    escapes (see `has_bad_bytes`, `quoted`)."""
    return data.removeprefix(BOM).decode("utf-8", "surrogateescape")


def has_bad_bytes(text: str) -> bool:
    """Whether `text` (from `decode_lenient`) holds bytes that were not UTF-8."""
    return any("\udc80" <= ch <= "\udcff" for ch in text)


def quoted(text: str) -> str:
    """`text` quoted for a message: repr(), with bytes that were not UTF-8 shown as \\xNN."""
    if not has_bad_bytes(text):
        return repr(text)
    shown = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    return "'" + shown.replace("'", "\\'") + "'"


def not_a_number(text: str) -> str:
    """The problem text for a cell that should hold a number and does not."""
    hint = " (it holds bytes that are not UTF-8 text)" if has_bad_bytes(text) else ""
    return f"value {quoted(text)} is not a number{hint}"
