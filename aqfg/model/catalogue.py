"""The built-in effects: each one's parameters (unit, null value, bounds, plausible range,
typical value), its wording (``description``, what an implausible estimate ``absorbs``) and its
term; :data:`BUILTIN` holds one object of each, by name, in catalogue order (the order of the
parameter table, :mod:`aqfg.model.params`)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from aqfg.model.spec import ParamSpec
from aqfg.model.terms import (
    BodyForceTerm,
    CurrentTerm,
    DemandLagTerm,
    Effect,
    FixDelayTerm,
    GroundForceTerm,
    HeadingTerm,
    InflowTerm,
    SensorOffsetTerm,
    ThrustGainTerm,
    UsblTerm,
)


class BuiltinEffect(Effect):
    """An effect of the catalogue: parameters declared by short name in ``parameters``."""
    parameters: tuple[ParamSpec, ...] = ()
    in_cpp = True

    def __init__(self) -> None:
        self._specs = tuple(replace(s, name=f"{self.name}.{s.name}") for s in self.parameters)

    def specs(self) -> tuple[ParamSpec, ...]:
        return self._specs

    def __reduce_ex__(self, protocol):
        # a catalogue effect is its catalogue object in every process and every copy: the
        # model tells built-in from user effects by identity (Model.user_effects)
        if BUILTIN.get(self.name) is self:
            return (resolve, (self.name,))
        return super().__reduce_ex__(protocol)


def _param(short: str, unit: str, null: float, lower: float, upper: float, group: str,
           scale: float, typical: float, doc: str,
           plausible: tuple[float, float] | None = None) -> ParamSpec:
    return ParamSpec(short, unit, null, lower, upper, group, scale, doc, typical, plausible)


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


def resolve(effect: str | Effect) -> Effect:
    """An effect object from its name (built-in) or the object itself."""
    if isinstance(effect, Effect):
        return effect
    if effect not in BUILTIN:
        raise KeyError(f"unknown effect {effect!r}; built-in effects: {', '.join(BUILTIN)}")
    return BUILTIN[effect]
