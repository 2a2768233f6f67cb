"""The simulator: determinism, the shared model, hidden effects, sensor noise, the CLI."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.data import io
from aqfg.model import params
from aqfg.sim import simulator as sim
from aqfg.cli import main as cli_main
from aqfg.model.effects import BUILTIN
from aqfg.model.reference import wrap_angle
from aqfg.model.vehicle import Model, quat_to_rot, yaw_of
from aqfg.model.retrace import rollout
from aqfg.sim.plan import depth_reference

DYN_EFFECTS = ("thrust_asymmetry", "reverse_thrust", "thrust_lag", "linear_drag",
               "heading_drift", "current_drift", "wind_drag")


def p_true(truth) -> np.ndarray:
    return params.vector({k: v for k, v in truth.params.items() if k in params.INDEX})


def arrays(mission, truth) -> dict[str, np.ndarray]:
    out = {"imu.q": mission.imu.q, "imu.acc": mission.imu.acc, "imu.gyro": mission.imu.gyro,
           "motors.u": mission.motors.u, "truth.pos": truth.pos, "truth.vel": truth.vel,
           "truth.yaw": truth.yaw}
    if mission.gnss is not None:
        out["gnss.ne"] = mission.gnss.ne
    if mission.usbl is not None:
        out["usbl.range"], out["usbl.bearing"] = mission.usbl.range, mission.usbl.bearing
    if mission.depth is not None:
        out["depth"] = mission.depth.depth
    return out


def rollout_errors(mission, truth, p, span=5.0, every=10.0, effects=None):
    """End-of-window position errors (m) of span-s model rollouts from the true state."""
    model = Model.for_mission(mission, truth.params["effects"] if effects is None else effects)
    errs = []
    for t0 in np.arange(5.0, truth.t[-1] - span, every):
        i0 = int(round(t0 * 10))
        i1 = i0 + int(round(span * 10))
        x0 = np.concatenate([truth.pos[i0], truth.vel[i0]])
        trk = rollout(model, mission, p, x0, truth.t[i0], truth.t[i0 + 1:i1 + 1])
        errs.append(np.linalg.norm(trk.pos[-1] - truth.pos[i1]))
    return np.array(errs)


@pytest.fixture(scope="module")
def asv():
    return sim.simulate("asv", seed=4, duration=300.0, usbl=True)


@pytest.fixture(scope="module")
def auv():
    return sim.simulate("auv", seed=4, duration=300.0, usbl=True)


@pytest.fixture(scope="module")
def asv_all_dyn():
    """An ASV with every dynamics effect on (defaults)."""
    return sim.simulate("asv", seed=5, duration=240.0, effects={e: None for e in DYN_EFFECTS})


# ---------------------------------------------------------------- determinism
def test_same_seed_same_arrays_different_seed_differs():
    a = sim.simulate("asv", seed=7, duration=60.0, usbl=True)
    b = sim.simulate("asv", seed=7, duration=60.0, usbl=True)
    c = sim.simulate("asv", seed=8, duration=60.0, usbl=True)
    A, B, C = arrays(*a), arrays(*b), arrays(*c)
    for k in A:
        assert np.array_equal(A[k], B[k]), k
        assert not np.array_equal(A[k], C[k]), k
    assert a[1].params == b[1].params


def test_switching_a_sensor_leaves_other_streams_unchanged():
    a = sim.simulate("asv", seed=3, duration=60.0, usbl=False)
    b = sim.simulate("asv", seed=3, duration=60.0, usbl=True, gnss_period=None)
    assert b[0].gnss is None and a[0].usbl is None
    assert np.array_equal(a[0].imu.q, b[0].imu.q)
    assert np.array_equal(a[1].pos, b[1].pos)


# ---------------------------------------------------------------- the shared model
@pytest.mark.parametrize("case", ["asv", "auv", "asv_all_dyn"])
def test_truth_obeys_the_shared_model(case, request):
    """5 s model rollouts from the true state with the recorded inputs (noisy IMU attitude)
    land within centimetres of the truth; with k off by 20 % they do not."""
    mission, truth = request.getfixturevalue(case)
    p = p_true(truth)
    err = rollout_errors(mission, truth, p)
    assert len(err) >= 20
    assert err.max() < 0.06, err.max()
    p_bad = p.copy()
    p_bad[params.INDEX["k"]] *= 1.2
    assert np.median(rollout_errors(mission, truth, p_bad)) > 10 * np.median(err)


@pytest.mark.parametrize("effect", DYN_EFFECTS)
def test_each_dynamics_effect_is_in_the_truth(effect, asv_all_dyn):
    """Dropping one hidden effect from the model (its parameters at null) makes the model's
    predictions of the truth clearly worse."""
    mission, truth = asv_all_dyn
    p = p_true(truth)
    base = np.sqrt(np.mean(rollout_errors(mission, truth, p) ** 2))
    p_null = p.copy()
    for n in BUILTIN[effect].params:
        p_null[params.INDEX[n]] = params.SPEC[n].null
    worse = np.sqrt(np.mean(rollout_errors(mission, truth, p_null) ** 2))
    assert worse > 3 * base + 0.02, (effect, base, worse)


# ---------------------------------------------------------------- attitude
def test_reported_yaw_is_true_yaw_minus_theta(asv):
    mission, truth = asv
    k = np.searchsorted(mission.imu.t, truth.t - 1e-9)          # IMU rows at truth times
    assert np.allclose(mission.imu.t[k], truth.t)
    reported = yaw_of(quat_to_rot(mission.imu.q[k]))
    off = wrap_angle(truth.yaw - reported - truth.params["theta_e"])
    assert np.abs(off).max() < 1e-6
    # roll/pitch carry ~0.3 deg noise plus the wobble, but stay small
    R = quat_to_rot(mission.imu.q)
    assert np.degrees(np.arcsin(np.abs(R[:, 2, 0]))).max() < 6.0


def test_heading_drift_makes_the_offset_grow():
    rate = 1e-3
    mission, truth = sim.simulate("asv", seed=2, duration=200.0,
                                  effects={"heading_drift": rate})
    k = np.searchsorted(mission.imu.t, truth.t - 1e-9)
    off = np.unwrap(truth.yaw - yaw_of(quat_to_rot(mission.imu.q[k])))
    expected = truth.params["theta_e"] + rate * truth.t
    assert np.abs(wrap_angle(off - expected)).max() < 1e-6
    assert off[-1] - off[0] == pytest.approx(rate * 200.0, rel=1e-6)


# ---------------------------------------------------------------- hidden effects
def test_thrust_asymmetry_changes_track_and_commands():
    a_m, a_t = sim.simulate("asv", seed=6, duration=200.0)
    b_m, b_t = sim.simulate("asv", seed=6, duration=200.0, effects={"thrust_asymmetry": 0.8})
    assert b_t.params["thrust_asymmetry.ratio"] == 0.8
    assert b_t.params["effects"] == ["thrust_asymmetry"]
    assert np.linalg.norm(a_t.pos - b_t.pos, axis=1).max() > 3.0
    # holding a straight course, the controller must run the weaker starboard propeller
    # faster: zero yaw moment needs u_s / u_p = sqrt(1 / 0.8) = 1.118
    def straight_ratio(m, t):
        rate = np.abs(wrap_angle(np.diff(t.yaw))) / 0.1
        u = m.motors.u
        ok = (rate < 0.02) & (u.min(axis=1) > 0.15)
        assert ok.sum() > 100
        return np.median(u[ok, 1] / u[ok, 0])
    assert straight_ratio(a_m, a_t) == pytest.approx(1.0, abs=0.02)
    assert straight_ratio(b_m, b_t) == pytest.approx(np.sqrt(1 / 0.8), abs=0.02)


def test_reverse_thrust_acts_only_on_negative_commands():
    a_m, a_t = sim.simulate("asv", seed=6, duration=200.0)
    b_m, b_t = sim.simulate("asv", seed=6, duration=200.0, effects={"reverse_thrust": 0.5})
    neg = np.flatnonzero((a_m.motors.u < 0).any(axis=1))
    assert len(neg), "the mission must have negative commands"
    t_neg = a_m.motors.t[neg[0]]
    before = a_t.t <= t_neg + 1e-9
    assert np.array_equal(a_t.pos[before], b_t.pos[before])
    assert np.linalg.norm(a_t.pos - b_t.pos, axis=1).max() > 1.0


def test_thrust_lag_delays_the_start_and_linear_drag_slows_down():
    a = sim.simulate("asv", seed=6, duration=120.0)[1]
    lag = sim.simulate("asv", seed=6, duration=120.0, effects={"thrust_lag": 0.8})[1]
    drag = sim.simulate("asv", seed=6, duration=120.0, effects={"linear_drag": None})[1]
    i = 10                                            # t = 1 s
    assert np.linalg.norm(lag.vel[i]) < 0.8 * np.linalg.norm(a.vel[i])
    s_a = np.median(np.linalg.norm(a.vel, axis=1))
    s_d = np.median(np.linalg.norm(drag.vel, axis=1))
    assert s_d < s_a - 0.02


def test_measurement_effects_change_only_the_measurements():
    kw = dict(seed=9, duration=200.0, usbl=True, usbl_outlier_rate=0.0)
    a_m, a_t = sim.simulate("asv", **kw)
    scale, bias, arm = 1.03, 0.04, 0.5
    b_m, b_t = sim.simulate("asv", effects={"usbl_range_scale": scale,
                                            "usbl_bearing_bias": bias,
                                            "lever_arm": {"x": arm}}, **kw)
    assert np.array_equal(a_t.pos, b_t.pos)               # dynamics untouched
    assert np.array_equal(a_m.imu.q, b_m.imu.q)
    assert b_t.params["lever_arm.y"] == 0.0 and b_t.params["lever_arm.z"] == 0.0
    # range scale and bearing bias, on top of the lever-arm shift
    c_m, _ = sim.simulate("asv", effects={"lever_arm": {"x": arm}}, **kw)
    ratio = (b_m.usbl.range - c_m.usbl.range) / c_m.usbl.range
    assert np.median(ratio) == pytest.approx(scale - 1.0, abs=5e-4)
    assert np.abs(ratio - (scale - 1.0)).max() < 0.01
    assert np.allclose(wrap_angle(b_m.usbl.bearing - c_m.usbl.bearing), bias, atol=1e-9)
    # lever arm: fixes move by R l (horizontal), l along body x
    k = np.searchsorted(a_t.t, a_m.gnss.t - 1e-9)
    yaw = a_t.yaw[k]
    shift = c_m.gnss.ne - a_m.gnss.ne
    expected = arm * np.column_stack([np.cos(yaw), np.sin(yaw)])
    assert np.abs(shift - expected).max() < 0.02 * arm     # cos(pitch) ~ 1


def test_a_time_offset_delays_only_its_stream():
    """gnss_delay: each (noise-free) GNSS fix is the true position 0.8 s before its stamp,
    about 0.8 s x the speed away from the position at the stamp; USBL and the truth are
    untouched."""
    kw = dict(seed=9, duration=120.0, usbl=True, usbl_outlier_rate=0.0, gnss_sigma=0.0)
    a_m, a_t = sim.simulate("asv", **kw)
    b_m, b_t = sim.simulate("asv", effects={"gnss_delay.tau": 0.8}, **kw)
    assert np.array_equal(a_t.pos, b_t.pos) and np.array_equal(a_m.usbl.range, b_m.usbl.range)
    tt = b_m.gnss.t[b_m.gnss.t >= 1.0]
    late = b_m.gnss.ne[b_m.gnss.t >= 1.0]
    true_then = np.column_stack([np.interp(tt - 0.8, a_t.t, a_t.pos[:, j]) for j in (0, 1)])
    assert np.abs(late - true_then).max() < 0.02        # 10-Hz truth, linear between ticks
    speed = np.hypot(*np.diff(a_t.pos[:, :2], axis=0).T).mean() / np.diff(a_t.t).mean()
    assert np.hypot(*(late - np.column_stack([np.interp(tt, a_t.t, a_t.pos[:, j])
                                              for j in (0, 1)])).T).mean() > 0.5 * 0.8 * speed


# ---------------------------------------------------------------- sensor noise
def test_gnss_noise_std_is_sigma():
    mission, truth = sim.simulate("asv", seed=11, duration=600.0, gnss_sigma=2.0)
    k = np.searchsorted(truth.t, mission.gnss.t - 1e-9)
    res = mission.gnss.ne - truth.pos[k, :2]
    assert np.all(mission.gnss.sigma == 2.0)
    assert np.std(res, axis=0) == pytest.approx([2.0, 2.0], rel=0.1)
    assert np.abs(np.mean(res, axis=0)).max() < 0.3


def test_usbl_noise_and_outlier_fraction():
    rate = 0.2
    mission, truth = sim.simulate("asv", seed=12, duration=600.0, usbl=True, usbl_period=1.0,
                                  usbl_outlier_rate=rate, gnss_period=None)
    u = mission.usbl
    st = mission.usbl_station
    pos = np.column_stack([np.interp(u.t, truth.t, truth.pos[:, i]) for i in range(3)])
    d = pos - st
    r_true = np.linalg.norm(d, axis=1)
    b_true = np.arctan2(d[:, 1], d[:, 0])
    dr, db = u.range - r_true, wrap_angle(u.bearing - b_true)
    out = (np.abs(dr) > 5.0) | (np.abs(db) > np.radians(8.0))
    assert out.mean() == pytest.approx(rate, abs=0.05)
    assert np.std(dr[~out]) == pytest.approx(0.15, rel=0.2)
    assert np.std(db[~out]) == pytest.approx(np.radians(1.5), rel=0.2)
    assert np.all(u.range > 0) and np.all(np.abs(u.bearing) <= np.pi)


def test_usbl_ranges_are_tens_of_metres(asv, auv):
    for mission, _ in (asv, auv):
        r = mission.usbl.range
        assert np.percentile(r, 5) > 8.0 and np.percentile(r, 95) < 160.0
        assert np.allclose(mission.usbl_station, [0.0, 0.0, 1.5])


# ---------------------------------------------------------------- vehicles and control
@pytest.mark.parametrize("case", ["asv", "auv"])
def test_commands_and_speeds(case, request):
    mission, truth = request.getfixturevalue(case)
    u = mission.motors.u
    assert np.all(np.abs(u) <= 1.0)
    assert np.all(np.diff(mission.motors.t) > 0)
    assert (u[:, :2] < -0.05).any(), "sharp turns must run a propeller backwards"
    speed = np.linalg.norm(truth.vel, axis=1)
    assert speed[0] == 0.0                                  # starts at rest
    assert 0.5 <= np.median(speed) <= 1.5
    assert np.percentile(speed, 99) < 2.5


def test_asv_stays_on_the_surface(asv):
    mission, truth = asv
    assert mission.depth is None and mission.n_thrusters == 2
    assert np.all(truth.pos[:, 2] == 0.0) and np.all(truth.vel[:, 2] == 0.0)
    assert mission.thruster_pos[0, 1] < 0 < mission.thruster_pos[1, 1]   # port first


def test_auv_has_depth_five_thrusters_and_follows_its_profile(auv):
    mission, truth = auv
    assert mission.n_thrusters == 5 and mission.thruster_pos.shape == (5, 3)
    dirs = mission.thruster_dir
    assert (dirs[:, 2] == 1).sum() == 2 and (dirs[:, 1] == 1).sum() == 1
    assert (mission.motors.u[:, 2:4] != 0).any() and (mission.motors.u[:, 4] != 0).any()
    prof = np.array(truth.params["depth_profile"])
    z_ref, _ = depth_reference(prof, truth.t)
    late = truth.t > 30.0
    err = truth.pos[late, 2] - z_ref[late]
    assert np.percentile(np.abs(err), 95) < 0.3
    assert np.ptp(truth.pos[:, 2]) > 1.0
    k = np.searchsorted(truth.t, mission.depth.t - 1e-9)
    res = mission.depth.depth - truth.pos[k, 2]
    assert np.std(res) == pytest.approx(0.05, rel=0.25)


def test_custom_waypoints_are_visited_in_order():
    wps = np.array([[20.0, 20.0], [60.0, 20.0], [60.0, 50.0], [20.0, 50.0]])
    mission, truth = sim.simulate("asv", seed=1, duration=200.0, waypoints=wps)
    assert np.allclose(truth.pos[0, :2], wps[0])
    t_hit = []
    for w in wps[1:]:
        d = np.linalg.norm(truth.pos[:, :2] - w, axis=1)
        hit = np.flatnonzero(d < 3.0)
        assert len(hit), w
        t_hit.append(truth.t[hit[0]])
    assert np.all(np.diff(t_hit) > 0)


# ---------------------------------------------------------------- parameters
def test_truth_params_record_everything():
    _, truth = sim.simulate("asv", seed=2, duration=30.0, effects={"lever_arm.x": 0.3},
                            params={"theta_e": 0.1, "s_x": 0.0, "s_y": 0.05})
    tp = truth.params
    assert all(n in tp for n in params.NAMES)
    assert tp["effects"] == ["lever_arm"] and tp["seed"] == 2
    assert (tp["theta_e"], tp["s_x"], tp["s_y"]) == (0.1, 0.0, 0.05)
    assert tp["lever_arm.x"] == 0.3 and tp["lever_arm.y"] == 0.0
    assert tp["k"] == 9.26 and tp["k_x"] == 1.82 and tp["k_yz"] == 0.14


def test_theta_and_current_randomised_by_seed_fixed_params_not():
    t1 = sim.simulate("auv", seed=1, duration=5.0)[1].params
    t2 = sim.simulate("auv", seed=2, duration=5.0)[1].params
    assert t1["theta_e"] != t2["theta_e"] and t1["s_x"] != t2["s_x"]
    for tp in (t1, t2):
        assert abs(tp["theta_e"] - 0.5) <= 0.15
        assert 0.07 <= np.hypot(tp["s_x"], tp["s_y"]) <= 0.13
        assert (tp["k"], tp["k_x"], tp["k_yz"]) == (4.42, 0.55, 0.07)
    assert sim.true_params("asv")["k"] == 9.26 and sim.true_params("auv")["k_x"] == 0.55


def test_effect_values_normalisation_and_errors():
    assert sim.effect_values({"thrust_asymmetry": 0.8}) == {"thrust_asymmetry.ratio": 0.8}
    full = {"lever_arm.x": 0.3, "lever_arm.y": 0.0, "lever_arm.z": 0.0}
    assert sim.effect_values({"lever_arm": {"x": 0.3}}) == full
    assert sim.effect_values({"lever_arm.x": 0.3}) == full
    assert sim.effect_values({"lever_arm": [0.3, 0.0]}) == full
    assert sim.effect_values({"linear_drag": None}) == {
        "linear_drag.c_x": sim.EFFECT_DEFAULTS["linear_drag.c_x"],
        "linear_drag.c_yz": sim.EFFECT_DEFAULTS["linear_drag.c_yz"]}
    assert sim.effect_values(None) == {}
    with pytest.raises(KeyError, match="thrust_asymmetry"):        # lists the valid names
        sim.effect_values({"thrust_asymetry": 0.8})
    with pytest.raises(KeyError, match="x, y, z"):
        sim.effect_values({"lever_arm": {"w": 1.0}})
    with pytest.raises(ValueError, match="bounds"):
        sim.effect_values({"thrust_asymmetry": 50.0})
    with pytest.raises(ValueError, match="does not apply"):
        sim.simulate("auv", duration=5.0, effects={"wind_drag": None})
    with pytest.raises(KeyError, match="unknown parameter"):
        sim.simulate("asv", duration=5.0, params={"kk": 1.0})
    with pytest.raises(ValueError, match="vehicle"):
        sim.simulate("boat", duration=5.0)


# ---------------------------------------------------------------- CLI
def test_cli_writes_a_mission_that_loads_back(tmp_path, capsys):
    out = tmp_path / "m"
    rc = cli_main(["simulate", "--vehicle", "asv", "--effect", "thrust_asymmetry=0.8",
                   "--seed", "3", "--duration", "60", "--usbl", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    for s in ("imu", "motors", "gnss", "usbl", "truth"):
        assert s in text
    mission = io.load_mission(out)
    truth = io.load_truth(out)
    ref_m, ref_t = sim.simulate("asv", seed=3, duration=60.0, usbl=True,
                                effects={"thrust_asymmetry": 0.8})
    A, B = arrays(mission, truth), arrays(ref_m, ref_t)
    for k in B:
        assert np.array_equal(A[k], B[k]), k
    assert truth.params["thrust_asymmetry.ratio"] == 0.8
    assert truth.params["effects"] == ["thrust_asymmetry"]
    # refuses to overwrite without --force; --force works
    assert cli_main(["simulate", "--duration", "5", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert cli_main(["simulate", "--duration", "5", "--force", "--gnss-period", "0",
                     str(out)]) == 0
    assert io.load_mission(out).gnss is None


def test_cli_unknown_effect_lists_valid_names(tmp_path, capsys):
    assert cli_main(["simulate", "--effect", "bogus=1", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "bogus" in err and "thrust_lag" in err and "lever_arm.x" in err
    assert not (tmp_path / "x").exists()
