"""The online causal track's kinematic floor (aqfg.fg.kinematic): a constant-velocity
Kalman filter on the fixes."""
from __future__ import annotations

import numpy as np

from aqfg.fg.kinematic import KinematicFilter, baseline_tracks, track_from, transition


def test_transition_is_the_double_integrators():
    """Q by quadrature of F(s) G q G^T F(s)^T over the interval, F x by kinematics."""
    dt, q = 2.5, 0.3
    F, Q = transition(dt, q)
    np.testing.assert_allclose(F @ np.array([1.0, 2.0, 0.5, -1.0]), [2.25, -0.5, 0.5, -1.0])
    s = np.linspace(0.0, dt, 20001)
    g = np.stack([s, np.ones_like(s)])                     # (pos, vel) response to a kick
    y = g[:, None, :] * g[None, :, :]
    num = q * np.sum(0.5 * (y[..., 1:] + y[..., :-1]) * np.diff(s), axis=2)   # trapezoid rule
    np.testing.assert_allclose(Q[np.ix_([0, 2], [0, 2])], num, rtol=1e-6)
    np.testing.assert_allclose(Q[np.ix_([1, 3], [1, 3])], num, rtol=1e-6)
    assert Q[0, 1] == Q[0, 3] == 0.0


def test_it_learns_a_constant_velocity_from_noisy_fixes():
    rng = np.random.default_rng(3)
    v = np.array([1.2, -0.7])
    kf = KinematicFilter(q=0.01)
    for t in np.arange(0.0, 60.0, 4.0):
        kf.update(t, v * t + rng.normal(0.0, 1.0, 2), 1.0)
    np.testing.assert_allclose(kf.x[2:], v, atol=0.1)
    np.testing.assert_allclose(kf.at(70.0)[:2], v * 70.0, atol=2.0)
    assert np.all(np.linalg.eigvalsh(kf.P) > 0)


def test_an_outlier_is_left_out_until_max_rejects_in_a_row():
    kf = KinematicFilter(q=0.01, max_rejects=2)
    for t in range(10):
        assert kf.update(float(t), np.array([float(t), 0.0]), 0.25)
    x_before = kf.x.copy()
    assert not kf.update(10.0, np.array([10.0, 30.0]), 0.25)     # a 30-m jump: left out
    np.testing.assert_allclose(kf.x[:2], x_before[:2] + x_before[2:], atol=1e-9)
    assert not kf.update(11.0, np.array([11.0, 30.0]), 0.25)
    assert kf.update(12.0, np.array([12.0, 30.0]), 0.25)          # the third in a row: taken
    assert kf.x[1] > 5.0


def test_track_from_predicts_each_time_from_the_last_record_before_it():
    log_t = np.array([0.0, 10.0])
    log_x = np.array([[0.0, 0.0, 1.0, 0.0], [12.0, 0.0, 0.0, 2.0]])
    out = track_from(log_t, log_x, np.array([0.0, 4.0, 10.0, 13.0]))
    np.testing.assert_allclose(out[:, :2], [[0, 0], [4, 0], [12, 0], [12, 6]])
    np.testing.assert_allclose(out[:, 2:], [[1, 0], [1, 0], [0, 2], [0, 2]])


def test_the_floor_is_the_filter_while_held_and_the_model_after():
    """CausalFloor: fixes of a vehicle at 1 m/s north, every 2 s; the fix that finds the
    parameters released hands the track to the model, once. Before it every knot is the
    filter's prediction from the fixes so far; from it, the model's (untouched)."""
    from aqfg.fg.kinematic import CausalFloor
    t = np.arange(0.0, 22.0, 2.0)
    pos = np.column_stack([t, np.zeros_like(t)])
    fixes = (t, pos, np.full(len(t), 0.25))
    fl = CausalFloor(KinematicFilter(q=0.1))
    switched = [fl.step(float(tk), fixes, held=k < 9) for k, tk in enumerate(t)]
    assert fl.until == t[9] and switched == [False] * 9 + [True, False]
    assert len(fl.t) == 9 and fl.next_row == 10          # fed up to the switch, no further
    knots = np.arange(0.0, 21.0, 1.0)
    X = np.full((len(knots), 6), 7.0)
    fl.apply(knots, X)
    followed = knots < t[9]
    K = track_from(np.array(fl.t), np.array(fl.x), knots[followed])         # the filter's
    np.testing.assert_array_equal(X[followed][:, [0, 1, 3, 4]], K)
    np.testing.assert_allclose(X[followed, 0], knots[followed], atol=2.0)
    assert np.all(X[followed][:, [2, 5]] == 7.0)                            # depth: model's
    assert np.all(X[~followed] == 7.0)                                      # the model's
    # no hold at all (until at the first fix): nothing recorded, nothing replaced
    fl0 = CausalFloor(KinematicFilter(q=0.1), until=float(t[0]))
    assert not any(fl0.step(float(tk), fixes, held=False) for tk in t)
    X0 = np.full((len(knots), 6), 7.0)
    fl0.apply(knots, X0)
    assert np.all(X0 == 7.0)


def test_the_floor_carries_the_track_only_where_it_predicted_the_fixes_better():
    """A boat at rest for 8 s, then accelerating at 1 m/s^2 north, fixes every 2 s (sigma
    0.3 m). A model that predicts the fixes (knows the thrust) keeps the track: at rest the
    two predict alike, within the fixes' noise; a model 5 m off hands it to the filter
    while that predicts better (at rest), not once the filter falls further behind. The
    first fix, which nothing has predicted yet, leaves the model."""
    from aqfg.fg.kinematic import CausalFloor
    t = np.arange(0.0, 20.0, 2.0)
    north = np.where(t > 8.0, 0.5 * (t - 8.0) ** 2, 0.0)
    pos = np.column_stack([north, np.zeros_like(t)])
    fixes = (t, pos, np.full(len(t), 0.09))
    fl = CausalFloor(KinematicFilter(q=0.1))
    for tk in t:
        fl.step(float(tk), fixes, held=True)
    good = np.column_stack([pos, np.zeros((len(t), 4))])[1:]        # exact predictions
    ch = fl.chosen((t[1:], good))
    assert not ch.any()                               # the model throughout
    bad = good.copy()
    bad[:, 1] += 5.0
    ch = fl.chosen((t[1:], bad))
    assert not ch[0] and ch[(t > 0.0) & (t <= 8.0)].all() and not ch[t >= 16.0].any()
    knots = np.arange(0.0, 19.0, 1.0)
    X = np.full((len(knots), 6), 7.0)
    fl.apply(knots, X, (t[1:], good))
    assert np.all(X == 7.0)
    fl.apply(knots, X, (t[1:], bad))
    floor = ch[np.searchsorted(t, knots + 1e-9) - 1]  # after each fix the floor was chosen at
    assert floor[2] and not floor[:2].any()
    assert np.all(X[~floor] == 7.0) and not np.any(X[floor][:, 0] == 7.0)


def test_the_baseline_smoother_is_the_map_of_its_model_and_the_causal_track_the_filters():
    """With (almost) no process noise the Rauch-Tung-Striebel pass is the MAP straight line
    through the fixes under the filter's start (the first fix, the velocity prior of
    ``vel_sigma``), and the causal states are the filter's predictions from the fixes so
    far (:func:`track_from` of its records). A gated outlier moves neither."""
    rng = np.random.default_rng(5)
    tf = np.arange(0.0, 60.0, 4.0)
    pf = np.column_stack([3.0 + 0.8 * tf, -1.0 + 0.3 * tf]) + rng.normal(0.0, 0.7, (len(tf), 2))
    var = np.full(len(tf), 0.5)
    bad = pf.copy()
    bad[7] += 40.0                                    # left out by the gate
    t = np.concatenate([[-3.0], np.arange(0.0, 62.0, 0.7)])
    q = 1e-10
    causal, smooth = baseline_tracks((tf, bad, var), t, KinematicFilter(q=q))
    keep = np.arange(len(tf)) != 7
    # MAP line a + b t: fixes (variance var), b ~ N(0, 1) per axis (the filter's vel_sigma)
    A = np.vstack([np.column_stack([np.ones(keep.sum()), tf[keep]]) / np.sqrt(0.5), [[0.0, 1.0]]])
    for ax in range(2):
        y = np.concatenate([pf[keep, ax] / np.sqrt(0.5), [0.0]])
        a, b = np.linalg.lstsq(A, y, rcond=None)[0]
        np.testing.assert_allclose(smooth[1:, ax], a + b * t[1:], atol=1e-3)
        np.testing.assert_allclose(smooth[0, ax], a, atol=1e-3)   # before the first fix
        np.testing.assert_allclose(smooth[1:, 2 + ax], b, atol=1e-4)
    kf = KinematicFilter(q=q)
    rec_t, rec_x = [], []
    for i in range(len(tf)):
        kf.update(tf[i], bad[i], var[i])
        rec_t.append(tf[i])
        rec_x.append(kf.x.copy())
    np.testing.assert_allclose(causal[1:], track_from(np.array(rec_t), np.array(rec_x), t[1:]),
                               atol=1e-9)
    np.testing.assert_allclose(causal[0], rec_x[0])


def test_the_advantage_is_measured_in_sigma_of_the_fixes_noise():
    """Two predictions equally far from the true position (so neither is better), scored
    against noisy fixes of unequal precision: the advantage of one exceeds 2 sigma about as
    often as a normal variable does (2.3 %)."""
    from aqfg.fg.kinematic import advantage_z
    rng = np.random.default_rng(3)
    trials = 20000
    sigma = np.array([0.3, 3.0, 1.0])
    a = np.array([0.4, 0.1])                 # both 0.41 m from the truth (the origin)
    b = np.array([-0.1, 0.4])
    z = rng.normal(0.0, 1.0, (trials, 3, 2)) * sigma[None, :, None]
    d = np.sum((a - z) ** 2, axis=2) - np.sum((b - z) ** 2, axis=2)
    gap = np.full(3, np.sum((a - b) ** 2))
    zs = np.array([advantage_z(row, gap, sigma ** 2) for row in d])
    assert 0.015 < np.mean(zs > 2.0) < 0.032
    assert advantage_z(np.zeros(3), np.zeros(3), sigma ** 2) == 0.0


def test_one_precise_fix_outweighs_noisy_ones():
    """The filter 9 m closer at a GNSS fix (sigma 1 m) decides, although at two USBL fixes
    of 3-m sigma around it the model was a little closer."""
    from aqfg.fg.kinematic import advantage_z
    z = advantage_z(np.array([-14.6, 15.6, 77.4]), np.array([52.0, 138.4, 90.8]),
                    np.array([10.0, 9.1, 1.0]))
    assert z > 3.0


def test_a_model_within_the_noise_of_the_floor_keeps_the_track():
    """A boat at rest: the fix wanders 0.23 m in 8.5 s (fixes' sigma 0.08 m); the model
    predicts 0.06 m from the filter, 0.13 m further from the fix. The noise explains that;
    the model, which knows the thrust of the next interval, keeps the track."""
    from aqfg.fg.kinematic import CausalFloor
    t = np.array([0.0, 8.5])
    pos = np.array([[0.0, 0.0], [0.17, -0.15]])
    fl = CausalFloor(KinematicFilter(q=0.1))
    for tk in t:
        fl.step(float(tk), (t, pos, np.full(2, 0.0064)), held=True)
    model = np.array([[0.02, 0.06, 0.0, 0.0, 0.0, 0.0]])
    assert not fl.chosen((t[1:], model))[1]
    far = model.copy()
    far[0, :2] = [-1.0, 1.0]                 # 1.6 m off: the floor
    assert fl.chosen((t[1:], far))[1]
