"""Dead reckoning with the model alone: the paper's "inertial trajectory" (§V-A).

Starting from the first absolute fix (position from the fix, velocity zero unless given),
the model integrates the recorded inputs with the given parameters and never looks at a
later fix. Both estimators use this to report ``inertial.csv`` and the evaluations use it
to measure dead-reckoning error.
"""
from __future__ import annotations

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model.measurements import usbl_inverse
from aqfg.model.params import null_vector
from aqfg.model.vehicle import Model
from aqfg.result import Track


def usbl_positions(mission: Mission, down: np.ndarray | None = None,
                   p: np.ndarray | None = None) -> np.ndarray:
    """USBL fixes converted to NED positions (n, 3), m (:func:`~aqfg.model.measurements.usbl_inverse`).

    The vehicle's depth (``down``, default: surface for an ASV, the nearest depth reading
    for an AUV, else the station depth) fixes the vertical leg of the slant range. ``p``
    (full parameter vector, default nominal) supplies the USBL range scale and bearing bias
    that are removed first.
    """
    u = mission.usbl
    if u is None:
        raise ValueError(f"mission {mission.name!r} has no USBL fixes")
    st = np.asarray(mission.usbl_station, float)
    if down is None:
        if mission.planar:
            down = np.zeros(len(u.t))
        elif mission.depth is not None and len(mission.depth.t):
            down = np.interp(u.t, mission.depth.t, mission.depth.depth)
        else:
            down = np.full(len(u.t), st[2])
    return usbl_inverse(u.range, u.bearing, down, st, null_vector() if p is None else p)[0]


def fixes(mission: Mission, p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All absolute fixes as (t (n,), NED position (n, 3)), sorted by time; USBL fixes with
    the range scale and bearing bias of ``p`` removed (default: nominal parameters)."""
    ts, ps = [], []
    if mission.gnss is not None and len(mission.gnss.t):
        down = np.zeros(len(mission.gnss.t))
        if not mission.planar and mission.depth is not None and len(mission.depth.t):
            down = np.interp(mission.gnss.t, mission.depth.t, mission.depth.depth)
        ts.append(mission.gnss.t); ps.append(np.column_stack([mission.gnss.ne, down]))
    if mission.usbl is not None and len(mission.usbl.t):
        ts.append(mission.usbl.t); ps.append(usbl_positions(mission, p=p))
    if not ts:
        return np.zeros(0), np.zeros((0, 3))
    t = np.concatenate(ts); p = np.vstack(ps)
    o = np.argsort(t, kind="stable")
    return t[o], p[o]


def rollout(model: Model, mission: Mission, p: np.ndarray, x0: np.ndarray, t_start: float,
            t_out: np.ndarray) -> Track:
    """Integrate from state ``x0`` at ``t_start`` and report the state at times ``t_out``
    (those before ``t_start`` are dropped)."""
    t_out = np.asarray(t_out, float)
    t_out = t_out[t_out > t_start + 1e-9]
    knots = np.concatenate([[t_start], t_out])
    steps, off = model.steps(mission, knots)
    X = model.rollout_segments(np.asarray(x0, float), p, steps, off)
    return Track(knots, X[:, :3], X[:, 3:])


def inertial_track(model: Model, mission: Mission, p: np.ndarray, rate: float = 10.0,
                   v0: np.ndarray | None = None) -> Track:
    """The paper's inertial trajectory: from the first fix, model only, at ``rate`` Hz."""
    tf, pf = fixes(mission, p)
    if not len(tf):
        raise ValueError(f"mission {mission.name!r} has no absolute fix to start the inertial track from")
    x0 = np.concatenate([pf[0], np.zeros(3) if v0 is None else v0])
    t_out = np.arange(tf[0], mission.t1 + 1e-9, 1.0 / rate)
    return rollout(model, mission, p, x0, tf[0], t_out)
