"""Where the messages come from: a MAVLink telemetry log (``.tlog``) or an ArduPilot
DataFlash log (``.bin``) replayed at a speed,
or a live MAVLink connection (pymavlink connection strings ``udpin:HOST:PORT``,
``udp:HOST:PORT``, ``udpout:``, ``tcp:HOST:PORT``, ``tcpin:``, a serial device
``/dev/ttyUSB0[,BAUD]`` or ``COM3``).

Each yields ``(message, stamp_ns)``, and ``None`` when nothing arrived for a while (so the
caller can show its status). Stamps: a log's own, as ``aqfg import mavlink`` reads them
(a tlog: the time the ground station logged each message; DataFlash: ``TimeUS``, the
autopilot's time since boot); for a connection, the time of reception on
this computer (unix ns, from a monotonic clock), the stamp a ground station writes in a
tlog. A connection's messages are recorded as such a tlog (``record``), so the run can be
checked offline afterwards: ``aqfg import mavlink`` on it gives the mission the run had.
"""
from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from aqfg.data.importers.common import LogFormatError, require
from aqfg.data.importers.mavlink import DF_MAGIC, _ns, load_mavutil

CONNECTIONS = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "serial:")
IDLE_S = 0.25                  # s: a pause this long yields None (status, Ctrl-C)


def is_connection(spec: str) -> bool:
    """A pymavlink connection string (or a serial device), not a log file."""
    s = spec.lower()
    return s.startswith(CONNECTIONS) or s.startswith("/dev/") or \
        (s.startswith("com") and s[3:].split(",")[0].isdigit())


def pace_delay(stamp_ns: int, first_ns: int, started: float, now: float, speed: float
               ) -> float:
    """Seconds to wait before handing over a message stamped ``stamp_ns`` of a log replayed
    at ``speed`` (1 real time, 2 twice as fast; 0 as fast as possible) that started at wall
    time ``started`` with the message stamped ``first_ns``."""
    if speed <= 0:
        return 0.0
    due = started + (stamp_ns - first_ns) * 1e-9 / speed
    return max(due - now, 0.0)


def open_source(spec: str, speed: float | None, record: Path | None = None):
    """The message source of ``spec`` (module docstring). LogFormatError for a file that
    is not a tlog; ValueError for a connection that cannot be opened."""
    require("pymavlink", "mavlink", "MAVLink streams")
    if is_connection(spec):
        return LinkSource(spec, record)
    p = Path(spec)
    if not p.is_file():
        raise FileNotFoundError(f"{spec}: no such file, and not a MAVLink connection "
                                f"(udpin:HOST:PORT, udp:, tcp:HOST:PORT, /dev/ttyUSB0, ...)")
    with open(p, "rb") as fh:
        dataflash = fh.read(2) == DF_MAGIC
    return LogSource(p, 1.0 if speed is None else speed, dataflash)


class LogSource:
    """A tlog's or a DataFlash log's messages in file order, handed over at ``speed``
    (module docstring); a DataFlash message is stamped with its ``TimeUS``."""

    live = False

    def __init__(self, path: Path, speed: float, dataflash: bool = False):
        self.path, self.speed, self.dataflash = path, speed, dataflash
        try:
            if dataflash:
                from pymavlink import DFReader
                self.log = DFReader.DFReader_binary(str(path), zero_time_base=False)
            else:
                self.log = load_mavutil().mavmmaplog(str(path))
        except Exception as e:  # noqa: BLE001 - pymavlink raises bare Exceptions on bad files
            what = "an ArduPilot DataFlash log" if dataflash else "a MAVLink telemetry log"
            raise LogFormatError(str(path), f"cannot read as {what}: {e}") from None
        self.name = str(path)

    def stamp(self, msg) -> int | None:
        """The message's stamp (ns): the tlog's, or DataFlash ``TimeUS`` (None: none)."""
        if not self.dataflash:
            return _ns(msg._timestamp)
        us = getattr(msg, "TimeUS", None)
        return None if us is None else int(us) * 1000

    def __iter__(self) -> Iterator[tuple[Any, int] | None]:
        first: int | None = None
        started = time.perf_counter()
        while True:
            msg = self.log.recv_match()
            if msg is None:
                return
            if msg.get_type() == "BAD_DATA":
                continue
            stamp = self.stamp(msg)
            if stamp is None:                   # DataFlash FMT, FMTU...: no time
                continue
            if first is None:
                first, started = stamp, time.perf_counter()
            while True:
                wait = pace_delay(stamp, first, started, time.perf_counter(), self.speed)
                if wait <= 0:
                    break
                time.sleep(min(wait, IDLE_S))
                if wait > IDLE_S:
                    yield None
            yield msg, stamp

    def close(self) -> None:
        self.log.close()


class LinkSource:
    """A live MAVLink connection (module docstring); ends on Ctrl-C or when the caller
    stops iterating."""

    live = True

    def __init__(self, spec: str, record: Path | None):
        mavutil = load_mavutil()
        try:
            self.conn = mavutil.mavlink_connection(spec, source_system=255, source_component=190)
        except Exception as e:  # noqa: BLE001 - sockets and serial ports raise many kinds
            raise ValueError(f"cannot open the MAVLink connection {spec!r}: {e}") from None
        self.name = spec
        self.rec: BinaryIO | None = open(record, "wb") if record is not None else None
        self.wall0_ns = time.time_ns()
        self.mono0_ns = time.monotonic_ns()

    def now_ns(self) -> int:
        """Unix time (ns) from a monotonic clock, to the microsecond (as a tlog holds it)."""
        ns = self.wall0_ns + time.monotonic_ns() - self.mono0_ns
        return ns // 1000 * 1000

    def __iter__(self) -> Iterator[tuple[Any, int] | None]:
        while True:
            msg = self.conn.recv_match(blocking=True, timeout=IDLE_S)
            if msg is None:
                if self.rec is not None:
                    self.rec.flush()        # whole messages on disk while the link is quiet
                yield None
                continue
            if msg.get_type() == "BAD_DATA":
                continue
            stamp = self.now_ns()
            if self.rec is not None:
                self.rec.write(struct.pack(">Q", stamp // 1000) + msg.get_msgbuf())
            yield msg, stamp

    def send(self, msg) -> None:
        """Send a message on the connection (its own link back to the vehicle)."""
        self.conn.mav.send(msg)

    def request_params(self, names: list[str], system: int, component: int) -> None:
        """``PARAM_REQUEST_READ`` of each named parameter, to the vehicle's component."""
        for name in names:
            self.conn.mav.param_request_read_send(system, component, name.encode(), -1)

    def close(self) -> None:
        if self.rec is not None:
            self.rec.close()
        self.conn.close()
