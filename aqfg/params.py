"""The parameter vector: names, units, nominal values, bounds and groups, in one table.

Every estimator, the simulator and the C++ kernel index parameters through this layout.
The first six are the paper's ``P`` (Eq. 12, Table I); the others belong to the model
extensions ("effects", see :mod:`aqfg.effects`) and sit at their *null value* (the value at
which the effect vanishes) unless the effect is switched on.

Groups: ``fixed`` = one value per vehicle (shared by its missions), ``variable`` = one
value per mission, ``sensor`` = measurement-model parameters (per mission).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ParamSpec:
    name: str          # name in outputs, e.g. "k" or "thrust_lag.tau"
    unit: str
    null: float        # nominal (base params) or null value (effect params)
    lower: float       # physical bounds (defaults; users may narrow them)
    upper: float
    group: str         # "fixed" | "variable" | "sensor"
    scale: float       # typical magnitude, for priors and finite differences
    doc: str


INF = np.inf
# Order is the kernel's order: cpp_factors/kernel.hpp mirrors it (enum ParamIndex).
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("theta_e", "rad", 0.0, -np.pi * 190 / 180, np.pi * 190 / 180, "variable", 0.5,
              "heading offset: true yaw = reported yaw + theta_e (Eq. 6)"),
    ParamSpec("s_x", "m/s", 0.0, -2.0, 2.0, "variable", 0.2, "water current, north (Eq. 3)"),
    ParamSpec("s_y", "m/s", 0.0, -2.0, 2.0, "variable", 0.2, "water current, east (Eq. 3)"),
    ParamSpec("k", "m/s^2", 8.0, 1e-6, INF, "fixed", 5.0,
              "thrust constant / mass, per unit u*|u| (Eq. 1)"),
    ParamSpec("k_x", "1/m", 2.0, 1e-6, INF, "fixed", 1.0, "surge drag constant / mass (Eq. 2)"),
    ParamSpec("k_yz", "1/m", 0.3, 1e-6, INF, "fixed", 0.3,
              "sway and heave drag constant / mass (Eq. 2)"),
    # --- dynamics effects ---
    ParamSpec("thrust_asymmetry.ratio", "-", 1.0, 0.2, 5.0, "fixed", 0.2,
              "starboard thrust constant / port thrust constant"),
    ParamSpec("reverse_thrust.ratio", "-", 1.0, 0.05, 3.0, "fixed", 0.3,
              "thrust constant for negative commands / for positive commands"),
    ParamSpec("thrust_lag.tau", "s", 0.0, 0.0, 1.5, "fixed", 0.3,
              "time constant of the first-order thrust response"),
    ParamSpec("linear_drag.c_x", "1/s", 0.0, 0.0, INF, "fixed", 0.3,
              "surge drag linear in relative velocity, / mass"),
    ParamSpec("linear_drag.c_yz", "1/s", 0.0, 0.0, INF, "fixed", 0.3,
              "sway/heave drag linear in relative velocity, / mass"),
    ParamSpec("heading_drift.rate", "rad/s", 0.0, -0.05, 0.05, "variable", 1e-3,
              "theta_e changes at this constant rate from the mission start"),
    ParamSpec("current_drift.ds_x", "m/s^2", 0.0, -0.01, 0.01, "variable", 2e-4,
              "rate of change of the north current"),
    ParamSpec("current_drift.ds_y", "m/s^2", 0.0, -0.01, 0.01, "variable", 2e-4,
              "rate of change of the east current"),
    ParamSpec("wind_drag.a_n", "m/s^2", 0.0, -2.0, 2.0, "variable", 0.05,
              "wind force / mass on the hull above water, north (ground frame)"),
    ParamSpec("wind_drag.a_e", "m/s^2", 0.0, -2.0, 2.0, "variable", 0.05,
              "wind force / mass on the hull above water, east (ground frame)"),
    # --- measurement effects ---
    ParamSpec("usbl_range_scale.scale", "-", 1.0, 0.8, 1.2, "sensor", 0.02,
              "measured range / true range (sound-speed error)"),
    ParamSpec("usbl_bearing_bias.bias", "rad", 0.0, -0.5, 0.5, "sensor", 0.02,
              "measured bearing - true bearing"),
    ParamSpec("lever_arm.x", "m", 0.0, -3.0, 3.0, "sensor", 0.3,
              "position-sensor offset from the centre of mass, body x"),
    ParamSpec("lever_arm.y", "m", 0.0, -3.0, 3.0, "sensor", 0.3,
              "position-sensor offset from the centre of mass, body y"),
    ParamSpec("lever_arm.z", "m", 0.0, -3.0, 3.0, "sensor", 0.3,
              "position-sensor offset from the centre of mass, body z"),
)

NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
INDEX: dict[str, int] = {n: i for i, n in enumerate(NAMES)}
SPEC: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
N_PARAMS = len(PARAMS)
N_DYN = INDEX["wind_drag.a_e"] + 1       # the dynamics kernel reads params[0:N_DYN]
BASE_NAMES: tuple[str, ...] = NAMES[:6]
FIXED_BASE = ("k", "k_x", "k_yz")
VARIABLE_BASE = ("theta_e", "s_x", "s_y")

# The paper's "old" parameters (Table II, ASV.Old).
OLD_PARAMS = {"k": 8.0, "k_x": 2.0, "k_yz": 0.3}


def null_vector() -> np.ndarray:
    """Full parameter vector at nominal/null values."""
    return np.array([p.null for p in PARAMS], dtype=float)


def vector(values: dict[str, float] | None = None, base: np.ndarray | None = None) -> np.ndarray:
    """Full parameter vector from a ``{name: value}`` dict (others at ``base`` or null)."""
    p = null_vector() if base is None else np.array(base, dtype=float).copy()
    for name, v in (values or {}).items():
        if name not in INDEX:
            raise KeyError(f"unknown parameter {name!r}; known: {', '.join(NAMES)}")
        p[INDEX[name]] = float(v)
    return p


def as_dict(p: np.ndarray, names: tuple[str, ...] | list[str] = NAMES) -> dict[str, float]:
    return {n: float(p[INDEX[n]]) for n in names}
