"""A MAVLink stream (or a DataFlash log's messages), message by message -> the growing
mission.

The messages, their system, the PWM range and reversal (``[motors]`` or the vehicle's
``SERVOn_*`` parameters) and every conversion are the importer's
(:mod:`aqfg.data.importers.mavlink`: :func:`~aqfg.data.importers.mavlink.tlog_series`,
:func:`~aqfg.data.importers.mavlink.df_series`, :func:`~aqfg.data.importers.mavlink.servo_map`),
applied to one message at a time, so a log replayed here gives the mission
``aqfg import mavlink`` writes from it. Times are the stream's clock (a tlog's stamps,
DataFlash ``TimeUS``, or the receiving clock of a live link) in integer nanoseconds;
mission ``t`` is seconds from the first message of an imported stream.

What a stream does that a file does not is handled here and counted in ``dropped``:

* a message sent twice (the same own time, ``time_boot_ms``/``time_usec``, as the one
  before it of its type): dropped, "duplicate";
* a message older than the last of its type (own time or stream stamp behind by less than
  :data:`REBOOT_BACK`): dropped, "late";
* the vehicle's boot clock (``time_boot_ms``, ``SERVO_OUTPUT_RAW.time_usec``; not
  ``GPS_RAW_INT``/``GPS2_RAW.time_usec``, which ArduPilot fills with UTC) back by more than
  :data:`REBOOT_BACK` (a reboot), or an input
  stream silent for more than the map's ``[time] max_gap`` (the link was lost): ``add``
  returns a :class:`Restart` and the caller starts a new mission from that message;
* a bad attitude quaternion, a PWM outside its range: dropped, counted, the first reason kept.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.geodesy import latlon_to_ne
from aqfg.data.importers.common import QUAT_TOL, LogFormatError, check_layout, output_channels
from aqfg.data.importers.mapfile import ImportMap, TopicSpec
from aqfg.data.importers.mavlink import (
    DF_DEFAULTS,
    DF_TYPES,
    TLOG_DEFAULTS,
    TLOG_DEPTH,
    TLOG_TYPES,
    _df_utc_offset,
    _select,
    df_instance,
    df_series,
    servo_map,
    tlog_series,
)
from aqfg.data.io.plausibility import GNSS_SIGMA_FLOOR
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Usbl
from aqfg.live.buffers import Column

REBOOT_BACK = 5.0          # s: the vehicle's own clock this far back is a reboot
EARLY_LIMIT = 2000         # messages kept before the vehicle's system is known
HELD_PWM = ("no PWM range (the vehicle's SERVOn_MIN/TRIM/MAX, or [motors] pwm_min/pwm_trim/"
            "pwm_max in the map)")
# the message field that carries the sender's own time, and its units per second
OWN_TIME = {"ATTITUDE": ("time_boot_ms", 1e3), "ATTITUDE_QUATERNION": ("time_boot_ms", 1e3),
            "GLOBAL_POSITION_INT": ("time_boot_ms", 1e3), "SCALED_PRESSURE": ("time_boot_ms", 1e3),
            "SCALED_PRESSURE2": ("time_boot_ms", 1e3), "GPS_RAW_INT": ("time_usec", 1e6),
            "GPS2_RAW": ("time_usec", 1e6), "SERVO_OUTPUT_RAW": ("time_usec", 1e6),
            # DataFlash: the autopilot's time since boot, which is also the stamp
            "ATT": ("TimeUS", 1e6), "GPS": ("TimeUS", 1e6), "GPS2": ("TimeUS", 1e6),
            "RCOU": ("TimeUS", 1e6)}
WRAP32 = {"SERVO_OUTPUT_RAW"}     # a uint32 microsecond field: wraps after 71.6 min
UTC_TIME = {"GPS_RAW_INT", "GPS2_RAW"}   # own time UTC (ArduPilot), not the boot clock


@dataclass
class Restart:
    """The stream cannot go on as one mission: ``reason`` (an event), from ``stamp_ns``."""
    reason: str
    stamp_ns: int


def live_topics(imap: ImportMap, source: str, dataflash: bool = False
                ) -> dict[str, TopicSpec]:
    """The streams and their messages, as the importer chooses them for a tlog or a
    DataFlash log (the map's ``[topics]``, else the defaults), checked the same way; a
    tlog's depth is chosen later (:meth:`StreamAssembler.depth_choice`) when the map names
    none."""
    types = DF_TYPES if dataflash else TLOG_TYPES
    every = {n: 1 for names in types.values() for n in names}
    every.update({s.topic: 1 for s in imap.topics.values()})
    return _select(source, imap, DF_DEFAULTS if dataflash else TLOG_DEFAULTS, types, every,
                   "stream")


class StreamAssembler:
    """Messages -> a growing :class:`~aqfg.data.mission.Mission` (module docstring).

    ``add(msg, stamp_ns)`` takes one pymavlink message; ``ready(t)`` tells whether the
    inputs have passed mission time ``t``; ``mission(t_fixes)`` is the mission so far with
    its fixes up to ``t_fixes``.
    """

    def __init__(self, imap: ImportMap, source: str, params: dict[str, float] | None = None,
                 sysid: int | None = None, dataflash: bool = False):
        self.source = source
        check_layout(source, imap)
        self.base_map = imap
        self.dataflash = dataflash
        self.specs = live_topics(imap, source, dataflash)
        self.depth_auto = imap.vehicle == "auv" and "depth" not in imap.topics and not dataflash
        if self.depth_auto:
            for name, fld, scale in TLOG_DEPTH:
                self.specs[f"depth:{name}"] = TopicSpec(name, None, {"field": fld, "scale": scale})
        for spec in self.specs.values():
            if spec.topic.startswith("SCALED_PRESSURE") and "offset" not in spec.fields:
                spec.fields["offset"] = None       # the first reading (the importer's rule)
        self.by_type: dict[str, list[str]] = {}
        for stream, spec in self.specs.items():
            self.by_type.setdefault(spec.topic, []).append(stream)
        self.params: dict[str, float] = dict(params or {})
        self.imap, self.notes = servo_map(imap, self.params)
        self.sysid = sysid if sysid is not None else self.specs["imu"].instance
        self.compid: int | None = None           # the component that sends the attitude
        self.gps_wait: tuple[Any, int] | None = None     # a DataFlash fix until its GPA
        self.gpa: dict[tuple[int, int], Any] = {}
        self.utc_offset: float | None = None
        self.fixes: list[float] = []
        self.t_zero_ns: int | None = None
        self.dropped: Counter = Counter()
        self.reasons: dict[str, str] = {}
        self.early: list[tuple[Any, int]] = []
        self.held_pwm: list[tuple[Any, int]] = []
        self.last_stamp: dict[str, int] = {}
        self.last_own: dict[str, int] = {}
        self.cols = {s: self._columns(s) for s in self.specs}
        self.origin = imap.origin
        self.sigma_known: bool | None = None
        self.n_messages = 0

    # ------------------------------------------------------------------ input
    def _columns(self, stream: str) -> dict[str, Column]:
        kind = stream.split(":")[0]
        cols = {"t": Column()}
        if kind == "imu":
            cols.update(q=Column(4), gyro=Column(3))
        elif kind == "gnss":
            cols.update(latlon=Column(2), sigma=Column(), ne=Column(2))
        elif kind == "motors":
            cols["u"] = Column(self.base_map.n_thrusters)
        elif kind == "usbl":
            cols.update(range=Column(), bearing=Column(), elevation=Column())
        else:
            cols["depth"] = Column()
        return cols

    def add(self, msg, stamp_ns: int) -> Restart | None:
        """Take one message stamped ``stamp_ns`` (the stream's clock, ns)."""
        self.n_messages += 1
        mtype = msg.get_type()
        if self.dataflash:
            return self._add_dataflash(msg, mtype, stamp_ns)
        if mtype == "PARAM_VALUE":
            self._param(str(msg.param_id).rstrip("\x00"), float(msg.param_value))
            return None
        streams = self.by_type.get(mtype)
        if not streams:
            return None
        if self.sysid is None:
            if "imu" not in streams:
                self.early.append((msg, stamp_ns))
                if len(self.early) > EARLY_LIMIT:
                    self.early.pop(0)
                    self.drop("before the first attitude message", "")
                return None
            self.sysid = msg.get_srcSystem()
            self.compid = msg.get_srcComponent()
            early, self.early = self.early, []
            for m, s in early:
                self.add(m, s)
        if msg.get_srcSystem() != self.sysid:
            self.drop(f"from another MAVLink system than {self.sysid}", mtype)
            return None
        verdict = self._order(msg, mtype, stamp_ns, streams)
        if verdict is not True:
            return verdict or None
        for stream in list(streams):
            self._record(stream, msg, stamp_ns)
        return None

    def _add_dataflash(self, msg, mtype: str, stamp_ns: int) -> Restart | None:
        """:meth:`add` of a DataFlash message: no MAVLink systems; a GPS fix waits for the
        GPA message of its ``TimeUS`` (its accuracy) or the next message."""
        if self.gps_wait is not None and (mtype == "GPA" or stamp_ns > self.gps_wait[1]):
            if mtype == "GPA":
                self.gpa = {(int(getattr(msg, "I", 0)), int(msg.TimeUS)): msg}
            self.flush()
        if mtype == "PARM":
            self._param(str(msg.Name), float(msg.Value))
            return None
        streams = self.by_type.get(mtype)
        if not streams:
            return None
        verdict = self._order(msg, mtype, stamp_ns, streams)
        if verdict is not True:
            return verdict or None
        if not df_instance(self.specs[streams[0]], [msg]):
            return None                      # another instance (another GPS)
        if streams == ["gnss"]:
            self.gps_wait = (msg, stamp_ns)
            return None
        for stream in list(streams):
            self._record(stream, msg, stamp_ns)
        return None

    def flush(self) -> None:
        """Record a DataFlash fix still waiting for its GPA (the log has moved on)."""
        if self.gps_wait is not None:
            msg, stamp = self.gps_wait
            self.gps_wait = None
            self._record("gnss", msg, stamp)

    def _order(self, msg, mtype: str, stamp_ns: int, streams: list[str]) -> bool | Restart:
        """Duplicates, late messages, a reboot, a lost link (module docstring): True (take
        the message), False (dropped, counted) or a :class:`Restart`."""
        own = OWN_TIME.get(mtype)
        if own is not None:
            v = int(getattr(msg, own[0]))
            last = self.last_own.get(mtype)
            if last is not None:
                d = v - last
                if mtype in WRAP32:
                    d = (d + 2**31) % 2**32 - 2**31
                if d == 0:
                    return self.drop("duplicate", mtype)
                if d < 0:
                    if -d / own[1] > REBOOT_BACK and mtype not in UTC_TIME:
                        return Restart(f"vehicle reboot: its clock went back {-d / own[1]:.1f} s "
                                       f"({mtype}.{own[0]})", stamp_ns)
                    return self.drop("late (older than the last of its type)", mtype)
            self.last_own[mtype] = v
        last_s = self.last_stamp.get(mtype)
        if last_s is not None:
            if stamp_ns < last_s:
                return self.drop("late (older than the last of its type)", mtype)
            gap = (stamp_ns - last_s) * 1e-9
            if gap > self.base_map.max_gap and any(s in ("imu", "motors") for s in streams):
                return Restart(f"link lost: no {mtype} for {gap:.1f} s (more than [time] "
                               f"max_gap = {self.base_map.max_gap:g} s)", stamp_ns)
        self.last_stamp[mtype] = stamp_ns
        return True

    def drop(self, why: str, where: str, detail: str = "", n: int = 1) -> bool:
        """Count ``n`` messages (or fixes) left out, by reason (``where: why``); ``detail``:
        the first one's full reason. ``False``, for :meth:`_order`."""
        key = f"{where}: {why}" if where else why
        self.dropped[key] += n
        if detail:
            self.reasons.setdefault(key, detail)
        return False

    def _param(self, name: str, value: float) -> None:
        self.params[name] = value
        if name.startswith("SERVO") and self.imap.pwm is None:
            self.imap, notes = servo_map(self.base_map, self.params)
            self.notes += notes
            if self.imap.pwm is not None:
                held, self.held_pwm = self.held_pwm, []
                for m, s in held:
                    self._record("motors", m, s)

    def params_wanted(self) -> list[str]:
        """The vehicle's parameters the map leaves to it and that have not arrived: each
        thruster output's ``SERVOn_MIN/TRIM/MAX`` (and ``_REVERSED`` unless the map says the
        reversal), while no PWM range is known; none for a DataFlash log."""
        if self.dataflash or self.imap.pwm is not None or self.base_map.n_thrusters is None:
            return []
        keys = ("MIN", "TRIM", "MAX") + (("REVERSED",) if self.base_map.reversed is None else ())
        return [f"SERVO{c}_{k}" for c in output_channels(self.base_map) for k in keys
                if f"SERVO{c}_{k}" not in self.params]

    def _record(self, stream: str, msg, stamp_ns: int) -> None:
        """Convert one message with the importer's function and append it."""
        kind = stream.split(":")[0]
        spec = self.specs[stream]
        if kind == "motors" and self.imap.pwm is None:
            self.held_pwm.append((msg, stamp_ns))       # until SERVOn_* arrive
            if len(self.held_pwm) > EARLY_LIMIT:
                self.held_pwm.pop(0)
                self.drop(HELD_PWM, spec.topic)
            return
        notes: list[str] = []
        try:
            if self.dataflash:
                s = df_series(self.source, kind, spec, [msg], list(self.gpa.values()),
                              self.imap)
                if kind == "gnss" and self.utc_offset is None:
                    self.utc_offset = _df_utc_offset([msg])
            else:
                s = tlog_series(self.source, kind, spec, [msg], np.array([stamp_ns], np.int64),
                                self.imap, notes)
        except LogFormatError as e:
            self.drop(e.problem.split(";")[0], spec.topic, str(e))
            return
        if not len(s.t_ns):
            why = [k for k, v in s.dropped.items() if v] or ["; ".join(notes) or "left out"]
            for k in why:
                self.drop(k, spec.topic)
            return
        if kind == "imu" and abs(float(np.linalg.norm(s.data["q"][0])) - 1.0) > QUAT_TOL:
            self.drop("attitude not a unit quaternion", spec.topic)
            return
        if kind == "gnss" and not self._gnss_ok(s.data):
            return
        if self.t_zero_ns is None:
            self.t_zero_ns = int(stamp_ns)
        c = self.cols[stream]
        c["t"].append(float(stamp_ns - self.t_zero_ns) * 1e-9)
        if kind in ("gnss", "usbl"):
            self.fixes.append(c["t"].last())
        if kind == "gnss":
            self._gnss_frame(c, s.data)
            return
        for k, v in s.data.items():
            c[k].append(v[0])
        if kind == "usbl" and "elevation" not in s.data:
            c["elevation"].append(np.nan)

    def _gnss_ok(self, data: dict) -> bool:
        lat, lon = float(data["lat"][0]), float(data["lon"][0])
        if not (np.isfinite(lat) and np.isfinite(lon) and abs(lat) < 90 and abs(lon) <= 180):
            self.drop("fix outside |lat| < 90, |lon| <= 180 deg", self.specs["gnss"].topic)
            return False
        return True

    def _gnss_frame(self, c: dict[str, Column], data: dict) -> None:
        """The fix in the NED frame of the origin (the map's, else the first fix)."""
        lat, lon = float(data["lat"][0]), float(data["lon"][0])
        if self.origin is None:
            self.origin = (lat, lon)
            self.notes.append("no [origin] in the map: the first fix is the origin of the NED frame")
        c["latlon"].append((lat, lon))
        c["sigma"].append(float(data["sigma"][0]))
        c["ne"].append(latlon_to_ne(np.array([lat]), np.array([lon]), self.origin)[0])

    # ------------------------------------------------------------------ output
    def last_input(self) -> float:
        """Mission time up to which every input stream has data (-inf: none yet)."""
        ts = [self.cols[s]["t"] for s in ("imu", "motors")]
        if any(not len(c) for c in ts):
            return -np.inf
        return float(min(c.last() for c in ts))

    def first_input(self) -> float:
        ts = [self.cols[s]["t"] for s in ("imu", "motors")]
        if any(not len(c) for c in ts):
            return np.inf
        return float(min(c.view(1)[0] for c in ts))

    def fix_times(self) -> list[float]:
        """Mission times of the fixes (GNSS and USBL) recorded so far, in arrival order."""
        return self.fixes

    def depth_choice(self) -> None:
        """An AUV's depth source when the map names none: the first of the importer's
        (:data:`~aqfg.data.importers.mavlink.TLOG_DEPTH`) that the stream has sent so far;
        the others are dropped from here on."""
        if not self.depth_auto:
            return
        self.depth_auto = False
        have = [s for s in list(self.specs) if s.startswith("depth:") and len(self.cols[s]["t"])]
        keep = have[0] if have else None
        for s in [s for s in self.specs if s.startswith("depth:")]:
            spec, cols = self.specs.pop(s), self.cols.pop(s)
            self.by_type[spec.topic].remove(s)
            if s == keep:
                self.specs["depth"], self.cols["depth"] = spec, cols
                self.by_type[spec.topic].append("depth")

    def mission(self, t_fixes: float) -> Mission:
        """The mission so far, its fixes up to ``t_fixes`` (views of the buffers)."""
        imap = self.imap
        assert imap.vehicle is not None and imap.thruster_dir is not None
        ci, cm = self.cols["imu"], self.cols["motors"]
        imu = Imu(ci["t"].view(), ci["q"].view(), None, ci["gyro"].view())
        motors = Motors(cm["t"].view(), cm["u"].view())
        gnss, usbl, depth = None, None, None
        if "gnss" in self.cols and len(self.cols["gnss"]["t"]):
            gnss = self._gnss(t_fixes)
        if "usbl" in self.cols and len(self.cols["usbl"]["t"]):
            cu = self.cols["usbl"]
            tu = cu["t"].view()
            a = int(np.searchsorted(tu, self.first_input() - 1e-12, side="left"))
            n = int(np.searchsorted(tu, t_fixes + 1e-9, side="right"))
            el = cu["elevation"].view(n)[a:]
            if n > a:
                usbl = Usbl(tu[a:n], cu["range"].view(n)[a:], cu["bearing"].view(n)[a:],
                            None if np.isnan(el).all() else el)
        if "depth" in self.cols and len(self.cols["depth"]["t"]):
            cd = self.cols["depth"]
            depth = Depth(cd["t"].view(), cd["depth"].view())
        topics = {k: s.topic for k, s in self.specs.items() if not k.startswith("depth:")}
        extra = dict(imap.extra)
        t_zero = (self.t_zero_ns or 0) * 1e-9
        extra["source"] = {"format": "mavlink", "file": Path(self.source).name,
                           "clock": ("boot (DataFlash TimeUS)" if self.dataflash
                                     else "unix (ground station log time)"),
                           "t_zero": t_zero, "topics": topics}
        utc = self.utc_offset if self.dataflash else 0.0
        if utc is not None:
            extra["source"]["utc_zero"] = float(utc) + t_zero
        return Mission(name=imap.name or Path(self.source).stem or "live", vehicle=imap.vehicle,
                       thruster_dir=imap.thruster_dir, imu=imu, motors=motors,
                       thruster_pos=imap.thruster_pos, gnss=gnss, usbl=usbl,
                       usbl_station=imap.usbl_station, depth=depth, origin=self.origin,
                       hull=imap.hull, gnss_latlon=gnss is not None, extra=extra)

    def _gnss(self, t_fixes: float) -> Gnss | None:
        """The fixes in the inputs' span up to ``t_fixes``, their sigma as the importer and
        the preflight set them: all stated (floored at 1 cm) or none; a fix without one
        in a stream whose first fix stated one takes the median of those before it."""
        cg = self.cols["gnss"]
        t = cg["t"].view()
        a = int(np.searchsorted(t, self.first_input() - 1e-12, side="left"))
        b = int(np.searchsorted(t, t_fixes + 1e-9, side="right"))
        if b <= a:
            return None
        sig = cg["sigma"].view(b)
        if self.sigma_known is None:
            self.sigma_known = bool(np.isfinite(sig[0]) and sig[0] > 0)
        sigma = None
        if self.sigma_known:
            bad = ~(np.isfinite(sig) & (sig > 0))
            sigma = np.maximum(sig, GNSS_SIGMA_FLOOR)
            if bad.any():
                sigma = sigma.copy()
                for i in np.flatnonzero(bad):
                    prev = sig[:i][~bad[:i]]
                    sigma[i] = max(float(np.median(prev)), GNSS_SIGMA_FLOOR)
            sigma = sigma[a:b]
        return Gnss(t[a:b], cg["ne"].view(b)[a:], sigma, cg["latlon"].view(b)[a:])

    def counts(self) -> dict[str, int]:
        """Messages left out so far, by reason; motor messages still held for their PWM
        range among them (they are converted if it arrives)."""
        out = dict(self.dropped)
        if self.held_pwm:
            key = f"{self.specs['motors'].topic}: {HELD_PWM}"      # as drop() keys it
            out[key] = out.get(key, 0) + len(self.held_pwm)
        return out

