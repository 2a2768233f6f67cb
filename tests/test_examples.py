"""The shipped examples work as their comments say: each import map loads through the map
reader and imports a log of its family (written from a simulated mission by
tests/log_writers.py); the fleet manifest runs on the missions its comments simulate."""
from __future__ import annotations

import copy
import shlex
import shutil
from pathlib import Path

import log_writers as lw
import numpy as np
import pytest

from aqfg.cli import main
from aqfg.data.importers import import_log, load_map
from aqfg.data.io import load_mission, save_mission
from aqfg.sim.simulator import simulate

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
MAPS = sorted((EXAMPLES / "maps").glob("*.toml"))


def test_examples_are_there():
    names = {p.name for p in MAPS}
    assert {"ros2-asv.toml", "ardupilot-boat.toml", "px4-ulog.toml", "nmea.toml"} <= names
    assert (EXAMPLES / "fleet.toml").is_file() and (EXAMPLES / "README.md").is_file()


@pytest.mark.parametrize("path", MAPS, ids=[p.name for p in MAPS])
def test_every_map_loads_through_the_map_reader(path):
    imap = load_map(path)
    if path.name != "nmea.toml":          # nmea adds fixes to a mission: no vehicle needed
        assert imap.vehicle in ("asv", "auv") and imap.n_thrusters


@pytest.fixture(scope="module")
def sim():
    m, _ = simulate("asv", seed=4, duration=60.0)
    return m


def check(mi, m, imap, motors_tol):
    assert mi.vehicle == imap.vehicle and mi.name == imap.name
    np.testing.assert_array_equal(mi.thruster_pos, imap.thruster_pos)
    for a, b in ((mi.imu, m.imu), (mi.motors, m.motors), (mi.gnss, m.gnss)):
        assert len(a.t) == len(b.t)
    assert np.abs(mi.motors.u - m.motors.u).max() <= motors_tol
    # (a map without [origin] puts the origin at the first fix)
    assert np.abs((mi.gnss.ne - mi.gnss.ne[0]) - (m.gnss.ne - m.gnss.ne[0])).max() < 0.03


def test_ros2_map_imports_a_bag(sim, tmp_path):
    imap = load_map(EXAMPLES / "maps" / "ros2-asv.toml")
    r = import_log("ros2", lw.write_ros_bag(sim, tmp_path / "bag"), imap)
    check(r.mission, sim, imap, 1e-9)


def test_ardupilot_map_imports_dataflash_and_tlog(sim, tmp_path):
    imap = load_map(EXAMPLES / "maps" / "ardupilot-boat.toml")
    for path in (lw.write_dataflash(tmp_path / "a.bin", lw.dataflash_records(sim)),
                 lw.write_tlog(tmp_path / "a.tlog", lw.tlog_records(sim))):
        check(import_log("mavlink", path, imap).mission, sim, imap, 1.25e-3)   # 1-us PWM steps


def test_px4_map_imports_a_ulog(sim, tmp_path):
    imap = load_map(EXAMPLES / "maps" / "px4-ulog.toml")
    r = import_log("ulog", lw.write_ulog(tmp_path / "a.ulg", lw.ulog_records(sim)), imap)
    check(r.mission, sim, imap, 1e-6)


def test_nmea_map_adds_fixes(sim, tmp_path):
    base = copy.copy(sim)
    base.gnss = None
    base.extra = {"source": {"utc_zero": lw.T_BASE}}
    save_mission(base, tmp_path / "M")
    (tmp_path / "gps.nmea").write_bytes(b"".join(lw.nmea_lines(sim)))
    assert main(["import", "nmea", str(tmp_path / "gps.nmea"), "--out", str(tmp_path / "M"),
                 "--map", str(EXAMPLES / "maps" / "nmea.toml")]) == 0
    mi = load_mission(tmp_path / "M")
    assert len(mi.gnss.t) == len(sim.gnss.t)


def simulate_lines(text: str) -> list[list[str]]:
    """The `aqfg simulate ...` commands in a file's comments, as argument lists."""
    return [shlex.split(ln.split("aqfg", 1)[1]) for ln in text.splitlines()
            if ln.lstrip("# ").startswith("aqfg simulate")]


def test_fleet_manifest_runs_on_the_missions_its_comments_simulate(tmp_path, capsys):
    pytest.importorskip("distributed")
    ex = tmp_path / "examples"
    ex.mkdir()
    shutil.copy(EXAMPLES / "fleet.toml", ex)
    lines = simulate_lines((ex / "fleet.toml").read_text())
    assert len(lines) == 3
    for argv in lines:                     # shorter missions than the comments', for speed
        argv = [a.replace("examples/", str(ex) + "/") for a in argv]
        i = argv.index("--duration")
        argv[i + 1] = "120"
        assert main([argv[0], "-q", *argv[1:]]) == 0
    out = tmp_path / "season"
    assert main(["fleet", str(ex / "fleet.toml"), "--out", str(out), "--workers", "1"]) == 0
    for v in ("boat-1", "boat-2"):
        assert (out / v / "parameters.json").is_file()
    assert (out / "fleet.json").is_file()
