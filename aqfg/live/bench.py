"""The figures of ``aqfg live`` for ``aqfg bench``: a simulated mission's MAVLink stream
(ATTITUDE, GPS_RAW_INT, SERVO_OUTPUT_RAW as an ArduPilot vehicle sends them, each packed
into its MAVLink 2 frame and parsed back) fed to :class:`~aqfg.live.runner.LiveRunner` as
fast as possible: the per-message handling time (median); per fix, the time to its report
(mission view, the window's update, report), the work after it (the batch
re-initialisations due there) and both at the stream's real-time pace (a fix that arrives
while the previous one's work runs waits for it); and the RSS over the first and the
last ``edge`` s of the stream (memory flat when these agree). Timings only."""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

from aqfg.data.geodesy import ne_to_latlon
from aqfg.data.importers.mapfile import ImportMap, PwmRange
from aqfg.data.mission import Mission, with_gnss_every

PWM = (1100.0, 1500.0, 1900.0)
ORIGIN = (46.5191, 6.5668)
T_BASE = 1_700_000_000.0


def euler(q: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw (rad, ZYX) of (n, 4) quaternions w, x, y, z body -> NED."""
    w, x, y, z = np.asarray(q, float).T
    return np.column_stack([np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                            np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)),
                            np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))])


def stream_map(m: Mission) -> ImportMap:
    """The import map of :func:`mission_stream`'s vehicle."""
    n = m.n_thrusters
    return ImportMap(vehicle=m.vehicle, name=m.name, thruster_dir=m.thruster_dir,
                     thruster_pos=m.thruster_pos, origin=ORIGIN,
                     pwm=PwmRange(*(np.full(n, v) for v in PWM)))


def mission_frames(m: Mission) -> Iterator[tuple[bytes, int]]:
    """(MAVLink 2 frame, stamp ns) of a mission's IMU, GNSS and motors as an ArduPilot
    boat sends them (ATTITUDE, GPS_RAW_INT, SERVO_OUTPUT_RAW on outputs 1, 2...), in time
    order; stamps unix ns (``T_BASE`` + mission t), fixes placed at ``ORIGIN``."""
    from aqfg.data.importers.mavlink import load_mavutil
    load_mavutil()
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    lo, mid, hi = PWM
    u = m.motors.u
    pwm = np.rint(np.where(u >= 0, mid + u * (hi - mid), mid + u * (mid - lo))).astype(int)
    eul = euler(m.imu.q)
    gyro = m.imu.gyro if m.imu.gyro is not None else np.zeros((len(m.imu.t), 3))
    rows = [(t, 0, i) for i, t in enumerate(m.imu.t)]
    rows += [(t, 1, i) for i, t in enumerate(m.motors.t)]
    if m.gnss is not None:
        ll = ne_to_latlon(m.gnss.ne, ORIGIN)
        rows += [(t, 2, i) for i, t in enumerate(m.gnss.t)]
    rows.sort()
    for t, kind, i in rows:
        if kind == 0:
            msg = tx.attitude_encode(int(t * 1000), *eul[i], *gyro[i])
        elif kind == 1:
            servo = [1500] * 16
            servo[:pwm.shape[1]] = pwm[i].tolist()
            msg = tx.servo_output_raw_encode(int(t * 1e6) % 2**32, 0, *servo)
        else:
            msg = tx.gps_raw_int_encode(int((T_BASE + t) * 1e6), 3, round(ll[i, 0] * 1e7),
                                        round(ll[i, 1] * 1e7), 0, 120, 200, 0, 0, 12)
        yield bytes(msg.pack(tx)), round((T_BASE + t) * 1e6) * 1000


def mission_stream(m: Mission) -> Iterator[tuple[object, int]]:
    """(pymavlink message, stamp ns) of :func:`mission_frames`, each frame parsed back."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    rx = mavlink2.MAVLink(None)
    for frame, stamp in mission_frames(m):
        yield rx.decode(bytearray(frame)), stamp


def write_tlog(m: Mission, path) -> None:
    """:func:`mission_frames` as a telemetry log (big-endian unix microseconds before
    each frame, as ground stations write it)."""
    import struct
    with open(path, "wb") as fh:
        for frame, stamp in mission_frames(m):
            fh.write(struct.pack(">Q", stamp // 1000) + frame)


TARGETS = {"handle_ms": 0.2, "fix_p99_ms": 5.0, "rss_growth": 1.10}


def live_times(duration: float = 7200.0, period: float = 8.0, seed: int = 0,
               edge: float = 600.0, estimate=("theta_e", "s_x", "s_y"),
               rss: Callable[[], float] = lambda: math.nan) -> dict:
    """The stream of a simulated ASV (GNSS every ``period`` s; the smoother as
    :func:`aqfg.bench.stream_times` runs it: 3-fix window, ``estimate`` estimated)
    through :class:`LiveRunner` (module docstring); ``rss()``: the process's memory (MB)."""
    from aqfg.fg.online.smoother import FixedLagSmoother
    from aqfg.live.runner import LiveRunner
    from aqfg.sim.simulator import simulate
    full, truth = simulate("asv", seed=seed, duration=duration,
                           params={"theta_e": float(np.radians(30.0))}, gnss_period=period)
    m = with_gnss_every(full, period)
    init = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    mem: list[tuple[float, float]] = []       # (fix t, RSS) at each fix's first report

    def on_fix(rep) -> None:
        if not rep.revised:
            mem.append((rep.t, rss()))
    runner = LiveRunner(stream_map(m), "bench", lambda: FixedLagSmoother(
        None, estimate=estimate, init=init, window=3 * period), on_fix=on_fix)
    for msg, stamp in mission_stream(m):
        runner.feed(msg, stamp)
    segments = runner.finish()
    t = np.array([x[0] for x in mem])
    r = np.array([x[1] for x in mem])
    first, last = t <= t[0] + edge, t >= t[-1] - edge
    return {"duration": duration, "edge": edge, "messages": runner.n_messages,
            "fixes": runner.n_fix, "handle": list(runner.handle_s), "fix_t": t.tolist(),
            "fix": list(runner.fix_s), "fix_cpu": list(runner.fix_cpu_s),
            "after": list(runner.after_s),
            "update": [u for s in segments for u in s.result.timings.get("update", [])[1:]],
            "rss_first": float(np.median(r[first])), "rss_last": float(np.median(r[last]))}


def at_pace(t, fix, after) -> np.ndarray:
    """Seconds from each fix's arrival (stream time ``t``, s) to its report with the stream
    coming at real time: a fix that arrives while the work after the previous one's report
    (``after``) runs waits for it (message handling left out). ``fix``: to the report."""
    free, out = -math.inf, []
    for tk, f, a in zip(t, fix, after):
        start = max(float(tk), free)
        out.append(start - float(tk) + f)
        free = start + f + a
    return np.array(out)


def report_rows(figs: dict) -> list[tuple[str, str, str]]:
    """Rows (figure, value, target) of the report."""
    h, f, u, a = (np.asarray(figs[k]) for k in ("handle", "fix", "update", "after"))
    ms = 1e3
    slow = a[a > 5e-3]
    pace = at_pace(figs["fix_t"], f, a)
    p99 = float(np.percentile(f, 99))
    growth = figs["rss_last"] / figs["rss_first"]

    def ok(v: float, key: str) -> str:
        return f"{'met' if v <= TARGETS[key] else 'NOT met'} (<= {TARGETS[key]:g})"
    return [(f"aqfg live, {figs['duration'] / 3600:.2g}-h stream at --speed 0 "
             f"({figs['messages']} messages, {figs['fixes']} fixes): per message, median",
             f"{ms * float(np.median(h)):.3f} ms", ok(ms * float(np.median(h)), "handle_ms")),
            ("aqfg live, per fix, to its report (mission view, the window's update, "
             "report): median / p99 / max (p99 of its CPU time, without the waits for "
             "other processes)",
             f"{ms * float(np.median(f)):.2f} / {ms * p99:.2f} / {ms * float(f.max()):.2f} ms "
             f"({ms * float(np.percentile(figs['fix_cpu'], 99)):.2f} ms)",
             ok(ms * p99, "fix_p99_ms")),
            ("aqfg live, the work after a fix's report (batch re-initialisations, before the "
             "next message): the fixes with more than 5 ms of it, their median / max",
             f"{len(slow)}: {ms * float(np.median(slow)) if len(slow) else 0.0:.0f} / "
             f"{ms * float(slow.max()) if len(slow) else 0.0:.0f} ms", ""),
            ("aqfg live, per fix at the stream's real-time pace (from its arrival to its "
             "report; a fix that arrives during that work waits for it): p99 / max",
             f"{ms * float(np.percentile(pace, 99)):.2f} / {ms * float(pace.max()):.2f} ms", ""),
            ("aqfg live, per fix, all of it (to the report and the work after it): "
             "median / p99",
             f"{ms * float(np.median(f + a)):.2f} / {ms * float(np.percentile(f + a, 99)):.2f} ms",
             ""),
            ("aqfg live, per fix, the smoother's window solve alone (timings['update']): "
             "median / p99",
             f"{ms * float(np.median(u)):.2f} / {ms * float(np.percentile(u, 99)):.2f} ms", ""),
            (f"aqfg live, RSS over the first / last {figs['edge'] / 60:.0f} min of the stream",
             f"{figs['rss_first']:.0f} / {figs['rss_last']:.0f} MB",
             f"{'met' if growth <= TARGETS['rss_growth'] else 'NOT met'} (last within "
             f"{100 * (TARGETS['rss_growth'] - 1):.0f} % of first: {growth:.3f})")]
