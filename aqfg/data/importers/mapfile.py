"""The import map file (TOML): what a log cannot say about the vehicle, and where its
streams are.

Top-level ``vehicle`` (and optional ``name``) and the ``[thrusters]``, ``[usbl]``,
``[origin]`` and ``[hull]`` tables have exactly the shape they have in ``mission.toml`` (they are checked
by the mission reader's own rules); the importer-only tables are ``[topics]`` (stream ->
topic or message name), ``[motors]`` (output channels, sign and PWM range), ``[time]``
(which stamps to use, how far stamps may jump) and ``[csv]`` (the columns of a CSV
export). The shape is documented in docs/mission-format.md, "Importing logs".
"""
from __future__ import annotations

import math
import os
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

try:                                     # Python >= 3.11
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

import tomli_w

from aqfg.data.io import MissionFormatError, MissionWarning, load_mission
from aqfg.data.mission import FORMAT, VEHICLES

STREAMS = ("imu", "gnss", "motors", "usbl", "depth")
MISSION_KEYS = ("vehicle", "name")
MISSION_TABLES = ("thrusters", "usbl", "origin", "hull")
IMPORT_TABLES = ("topics", "motors", "time", "csv")
TOPIC_KEYS = {                       # keys a [topics] entry may hold when it is a table
    "imu": ("topic", "instance"),
    "gnss": ("topic", "instance"),
    "motors": ("topic", "instance"),
    "depth": ("topic", "instance", "field", "scale", "offset"),
    "usbl": ("topic", "instance", "range", "bearing", "elevation", "angle_unit"),
}
STAMPS = ("header", "log")
DEFAULT_MAX_GAP = 60.0       # s: a longer forward step within one stream is a clock jump
DEFAULT_MAX_SKEW = 5.0       # s: |header stamp - record time| beyond this: two clocks
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}      # [csv] time_unit -> seconds
THRUST_UNITS = ("pwm", "N")
CSV_COLUMNS = ("time", "lat", "lon", "north", "east", "sigma", "roll", "pitch", "yaw", "depth")
CSV_KEYS = CSV_COLUMNS + ("time_unit", "angle_unit", "thrust", "thrust_unit", "full_scale")


@dataclass
class TopicSpec:
    """Where one stream is in the log: topic (ROS) or message (MAVLink, DataFlash, ULog,
    NMEA) name, the instance (DataFlash ``I`` field, ULog multi_id) and, for depth and
    USBL, the fields to read."""
    topic: str
    instance: int | None = None
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass
class PwmRange:
    """PWM pulse widths (microseconds) of full reverse, neutral and full forward, one per
    thruster."""
    min: np.ndarray
    trim: np.ndarray
    max: np.ndarray


@dataclass
class CsvSpec:
    """The ``[csv]`` table: which column holds what in a CSV export (one row per time).

    ``columns``: role (``time``, ``lat``/``lon`` or ``north``/``east``, ``sigma``, ``roll``,
    ``pitch``, ``yaw``, ``depth``) -> column name; ``thrust``: one column per thruster;
    ``thrust_unit``: ``"pwm"`` (pulse widths, mapped with ``[motors]``) or ``"N"`` (force,
    ``u|u| = F / full_scale``)."""
    columns: dict[str, str]
    thrust: list[str]
    time_unit: str = "s"
    angle_unit: str = "rad"
    thrust_unit: str = "pwm"
    full_scale: float | None = None             # N, force of a full command (u = 1)


@dataclass
class ImportMap:
    """A parsed map file (see the module docstring); every field may be absent."""
    path: str | None = None
    vehicle: str | None = None
    name: str | None = None
    thruster_dir: np.ndarray | None = None      # (N, 3) unit axes, body FRD
    thruster_pos: np.ndarray | None = None      # (N, 3) m, body FRD
    usbl_station: np.ndarray | None = None      # (3,) NED, m
    origin: tuple[float, float] | None = None   # (lat, lon) deg
    hull: tuple[float, float] | None = None     # (length, beam) m
    topics: dict[str, TopicSpec] = field(default_factory=dict)
    channels: list[int] | None = None           # 1-based output per thruster
    reversed: list[bool] | None = None          # negate the command of each thruster
    pwm: PwmRange | None = None
    pwm_trim_columns: list[str | None] | None = None   # CSV: a column per thruster's trim
    csv: CsvSpec | None = None
    stamp: str = "header"                       # ROS: "header" or "log"
    max_gap: float = DEFAULT_MAX_GAP
    max_skew: float = DEFAULT_MAX_SKEW
    utc_zero: float | None = None               # UTC (unix s) of mission t = 0, for NMEA
    extra: dict[str, Any] = field(default_factory=dict)   # mission.toml extras

    @property
    def n_thrusters(self) -> int | None:
        return None if self.thruster_dir is None else len(self.thruster_dir)

    def topic(self, stream: str, default: str | None) -> TopicSpec | None:
        """The map's entry for ``stream``, else ``default`` as a plain topic (or None)."""
        if stream in self.topics:
            return self.topics[stream]
        return None if default is None else TopicSpec(default)


def load_map(path: str | os.PathLike | None) -> ImportMap:
    """Read and check a map file; ``None`` gives the empty map (every default)."""
    if path is None:
        return ImportMap()
    p = Path(path)
    f = str(p)
    if not p.is_file():
        raise MissionFormatError(f, "no such map file; expected a TOML file (see "
                                    "docs/mission-format.md, 'Importing logs')")
    try:
        with open(p, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise MissionFormatError(f, f"not valid TOML ({e})") from None
    except UnicodeDecodeError as e:
        raise MissionFormatError(f, f"not UTF-8 text ({e.reason})") from None
    return parse_map(raw, f)


def parse_map(raw: dict[str, Any], f: str = "map") -> ImportMap:
    """Check a map file's dict (as read by tomllib); errors name the file and the key."""
    for k in raw:
        if k in ("format", "truth"):
            raise MissionFormatError(f, f"{k!r} belongs in mission.toml, not in a map file",
                                     column=k)
        if k not in MISSION_KEYS + MISSION_TABLES + IMPORT_TABLES:
            raise MissionFormatError(
                f, "unknown key; a map file holds vehicle, name, [thrusters], [usbl], "
                   "[origin], [hull], [topics], [motors], [time] and [csv]", column=k)
    m = ImportMap(path=f)
    m.vehicle = raw.get("vehicle")
    if m.vehicle is not None and m.vehicle not in VEHICLES:
        raise MissionFormatError(f, f"got {m.vehicle!r}; expected one of "
                                    f"{', '.join(map(repr, VEHICLES))}", column="vehicle")
    m.name = raw.get("name")
    if m.name is not None and not isinstance(m.name, str):
        raise MissionFormatError(f, f"got {m.name!r}; expected a string", column="name")
    _mission_tables(m, raw, f)
    _topics(m, raw.get("topics"), f)
    _csv(m, raw.get("csv"), f)
    _motors(m, raw.get("motors"), f)
    _time(m, raw.get("time"), f)
    return m


def _mission_tables(m: ImportMap, raw: dict[str, Any], f: str) -> None:
    """[thrusters], [usbl], [origin], [hull]: parsed by the mission reader itself (so the shape is
    exactly mission.toml's), from a minimal mission written to a scratch directory."""
    org = raw.get("origin")
    if isinstance(org, dict):            # a typo here would silently drop the origin
        for k in org:
            if k not in ("lat", "lon"):
                raise MissionFormatError(f, "unknown key; [origin] holds lat and lon (degrees "
                                            "WGS84)", column=f"[origin] {k}")
    meta: dict[str, Any] = {"format": FORMAT, "vehicle": m.vehicle or VEHICLES[0]}
    meta.update({k: raw[k] for k in MISSION_TABLES if k in raw})
    meta.setdefault("thrusters", {"direction": [[1.0, 0.0, 0.0]]})   # placeholder only
    thr = meta["thrusters"]
    n = len(thr["direction"]) if isinstance(thr, dict) and isinstance(
        thr.get("direction"), list) and thr["direction"] else 1
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        try:
            (root / "mission.toml").write_text(tomli_w.dumps(meta))
        except (TypeError, ValueError) as e:     # pragma: no cover - tomllib output dumps
            raise MissionFormatError(f, f"cannot use the mission tables ({e})") from None
        (root / "imu.csv").write_text("t,qw,qx,qy,qz\n0,1,0,0,0\n")
        (root / "motors.csv").write_text("t," + ",".join(f"u{i + 1}" for i in range(n))
                                         + "\n0" + ",0" * n + "\n")
        try:
            with warnings.catch_warnings():     # a placeholder mission: no data to judge
                warnings.simplefilter("ignore", MissionWarning)
                parsed = load_mission(root)
        except MissionFormatError as e:
            raise MissionFormatError(f, e.problem, column=e.column) from None
    if "thrusters" in raw:
        m.thruster_dir, m.thruster_pos = parsed.thruster_dir, parsed.thruster_pos
    m.usbl_station, m.origin, m.hull = parsed.usbl_station, parsed.origin, parsed.hull
    m.extra = {k: v for k, v in parsed.extra.items() if k in MISSION_TABLES}


def _entry(f: str, stream: str, v: Any) -> TopicSpec:
    col = f"[topics] {stream}"
    if isinstance(v, str):
        if not v:
            raise MissionFormatError(f, "empty topic name", column=col)
        return TopicSpec(v)
    if not isinstance(v, dict):
        raise MissionFormatError(f, f"got {v!r}; expected a topic name or a table "
                                    "{ topic = ..., ... }", column=col)
    allowed = TOPIC_KEYS[stream]
    for k in v:
        if k not in allowed:
            raise MissionFormatError(f, f"unknown key {k!r}; expected {', '.join(allowed)}",
                                     column=col)
    topic = v.get("topic")
    if not isinstance(topic, str) or not topic:
        raise MissionFormatError(f, "missing 'topic' (the topic or message name)", column=col)
    inst = v.get("instance")
    if inst is not None and (isinstance(inst, bool) or not isinstance(inst, int) or inst < 0):
        raise MissionFormatError(f, f"instance {inst!r}; expected an integer >= 0",
                                 column=col)
    fields = {k: x for k, x in v.items() if k not in ("topic", "instance")}
    need = {"depth": ("field",), "usbl": ("range", "bearing")}.get(stream, ())
    for k in need:
        if not isinstance(fields.get(k), str) or not fields[k]:
            raise MissionFormatError(f, f"missing {k!r}: the message field holding the "
                                        f"{'depth (m)' if k == 'field' else k}", column=col)
    if "elevation" in fields and not isinstance(fields["elevation"], str):
        raise MissionFormatError(f, "'elevation' must name a field", column=col)
    for k in ("scale", "offset"):
        if k in fields and not _is_num(fields[k]):
            raise MissionFormatError(f, f"{k} {fields[k]!r}; expected a finite number",
                                     column=col)
    if fields.get("angle_unit", "rad") not in ("rad", "deg"):
        raise MissionFormatError(f, f"angle_unit {fields['angle_unit']!r}; expected "
                                    "'rad' or 'deg'", column=col)
    return TopicSpec(topic, inst, fields)


def _is_table(t: Any, f: str, name: str) -> bool:
    """Whether the map file has the table ``[name]`` (``t``, None where absent); a value
    that is not a table is refused."""
    if t is None:
        return False
    if not isinstance(t, dict):
        raise MissionFormatError(f, f"got {t!r}; expected a [{name}] table", column=name)
    return True


def _known(f: str, table: str, k: str, keys: Sequence[str], what: str = "key; expected") -> None:
    """Refuses the key ``k`` of the map's ``[table]`` unless it is one of ``keys``."""
    if k not in keys:
        raise MissionFormatError(f, f"unknown {what} {', '.join(keys)}", column=f"[{table}] {k}")


def _topics(m: ImportMap, t: Any, f: str) -> None:
    if not _is_table(t, f, "topics"):
        return
    for k, v in t.items():
        _known(f, "topics", k, STREAMS, "stream; expected one of")
        m.topics[k] = _entry(f, k, v)
    if "usbl" in m.topics and m.usbl_station is None:
        raise MissionFormatError(f, "a usbl topic needs [usbl] station = [north, east, down] "
                                    "(m)", column="[usbl] station")


def _is_num(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _per_thruster(f: str, key: str, v: Any, n: int | None) -> np.ndarray:
    col = f"[motors] {key}"
    if _is_num(v):
        return np.full(n or 1, float(v))
    if not (isinstance(v, list) and v and all(_is_num(x) for x in v)):
        raise MissionFormatError(f, f"got {v!r}; expected a number (microseconds) or one "
                                    "per thruster", column=col)
    if n is not None and len(v) != n:
        raise MissionFormatError(f, f"has {len(v)} entries; expected one per thruster ({n})",
                                 column=col)
    return np.array(v, dtype=float)


def _motors(m: ImportMap, t: Any, f: str) -> None:
    if not _is_table(t, f, "motors"):
        return
    known = ("channels", "reversed", "pwm_min", "pwm_trim", "pwm_max")
    for k in t:
        _known(f, "motors", k, known)
    n = m.n_thrusters
    if "channels" in t:
        c = t["channels"]
        if not (isinstance(c, list) and c and all(isinstance(x, int) and not isinstance(x, bool)
                                                  and x >= 1 for x in c)):
            raise MissionFormatError(f, f"got {c!r}; expected a list of output numbers "
                                        "(1-based), one per thruster", column="[motors] channels")
        if n is not None and len(c) != n:
            raise MissionFormatError(f, f"has {len(c)} entries; expected one per thruster "
                                        f"({n}, as in [thrusters] direction)",
                                     column="[motors] channels")
        m.channels = list(c)
    if "reversed" in t:
        r = t["reversed"]
        if not (isinstance(r, list) and all(isinstance(x, bool) for x in r)) or (
                n is not None and len(r) != n):
            raise MissionFormatError(f, f"got {r!r}; expected one true/false per thruster",
                                     column="[motors] reversed")
        m.reversed = list(r)
    pw = [k for k in ("pwm_min", "pwm_trim", "pwm_max") if k in t]
    if pw and len(pw) < 3:
        miss = next(k for k in ("pwm_min", "pwm_trim", "pwm_max") if k not in t)
        raise MissionFormatError(f, "pwm_min, pwm_trim and pwm_max come together",
                                 column=f"[motors] {miss}")
    if pw:
        mid = _trim_columns(m, f, t["pwm_trim"], n)
        lo, hi = (_per_thruster(f, k, t[k], n) for k in ("pwm_min", "pwm_max"))
        if not (len(lo) == len(mid) == len(hi)):
            raise MissionFormatError(f, "pwm_min, pwm_trim, pwm_max have different lengths",
                                     column="[motors] pwm_min")
        known = np.isfinite(mid)          # a trim read from a column is checked row by row
        if not (np.all(lo[known] < mid[known]) and np.all(mid[known] < hi[known])
                and np.all(lo < hi)):
            raise MissionFormatError(f, f"got min {lo.tolist()}, trim {mid.tolist()}, max "
                                        f"{hi.tolist()}; expected pwm_min < pwm_trim < pwm_max",
                                     column="[motors] pwm_trim")
        m.pwm = PwmRange(lo, mid, hi)


def _trim_columns(m: ImportMap, f: str, v: Any, n: int | None) -> np.ndarray:
    """``pwm_trim``: numbers (microseconds), or, in a CSV map, column names holding each
    thruster's zero point row by row (NaN in the returned array where a column is named)."""
    vals = v if isinstance(v, list) else [v]
    if not any(isinstance(x, str) for x in vals):
        return _per_thruster(f, "pwm_trim", v, n)
    col = "[motors] pwm_trim"
    if m.csv is None:
        raise MissionFormatError(f, "a column name is a trim only for CSV exports ([csv] "
                                    "table); expected microseconds", column=col)
    if not isinstance(v, list) or (n is not None and len(v) != n) or not all(
            (isinstance(x, str) and x) or _is_num(x) for x in v):
        raise MissionFormatError(f, f"got {v!r}; expected one column name or number "
                                    f"(microseconds) per thruster ({n})", column=col)
    m.pwm_trim_columns = [x if isinstance(x, str) else None for x in v]
    return np.array([np.nan if isinstance(x, str) else float(x) for x in v])


def _csv(m: ImportMap, t: Any, f: str) -> None:
    """[csv]: column names by role, units, thrust columns (see :class:`CsvSpec`)."""
    if not _is_table(t, f, "csv"):
        return
    for k, v in t.items():
        _known(f, "csv", k, CSV_KEYS)
        if k in CSV_COLUMNS and (not isinstance(v, str) or not v):
            raise MissionFormatError(f, f"got {v!r}; expected a column name", column=f"[csv] {k}")
    need = ["time", "yaw", "thrust"]
    pos = [k for k in ("lat", "lon", "north", "east") if k in t]
    if sorted(pos) not in (["lat", "lon"], ["east", "north"]):
        raise MissionFormatError(f, f"position columns {pos}; expected lat and lon (deg) or "
                                    "north and east (m, NED)", column="[csv] lat")
    for k in need:
        if k not in t:
            raise MissionFormatError(f, f"missing {k!r}: the column holding the "
                                        f"{'time' if k == 'time' else k}"
                                        + (" (a list, one per thruster)" if k == "thrust" else ""),
                                     column=f"[csv] {k}")
    thr = t["thrust"]
    n = m.n_thrusters
    if not (isinstance(thr, list) and thr and all(isinstance(x, str) and x for x in thr)) or (
            n is not None and len(thr) != n):
        raise MissionFormatError(f, f"got {thr!r}; expected one column name per thruster"
                                    + (f" ({n}, as in [thrusters] direction)" if n else ""),
                                 column="[csv] thrust")
    spec = CsvSpec({k: t[k] for k in CSV_COLUMNS if k in t}, list(thr))
    for k, allowed in (("time_unit", tuple(TIME_UNITS)), ("angle_unit", ("rad", "deg")),
                       ("thrust_unit", THRUST_UNITS)):
        if k in t:
            if t[k] not in allowed:
                raise MissionFormatError(f, f"got {t[k]!r}; expected one of "
                                            f"{', '.join(map(repr, allowed))}", column=f"[csv] {k}")
            setattr(spec, k, t[k])
    if "full_scale" in t and (not _is_num(t["full_scale"]) or t["full_scale"] <= 0):
        raise MissionFormatError(f, f"got {t['full_scale']!r}; expected the force (N) of a "
                                    "full command, > 0", column="[csv] full_scale")
    if spec.thrust_unit == "N":
        if "full_scale" not in t:
            raise MissionFormatError(f, "thrust in N needs full_scale: the force (N) of a full "
                                        "forward command (u = 1); u|u| = F / full_scale",
                                     column="[csv] full_scale")
        spec.full_scale = float(t["full_scale"])
    elif "full_scale" in t:
        raise MissionFormatError(f, "full_scale is for thrust_unit = \"N\"; PWM thrust is "
                                    "mapped with [motors] pwm_min, pwm_trim, pwm_max",
                                 column="[csv] full_scale")
    m.csv = spec


def _time(m: ImportMap, t: Any, f: str) -> None:
    if not _is_table(t, f, "time"):
        return
    for k, v in t.items():
        col = f"[time] {k}"
        if k == "stamp":
            if v not in STAMPS:
                raise MissionFormatError(f, f"got {v!r}; expected 'header' (the messages' own "
                                            "stamps) or 'log' (the recorder's)", column=col)
            m.stamp = v
        elif k in ("max_gap", "max_skew"):
            if not _is_num(v) or v <= 0:
                raise MissionFormatError(f, f"got {v!r}; expected seconds > 0", column=col)
            setattr(m, k, float(v))
        elif k == "utc_zero":
            if not _is_num(v) or v < 0:
                raise MissionFormatError(f, f"got {v!r}; expected the UTC time of mission "
                                            "t = 0 in unix seconds", column=col)
            m.utc_zero = float(v)
        else:
            raise MissionFormatError(f, "unknown key; expected stamp, max_gap, max_skew, "
                                        "utc_zero", column=col)
