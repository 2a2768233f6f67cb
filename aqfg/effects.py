"""The catalogue of candidate effects: small, physically meaningful model extensions.

Each effect owns a few parameters (declared in :mod:`aqfg.params` for the built-in ones)
that sit at a *null value* where the effect vanishes, so "is this effect missing?" is a
test of those parameters at their null. Built-in effects are evaluated by the C++ kernel
(and its numpy mirror :mod:`aqfg.kernel_ref`); a user's effect is a subclass of
:class:`Effect` written in Python (see :class:`UserEffect`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .params import SPEC, ParamSpec


@dataclass(frozen=True)
class Effect:
    """A model extension: its name, parameters and what it means physically."""
    name: str
    params: tuple[str, ...]             # full names, e.g. ("thrust_lag.tau",)
    kind: str                           # "dynamics" or "measurement"
    description: str
    vehicles: tuple[str, ...] = ("asv", "auv")
    needs: tuple[str, ...] = ()         # streams the effect needs to be observable

    def specs(self) -> tuple[ParamSpec, ...]:
        return tuple(SPEC[n] for n in self.params)

    def applicable(self, mission) -> bool:
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


BUILTIN: dict[str, Effect] = {e.name: e for e in (
    Effect("thrust_asymmetry", ("thrust_asymmetry.ratio",), "dynamics",
           "propellers of unequal strength: starboard thrust = ratio x port thrust"),
    Effect("reverse_thrust", ("reverse_thrust.ratio",), "dynamics",
           "a propeller pushes with another constant when turning backwards",
           needs=("reverse",)),
    Effect("thrust_lag", ("thrust_lag.tau",), "dynamics",
           "thrust follows the command with a first-order lag (motor and propeller inertia)"),
    Effect("linear_drag", ("linear_drag.c_x", "linear_drag.c_yz"), "dynamics",
           "drag linear in relative velocity (laminar skin friction, dominant at low speed)"),
    Effect("heading_drift", ("heading_drift.rate",), "dynamics",
           "the IMU's unreferenced yaw drifts at a constant rate"),
    Effect("current_drift", ("current_drift.ds_x", "current_drift.ds_y"), "dynamics",
           "the water current changes linearly over the mission"),
    Effect("wind_drag", ("wind_drag.a_n", "wind_drag.a_e"), "dynamics",
           "wind pushes the hull above water with a constant ground-frame force",
           vehicles=("asv",)),
    Effect("usbl_range_scale", ("usbl_range_scale.scale",), "measurement",
           "USBL ranges are scaled by a sound-speed error", needs=("usbl",)),
    Effect("usbl_bearing_bias", ("usbl_bearing_bias.bias",), "measurement",
           "USBL bearings carry a constant bias (array mounting misalignment)",
           needs=("usbl",)),
    Effect("lever_arm", ("lever_arm.x", "lever_arm.y", "lever_arm.z"), "measurement",
           "the position sensor sits away from the centre of mass", needs=("fixes",)),
)}


@dataclass(frozen=True)
class UserEffect:
    """A user-defined dynamics effect, evaluated in Python.

    ``accel(v, R, d, tm, q) -> (3,)`` returns the extra ground-frame acceleration (m/s^2)
    given the ground velocity ``v`` (m/s, NED), the heading-corrected attitude ``R``
    (body->ground 3x3), the mean thrust demand per thruster ``d`` (u|u|), the time since the
    mission start ``tm`` (s) and this effect's parameters ``q``. It must return zeros when
    ``q`` equals ``null``. Derivatives are taken by finite differences unless ``jac`` is
    given: ``jac(v, R, d, tm, q) -> (d a/d v (3x3), d a/d q (3 x len(q)))``.

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

    def jacobians(self, v, R, d, tm, q, eps: float = 1e-6):
        """d a/d v and d a/d q, analytic if given, else central differences."""
        if self.jac is not None:
            return self.jac(v, R, d, tm, q)
        Jv = np.zeros((3, 3))
        for i in range(3):
            e = np.zeros(3); e[i] = eps
            Jv[:, i] = (self.accel(v + e, R, d, tm, q) - self.accel(v - e, R, d, tm, q)) / (2 * eps)
        q = np.asarray(q, dtype=float)
        Jq = np.zeros((3, len(q)))
        for i in range(len(q)):
            e = np.zeros(len(q)); e[i] = eps * max(1.0, abs(q[i]))
            Jq[:, i] = (self.accel(v, R, d, tm, q + e) - self.accel(v, R, d, tm, q - e)) / (2 * e[i])
        return Jv, Jq


def resolve(effect: "str | Effect | UserEffect") -> "Effect | UserEffect":
    """An effect object from its name (built-in) or the object itself."""
    if isinstance(effect, (Effect, UserEffect)):
        return effect
    if effect not in BUILTIN:
        raise KeyError(f"unknown effect {effect!r}; built-in effects: {', '.join(BUILTIN)}")
    return BUILTIN[effect]
