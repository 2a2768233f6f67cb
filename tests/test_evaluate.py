"""aqfg.evaluate: metrics against truth on hand-made tracks with known answers."""
import numpy as np
import pytest

from aqfg import evaluate as ev
from aqfg.data.mission import Truth
from aqfg.model.vehicle import Model
from aqfg.result import Track


def _truth(t, pos, **params):
    return Truth(t=t, pos=pos, params=params)


def _line(t, offset=(0.0, 0.0, 0.0)):
    pos = np.column_stack([t, 2 * t, np.zeros_like(t)]) + np.asarray(offset)
    return pos


def test_position_error_constant_offset_horizontal_and_3d():
    t = np.arange(0.0, 10.01, 0.1)
    truth = _truth(t, _line(t))
    tr = Track(t[::10], _line(t[::10], (3.0, 4.0, 12.0)), np.zeros((len(t[::10]), 3)))
    tt, e = ev.position_error(tr, truth)
    assert np.allclose(tt, t[::10])
    assert np.allclose(e, 5.0)
    _, e3 = ev.position_error(tr, truth, horizontal=False)
    assert np.allclose(e3, 13.0)
    assert ev.rmse(tr, truth) == pytest.approx(5.0)


def test_position_error_interpolates_truth_and_track_and_drops_outside():
    t_true = np.arange(0.0, 10.01, 0.1)
    truth = _truth(t_true, _line(t_true))
    t_tr = np.array([-1.0, 0.5, 2.0, 11.0])
    tr = Track(t_tr, _line(t_tr), np.zeros((4, 3)))
    tt, e = ev.position_error(tr, truth, t=np.array([-0.5, 1.0, 1.7, 10.5]))
    assert np.allclose(tt, [1.0, 1.7])             # outside the truth span: dropped
    assert np.allclose(e, 0.0, atol=1e-12)         # straight line: exact under interpolation


def test_rmse_window_and_values():
    t = np.arange(0.0, 10.0, 1.0)
    truth = _truth(t, np.zeros((10, 3)))
    pos = np.zeros((10, 3))
    pos[:, 0] = np.where(t < 5, 1.0, 3.0)
    tr = Track(t, pos, np.zeros((10, 3)))
    assert ev.rmse(tr, truth) == pytest.approx(np.sqrt((5 * 1 + 5 * 9) / 10))
    assert ev.rmse(tr, truth, t_from=5.0) == pytest.approx(3.0)
    assert ev.rmse(tr, truth, t_to=4.0) == pytest.approx(1.0)
    assert np.isnan(ev.rmse(tr, truth, t_from=100.0))


def test_bad_track_is_named():
    t = np.arange(3.0)
    with pytest.raises(ValueError, match="pos"):
        ev.position_error(Track(t, np.zeros((3, 2)), np.zeros((3, 3))), _truth(t, np.zeros((3, 3))))
    with pytest.raises(ValueError, match="non-decreasing"):
        ev.position_error(Track(t[::-1], np.zeros((3, 3)), np.zeros((3, 3))),
                          _truth(t, np.zeros((3, 3))))


def test_time_since_fix_and_between_fixes():
    t = np.arange(0.0, 12.0, 1.0)
    fix = np.array([2.0, 6.0])
    since = ev.time_since_fix(t, fix)
    assert np.all(np.isnan(since[:2]))
    assert np.allclose(since[2:], [0, 1, 2, 3, 0, 1, 2, 3, 4, 5])
    err = np.where(np.isnan(since), 0.0, since * 2.0)      # grows 2 m/s after each fix
    b = ev.error_between_fixes(t, err, fix)
    assert np.allclose(b.t0, fix)
    assert np.allclose(b.peak, [6.0, 10.0])
    assert np.allclose(b.mean, [3.0, 5.0])
    assert np.allclose(b.growth[:6], [0, 2, 4, 6, 8, 10])
    with pytest.raises(ValueError, match="same shape"):
        ev.error_between_fixes(t, err[:-1], fix)


def test_percentile_ignores_nan():
    x = np.concatenate([np.arange(1.0, 101.0), [np.nan]])
    assert ev.percentile(x, 95) == pytest.approx(np.percentile(np.arange(1.0, 101.0), 95))
    assert np.isnan(ev.percentile(np.array([np.nan])))


def test_param_errors_z_and_wrap():
    truth = {"theta_e": np.pi - 0.05, "k": 9.0, "s_x": 0.1}
    values = {"theta_e": -np.pi + 0.05, "k": 9.5, "s_x": 0.1}
    sigma = {"theta_e": 0.05, "k": 0.25}
    pe = ev.param_errors(values, sigma, truth, ["theta_e", "k", "s_x"])
    assert pe.error == pytest.approx([0.1, 0.5, 0.0])
    assert pe.z[:2] == pytest.approx([2.0, 2.0])
    assert np.isnan(pe.z[2])                               # no sigma reported
    assert pe.as_dict()["k"]["z"] == pytest.approx(2.0)
    with pytest.raises(KeyError, match="k_x"):
        ev.param_errors(values, sigma, truth, ["k_x"])


def test_consistency_on_honest_and_overconfident_samples():
    rng = np.random.default_rng(0)
    z = rng.standard_normal(20000)
    c = ev.consistency(np.concatenate([z, [np.nan]]))
    assert c["n"] == 20000
    assert c["rms"] == pytest.approx(1.0, abs=0.02)
    assert c["within2"] == pytest.approx(0.954, abs=0.01)
    c3 = ev.consistency(3 * z)
    assert c3["rms"] == pytest.approx(3.0, abs=0.06)
    assert c3["within2"] < 0.55
    assert ev.consistency(np.array([np.nan]))["n"] == 0


def test_heading_truth_with_drift():
    t = np.array([10.0, 20.0])
    assert ev.heading_truth({"theta_e": 0.5}, t) == pytest.approx([0.5, 0.5])
    h = ev.heading_truth({"theta_e": 0.5, "heading_drift.rate": 1e-3}, t, t0=10.0)
    assert h == pytest.approx([0.5, 0.51])


def test_summary():
    s = ev.summary([1.0, 2.0, 3.0, np.nan])
    assert s["mean"] == pytest.approx(2.0) and s["std"] == pytest.approx(1.0)
    assert s["n"] == 3 and s["n_nan"] == 1 and s["median"] == pytest.approx(2.0)
    assert ev.summary([np.nan])["n"] == 0


def test_inertial_rmse_zero_with_true_parameters_and_positive_with_wrong_ones():
    from tests.ekf_synth import synth_mission
    m, p_true, tr = synth_mission("asv", duration=60.0, seed=3, gnss_period=2.0,
                                  sigma_gnss=1e-6)
    truth = Truth(t=tr.t, pos=tr.pos, vel=tr.vel)
    model = Model.for_mission(m)
    assert ev.inertial_rmse(model, m, p_true, truth) < 0.05
    p_bad = p_true.copy()
    p_bad[0] += 0.3                                        # 17 deg heading error
    assert ev.inertial_rmse(model, m, p_bad, truth) > 2.0
