"""Does a binary log end in the middle of a message? The parsers stop quietly at a message
cut short, so a log truncated in a copy imports as its readable part; walking the record
framing of the file says where the last complete message ends.

:func:`cut_short` returns the byte offset where the complete messages end when the file
goes on past it with an incomplete message, else None (a whole file, or framing that is
not understood: no claim is made). A ROS bag's readers need its end (a ROS 1 bag's index,
an MCAP file's summary and footer, every page of a sqlite3 database): for those, a file
that stops before that end is cut short too, at a record boundary or not.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

ULOG_MAGIC = b"ULog\x01\x12\x35"
DF_HEAD = b"\xa3\x95"
DF_FMT_TYPE = 128
DF_FMT_LENGTH = 89


ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
MCAP_FOOTER = 0x02
SQLITE_MAGIC = b"SQLite format 3\x00"


def cut_short(fmt: str, path: str | Path) -> int | None:
    """Offset of the end of the last complete message of a ``ulog`` (.ulg) or ``mavlink``
    (.tlog, DataFlash .bin) log whose bytes go on with a message cut short, or of a ``ros1``
    (.bag) or ``ros2`` (.mcap, .db3 storage file) bag that stops before its end; None
    otherwise."""
    p = Path(path)
    if not p.is_file():
        return None
    if fmt in ("ros1", "ros2"):
        with p.open("rb") as f:
            head = f.read(16)
            f.seek(0)
            if head.startswith(ROS1_MAGIC):
                return _ros1(f, p.stat().st_size)
            if head.startswith(MCAP_MAGIC):
                return _mcap(f, p.stat().st_size)
            if head.startswith(SQLITE_MAGIC):
                return _sqlite(f, p.stat().st_size)
        magics = (ROS1_MAGIC, MCAP_MAGIC, SQLITE_MAGIC)
        # empty, or cut inside the magic itself
        return 0 if len(head) < 16 and any(m.startswith(head) for m in magics) else None
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


def _ros1_fields(header: bytes) -> dict[str, bytes]:
    """The ``name=value`` fields of a ROS 1 bag record header (each length-prefixed)."""
    out, pos = {}, 0
    while pos + 4 <= len(header):
        n = struct.unpack_from("<I", header, pos)[0]
        name, _, value = header[pos + 4:pos + 4 + n].partition(b"=")
        out[name.decode("latin-1")] = value
        pos += 4 + n
    return out


def _ros1_records(f: BinaryIO, pos: int, size: int, first: bool = False
                  ) -> tuple[int, int | None] | None:
    """Walk ROS 1 bag records ``<u32 header length><header><u32 data length><data>``
    from ``pos``: (where the last complete one ends, the bag header's ``index_pos`` when
    ``first``), or None where the first record is not a bag header."""
    index_pos = None
    while pos < size:
        f.seek(pos)
        raw = f.read(4)
        if len(raw) < 4:
            break
        hlen = struct.unpack("<I", raw)[0]
        if pos + 8 + hlen > size:
            break
        header = f.read(hlen)
        dlen = struct.unpack("<I", f.read(4))[0]
        if pos + 8 + hlen + dlen > size:
            break
        if first:
            fields = _ros1_fields(header)
            if fields.get("op") != b"\x03" or len(fields.get("index_pos", b"")) != 8:
                return None                # not the framing understood here
            index_pos = struct.unpack("<Q", fields["index_pos"])[0]
            first = False
        pos += 8 + hlen + dlen
    return pos, index_pos


def _ros1(f: BinaryIO, size: int) -> int | None:
    """ROS 1 bag: the bag header record (after the magic line) says where the index starts
    (``index_pos``, 0 while the recorder has not written it); a whole bag's records run
    from there to the end of the file."""
    head = _ros1_records(f, len(ROS1_MAGIC), min(size, len(ROS1_MAGIC) + 8 + 4096 + 4096),
                         first=True)
    if head is None:
        return None
    index_pos = head[1]
    if index_pos is not None and 0 < index_pos < size:
        end = _ros1_records(f, index_pos, size)
        if end is not None and end[0] == size:
            return None
    walked = _ros1_records(f, len(ROS1_MAGIC), size)
    return walked[0] if walked is not None else None


MCAP_FOOTER_LENGTH = 20     # bytes of a footer record's content


def _mcap(f: BinaryIO, size: int) -> int | None:
    """MCAP: records ``<u8 opcode><u64 length><content>`` after the magic, ending with
    the footer record and the magic again (a whole file is told by its last 37 bytes)."""
    tail = 9 + MCAP_FOOTER_LENGTH + len(MCAP_MAGIC)
    if size >= len(MCAP_MAGIC) + tail:
        f.seek(size - tail)
        end = f.read(tail)
        if end[0] == MCAP_FOOTER and end[-8:] == MCAP_MAGIC \
                and struct.unpack("<Q", end[1:9])[0] == MCAP_FOOTER_LENGTH:
            return None
    pos = len(MCAP_MAGIC)
    while pos < size:
        f.seek(pos)
        raw = f.read(9)
        if len(raw) < 9:
            return pos
        op, n = raw[0], struct.unpack("<Q", raw[1:])[0]
        if pos + 9 + n > size:
            return pos
        pos += 9 + n
        if op == MCAP_FOOTER:
            f.seek(pos)
            return None if f.read(8) == MCAP_MAGIC else pos
    return pos


def _sqlite(f: BinaryIO, size: int) -> int | None:
    """sqlite3 database: pages of the header's page size, as many as its page count (when
    that count is valid: the header's change counter equals its version-valid-for)."""
    h = f.read(100)
    if len(h) < 100:
        return 0
    page = struct.unpack(">H", h[16:18])[0]
    page = 65536 if page == 1 else page
    pages, change, valid_for = (struct.unpack(">I", h[k:k + 4])[0] for k in (28, 24, 92))
    if page < 512 or change != valid_for or pages == 0:
        return None
    return None if size >= page * pages else size // page * page
