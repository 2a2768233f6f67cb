"""Per-mission results kept for the next graph of the same mission.

A default batch fit builds a mission's graph up to three times (the model as given, then
with the effect the structural test names, from two starts: :mod:`aqfg.fg.fit`). The
kernel steps of the same knots are the same, and so are the closed-form starts where the
dynamics are (the C++ kernel reads the dynamics parameters only, so a model with an
effect at its null rolls out as the one without it): :func:`remember` returns the value
made for the same mission object and key, else makes it. The last ``SIZE`` values are
kept (a mission's starts hold its model track at every knot per grid point, ~3 MB for a
15-min mission at 1-Hz fixes).
"""
from __future__ import annotations

import weakref
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

SIZE = 6
T = TypeVar("T")
_KEPT: list[tuple[weakref.ref, Hashable, Any]] = []


def remember(mission: Any, key: Hashable, make: Callable[[], T]) -> T:
    """``make()``, or the value it gave for this ``mission`` (the same object) and ``key``."""
    for i, (ref, k, v) in enumerate(_KEPT):
        if ref() is mission and k == key:
            _KEPT.insert(0, _KEPT.pop(i))
            return v
    v = make()
    _KEPT.insert(0, (weakref.ref(mission), key, v))
    del _KEPT[SIZE:]
    return v


def clear() -> None:
    """Forget every kept value."""
    _KEPT.clear()
