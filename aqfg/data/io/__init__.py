"""Read and write mission directories in the ``aqfg-mission/1`` format (the data contract).

Public API:

- :func:`load_mission` (dir -> :class:`~aqfg.data.mission.Mission`, never carries truth)
- :func:`load_truth` (dir -> :class:`~aqfg.data.mission.Truth` or None; evaluation only)
- :func:`save_mission` (Mission [+ Truth] -> dir; refuses to overwrite unless asked)
- :func:`check_mission` (the same value checks for a Mission built in memory)
- :func:`has_truth`, :func:`truth_sources` (whether a directory holds truth, unread)
- :class:`MissionFormatError` (``ValueError`` naming file, row and column)
- :class:`MissionWarning`, :func:`plausibility_warnings` (legal but suspicious input)

Reading is :mod:`.read`, the contract's rules :mod:`.check`, the suspicious-input checks
:mod:`.plausibility`, writing :mod:`.write`.
"""
from aqfg.data.io.check import (
    DIRECTION_TOL,
    KNOWN_KEYS,
    KNOWN_TABLES,
    MISSION_FILES,
    MISSION_TOML,
    QUAT_TOL,
    STREAM_FILES,
    MissionFormatError,
    check_mission,
    check_truth,
)
from aqfg.data.io.plausibility import MissionWarning, plausibility_warnings
from aqfg.data.io.read import has_truth, load_mission, load_truth, truth_sources
from aqfg.data.io.write import save_mission

__all__ = ["DIRECTION_TOL", "KNOWN_KEYS", "KNOWN_TABLES", "MISSION_FILES", "MISSION_TOML",
           "QUAT_TOL", "STREAM_FILES", "MissionFormatError", "MissionWarning", "check_mission",
           "check_truth", "has_truth", "load_mission", "load_truth", "plausibility_warnings",
           "save_mission", "truth_sources"]
