"""Per-mission results kept for the next use with the same mission.

A default batch fit builds a mission's graph up to three times (the model as given, then
with the effect the structural test names, from two starts: :mod:`aqfg.fg.fit`), and a
diagnosis re-traces and refits the same missions many times. The kernel steps of the same
knots are the same (:meth:`aqfg.model.vehicle.Model.steps`), and so are the closed-form
starts where the dynamics are (the C++ kernel reads the dynamics parameters only, so a
model with an effect at its null rolls out as the one without it: :mod:`aqfg.fg.graph`):
:func:`remember` returns the value made for the same mission object and key, else makes
it. At most ``SIZE`` values and ``BUDGET`` bytes of numpy arrays are kept, the most
recently used; a larger value is not kept (a 15-min mission's steps at 50 Hz are ~5 MB,
its starts ~3 MB).
"""
from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import numpy as np

SIZE = 8
BUDGET = 128 * 2 ** 20          # bytes
T = TypeVar("T")
_KEPT: list[tuple[weakref.ref, Hashable, Any, int]] = []


def nbytes(v: Any) -> int:
    """Bytes of the numpy arrays in ``v`` (arrays, tuples, lists, dataclasses of them)."""
    if isinstance(v, np.ndarray):
        return int(v.nbytes)
    if isinstance(v, (tuple, list)):
        return sum(nbytes(x) for x in v)
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return sum(nbytes(getattr(v, f.name)) for f in dataclasses.fields(v))
    return 0


def remember(mission: Any, key: Hashable, make: Callable[[], T]) -> T:
    """``make()``, or the value it gave for this ``mission`` (the same object) and ``key``."""
    for i, (ref, k, v, _) in enumerate(_KEPT):
        if ref() is mission and k == key:
            _KEPT.insert(0, _KEPT.pop(i))
            return v
    v = make()
    size = nbytes(v)
    try:
        ref = weakref.ref(mission)
    except TypeError:               # (an object that cannot be referred to weakly)
        return v
    if size > BUDGET:
        return v
    _KEPT.insert(0, (ref, key, v, size))
    # the least recently used beyond the count or the bytes, and those of missions gone
    _KEPT[:] = [e for e in _KEPT if e[0]() is not None]
    while len(_KEPT) > SIZE or sum(e[3] for e in _KEPT) > BUDGET:
        _KEPT.pop()
    return v


def clear() -> None:
    """Forget every kept value."""
    _KEPT.clear()
