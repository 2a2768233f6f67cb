"""The catalogue of candidate effects: small, physically meaningful model extensions.

Every effect is an :class:`Effect` that owns its parameters (:class:`ParamSpec`: unit,
null value, bounds, plausible range, group) and its term in the model, and says whether the
C++ kernel evaluates it (``in_cpp``). Each parameter sits at a *null value* where the effect
vanishes, so "is this effect missing?" is a test of those parameters at their null. An
estimate outside the parameter's *plausible range* (:meth:`Effect.plausible_range`: a real
vehicle's values, narrower than the bounds the fit may use) fits, but is the effect absorbing
something else, which it names (``absorbs``).

This module is where callers import the catalogue from; its parts live in

* :mod:`aqfg.model.terms`: :class:`Effect` and where a term acts, the class an effect
  derives from (``HeadingTerm``, ``CurrentTerm``, ``ThrustGainTerm``, ... ``UsblTerm``);
* :mod:`aqfg.model.catalogue`: the built-in effects, their parameters and wording,
  :data:`BUILTIN` and :func:`resolve`;
* :mod:`aqfg.model.user_effect`: :class:`UserEffect`, a user's :class:`GroundForceTerm`
  written in Python; its parameters are appended to the table by the model that uses it.

The numpy model (:mod:`aqfg.model.reference`, :mod:`aqfg.model.measurements`,
:func:`aqfg.model.frames.heading`) evaluates every built-in effect through the term methods;
the C++ kernel (``cpp_factors/kernel.hpp``) repeats the terms of those with ``in_cpp`` and
tests hold the two equal. The built-in parameters form the parameter table
(:mod:`aqfg.model.params`, dynamics effects first, in catalogue order).
"""
from __future__ import annotations

from aqfg.model.catalogue import (
    BUILTIN,
    BuiltinEffect,
    CurrentDrift,
    GnssDelay,
    GroundAdvance,
    HeadingDrift,
    LeverArm,
    LinearDrag,
    ReverseThrust,
    ThrustAsymmetry,
    ThrustLag,
    UsblBearingBias,
    UsblDelay,
    UsblRangeScale,
    WindDrag,
    resolve,
)
from aqfg.model.spec import ParamSpec
from aqfg.model.terms import (
    INFLOW_EPS4,
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
    abs_command,
)
from aqfg.model.user_effect import UserEffect

__all__ = [
    "BUILTIN", "INFLOW_EPS4", "BodyForceTerm", "BuiltinEffect", "CurrentDrift", "CurrentTerm",
    "DemandLagTerm", "Effect", "FixDelayTerm", "GnssDelay", "GroundAdvance", "GroundForceTerm",
    "HeadingDrift", "HeadingTerm", "InflowTerm", "LeverArm", "LinearDrag", "ParamSpec",
    "ReverseThrust", "SensorOffsetTerm", "ThrustAsymmetry", "ThrustGainTerm", "ThrustLag",
    "UsblBearingBias", "UsblDelay", "UsblRangeScale", "UsblTerm", "UserEffect", "WindDrag",
    "abs_command", "resolve",
]
