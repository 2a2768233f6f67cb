"""ROS 1 bags and ROS 2 bags (sqlite3 or MCAP storage) -> mission, read with ``rosbags``
(no ROS installation needed; the optional extra ``aqfg[ros]``).

Default topics: ``/imu/data`` (sensor_msgs/msg/Imu), ``/gps/fix``
(sensor_msgs/msg/NavSatFix), ``/thrusters/cmd`` (std_msgs/msg/Float64MultiArray, one
element per thruster, normalised in [-1, 1]). Attitude and body vectors are converted from
REP-103 ENU/FLU to NED/FRD (:mod:`aqfg.data.importers.frames`). Stamps: the messages'
``header.stamp`` where they have one (``[time] stamp = "header"``, the default), else the
recorder's time; ``[time] stamp = "log"`` uses the recorder's time throughout.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    Series,
    assemble,
    at,
    motor_commands,
    require,
    scalar_streams,
)
from aqfg.data.importers.frames import enu_flu_to_ned_frd, flu_to_frd
from aqfg.data.importers.mapfile import ImportMap, TopicSpec
from aqfg.data.importers.truncation import cut_short

DEFAULT_TOPICS = {"imu": "/imu/data", "gnss": "/gps/fix", "motors": "/thrusters/cmd"}
MSG_TYPES = {
    "imu": ("sensor_msgs/msg/Imu",),
    "gnss": ("sensor_msgs/msg/NavSatFix",),
    "motors": ("std_msgs/msg/Float64MultiArray", "std_msgs/msg/Float32MultiArray"),
}
UNIX_AFTER = 1.0e9      # s: ROS stamps past 2001-09-09 are wall-clock (UTC) time, not sim time


def _open(source: Path, version: str):
    require("rosbags", "ros", "ROS bags")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    src = str(source)
    if not source.exists():
        raise LogFormatError(src, "no such file or directory")
    if version == "ros1":
        if source.is_dir() or source.suffix != ".bag":
            raise LogFormatError(src, "expected a ROS 1 bag file (NAME.bag); a ROS 2 bag is "
                                      "a directory or a .mcap/.db3 file: use 'aqfg import ros2'")
        store = Stores.ROS1_NOETIC
    else:
        if source.is_file() and source.suffix == ".bag":
            raise LogFormatError(src, "this is a ROS 1 bag (.bag): use 'aqfg import ros1'")
        if source.is_dir() and not (source / "metadata.yaml").is_file():
            raise LogFormatError(src, "a ROS 2 bag directory needs its metadata.yaml; or pass "
                                      "the .mcap/.db3 storage file itself")
        if source.is_file() and source.suffix not in (".mcap", ".db3"):
            raise LogFormatError(src, "expected a ROS 2 bag: a directory with metadata.yaml, "
                                      "or a .mcap or .db3 storage file")
        store = Stores.ROS2_HUMBLE
    return AnyReader([source], default_typestore=get_typestore(store))


def _reader_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as R1
    from rosbags.rosbag2 import ReaderError as R2
    return (AnyReaderError, R1, R2)


def read_ros(source: str | Path, imap: ImportMap, version: str = "ros2") -> ImportResult:
    """Read a ROS 1 (``version="ros1"``) or ROS 2 bag into a mission (see module doc)."""
    source = Path(source)
    src = str(source)
    reader = _open(source, version)
    cut = cut_short_words(source, version)
    if cut:                 # a sqlite3 reader may not miss its last pages: refused whole
        raise LogFormatError(src, cut)
    errors = _reader_errors()
    try:
        with reader:
            return _read(reader, src, imap, version)
    except errors + (UnicodeDecodeError, struct.error, EOFError) as e:
        raise LogFormatError(src, f"cannot read the bag: {e}") from None


REPAIR = {".bag": "'rosbag reindex'", ".mcap": "'mcap recover'",
          ".db3": "sqlite3's '.recover' (then 'ros2 bag reindex')"}


def cut_short_words(source: Path, version: str) -> str | None:
    """Why a bag that stops before its end cannot be read, or None for a whole bag: its
    readers need the end (a ROS 1 bag's index, an MCAP file's summary and footer, every
    page of a sqlite3 database), so nothing of a cut bag is imported; the repair tool of
    its storage recovers the complete messages."""
    files = (sorted(f for f in source.iterdir() if f.suffix in (".mcap", ".db3"))
             if source.is_dir() else [source])
    for f in files:
        end = cut_short(version, f)
        if end is None:
            continue
        size = f.stat().st_size
        name = f"{f.name}: " if f != source else ""
        if size == 0:
            return f"{name}the file is empty (0 bytes): a recording that never wrote a record"
        return (f"{name}the bag is cut short: it stops at byte {size:,}, in the middle of "
                f"a record or before the end its reader needs (complete records end at byte "
                f"{end:,}): a recording stopped abruptly or a truncated copy. Nothing of it "
                f"is imported; repair it with {REPAIR.get(f.suffix, 'its storage tool')} and "
                "import the repaired bag")
    return None


def _topic_list(topics: dict[str, Any]) -> str:
    return ", ".join(f"{k} ({v.msgtype})" for k, v in sorted(topics.items())) or "none"


def _select(topics: dict[str, Any], src: str, imap: ImportMap) -> dict[str, TopicSpec]:
    chosen: dict[str, TopicSpec] = {}
    for stream in ("imu", "gnss", "motors", "usbl", "depth"):
        spec = imap.topic(stream, DEFAULT_TOPICS.get(stream))
        if spec is None:
            continue
        if spec.topic not in topics:
            if stream == "gnss" and "gnss" not in imap.topics and "usbl" in imap.topics:
                continue                    # default GNSS topic absent, USBL mapped instead
            raise LogFormatError(src, f"topic not in the bag (it has: {_topic_list(topics)}); "
                                      f"map [topics] {stream} to the topic holding the "
                                      f"{stream} stream", topic=spec.topic)
        have = topics[spec.topic].msgtype
        want = MSG_TYPES.get(stream)
        if want is not None and have not in want:
            raise LogFormatError(src, f"message type {have}; the {stream} stream needs "
                                      f"{' or '.join(want)}", topic=spec.topic)
        chosen[stream] = spec
    return chosen


def _read(reader, src: str, imap: ImportMap, version: str) -> ImportResult:
    topics = reader.topics
    chosen = _select(topics, src, imap)
    by_topic: dict[str, list[tuple[int, Any]]] = {s.topic: [] for s in chosen.values()}
    conns = [c for c in reader.connections if c.topic in by_topic]
    for conn, t_log, raw in reader.messages(connections=conns):
        by_topic[conn.topic].append((int(t_log), reader.deserialize(raw, conn.msgtype)))
    notes: list[str] = []
    series: dict[str, Series] = {}
    start = min((ms[0][0] for ms in by_topic.values() if ms), default=0)
    for stream, spec in chosen.items():
        msgs = by_topic[spec.topic]
        msgtype = topics[spec.topic].msgtype
        if not msgs:
            raise LogFormatError(src, f"no {msgtype} messages on the topic", topic=spec.topic)
        t = _stamps(src, spec.topic, msgs, imap, notes, stream, start)
        rows = [m for _, m in msgs]
        s = Series(stream, spec.topic, msgtype, t, {})
        if stream == "imu":
            s.data = _imu(src, spec.topic, rows, t)
        elif stream == "gnss":
            s = _gnss(spec.topic, msgtype, rows, t)
        elif stream == "motors":
            vals = _arrays(src, spec.topic, rows, t)
            s.data = {"u": motor_commands(vals, imap, src, spec.topic, t, pwm=False,
                                          what="element")}
        else:
            try:
                s.data = scalar_streams(spec.fields, stream, rows)
            except (AttributeError, IndexError, KeyError, TypeError, ValueError) as e:
                raise LogFormatError(src, f"cannot read the {stream} fields "
                                          f"{_fields(spec)} of {msgtype}: {e}",
                                     topic=spec.topic) from None
        series[stream] = s
    t_first = min(int(s.t_ns[0]) for s in series.values() if len(s.t_ns))
    unix = t_first * 1e-9 > UNIX_AFTER
    return assemble(src, imap, series, version, "ros (unix time)" if unix else "ros (sim time)",
                    utc_offset=0.0 if unix else None, notes=notes)


def _fields(spec: TopicSpec) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in spec.fields.items())


def _stamps(src: str, topic: str, msgs: list[tuple[int, Any]], imap: ImportMap,
            notes: list[str], stream: str, start: int) -> np.ndarray:
    """Header stamps (checked against the record times) or record times, int64 ns."""
    t_log = np.array([t for t, _ in msgs], dtype=np.int64)
    header = getattr(msgs[0][1], "header", None)
    if imap.stamp == "log":
        return t_log
    if header is None:
        notes.append(f"{stream}: {topic} has no header; the recorder's times are used")
        return t_log
    t_hdr = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                      for _, m in msgs], dtype=np.int64)
    zero = np.flatnonzero(t_hdr == 0)
    if len(zero):
        i = int(zero[0])
        raise LogFormatError(src, "header.stamp is zero (never set by the publisher); set "
                                  "[time] stamp = \"log\" in the map file to use the "
                                  "recorder's times", **at(src, topic, t_log[i], start))
    skew = (t_hdr - t_log) * 1e-9
    bad = np.flatnonzero(np.abs(skew) > imap.max_skew)
    if len(bad):
        i = int(bad[0])
        raise LogFormatError(src, f"header.stamp {t_hdr[i] * 1e-9:.6f} s is {skew[i]:+.3f} s "
                                  f"from the time the message was recorded (more than [time] "
                                  f"max_skew = {imap.max_skew:g} s): a clock jump, or the "
                                  "publisher's clock is not the recorder's; set [time] stamp "
                                  "= \"log\" to use the recorder's times",
                             **at(src, topic, t_log[i], start))
    return t_hdr


def _imu(src: str, topic: str, rows: list[Any], t: np.ndarray) -> dict[str, np.ndarray]:
    m0 = rows[0]
    if m0.orientation_covariance[0] == -1.0:
        raise LogFormatError(src, "the IMU reports no orientation (orientation_covariance[0] "
                                  "= -1); the imu stream needs the attitude", **at(src, topic, t[0]))
    q = np.array([(m.orientation.w, m.orientation.x, m.orientation.y, m.orientation.z)
                  for m in rows])
    out = {"q": enu_flu_to_ned_frd(q)}
    if m0.angular_velocity_covariance[0] != -1.0:
        out["gyro"] = flu_to_frd([(m.angular_velocity.x, m.angular_velocity.y,
                                   m.angular_velocity.z) for m in rows])
    if m0.linear_acceleration_covariance[0] != -1.0:
        out["acc"] = flu_to_frd([(m.linear_acceleration.x, m.linear_acceleration.y,
                                  m.linear_acceleration.z) for m in rows])
    return out


def _gnss(topic: str, msgtype: str, rows: list[Any], t: np.ndarray) -> Series:
    st = np.array([m.status.status for m in rows])
    lat = np.array([m.latitude for m in rows], dtype=float)
    lon = np.array([m.longitude for m in rows], dtype=float)
    cov_t = np.array([m.position_covariance_type for m in rows])
    cov = np.array([(m.position_covariance[0], m.position_covariance[4]) for m in rows])
    nofix = st < 0                                   # STATUS_NO_FIX = -1
    nopos = ~nofix & ~(np.isfinite(lat) & np.isfinite(lon))
    keep = ~(nofix | nopos)
    with np.errstate(invalid="ignore"):
        sigma = np.where(cov_t > 0, np.sqrt(0.5 * (cov[:, 0] + cov[:, 1])), np.nan)
    return Series("gnss", topic, msgtype, t[keep],
                  {"lat": lat[keep], "lon": lon[keep], "sigma": sigma[keep]},
                  {"no fix (status -1)": int(nofix.sum()), "NaN position": int(nopos.sum())})


def _arrays(src: str, topic: str, rows: list[Any], t: np.ndarray) -> np.ndarray:
    n = len(rows[0].data)
    for i, m in enumerate(rows):
        if len(m.data) != n:
            raise LogFormatError(src, f"{len(m.data)} elements where the first message had "
                                      f"{n}; expected one element per thruster in every "
                                      "message", **at(src, topic, t[i]))
    return np.array([np.asarray(m.data, dtype=float) for m in rows]).reshape(len(rows), n)
