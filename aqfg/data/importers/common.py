"""What every importer shares: the errors, the optional-dependency check, the per-stream
series a reader hands over, and :func:`assemble`, which checks the stamps and builds the
:class:`~aqfg.data.mission.Mission`.

Times are integer nanoseconds on the log's own clock until :func:`assemble` subtracts the
earliest stamp of the imported streams (``t_zero``): mission ``t`` is seconds from there.
"""
from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from aqfg.data.geodesy import latlon_to_ne
from aqfg.data.importers.mapfile import ImportMap
from aqfg.data.io import MissionFormatError, check_mission
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Usbl

QUAT_TOL = 0.05          # |norm - 1| allowed for an attitude quaternion (the format's)
EXTRAS = {"ros": "rosbags", "mavlink": "pymavlink", "ulog": "pyulog", "nmea": "pynmeagps"}


class LogFormatError(MissionFormatError):
    """A log that cannot become a mission; names the log, the topic and the time.

    Attributes (besides :class:`MissionFormatError`'s): ``topic`` (topic or message name,
    or None), ``time`` (seconds on the log's clock, or None), ``since_start`` (seconds after
    the log's first imported message, or None).
    """

    def __init__(self, file: str | os.PathLike, problem: str, topic: str | None = None,
                 time: float | None = None, since_start: float | None = None):
        self.file, self.row, self.column, self.problem = str(file), None, topic, problem
        self.topic, self.time, self.since_start = topic, time, since_start
        where = [self.file]
        if topic is not None:
            where.append(f"topic {topic}")
        if time is not None:
            at = f"log time {time:.6f} s"
            if since_start is not None:
                at += f" ({since_start:.3f} s after the start)"
            where.append(at)
        ValueError.__init__(self, ", ".join(where) + ": " + problem)

    def __reduce__(self):
        return (type(self), (self.file, self.problem, self.topic, self.time, self.since_start))


class MissingExtraError(ImportError):
    """An optional dependency of one importer is not installed; says how to install it."""


def require(module: str, extra: str, what: str) -> ModuleType:
    """Import ``module`` or raise :class:`MissingExtraError` naming the pip command."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name is not None and e.name.split(".")[0] != module.split(".")[0]:
            raise
        raise MissingExtraError(
            f"reading {what} needs the optional package {EXTRAS[extra]!r}, which is not "
            f"installed; install it with: pip install \"aqfg[{extra}]\"") from None


@dataclass
class Series:
    """One stream as read from a log, before any check.

    ``t_ns``: int64 stamps on the log's clock. ``data`` by stream: imu ``q`` (n, 4) w, x,
    y, z body FRD -> NED, optional ``acc``/``gyro`` (n, 3) FRD; gnss ``lat``, ``lon`` (deg),
    ``sigma`` (m per horizontal axis, NaN unknown); motors ``u`` (n, N) in [-1, 1]; usbl
    ``range`` (m), ``bearing``, ``elevation`` (rad); depth ``depth`` (m, down).
    ``dropped``: reason -> count of messages left out on purpose (e.g. GNSS without fix).
    """
    stream: str
    topic: str
    msgtype: str
    t_ns: np.ndarray
    data: dict[str, np.ndarray]
    dropped: dict[str, int] = field(default_factory=dict)


@dataclass
class ImportResult:
    """A mission read from a log, and what was done on the way."""
    mission: Mission
    series: dict[str, Series]
    t_zero_ns: int                 # log-clock stamp of mission t = 0
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """Lines for the command's output: one per stream, then the notes."""
        m = self.mission
        out = []
        for name, s in self.series.items():
            t = (s.t_ns - self.t_zero_ns) * 1e-9
            n = len(t)
            rate = f"{(n - 1) / (t[-1] - t[0]):7.3g} Hz" if n > 1 and t[-1] > t[0] else \
                "    n/a   "
            drop = "".join(f", {k} left out: {v}" for k, v in s.dropped.items() if v)
            out.append(f"  {name:<7} {n:>7} rows  t {t[0]:8.2f} .. {t[-1]:8.2f} s  {rate}  "
                       f"<- {s.topic} ({s.msgtype}){drop}")
        if m.origin is not None:
            out.append(f"  origin  lat {m.origin[0]:.7f}, lon {m.origin[1]:.7f} deg")
        out += [f"  note: {x}" for x in self.notes]
        return "\n".join(out)


def at(source: str, topic: str | None, t_ns: int | None, start_ns: int | None = None,
       ) -> dict[str, Any]:
    """Keyword arguments locating an error for :class:`LogFormatError`."""
    if t_ns is None:
        return {"topic": topic}
    return {"topic": topic, "time": int(t_ns) * 1e-9,
            "since_start": None if start_ns is None else (int(t_ns) - int(start_ns)) * 1e-9}


# ------------------------------------------------------------------ motor commands

def output_channels(imap: ImportMap) -> list[int]:
    """The output (1-based) driving each thruster: the map's ``[motors] channels``, else
    1..N."""
    return imap.channels or list(range(1, (imap.n_thrusters or 0) + 1))


def motor_commands(values: np.ndarray, imap: ImportMap, source: str, topic: str,
                   t_ns: np.ndarray, pwm: bool, what: str = "output") -> np.ndarray:
    """Select the thrusters' outputs from ``values`` (n, C) and normalise them to [-1, 1].

    Output ``[motors] channels[i]`` (1-based, default i + 1) drives thruster i. With
    ``pwm`` the values are pulse widths (microseconds) mapped piecewise-linearly:
    ``pwm_min`` -> -1, ``pwm_trim`` -> 0, ``pwm_max`` -> +1; a value outside
    [pwm_min, pwm_max] is an error. ``[motors] reversed`` negates a thruster's command.
    """
    n_thr = imap.n_thrusters
    assert n_thr is not None
    values = np.asarray(values, dtype=float).reshape(len(t_ns), -1)
    chans = output_channels(imap)
    if max(chans) > values.shape[1]:
        raise LogFormatError(source, f"[motors] channels asks for {what} {max(chans)} but "
                                     f"the message has {values.shape[1]}", **at(source, topic, None))
    u = values[:, [c - 1 for c in chans]]
    if pwm:
        if imap.pwm_trim_columns is not None:
            raise LogFormatError(source, "[motors] pwm_trim names CSV columns; a log's PWM "
                                         "needs the trims in microseconds", topic=topic)
        if imap.pwm is None:
            raise LogFormatError(source, f"{topic} holds PWM pulse widths; give their range "
                                         "in the map file: [motors] pwm_min, pwm_trim, pwm_max "
                                         "(microseconds, e.g. 1100, 1500, 1900 as in the "
                                         "autopilot's SERVOn_MIN/TRIM/MAX)", topic=topic)
        lo = _fit(imap.pwm.min, n_thr)
        mid = _fit(imap.pwm.trim, n_thr)
        hi = _fit(imap.pwm.max, n_thr)
        bad = (u < lo) | (u > hi) | ~np.isfinite(u)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise LogFormatError(source, f"{what} {chans[j]} (thruster {j + 1}) is {u[i, j]:g} "
                                         f"us, outside [pwm_min, pwm_max] = [{lo[j]:g}, "
                                         f"{hi[j]:g}] of the map file (0 means the output was "
                                         "off)", **at(source, topic, t_ns[i]))
        u = pwm_to_command(u, lo, mid, hi)
    else:
        bad = ~np.isfinite(u) | (np.abs(u) > 1.0)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise LogFormatError(source, f"{what} {chans[j]} (thruster {j + 1}) is {u[i, j]!r}; "
                                         "expected a normalised command in [-1, 1]",
                                 **at(source, topic, t_ns[i]))
    if imap.reversed is not None:
        u = u * np.where(np.asarray(imap.reversed), -1.0, 1.0)
    return u + 0.0                       # no negative zeros in motors.csv


def pwm_to_command(pwm: np.ndarray, lo, mid, hi) -> np.ndarray:
    """Pulse widths (us) -> commands in [-1, 1], piecewise linear: ``lo`` -> -1, ``mid`` ->
    0, ``hi`` -> +1 (each broadcast against ``pwm``; ``mid`` may vary row by row)."""
    return np.where(pwm >= mid, (pwm - mid) / (hi - mid), (pwm - mid) / (mid - lo))


def _fit(v: np.ndarray, n: int) -> np.ndarray:
    return np.full(n, float(v[0])) if len(v) == 1 else np.asarray(v, dtype=float)


# ------------------------------------------------------------------------ assembling

def check_stamps(source: str, s: Series, start_ns: int, max_gap: float) -> None:
    t = s.t_ns
    if not len(t):
        raise LogFormatError(source, f"no usable {s.msgtype} messages"
                             + "".join(f" ({k}: {v})" for k, v in s.dropped.items() if v),
                             topic=s.topic)
    d = np.diff(t)
    fault = first_stamp_fault(d, max_gap * 1e9)
    if fault is None:
        return
    kind, i = fault
    if kind == "back":
        raise LogFormatError(source, f"stamps out of order: {t[i] * 1e-9:.6f} s comes after "
                                     f"{t[i - 1] * 1e-9:.6f} s ({d[i - 1] * 1e-9:+.6f} s); "
                                     "expected non-decreasing stamps (a clock reset, or messages "
                                     "merged from several sources?)",
                             **at(source, s.topic, t[i], start_ns))
    raise LogFormatError(source, f"clock jump: {d[i - 1] * 1e-9:.3f} s without a message "
                                 f"(from {t[i - 1] * 1e-9:.6f} s); more than [time] max_gap "
                                 f"= {max_gap:g} s. If the stream really paused, raise "
                                 "max_gap in the map file's [time] table",
                         **at(source, s.topic, t[i], start_ns))


def first_stamp_fault(d: np.ndarray, max_gap: float) -> tuple[str, int] | None:
    """The first fault in a series' steps between stamps ``d`` (``np.diff`` of the stamps):
    ``("back", i)`` where a stamp is earlier than the one before it, else ``("jump", i)``
    where a step exceeds ``max_gap`` (in ``d``'s unit); ``i`` indexes the later stamp. None
    when the stamps are in order without a jump."""
    back = np.flatnonzero(d < 0)
    if len(back):
        return "back", int(back[0]) + 1
    jump = np.flatnonzero(d > max_gap)
    if len(jump):
        return "jump", int(jump[0]) + 1
    return None


def _check_overlap(source: str, series: dict[str, Series], start_ns: int) -> None:
    """Every stream must share the IMU's clock: its stamps must overlap the IMU's span."""
    ref = series["imu"]
    a0, a1 = int(ref.t_ns[0]), int(ref.t_ns[-1])
    for name, s in series.items():
        b0, b1 = int(s.t_ns[0]), int(s.t_ns[-1])
        if b1 < a0 or b0 > a1:
            raise LogFormatError(
                source, f"the {name} stamps ({b0 * 1e-9:.3f} .. {b1 * 1e-9:.3f} s) do not "
                        f"overlap those of the imu topic {ref.topic} ({a0 * 1e-9:.3f} .. "
                        f"{a1 * 1e-9:.3f} s): the two are on different clocks",
                **at(source, s.topic, b0, start_ns))


def check_layout(source: str, imap: ImportMap) -> None:
    """The map must give what no log says: the vehicle type and the thruster axes."""
    if imap.vehicle is None or imap.thruster_dir is None:
        missing = " and ".join(x for x, v in (("vehicle", imap.vehicle),
                                              ("[thrusters] direction", imap.thruster_dir))
                               if v is None)
        where = f"the map file {imap.path}" if imap.path else "a map file (--map MAP.toml)"
        raise LogFormatError(source, f"the log does not say {missing}; give them in {where}: "
                                     "vehicle = \"asv\" or \"auv\" and [thrusters] direction "
                                     "= one unit axis per propeller (body x forward, y "
                                     "starboard, z down), as in mission.toml")


def assemble(source: str | os.PathLike, imap: ImportMap, series: dict[str, Series],
             fmt: str, clock: str, utc_offset: float | None = None,
             notes: list[str] | None = None, fixes_required: bool = True) -> ImportResult:
    """Check the series' stamps and values and build the mission.

    ``series`` must hold ``imu`` and ``motors``; ``clock`` names the log's clock for the
    ``[source]`` table of mission.toml; ``utc_offset`` is the UTC time (unix seconds) at
    log-clock 0 when the log tells it (0 for a unix clock), from which ``[source] utc_zero``,
    the UTC time of mission t = 0, is written. ``fixes_required``: a mission without a
    gnss or usbl stream is an error (else the caller has noted why it has none).
    """
    src = str(source)
    notes = list(notes or [])
    for k in ("imu", "motors"):
        if k not in series:
            raise LogFormatError(src, f"no {k} stream")
    if fixes_required and "gnss" not in series and "usbl" not in series:
        raise LogFormatError(src, "no position fixes: neither a gnss nor a usbl stream; "
                                  "map [topics] gnss (or usbl) to the topic holding them")
    check_layout(src, imap)
    assert imap.vehicle is not None and imap.thruster_dir is not None
    start = min((int(np.min(s.t_ns)) for s in series.values() if len(s.t_ns)), default=0)
    for s in series.values():
        check_stamps(src, s, start, imap.max_gap)
    _check_overlap(src, series, start)
    t0 = min(int(s.t_ns[0]) for s in series.values())

    def secs(s: Series) -> np.ndarray:
        return (s.t_ns - t0).astype(np.float64) * 1e-9

    imu = _imu(src, series["imu"], secs, start)
    sm = series["motors"]
    motors = Motors(secs(sm), np.asarray(sm.data["u"], dtype=float))
    gnss, origin = _gnss(src, series.get("gnss"), secs, start, imap.origin, notes)
    usbl = None
    if "usbl" in series:
        su = series["usbl"]
        usbl = Usbl(secs(su), np.asarray(su.data["range"], float),
                    np.asarray(su.data["bearing"], float),
                    None if su.data.get("elevation") is None
                    else np.asarray(su.data["elevation"], float))
    depth = None
    if "depth" in series:
        sd = series["depth"]
        depth = Depth(secs(sd), np.asarray(sd.data["depth"], float))
    extra = dict(imap.extra)
    src_table: dict[str, Any] = {
        "format": fmt, "file": Path(src).name, "clock": clock, "t_zero": t0 * 1e-9,
        "topics": {k: s.topic for k, s in series.items()}}
    if utc_offset is not None:
        src_table["utc_zero"] = float(utc_offset) + t0 * 1e-9
    extra["source"] = src_table
    mission = Mission(name=imap.name or Path(src).stem, vehicle=imap.vehicle,
                      thruster_dir=imap.thruster_dir, imu=imu, motors=motors,
                      thruster_pos=imap.thruster_pos, gnss=gnss, usbl=usbl,
                      usbl_station=imap.usbl_station, depth=depth, origin=origin,
                      hull=imap.hull,
                      gnss_latlon=gnss is not None and gnss.latlon is not None, extra=extra)
    if motors.u.shape[1] != mission.n_thrusters:
        raise LogFormatError(src, f"{motors.u.shape[1]} motor commands per message but "
                                  f"[thrusters] lists {mission.n_thrusters} propellers",
                             topic=sm.topic)
    check_mission(mission)
    return ImportResult(mission, series, t0, notes)


def _imu(src: str, si: Series, secs: Callable[[Series], np.ndarray], start: int) -> Imu:
    """The IMU stream, its attitude quaternions checked to be unit ones (``secs``: a
    series' stamps in mission seconds)."""
    q = np.asarray(si.data["q"], dtype=float)
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1.0) > QUAT_TOL))
    if len(bad):
        i = int(bad[0])
        raise LogFormatError(src, f"attitude quaternion {q[i].tolist()} has norm {norm[i]:.4g}; "
                                  "expected a unit quaternion", **at(src, si.topic, si.t_ns[i], start))
    return Imu(secs(si), q, si.data.get("acc"), si.data.get("gyro"))


def _gnss(src: str, sg: Series | None, secs: Callable[[Series], np.ndarray], start: int,
          origin: tuple[float, float] | None, notes: list[str]):
    """The GNSS stream (None: none) from local NED positions or checked latitude/longitude
    (degrees), and the NED frame's origin (the first fix when the map names none, with a
    note)."""
    gnss = None
    if sg is not None and "ne" in sg.data:                   # a local NED frame already
        gnss = Gnss(secs(sg), np.asarray(sg.data["ne"], dtype=float), _sigma(sg, notes))
    elif sg is not None:
        ll = np.column_stack([sg.data["lat"], sg.data["lon"]]).astype(float)
        badll = np.flatnonzero(~np.isfinite(ll).all(axis=1) | (np.abs(ll[:, 0]) >= 90.0)
                               | (np.abs(ll[:, 1]) > 180.0))
        if len(badll):
            i = int(badll[0])
            raise LogFormatError(src, f"fix at lat {ll[i, 0]!r}, lon {ll[i, 1]!r}; expected "
                                      "degrees (|lat| < 90, |lon| <= 180)",
                                 **at(src, sg.topic, sg.t_ns[i], start))
        if origin is None:
            origin = (float(ll[0, 0]), float(ll[0, 1]))
            notes.append("no [origin] in the map: the first fix is the origin of the NED frame")
        gnss = Gnss(secs(sg), latlon_to_ne(ll[:, 0], ll[:, 1], origin), _sigma(sg, notes),
                    latlon=ll)
    return gnss, origin


def _sigma(sg: Series, notes: list[str]) -> np.ndarray | None:
    """The fixes' sigma, or None (with a note) when any fix lacks a positive one."""
    sig = sg.data.get("sigma")
    if sig is None:
        return None
    sig = np.asarray(sig, dtype=float)
    if not np.isfinite(sig).all() or (sig <= 0).any():
        n_bad = int(np.sum(~np.isfinite(sig) | (sig <= 0)))
        notes.append(f"gnss: {n_bad} of {len(sig)} fixes carry no accuracy; no sigma "
                     "column written (the estimators' default applies)")
        return None
    return sig


# ------------------------------------------------------------------- field access

def get_field(msg: Any, path: str) -> Any:
    """``msg.a.b[2]``-style access by a dotted path with optional ``[i]`` indices."""
    obj = msg
    for part in path.split("."):
        name, _, idx = part.partition("[")
        if name:
            obj = obj[name] if isinstance(obj, dict) else getattr(obj, name)
        while idx:
            k, _, rest = idx.partition("]")
            obj = obj[int(k)]
            idx = rest[1:] if rest.startswith("[") else ""
    return obj


def scalar_streams(spec_fields: dict[str, Any], stream: str, rows: list[Any],
                   getter=get_field) -> dict[str, np.ndarray]:
    """Depth or USBL values of ``rows`` (messages) by the map's field names."""
    if stream == "depth":
        v = np.array([float(getter(r, spec_fields["field"])) for r in rows])
        return {"depth": v * float(spec_fields.get("scale", 1.0))
                + float(spec_fields.get("offset", 0.0))}
    k = np.pi / 180.0 if spec_fields.get("angle_unit", "rad") == "deg" else 1.0
    out = {"range": np.array([float(getter(r, spec_fields["range"])) for r in rows]),
           "bearing": k * np.array([float(getter(r, spec_fields["bearing"])) for r in rows])}
    if spec_fields.get("elevation"):
        out["elevation"] = k * np.array([float(getter(r, spec_fields["elevation"]))
                                         for r in rows])
    return out
