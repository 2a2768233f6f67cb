"""The few functions most users need, re-exported at the top level (``aqfg.fit``, ...)::

    import aqfg
    m = aqfg.load_mission("run3")             # a directory in aqfg-mission/1 format
    r = aqfg.fit(m)                           # factor graph, batch: a Result
    r = aqfg.fit(m, method="update-error")    # the paper's method, the same Result type
    r = aqfg.fit(m, mode="online", init=r.vehicle_constants(), effects=r.effects)
    d = aqfg.diagnose(m)                      # which physics is the model missing?
    print(d.summary())

Each is a thin front of the function that does the work (named in its docstring), which
takes further options; the rest of the API lives where it is implemented
(:mod:`aqfg.fg.fit`, :mod:`aqfg.ekf.estimator`, :mod:`aqfg.diagnose`, :mod:`aqfg.data.io`).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from aqfg.data.mission import Mission
    from aqfg.diagnose.workflow import Diagnosis
    from aqfg.result import Result

    MissionLike = Mission | str | os.PathLike

METHODS = ("fg", "update-error")


def missions_of(missions: MissionLike | Sequence[MissionLike]) -> list[Mission]:
    """One mission or several, each a :class:`~aqfg.data.mission.Mission` or the path of a
    mission directory (loaded with :func:`aqfg.data.io.load_mission`)."""
    from aqfg.data.io import load_mission
    from aqfg.data.mission import Mission
    if isinstance(missions, (Mission, str, os.PathLike)):
        missions = [missions]
    return [m if isinstance(m, Mission) else load_mission(m) for m in missions]


def fit(missions: MissionLike | Sequence[MissionLike], *, method: str = "fg",
        mode: str = "batch", **kw: Any) -> Result:
    """Estimate the parameters and the trajectory of ``missions`` (as ``aqfg fit``).

    ``method``: "fg" (factor graph, :func:`aqfg.fg.fit.fit_fg`) or "update-error" (the
    paper's EKF method, :func:`aqfg.ekf.estimator.fit_update_error`); ``mode``: "batch"
    (all missions jointly) or "online". Other keywords (``estimate``, ``init``,
    ``effects``, ``window``, ...) go to that function. Returns a :class:`aqfg.result.Result`.
    """
    ms = missions_of(missions)
    if method == "fg":
        from aqfg.fg.fit import fit_fg
        return fit_fg(ms, mode=mode, **kw)
    if method == "update-error":
        from aqfg.ekf.estimator import fit_update_error
        return fit_update_error(ms, mode=mode, **kw)
    raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")


def diagnose(missions: MissionLike | Sequence[MissionLike], **kw: Any) -> Diagnosis:
    """Which physical effect the model is missing (as ``aqfg diagnose``):
    :func:`aqfg.diagnose.workflow.diagnose` (keywords ``effects``, ``gnss_every``, ...).
    The loop that adds effects until nothing more is confirmed is
    :func:`aqfg.diagnose.diagnose_sequence`."""
    from aqfg.diagnose.workflow import diagnose as run
    return run(missions_of(missions), **kw)
