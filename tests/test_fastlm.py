"""The numpy form of the batch graph (aqfg.fg.fastlm) is the GTSAM graph's problem: the same
cost, gradient and Gauss-Newton Hessian at any values, and the same fit (values and sigmas)
as the LM driven on GTSAM's linearisation."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp

from aqfg.data.mission import with_gnss_every
from aqfg.fg.batch import BatchSmoother
from aqfg.fg.settings import FGSettings
from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast
from aqfg.fg.fit import fit_fg
from aqfg.sim.simulator import simulate


def gtsam_normal(bg, values, fs):
    """H = A^T A and g = A^T r of GTSAM's linearisation, in the numpy system's order."""
    gfg = bg.linearize(values)
    r, c, v = gfg.sparseJacobian_()
    r, c = r.astype(int) - 1, c.astype(int) - 1
    keys = sorted(bg.key_dims())
    col0, n = {}, 0
    for k, d in keys:
        col0[k] = n
        n += d
    isb = c == n
    b = np.zeros(r.max() + 1)
    b[r[isb]] = v[isb]
    A = sp.csr_matrix((v[~isb], (r[~isb], c[~isb])), shape=(len(b), n))
    perm = [col0[k] + j for p in bg.parts for k in p.keys for j in range(6)]
    perm += [col0[nd.key] + j for nd in bg.nodes for j in range(fs.node_off[nd.key][1])]
    perm = np.array(perm)
    H = (A.T @ A).toarray()[np.ix_(perm, perm)]
    return H, -(A.T @ b)[perm]


def dense(fs, D, E, Hsp, Hpp):
    Ns = 6 * fs.N
    H = np.zeros((Ns + fs.P, Ns + fs.P))
    for i in range(fs.N):
        H[6 * i:6 * i + 6, 6 * i:6 * i + 6] = D[i]
        if i < fs.N - 1:
            H[6 * i:6 * i + 6, 6 * i + 6:6 * i + 12] = E[i]
            H[6 * i + 6:6 * i + 12, 6 * i:6 * i + 6] = E[i].T
    H[:Ns, Ns:] = Hsp.reshape(Ns, -1)
    H[Ns:, :Ns] = Hsp.reshape(Ns, -1).T
    H[Ns:, Ns:] = Hpp
    return H


def assert_same_problem(bg, fs, values):
    """The numpy system at ``values`` has the graph's cost, Hessian and gradient."""
    X, th = fs.from_values(values)
    ev = fs.evaluate(X, th)
    assert ev["cost"] == pytest.approx(bg.error(values), rel=1e-12)
    H, g = gtsam_normal(bg, values, fs)
    D, E, Hsp, Hpp, gs, gp = fs.normal(ev)
    assert np.allclose(dense(fs, D, E, Hsp, Hpp), H, rtol=1e-10, atol=1e-10 * np.abs(H).max())
    assert np.allclose(np.concatenate([gs.ravel(), gp]), g, rtol=1e-10,
                       atol=1e-10 * np.abs(g).max())


def states_far(bg, values, rng):
    """``values`` (changed in place and returned) with every state moved far from where it
    was: the robust losses beyond their thresholds."""
    for p in bg.parts:
        for k in p.keys:
            values.update(k, values.atVector(k) + rng.normal(0, [5, 5, 0, .5, .5, 0]))
    return values


@pytest.fixture(scope="module")
def missions():
    out = []
    for seed in (2, 3):
        m, _ = simulate("asv", seed=seed, duration=150.0, usbl=True)
        out.append(with_gnss_every(m, 4.0))
    return out


@pytest.mark.parametrize("walk", [False, True])
def test_same_cost_gradient_hessian(missions, walk):
    st = (FGSettings().with_(graph={"walk_sigma": {"theta_e": 0.004}, "walk_segment": 60.0})
          if walk else FGSettings())
    bg = BatchSmoother(settings=st).build(missions)
    fs = FastSystem.build(bg, st)
    assert fs is not None
    values = bg.values
    rng = np.random.default_rng(0)
    for _ in range(2):
        assert_same_problem(bg, fs, values)
        values = states_far(bg, gtsam.Values(values), rng)


def test_process_scale_and_evidence(missions):
    """The process-noise factor scales the horizontal axes' noise of a planar vehicle
    (W^T W = (D Q D)^-1) and the log evidence is -cost - n/2 log q - 1/2 log det H of the
    dense Gauss-Newton Hessian."""
    st = FGSettings()
    bg = BatchSmoother(settings=st).build(missions[:1])
    fs = FastSystem.build(bg, st)
    assert fs is not None
    X, th = fs.from_values(bg.values)
    q = 4.0
    fs.set_process_scale(q)
    d = np.sqrt(np.array([q, q, 1.0, q, q, 1.0]))
    dt = float(bg.parts[0].knots[1] - bg.parts[0].knots[0])
    Q = st.graph.process.cov(dt, True)
    assert np.allclose(fs.WtW[0], np.linalg.inv(d[:, None] * Q * d[None, :]), rtol=1e-9)
    ev = fs.evaluate(X, th)
    D, E, Hsp, Hpp, _, _ = fs.normal(ev)
    ld = np.linalg.slogdet(dense(fs, D, E, Hsp, Hpp))[1]
    n_q = 4 * len(fs.d0)
    assert fs.log_evidence(ev) == pytest.approx(-ev["cost"] - 0.5 * n_q * np.log(q) - 0.5 * ld,
                                                rel=1e-9)


def test_held_parameters_and_the_states_evidence(missions):
    """``hold_params`` moves the states alone to their optimum given the parameters; the
    parts' evidence of their states given the parameters sums to the evidence without the
    parameters' block of log det H and their priors' cost, and follows each part's own
    process-noise factor."""
    st = FGSettings()
    bg = BatchSmoother(settings=st).build(missions)
    fs = FastSystem.build(bg, st)
    assert fs is not None
    X, th = fs.from_values(bg.values)
    ev0 = fs.evaluate(X, th)
    X1, th1, cost1, ev1, *_ = levenberg_marquardt_fast(fs, None, st, start=(X, th),
                                                       hold_params=True)
    assert np.array_equal(th1, th)
    assert cost1 < ev0["cost"]
    _, _, _, _, gs0, _ = fs.normal(ev0)
    D, E, Hsp, Hpp, gs, gp = fs.normal(ev1)
    assert np.linalg.norm(gs) < 1e-3 * np.linalg.norm(gs0)      # the states' optimum
    assert np.linalg.norm(gp) > 1e3 * np.linalg.norm(gs)         # not the parameters'
    H = dense(fs, D, E, Hsp, Hpp)
    Ns = 6 * fs.N
    ld_all, ld_states = np.linalg.slogdet(H)[1], np.linalg.slogdet(H[:Ns, :Ns])[1]
    parts = fs.part_log_evidence(ev1)
    assert len(parts) == 2
    assert np.sum(parts) - fs.log_evidence(ev1) == \
        pytest.approx(0.5 * (ld_all - ld_states) + 0.5 * ev1["lin_p"] @ ev1["lin_p"], rel=1e-7)
    # a factor on the second part alone changes the second part's evidence alone: by the
    # log det of its scaled process noise, its cost and its states' log det H
    fs.set_process_scale(1.0, per_part=np.array([1.0, 4.0]))
    ev4 = fs.evaluate(X1, th1)
    parts4 = fs.part_log_evidence(ev4)
    assert parts4[0] == pytest.approx(parts[0], rel=1e-12)
    D4, E4, *_ = fs.normal(ev4)
    H4 = dense(fs, D4, E4, Hsp, Hpp)
    o = fs.part_off[1]
    k2 = fs.d0 >= o
    sl = slice(6 * o, Ns)
    want = -0.5 * (fs.q_axes[k2].sum() * np.log(4.0)) - fs.state_cost(ev4)[o:].sum() \
        - 0.5 * np.linalg.slogdet(H4[sl, sl])[1]
    assert parts4[1] == pytest.approx(want, rel=1e-9)


def test_held_parameter_stays_when_another_meets_its_bound(missions):
    """A parameter held (``hold_params``, as the heading profile holds theta_e) keeps its
    value when the step of the free ones crosses their bounds and is re-solved with them
    at the bound."""
    st = FGSettings()
    bg = BatchSmoother(settings=st).build(missions)
    fs = FastSystem.build(bg, st)
    assert fs is not None
    X, th = fs.from_values(bg.values)
    # every free parameter boxed tightly around its start: any step crosses a bound
    fs.lo, fs.hi = th - 1e-6, th + 1e-6
    fs.lo[0], fs.hi[0] = -np.inf, np.inf
    X1, th1, *_ = levenberg_marquardt_fast(fs, None, st, start=(X, th), hold_params=[0],
                                           max_iterations=3)
    assert th1[0] == th[0]
    assert np.all(np.abs(th1 - th) <= 1e-6 + 1e-15)
    assert np.any(th1 != th)                                     # the free ones moved


@pytest.mark.slow
def test_same_fit_as_gtsam_path(missions):
    a = fit_fg(missions)
    b = fit_fg(missions, settings=FGSettings().with_(solver={"fast_lm": False}))
    assert a.iterations == b.iterations
    assert a.cost == pytest.approx(b.cost, rel=1e-9)
    for n in a.estimated:
        assert a.values[n] == pytest.approx(b.values[n], rel=1e-7, abs=1e-9), n
        assert a.sigma[n] == pytest.approx(b.sigma[n], rel=1e-6), n
        assert a.sigma_model[n] == pytest.approx(b.sigma_model[n], rel=1e-6), n


def test_usbl_distortions_keep_the_gtsam_path(missions):
    sm = BatchSmoother(effects=("usbl_range_scale",))
    bg = sm.build(missions[:1])
    assert FastSystem.build(bg, sm.settings) is None


@pytest.mark.parametrize("effects, walk", [
    (("gnss_delay",), False), (("lever_arm",), False), (("gnss_delay", "lever_arm"), True),
    (("lever_arm", "usbl_delay", "heading_drift"), True)])
def test_sensor_effects_same_cost_gradient_hessian(missions, effects, walk):
    """With a lever arm (rotated by the heading, so theta_e and a heading drift enter the
    fixes) or a fix time offset, the numpy system is still the GTSAM graph's problem, the
    parameters away from their start and the states far from theirs."""
    st = (FGSettings().with_(graph={"walk_sigma": {"theta_e": 0.004}, "walk_segment": 60.0})
          if walk else FGSettings())
    sm = BatchSmoother(effects=effects, settings=st)
    bg = sm.build(missions)
    fs = FastSystem.build(bg, sm.settings)
    assert fs is not None
    assert any(m.cols is not None and len(m.cols) for m in fs.meas)
    rng = np.random.default_rng(0)
    values = gtsam.Values(bg.values)
    for n in bg.nodes:
        values.update(n.key, values.atVector(n.key)
                      + rng.normal(0, 0.05, fs.node_off[n.key][1]))
    for _ in range(2):
        assert_same_problem(bg, fs, values)
        values = states_far(bg, values, rng)


def test_gnss_rows_are_the_gtsam_factors():
    """Each GNSS fix's whitened residual and Jacobian blocks (state, and the parameter
    nodes it reads: the lever arm, the time offset, the heading) are its GTSAM factor's
    linearisation, Huber reweighting included."""
    m, _ = simulate("asv", seed=4, duration=120.0, effects={"gnss_delay.tau": 0.6,
                                                            "lever_arm.x": -0.4})
    st = FGSettings().with_(graph={"walk_sigma": {"theta_e": 0.004}, "walk_segment": 50.0})
    sm = BatchSmoother(effects=("gnss_delay", "lever_arm", "heading_drift"), settings=st)
    bg = sm.build([m])
    fs = FastSystem.build(bg, sm.settings)
    assert fs is not None
    rng = np.random.default_rng(2)
    values = gtsam.Values(bg.values)
    for n in bg.nodes:
        values.update(n.key, values.atVector(n.key)
                      + rng.normal(0, 0.05, fs.node_off[n.key][1]))
    for k in bg.parts[0].keys:      # some fixes beyond the Huber threshold
        values.update(k, values.atVector(k) + rng.normal(0, [2, 2, 0, .3, .3, 0]))
    X, th = fs.from_values(values)
    ev = fs.evaluate(X, th)
    rows = {}
    for meas, (r, J, w, Jp) in zip(fs.meas, ev["meas"]):
        if meas.kind == "gnss":
            assert Jp is not None and meas.cols is not None and len(meas.cols) == 8
            for i, si in enumerate(meas.idx):
                rows[int(si)] = (r[i], J[i], w[i], Jp[i], meas.cols)
    assert len(rows) > 50
    state_of = {k: fs.state_index[k] for k in bg.parts[0].keys}
    col_of = {k: o for k, (o, _) in fs.node_off.items()}
    seen, reweighted = 0, 0
    for f in (bg.graph.at(i) for i in range(bg.graph.size())):
        if not isinstance(f, gtsam.CustomFactor) or f.dim() != 2:
            continue
        keys = list(f.keys())
        r, J, w, Jp, cols = rows[state_of[keys[0]]]
        A, b = f.linearize(values).jacobian()
        sw = np.sqrt(w)
        assert np.allclose(b, -sw * r, rtol=1e-12, atol=1e-12)
        assert np.allclose(A[:, :6], sw * J, rtol=1e-12, atol=1e-12)
        Ap = np.zeros((2, fs.P))
        Ap[:, cols] = sw * Jp
        c = 6
        for k in keys[1:]:
            d = fs.node_off[k][1]
            assert np.allclose(A[:, c:c + d], Ap[:, col_of[k]:col_of[k] + d],
                               rtol=1e-12, atol=1e-12)
            c += d
        assert np.count_nonzero(Ap) == np.count_nonzero(A[:, 6:])   # no column elsewhere
        seen += 1
        reweighted += w < 1.0
    assert seen == len(rows)
    assert reweighted > 0


def test_fit_recovers_a_simulated_gnss_delay():
    """A fit with gnss_delay on the numpy path finds the simulated 0.8-s time offset, and
    is the GTSAM path's fit."""
    m, _ = simulate("asv", seed=0, duration=600.0, effects={"gnss_delay.tau": 0.8})
    st = FGSettings().with_(batch={"adapt_noise": False, "adapt_track": False})
    bs = BatchSmoother(effects=("gnss_delay",), settings=st)
    assert FastSystem.build(bs.build([m]), bs.settings) is not None
    a = fit_fg([m], effects=("gnss_delay",), settings=st)
    tau, sig = a.values["gnss_delay.tau"], a.sigma["gnss_delay.tau"]
    assert abs(tau - 0.8) < 3.0 * sig, (tau, sig)
    assert tau > 4.0 * sig                                        # distinct from no delay
    b = fit_fg([m], effects=("gnss_delay",), settings=st.with_(solver={"fast_lm": False}))
    for n in a.estimated:
        assert a.values[n] == pytest.approx(b.values[n], rel=1e-6, abs=1e-4 * b.sigma[n]), n


def test_linear_terms_are_the_graphs_linear_factors(missions):
    """The numpy form of the priors, surface constraint and random walk is what GTSAM's
    factors linearise to (whitened A, b at zero) and evaluate to (whitened error)."""
    s = FGSettings().with_(graph={"walk_sigma": {"theta_e": 1e-8, "s_x": 0.003, "s_y": 0.003},
                                  "walk_segment": 40.0})
    bg = BatchSmoother(settings=s).build(missions)
    rng = np.random.default_rng(1)
    assert {t.kind for t in bg.linear} == {"prior", "linear", "between"}
    for t in bg.linear:
        f = t.factor()
        zero, at, x = gtsam.Values(), gtsam.Values(), {}
        for k, J in zip(t.keys, t.J):
            x[k] = 3.0 * rng.normal(size=J.shape[1])
            zero.insert(k, np.zeros(J.shape[1]))
            at.insert(k, x[k])
        A, b = f.linearize(zero).jacobian()
        assert np.array_equal(A, np.hstack(t.whitened_jacobians()))
        assert b == pytest.approx(t.mean / t.sigma, rel=1e-15, abs=0.0)
        assert f.error(at) == pytest.approx(0.5 * np.sum(t.whitened_residual(x) ** 2), rel=1e-12)


@pytest.mark.parametrize("lever", [True, False])
def test_sensor_positions_are_sensor_position_row_by_row(lever):
    """The vectorised sensor model of the numpy system is the per-fix one: position and
    Jacobians w.r.t. the state and every parameter, on both streams."""
    from aqfg.model.measurements import sensor_position, sensor_positions
    from aqfg.model.params import N_PARAMS, SLICE
    from aqfg.model.rotation import rot_z
    rng = np.random.default_rng(5)
    p = 0.3 * rng.normal(size=N_PARAMS)
    if not lever:
        p[SLICE["lever_arm"]] = 0.0
    X = rng.normal(size=(9, 6))
    R = np.array([rot_z(a) @ rot_z(b).T for a, b in rng.normal(size=(9, 2))])
    tm = rng.uniform(0.0, 300.0, 9)
    for stream in ("gnss", "usbl"):
        h, Jx, Jp = sensor_positions(X, R, tm, p, stream)
        for i in range(len(X)):
            hi, Jxi, Jpi = sensor_position(X[i], R[i], tm[i], p, stream)
            assert np.allclose(h[i], hi, rtol=1e-14, atol=1e-14)
            assert np.array_equal(Jx[i], Jxi)
            assert np.allclose(Jp[i], Jpi, rtol=1e-13, atol=1e-14)
            assert np.any(Jpi[:, SLICE[f"{stream}_delay"]] != 0.0)
            assert np.any(Jpi[:, SLICE["heading_drift"]] != 0.0) == lever


def test_structural_projection_is_orthogonal_to_the_fix_parameter_columns(missions):
    """The structural test's projected columns ``C~ = C - A Z`` (aqfg.fg.structure) are
    orthogonal to every parameter column of the system, the fixes' lever-arm and
    time-offset columns included (with the parameter priors' rows, which it leaves out)."""
    from aqfg.fg.structure import _projected, _solve_columns
    sm = BatchSmoother(effects=("gnss_delay", "lever_arm"))
    bg = sm.build(missions[:1])
    fs = FastSystem.build(bg, sm.settings)
    assert fs is not None
    X, th = fs.from_values(bg.values)
    ev = fs.evaluate(X, th)
    fac = fs.factor(*fs.normal(ev)[:4])
    C = np.random.default_rng(3).normal(size=(len(fs.d0), 6, 2))
    Zs, Zp = _solve_columns(fs, fac, ev, C)
    pr = _projected(fs, ev, bg.parts[0].model, ["s_x", "s_y"], C, Zs, Zp)
    K = len(fs.d0)
    at = 6 * K
    eq = np.einsum("kap,kac->pc", ev["Ap"], pr.Ct[:at].reshape(K, 6, 2))
    n_fix_cols = 0
    for m, (r, _, w, Jp) in zip(fs.meas, ev["meas"]):
        n = r.size
        Ctm = pr.Ct[at:at + n].reshape(r.shape + (2,))
        at += n
        if Jp is not None:
            eq[m.cols] += np.einsum("nap,nac->pc", Jp * np.sqrt(w)[:, None, None], Ctm)
            n_fix_cols += len(m.cols)
    eq -= fs.lin_pA.T @ (fs.lin_pA @ Zp)
    assert n_fix_cols == 2 * (3 + 4)    # GNSS and USBL: the variable node, the sensor node
    assert np.abs(eq).max() < 1e-8 * np.abs(np.einsum("kap,kac->pc", ev["Ap"], C)).max()
