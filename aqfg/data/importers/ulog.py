"""PX4 ULog files (``.ulg``) -> mission, read with ``pyulog`` (the optional extra
``aqfg[ulog]``).

PX4 logs NED/FRD already. Default topics: ``vehicle_attitude`` (``q`` body FRD -> NED,
w first), ``vehicle_gps_position`` (``latitude_deg``/``longitude_deg``, or the older
``lat``/``lon`` in 1e-7 degrees; ``eph`` as sigma; fix_type >= 2), ``actuator_motors``
(``control[i]`` normalised in [-1, 1]; NaN, PX4's "disarmed", becomes 0). The topic
``actuator_outputs`` (``output[i]``) holds PWM pulse widths and is normalised with the
map's ``[motors] pwm_*`` range. Clock: the ``timestamp`` field, microseconds since boot,
tied to UTC by the GPS topic's ``time_utc_usec`` when it is set.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    Series,
    assemble,
    motor_commands,
    require,
)
from aqfg.data.importers.mapfile import ImportMap, TopicSpec

DEFAULT_TOPICS = {"imu": "vehicle_attitude", "gnss": "vehicle_gps_position",
                  "motors": "actuator_motors"}
TOPIC_TYPES = {"imu": ("vehicle_attitude", "vehicle_attitude_groundtruth"),
               "gnss": ("vehicle_gps_position", "sensor_gps"),
               "motors": ("actuator_motors", "actuator_outputs")}


def read_ulog(source: str | Path, imap: ImportMap) -> ImportResult:
    """Read a PX4 ULog into a mission (see module doc)."""
    source = Path(source)
    src = str(source)
    if not source.is_file():
        raise LogFormatError(src, "no such file; expected a PX4 ULog (.ulg)")
    pyulog = require("pyulog", "ulog", "PX4 ULog files")
    from pyulog.exceptions import ULogException
    try:
        ulog = pyulog.ULog(src)
    except (ULogException, OSError, ValueError, IndexError) as e:
        raise LogFormatError(src, f"cannot read as a PX4 ULog: {e}") from None
    present: dict[tuple[str, int], dict[str, np.ndarray]] = {
        (d.name, d.multi_id): d.data for d in ulog.data_list}
    names = sorted({f"{n}[{i}]" if i else n for n, i in present})
    notes = ["the log is marked corrupt by pyulog; damaged messages were skipped"] \
        if ulog.file_corruption else []
    series: dict[str, Series] = {}
    utc_offset = None
    for stream in ("imu", "gnss", "motors", "usbl", "depth"):
        spec = imap.topic(stream, DEFAULT_TOPICS.get(stream))
        if spec is None:
            continue
        inst = spec.instance or 0
        data = present.get((spec.topic, inst))
        if data is None or not len(data.get("timestamp", ())):
            if stream == "gnss" and "gnss" not in imap.topics and "usbl" in imap.topics:
                continue
            raise LogFormatError(src, f"topic (instance {inst}) not in the log (it has: "
                                      f"{', '.join(names) or 'none'}); map [topics] {stream} "
                                      f"to the topic holding the {stream} stream",
                                 topic=spec.topic)
        want = TOPIC_TYPES.get(stream)
        if want is not None and spec.topic not in want:
            raise LogFormatError(src, f"the {stream} stream reads {' or '.join(want)}, not "
                                      f"{spec.topic}", topic=spec.topic)
        t = data["timestamp"].astype(np.int64) * 1000
        if stream == "imu":
            q = _array(src, spec, data, "q", 4)
            s = Series(stream, spec.topic, spec.topic, t, {"q": q})
        elif stream == "gnss":
            s = _gnss(src, spec, data, t)
            utc = data.get("time_utc_usec")
            if utc is not None and (utc > 0).any():
                k = int(np.flatnonzero(utc > 0)[0])
                utc_offset = int(utc[k]) * 1e-6 - int(data["timestamp"][k]) * 1e-6
        elif stream == "motors":
            s, n_nan = _motors(src, spec, data, t, imap)
            if n_nan:
                notes.append(f"motors: {n_nan} {spec.topic} messages with NaN (PX4: disarmed, "
                             "motors stopped) read as command 0")
        else:
            try:
                s = Series(stream, spec.topic, spec.topic, t, _scalars(spec, stream, data))
            except KeyError as e:
                raise LogFormatError(src, f"no field {e} (fields: {', '.join(sorted(data))})",
                                     topic=spec.topic) from None
        series[stream] = s
    if utc_offset is None:
        notes.append("no GPS UTC time in the log: the mission's UTC time is unknown")
    return assemble(src, imap, series, "ulog", "boot (ULog timestamp)", utc_offset=utc_offset,
                    notes=notes)


def _array(src: str, spec: TopicSpec, data: dict[str, np.ndarray], name: str,
           n: int) -> np.ndarray:
    cols = [f"{name}[{k}]" for k in range(n)]
    miss = [c for c in cols if c not in data]
    if miss:
        raise LogFormatError(src, f"no field {miss[0]} (fields: {', '.join(sorted(data))})",
                             topic=spec.topic)
    return np.column_stack([data[c].astype(float) for c in cols])


def _gnss(src: str, spec: TopicSpec, data: dict[str, np.ndarray], t: np.ndarray) -> Series:
    if "latitude_deg" in data:
        lat, lon = data["latitude_deg"].astype(float), data["longitude_deg"].astype(float)
    elif "lat" in data:
        lat, lon = data["lat"].astype(float) * 1e-7, data["lon"].astype(float) * 1e-7
    else:
        raise LogFormatError(src, "no latitude_deg/longitude_deg (or lat/lon) fields",
                             topic=spec.topic)
    fix = data.get("fix_type", np.full(len(t), 3))
    eph = data.get("eph")
    sigma = eph.astype(float) if eph is not None else np.full(len(t), np.nan)
    keep = fix >= 2
    return Series("gnss", spec.topic, spec.topic, t[keep],
                  {"lat": lat[keep], "lon": lon[keep], "sigma": sigma[keep]},
                  {"no fix (fix_type < 2)": int((~keep).sum())})


def _motors(src: str, spec: TopicSpec, data: dict[str, np.ndarray], t: np.ndarray,
            imap: ImportMap) -> tuple[Series, int]:
    name = "control" if spec.topic == "actuator_motors" else "output"
    n = 0
    while f"{name}[{n}]" in data:
        n += 1
    if n == 0:
        raise LogFormatError(src, f"no {name}[i] fields", topic=spec.topic)
    vals = _array(src, spec, data, name, n)
    n_nan = 0
    if name == "control":
        nan = np.isnan(vals)
        used = [c - 1 for c in (imap.channels or range(1, (imap.n_thrusters or 0) + 1))
                if c <= vals.shape[1]]
        n_nan = int(nan[:, used].any(axis=1).sum())
        vals = np.where(nan, 0.0, vals)      # NaN: disarmed, motors stopped
    u = motor_commands(vals, imap, src, spec.topic, t, pwm=name == "output",
                       what="output" if name == "output" else "motor")
    return Series("motors", spec.topic, spec.topic, t, {"u": u}), n_nan


def _scalars(spec: TopicSpec, stream: str, data: dict[str, np.ndarray]) -> dict[str, Any]:
    f = spec.fields
    if stream == "depth":
        return {"depth": data[f["field"]].astype(float) * float(f.get("scale", 1.0))
                + float(f.get("offset", 0.0))}
    k = np.pi / 180.0 if f.get("angle_unit", "rad") == "deg" else 1.0
    out = {"range": data[f["range"]].astype(float), "bearing": k * data[f["bearing"]]}
    if f.get("elevation"):
        out["elevation"] = k * data[f["elevation"]].astype(float)
    return out
