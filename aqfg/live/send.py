"""What ``aqfg live --send-to ENDPOINT`` sends to the autopilot, once per fix:

* ``GPS_INPUT`` (ArduPilot's MAVLink GPS, ``GPS_TYPE = 14``): the smoother's position at
  the fix right after its update (lat/lon from the origin), its north/east velocity and
  horizontal 1-sigma (``horiz_accuracy``, m); altitude, DOPs, vertical velocity and speed
  accuracy marked ignored. Time: GPS week and milliseconds of the fix's stamp.
* ``NAMED_VALUE_FLOAT`` per estimated parameter (its name cut to MAVLink's 10 characters),
  SI units (rad, m/s, ...).

Nothing is sent before the NED frame has an origin (the map's ``[origin]`` or the first fix).
"""
from __future__ import annotations

import math
import time

import numpy as np

from aqfg.data.geodesy import ne_to_latlon
from aqfg.data.importers.mavlink import GPS_EPOCH_UNIX, LEAP_SECONDS, load_mavutil

SOURCE_SYSTEM, SOURCE_COMPONENT = 255, 191       # MAV_COMP_ID_ONBOARD_COMPUTER
# GPS_INPUT_IGNORE_FLAG_ ALT | HDOP | VDOP | VEL_VERT | SPEED_ACCURACY | VERTICAL_ACCURACY
IGNORE = 1 | 2 | 4 | 16 | 32 | 128
NAME_LEN = 10


def gps_week_ms(unix_s: float) -> tuple[int, int]:
    """GPS week and milliseconds of the week of a unix time (s)."""
    leap = 0
    for since, n in LEAP_SECONDS:
        if unix_s >= since:
            leap = n
    gps = unix_s - GPS_EPOCH_UNIX + leap
    week = int(gps // 604800)
    return week, int(round((gps - week * 604800) * 1000))


def gps_input_fields(stamp: float, state: np.ndarray, sigma_ne: np.ndarray,
                     origin: tuple[float, float]) -> dict:
    """The fields of the ``GPS_INPUT`` message of one fix (module docstring)."""
    lat, lon = ne_to_latlon(np.asarray(state[:2], float)[None, :], origin)[0]
    week, ms = gps_week_ms(stamp)
    acc = float(np.nanmax(sigma_ne)) if np.isfinite(sigma_ne).any() else 0.0
    return {"time_usec": int(stamp * 1e6), "gps_id": 0, "ignore_flags": IGNORE,
            "time_week_ms": ms, "time_week": week, "fix_type": 3,
            "lat": int(round(lat * 1e7)), "lon": int(round(lon * 1e7)), "alt": 0.0,
            "hdop": 0.0, "vdop": 0.0, "vn": float(state[3]), "ve": float(state[4]),
            "vd": 0.0, "speed_accuracy": 0.0, "horiz_accuracy": acc,
            "vert_accuracy": 0.0, "satellites_visible": 10}


def named_values(values: dict) -> list[tuple[bytes, float]]:
    """(name, value) of the ``NAMED_VALUE_FLOAT`` messages of one fix."""
    return [(n[:NAME_LEN].encode(), float(v)) for n, v in values.items() if math.isfinite(v)]


class Sender:
    """A MAVLink connection that the fixes are sent on (module docstring)."""

    def __init__(self, endpoint: str):
        mavutil = load_mavutil()
        try:
            self.conn = mavutil.mavlink_connection(endpoint, source_system=SOURCE_SYSTEM,
                                                   source_component=SOURCE_COMPONENT,
                                                   input=False)
        except Exception as e:  # noqa: BLE001 - sockets and serial ports raise many kinds
            raise ValueError(f"--send-to {endpoint}: cannot open it: {e}") from None
        self.t0 = time.monotonic()
        self.sent = 0

    def fix(self, rep, origin: tuple[float, float] | None) -> None:
        if origin is None:
            return
        mav = self.conn.mav
        mav.gps_input_send(**gps_input_fields(rep.stamp, rep.state, rep.sigma_ne, origin))
        boot_ms = int((time.monotonic() - self.t0) * 1000) % 2**32
        for name, v in named_values(rep.values):
            mav.named_value_float_send(boot_ms, name, v)
        self.sent += 1

    def close(self) -> None:
        self.conn.close()
