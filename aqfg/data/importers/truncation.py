"""Does a binary log end in the middle of a message? The parsers stop quietly at a message
cut short, so a log truncated in a copy imports as its readable part; walking the record
framing of the file says where the last complete message ends.

:func:`cut_short` returns the byte offset where the complete messages end when the file
goes on past it with an incomplete message, else None (a whole file, or framing that is
not understood: no claim is made).
"""
from __future__ import annotations

import struct
from pathlib import Path

ULOG_MAGIC = b"ULog\x01\x12\x35"
DF_HEAD = b"\xa3\x95"
DF_FMT_TYPE = 128
DF_FMT_LENGTH = 89


def cut_short(fmt: str, path: str | Path) -> int | None:
    """Offset of the end of the last complete message of a ``ulog`` (.ulg) or ``mavlink``
    (.tlog, DataFlash .bin) log whose bytes go on with a message cut short; None otherwise."""
    p = Path(path)
    if not p.is_file():
        return None
    data = p.read_bytes()
    if fmt == "ulog":
        return _ulog(data)
    if fmt == "mavlink":
        return _dataflash(data) if data[:2] == DF_HEAD else _tlog(data)
    return None


def _ulog(b: bytes) -> int | None:
    if not b.startswith(ULOG_MAGIC) or len(b) < 16:
        return None
    pos = 16
    while pos + 3 <= len(b):
        size = struct.unpack_from("<H", b, pos)[0]
        if pos + 3 + size > len(b):
            return pos
        pos += 3 + size
    return pos if pos != len(b) else None


def _tlog(b: bytes) -> int | None:
    pos = 0
    while pos < len(b):
        if pos + 8 + 2 > len(b):
            return pos
        magic, n = b[pos + 8], b[pos + 9]
        if magic == 0xFE:
            size = 8 + n
        elif magic == 0xFD:
            if pos + 8 + 3 > len(b):
                return pos
            size = 12 + n + (13 if b[pos + 10] & 1 else 0)
        else:
            return None                    # not the framing understood here
        if pos + 8 + size > len(b):
            return pos
        pos += 8 + size
    return None


def _dataflash(b: bytes) -> int | None:
    lengths = {DF_FMT_TYPE: DF_FMT_LENGTH}
    pos = 0
    while pos < len(b):
        if pos + 3 > len(b):
            return pos
        if b[pos:pos + 2] != DF_HEAD:
            return None
        kind = b[pos + 2]
        if kind == DF_FMT_TYPE and pos + 5 <= len(b):
            lengths[b[pos + 3]] = b[pos + 4]
        size = lengths.get(kind)
        if size is None:
            return None
        if pos + size > len(b):
            return pos
        pos += size
    return None
