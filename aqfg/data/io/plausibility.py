"""Suspicious-but-legal input: data the format allows that is probably not what the
writer meant (times in milliseconds, rates in deg/s, duplicate stamps, fixes outside the
inputs...). Each finding is a :class:`MissionWarning` naming the file, the rows (1-based,
header = row 1) and the column, what looks wrong and what the estimators will do with it.

:func:`load_mission` issues these through :mod:`warnings`; :func:`plausibility_warnings`
returns them for a :class:`Mission` built in memory. The thresholds are deliberately
generous: a warning should mean "look at this", never fire on ordinary logs.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from aqfg.data.io.check import MISSION_TOML, STREAM_FILES
from aqfg.data.mission import Mission

IMU_MAX_INTERVAL = 1.0      # s: an IMU reports many times a second; slower means other units
IMU_GAP_MIN = 10.0          # s: an IMU silence longer than this (and 50 intervals) is a gap
SPAN_TOL = 2.0              # s: imu.csv and motors.csv may start/end this far apart quietly
DEG_PER_RAD = 180.0 / np.pi
GYRO_MAX = 2 * np.pi        # rad/s: a small vehicle does not turn a full turn per second
GYRO_WINDOW = 2.0           # s: heading change from the rates vs from the attitude over this
GYRO_MIN_TURN = 0.1         # rad: windows turning less are too small to compare
G = 9.80665                 # m/s^2
GNSS_SIGMA_FLOOR = 0.01     # m: no receiver fix is better than 1 cm (RTK at best)
GNSS_MAX_SPEED = 50.0       # m/s between consecutive fixes, and ...
GNSS_MIN_JUMP = 100.0       # ... at least this far (m): a fix that jumps is an outlier
NED_MAX_OFFSET = 1e5        # m: local NED positions beyond 100 km are not a local frame
USBL_RANGE_TOL = 0.5        # m: slant range shorter than the vertical offset by more than this
MAX_LISTED = 6              # rows listed in a message before "... N rows in all"


class MissionWarning(UserWarning):
    """Legal but suspicious input. Attributes: ``file``, ``rows`` (1-based file rows,
    header = row 1; empty for a whole column or file), ``column`` (or None), ``problem``."""

    def __init__(self, file: str | os.PathLike, problem: str,
                 rows: Sequence[int] = (), column: str | None = None):
        self.file, self.problem, self.column = str(file), problem, column
        self.rows = [int(r) for r in rows]
        where = [self.file]
        if self.rows:
            where.append(format_rows(self.rows))
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(", ".join(where) + ": " + problem)

    def __reduce__(self):
        return (type(self), (self.file, self.problem, self.rows, self.column))


def format_rows(rows: Sequence[int]) -> str:
    """``[2, 3, 4, 9]`` -> "rows 2-4, 9"; long lists end with "... (N rows in all)"."""
    rows = sorted({int(r) for r in rows})
    runs: list[tuple[int, int]] = []
    for r in rows:
        if runs and r == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], r)
        else:
            runs.append((r, r))
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:MAX_LISTED]]
    text = ("row " if len(rows) == 1 else "rows ") + ", ".join(parts)
    if len(runs) > MAX_LISTED:
        text += f", ... ({len(rows)} rows in all)"
    return text


def _rows(idx) -> list[int]:
    return [int(i) + 2 for i in np.atleast_1d(idx)]


def _span(t: np.ndarray) -> str:
    return f"t {float(t[0]):.6g} .. {float(t[-1]):.6g} s"


# ------------------------------------------------------------------------------ checks

def _time_units(m: Mission, f) -> list[MissionWarning]:
    t = m.imu.t
    if len(t) < 3:
        return []
    dt = float(np.median(np.diff(t)))
    if dt > IMU_MAX_INTERVAL:
        return [MissionWarning(f("imu"), f"median interval {dt:.6g} s ({1 / dt:.3g} Hz); an IMU "
                               "reports many times a second: are the times in milliseconds "
                               "(or another unit)? expected seconds on every stream",
                               column="t")]
    return []


def _imu_gaps(m: Mission, f) -> list[MissionWarning]:
    t = m.imu.t
    if len(t) < 3:
        return []
    dt = np.diff(t)
    med = float(np.median(dt))
    gap = np.flatnonzero(dt > max(IMU_GAP_MIN, 50 * med))
    if not len(gap):
        return []
    k = gap[np.argmax(dt[gap])]
    return [MissionWarning(f("imu"), f"{len(gap)} gap(s) in the attitude, longest "
                           f"{float(dt[k]):.6g} s after t = {float(t[k]):.6g} s; the motion "
                           "model integrates across a gap with the attitude interpolated, and "
                           "the graph spans it with state knots (cost grows with time, not "
                           "rows)", rows=_rows(gap + 1), column="t")]


def _input_spans(m: Mission, f) -> list[MissionWarning]:
    out = []
    ti, tm = m.imu.t, m.motors.t
    dur = max(m.t1 - m.t0, 0.0)
    tol = max(SPAN_TOL, 0.01 * dur)
    if tm[0] - ti[0] > tol:
        out.append(MissionWarning(f("motors"), f"starts at t = {float(tm[0]):.6g} s, "
                                  f"{float(tm[0] - ti[0]):.6g} s after imu.csv; before it the "
                                  "first command is used", rows=[2], column="t"))
    if ti[0] - tm[0] > tol:
        out.append(MissionWarning(f("imu"), f"starts at t = {float(ti[0]):.6g} s, "
                                  f"{float(ti[0] - tm[0]):.6g} s after motors.csv; before it "
                                  "the first attitude is held", rows=[2], column="t"))
    if ti[-1] - tm[-1] > tol:
        out.append(MissionWarning(f("motors"), f"ends at t = {float(tm[-1]):.6g} s, "
                                  f"{float(ti[-1] - tm[-1]):.6g} s before imu.csv; the last "
                                  "command holds to the end", rows=[len(tm) + 1], column="t"))
    if tm[-1] - ti[-1] > tol:
        out.append(MissionWarning(f("imu"), f"ends at t = {float(ti[-1]):.6g} s, "
                                  f"{float(tm[-1] - ti[-1]):.6g} s before motors.csv; the last "
                                  "attitude is held to the end", rows=[len(ti) + 1], column="t"))
    return out


def _outside_inputs(m: Mission, f) -> list[MissionWarning]:
    """Fixes and depths before the first or after the last input row are not used."""
    out = []
    t0, t1 = m.t0, m.t1
    for key, s in (("gnss", m.gnss), ("usbl", m.usbl), ("depth", m.depth)):
        if s is None or not len(s.t):
            continue
        for sel, word, edge in ((s.t < t0, "before the first", t0), (s.t > t1, "after the last",
                                                                      t1)):
            idx = np.flatnonzero(sel)
            if len(idx):
                out.append(MissionWarning(
                    f(key), f"{len(idx)} of {len(s.t)} rows ({_span(s.t[idx])}) lie {word} "
                    f"input (imu.csv/motors.csv span t {t0:.6g} .. {t1:.6g} s, edge "
                    f"{edge:.6g} s); nothing predicts the motion there, so the fits do not "
                    "use them", rows=_rows(idx), column="t"))
    return out


def _duplicates(m: Mission, f) -> list[MissionWarning]:
    out = []
    # (stream, times, its arrays, what they hold, unit)
    streams: list[tuple[str, np.ndarray, list[np.ndarray | None], str, float | str]] = [
        ("imu", m.imu.t, [m.imu.q, m.imu.acc, m.imu.gyro], "attitude/rates", 1.0),
               ("motors", m.motors.t, [m.motors.u], "commands", 1.0)]
    if m.gnss is not None:
        streams.append(("gnss", m.gnss.t, [m.gnss.ne], "positions", "m"))
    if m.usbl is not None:
        streams.append(("usbl", m.usbl.t, [m.usbl.range[:, None], m.usbl.bearing[:, None]],
                        "range/bearing", 1.0))
    if m.depth is not None:
        streams.append(("depth", m.depth.t, [m.depth.depth[:, None]], "depths", "m"))
    for key, t, arrays, what, unit in streams:
        same = np.flatnonzero(np.diff(t) == 0)
        if not len(same):
            continue
        vals = np.column_stack([np.asarray(a, float).reshape(len(t), -1)
                                for a in arrays if a is not None])
        a, b = vals[same], vals[same + 1]
        differ = ~np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)
        if not differ.any():
            continue
        idx = same[differ]
        if unit == "m":
            gap = np.linalg.norm(a[differ][:, :2] - b[differ][:, :2], axis=1) \
                if a.shape[1] >= 2 else np.abs(a[differ][:, 0] - b[differ][:, 0])
            size = f" (up to {float(np.nanmax(gap)):.4g} m apart)"
        else:
            size = f" (largest difference {float(np.nanmax(np.abs(a[differ] - b[differ]))):.4g})"
        rows = sorted(set(_rows(idx)) | set(_rows(idx + 1)))
        then = ("the later row's command holds from then on" if key == "motors"
                else "both rows are kept, as two measurements at one instant")
        out.append(MissionWarning(f(key), f"{len(idx)} time stamp(s) repeated with different "
                                  f"{what}{size}: a logging fault? {then}", rows=rows,
                                  column="t"))
    return out


def _gyro_ratio(t: np.ndarray, q: np.ndarray, gyro: np.ndarray) -> float:
    """Median ratio of the heading change integrated from the rates to the heading change
    of the attitude quaternions, over 2-s windows that turn by more than GYRO_MIN_TURN
    (per-sample differences are dominated by attitude noise). NaN if too few turns."""
    w, x, y, z = (q[:, k] for k in range(4))
    yaw = np.unwrap(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    u = q[:, 1:] / np.linalg.norm(q, axis=1, keepdims=True)
    w = w / np.linalg.norm(q, axis=1)
    c = np.cross(u, gyro)
    wz = (gyro + 2 * w[:, None] * c + 2 * np.cross(u, c))[:, 2]    # rate about ground down
    wz = np.where(np.isfinite(wz), wz, 0.0)
    turned = np.concatenate([[0.0], np.cumsum(0.5 * (wz[1:] + wz[:-1]) * np.diff(t))])
    i = np.arange(0, len(t), max(1, len(t) // 2000))
    j = np.minimum(np.searchsorted(t, t[i] + GYRO_WINDOW), len(t) - 1)
    dq, dg = yaw[j] - yaw[i], turned[j] - turned[i]
    use = np.abs(dq) > GYRO_MIN_TURN
    return float(np.median(dg[use] / dq[use])) if use.sum() >= 10 else float("nan")


def _imu_units(m: Mission, f) -> list[MissionWarning]:
    out = []
    i = m.imu
    if i.gyro is not None and len(i.t) > 2:
        g = np.linalg.norm(i.gyro, axis=1)
        ratio = _gyro_ratio(i.t, np.asarray(i.q, float), np.asarray(i.gyro, float))
        if np.isfinite(ratio) and DEG_PER_RAD / 2 < abs(ratio) < DEG_PER_RAD * 2:
            out.append(MissionWarning(f("imu"), f"the angular rates turn the heading {ratio:.3g}"
                                      " times as far as the attitude quaternions do: deg/s "
                                      "instead of rad/s?", column="wx"))
        elif not np.isfinite(ratio):
            fast = np.flatnonzero(g > GYRO_MAX)
            if len(fast) > 0.01 * len(g):
                out.append(MissionWarning(f("imu"), f"{len(fast)} rows turn faster than "
                                          f"{GYRO_MAX:.3g} rad/s (a turn per second): deg/s "
                                          "instead of rad/s?", rows=_rows(fast), column="wx"))
    if i.acc is not None and len(i.t):
        a = np.linalg.norm(i.acc, axis=1)
        med = float(np.nanmedian(a)) if np.isfinite(a).any() else float("nan")
        if np.isfinite(med) and 0.5 < med < 2.0:
            out.append(MissionWarning(f("imu"), f"median |specific force| {med:.3g}: in g "
                                      f"instead of m/s^2 (expected about {G:.3g} at rest)?",
                                      column="ax"))
        elif np.isfinite(med) and med <= 0.5:
            out.append(MissionWarning(f("imu"), f"median |specific force| {med:.3g} m/s^2: "
                                      "gravity removed? the format's ax, ay, az are specific "
                                      f"force (about {G:.3g} m/s^2 at rest)", column="ax"))
    if len(i.t) > 10 and np.all(i.q == i.q[0]):
        out.append(MissionWarning(f("imu"), "the attitude never changes: a vehicle that does "
                                  "not turn cannot show its heading offset", column="qw"))
    return out


def _commands(m: Mission, f) -> list[MissionWarning]:
    u = m.motors.u
    if len(u) and np.all(u == 0):
        return [MissionWarning(f("motors"), "every command is 0: nothing in this mission shows "
                               "the thrust or the drag", column="u1")]
    return []


def _gnss(m: Mission, f) -> list[MissionWarning]:
    g = m.gnss
    if g is None or not len(g.t):
        return []
    out = []
    if g.sigma is not None:
        small = np.flatnonzero(g.sigma < GNSS_SIGMA_FLOOR)
        if len(small):
            out.append(MissionWarning(f("gnss"), f"sigma {float(np.min(g.sigma[small])):.3g} m "
                                      f"in {len(small)} rows: below {GNSS_SIGMA_FLOOR} m, finer "
                                      "than any receiver; the fits use "
                                      f"{GNSS_SIGMA_FLOOR} m there", rows=_rows(small),
                                      column="sigma"))
    far = np.flatnonzero(np.linalg.norm(g.ne, axis=1) > NED_MAX_OFFSET)
    if len(far) and not m.gnss_latlon:
        out.append(MissionWarning(f("gnss"), f"{len(far)} fixes lie more than "
                                  f"{NED_MAX_OFFSET / 1e3:.0f} km from the NED origin: UTM or "
                                  "ECEF coordinates? north/east are metres in a local frame; "
                                  "give lat/lon with an [origin] instead", rows=_rows(far),
                                  column="north"))
    elif len(far):
        out.append(MissionWarning(f("gnss"), f"{len(far)} fixes lie more than "
                                  f"{NED_MAX_OFFSET / 1e3:.0f} km from [origin]: lat and lon "
                                  "swapped, or a wrong origin?", rows=_rows(far), column="lat"))
    dt = np.diff(g.t)
    dist = np.linalg.norm(np.diff(g.ne, axis=0), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.where(dt > 0, dist / np.where(dt > 0, dt, 1.0), np.inf)
    jump = (speed > GNSS_MAX_SPEED) & (dist > GNSS_MIN_JUMP)      # from fix i to fix i + 1
    if jump.any():
        into, out_of = np.append(False, jump), np.append(jump, False)
        lone = into & out_of                      # away from both neighbours: an outlier
        step = jump & ~(lone[:-1] | lone[1:])     # a jump not explained by one outlier
        idx = np.union1d(np.flatnonzero(lone), np.flatnonzero(step) + 1)
        big = float(np.max(dist[jump]))
        kinds = ("away from both neighbouring fixes" if lone.any() else "") + \
                (" / " if lone.any() and step.any() else "") + \
                ("a step from the previous fix" if step.any() else "")
        out.append(MissionWarning(f("gnss"), f"{len(idx)} fix(es) jump faster than "
                                  f"{GNSS_MAX_SPEED:g} m/s, {kinds} (largest jump {big:.4g} m): outliers?",
                                  rows=_rows(idx), column="north"))
    return out


def _usbl(m: Mission, f) -> list[MissionWarning]:
    u = m.usbl
    if u is None or not len(u.t):
        return []
    out = []
    big = np.flatnonzero(np.abs(u.bearing) > 2 * np.pi)
    if len(big):
        out.append(MissionWarning(f("usbl"), f"{len(big)} bearings beyond 2 pi (largest "
                                  f"{float(np.max(np.abs(u.bearing[big]))):.4g}): degrees "
                                  "instead of radians?", rows=_rows(big), column="bearing"))
    if u.elevation is not None:
        big = np.flatnonzero(np.abs(u.elevation) > np.pi / 2)
        if len(big):
            out.append(MissionWarning(f("usbl"), f"{len(big)} elevations beyond pi/2: degrees "
                                      "instead of radians?", rows=_rows(big),
                                      column="elevation"))
    if m.usbl_station is not None:
        down = np.zeros(len(u.t))
        if not m.planar and m.depth is not None and len(m.depth.t):
            down = np.interp(u.t, m.depth.t, m.depth.depth)
        vert = np.abs(down - float(m.usbl_station[2]))
        short = np.flatnonzero(u.range < vert - np.maximum(USBL_RANGE_TOL, 0.05 * vert))
        if len(short) and not m.planar and m.depth is None:
            short = short[:0]            # AUV without depth: the vertical offset is unknown
        if len(short):
            out.append(MissionWarning(f("usbl"), f"{len(short)} slant ranges shorter than the "
                                      "vertical distance between vehicle and station (e.g. "
                                      f"{float(u.range[short[0]]):.4g} m < "
                                      f"{float(vert[short[0]]):.4g} m): km or another unit? "
                                      "expected metres", rows=_rows(short), column="range"))
    return out


def _thrusters(m: Mission, f) -> list[MissionWarning]:
    """A thruster whose demand correlates negatively with the motion it should cause
    (:mod:`aqfg.data.thrusters`)."""
    from aqfg.data.thrusters import thruster_findings
    return [MissionWarning(f("motors"), x.message(),
                           column=None if x.thruster is None else f"u{x.thruster + 1}")
            for x in thruster_findings(m)]


CHECKS = (_time_units, _input_spans, _imu_gaps, _outside_inputs, _duplicates, _imu_units,
          _commands, _gnss, _usbl, _thrusters)


def plausibility_warnings(mission: Mission, where: str | os.PathLike | None = None
                          ) -> list[MissionWarning]:
    """Every suspicious-but-legal finding in a mission that passed :func:`check_mission`.

    Files are named inside ``where`` when given (as :func:`load_mission` does)."""
    def f(key: str) -> str:
        name = MISSION_TOML if key == "toml" else STREAM_FILES[key]
        return str(Path(where) / name) if where is not None else name
    out: list[MissionWarning] = []
    with np.errstate(all="ignore"):
        for check in CHECKS:
            out += check(mission, f)
    return out
