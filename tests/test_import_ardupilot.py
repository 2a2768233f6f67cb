"""ArduPilot logs: the PWM range and reversal from the log's own SERVOn parameters, depth
from the tlog's messages, and a log without a GNSS fix imported with a warning."""
from __future__ import annotations

import log_writers as lw
import numpy as np
import pytest

from aqfg.data.importers import import_log, parse_map
from aqfg.data.io import MissionWarning
from aqfg.sim import simulate

try:
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

pytest.importorskip("pymavlink")
SERVO = {1: (1100.0, 1500.0, 1900.0, 0), 3: (1000.0, 1520.0, 2000.0, 1)}   # min trim max rev


@pytest.fixture(scope="module")
def sim():
    return simulate("asv", seed=3, duration=120.0)[0]


def imap_for(m, **tables):
    return parse_map(tomllib.loads(lw.map_toml(m, **tables)), "map.toml")


def servo_pwm(u, c):
    lo, mid, hi, rev = SERVO[c]
    v = -u if rev else u
    return np.where(v >= 0, mid + v * (hi - mid), mid + v * (mid - lo))


def params():
    return [(f"SERVO{c}_{k}", float(v)) for c, vals in SERVO.items()
            for k, v in zip(("MIN", "TRIM", "MAX", "REVERSED"), vals)]


def test_tlog_servo_parameters_give_range_and_reversal(sim, tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    m = sim
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    recs = lw.tlog_records(m)
    servo = [msg for _, msg in recs if msg.get_type() == "SERVO_OUTPUT_RAW"]
    for msg, u in zip(servo, m.motors.u):
        msg.servo1_raw = int(np.rint(servo_pwm(u[0], 1)))
        msg.servo3_raw = int(np.rint(servo_pwm(u[1], 3)))
    first = recs[0][0]
    recs = [(first, mav.param_value_encode(name.encode(), v, 9, 100, i))
            for i, (name, v) in enumerate(params())] + recs
    r = import_log("mavlink", lw.write_tlog(tmp_path / "a.tlog", recs),
                   imap_for(m, motors="channels = [1, 3]"))
    np.testing.assert_allclose(r.mission.motors.u, m.motors.u, atol=1.25e-3)
    assert any("SERVOn_REVERSED" in n for n in r.notes)


def test_dataflash_parm_gives_range_and_reversal(sim, tmp_path):
    m = sim
    recs = lw.dataflash_records(m)
    for rec in recs:
        if rec[1] == "RCOU":
            i = int(np.argmin(np.abs(m.motors.t - (rec[0] * 1e-6 - 20.0))))
            rec[2][1] = float(np.rint(servo_pwm(m.motors.u[i, 0], 1)))
            rec[2][3] = float(np.rint(servo_pwm(m.motors.u[i, 1], 3)))
    t0 = recs[0][0]
    recs = [(t0, "PARM", [t0, name, v]) for name, v in params()] + recs
    r = import_log("mavlink", lw.write_dataflash(tmp_path / "a.bin", recs),
                   imap_for(m, motors="channels = [1, 3]"))
    np.testing.assert_allclose(r.mission.motors.u, m.motors.u, atol=1.25e-3)
    # a map's own range wins over the log's parameters
    r = import_log("mavlink", tmp_path / "a.bin", imap_for(
        m, motors="channels = [1, 3]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"))
    assert np.abs(r.mission.motors.u - m.motors.u).max() > 0.1


def test_auv_depth_from_global_position_int(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    m, _ = simulate("auv", seed=4, duration=120.0)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    recs = lw.tlog_records(m)
    # depth 1 Hz as GLOBAL_POSITION_INT.relative_alt (mm up) and, lower priority, VFR_HUD
    extra = [(round((lw.T_BASE + t) * 1e6), mav.global_position_int_encode(
        int(t * 1000), 0, 0, 0, int(round(-d * 1000)), 0, 0, 0, 0))
        for t, d in zip(m.depth.t, m.depth.depth)]
    extra += [(u, mav.vfr_hud_encode(0, 0, 0, 0, 99.0, 0)) for u, _ in extra]
    recs = sorted(recs + extra, key=lambda r: r[0])
    r = import_log("mavlink", lw.write_tlog(tmp_path / "a.tlog", recs),
                   imap_for(m, motors=lw_pwm_map(m)))
    d = r.mission.depth
    assert r.series["depth"].topic == "GLOBAL_POSITION_INT"
    np.testing.assert_allclose(d.t, m.depth.t, atol=1e-6)
    np.testing.assert_allclose(d.depth, m.depth.depth, atol=1e-3)


def lw_pwm_map(m):
    chans = ", ".join(str(c) for c in range(1, m.n_thrusters + 1))
    return f"channels = [{chans}]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"


def test_log_without_fix_is_imported_with_a_warning(sim, tmp_path):
    m = sim
    recs = lw.tlog_records(m)
    for _, msg in recs:
        if msg.get_type() == "GPS_RAW_INT":
            msg.fix_type = 1
    with pytest.warns(MissionWarning, match="no GNSS fix in GPS_RAW_INT"):
        r = import_log("mavlink", lw.write_tlog(tmp_path / "a.tlog", recs),
                       imap_for(m, motors="channels = [1, 3]\npwm_min = 1100\n"
                                          "pwm_trim = 1500\npwm_max = 1900"))
    assert r.mission.gnss is None and len(r.mission.motors.t) == len(m.motors.t)
