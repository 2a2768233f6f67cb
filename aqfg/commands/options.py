"""Bounded numbers: the one check every numeric option and every parameter value passes.

A number that validates is finite and inside bounds that keep every command bounded in
time and memory: :func:`number` builds the ``argparse`` type of a numeric option (a bad
value is a usage error, exit 2), :func:`parameter_value` checks a model parameter's value
from the command line or a file (its physical bounds, and at most :data:`ABSURD` times its
typical magnitude).
"""
from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass

MAX_SECONDS = 86_400.0   # one day: the longest duration, window or fix period an option takes
POSITIONAL = ("out_dir",)   # the positional arguments a check may name
ABSURD = 1e6             # a parameter value beyond ABSURD x its typical magnitude is no value


def parse(text: str, lo: float, hi: float, *, lo_open: bool = False,
          integer: bool = False) -> float:
    """``text`` as a finite number in ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``), a whole
    number if ``integer``; ValueError saying what was expected otherwise."""
    what = "a whole number" if integer else "a number"
    rng = f"{'above' if lo_open else 'at least'} {lo:g} and at most {hi:g}"
    try:
        v = float(int(text)) if integer else float(text)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"expected {what} {rng}, got {text!r}") from None
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        raise ValueError(f"expected {what} {rng}, got {text!r}")
    return v


@dataclass(frozen=True)
class Invalid:
    """A numeric option's value that did not validate: :func:`check_parsed` turns it into
    a usage error (one line, exit 2, as every other bad option value)."""
    text: str
    problem: str


def number(lo: float, hi: float, *, lo_open: bool = False,
           integer: bool = False) -> Callable[[str], float | int | Invalid]:
    """The ``argparse`` type of a numeric option: :func:`parse` with these bounds (an
    :class:`Invalid` for a value that does not validate)."""
    def convert(text: str) -> float | int | Invalid:
        try:
            v = parse(text, lo, hi, lo_open=lo_open, integer=integer)
        except ValueError as e:
            return Invalid(text, str(e))
        return int(v) if integer else v
    return convert


def check_parsed(args: argparse.Namespace) -> None:
    """UsageError naming the first option whose value did not validate."""
    from aqfg.commands.common import UsageError
    for dest, v in vars(args).items():
        if isinstance(v, Invalid):
            name = dest.upper() if dest in POSITIONAL else f"--{dest.replace('_', '-')}"
            raise UsageError(f"{name}: {v.problem}")


def seconds(*, zero: bool = False) -> Callable[[str], float | int | Invalid]:
    """A duration option in seconds: positive (or 0 when ``zero`` means "off"), at most
    :data:`MAX_SECONDS`."""
    return number(0.0, MAX_SECONDS, lo_open=not zero)


def parameter_value(name: str, value: object, where: str) -> float:
    """``value`` of the model parameter ``name`` as a float, checked: a finite number inside
    the parameter's physical bounds and within :data:`ABSURD` x its typical magnitude.
    ValueError naming ``where`` and the parameter otherwise (names the model does not know
    pass through: the fit's own checks name them)."""
    from aqfg.model.params import SPEC
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"{where}: value of {name!r} must be a number, got {value!r}")
    try:
        v = float(value)
    except ValueError:
        raise ValueError(f"{where}: value of {name!r} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: value of {name!r} must be finite, got {value!r}")
    spec = SPEC.get(name)
    if spec is None:
        return v
    limit = ABSURD * spec.scale
    lo, hi = max(spec.lower, -limit), min(spec.upper, limit)
    if not lo <= v <= hi:
        raise ValueError(f"{where}: {name} = {v:g} {spec.unit} is outside [{lo:g}, {hi:g}] "
                         f"(its physical bounds, and at most {ABSURD:g}x its typical "
                         f"size {spec.scale:g})")
    return v
