"""``aqfg import FORMAT SOURCE... --out MISSION [--map MAP.toml]``: a vehicle log -> mission.

FORMAT: ``ros2`` (bag directory, .mcap or .db3), ``ros1`` (.bag), ``mavlink`` (.tlog or
DataFlash .bin), ``ulog`` (.ulg), ``nmea`` (adds the log's fixes to the existing mission
MISSION), ``csv`` (CSV exports read by the map's ``[csv]`` table; several files make one
mission each, written to ``MISSION/<file name without .csv>``). The map file gives what the
log cannot (vehicle, thrusters, origin, topics, columns); see docs/mission-format.md,
"Importing logs". The imported mission's suspicious-input findings (the thruster check
included) are printed as warnings, as loading it would.
"""
from __future__ import annotations

import argparse
import copy
import sys
import warnings
from pathlib import Path

from aqfg.commands.common import UsageError, log, printable
from aqfg.data.importers import (
    ImportMap,
    LogFormatError,
    MissingExtraError,
    import_log,
    load_map,
)
from aqfg.data.importers.truncation import cut_short
from aqfg.data.io import (
    MISSION_FILES,
    MissionFormatError,
    load_mission,
    load_truth,
    plausibility_warnings,
    save_mission,
)
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
    sources = [str(s) for s in args.source]
    if len(sources) > 1 and args.format != "csv":
        raise UsageError(f"'aqfg import {args.format}' reads one log, got {len(sources)}; "
                         "only csv takes several files (one mission each)")
    imap = load_map(args.map)
    try:
        if args.format == "nmea":
            return _nmea(args, sources[0], out, imap)
        if len(sources) > 1:
            return _many(args, sources, out, imap)
        if (out / "mission.toml").exists() and not args.force:
            raise FileExistsError(f"{out} already holds a mission; pass --force to "
                                  "overwrite it")
        outs = OutputSet(out, MISSION_FILES, force=args.force)
        outs.check()
        result = _read(args.format, sources[0], imap)
        with outs as stage:               # the mission appears whole, or not at all
            save_mission(result.mission, stage)
    except MissingExtraError as e:
        print(f"aqfg import: error: {e}", file=sys.stderr)
        return EXIT_MISSING_EXTRA
    _report("imported", result, sources[0], args.format, out)
    return 0


def _nmea(args: argparse.Namespace, source: str, out: Path, imap: ImportMap) -> int:
    if not (out / "mission.toml").is_file():
        raise FileNotFoundError(f"{out} holds no mission; 'aqfg import nmea' adds GNSS "
                                "fixes to a mission imported first from the vehicle's "
                                "own log")
    base = load_mission(out)
    truth = load_truth(out)
    if base.gnss is not None and not args.force:
        raise FileExistsError(f"{out} already has GNSS fixes (gnss.csv); pass --force "
                              "to replace them with the NMEA log's")
    result = _read("nmea", source, imap, base=base)
    with OutputSet(out, MISSION_FILES, force=True) as stage:   # whole set, or none
        save_mission(result.mission, stage, truth)
    _report("added GNSS fixes to", result, source, "nmea", out)
    return 0


def _many(args: argparse.Namespace, sources: list[str], out: Path, imap: ImportMap) -> int:
    """One mission per CSV file, each in ``out/<stem>``; all are read before any is
    written, so a bad file leaves every mission directory as it was."""
    stems = [Path(s).stem for s in sources]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise UsageError(f"several files named {dup[0]!r}: each becomes {out}/<name>; rename "
                         "one or import them separately")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out} is not a directory; with several files --out is the "
                                 "directory receiving one mission per file")
    targets = [out / s for s in stems]
    outsets = []
    for t in targets:
        if (t / "mission.toml").exists() and not args.force:
            raise FileExistsError(f"{t} already holds a mission; pass --force to overwrite it")
        o = OutputSet(t, MISSION_FILES, force=args.force)
        o.check()
        outsets.append(o)
    results = []
    for src, stem in zip(sources, stems):
        m = copy.copy(imap)
        m.name = f"{imap.name}-{stem}" if imap.name else stem
        results.append(_read("csv", src, m))
    out.mkdir(parents=True, exist_ok=True)
    for o, r in zip(outsets, results):
        with o as stage:
            save_mission(r.mission, stage)
    for src, t, r in zip(sources, targets, results):
        _report("imported", r, src, "csv", t)
    return 0


def _report(what: str, result, source: str, fmt: str, out: Path) -> None:
    m = result.mission
    print(printable(f"{what} {m.vehicle} mission '{m.name}' from {source} ({fmt}) -> {out}"))
    print(result.summary())
    for w in plausibility_warnings(m, out):
        warnings.warn(w, stacklevel=2)
