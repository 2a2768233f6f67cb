"""Views of a mission for the online smoother: what was known at a time, the inputs a window
of knots needs, and the kernel steps of a recorded mission's knots planned at once."""
from __future__ import annotations

import copy
from typing import Any

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model.vehicle import Model


def mission_until(mission: Mission, t: float) -> Mission:
    """A shallow view of ``mission`` without the fixes and inputs after ``t`` (what was
    known at ``t``)."""
    view = copy.copy(mission)
    a = int(np.searchsorted(mission.imu.t, t + 1e-9, side="right"))
    b = int(np.searchsorted(mission.motors.t, t + 1e-9, side="right"))
    if a >= 2 and b >= 1:
        view.imu = copy.copy(mission.imu)
        for f in ("t", "q", "acc", "gyro"):
            x = getattr(mission.imu, f, None)
            if isinstance(x, np.ndarray) and len(x) == len(mission.imu.t):
                setattr(view.imu, f, x[:a])
        view.motors = copy.copy(mission.motors)
        view.motors.t, view.motors.u = mission.motors.t[:b], mission.motors.u[:b]
    if mission.gnss is not None:
        g = copy.copy(mission.gnss)
        k = mission.gnss.t <= t + 1e-9
        g.t, g.ne = mission.gnss.t[k], mission.gnss.ne[k]
        if mission.gnss.sigma is not None:
            g.sigma = mission.gnss.sigma[k]
        if mission.gnss.latlon is not None:
            g.latlon = mission.gnss.latlon[k]
        view.gnss = g
    if mission.usbl is not None:
        u = copy.copy(mission.usbl)
        k = mission.usbl.t <= t + 1e-9
        u.t, u.range, u.bearing = mission.usbl.t[k], mission.usbl.range[k], mission.usbl.bearing[k]
        if mission.usbl.elevation is not None:
            u.elevation = mission.usbl.elevation[k]
        view.usbl = u
    return view


def window_steps(model: Model, mission: Mission, knots: np.ndarray):
    """``model.steps(mission, knots)`` over a view of the mission cut to the knots' span
    (plus the thrust-lag look-back): build_steps sorts every input time of the mission it is
    given, a cost per update that grows with the mission's length (docs/architecture.md)."""
    t_lo = knots[0] - model.lookback - 1.0
    t_hi = knots[-1] + 1.0
    imu, mot = mission.imu, mission.motors
    a = max(int(np.searchsorted(imu.t, t_lo)) - 1, 0)
    b = int(np.searchsorted(imu.t, t_hi, side="right")) + 1
    c = max(int(np.searchsorted(mot.t, t_lo, side="right")) - 1, 0)
    d = int(np.searchsorted(mot.t, t_hi, side="right")) + 1
    view = copy.copy(mission)
    view.imu = copy.copy(imu)
    view.imu.t, view.imu.q = imu.t[a:b], imu.q[a:b]
    view.motors = copy.copy(mot)
    view.motors.t, view.motors.u = mot.t[c:d], mot.u[c:d]
    steps, off = model.steps(view, knots)
    steps.tm = steps.tm + (view.t0 - mission.t0)    # time since the MISSION start
    return steps, off


class StepSource:
    """Kernel steps between knots of one mission. ``plan``: the mission is recorded (not
    growing): the knots of all its fixes (the rule of the smoother's updates) and their
    steps are built in one build_steps call and sliced per update (docs/architecture.md);
    otherwise each window's steps are built from a view of the mission (:func:`window_steps`)."""

    def __init__(self, model: Model, mission: Mission, fix_t: np.ndarray, spacing: float,
                 plan: bool):
        self.model, self.mission = model, mission
        self.plan: tuple[np.ndarray, dict[float, int], Any, np.ndarray] | None = None
        if plan:
            self._make_plan(fix_t, spacing)

    def _make_plan(self, fix_t: np.ndarray, sp: float) -> None:
        ks = [np.array([fix_t[0]])]
        t_last = float(fix_t[0])
        for t_fix in fix_t[1:]:
            ks.append(np.concatenate([np.arange(t_last + sp, t_fix - sp / 4, sp), [t_fix]]))
            t_last = float(t_fix)
        knots = np.concatenate(ks)
        if len(knots) < 2:
            return
        steps, off = self.model.steps(self.mission, knots)
        self.plan = (knots, {float(t): i for i, t in enumerate(knots)}, steps, off)

    @property
    def planned(self) -> bool:
        return self.plan is not None

    def steps(self, all_t: np.ndarray):
        """Kernel steps for the intervals of ``all_t``: from the plan when it has them."""
        if self.plan is not None:
            knots, index, steps, off = self.plan
            i = index.get(float(all_t[0]))
            j = None if i is None else i + len(all_t) - 1
            if j is not None and j < len(knots) and np.array_equal(knots[i:j + 1], all_t):
                return steps.slice(int(off[i]), int(off[j])), off[i:j + 1] - off[i]
        return window_steps(self.model, self.mission, all_t)

    def interval(self, all_t: np.ndarray):
        """Kernel steps from ``all_t[0]`` to ``all_t[-1]`` in one piece (the numpy engine's
        dynamics factor): a slice of the plan when it has both knots."""
        if self.plan is not None:
            _, index, steps, off = self.plan
            i, j = index.get(float(all_t[0])), index.get(float(all_t[-1]))
            if i is not None and j is not None and j > i:
                return steps.slice(int(off[i]), int(off[j]))
        steps, off = self.steps(all_t)
        return steps.slice(int(off[0]), int(off[-1]))
