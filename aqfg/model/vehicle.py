"""The vehicle model that every estimator, the simulator and the diagnosis ask.

:class:`Model` holds the parameter layout (:mod:`aqfg.model.params`), the thruster geometry and
the active effects, and answers two questions:

* "given the state, the inputs over ``[t0, t1]`` and the parameters, what is the next
  state, and its Jacobians?" -> :meth:`Model.propagate` (C++ kernel ``aqfg._kernel``, or the
  numpy mirror :mod:`aqfg.model.reference` when a user effect is active or the extension is not
  built);
* "what does sensor S measure from this state?" -> :meth:`Model.h_gnss`,
  :meth:`Model.h_usbl`, :meth:`Model.h_depth`.

The inputs between two times are turned into kernel steps by :func:`build_steps`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from types import ModuleType

import numpy as np

from aqfg.data.mission import Mission
from aqfg.memo import remember
from aqfg.model import batched
from aqfg.model import measurements as meas
from aqfg.model import reference as ref
from aqfg.model.effects import BUILTIN, DemandLagTerm, Effect, GroundForceTerm, resolve
from aqfg.model.params import BASE_NAMES, INDEX, N_DYN, N_PARAMS, ParamSpec
from aqfg.model.reference import Geometry, Steps

try:  # the compiled kernel; the numpy mirror serves when it is missing
    from aqfg import _kernel as _cpp
except ImportError:  # pragma: no cover - exercised only without a build
    _cpp = None


def compiled_kernel() -> ModuleType | None:
    """The compiled kernel module (``aqfg._kernel``), or None when it is not built."""
    return _cpp

LAG_LOOKBACK = 5.0  # s of commands before a segment used to warm the thrust-lag filter
MAX_STEP = 0.05     # s, longest integration step (inputs are sub-divided beyond it)


# ---------------------------------------------------------------- attitude helpers
def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) body->ground from quaternions (n, 4) w, x, y, z."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def yaw_of(R: np.ndarray) -> np.ndarray:
    """ZYX yaw (rad) of rotation matrices (..., 3, 3)."""
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def interp_quat(t_q: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Normalised linear interpolation of quaternions at times ``t`` (held at the ends)."""
    q = np.asarray(q, dtype=float)
    if len(t_q) == 1:
        return np.repeat(q[:1], len(t), axis=0)
    j = np.clip(np.searchsorted(t_q, t, side="right") - 1, 0, len(t_q) - 2)
    dt = t_q[j + 1] - t_q[j]
    w = np.clip(np.where(dt > 0, (t - t_q[j]) / np.where(dt > 0, dt, 1.0), 0.0), 0.0, 1.0)
    q0, q1 = q[j], q[j + 1]
    q1 = np.where((np.sum(q0 * q1, axis=1) < 0)[:, None], -q1, q1)
    out = (1 - w)[:, None] * q0 + w[:, None] * q1
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def attitude_at(mission: Mission, t: np.ndarray) -> np.ndarray:
    """Raw IMU attitude (n, 3, 3) body->ground at times ``t`` (interpolated)."""
    return quat_to_rot(interp_quat(mission.imu.t, mission.imu.q, np.atleast_1d(t)))


def demand(u: np.ndarray) -> np.ndarray:
    """Thrust demand u|u| (Eq. 1 without k)."""
    return u * np.abs(u)


# ---------------------------------------------------------------- inputs -> kernel steps
def build_steps(mission: Mission, knots: np.ndarray, lookback: float = 0.0,
                max_step: float = MAX_STEP) -> tuple[Steps, np.ndarray]:
    """Kernel steps for the segments ``[knots[i], knots[i+1]]``.

    Step boundaries are the union of IMU and motor sample times and the knots, split so that
    no step is longer than ``max_step``. A step's attitude is the IMU attitude interpolated at
    its midpoint; its command is the last motor row at or before its start (commands hold).
    With ``lookback > 0`` each segment is preceded by warm-up steps covering
    ``[knots[i] - lookback, knots[i])`` for the thrust-lag filter.
    Returns the steps and ``offsets`` (K+1,): segment i is ``offsets[i]:offsets[i+1]``.
    """
    knots = np.asarray(knots, dtype=float)
    if knots.ndim != 1 or len(knots) < 2 or np.any(np.diff(knots) <= 0):
        raise ValueError("knots must be a strictly increasing 1-D array of at least 2 times")
    lo = knots[0] - lookback
    hi = knots[-1]
    src = np.concatenate([mission.imu.t, mission.motors.t, knots])
    grid = np.unique(src[(src >= lo) & (src <= hi)])
    if grid[0] > lo:
        grid = np.concatenate([[lo], grid])
    # sub-divide long intervals
    gaps = np.diff(grid)
    nsub = np.maximum(1, np.ceil(gaps / max_step - 1e-9).astype(int))
    if np.any(nsub > 1):
        pieces = [grid[:-1, None] + gaps[:, None] * (np.arange(nsub.max())[None, :] / nsub[:, None])]
        mask = np.arange(nsub.max())[None, :] < nsub[:, None]
        grid = np.concatenate([pieces[0][mask], grid[-1:]])
        grid.sort()
    t_a, t_b = grid[:-1], grid[1:]
    mid = 0.5 * (t_a + t_b)
    R_all = quat_to_rot(interp_quat(mission.imu.t, mission.imu.q, mid)).reshape(-1, 9)
    jm = np.searchsorted(mission.motors.t, t_a + 1e-12, side="right") - 1
    dem_all = np.where((jm >= 0)[:, None], demand(mission.motors.u[np.clip(jm, 0, None)]), 0.0)
    tm_all = t_a - mission.t0
    # index ranges per segment, and per lookback window
    ks = np.searchsorted(t_a, knots - 1e-9)
    parts: list[np.ndarray] = []
    warm: list[np.ndarray] = []
    offsets = [0]
    for i in range(len(knots) - 1):
        a, b = ks[i], ks[i + 1]
        if lookback > 0:
            w0 = np.searchsorted(t_a, knots[i] - lookback - 1e-9)
            parts.append(np.arange(w0, a)); warm.append(np.ones(a - w0, bool))
        parts.append(np.arange(a, b)); warm.append(np.zeros(b - a, bool))
        offsets.append(offsets[-1] + sum(len(x) for x in parts[-(2 if lookback > 0 else 1):]))
    idx = np.concatenate(parts) if parts else np.zeros(0, int)
    steps = Steps(h=(t_b - t_a)[idx], warm=np.concatenate(warm), R=R_all[idx],
                  dem=dem_all[idx], tm=tm_all[idx])
    return steps, np.asarray(offsets, dtype=np.int64)


# ---------------------------------------------------------------- the model
@dataclass(frozen=True)
class Model:
    """One definition of the vehicle physics, its parameters and its active effects."""
    vehicle: str
    geometry: Geometry
    effects: tuple[Effect, ...] = ()          # Effect objects, in order added
    t0: float = 0.0                           # mission start (s), origin of drift terms

    @classmethod
    def for_mission(cls, mission: Mission, effects=()) -> Model:
        geom = Geometry(dirs=np.asarray(mission.thruster_dir, float),
                        side=mission.thruster_side(), planar=mission.planar)
        return cls(mission.vehicle, geom, (), mission.t0).with_effects(*effects)

    def with_effects(self, *effects: str | Effect) -> Model:
        """A copy with more effects switched on (names of built-ins or Effect objects).

        Effects outside the built-in catalogue (e.g. :class:`UserEffect`) must be ground-force
        terms; their parameters are appended to the parameter table.
        """
        have = {e.name for e in self.effects}
        new = list(self.effects)
        for e in effects:
            e = resolve(e)
            if e.name in have:
                continue
            if self.vehicle not in e.vehicles:
                raise ValueError(f"effect {e.name!r} does not apply to a {self.vehicle}")
            if BUILTIN.get(e.name) is not e:
                if not isinstance(e, GroundForceTerm):
                    raise ValueError(f"effect {e.name!r}: an effect outside the built-in catalogue "
                                     "must be a ground-force term (e.g. a UserEffect)")
                clash = [n for n in e.params if n in INDEX]
                if clash:
                    raise ValueError(f"effect {e.name!r}: parameter names {clash} are built-in "
                                     "parameters; give the effect another name")
            new.append(e); have.add(e.name)
        return replace(self, effects=tuple(new))

    # ---- parameter layout
    @property
    def user_effects(self) -> tuple[Effect, ...]:
        """Active effects outside the built-in catalogue (their parameters follow the table)."""
        return tuple(e for e in self.effects if BUILTIN.get(e.name) is not e)

    @property
    def param_specs(self) -> tuple[ParamSpec, ...]:
        """Specs of the full vector: the built-in table, then user-effect parameters."""
        from aqfg.model.params import PARAMS
        extra = tuple(s for e in self.user_effects for s in e.specs())
        return PARAMS + extra

    @property
    def all_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.param_specs)

    @property
    def n_full(self) -> int:
        return len(self.param_specs)

    @property
    def active_names(self) -> tuple[str, ...]:
        """The base parameters and those of the active effects (what a fit may estimate)."""
        out = list(BASE_NAMES)
        for e in self.effects:
            out += list(e.params)
        return tuple(out)

    def index(self, name: str) -> int:
        names = self.all_names
        if name not in names:
            raise KeyError(f"unknown parameter {name!r}; this model has: {', '.join(names)}")
        return names.index(name)

    def spec(self, name: str) -> ParamSpec:
        return self.param_specs[self.index(name)]

    def nominal(self, values: dict[str, float] | None = None) -> np.ndarray:
        """Full parameter vector at nominal/null values, updated from ``values``."""
        p = np.array([s.null for s in self.param_specs])
        for k, v in (values or {}).items():
            p[self.index(k)] = float(v)
        return p

    def user_layout(self) -> tuple[tuple[Effect, int], ...]:
        """Each user (Python) effect with the index of its first parameter in ``p``, as
        the numpy propagation takes them."""
        i = N_PARAMS
        out = []
        for e in self.user_effects:
            out.append((e, i)); i += len(e.params)
        return tuple(out)

    def dyn_columns(self) -> np.ndarray:
        """Indices in the full vector of the columns of :meth:`propagate`'s ``J_p``."""
        return np.concatenate([np.arange(N_DYN), np.arange(N_PARAMS, self.n_full)]).astype(int)

    @property
    def lookback(self) -> float:
        return LAG_LOOKBACK if any(isinstance(e, DemandLagTerm) for e in self.effects) else 0.0

    @property
    def uses_cpp(self) -> bool:
        """Whether :meth:`propagate` runs the C++ kernel: built and every active effect in it."""
        return _cpp is not None and all(e.in_cpp for e in self.effects)

    # ---- dynamics
    def steps(self, mission: Mission, knots: np.ndarray, max_step: float = MAX_STEP):
        """:func:`build_steps` of ``mission`` for this model's lookback, those of an
        earlier call with the same mission object and knots where kept (:mod:`aqfg.memo`;
        the steps are read, never written)."""
        knots = np.asarray(knots, dtype=float)
        return remember(mission, ("steps", knots.tobytes(), self.lookback, max_step),
                        lambda: build_steps(mission, knots, self.lookback, max_step))

    def propagate(self, x0: np.ndarray, p: np.ndarray, steps: Steps):
        """State [pos, vel] (NED) after ``steps``; J_x0 (6x6), J_p (6 x len(dyn_columns()))."""
        if self.uses_cpp:
            g = self.geometry
            return _cpp.propagate(np.ascontiguousarray(x0, float),
                                  np.ascontiguousarray(p[:N_DYN], float),
                                  steps.h, steps.warm.astype(np.uint8), steps.R, steps.dem,
                                  steps.tm, g.dirs, g.side, g.planar)
        if self.user_effects:
            return batched.propagate(x0, p, steps, self.geometry, self.user_layout())
        return ref.propagate(x0, p, steps, self.geometry, self.user_layout())

    def rollout(self, x0: np.ndarray, p: np.ndarray, steps: Steps) -> np.ndarray | None:
        """States [pos, vel] (NED) after every step (n, 6) in one kernel call, no Jacobians
        (warm-up steps repeat the state); None where only the numpy reference can evaluate
        the model (user effects): use :func:`aqfg.model.retrace.rollout` then."""
        if not self.uses_cpp:
            return None
        g = self.geometry
        return _cpp.rollout(np.ascontiguousarray(x0, float),
                            np.ascontiguousarray(p[:N_DYN], float), steps.h,
                            steps.warm.astype(np.uint8), steps.R, steps.dem, steps.tm,
                            g.dirs, g.side, g.planar)

    def accel(self, v: np.ndarray, R_raw: np.ndarray, d: np.ndarray, dd_tau: np.ndarray,
              tm: float, p: np.ndarray):
        """Ground acceleration (m/s^2) at one kernel step, user effects included, and its
        Jacobians w.r.t. ``v`` (3x3) and the dynamics parameters (3 x len(dyn_columns())).

        ``R_raw``: IMU attitude (3x3); ``d``: mean thrust demand per thruster over the step,
        ``dd_tau`` its d/d``thrust_lag.tau``; ``tm``: s since the mission start; ``p``: full
        parameter vector (numpy reference, :func:`aqfg.model.reference.accel`).
        """
        a, A, Jp = ref.accel(v, R_raw, d, dd_tau, tm, p, self.geometry)
        user = self.user_layout()
        if user:
            a, A, Jp = ref.add_user(a, A, Jp, user, v, R_raw, d, tm, p, self.geometry)
        return a, A, Jp

    def rollout_segments(self, x0: np.ndarray, p: np.ndarray, steps: Steps,
                         offsets: np.ndarray) -> np.ndarray:
        """States (K + 1, 6) at the boundaries of K consecutive segments integrated from
        ``x0`` (segment i: steps ``offsets[i]:offsets[i+1]``), model only, no Jacobians."""
        user = self.user_layout()
        x0 = np.asarray(x0, float)
        if user and any(np.any(p[i0:i0 + len(e.params)]
                               != np.array([sp.null for sp in e.specs()], float))
                        for e, i0 in user):
            return batched.rollout(x0, p, steps, offsets, self.geometry, user)
        if user:     # every user effect at its null, where it vanishes: the built-in kernel
            return replace(self, effects=tuple(e for e in self.effects
                                               if e not in self.user_effects)
                           ).rollout_segments(x0, p, steps, offsets)
        offsets = np.asarray(offsets, np.int64)
        if self.lookback <= 0 and len(offsets) > 2:
            # no warm-up steps between segments: one kernel call over the whole span
            S = self.rollout(x0, p, steps)
            if S is not None:
                return np.vstack([x0[None, :], S[offsets[1:] - 1]])
        X = np.zeros((len(offsets), 6))
        X[0] = x0
        x = x0
        for i in range(len(offsets) - 1):
            x = self.propagate(x, p, steps.slice(int(offsets[i]), int(offsets[i + 1])))[0]
            X[i + 1] = x
        return X

    def propagate_many(self, X0: np.ndarray, p: np.ndarray, steps: Steps, offsets: np.ndarray):
        if self.uses_cpp:
            g = self.geometry
            return _cpp.propagate_many(np.ascontiguousarray(X0, float),
                                       np.ascontiguousarray(p[:N_DYN], float),
                                       steps.h, steps.warm.astype(np.uint8), steps.R, steps.dem,
                                       steps.tm, np.asarray(offsets, np.int64), g.dirs, g.side,
                                       g.planar)
        if self.user_effects:
            return batched.propagate_many(X0, p, steps, offsets, self.geometry,
                                          self.user_layout())
        return ref.propagate_many(X0, p, steps, offsets, self.geometry, self.user_layout())

    # ---- measurements (Jacobians w.r.t. the built-in parameter table, N_PARAMS columns)
    def h_gnss(self, pos, R_raw, t, p):
        """GNSS north, east at mission time ``t`` (s): :func:`aqfg.model.measurements.h_gnss`."""
        return meas.h_gnss(pos, R_raw, t - self.t0, p)

    def h_usbl(self, pos, R_raw, t, p, station):
        """USBL range, bearing at mission time ``t``: :func:`aqfg.model.measurements.h_usbl`."""
        return meas.h_usbl(pos, R_raw, t - self.t0, p, station)

    def h_depth(self, pos):
        return meas.h_depth(pos)
