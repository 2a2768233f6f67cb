"""The parameter vector: names, units, nominal values, bounds and groups, in one table.

Every estimator, the simulator and the C++ kernel index parameters through this layout.
The first six are the paper's ``P`` (Eq. 12, Table I); the others are declared by the model
extensions ("effects", see :mod:`aqfg.model.effects`) and sit at their *null value* (the value
at which the effect vanishes) unless the effect is switched on. The C++ kernel's indices are
generated from this table (``cpp_factors/gen_layout.py``).

Groups: ``fixed`` = one value per vehicle (shared by its missions), ``variable`` = one
value per mission, ``sensor`` = measurement-model parameters (per mission).
"""
from __future__ import annotations

import math

import numpy as np

from aqfg.model.effects import BUILTIN, Effect
from aqfg.model.spec import ParamSpec as ParamSpec  # re-exported: the table's row type

INF = np.inf
# The paper's P (Eq. 12, Table I); the kernel's parameter vector starts with them.
BASE_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("theta_e", "rad", 0.0, -np.pi * 190 / 180, np.pi * 190 / 180, "variable", 0.5,
              "heading offset: true yaw = reported yaw + theta_e (Eq. 6)"),
    ParamSpec("s_x", "m/s", 0.0, -2.0, 2.0, "variable", 0.2, "water current, north (Eq. 3)"),
    ParamSpec("s_y", "m/s", 0.0, -2.0, 2.0, "variable", 0.2, "water current, east (Eq. 3)"),
    ParamSpec("k", "m/s^2", 8.0, 1e-6, INF, "fixed", 5.0,
              "thrust constant / mass, per unit u*|u| (Eq. 1)"),
    ParamSpec("k_x", "1/m", 2.0, 1e-6, INF, "fixed", 1.0, "surge drag constant / mass (Eq. 2)"),
    ParamSpec("k_yz", "1/m", 0.3, 1e-6, INF, "fixed", 0.3,
              "sway and heave drag constant / mass (Eq. 2)"),
)

# The built-in effects in table order: dynamics first (the C++ dynamics kernel reads
# params[0:N_DYN]), then measurement effects.
DYNAMICS_EFFECTS: tuple[Effect, ...] = tuple(e for e in BUILTIN.values() if e.kind == "dynamics")
MEASUREMENT_EFFECTS: tuple[Effect, ...] = tuple(e for e in BUILTIN.values()
                                                if e.kind == "measurement")
PARAMS: tuple[ParamSpec, ...] = BASE_PARAMS + tuple(
    s for e in DYNAMICS_EFFECTS + MEASUREMENT_EFFECTS for s in e.specs())

NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
INDEX: dict[str, int] = {n: i for i, n in enumerate(NAMES)}
SPEC: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
N_PARAMS = len(PARAMS)
N_DYN = len(BASE_PARAMS) + sum(len(e.params) for e in DYNAMICS_EFFECTS)
# where each built-in effect's parameters sit in the table
SLICE: dict[str, slice] = {}
for _e in DYNAMICS_EFFECTS + MEASUREMENT_EFFECTS:
    SLICE[_e.name] = slice(INDEX[_e.params[0]], INDEX[_e.params[0]] + len(_e.params))
del _e
MEAS_INDEX = np.arange(N_DYN, N_PARAMS)  # the measurement parameters (the C++ EKF's ``pm``)
BASE_NAMES: tuple[str, ...] = tuple(p.name for p in BASE_PARAMS)
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


def difference(name: str, a: float, b: float) -> float:
    """``a - b`` of parameter ``name``, wrapped to (-pi, pi] for the heading offset (the
    one circular parameter)."""
    return math.remainder(a - b, 2 * math.pi) if name == "theta_e" else a - b


def as_dict(p: np.ndarray, names: tuple[str, ...] | list[str] = NAMES) -> dict[str, float]:
    return {n: float(p[INDEX[n]]) for n in names}
