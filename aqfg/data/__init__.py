"""Missions in and out: the ``aqfg-mission/1`` contract (docs/mission-format.md), the
in-memory ``Mission`` of numpy arrays, geodesy for lat/lon input, and the preflight of a fit
(suspicious input, cost estimate)."""
from aqfg.data.io import (
    MissionFormatError,
    MissionWarning,
    check_mission,
    has_truth,
    load_mission,
    load_truth,
    save_mission,
)
from aqfg.data.mission import Mission, Truth

__all__ = ["Mission", "MissionFormatError", "MissionWarning", "Truth", "check_mission",
           "has_truth", "load_mission", "load_truth", "save_mission"]
