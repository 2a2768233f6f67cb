"""NMEA 0183 logs -> the GNSS stream of an existing mission, read with ``pynmeagps`` (the
optional extra ``aqfg[nmea]``).

An NMEA log holds positions only, so it adds ``gnss.csv`` to a mission imported from the
vehicle's own log. Fixes come from ``GGA`` by default (``[topics] gnss = "RMC"``, ``"GNS"``
or ``"GLL"`` otherwise); fixes without a position solution (GGA quality 0, RMC/GLL status
V, GNS mode N) are left out; ``GST`` gives sigma (RMS of the latitude and longitude
standard deviations). NMEA times are UTC times of day: each is placed on the day that puts it
nearest the previous dated time (an RMC or ZDA date, else the mission's UTC start), which
also carries fixes over midnight. The mission's UTC start is ``[source] utc_zero`` of its
mission.toml (written by the other importers when their log tells it) or the map's
``[time] utc_zero``.
"""
from __future__ import annotations

import copy
import datetime as dt
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.geodesy import latlon_to_ne
from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    Series,
    check_stamps,
    require,
)
from aqfg.data.importers.mapfile import ImportMap
from aqfg.data.mission import Gnss, Mission

SENTENCES = ("GGA", "RMC", "GNS", "GLL")
DAY = 86400.0


def _tod(t: dt.time) -> float:
    return t.hour * 3600.0 + t.minute * 60.0 + t.second + t.microsecond * 1e-6


def _nearest(tod: float, ref: float) -> float:
    """The UTC time (unix s) with time of day ``tod`` nearest to ``ref``."""
    midnight = np.floor(ref / DAY) * DAY
    cands = midnight + tod + DAY * np.array([-1.0, 0.0, 1.0])
    return float(cands[np.argmin(np.abs(cands - ref))])


def _valid(p: Any, kind: str) -> tuple[bool, str]:
    if kind == "GGA":
        return (p.quality not in ("", None, 0)), "no fix (GGA quality 0)"
    if kind in ("RMC", "GLL"):
        return p.status == "A", f"no fix ({kind} status V)"
    return (p.posMode not in ("", "N") and not set(str(p.posMode)) <= {"N"}), \
        "no fix (GNS mode N)"


def read_nmea(source: str | Path, imap: ImportMap, base: Mission) -> ImportResult:
    """The fixes of an NMEA log as ``base``'s GNSS stream (see module doc)."""
    source = Path(source)
    src = str(source)
    if not source.is_file():
        raise LogFormatError(src, "no such file; expected an NMEA 0183 log")
    require("pynmeagps", "nmea", "NMEA logs")
    from pynmeagps import NMEAReader
    spec = imap.topic("gnss", "GGA")
    assert spec is not None
    kind = spec.topic
    if kind not in SENTENCES:
        raise LogFormatError(src, f"the gnss stream reads one of {', '.join(SENTENCES)}, not "
                                  f"{kind}", topic=kind)
    src_tab = base.extra.get("source", {}) if isinstance(base.extra.get("source"), dict) else {}
    utc_zero = imap.utc_zero if imap.utc_zero is not None else src_tab.get("utc_zero")
    if utc_zero is None:
        raise LogFormatError(src, "NMEA times are UTC but the mission's UTC start is unknown "
                                  "(no [source] utc_zero in its mission.toml); give it in the "
                                  "map file: [time] utc_zero = <unix seconds of mission t = 0>")
    utc_zero = float(utc_zero)
    ref = utc_zero
    t_utc, lat, lon, tods, gst, n_bad, seen, reason = _sentences(src, source, kind, ref,
                                                                  NMEAReader)
    raw, bad_sum = _raw_count(source, kind)
    if not seen:
        why = (f": {raw} look like {kind} but none is readable ({bad_sum} with a wrong "
               f"checksum, {raw - bad_sum} with a field out of range, e.g. a latitude beyond "
               "90 degrees)" if raw else "")
        raise LogFormatError(src, f"no {kind} sentences in the log{why}", topic=kind)
    if not t_utc:
        raise LogFormatError(src, f"none of the log's {seen} {kind} sentences holds a usable "
                                  f"fix (the last reason: {reason})", topic=kind)
    t_ns = np.array([round(u * 1e6) * 1000 for u in t_utc], dtype=np.int64)
    s = Series("gnss", kind, f"NMEA {kind}", t_ns,
               {"lat": np.array(lat), "lon": np.array(lon),
                "sigma": np.array([gst.get(k, np.nan) for k in tods])},
               {reason: n_bad} if n_bad else {})
    zero_ns = round(utc_zero * 1e6) * 1000
    check_stamps(src, s, int(t_ns[0]) if len(t_ns) else zero_ns, imap.max_gap)
    t = (t_ns - zero_ns).astype(float) * 1e-9
    notes: list[str] = []
    if raw > seen:
        notes.append(f"gnss: {raw - seen} of {raw} {kind} sentences unreadable and left out "
                     f"({bad_sum} with a wrong checksum)")
    if t[-1] < base.t0 or t[0] > base.t1:
        raise LogFormatError(src, f"the fixes (mission t {t[0]:.1f} .. {t[-1]:.1f} s, from the "
                                  f"UTC start {utc_zero:.3f}) do not overlap the mission "
                                  f"({base.t0:.1f} .. {base.t1:.1f} s): a different day, or "
                                  "a wrong utc_zero?", topic=kind)
    ll = np.column_stack([s.data["lat"], s.data["lon"]])
    origin = _origin(src, base, imap, ll, notes)
    sig: np.ndarray | None = s.data["sigma"]
    if not np.isfinite(s.data["sigma"]).all():
        bad = int((~np.isfinite(s.data["sigma"])).sum())
        notes.append(f"gnss: {bad} of {len(t)} fixes have no GST "
                     "accuracy; no sigma column written (the estimators' default applies)")
        sig = None
    m = copy.copy(base)
    m.gnss = Gnss(t, latlon_to_ne(ll[:, 0], ll[:, 1], origin), sig, latlon=ll)
    m.origin, m.gnss_latlon = origin, True
    m.extra = dict(base.extra)
    m.extra["source"] = {**src_tab, "gnss": {"format": "nmea", "file": source.name,
                                             "sentence": kind}}
    if imap.utc_zero is not None:
        m.extra["source"]["utc_zero"] = utc_zero
    return ImportResult(m, {"gnss": s}, zero_ns, notes)


def _sentences(src: str, source: Path, kind: str, ref: float, reader):
    """The usable fixes of the sentences ``kind`` in the log: UTC times (unix s, the date
    from the RMC/ZDA sentences, starting from ``ref``), latitudes, longitudes (degrees),
    times of day (s, rounded to ms), GST sigmas by time of day (m), and the count of
    unusable ones, the count seen and the last reason one was unusable."""
    t_utc, lat, lon, tods = [], [], [], []
    gst: dict[float, float] = {}
    n_bad, seen, reason = 0, 0, ""
    try:
        with open(source, "rb") as fh:
            for _, p in reader(fh, nmeaonly=False, quitonerror=0):
                if p is None:
                    continue
                mid = getattr(p, "msgID", "")
                if mid in ("RMC", "ZDA") and getattr(p, "time", "") not in ("", None):
                    date = _date(p)
                    if date is not None:
                        ref = dt.datetime.combine(date, p.time, dt.timezone.utc).timestamp()
                if mid == "GST" and p.time not in ("", None) and p.stdLat not in ("", None):
                    gst[round(_tod(p.time), 3)] = float(np.sqrt(0.5 * (p.stdLat ** 2
                                                                      + p.stdLong ** 2)))
                if mid != kind:
                    continue
                seen += 1
                ok, reason = _valid(p, kind)
                if not ok or p.lat in ("", None) or p.time in ("", None):
                    n_bad += 1
                    continue
                if not (abs(float(p.lat)) <= 90.0 and abs(float(p.lon)) <= 180.0):
                    n_bad += 1
                    reason = "latitude or longitude out of range"
                    continue
                tod = _tod(p.time)
                ref = _nearest(tod, ref)
                t_utc.append(ref)
                tods.append(round(tod, 3))
                lat.append(float(p.lat))
                lon.append(float(p.lon))
    except (OSError, ValueError) as e:
        raise LogFormatError(src, f"cannot read as NMEA 0183: {e}") from None
    return t_utc, lat, lon, tods, gst, n_bad, seen, reason


def _origin(src: str, base: Mission, imap: ImportMap, ll: np.ndarray, notes: list[str]):
    """The NED frame's origin (lat, lon degrees): the mission's, the map's (which must not
    differ from the mission's), else the first fix (with a note)."""
    origin = base.origin
    if imap.origin is not None:
        if origin is not None and tuple(origin) != tuple(imap.origin):
            raise LogFormatError(src, f"the map's [origin] {imap.origin} differs from the "
                                      f"mission's {tuple(origin)}; leave it out of the map")
        origin = imap.origin
    if origin is None:
        origin = (float(ll[0, 0]), float(ll[0, 1]))
        notes.append("the mission has no [origin]: the first fix is the origin of its NED "
                     "frame")
    return origin


def _raw_count(source: Path, kind: str) -> tuple[int, int]:
    """Lines of the log that look like ``$..<kind>`` sentences, and how many of them have
    a wrong checksum (what the reader skipped without a word)."""
    n = bad = 0
    with open(source, "rb") as fh:
        for line in fh:
            line = line.strip()
            if not line.startswith(b"$") or line[3:6] != kind.encode() or line[6:7] != b",":
                continue
            n += 1
            body, star, given = line[1:].partition(b"*")
            calc = 0
            for c in body:
                calc ^= c
            if not star or given[:2].upper() != f"{calc:02X}".encode():
                bad += 1
    return n, bad


def _date(p: Any) -> dt.date | None:
    if p.msgID == "RMC":
        return p.date if isinstance(p.date, dt.date) else None
    try:
        return dt.date(int(p.year), int(p.month), int(p.day))
    except (TypeError, ValueError):
        return None
