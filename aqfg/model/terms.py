"""Where an effect's term acts: :class:`Effect`, the base of every effect, and one abstract
class per place in the model a term enters (the shape of a candidate-term library).

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
"""
from __future__ import annotations

from abc import ABC, abstractmethod

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

    def implausible(self, values: dict[str, float], missions=()) -> list[str]:
        """The estimates in ``values`` (``{full name: value}``) outside their
        :meth:`plausible_range`, in words, e.g. ``"ratio = 1.63 outside [0.3, 1.5]"``;
        empty when all are plausible (names not in ``values`` are not judged)."""
        out = []
        for s in self.specs():
            if s.name not in values:
                continue
            v = float(values[s.name])
            lo, hi = self.plausible_range(s, missions)
            if np.isfinite(v) and not lo <= v <= hi:
                out.append(f"{s.name.split('.')[-1]} = {v:.3g} {s.unit if s.unit != '-' else ''}"
                           .rstrip() + f" outside [{lo:.3g}, {hi:.3g}]")
        return out

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
