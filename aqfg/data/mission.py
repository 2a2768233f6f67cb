"""Plain data containers for one mission (format ``aqfg-mission/1``).

Frames: ground = local level NED (metres), body = x forward, y starboard, z down.
Times are seconds on the mission's single clock. Truth lives in :class:`Truth`, a separate
object that :func:`aqfg.data.io.load_mission` never attaches to a :class:`Mission`, so an
estimator handed a ``Mission`` cannot read it by accident.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

FORMAT = "aqfg-mission/1"
VEHICLES = ("asv", "auv")


@dataclass
class Imu:
    """Attitude body->ground as reported by the IMU fusion (yaw unreferenced)."""
    t: np.ndarray                      # (n,) s
    q: np.ndarray                      # (n, 4) quaternion w, x, y, z
    acc: np.ndarray | None = None      # (n, 3) specific force, body, m/s^2
    gyro: np.ndarray | None = None     # (n, 3) angular rate, body, rad/s


@dataclass
class Motors:
    """Normalised propeller commands in [-1, 1]; a command holds until the next row."""
    t: np.ndarray                      # (n,) s
    u: np.ndarray                      # (n, N)


@dataclass
class Gnss:
    """Horizontal position fixes in the NED frame."""
    t: np.ndarray                      # (n,) s
    ne: np.ndarray                     # (n, 2) north, east, m
    sigma: np.ndarray | None = None    # (n,) 1-sigma horizontal, m
    latlon: np.ndarray | None = None   # (n, 2) lat, lon deg as read (geodetic gnss.csv only)


@dataclass
class Usbl:
    """Acoustic fixes seen from the base station."""
    t: np.ndarray                      # (n,) s
    range: np.ndarray                  # (n,) slant range, m
    bearing: np.ndarray                # (n,) azimuth from north, clockwise, rad
    elevation: np.ndarray | None = None  # (n,) rad, optional


@dataclass
class Depth:
    t: np.ndarray                      # (n,) s
    depth: np.ndarray                  # (n,) m, positive down


@dataclass
class Truth:
    """Ground truth of a (simulated) mission: for evaluation only."""
    t: np.ndarray                      # (n,) s
    pos: np.ndarray                    # (n, 3) NED, m
    vel: np.ndarray | None = None      # (n, 3) NED, m/s
    yaw: np.ndarray | None = None      # (n,) rad
    params: dict[str, Any] = field(default_factory=dict)  # the [truth] table


@dataclass
class Mission:
    """One mission: metadata plus one array bundle per stream (no truth)."""
    name: str
    vehicle: str                           # "asv" or "auv"
    thruster_dir: np.ndarray               # (N, 3) unit thrust axes, body
    imu: Imu
    motors: Motors
    thruster_pos: np.ndarray | None = None  # (N, 3) m, body
    gnss: Gnss | None = None
    usbl: Usbl | None = None
    usbl_station: np.ndarray | None = None  # (3,) NED, m
    depth: Depth | None = None
    origin: tuple[float, float] | None = None  # (lat, lon) deg, WGS84
    gnss_latlon: bool = False              # gnss.csv was geodetic (kept for round trips)
    hull: tuple[float, float] | None = None   # (length, beam) m: the [hull] table
    extra: dict[str, Any] = field(default_factory=dict)  # other mission.toml tables

    @property
    def n_thrusters(self) -> int:
        return int(self.thruster_dir.shape[0])

    @property
    def t0(self) -> float:
        return float(min(self.imu.t[0], self.motors.t[0]))

    @property
    def t1(self) -> float:
        return float(max(self.imu.t[-1], self.motors.t[-1]))

    @property
    def planar(self) -> bool:
        """Surface vehicles stay on the surface: no vertical motion (paper §II-D)."""
        return self.vehicle == "asv"

    def fix_times(self) -> np.ndarray:
        """Sorted times of all absolute position fixes (GNSS and USBL)."""
        ts = [s.t for s in (self.gnss, self.usbl) if s is not None and len(s.t)]
        return np.sort(np.concatenate(ts)) if ts else np.zeros(0)

    def thruster_side(self) -> np.ndarray:
        """+1 for starboard thrusters (body y > 0), -1 port, 0 on the centre line.

        Without positions, the first half of the thrusters is port and the rest starboard
        (the convention of the format's example: port first).
        """
        n = self.n_thrusters
        if self.thruster_pos is not None:
            y = self.thruster_pos[:, 1]
            return np.where(y > 1e-9, 1.0, np.where(y < -1e-9, -1.0, 0.0))
        side = -np.ones(n)
        side[n // 2:] = 1.0
        return side


def with_gnss_every(mission: Mission, period: float) -> Mission:
    """A copy keeping one GNSS fix every ``period`` seconds (the first fix is kept).

    The paper restricts GNSS to one fix in 8 s to emulate acoustic positioning (§V-B);
    the dropped fixes stay available to the caller for evaluation.
    """
    import copy
    if mission.gnss is None or period <= 0:
        return mission
    t = mission.gnss.t
    idx, last = [], -np.inf
    for i, ti in enumerate(t):
        if ti >= last + period - 1e-6:
            idx.append(i); last = ti
    keep = np.asarray(idx, dtype=int)
    g = mission.gnss
    out = copy.copy(mission)
    out.gnss = Gnss(g.t[keep], g.ne[keep], None if g.sigma is None else g.sigma[keep])
    return out


def without_gnss(mission: Mission, keep_first: bool = True) -> Mission:
    """A copy with GNSS removed (optionally keeping the first fix, the launch position)."""
    import copy
    out = copy.copy(mission)
    if mission.gnss is None or not len(mission.gnss.t):
        return out
    g = mission.gnss
    n = 1 if keep_first else 0
    out.gnss = Gnss(g.t[:n], g.ne[:n], None if g.sigma is None else g.sigma[:n])
    return out


def samples(stream, keep: np.ndarray):
    """A copy of the stream ``stream`` (:class:`Imu`, :class:`Motors`, :class:`Gnss`,
    :class:`Usbl` or :class:`Depth`) holding only its samples where the boolean ``keep``
    (one per sample) is true: every array field of one row per sample is cut; None stays
    None."""
    import copy
    if stream is None:
        return None
    out = copy.copy(stream)
    n = len(stream.t)
    for f in fields(stream):
        x = getattr(stream, f.name)
        if isinstance(x, np.ndarray) and len(x) == n:
            setattr(out, f.name, x[keep])
    return out


def between(mission: Mission, t_from: float, t_to: float) -> Mission:
    """A copy holding only the samples of every stream (IMU, motors, GNSS, USBL, depth) with
    ``t_from <= t <= t_to`` (s, the mission's clock): part of a mission fitted on its own,
    e.g. from a start under way instead of at rest."""
    import copy
    if not t_to > t_from:
        raise ValueError(f"between: the end {t_to} s is not after the start {t_from} s")
    out = copy.copy(mission)

    def cut(stream):
        return None if stream is None else samples(stream, (stream.t >= t_from) & (stream.t <= t_to))
    out.imu = cut(mission.imu)
    out.motors = cut(mission.motors)
    out.gnss = cut(mission.gnss)
    out.usbl = cut(mission.usbl)
    out.depth = cut(mission.depth)
    return out
