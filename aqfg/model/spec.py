"""The description of one model parameter (its row in the parameter table)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ParamSpec:
    """A parameter: name, unit, value where it does nothing, physical bounds and group.

    Groups: ``fixed`` = one value per vehicle (shared by its missions), ``variable`` = one
    value per mission, ``sensor`` = measurement-model parameters (per mission).
    """
    name: str          # name in outputs, e.g. "k" or "thrust_lag.tau"
    unit: str
    null: float        # nominal (base params) or null value (effect params)
    lower: float       # physical bounds (defaults; users may narrow them)
    upper: float
    group: str         # "fixed" | "variable" | "sensor"
    scale: float       # typical magnitude, for priors and finite differences
    doc: str
    typical: float | None = None   # a plausible non-null value (simulated hidden effects)
    # the range a real vehicle's value lies in (default: the bounds); an estimate outside
    # it fits, but is the effect absorbing something else (Effect.absorbs)
    plausible: tuple[float, float] | None = None
