"""The vehicle model, defined once: parameters, effects, the numpy reference of the C++
kernel, and ``Model``, which every estimator, the simulator and the diagnosis ask."""
from aqfg.model.effects import BUILTIN, Effect, UserEffect, resolve
from aqfg.model.vehicle import Model

__all__ = ["BUILTIN", "Effect", "Model", "UserEffect", "resolve"]
