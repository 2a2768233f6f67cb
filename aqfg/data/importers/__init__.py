"""Vehicle logs -> ``aqfg-mission/1``: one reader per ecosystem, each behind an optional
extra (``pip install "aqfg[ros]"``, ``[mavlink]``, ``[ulog]``, ``[nmea]``).

:func:`import_log` reads a log with a map file (:mod:`.mapfile`) and returns an
:class:`~aqfg.data.importers.common.ImportResult` whose ``mission`` the caller saves with
:func:`aqfg.data.io.save_mission`. NMEA logs carry positions only: :func:`import_log` with
``"nmea"`` adds their fixes to an existing mission (``base``). CSV exports (``"csv"``) are
read by the map's ``[csv]`` table, without an optional package. The formats, defaults and frame
conversions are documented in docs/mission-format.md, "Importing logs".
"""
from __future__ import annotations

import os
from pathlib import Path

from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    MissingExtraError,
    Series,
    check_layout,
)
from aqfg.data.importers.mapfile import ImportMap, load_map, parse_map
from aqfg.data.mission import Mission

FORMATS = ("ros2", "ros1", "mavlink", "ulog", "nmea", "csv")

__all__ = ["FORMATS", "ImportMap", "ImportResult", "LogFormatError", "MissingExtraError",
           "Series", "import_log", "load_map", "parse_map"]


def import_log(fmt: str, source: str | os.PathLike, imap: ImportMap | None = None,
               base: Mission | None = None) -> ImportResult:
    """Read the log ``source`` of format ``fmt`` (one of :data:`FORMATS`) into a mission.

    ``imap``: the parsed map file (default: none, every default). ``base``: for ``"nmea"``,
    the mission the fixes are added to. Raises :class:`LogFormatError` for a bad log and
    :class:`MissingExtraError` when the format's optional package is not installed.
    """
    imap = imap if imap is not None else ImportMap()
    path = Path(source)
    if fmt not in FORMATS:
        raise ValueError(f"unknown log format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if fmt != "nmea":
        check_layout(str(path), imap)
    if fmt in ("ros1", "ros2"):
        from aqfg.data.importers.ros import read_ros
        return read_ros(path, imap, fmt)
    if fmt == "mavlink":
        from aqfg.data.importers.mavlink import read_mavlink
        return read_mavlink(path, imap)
    if fmt == "csv":
        from aqfg.data.importers.csvlog import read_csv_log
        return read_csv_log(path, imap)
    if fmt == "ulog":
        from aqfg.data.importers.ulog import read_ulog
        return read_ulog(path, imap)
    if fmt == "nmea":
        from aqfg.data.importers.nmea import read_nmea
        if base is None:
            raise LogFormatError(str(path), "an NMEA log holds positions only: import the "
                                            "vehicle's log first, then add the NMEA fixes to "
                                            "that mission")
        return read_nmea(path, imap, base)
    raise AssertionError(fmt)      # pragma: no cover - FORMATS checked above
