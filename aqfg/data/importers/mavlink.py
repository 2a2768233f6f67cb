"""MAVLink telemetry logs (``.tlog``) and ArduPilot DataFlash logs (``.bin``) -> mission,
read with ``pymavlink`` (the optional extra ``aqfg[mavlink]``).

Both are NED/FRD already. Default messages: tlog ``ATTITUDE`` (or
``ATTITUDE_QUATERNION``), ``GPS_RAW_INT`` (or ``GPS2_RAW``), ``SERVO_OUTPUT_RAW``;
DataFlash ``ATT``, ``GPS`` (accuracy from ``GPA.HAcc``), ``RCOU``. Servo outputs are PWM
pulse widths, normalised with the map's ``[motors] pwm_min/pwm_trim/pwm_max``, else with
the log's own parameters ``SERVOn_MIN/TRIM/MAX`` of each thruster's output ``n``
(``PARAM_VALUE`` in a tlog, ``PARM`` in DataFlash), whose ``SERVOn_REVERSED`` then sets
``[motors] reversed`` unless the map gives it. Depth (``vehicle = "auv"``, tlog) is read
from the first of ``GLOBAL_POSITION_INT.relative_alt`` (the autopilot's depth estimate),
``VFR_HUD.alt``, ``SCALED_PRESSURE2`` then ``SCALED_PRESSURE`` (``press_abs`` less its first
reading, fresh water) that the log holds, unless ``[topics] depth`` names one. A log
without a GNSS fix is imported with a warning, as a mission without fixes.

Clocks: a tlog's messages carry the time the ground station logged them (unix time, one
clock for every message; telemetry latency is not removed); DataFlash messages carry
``TimeUS``, the autopilot's time since boot, tied to UTC through the GPS week and
milliseconds when a GPS message has them.
"""
from __future__ import annotations

import copy
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    Series,
    assemble,
    motor_commands,
    output_channels,
    require,
    scalar_streams,
)
from aqfg.data.importers.frames import euler_to_quat
from aqfg.data.importers.mapfile import ImportMap, PwmRange, TopicSpec
from aqfg.data.io import MissionWarning

TLOG_DEFAULTS = {"imu": "ATTITUDE", "gnss": "GPS_RAW_INT", "motors": "SERVO_OUTPUT_RAW"}
DF_DEFAULTS = {"imu": "ATT", "gnss": "GPS", "motors": "RCOU"}
TLOG_TYPES = {"imu": ("ATTITUDE", "ATTITUDE_QUATERNION"), "gnss": ("GPS_RAW_INT", "GPS2_RAW"),
              "motors": ("SERVO_OUTPUT_RAW",)}
DF_TYPES = {"imu": ("ATT",), "gnss": ("GPS", "GPS2"), "motors": ("RCOU",)}
GPS_EPOCH_UNIX = 315964800            # 1980-01-06T00:00:00Z in unix seconds
# GPS - UTC (leap seconds) from the given unix time on
LEAP_SECONDS = ((1136073600, 14), (1230768000, 15), (1341100800, 16), (1435708800, 17),
                (1483228800, 18))
DF_MAGIC = b"\xa3\x95"
G = 9.80665                             # m/s^2
RHO_WATER = 1000.0                      # kg/m^3: depth from pressure, fresh water
# default depth sources of a tlog, by priority: message, field, scale to metres down
TLOG_DEPTH = (("GLOBAL_POSITION_INT", "relative_alt", -1e-3), ("VFR_HUD", "alt", -1.0),
              ("SCALED_PRESSURE2", "press_abs", 100.0 / (RHO_WATER * G)),
              ("SCALED_PRESSURE", "press_abs", 100.0 / (RHO_WATER * G)))


def read_mavlink(source: str | Path, imap: ImportMap) -> ImportResult:
    """A tlog or a DataFlash ``.bin`` (told apart by the DataFlash header bytes)."""
    source = Path(source)
    src = str(source)
    if not source.is_file():
        raise LogFormatError(src, "no such file; expected a MAVLink .tlog or a DataFlash .bin")
    require("pymavlink", "mavlink", "MAVLink logs")
    with open(source, "rb") as fh:
        head = fh.read(2)
    if head == DF_MAGIC:
        return _read_dataflash(source, imap)
    return _read_tlog(source, imap)


# ---------------------------------------------------------------------------- common

def _select(src: str, imap: ImportMap, defaults: dict[str, str], types: dict[str, tuple],
            present: dict[str, int], what: str) -> dict[str, TopicSpec]:
    chosen: dict[str, TopicSpec] = {}
    listing = ", ".join(f"{k} ({v})" for k, v in sorted(present.items())) or "none"
    for stream in ("imu", "gnss", "motors", "usbl", "depth"):
        spec = imap.topic(stream, defaults.get(stream))
        if spec is None:
            continue
        if not present.get(spec.topic):
            if stream == "gnss" and "gnss" not in imap.topics:
                continue                 # no GNSS at all: a mission without fixes
            raise LogFormatError(src, f"no {spec.topic} messages in the {what} (it has: "
                                      f"{listing}); map [topics] {stream} to the message "
                                      f"holding the {stream} stream", topic=spec.topic)
        want = types.get(stream)
        if want is not None and spec.topic not in want:
            raise LogFormatError(src, f"the {stream} stream reads {' or '.join(want)}, not "
                                      f"{spec.topic}", topic=spec.topic)
        chosen[stream] = spec
    return chosen


def _generic(src: str, spec: TopicSpec, stream: str, rows: list[Any]) -> dict[str, np.ndarray]:
    try:
        return scalar_streams(spec.fields, stream, rows)
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as e:
        raise LogFormatError(src, f"cannot read the {stream} fields of {spec.topic}: {e}",
                             topic=spec.topic) from None


def servo_map(imap: ImportMap, params: dict[str, float]) -> tuple[ImportMap, list[str]]:
    """``imap`` with the PWM range (and, unless mapped, the reversal) of each thruster's
    output from the log's ``SERVOn_MIN/TRIM/MAX/REVERSED``, when the map gives no range."""
    if imap.pwm is not None or imap.n_thrusters is None:
        return imap, []
    chans = output_channels(imap)
    try:
        lo, mid, hi = (np.array([params[f"SERVO{c}_{k}"] for c in chans], dtype=float)
                       for k in ("MIN", "TRIM", "MAX"))
    except KeyError:
        return imap, []
    if not (np.all(lo < mid) and np.all(mid < hi)):
        return imap, [f"the autopilot's SERVOn_MIN/TRIM/MAX of outputs {chans} are not increasing; "
                      "not used"]
    out = copy.copy(imap)
    out.pwm = PwmRange(lo, mid, hi)
    notes = [f"PWM range of outputs {chans} from the autopilot's SERVOn_MIN/TRIM/MAX: "
             + ", ".join(f"{a:g}/{b:g}/{c:g}" for a, b, c in zip(lo, mid, hi)) + " us"]
    rev = [bool(params.get(f"SERVO{c}_REVERSED", 0)) for c in chans]
    if imap.reversed is None and any(rev):
        out.reversed = rev
        notes.append(f"reversed thrusters from the autopilot's SERVOn_REVERSED: {rev}")
    return out, notes


def default_depth(imap: ImportMap, present: dict[str, int]) -> TopicSpec | None:
    """The depth source of an AUV's tlog when the map names none (module docstring)."""
    if imap.vehicle != "auv" or "depth" in imap.topics:
        return None
    for name, fld, scale in TLOG_DEPTH:
        if present.get(name):
            return TopicSpec(name, None, {"field": fld, "scale": scale})
    return None


def _ns(seconds: float) -> int:
    return round(seconds * 1e6) * 1000


# ------------------------------------------------------------------------------ tlog

def load_mavutil():
    """``pymavlink.mavutil`` set to the ArduPilot dialect of MAVLink 2 (read with 1.0 too)."""
    from pymavlink import mavutil
    # MAVLink 2 frames (and the 1.0 ones) parse only with the 2.0 dialect modules; pymavlink
    # itself switches this way when it first meets a 2.0 frame.
    if not mavutil.mavlink20() or mavutil.current_dialect != "ardupilotmega":
        os.environ["MAVLINK20"] = "1"
        mavutil.set_dialect("ardupilotmega")
    return mavutil


def _read_tlog(source: Path, imap: ImportMap) -> ImportResult:
    src = str(source)
    mavutil = load_mavutil()
    # mavmmaplog directly: mavlink_connection() would execute a path containing "/bin/"
    try:
        log = mavutil.mavmmaplog(src)
    except Exception as e:  # noqa: BLE001 - pymavlink raises bare Exceptions on bad files
        raise LogFormatError(src, f"cannot read as a MAVLink telemetry log: {e}") from None
    present = {log.id_to_name[k]: n for k, n in getattr(log, "counts", {}).items()}
    if not present:
        raise LogFormatError(src, "no MAVLink messages found; expected a .tlog (8-byte "
                                  "timestamp before each MAVLink message) or a DataFlash .bin")
    depth = default_depth(imap, present)
    chosen = _select(src, imap, TLOG_DEFAULTS, TLOG_TYPES, present, "telemetry log")
    if depth is not None:
        chosen["depth"] = depth
    names = {s.topic for s in chosen.values()} | {"PARAM_VALUE"}
    if depth is not None and depth.topic.startswith("SCALED_PRESSURE"):
        depth.fields["offset"] = None      # the first reading: set once the rows are read
    rows = _read_rows(log, names)
    params = {str(m.param_id).rstrip("\x00"): float(m.param_value) for m in rows["PARAM_VALUE"]}
    imap, notes = servo_map(imap, params)
    series: dict[str, Series] = {}
    sysid = None
    for stream, spec in chosen.items():
        msgs = rows[spec.topic]
        if not msgs:                   # indexed, but none decodes: damaged bytes
            raise LogFormatError(src, f"no {spec.topic} message could be decoded (the log's "
                                      f"index counts {present.get(spec.topic, 0)}); a damaged "
                                      "or truncated log?", topic=spec.topic)
        msgs, want = _tlog_system(src, stream, spec, msgs, sysid)
        if stream == "imu":
            sysid = want
        t = np.array([_ns(m._timestamp) for m in msgs], dtype=np.int64)
        series[stream] = tlog_series(src, stream, spec, msgs, t, imap, notes)
    _no_fix(src, series)
    return assemble(src, imap, series, "mavlink", "unix (ground station log time)",
                    utc_offset=0.0, notes=notes, fixes_required=False)


def _read_rows(log, names: set[str]) -> dict[str, list[Any]]:
    """The messages of the types ``names`` in a telemetry or DataFlash log, by type (the
    log closed after)."""
    rows: dict[str, list[Any]] = {n: [] for n in names}
    try:
        while True:
            msg = log.recv_match(type=names)
            if msg is None:
                break
            if msg.get_type() in rows:
                rows[msg.get_type()].append(msg)
    finally:
        log.close()
    return rows


def _tlog_system(src: str, stream: str, spec, msgs: list, sysid):
    """The messages of one MAVLink system: the stream's ``instance``, else the IMU's
    (``sysid``), else the only one sending it; ``(messages, system id)``."""
    systems = sorted({m.get_srcSystem() for m in msgs})
    want = spec.instance if spec.instance is not None else sysid
    if want is None:
        if len(systems) > 1:
            raise LogFormatError(src, f"sent by several MAVLink systems {systems}; choose "
                                      f"one: [topics] {stream} = {{ topic = "
                                      f"\"{spec.topic}\", instance = SYSTEM_ID }}",
                                 topic=spec.topic)
        want = systems[0]
    msgs = [m for m in msgs if m.get_srcSystem() == want]
    if not msgs:
        raise LogFormatError(src, f"no {spec.topic} messages from MAVLink system {want} "
                                  f"(systems sending it: {systems})", topic=spec.topic)
    return msgs, want


def tlog_series(src: str, stream: str, spec, msgs: list, t: np.ndarray, imap: ImportMap,
                 notes: list[str]) -> Series:
    """One stream's series from its messages (stamps ``t``, ns); ``notes`` gets what was
    left out."""
    s = Series(stream, spec.topic, spec.topic, t, {})
    if stream == "imu":
        if spec.topic == "ATTITUDE":
            q = euler_to_quat(*(np.array([getattr(m, k) for m in msgs], dtype=float)
                                for k in ("roll", "pitch", "yaw")))
        else:
            q = np.array([(m.q1, m.q2, m.q3, m.q4) for m in msgs], dtype=float)
        s.data = {"q": q, "gyro": np.array([(m.rollspeed, m.pitchspeed, m.yawspeed)
                                            for m in msgs], dtype=float)}
    elif stream == "gnss":
        s = _tlog_gnss(spec.topic, msgs, t)
    elif stream == "motors":
        port = np.array([getattr(m, "port", 0) for m in msgs])
        if (port != 0).any():
            notes.append(f"motors: {int((port != 0).sum())} {spec.topic} messages of "
                         "port 1 (outputs 9-16 in MAVLink 1) left out")
            msgs = [m for m, p in zip(msgs, port) if p == 0]
            t = t[port == 0]
        pwm = np.array([[getattr(m, f"servo{k}_raw", 0) for k in range(1, 17)]
                        for m in msgs], dtype=float)
        s = Series(stream, spec.topic, spec.topic, t,
                   {"u": motor_commands(pwm, imap, src, spec.topic, t, pwm=True,
                                        what="servo output")})
    else:
        if spec.fields.get("offset", 0.0) is None:        # pressure: from the first
            spec.fields["offset"] = -float(getattr(msgs[0], spec.fields["field"])) \
                * spec.fields["scale"]
        s.data = _generic(src, spec, stream, msgs)
    return s


def _no_fix(src: str, series: dict[str, Series]) -> None:
    """A GNSS stream without a single fix is left out, with a warning."""
    g = series.get("gnss")
    why = None
    if g is not None and not len(g.t_ns):
        del series["gnss"]
        why = f"no GNSS fix in {g.topic} (" + ", ".join(
            f"{k}: {v}" for k, v in g.dropped.items() if v) + ")"
    elif g is None and "usbl" not in series:
        why = "no GNSS messages"
    if why is not None:
        warnings.warn(MissionWarning(src, f"{why}: imported as a mission without position "
                                          "fixes (a fit needs fixes from another source, e.g. "
                                          "'aqfg import nmea')"), stacklevel=4)


def _tlog_gnss(topic: str, msgs: list[Any], t: np.ndarray) -> Series:
    fix = np.array([m.fix_type for m in msgs])
    lat = np.array([m.lat for m in msgs], dtype=float) * 1e-7
    lon = np.array([m.lon for m in msgs], dtype=float) * 1e-7
    hacc = np.array([getattr(m, "h_acc", 0) for m in msgs], dtype=float) * 1e-3
    keep = fix >= 2                                   # GPS_FIX_TYPE_2D_FIX and better
    sigma = np.where(hacc > 0, hacc, np.nan)
    return Series("gnss", topic, topic, t[keep],
                  {"lat": lat[keep], "lon": lon[keep], "sigma": sigma[keep]},
                  {"no fix (fix_type < 2)": int((~keep).sum())})


# ------------------------------------------------------------------------- DataFlash

def _read_dataflash(source: Path, imap: ImportMap) -> ImportResult:
    src = str(source)
    from pymavlink import DFReader
    try:
        log = DFReader.DFReader_binary(src, zero_time_base=False)
    except Exception as e:  # noqa: BLE001 - DFReader raises bare Exceptions on bad files
        raise LogFormatError(src, f"cannot read as an ArduPilot DataFlash log: {e}") from None
    present = {n: c for n, c in _df_counts(log).items() if c}
    chosen = _select(src, imap, DF_DEFAULTS, DF_TYPES, present, "DataFlash log")
    names = {s.topic for s in chosen.values()} | {"PARM"}
    if "gnss" in chosen:
        names.add("GPA")
    rows = _read_rows(log, names)
    params = {str(m.Name): float(m.Value) for m in rows["PARM"]}
    imap, notes = servo_map(imap, params)
    series: dict[str, Series] = {}
    utc_offset = None
    for stream, spec in chosen.items():
        msgs = df_instance(spec, rows[spec.topic])
        if not msgs:
            raise LogFormatError(src, f"no {spec.topic} messages of instance I = "
                                      f"{spec.instance or 0}", topic=spec.topic)
        series[stream] = df_series(src, stream, spec, msgs, rows.get("GPA", []), imap)
        if stream == "gnss":
            utc_offset = _df_utc_offset(msgs)
    _no_fix(src, series)
    if utc_offset is None:
        notes.append("no GPS week/time in the log: the mission's UTC time is unknown")
    return assemble(src, imap, series, "mavlink", "boot (DataFlash TimeUS)",
                    utc_offset=utc_offset, notes=notes, fixes_required=False)


def df_instance(spec: TopicSpec, msgs: list[Any]) -> list[Any]:
    """The messages of the stream's instance (field ``I``: the map's ``instance``, else 0)."""
    if msgs and "I" in msgs[0].get_fieldnames():
        inst = spec.instance or 0
        return [m for m in msgs if m.I == inst]
    return msgs


def df_series(src: str, stream: str, spec: TopicSpec, msgs: list[Any], gpa: list[Any],
              imap: ImportMap) -> Series:
    """One stream's series from its DataFlash messages (one instance), stamped with their
    ``TimeUS`` (ns); ``gpa``: the GPA messages giving the fixes' accuracy."""
    t = np.array([int(m.TimeUS) * 1000 for m in msgs], dtype=np.int64)
    s = Series(stream, spec.topic, spec.topic, t, {})
    if stream == "imu":
        att = np.radians(np.array([(m.Roll, m.Pitch, m.Yaw) for m in msgs], dtype=float))
        s.data = {"q": euler_to_quat(att[:, 0], att[:, 1], att[:, 2])}
    elif stream == "gnss":
        s = _df_gnss(spec, msgs, gpa, t)
    elif stream == "motors":
        cols = sorted(int(k[1:]) for k in msgs[0].get_fieldnames()
                      if k[0] == "C" and k[1:].isdigit())
        pwm = np.array([[getattr(m, f"C{k}") for k in range(1, max(cols) + 1)]
                        for m in msgs], dtype=float)
        s.data = {"u": motor_commands(pwm, imap, src, spec.topic, t, pwm=True,
                                      what="output")}
    else:
        s.data = _generic(src, spec, stream, msgs)
    return s


def _df_counts(log) -> dict[str, int]:
    """Messages per type name of a DataFlash log (as DFReader indexed it)."""
    counts = getattr(log, "counts", None)
    out: dict[str, int] = {}
    if counts is not None:
        for mtype, n in enumerate(counts):
            fmt = log.formats.get(mtype)
            if fmt is not None and n:
                out[fmt.name] = out.get(fmt.name, 0) + int(n)
    return out


def _df_gnss(spec: TopicSpec, msgs: list[Any], gpa: list[Any], t: np.ndarray) -> Series:
    status = np.array([m.Status for m in msgs])
    lat = np.array([m.Lat for m in msgs], dtype=float)
    lon = np.array([m.Lng for m in msgs], dtype=float)
    inst = spec.instance or 0
    hacc = {int(m.TimeUS): float(m.HAcc) for m in gpa if getattr(m, "I", 0) == inst}
    sigma = np.array([hacc.get(int(m.TimeUS), np.nan) for m in msgs])
    sigma = np.where(sigma > 0, sigma, np.nan)
    keep = status >= 2                                # 2D fix and better
    return Series("gnss", spec.topic, spec.topic, t[keep],
                  {"lat": lat[keep], "lon": lon[keep], "sigma": sigma[keep]},
                  {"no fix (Status < 2)": int((~keep).sum())})


def _df_utc_offset(msgs: list[Any]) -> float | None:
    """UTC (unix s) at TimeUS = 0, from the first GPS message with a GPS week."""
    for m in msgs:
        wk, ms = int(getattr(m, "GWk", 0)), int(getattr(m, "GMS", 0))
        if wk > 0:
            gps = GPS_EPOCH_UNIX + wk * 604800 + ms * 1e-3
            leap = 0
            for since, n in LEAP_SECONDS:
                if gps >= since:
                    leap = n
            return gps - leap - int(m.TimeUS) * 1e-6
    return None

