"""``aqfg import``: real logs written by each ecosystem's writers from a simulated mission
come back as the same mission (within each format's resolution), fit to the same theta_e,
and bad logs get errors naming the topic and the time.

Tolerances are the formats' own resolutions: ROS float64 (exact to rounding); tlog float32
angles and microsecond stamps; DataFlash centidegrees and 1e-7 deg positions; PWM outputs
whole microseconds over a 400 us half range (1.25e-3); NMEA 1e-5 arc-minutes (< 1 cm).
"""
from __future__ import annotations

import copy
import json

import log_writers as lw
import numpy as np
import pytest

from aqfg.cli import main
from aqfg.data.importers import LogFormatError, MissingExtraError, import_log, parse_map
from aqfg.data.importers.frames import enu_flu_to_ned_frd, flu_to_frd, quat_mul
from aqfg.data.io import MissionFormatError, load_mission, save_mission
from aqfg.fg import fit_fg
from aqfg.sim import simulate

try:
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

THETA_TOL_DEG = 0.5                    # imported vs original fit (the tolerance)
PWM_MAP = "channels = [1, 3]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"


@pytest.fixture(scope="module")
def sim():
    return simulate("asv", seed=3, duration=300.0)


@pytest.fixture(scope="module")
def fit0(sim):
    return fit_fg(sim[0]).values["theta_e"]


def imap_for(m, **tables):
    return parse_map(tomllib.loads(lw.map_toml(m, **tables)), "map.toml")


def angle(q1, q2):
    """Rotation angle (rad) between attitudes (n, 4), sign of q ignored."""
    d = np.abs(np.sum(q1 * q2, axis=1)) / (np.linalg.norm(q1, axis=1) * np.linalg.norm(q2, axis=1))
    return 2 * np.arccos(np.clip(d, -1.0, 1.0))


def check_streams(mi, m, att, motors, pos, sigma=1e-9, dt=1e-6, gyro=None):
    assert mi.vehicle == m.vehicle and mi.n_thrusters == m.n_thrusters
    np.testing.assert_array_equal(mi.thruster_dir, m.thruster_dir)
    for a, b in ((mi.imu, m.imu), (mi.motors, m.motors), (mi.gnss, m.gnss)):
        assert len(a.t) == len(b.t) and np.abs(a.t - b.t).max() <= dt
    assert angle(mi.imu.q, m.imu.q).max() <= att
    assert np.abs(mi.motors.u - m.motors.u).max() <= motors
    assert np.abs(mi.gnss.ne - m.gnss.ne).max() <= pos
    assert np.abs(mi.gnss.sigma - m.gnss.sigma).max() <= sigma
    if gyro is not None:
        assert np.abs(mi.imu.gyro - m.imu.gyro).max() <= gyro
    assert mi.origin == lw.ORIGIN


# ------------------------------------------------------------------------ frames

def test_rep103_attitude_becomes_ned_frd():
    s = np.sqrt(0.5)
    # level, heading north: ENU yaw +90 deg -> NED yaw 0
    q = enu_flu_to_ned_frd(np.array([[s, 0, 0, s]]))
    assert angle(q, np.array([[1.0, 0, 0, 0]]))[0] < 1e-12
    # level, heading east: ENU yaw 0 -> NED yaw +90 deg
    q = enu_flu_to_ned_frd(np.array([[1.0, 0, 0, 0]]))
    assert angle(q, np.array([[s, 0, 0, s]]))[0] < 1e-12
    # heading north, nose down 0.2 rad: FLU pitch +0.2 about y-left -> FRD pitch -0.2
    nose_down = quat_mul([s, 0, 0, s], [np.cos(0.1), 0, np.sin(0.1), 0])
    q = enu_flu_to_ned_frd(nose_down[None])
    assert angle(q, np.array([[np.cos(0.1), 0, -np.sin(0.1), 0]]))[0] < 1e-12
    # starboard down is positive roll in both
    stbd_down = quat_mul([s, 0, 0, s], [np.cos(0.15), np.sin(0.15), 0, 0])
    q = enu_flu_to_ned_frd(stbd_down[None])
    assert angle(q, np.array([[np.cos(0.15), np.sin(0.15), 0, 0]]))[0] < 1e-12
    # at rest the accelerometer reads +g up (FLU) = -g along z down (FRD)
    np.testing.assert_allclose(flu_to_frd([[0.0, 0.0, 9.81]]), [[0.0, 0.0, -9.81]])


def test_rep103_conversion_matches_rotation_matrices():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ros = lw.ros_quaternions(q)[:, [3, 0, 1, 2]]        # via scipy matrices, w first
    back = enu_flu_to_ned_frd(ros)
    assert angle(back, q).max() < 1e-7
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-12)


# ------------------------------------------------------------------------ map file

def test_map_file_has_mission_toml_shape_and_names_bad_keys(tmp_path):
    good = ('vehicle = "auv"\nname = "x"\n[thrusters]\ndirection = [[1, 0, 0]]\n'
            '[usbl]\nstation = [0, 0, 1.5]\n[origin]\nlat = 46.5\nlon = 6.5\n'
            '[topics]\nimu = "/ins/imu"\nusbl = { topic = "/u", range = "r", bearing = "b" }\n'
            '[motors]\nchannels = [2]\npwm_min = 1000\npwm_trim = 1500\npwm_max = 2000\n'
            '[time]\nstamp = "log"\nmax_gap = 20\n')
    m = parse_map(tomllib.loads(good), "map.toml")
    assert m.vehicle == "auv" and m.thruster_dir.tolist() == [[1, 0, 0]]
    assert m.origin == (46.5, 6.5) and m.usbl_station.tolist() == [0, 0, 1.5]
    assert m.topics["imu"].topic == "/ins/imu" and m.topics["usbl"].fields["range"] == "r"
    assert m.channels == [2] and m.pwm.trim.tolist() == [1500] and m.stamp == "log"
    bad = {
        'vehicle = "boat"': "column 'vehicle'",
        '[thrusters]\ndirection = [[2, 0, 0]]': "[thrusters] direction",
        '[origin]\nlat = 46.5': "[origin] lon",
        '[topics]\nspeed = "/v"': "[topics] speed",
        '[topics]\nusbl = { topic = "/u", range = "r", bearing = "b" }': "[usbl] station",
        '[motors]\npwm_min = 1100\npwm_max = 1900': "[motors] pwm_trim",
        '[motors]\npwm_min = 1900\npwm_trim = 1500\npwm_max = 1100': "pwm_min < pwm_trim",
        '[time]\nstamp = "gps"': "[time] stamp",
        'format = "aqfg-mission/1"': "belongs in mission.toml",
        '[thruster]\ndirection = [[1, 0, 0]]': "column 'thruster'",
    }
    for text, where in bad.items():
        with pytest.raises(MissionFormatError, match="map.toml") as e:
            parse_map(tomllib.loads(text), "map.toml")
        assert where in str(e.value), (text, str(e.value))


# ------------------------------------------------------------------ round trips + fit

@pytest.mark.slow
@pytest.mark.parametrize("version,storage", [("ros2", "mcap"), ("ros2", "sqlite3"),
                                             ("ros1", None)])
def test_ros_bags_round_trip_and_fit(sim, fit0, tmp_path, version, storage):
    m, _ = sim
    path = tmp_path / ("log.bag" if version == "ros1" else "bag")
    lw.write_ros_bag(m, path, version, storage or "mcap")
    r = import_log(version, path, imap_for(m))
    check_streams(r.mission, m, att=1e-7, motors=0.0, pos=1e-6, gyro=1e-12)
    np.testing.assert_allclose(r.mission.imu.acc, m.imu.acc, atol=1e-12)
    assert r.mission.extra["source"]["utc_zero"] == lw.T_BASE
    assert abs(np.degrees(fit_fg(r.mission).values["theta_e"] - fit0)) < THETA_TOL_DEG


@pytest.mark.slow
def test_mavlink_tlog_and_dataflash_round_trip_and_fit(sim, fit0, tmp_path):
    m, _ = sim
    imap = imap_for(m, motors=PWM_MAP)
    r = import_log("mavlink", lw.write_tlog(tmp_path / "a.tlog", lw.tlog_records(m)), imap)
    check_streams(r.mission, m, att=1e-6, motors=1.25e-3, pos=0.01, sigma=1e-3, gyro=1e-6)
    assert abs(np.degrees(fit_fg(r.mission).values["theta_e"] - fit0)) < THETA_TOL_DEG
    path = lw.write_dataflash(tmp_path / "a.bin", lw.dataflash_records(m, gps_week=2280))
    r = import_log("mavlink", path, imap)
    check_streams(r.mission, m, att=3e-4, motors=1.25e-3, pos=0.01, sigma=0.005)
    src = r.mission.extra["source"]
    assert src["t_zero"] == pytest.approx(20.0) and src["clock"].startswith("boot")
    # GPS week 2280, 100000 s into it, 18 leap seconds: UTC of mission t = 0
    assert src["utc_zero"] == pytest.approx(315964800 + 2280 * 604800 + 100000 - 18)
    assert abs(np.degrees(fit_fg(r.mission).values["theta_e"] - fit0)) < THETA_TOL_DEG


def test_ulog_round_trip_and_fit(sim, fit0, tmp_path):
    m, _ = sim
    r = import_log("ulog", lw.write_ulog(tmp_path / "a.ulg", lw.ulog_records(m)), imap_for(m))
    check_streams(r.mission, m, att=1e-6, motors=1e-7, pos=1e-6, sigma=1e-6)
    assert r.mission.extra["source"]["utc_zero"] == pytest.approx(lw.T_BASE, abs=1e-6)
    assert abs(np.degrees(fit_fg(r.mission).values["theta_e"] - fit0)) < THETA_TOL_DEG


def test_nmea_adds_fixes_to_an_imported_mission(sim, tmp_path, capsys):
    m, _ = sim
    (tmp_path / "map.toml").write_text(lw.map_toml(m))
    bag = lw.write_ros_bag(m, tmp_path / "bag", drop=("gnss",))
    out = tmp_path / "M"
    # the bag alone has no fixes: a data error
    assert main(["import", "ros2", str(bag), "--out", str(out), "--map",
                 str(tmp_path / "map.toml")]) == 3
    assert "/gps/fix" in capsys.readouterr().err
    base = copy.copy(m)
    base.gnss = None
    base.extra = {"source": {"utc_zero": lw.T_BASE}}
    save_mission(base, out)
    (tmp_path / "fixes.nmea").write_bytes(b"".join(lw.nmea_lines(m)))
    assert main(["import", "nmea", str(tmp_path / "fixes.nmea"), "--out", str(out), "--map",
                 str(tmp_path / "map.toml")]) == 0
    mi = load_mission(out)
    assert np.abs(mi.gnss.t - m.gnss.t).max() < 1e-6
    assert np.abs(mi.gnss.ne - m.gnss.ne).max() < 0.015 and mi.origin == lw.ORIGIN
    np.testing.assert_allclose(mi.gnss.sigma, m.gnss.sigma, atol=0.05)
    assert "added GNSS fixes" in capsys.readouterr().out
    # fixes already there: not replaced without --force
    assert main(["import", "nmea", str(tmp_path / "fixes.nmea"), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    # without the mission's UTC start the times of day cannot be placed
    del base.extra["source"]
    out2 = tmp_path / "M2"
    save_mission(base, out2)
    with pytest.raises(LogFormatError, match="utc_zero"):
        import_log("nmea", tmp_path / "fixes.nmea", imap_for(m), base=load_mission(out2))


@pytest.mark.slow
def test_auv_depth_and_usbl_from_mapped_topics(tmp_path):
    m, _ = simulate("auv", seed=4, duration=300.0, gnss_period=None, usbl=True)
    bag = lw.write_ros_bag(m, tmp_path / "bag")
    st = ", ".join(repr(float(x)) for x in m.usbl_station)
    imap = imap_for(m, usbl=f"station = [{st}]", topics=(
        'depth = { topic = "/depth", field = "data" }\n'
        'usbl = { topic = "/usbl/fix", range = "range", bearing = "bearing_deg", '
        'angle_unit = "deg" }'))
    r = import_log("ros2", bag, imap)
    mi = r.mission
    assert mi.gnss is None and mi.vehicle == "auv"
    np.testing.assert_allclose(mi.depth.t, m.depth.t, atol=1e-9)
    np.testing.assert_allclose(mi.depth.depth, m.depth.depth, atol=1e-12)
    np.testing.assert_allclose(mi.usbl.range, m.usbl.range, atol=1e-12)
    np.testing.assert_allclose(mi.usbl.bearing, m.usbl.bearing, atol=1e-12)
    np.testing.assert_allclose(mi.usbl_station, m.usbl_station)
    a, b = fit_fg(m).values["theta_e"], fit_fg(mi).values["theta_e"]
    assert abs(np.degrees(a - b)) < THETA_TOL_DEG


def test_fixes_without_solution_are_left_out_and_counted(tmp_path):
    m, _ = simulate("asv", seed=5, duration=60.0)
    def no_fix(msgs):
        fixes = [x for x in msgs if x[1] == "/gps/fix"]
        for _, _, msg in fixes[10:15]:
            msg.status.status = -1
        return msgs
    r = import_log("ros2", lw.write_ros_bag(m, tmp_path / "bag", edit=no_fix), imap_for(m))
    keep = np.r_[0:10, 15:len(m.gnss.t)]
    np.testing.assert_allclose(r.mission.gnss.t, m.gnss.t[keep], atol=1e-9)
    assert "no fix (status -1) left out: 5" in r.summary()
    # MAVLink: fix_type 1 (no fix) left out; ATTITUDE_QUATERNION for the attitude
    recs = lw.tlog_records(m, quaternion=True)
    gps = [msg for _, msg in recs if msg.get_type() == "GPS_RAW_INT"]
    for msg in gps[:3]:
        msg.fix_type = 1
    r = import_log("mavlink", lw.write_tlog(tmp_path / "a.tlog", recs),
                   imap_for(m, motors=PWM_MAP, topics='imu = "ATTITUDE_QUATERNION"'))
    assert len(r.mission.gnss.t) == len(m.gnss.t) - 3 and "fix_type < 2) left out: 3" in r.summary()
    assert angle(r.mission.imu.q, m.imu.q).max() < 1e-6
    np.testing.assert_allclose(r.mission.imu.gyro, m.imu.gyro, atol=1e-6)


# ----------------------------------------------------------- the done-when

def _fit_theta(mission_dir, out):
    assert main(["fit", str(mission_dir), "--out", str(out), "--no-plots"]) == 0
    return json.loads((out / "parameters.json").read_text())["parameters"]["theta_e"]["value"]


@pytest.mark.slow
def test_cli_mcap_bag_and_tlog_fit_like_the_csv_mission(sim, tmp_path, capsys):
    m, tr = sim
    csv = save_mission(m, tmp_path / "csv", truth=tr)
    theta_csv = _fit_theta(csv, tmp_path / "fit-csv")
    (tmp_path / "map.toml").write_text(lw.map_toml(m))
    (tmp_path / "map-pwm.toml").write_text(lw.map_toml(m, motors=PWM_MAP))
    bag = lw.write_ros_bag(m, tmp_path / "bag", "ros2", "mcap")
    tlog = lw.write_tlog(tmp_path / "a.tlog", lw.tlog_records(m))
    for fmt, src, mp in (("ros2", bag, "map.toml"), ("mavlink", tlog, "map-pwm.toml")):
        out = tmp_path / f"M-{fmt}"
        assert main(["import", fmt, str(src), "--out", str(out), "--map",
                     str(tmp_path / mp)]) == 0
        printed = capsys.readouterr().out
        assert "imu       15001 rows" in printed and "gnss        301 rows" in printed
        theta = _fit_theta(out, tmp_path / f"fit-{fmt}")
        assert abs(np.degrees(theta - theta_csv)) < THETA_TOL_DEG, fmt
    # an existing mission is not overwritten without --force
    assert main(["import", "ros2", str(bag), "--out", str(tmp_path / "M-ros2"), "--map",
                 str(tmp_path / "map.toml")]) == 2
    assert "--force" in capsys.readouterr().err


# ---------------------------------------------------------------------- bad logs

def _ros_error(m, tmp_path, imap=None, **kw) -> str:
    bag = lw.write_ros_bag(m, tmp_path / "bad", **kw)
    with pytest.raises(LogFormatError) as e:
        import_log("ros2", bag, imap or imap_for(m))
    return str(e.value)


def test_missing_topic_and_wrong_type_name_the_topic(sim, tmp_path):
    m, _ = sim
    msg = _ros_error(m, tmp_path, drop=("imu",))
    assert "topic /imu/data" in msg and "not in the bag" in msg and "/gps/fix" in msg
    bag = tmp_path / "bad"
    imap = imap_for(m, topics='imu = "/gps/fix"')
    with pytest.raises(LogFormatError, match="topic /gps/fix: message type "
                                             "sensor_msgs/msg/NavSatFix; the imu stream needs "
                                             "sensor_msgs/msg/Imu"):
        import_log("ros2", bag, imap)
    with pytest.raises(LogFormatError, match="vehicle and \\[thrusters\\] direction"):
        import_log("ros2", bag)


def _shift(topic, after_s, by_s, header=True, record=False):
    """An edit moving the stamps of ``topic`` after mission time ``after_s`` by ``by_s``."""
    def edit(msgs):
        out = []
        for ns, t, msg in msgs:
            if t == topic and ns >= (lw.T_BASE + after_s) * 1e9:
                if header:
                    st = msg.header.stamp
                    tot = st.sec * 10**9 + st.nanosec + int(by_s * 1e9)
                    msg.header.stamp = type(st)(sec=tot // 10**9, nanosec=tot % 10**9)
                if record:
                    ns += int(by_s * 1e9)
            out.append((ns, t, msg))
        return sorted(out, key=lambda x: x[0])
    return edit


@pytest.mark.slow
def test_clock_jump_and_out_of_order_stamps_name_topic_and_time(sim, tmp_path):
    m, _ = sim
    # the IMU's clock jumps an hour ahead at t = 100 s (the recorder's does not)
    msg = _ros_error(m, tmp_path, edit=_shift("/imu/data", 100.0, 3600.0))
    assert "topic /imu/data" in msg and "log time 1700000100.000000 s" in msg
    assert "100.000 s after the start" in msg and "+3600.000 s" in msg and "clock" in msg
    # two IMU messages swap their stamps: out of order
    def swap(msgs):
        imu = [x for x in msgs if x[1] == "/imu/data"]
        a, b = imu[500][2], imu[501][2]
        a.header.stamp, b.header.stamp = b.header.stamp, a.header.stamp
        return msgs
    msg = _ros_error(m, tmp_path / "swap", edit=swap)
    assert "topic /imu/data" in msg and "out of order" in msg
    assert "log time 1700000010.000000 s" in msg and "after 1700000010.020000 s" in msg
    # the whole log jumps ahead (recorder clock reset): a gap longer than max_gap
    recs = [(us + (7200_000_000 if us >= (lw.T_BASE + 150) * 1e6 else 0), msg)
            for us, msg in lw.tlog_records(m)]
    tlog = lw.write_tlog(tmp_path / "jump.tlog", recs)
    with pytest.raises(LogFormatError, match="clock jump: 7200.020 s") as e:
        import_log("mavlink", tlog, imap_for(m, motors=PWM_MAP))
    assert "topic ATTITUDE, log time 1700007350.000000 s" in str(e.value)
    assert "from 1700000149.980000 s" in str(e.value)
    # ... and a ground-station clock stepping back: out of order, named
    recs = [(us - (5_000_000 if us >= (lw.T_BASE + 150) * 1e6 else 0), msg)
            for us, msg in lw.tlog_records(m)]
    with pytest.raises(LogFormatError, match="topic ATTITUDE.*out of order"):
        import_log("mavlink", lw.write_tlog(tmp_path / "back.tlog", recs),
                   imap_for(m, motors=PWM_MAP))


def test_streams_on_different_clocks_and_bad_values(sim, tmp_path):
    m, _ = sim
    recs = [(us + 10**10 if name == "vehicle_gps_position" else us, name,
             {**v, "timestamp": v["timestamp"] + (10**10 if name == "vehicle_gps_position"
                                                  else 0)})
            for us, name, v in lw.ulog_records(m)]
    with pytest.raises(LogFormatError, match="topic vehicle_gps_position.*do not overlap.*"
                                             "different clocks"):
        import_log("ulog", lw.write_ulog(tmp_path / "a.ulg", recs), imap_for(m))
    # a PWM output outside the map's range, with its time
    recs = lw.dataflash_records(m)
    k = next(i for i, r in enumerate(recs) if r[1] == "RCOU" and r[0] > 50e6)
    recs[k][2][3] = 2100
    with pytest.raises(LogFormatError, match="topic RCOU, log time .*: output 3 \\(thruster 2\\)"
                                             " is 2100 us, outside"):
        import_log("mavlink", lw.write_dataflash(tmp_path / "a.bin", recs),
                   imap_for(m, motors=PWM_MAP))
    # a PWM log without the map's PWM range
    with pytest.raises(LogFormatError, match="pwm_min, pwm_trim, pwm_max"):
        import_log("mavlink", tmp_path / "a.bin", imap_for(m))
    # commands out of [-1, 1] on a ROS topic
    def scale(msgs):
        for _, t, msg in msgs:
            if t == "/thrusters/cmd":
                msg.data = msg.data * 3.0
        return msgs
    msg = _ros_error(m, tmp_path, edit=scale)
    assert "topic /thrusters/cmd" in msg and "expected a normalised command in [-1, 1]" in msg


def test_missing_extra_names_the_pip_command(sim, tmp_path, monkeypatch, capsys):
    import importlib
    real = importlib.import_module

    def fake(name, *a, **k):
        if name.split(".")[0] == "rosbags":
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return real(name, *a, **k)
    monkeypatch.setattr(importlib, "import_module", fake)
    m, _ = sim
    with pytest.raises(MissingExtraError, match='pip install "aqfg\\[ros\\]"'):
        import_log("ros2", tmp_path, imap_for(m))
    (tmp_path / "map.toml").write_text(lw.map_toml(m))
    monkeypatch.setattr(importlib, "import_module",
                        lambda n, *a, **k: real(n, *a, **k) if n.startswith("aqfg")
                        else fake(n, *a, **k))
    assert main(["import", "ros2", str(tmp_path), "--out", str(tmp_path / "M"),
                 "--map", str(tmp_path / "map.toml")]) == 2
    err = capsys.readouterr().err
    assert "rosbags" in err and 'pip install "aqfg[ros]"' in err and "Traceback" not in err


def test_import_replaces_a_mission_whole_or_not_at_all(tmp_path, monkeypatch):
    """``aqfg import --force`` over an existing mission: a failure while writing leaves the
    old mission exactly as it was (no mix of old and new stream files)."""
    from aqfg.data.io import load_mission, save_mission
    from aqfg.data.io import write as io_write
    from aqfg.sim import simulate
    old, _ = simulate("asv", seed=1, duration=30.0)
    out = tmp_path / "m"
    save_mission(old, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    new, _ = simulate("asv", seed=2, duration=40.0)
    src = tmp_path / "src"
    save_mission(new, src)

    class Boom(RuntimeError):
        pass
    real = io_write._write_atomic
    calls = {"n": 0}

    def failing(path, text):
        calls["n"] += 1
        if calls["n"] == 3:                 # after two stream files of the new mission
            raise Boom("disk full")
        return real(path, text)
    monkeypatch.setattr(io_write, "_write_atomic", failing)
    from aqfg.commands import import_ as imp
    monkeypatch.setattr(imp, "import_log", lambda fmt, source, imap, base=None: type(
        "R", (), {"mission": load_mission(src), "summary": lambda self: ""})())
    assert main(["import", "ros2", str(src), "--out", str(out), "--force"]) == 1
    assert calls["n"] == 3
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
