"""Shared fixtures: the repository's own independent-vehicle missions (tests/data, see its
README for their origin) and a simulated one. Nothing here reads outside the repository."""
from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from aqfg.data.io import save_mission
from aqfg.sim.simulator import simulate

# Property tests: a moderate number of examples in CI; `pytest --hypothesis-profile=thorough`
# for a deep local run.
_QUIET = [HealthCheck.too_slow, HealthCheck.data_too_large]
settings.register_profile("ci", max_examples=150, deadline=None, suppress_health_check=_QUIET)
settings.register_profile("thorough", max_examples=10_000, deadline=None,
                          suppress_health_check=_QUIET)
settings.load_profile("ci")

DATA = Path(__file__).resolve().parent / "data"
OTTER_MISSIONS = ("otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
                  "otter-dev-current-weakprop", "otter-dev-yawdrift")


def data_path(name: str) -> Path:
    """Path of a mission in tests/data (fails clearly if the checkout lacks it)."""
    p = DATA / name
    assert (p / "mission.toml").is_file(), f"test mission {p} is missing from the checkout"
    return p


def mission_toml(name: str, vehicle: str, station_down: float,
                 origin: tuple[float, float] | None = None) -> str:
    """``mission.toml`` of a small two-thruster test vehicle (both pushing forward, 0.25 m
    aft, 0.12 m either side) with a USBL station ``station_down`` m below the ground
    origin, and an ``[origin]`` (lat, lon degrees) if given."""
    text = f"""format = "aqfg-mission/1"
name = "{name}"
vehicle = "{vehicle}"

[thrusters]
direction = [[1, 0, 0], [1, 0, 0]]
position = [[-0.25, 0.12, 0], [-0.25, -0.12, 0]]

[usbl]
station = [0.0, 0.0, {station_down!r}]
"""
    if origin is not None:
        text += f"\n[origin]\nlat = {origin[0]!r}\nlon = {origin[1]!r}\n"
    return text


@pytest.fixture(scope="session")
def wind_mission_dir(tmp_path_factory) -> Path:
    """A 240-s simulated ASV mission (seed 4) with hidden wind drag (0.06, 0.04), saved
    with its truth; tests only read it."""
    d = tmp_path_factory.mktemp("w") / "wind"
    m, truth = simulate("asv", seed=4, duration=240.0, effects={"wind_drag": [0.06, 0.04]})
    save_mission(m, d, truth=truth)
    return d


@pytest.fixture(scope="session")
def otter() -> Path:
    """The Otter USV example mission (Fossen's 6-DOF model; truth in mission.toml)."""
    return data_path("otter-example")
