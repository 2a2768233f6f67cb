"""``aqfg info MISSION``: what a mission holds (streams, durations, rates, gaps).

Truth is only reported as present or absent; its values are never read.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import numpy as np

from aqfg.commands.common import printable
from aqfg.data.io import load_mission, truth_sources
from aqfg.data.mission import FORMAT, Mission

GAP_FACTOR = 3.0          # an interval longer than this many median intervals is a gap


@dataclass
class StreamStats:
    """Timing summary of one stream: times in s, rate in Hz."""
    rows: int
    t0: float = float("nan")
    t1: float = float("nan")
    rate: float = float("nan")          # 1 / median interval (nan if undefined)
    gaps: int = 0                       # intervals > GAP_FACTOR x median interval
    longest_gap: float = 0.0            # s
    longest_gap_at: float = float("nan")  # start time of the longest gap, s


def stream_stats(t: np.ndarray) -> StreamStats:
    """Rows, span, median rate and gaps (intervals > 3x the median interval) of times ``t``."""
    t = np.asarray(t, dtype=float)
    s = StreamStats(len(t))
    if not len(t):
        return s
    s.t0, s.t1 = float(t[0]), float(t[-1])
    if len(t) < 2:
        return s
    dt = np.diff(t)
    med = float(np.median(dt))
    if med <= 0:
        return s
    s.rate = 1.0 / med
    gap = np.flatnonzero(dt > GAP_FACTOR * med)
    s.gaps = len(gap)
    if len(gap):
        k = gap[np.argmax(dt[gap])]
        s.longest_gap, s.longest_gap_at = float(dt[k]), float(t[k])
    return s


def _vec(v) -> str:
    return "[" + ", ".join(f"{x:g}" for x in np.asarray(v, dtype=float)) + "]"


def _stream_line(name: str, s: StreamStats, cols: str = "") -> str:
    if s.rows == 0:
        return f"  {name:<7} {0:>7} rows  (header only)"
    rate = f"{s.rate:8.3g} Hz" if np.isfinite(s.rate) else "    n/a   "
    gaps = ("no gaps" if s.gaps == 0 else
            f"{s.gaps} gap{'s' if s.gaps > 1 else ''} > {GAP_FACTOR:g}x median interval, "
            f"longest {s.longest_gap:.3f} s at t = {s.longest_gap_at:.3f} s")
    line = (f"  {name:<7} {s.rows:>7} rows  t {s.t0:.3f} .. {s.t1:.3f} s  {rate}  {gaps}")
    return line + (f"  [{cols}]" if cols else "")


def describe(m: Mission, truth_parts: list[str] | None = None) -> str:
    """The text ``aqfg info`` prints for a loaded mission."""
    out = [f"mission    {printable(m.name)}", f"format     {FORMAT}",
           f"vehicle    {m.vehicle} ("
           + ("surface vehicle: no vertical motion" if m.planar else "underwater vehicle") + ")"]
    side = {1.0: "starboard", -1.0: "port", 0.0: "centre"}
    thr = []
    for k in range(m.n_thrusters):
        where = (f" at {_vec(m.thruster_pos[k])} m" if m.thruster_pos is not None
                 else f" ({side[float(m.thruster_side()[k])]}, by column order)")
        thr.append(f"  u{k + 1}: axis {_vec(m.thruster_dir[k])}{where}")
    out.append(f"thrusters  {m.n_thrusters}")
    out += thr
    streams: list[tuple[str, Any]] = [("imu", m.imu), ("motors", m.motors), ("gnss", m.gnss),
                                      ("usbl", m.usbl), ("depth", m.depth)]
    ts = [s.t for _, s in streams if s is not None and len(s.t)]
    t0, t1 = min(float(t[0]) for t in ts), max(float(t[-1]) for t in ts)
    out.append(f"duration   {t1 - t0:.3f} s  (t {t0:.3f} .. {t1:.3f} s, all streams)")
    out.append("streams")
    for name, s in streams:
        if s is None:
            out.append(f"  {name:<7} absent")
            continue
        cols = ""
        if name == "imu":
            cols = ", ".join(c for c, a in (("acc", m.imu.acc), ("gyro", m.imu.gyro))
                             if a is not None)
        elif name == "gnss":
            cols = "lat/lon" if m.gnss_latlon else "north/east"
        out.append(_stream_line(name, stream_stats(s.t), cols))
    if m.gnss is not None and len(m.gnss.t):
        sg = m.gnss.sigma
        if sg is None:
            out.append("gnss sigma not given")
        else:
            fin = sg[np.isfinite(sg)]
            txt = (f"min {fin.min():.3g}, median {np.median(fin):.3g}, max {fin.max():.3g} m"
                   if len(fin) else "all unknown")
            nan = len(sg) - len(fin)
            out.append(f"gnss sigma {txt}" + (f" ({nan} unknown)" if nan else ""))
    if m.usbl is not None and len(m.usbl.t):
        r = m.usbl.range
        out.append(f"usbl range {r.min():.3f} .. {r.max():.3f} m from station "
                   f"{_vec(m.usbl_station)} (NED, m)")
    if m.origin is not None:
        out.append(f"origin     lat {m.origin[0]:.7f}, lon {m.origin[1]:.7f} deg (WGS84)")
    if m.extra:
        out.append(f"extra      {', '.join(sorted(m.extra))} (kept, not interpreted)")
    if truth_parts is not None:
        out.append("truth      " + (f"present ({', '.join(truth_parts)}; not read)"
                                    if truth_parts else "absent"))
    return "\n".join(out)


def run(args: argparse.Namespace) -> int:
    from aqfg.data.preflight import estimate_cost
    m = load_mission(args.mission)
    print(describe(m, truth_sources(args.mission)))
    print(f"fit cost   {estimate_cost([m]).describe()} (estimate for one batch solve; "
          "aqfg fit prints its own, with its solves)")
    return 0
