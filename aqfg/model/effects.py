"""The catalogue of candidate effects: small, physically meaningful model extensions.

Every effect is an :class:`Effect` that owns its parameters (:class:`ParamSpec`: unit,
null value, bounds, plausible range, group) and its term in the model, and says whether the
C++ kernel evaluates it (``in_cpp``). Each parameter sits at a *null value* where the effect
vanishes, so "is this effect missing?" is a test of those parameters at their null. An
estimate outside the parameter's *plausible range* (:meth:`Effect.plausible_range`: a real
vehicle's values, narrower than the bounds the fit may use) fits, but is the effect absorbing
something else, which it names (``absorbs``).

Where a term acts is the class it derives from (the shape of a candidate-term library):

==================== ===================================================================
class                the term, with its Jacobians (numpy)
==================== ===================================================================
HeadingTerm          adds to the heading offset ``theta(tm)`` (Eq. 6)
CurrentTerm          adds to the water current ``s(tm)``, ground frame (Eq. 3)
ThrustGainTerm       multiplies each thruster's gain (Eq. 1)
DemandLagTerm        the time constant of the first-order lag of the thrust demand
InflowTerm           takes from each propeller's thrust a loss of ``|u|`` and its advance speed
BodyForceTerm        adds a body-frame force / mass of the relative velocity (Eqs. 2, 4)
GroundForceTerm      adds a ground-frame acceleration ``a(v, R, d, tm, q)`` (Eq. 9)
SensorOffsetTerm     moves the position sensor away from the centre of mass (body frame)
FixDelayTerm         a stream's fix stamped ``t`` measures the sensor at ``t - delay`` (latency)
UsblTerm             distorts the USBL's range and bearing
==================== ===================================================================

The numpy model (:mod:`aqfg.model.reference`, :mod:`aqfg.model.measurements`,
:func:`aqfg.model.frames.heading`) evaluates every built-in effect through these methods;
the C++ kernel (``cpp_factors/kernel.hpp``) repeats the terms of those with ``in_cpp`` and
tests hold the two equal. The built-in parameters form the parameter table
(:mod:`aqfg.model.params`, dynamics effects first, in catalogue order).

A user's effect is a :class:`UserEffect` (a :class:`GroundForceTerm` written in Python);
its parameters are appended to the table by the model that uses it.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from aqfg.model.rotation import rot_z
from aqfg.model.spec import ParamSpec


class Effect(ABC):
    """A model extension: its name, its parameters and its term (see the subclasses; an
    effect that leaves out a method of its term cannot be created)."""
    name: str
    description: str = ""
    kind: str = "dynamics"                      # "dynamics" or "measurement"
    vehicles: tuple[str, ...] = ("asv", "auv")
    needs: tuple[str, ...] = ()                 # streams the effect needs to be observable
    in_cpp: bool = False                        # evaluated by the C++ kernel
    streams: tuple[str, ...] = ()               # measurement streams its term enters
    absorbs: str = ""                           # what an implausible estimate stands for

    @abstractmethod
    def specs(self) -> tuple[ParamSpec, ...]:
        """Its parameters, full names (``effect.param``)."""

    def plausible_range(self, spec: ParamSpec, missions=()) -> tuple[float, float]:
        """The values of parameter ``spec`` a real vehicle has (``spec.plausible``, default
        its bounds); ``missions`` may narrow it (e.g. a lever arm within the hull)."""
        return spec.plausible if spec.plausible is not None else (spec.lower, spec.upper)

    @property
    def params(self) -> tuple[str, ...]:
        """Full parameter names, e.g. ``("thrust_lag.tau",)``."""
        return tuple(s.name for s in self.specs())

    def applicable(self, mission) -> bool:
        """Whether ``mission`` can show the effect (vehicle type, streams it needs)."""
        if mission.vehicle not in self.vehicles:
            return False
        for s in self.needs:
            if s == "reverse" and not (mission.motors.u < -0.05).any():
                return False
            if s in ("usbl", "gnss") and (getattr(mission, s) is None or not len(getattr(mission, s).t)):
                return False
            if s == "fixes" and not len(mission.fix_times()):
                return False
        return True

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    def __reduce_ex__(self, protocol):
        # a catalogue effect is its catalogue object in every process and every copy: the
        # model tells built-in from user effects by identity (Model.user_effects)
        if BUILTIN.get(self.name) is self:
            return (resolve, (self.name,))
        return super().__reduce_ex__(protocol)


class BuiltinEffect(Effect):
    """An effect of the catalogue: parameters declared by short name in ``parameters``."""
    parameters: tuple[ParamSpec, ...] = ()
    in_cpp = True

    def __init__(self) -> None:
        self._specs = tuple(replace(s, name=f"{self.name}.{s.name}") for s in self.parameters)

    def specs(self) -> tuple[ParamSpec, ...]:
        return self._specs


def _param(short: str, unit: str, null: float, lower: float, upper: float, group: str,
           scale: float, typical: float, doc: str,
           plausible: tuple[float, float] | None = None) -> ParamSpec:
    return ParamSpec(short, unit, null, lower, upper, group, scale, doc, typical, plausible)


# ---------------------------------------------------------------- where terms act
class HeadingTerm(Effect):
    """Adds ``heading(tm, q)`` (rad) to the heading offset at ``tm`` s since the start."""

    @abstractmethod
    def heading(self, tm, q: np.ndarray):
        raise NotImplementedError

    @abstractmethod
    def heading_jacobian(self, tm: float, q: np.ndarray) -> np.ndarray:
        """d heading / d q, (nq,)."""
        raise NotImplementedError


class CurrentTerm(Effect):
    """Adds ``current(tm, q)`` (3,) m/s, ground frame, to the water current."""

    @abstractmethod
    def current(self, tm: float, q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @abstractmethod
    def current_jacobian(self, tm: float, q: np.ndarray) -> np.ndarray:
        """d current / d q, (3, nq)."""
        raise NotImplementedError


class ThrustGainTerm(Effect):
    """Multiplies the gain of thruster i by ``gain(side, d, q)[i]`` (side > 0: starboard;
    ``d`` the thrust demand u|u|)."""

    @abstractmethod
    def gain(self, side: np.ndarray, d: np.ndarray, q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @abstractmethod
    def gain_jacobian(self, side: np.ndarray, d: np.ndarray, q: np.ndarray) -> np.ndarray:
        """d gain / d q, (n_thr, nq)."""
        raise NotImplementedError


class DemandLagTerm(Effect):
    """The thrust demand passes a first-order filter with this time constant (s)."""

    @abstractmethod
    def time_constant(self, q: np.ndarray) -> float:
        raise NotImplementedError

    @abstractmethod
    def time_constant_jacobian(self, q: np.ndarray) -> np.ndarray:
        """d tau / d q, (nq,)."""
        raise NotImplementedError


class InflowTerm(Effect):
    """Takes ``loss(n, va, q)`` (m/s^2) from propeller i's thrust along its axis, with
    ``n = |u_i|`` (from the demand, :func:`abs_command`) and ``va`` its advance speed: the
    vehicle's velocity over ground, body frame, along the propeller's axis (m/s)."""

    @abstractmethod
    def loss(self, n: np.ndarray, va: np.ndarray, q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @abstractmethod
    def loss_jacobians(self, n: np.ndarray, va: np.ndarray, q: np.ndarray):
        """d loss / d n, d loss / d va (each like ``n``) and d loss / d q (len(n), nq)."""
        raise NotImplementedError


INFLOW_EPS4 = 1e-4   # smooths |u| = sqrt|d| at d = 0: (d^2 + eps^4)^(1/4), eps = 0.1


def abs_command(d):
    """``|u|`` from the demand ``d = u|u|``, smoothed at zero: ``(d^2 + 1e-4)^(1/4)``, 0.1 at
    ``u = 0`` (an idling propeller's drag), 1.5 % above ``|u|`` at 0.2 and 0.02 % at 0.5, so
    that its derivative through the thrust lag stays moderate. Returns ``|u|`` and
    ``d|u|/dd``."""
    r = np.asarray(d, dtype=float) ** 2 + INFLOW_EPS4
    n = r ** 0.25
    return n, 0.5 * np.asarray(d, dtype=float) * n / r


class BodyForceTerm(Effect):
    """Adds a body-frame force / mass (m/s^2) of the relative velocity ``vr`` (body, m/s)."""

    @abstractmethod
    def body_force(self, vr: np.ndarray, q: np.ndarray):
        """Returns the force (3,), d/d vr (3x3) and d/dq (3, nq)."""
        raise NotImplementedError


class GroundForceTerm(Effect):
    """Adds a ground-frame acceleration ``ground_accel(v, R, d, tm, q)`` (3,) m/s^2 given the
    ground velocity ``v`` (m/s, NED), the heading-corrected attitude ``R`` (body->ground),
    the mean thrust demand per thruster ``d``, the time since the mission start ``tm`` (s).

    Derivatives default to central differences (override :meth:`ground_jacobians`)."""

    @abstractmethod
    def ground_accel(self, v: np.ndarray, R: np.ndarray, d: np.ndarray, tm: float,
                     q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def ground_jacobians(self, v: np.ndarray, R: np.ndarray, d: np.ndarray, tm: float,
                         q: np.ndarray, eps: float = 1e-6):
        """d a/d v (3x3), d a/d q (3, nq) and d a/d theta (3,) (a turn of ``R`` about down)."""
        f = self.ground_accel
        Jv, Jq = self.central_differences(v, R, d, tm, q, eps)
        Jth = (f(v, rot_z(eps) @ R, d, tm, q) - f(v, rot_z(-eps) @ R, d, tm, q)) / (2 * eps)
        return Jv, Jq, Jth

    def central_differences(self, v: np.ndarray, R: np.ndarray, d: np.ndarray, tm: float,
                            q: np.ndarray, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """d a/d v (3x3) and d a/d q (3, nq) of :meth:`ground_accel` by central differences
        (steps ``eps``, relative to ``|q_i|`` above 1)."""
        f = self.ground_accel
        Jv = np.zeros((3, 3))
        for i in range(3):
            e = np.zeros(3); e[i] = eps
            Jv[:, i] = (f(v + e, R, d, tm, q) - f(v - e, R, d, tm, q)) / (2 * eps)
        q = np.asarray(q, dtype=float)
        Jq = np.zeros((3, len(q)))
        for i in range(len(q)):
            e = np.zeros(len(q)); e[i] = eps * max(1.0, abs(q[i]))
            Jq[:, i] = (f(v, R, d, tm, q + e) - f(v, R, d, tm, q - e)) / (2 * e[i])
        return Jv, Jq


class SensorOffsetTerm(Effect):
    """Moves the position sensor (GNSS antenna, USBL transponder) by ``offset(q)`` (3,) m,
    body frame, from the centre of mass."""
    kind = "measurement"
    streams = ("gnss", "usbl")

    @abstractmethod
    def offset(self, q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @abstractmethod
    def offset_jacobian(self, q: np.ndarray) -> np.ndarray:
        """d offset / d q, (3, nq)."""
        raise NotImplementedError


class FixDelayTerm(Effect):
    """A fix of ``stream`` stamped ``t`` measures the sensor at ``t - delay(q)`` (s): a time
    offset between that sensor's clock and the motion data's (IMU, motor commands). The
    measurement model takes it to first order along the state's velocity, ``p(t) - delay
    v(t)`` (its second-order error ``delay^2 a / 2`` is 0.05 m at 1 s and 0.1 m/s^2)."""
    kind = "measurement"
    stream: str = "gnss"

    @abstractmethod
    def delay(self, q: np.ndarray) -> float:
        raise NotImplementedError

    @abstractmethod
    def delay_jacobian(self, q: np.ndarray) -> np.ndarray:
        """d delay / d q, (nq,)."""
        raise NotImplementedError


class UsblTerm(Effect):
    """Distorts the USBL's ``z = (range m, bearing rad)`` into what it reports."""
    kind = "measurement"
    streams = ("usbl",)

    @abstractmethod
    def distort(self, z: np.ndarray, q: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @abstractmethod
    def distort_jacobian(self, z: np.ndarray, q: np.ndarray):
        """d z' / d z (2x2) and d z' / d q (2, nq)."""
        raise NotImplementedError

    @abstractmethod
    def undistort(self, rng, bearing, q: np.ndarray):
        """The inverse of :meth:`distort` on arrays of ranges and bearings."""
        raise NotImplementedError


# ---------------------------------------------------------------- the built-in effects
class ThrustAsymmetry(BuiltinEffect, ThrustGainTerm):
    name = "thrust_asymmetry"
    description = "propellers of unequal strength: starboard thrust = ratio x port thrust"
    absorbs = "a turning current or heading drift, or swapped/mis-scaled motor commands"
    parameters = (_param("ratio", "-", 1.0, 0.2, 5.0, "fixed", 0.2, 0.8,
                         "starboard thrust constant / port thrust constant", (0.5, 2.0)),)

    def gain(self, side, d, q):
        return np.where(side > 0, q[0], 1.0)

    def gain_jacobian(self, side, d, q):
        return np.where(side > 0, 1.0, 0.0)[:, None]


class ReverseThrust(BuiltinEffect, ThrustGainTerm):
    name = "reverse_thrust"
    description = "a propeller pushes with another constant when turning backwards"
    needs = ("reverse",)
    absorbs = ("a thrust curve/mapping error (thrust not proportional to u|u|, a dead band "
               "or an offset of the commands)")
    parameters = (_param("ratio", "-", 1.0, 0.05, 3.0, "fixed", 0.3, 0.6,
                         "thrust constant for negative commands / for positive commands",
                         (0.3, 1.5)),)

    def gain(self, side, d, q):
        return np.where(d < 0, q[0], 1.0)

    def gain_jacobian(self, side, d, q):
        return np.where(d < 0, 1.0, 0.0)[:, None]


class ThrustLag(BuiltinEffect, DemandLagTerm):
    name = "thrust_lag"
    description = "thrust follows the command with a first-order lag (motor and propeller inertia)"
    absorbs = "a time offset between the motor commands and the motion data"
    parameters = (_param("tau", "s", 0.0, 0.0, 1.5, "fixed", 0.3, 0.4,
                         "time constant of the first-order thrust response", (0.0, 1.2)),)

    def time_constant(self, q):
        return float(q[0])

    def time_constant_jacobian(self, q):
        return np.ones(1)


class LinearDrag(BuiltinEffect, BodyForceTerm):
    name = "linear_drag"
    description = "drag linear in relative velocity (laminar skin friction, dominant at low speed)"
    absorbs = "a thrust curve error at low commands"
    parameters = (
        _param("c_x", "1/s", 0.0, 0.0, np.inf, "fixed", 0.3, 0.3,
               "surge drag linear in relative velocity, / mass", (0.0, 3.0)),
        _param("c_yz", "1/s", 0.0, 0.0, np.inf, "fixed", 0.3, 0.2,
               "sway/heave drag linear in relative velocity, / mass", (0.0, 5.0)))

    def body_force(self, vr, q):
        c = np.array([q[0], q[1], q[1]])
        Fq = np.array([[-vr[0], 0.0], [0.0, -vr[1]], [0.0, -vr[2]]])
        return -c * vr, np.diag(-c), Fq


class GroundAdvance(BuiltinEffect, InflowTerm):
    name = "ground_advance"
    description = ("propeller thrust falls with the speed over ground along its axis "
                   "(a thrust curve linear in an advance speed taken over ground)")
    absorbs = "linear drag, or a current along the track"
    parameters = (_param("c", "1/s", 0.0, 0.0, np.inf, "fixed", 0.1, 0.1,
                         "thrust lost / mass per unit |u| and per m/s of advance speed over "
                         "ground", (0.0, 2.0)),)

    def loss(self, n, va, q):
        return q[0] * n * va

    def loss_jacobians(self, n, va, q):
        return q[0] * va, q[0] * n, (n * va)[:, None]


class HeadingDrift(BuiltinEffect, HeadingTerm):
    name = "heading_drift"
    description = "the IMU's unreferenced yaw drifts at a constant rate"
    absorbs = "a current that turns or changes over the mission"
    parameters = (_param("rate", "rad/s", 0.0, -0.05, 0.05, "variable", 1e-3, 5e-4,
                         "theta_e changes at this constant rate from the mission start",
                         (-2e-3, 2e-3)),)

    def heading(self, tm, q):
        return q[0] * tm

    def heading_jacobian(self, tm, q):
        return np.array([float(tm)])


class CurrentDrift(BuiltinEffect, CurrentTerm):
    name = "current_drift"
    description = "the water current changes linearly over the mission"
    absorbs = "a heading drift, or a current that changes other than linearly"
    parameters = (
        _param("ds_x", "m/s^2", 0.0, -0.01, 0.01, "variable", 2e-4, 2e-4,
               "rate of change of the north current", (-2e-3, 2e-3)),
        _param("ds_y", "m/s^2", 0.0, -0.01, 0.01, "variable", 2e-4, -1.5e-4,
               "rate of change of the east current", (-2e-3, 2e-3)))

    def current(self, tm, q):
        return np.array([q[0] * tm, q[1] * tm, 0.0])

    def current_jacobian(self, tm, q):
        return np.array([[tm, 0.0], [0.0, tm], [0.0, 0.0]])


class WindDrag(BuiltinEffect, GroundForceTerm):
    name = "wind_drag"
    description = "wind pushes the hull above water with a constant ground-frame force"
    vehicles = ("asv",)
    absorbs = "a thrust asymmetry or a current"
    parameters = (
        _param("a_n", "m/s^2", 0.0, -2.0, 2.0, "variable", 0.05, 0.04,
               "wind force / mass on the hull above water, north (ground frame)", (-0.5, 0.5)),
        _param("a_e", "m/s^2", 0.0, -2.0, 2.0, "variable", 0.05, 0.03,
               "wind force / mass on the hull above water, east (ground frame)", (-0.5, 0.5)))

    def ground_accel(self, v, R, d, tm, q):
        return np.array([q[0], q[1], 0.0])

    def ground_jacobians(self, v, R, d, tm, q, eps=1e-6):
        return np.zeros((3, 3)), np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]), np.zeros(3)


class UsblRangeScale(BuiltinEffect, UsblTerm):
    name = "usbl_range_scale"
    description = "USBL ranges are scaled by a sound-speed error"
    needs = ("usbl",)
    absorbs = "a wrong station depth or position, or a range offset"
    parameters = (_param("scale", "-", 1.0, 0.8, 1.2, "sensor", 0.02, 1.02,
                         "measured range / true range (sound-speed error)", (0.95, 1.05)),)

    def distort(self, z, q):
        return np.array([q[0] * z[0], z[1]])

    def distort_jacobian(self, z, q):
        return np.array([[q[0], 0.0], [0.0, 1.0]]), np.array([[z[0]], [0.0]])

    def undistort(self, rng, bearing, q):
        return np.asarray(rng, dtype=float) / q[0], bearing


class UsblBearingBias(BuiltinEffect, UsblTerm):
    name = "usbl_bearing_bias"
    description = "USBL bearings carry a constant bias (array mounting misalignment)"
    needs = ("usbl",)
    absorbs = "a wrong station position or a heading error of the station's reference"
    parameters = (_param("bias", "rad", 0.0, -0.5, 0.5, "sensor", 0.02, 0.05,
                         "measured bearing - true bearing", (-0.2, 0.2)),)

    def distort(self, z, q):
        return np.array([z[0], z[1] + q[0]])

    def distort_jacobian(self, z, q):
        return np.eye(2), np.array([[0.0], [1.0]])

    def undistort(self, rng, bearing, q):
        return rng, np.asarray(bearing, dtype=float) - q[0]


class LeverArm(BuiltinEffect, SensorOffsetTerm):
    name = "lever_arm"
    description = "the position sensor sits away from the centre of mass"
    needs = ("fixes",)
    absorbs = ("a time offset between the position fixes and the motion data (along the "
               "track), or a heading error (across it)")
    parameters = tuple(
        _param(ax, "m", 0.0, -3.0, 3.0, "sensor", 0.3, t,
               f"position-sensor offset from the centre of mass, body {ax}", (-a, a))
        for ax, t, a in (("x", -0.3, 1.5), ("y", 0.0, 1.0), ("z", 0.0, 1.5)))

    def plausible_range(self, spec, missions=()):
        """Within the hull where the missions declare it (``[hull]`` length along x, beam
        along y; the largest of the missions'), else the catalogue's range."""
        hulls = [m.hull for m in missions if getattr(m, "hull", None) is not None]
        ax = spec.name.rsplit(".", 1)[-1]
        if not hulls or ax == "z":
            return super().plausible_range(spec, missions)
        half = 0.5 * max(h[0] if ax == "x" else h[1] for h in hulls)
        return (-half, half)

    def offset(self, q):
        return np.asarray(q[:3], dtype=float)

    def offset_jacobian(self, q):
        return np.eye(3)


class _StreamDelay(BuiltinEffect, FixDelayTerm):
    def delay(self, q):
        return float(q[0])

    def delay_jacobian(self, q):
        return np.ones(1)


class GnssDelay(_StreamDelay):
    name = "gnss_delay"
    description = ("GNSS time offset: a fix stamped t is the antenna's position at t - tau "
                   "(tau > 0: stamped late against the IMU/motor clock)")
    stream = "gnss"
    streams = ("gnss",)
    needs = ("gnss",)
    absorbs = "a lever arm along the track, a thrust lag, or a thrust/drag scale error"
    parameters = (_param("tau", "s", 0.0, -3.0, 3.0, "sensor", 0.2, 0.8,
                         "GNSS time offset (latency) against the IMU/motor clock", (-2.0, 2.0)),)


class UsblDelay(_StreamDelay):
    name = "usbl_delay"
    description = ("USBL time offset: a fix stamped t is the transponder's position at t - tau "
                   "(tau > 0: stamped late against the IMU/motor clock)")
    stream = "usbl"
    streams = ("usbl",)
    needs = ("usbl",)
    absorbs = "a lever arm along the track, a thrust lag, or a thrust/drag scale error"
    parameters = (_param("tau", "s", 0.0, -5.0, 5.0, "sensor", 0.3, 1.0,
                         "USBL time offset (acoustic travel and processing latency) against "
                         "the IMU/motor clock", (-2.0, 4.0)),)


BUILTIN: dict[str, Effect] = {e.name: e for e in (
    ThrustAsymmetry(), ReverseThrust(), ThrustLag(), LinearDrag(), HeadingDrift(),
    CurrentDrift(), WindDrag(), GroundAdvance(), UsblRangeScale(), UsblBearingBias(), LeverArm(),
    GnssDelay(), UsblDelay(),
)}


# ---------------------------------------------------------------- a user's effect
@dataclass(frozen=True)
class UserEffect(GroundForceTerm):
    """A user-defined dynamics effect, evaluated in Python.

    ``accel(v, R, d, tm, q) -> (3,)`` returns the extra ground-frame acceleration (m/s^2)
    given the ground velocity ``v`` (m/s, NED), the heading-corrected attitude ``R``
    (body->ground 3x3), the mean thrust demand per thruster ``d`` (u|u|), the time since the
    mission start ``tm`` (s) and this effect's parameters ``q``. It must return zeros when
    ``q`` equals ``null``. Derivatives are taken by finite differences unless ``jac`` is
    given: ``jac(v, R, d, tm, q) -> (d a/d v (3x3), d a/d q (3 x len(q)))``.
    ``vectorized=True``: ``accel`` (and ``jac``) take ``n`` samples at once, ``v (n, 3)``,
    ``R (n, 3, 3)``, ``d (n, N)``, ``tm (n,)``, and return ``(n, 3)`` (and ``(n, 3, 3)``,
    ``(n, 3, len(q))``); the kernel then evaluates every dynamics factor's sample at once
    (:mod:`aqfg.model.batched`), which is what makes a user effect fast.

    Example::

        drag3 = UserEffect("cubic_drag", ("c3",), null=(0.0,), lower=(0.0,), upper=(10.0,),
                           units=("s/m^2",), scale=(0.1,),
                           accel=lambda v, R, d, tm, q: -q[0] * R @ ((R.T @ v) ** 3))
        model = model.with_effects(drag3)
    """
    name: str
    param_names: tuple[str, ...]
    accel: Callable[..., np.ndarray]
    null: tuple[float, ...]
    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()
    units: tuple[str, ...] = ()
    scale: tuple[float, ...] = ()
    description: str = "user-defined effect"
    jac: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None
    vectorized: bool = False
    kind: str = field(default="dynamics", init=False)

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(f"{self.name}.{n}" for n in self.param_names)

    def specs(self) -> tuple[ParamSpec, ...]:
        n = len(self.param_names)
        lo = self.lower or (-np.inf,) * n
        hi = self.upper or (np.inf,) * n
        un = self.units or ("-",) * n
        sc = self.scale or tuple(max(abs(x), 1.0) * 0.1 for x in self.null)
        return tuple(ParamSpec(f"{self.name}.{pn}", un[i], float(self.null[i]), float(lo[i]),
                               float(hi[i]), "fixed", float(sc[i]), self.description)
                     for i, pn in enumerate(self.param_names))

    def applicable(self, mission) -> bool:
        return True

    def sample_accel(self, v, R, d, tm, q) -> np.ndarray:
        """``accel`` at one sample (3,), whether or not it is ``vectorized``."""
        if self.vectorized:
            return np.asarray(self.accel(np.asarray(v, float)[None], np.asarray(R, float)[None],
                                         np.asarray(d, float)[None], np.array([tm], float),
                                         q), dtype=float)[0]
        return np.asarray(self.accel(v, R, d, tm, q), dtype=float)

    def ground_accel(self, v, R, d, tm, q):
        return self.sample_accel(v, R, d, tm, q)

    def ground_jacobians(self, v, R, d, tm, q, eps: float = 1e-6):
        Jv, Jq = self.jacobians(v, R, d, tm, q)
        Jth = (self.sample_accel(v, rot_z(eps) @ R, d, tm, q)
               - self.sample_accel(v, rot_z(-eps) @ R, d, tm, q)) / (2 * eps)
        return Jv, Jq, Jth

    def jacobians(self, v, R, d, tm, q, eps: float = 1e-6):
        """d a/d v and d a/d q at one sample, analytic if given, else central differences."""
        if self.jac is not None:
            if self.vectorized:
                Jv, Jq = self.jac(np.asarray(v, float)[None], np.asarray(R, float)[None],
                                  np.asarray(d, float)[None], np.array([tm], float), q)
                return np.asarray(Jv)[0], np.asarray(Jq)[0]
            return self.jac(v, R, d, tm, q)
        return self.central_differences(v, R, d, tm, q, eps)   # ground_accel = sample_accel


def resolve(effect: str | Effect) -> Effect:
    """An effect object from its name (built-in) or the object itself."""
    if isinstance(effect, Effect):
        return effect
    if effect not in BUILTIN:
        raise KeyError(f"unknown effect {effect!r}; built-in effects: {', '.join(BUILTIN)}")
    return BUILTIN[effect]
