"""``aqfg import FORMAT SOURCE --out MISSION [--map MAP.toml]``: a vehicle log -> mission.

FORMAT: ``ros2`` (bag directory, .mcap or .db3), ``ros1`` (.bag), ``mavlink`` (.tlog or
DataFlash .bin), ``ulog`` (.ulg), ``nmea`` (adds the log's fixes to the existing mission
MISSION). The map file gives what the log cannot (vehicle, thrusters, origin, topics); see
docs/mission-format.md, "Importing logs".
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aqfg.commands.common import log, printable
from aqfg.data.importers import LogFormatError, MissingExtraError, import_log, load_map
from aqfg.data.importers.truncation import cut_short
from aqfg.data.io import MISSION_FILES, MissionFormatError, load_mission, load_truth, save_mission
from aqfg.outputs import OutputSet

EXIT_MISSING_EXTRA = 2


def _read(fmt: str, source: str, imap, base=None):
    """:func:`import_log`, with a reader's own failure on a damaged file (a third-party
    parser's IndexError, AttributeError...) turned into a data error naming the file."""
    try:
        result = import_log(fmt, source, imap, base=base)
        end = cut_short(fmt, source)
        if end is not None:         # the parsers stop quietly at a message cut short
            size = Path(source).stat().st_size
            words = (f"{source}: the log ends in the middle of a message (complete messages "
                     f"end at byte {end:,} of {size:,}): truncated? imported as far as it "
                     f"reads, to mission t = {result.mission.t1:.1f} s")
            log.warning("%s", words)
            result.notes.append(words)
        return result
    except (MissionFormatError, MissingExtraError, OSError, MemoryError):
        raise
    except Exception as e:  # noqa: BLE001 - the parsers raise anything on bad bytes
        raise LogFormatError(source, f"cannot decode as a {fmt} log: the file is damaged, "
                                     f"truncated or not such a log ({type(e).__name__} in "
                                     "its reader)") from e


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    imap = load_map(args.map)
    try:
        if args.format == "nmea":
            if not (out / "mission.toml").is_file():
                raise FileNotFoundError(f"{out} holds no mission; 'aqfg import nmea' adds GNSS "
                                        "fixes to a mission imported first from the vehicle's "
                                        "own log")
            base = load_mission(out)
            truth = load_truth(out)
            if base.gnss is not None and not args.force:
                raise FileExistsError(f"{out} already has GNSS fixes (gnss.csv); pass --force "
                                      "to replace them with the NMEA log's")
            result = _read("nmea", args.source, imap, base=base)
            with OutputSet(out, MISSION_FILES, force=True) as stage:   # whole set, or none
                save_mission(result.mission, stage, truth)
        else:
            if (out / "mission.toml").exists() and not args.force:
                raise FileExistsError(f"{out} already holds a mission; pass --force to "
                                      "overwrite it")
            outs = OutputSet(out, MISSION_FILES, force=args.force)
            outs.check()
            result = _read(args.format, args.source, imap)
            with outs as stage:               # the mission appears whole, or not at all
                save_mission(result.mission, stage)
    except MissingExtraError as e:
        print(f"aqfg import: error: {e}", file=sys.stderr)
        return EXIT_MISSING_EXTRA
    m = result.mission
    what = "added GNSS fixes to" if args.format == "nmea" else "imported"
    print(printable(f"{what} {m.vehicle} mission '{m.name}' from {args.source} "
                    f"({args.format}) -> {out}"))
    print(result.summary())
    return 0
