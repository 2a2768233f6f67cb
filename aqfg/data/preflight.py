"""Before a fit: make loaded missions safe to estimate from, and say what the fit will cost
before anything is built.

:func:`prepare` applies what the loader's warnings announce (fixes outside the inputs are
not used, unknown GNSS sigmas take the mission's typical value, impossibly small ones are
floored); :func:`estimate_cost` counts the state knots a factor graph of the missions needs
and turns them into rough memory and time figures; :func:`check_cost` refuses, with the
override named, above a limit. Pure functions of the missions: nothing here reads files.
"""
from __future__ import annotations

import copy
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aqfg.data.io.plausibility import GNSS_SIGMA_FLOOR
from aqfg.data.mission import Depth, Gnss, Mission, Usbl
from aqfg.limits import DEFAULT_MAX_KNOTS

log = logging.getLogger(__name__)

# Measured per state knot of a 1-knot-per-second graph fed by a 50-Hz IMU and 10-Hz motors
# (docs/reliability.md, "Cost estimate"); rough on purpose, the refusal is about orders of
# magnitude (a mission whose times are in milliseconds needs 1000 times too many knots).
KNOT_BYTES = 50e3           # peak resident memory per knot, bytes
KNOT_SECONDS = 2e-3         # wall time per knot and batch solve, s (a shared 2-core machine)
LOAD_KNOT_SECONDS = 1e-3    # wall time per knot of the rest: loading, checks, dead reckoning,
#                             outputs, once per command
# Online fits re-solve their window at every fix: measured 0.24-0.26 ms per window knot and
# update for both methods (docs/reliability.md, "Cost estimate").
WINDOW_KNOT_SECONDS = 0.3e-3
# ``aqfg simulate``: per second of simulated mission, time (simulation and CSV writing)
# and memory of the streams held (50-Hz IMU, 10-Hz motors and truth).
SIM_SECONDS = 2e-3
SIM_BYTES = 10e3
SIM_START = 0.2     # s: the simulator's and the writer's set-up, whatever the duration


class CostLimitError(ValueError):
    """A fit whose estimated cost exceeds the limit; the message says how to override."""


def _keep(s, sel):
    if s is None or sel.all():
        return s
    if isinstance(s, Gnss):
        return Gnss(s.t[sel], s.ne[sel], None if s.sigma is None else s.sigma[sel],
                    None if s.latlon is None else s.latlon[sel])
    if isinstance(s, Usbl):
        return Usbl(s.t[sel], s.range[sel], s.bearing[sel],
                    None if s.elevation is None else s.elevation[sel])
    return Depth(s.t[sel], s.depth[sel])


def _check_spans(mission: Mission) -> None:
    """The inputs must span time: imu.csv and motors.csv each need rows at two different
    times (one row, or every row at one time, says nothing about the motion between)."""
    for name, s in (("imu.csv", mission.imu), ("motors.csv", mission.motors)):
        t = np.asarray(s.t, dtype=float)
        if len(t) == 0 or not t[-1] > t[0]:
            what = (f"{len(t)} row" + ("s, every one" if len(t) > 1 else "")
                    + (f" at t = {t[0]:g} s" if len(t) else ""))
            raise ValueError(f"mission {mission.name!r}, {name}: {what}: the inputs span no "
                             "time; a fit needs rows at two different times at least")


def prepare(mission: Mission) -> tuple[Mission, list[str]]:
    """A copy of ``mission`` ready for the estimators, and one note per change made.

    - GNSS, USBL and depth rows outside the inputs' span ``[mission.t0, mission.t1]`` are
      left out (nothing predicts the motion there);
    - GNSS ``sigma`` NaN ("unknown in this row", format doc) takes the median of the
      mission's known sigmas, or, when none is known, the column is dropped so the
      estimator's default applies;
    - GNSS ``sigma`` below :data:`GNSS_SIGMA_FLOOR` is raised to it.

    ValueError when imu.csv or motors.csv spans no time. The input mission is not modified.
    """
    _check_spans(mission)
    m = copy.copy(mission)
    notes: list[str] = []
    t0, t1 = mission.t0, mission.t1
    for key in ("gnss", "usbl", "depth"):
        s = getattr(m, key)
        if s is None or not len(s.t):
            continue
        sel = (s.t >= t0) & (s.t <= t1)
        if not sel.all():
            notes.append(f"{mission.name}: {int((~sel).sum())} {key} rows outside the inputs "
                         f"(t {t0:.6g} .. {t1:.6g} s) not used")
            setattr(m, key, _keep(s, sel))
    g = m.gnss
    if g is not None and g.sigma is not None and len(g.t):
        sig = np.asarray(g.sigma, dtype=float)
        unknown = ~np.isfinite(sig)
        new: np.ndarray | None = sig
        if unknown.all():
            notes.append(f"{mission.name}: GNSS sigma unknown in every row: the estimator's "
                         "default is used")
            new = None
        else:
            if unknown.any():
                typical = float(np.median(sig[~unknown]))
                notes.append(f"{mission.name}: GNSS sigma unknown in {int(unknown.sum())} rows: "
                             f"the mission's median {typical:.3g} m is used there")
                sig = np.where(unknown, typical, sig)
            low = sig < GNSS_SIGMA_FLOOR
            if low.any():
                notes.append(f"{mission.name}: GNSS sigma below {GNSS_SIGMA_FLOOR} m in "
                             f"{int(low.sum())} rows raised to {GNSS_SIGMA_FLOOR} m")
                sig = np.maximum(sig, GNSS_SIGMA_FLOOR)
            new = sig
        if new is None or not np.array_equal(new, g.sigma, equal_nan=True):
            m.gnss = Gnss(g.t, g.ne, new, g.latlon)
    for n in notes:
        log.debug(n)
    return m, notes


@dataclass(frozen=True)
class Cost:
    """What fitting some missions will take, estimated before building anything."""
    duration: float          # s of mission time covered by state knots, all missions
    knots: int               # state knots of one factor graph over all missions
    inputs: int              # IMU and motor rows integrated by the motion model
    fixes: int               # GNSS and USBL fixes inside the inputs
    fits: int                # how many times the graph is built and solved
    memory_bytes: float      # rough peak memory of one fit
    seconds: float           # rough wall time of all fits
    window: float | None = None   # online: the window (s) re-solved at every fix
    window_knots: int = 0    # online: the knots its windows re-solve, all fixes together

    @property
    def work(self) -> int:
        """The work in batch state knots: the knots, or for an online fit the knots its
        windows re-solve, in knots of the same time (what ``--max-knots`` bounds)."""
        return max(self.knots, math.ceil(self.window_knots * WINDOW_KNOT_SECONDS / KNOT_SECONDS))

    def describe(self) -> str:
        online = (f", a {self.window:g}-s window re-solved at each fix" if self.window
                  else "")
        return (f"{self.knots:,} state knots ({_hours(self.duration)} of mission), "
                f"{self.inputs:,} input rows, {self.fixes:,} fixes{online}: about "
                f"{_bytes(self.memory_bytes)} and {_duration(self.seconds)}"
                + (f" for {self.fits} batch solves" if self.fits > 1 else ""))


def _hours(s: float) -> str:
    return f"{s / 3600:.3g} h" if s >= 3600 else f"{s / 60:.3g} min" if s >= 60 else f"{s:.3g} s"


def _duration(s: float) -> str:
    return _hours(s)


def _bytes(b: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6)):
        if b >= size:
            return f"{b / size:.3g} {unit}"
    return f"{b / 1e3:.3g} kB"


def estimate_cost(missions: Sequence[Mission], knot_spacing: float = 1.0,
                  fits: int = 1, window: float | None = None) -> Cost:
    """Knots of a graph with one knot every ``knot_spacing`` s (plus one per fix) from each
    mission's first fix to the end of its inputs, and the rough memory and time they need
    (:data:`KNOT_BYTES`; :data:`LOAD_KNOT_SECONDS` once and :data:`KNOT_SECONDS` for each
    of ``fits`` batch solves). ``window`` (s): an online fit, which re-solves the window's
    knots (the mission's, where shorter) at every fix (:data:`WINDOW_KNOT_SECONDS`); its
    solving time is the larger of that and a batch solve's."""
    if not knot_spacing > 0:
        raise ValueError(f"knot spacing must be positive, got {knot_spacing}")
    if window is not None and not window > 0:
        raise ValueError(f"window must be positive, got {window}")
    knots = inputs = fixes = 0
    duration = 0.0
    window_work = 0
    for m in missions:
        t0, t1 = m.t0, m.t1
        tf = m.fix_times()
        tf = tf[(tf >= t0) & (tf <= t1)]
        start = float(tf[0]) if len(tf) else t0
        span = max(t1 - start, 0.0)
        duration += span
        knots += math.ceil(span / knot_spacing) + 1 + len(np.unique(tf))
        inputs += len(m.imu.t) + len(m.motors.t)
        fixes += len(tf)
        if window is not None:
            window_work += len(tf) * math.ceil(min(window, span) / knot_spacing)
    solve = knots * KNOT_SECONDS
    if window is not None:
        solve = max(solve, window_work * WINDOW_KNOT_SECONDS)
    return Cost(duration, knots, inputs, fixes, fits, knots * KNOT_BYTES,
                knots * LOAD_KNOT_SECONDS + solve * fits, window, int(window_work))


def estimate_simulation(duration: float) -> str:
    """Rough memory and time of ``aqfg simulate`` for ``duration`` s of mission."""
    return (f"{_hours(duration)} of mission: about {_bytes(duration * SIM_BYTES)} and "
            f"{_duration(SIM_START + duration * SIM_SECONDS)}")


def check_cost(cost: Cost, max_knots: int | None = DEFAULT_MAX_KNOTS,
               override: str = "--max-knots") -> None:
    """Raise :class:`CostLimitError` when ``cost.knots`` exceeds ``max_knots`` (None: no
    limit); the message gives the estimate, the likely cause and the override."""
    if max_knots is None or cost.work <= max_knots:
        return
    if cost.knots <= max_knots:           # the online windows, not the mission, are too long
        raise CostLimitError(
            f"refusing an online fit of {cost.describe()}: the windows re-solve as many "
            f"knots as a batch graph of {cost.work:,}; the limit is {max_knots:,}. Pass a "
            f"shorter --window, or {override} {cost.work} to fit anyway")
    raise CostLimitError(
        f"refusing to build a graph of {cost.describe()}; the limit is {max_knots:,} knots. "
        "Are the times in seconds (not milliseconds), and is there no long gap between "
        f"streams? To fit anyway, pass {override} {cost.work}")
