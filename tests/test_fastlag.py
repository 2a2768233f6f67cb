"""The fixed-lag smoother's numpy engine (aqfg.fg.fastlag): its linearisations against finite
differences of its own residuals, its marginalisation against the joint solve, and whole
online runs against the GTSAM engine and the truth.

Tolerances: derivatives to a relative 1e-5 (central differences); the Schur complement to
1e-8 of the joint Newton step; on simulated ASV missions (5 min, GNSS every 8 s or USBL
every 4.5 s) the two engines' final parameters within 3 of the numpy engine's sigmas, their
causal tracks within 1.5 m (median) of each other, the parameters within 3 sigma of the
truth. The engines differ by design (knots at the fixes here, 1-s knots and ISAM2's
marginals there), so they do not agree exactly.
"""
from __future__ import annotations

import copy

import numpy as np
import pytest

from aqfg.data.mission import without_gnss
from aqfg.fg.fit import FGSettings, FixedLagSmoother
from aqfg.sim.simulator import simulate

VAR = ("theta_e", "s_x", "s_y")


def _mission(seed: int, usbl: bool):
    m, truth = simulate("asv", seed=seed, duration=300.0, gnss_period=8.0, usbl=usbl)
    if usbl:
        m = without_gnss(m)
    return m, truth, {n: truth.params[n] for n in ("k", "k_x", "k_yz")}


def _engine(usbl: bool, n_fix: int = 12, window: float = 1e9):
    """A numpy-engine smoother after ``n_fix`` fixes (window ``window`` s: no
    marginalisation by default)."""
    m, _, init = _mission(4, usbl)
    fl = FixedLagSmoother(init=init, window=window)
    fl.start(m, plan=True)
    while fl.n_fix < n_fix:
        fl.update()
    assert fl.engine == "numpy"
    return fl, fl.backend.win


def _fd(f, x, h):
    J = []
    for j in range(len(x)):
        e = np.zeros(len(x))
        e[j] = h[j] if np.ndim(h) else h
        J.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * e[j]))
    return np.array(J).T


@pytest.mark.parametrize("usbl", [False, True])
def test_dynamics_and_fix_linearisations_match_finite_differences(usbl):
    fl, eng = _engine(usbl)
    P = eng.P
    lay = eng.layout
    for i in range(len(eng.dyn)):
        steps, W = eng.dyn[i][0], eng.dyn[i][1]
        th = eng.th.copy()
        x0 = eng.X[i].copy()
        x1 = eng.X[i + 1].copy()

        def resid(v):        # the negated whitened residual W (f(x0, p) - x1), as dyn_linear
            p = lay.full({g: v[:P][sl] for g, sl in eng.slices.items()})
            return W @ (eng.model.propagate(v[P:P + 6], p, steps)[0] - v[P + 6:])
        pred, Jx, Jp = eng.model.propagate(x0, eng.full_params(), steps)
        J, c = eng.dyn_linear(i, x0, th, pred, Jx, Jp, W)
        v = np.concatenate([th, x0, x1])
        assert np.allclose(J @ v + c, resid(v), rtol=0, atol=1e-9 * np.abs(resid(v)).max() + 1e-12)
        Jfd = _fd(resid, v, np.concatenate([np.full(P, 1e-6), np.full(12, 1e-5)]))
        assert np.allclose(J, Jfd, rtol=1e-5, atol=1e-6 * np.abs(J).max()), (i, J - Jfd)
    # fixes: gradient of their (Huber) cost, and the Gauss-Newton block against the
    # derivative of that gradient where the loss is quadratic
    n_checked = 0
    for i, f in enumerate(eng.fx):
        if f is None:
            continue
        x = eng.X[i, :3] + np.array([0.7, -0.4, 0.0])
        _, g, Hk = eng.fix_terms(i, x)
        gfd = _fd(lambda y: [eng.fix_terms(i, y)[0]], x, 1e-5)[0]
        assert np.allclose(g, gfd, rtol=1e-5, atol=1e-7), (i, g, gfd)
        n_checked += 1
        # the vectorised path (several fixes on a knot) equals the single-fix one
        twice = copy.copy(f)
        twice[:4] = [np.concatenate([a, a]) for a in f[:4]]
        eng.fx[i] = twice
        c2, g2, H2 = eng.fix_terms(i, x)
        eng.fx[i] = f
        c1 = eng.fix_terms(i, x)[0]
        assert np.isclose(c2, 2 * c1) and np.allclose(g2, 2 * g) and np.allclose(H2, 2 * Hk)
    assert n_checked >= 10


def test_cpp_block_matches_the_numpy_linearisation_and_swaps_in_place():
    """kernel ``linearise`` / ``linearise_into`` (one C++ call per dynamics factor) against
    the numpy reference (``dyn_linear`` and the products ``_set_dyn`` takes), and whole runs
    with and without it."""
    from aqfg.model.params import N_DYN
    from aqfg.model.vehicle import compiled_kernel
    cpp = compiled_kernel()
    fl, eng = _engine(False)
    g = eng.model.geometry
    geo = (np.ascontiguousarray(g.dirs, float), np.ascontiguousarray(g.side, float),
           bool(g.planar))
    P = eng.P
    cols = np.ascontiguousarray(eng.jcols, np.int64)
    p = np.ascontiguousarray(eng.full_params()[:N_DYN])
    rng = np.random.default_rng(1)
    for i in range(len(eng.dyn)):
        steps, W = eng.dyn[i][0], eng.dyn[i][1]
        st = (np.ascontiguousarray(steps.h, float), np.ascontiguousarray(steps.warm, np.uint8),
              np.ascontiguousarray(steps.R, float), np.ascontiguousarray(steps.dem, float),
              np.ascontiguousarray(steps.tm, float))
        x0, th = eng.X[i].copy(), eng.th.copy()
        pred, Jx, Jp = eng.model.propagate(x0, eng.full_params(), steps)
        J, c = eng.dyn_linear(i, x0, th, pred, Jx, Jp, W)
        x1, Hc, bc = cpp.linearise(x0, p, th, cols, W, *st, *geo)
        assert np.allclose(x1, pred, rtol=1e-13, atol=1e-12)
        assert np.allclose(Hc, J.T @ J, rtol=1e-11, atol=1e-11 * np.abs(Hc).max())
        assert np.allclose(bc, J.T @ c, rtol=1e-11, atol=1e-11 * np.abs(bc).max())
        # in place: rows/columns [0, P) and [o, o + 12) get the new block minus the old one
        N = len(eng.z)
        H0, b0 = rng.standard_normal((N, N)), rng.standard_normal(N)
        Hold, bold = rng.standard_normal((P + 12, P + 12)), rng.standard_normal(P + 12)
        H, b, Hb, bb = H0.copy(), b0.copy(), Hold.copy(), bold.copy()
        o = P + 6 * i
        out = cpp.linearise_into(x0, p, th, cols, W, o, H, b, Hb, bb, *st, *geo)
        r = np.concatenate([np.arange(P), np.arange(o, o + 12)])
        want = H0.copy()
        want[np.ix_(r, r)] += Hc - Hold
        wb = b0.copy()
        wb[r] += bc - bold
        assert np.allclose(out, x1) and np.allclose(H, want, rtol=0, atol=1e-12)
        assert np.allclose(b, wb, rtol=0, atol=1e-12)
        assert np.array_equal(Hb, Hc) and np.array_equal(bb, bc)
        # a prediction that is not finite writes nothing
        bad = p.copy()
        bad[eng.jcols[0]] = np.nan
        out = cpp.linearise_into(x0, bad, th, cols, W, o, H, b, Hb, bb, *st, *geo)
        assert not np.all(np.isfinite(out))
        assert np.allclose(H, want, rtol=0, atol=1e-12) and np.array_equal(Hb, Hc)
    # a bad argument is named
    with pytest.raises(ValueError, match="cols"):
        cpp.linearise(x0, p, th, cols + N_DYN, W, *st, *geo)
    with pytest.raises(ValueError, match="'o'"):
        cpp.linearise_into(x0, p, th, cols, W, len(eng.z), H, b, Hb, bb, *st, *geo)
    assert hasattr(eng.dyn[-1][4], "into")          # the engine uses the C++ block
    # other parameter sets and orders, against numpy products of the kernel's Jacobians
    from aqfg.model.params import INDEX
    for names in (("k", "theta_e", "s_y", "k_x", "s_x"), ("s_y", "theta_e", "s_x")):
        cs = np.array([INDEX[n] for n in names], np.int64)
        t = p[cs].copy()
        x1, Hc, bc = cpp.linearise(x0, p, t, cs, W, *st, *geo)
        _, Jx, Jp = eng.model.propagate(x0, eng.full_params(), steps)
        M = np.hstack([Jp[:, cs], Jx, -np.eye(6)])
        J = W @ M
        c = W @ (x1 - M[:, :len(cs) + 6] @ np.concatenate([t, x0]))
        assert np.allclose(Hc, J.T @ J, rtol=1e-11, atol=1e-11 * np.abs(Hc).max()), names
        assert np.allclose(bc, J.T @ c, rtol=1e-11, atol=1e-11 * np.abs(bc).max()), names
    # whole runs: the same estimates and sigmas to rounding
    m, _, init = _mission(2, False)
    a, b2 = (FixedLagSmoother(init=init, window=24.0,
                              settings=FGSettings().with_(online={"cpp_block": f})).run(m)
              for f in (True, False))
    assert np.allclose(a.history.values, b2.history.values, rtol=1e-8, atol=1e-10)
    assert np.allclose(a.history.sigma, b2.history.sigma, rtol=1e-8, atol=1e-12)
    assert np.allclose(a.missions[0].filtered.pos, b2.missions[0].filtered.pos, rtol=0, atol=1e-7)


def test_cpp_window_step_and_schur_complement_match_numpy():
    """kernel ``window_step`` (the Gauss-Newton step and the parameters' covariance) and
    ``schur_drop`` (a knot marginalised) against numpy on a real window, held and released;
    a system that is not positive definite is reported, not solved; bad arguments named."""
    from aqfg.model.vehicle import compiled_kernel
    cpp = compiled_kernel()
    fl, eng = _engine(False, n_fix=9)
    P = eng.P
    z = eng.z + 0.01 * np.random.default_rng(3).standard_normal(len(eng.z))   # off the optimum
    for hold in (None, np.full(P, 1e4)):
        eng.hold_w = hold
        H, g = eng.system(z)
        ok, s, C = cpp.window_step(eng.H, eng.b, z, np.zeros(0) if hold is None else hold,
                                   eng.th0, P)
        assert ok
        want = np.linalg.solve(H, g)
        assert np.allclose(s, want, rtol=1e-9, atol=1e-11 * np.abs(want).max())
        assert np.allclose(C, np.linalg.inv(H)[:P, :P], rtol=1e-8, atol=1e-14)
    H, b = eng.H, eng.b
    N = len(b)
    ok, Hn, bn = cpp.schur_drop(H, b, P, 6)
    r = np.r_[0:P, P + 6:N]
    a = np.r_[P:P + 6]
    X = np.linalg.solve(H[np.ix_(a, a)], np.column_stack([H[np.ix_(a, r)], b[a]]))
    assert ok
    assert np.allclose(Hn, H[np.ix_(r, r)] - H[np.ix_(a, r)].T @ X[:, :-1], rtol=1e-10,
                       atol=1e-10 * np.abs(H).max())
    assert np.allclose(bn, b[r] - H[np.ix_(a, r)].T @ X[:, -1], rtol=1e-10,
                       atol=1e-10 * np.abs(b).max())
    bad = -np.eye(N)
    assert not cpp.window_step(bad, b, eng.z, np.zeros(0), eng.th0, P)[0]
    assert not cpp.schur_drop(bad, b, P, 6)[0]
    with pytest.raises(ValueError, match="'b'"):
        cpp.window_step(H, b[:-1], eng.z, np.zeros(0), eng.th0, P)
    with pytest.raises(ValueError, match="'a', 'na'"):
        cpp.schur_drop(H, b, N - 3, 6)
    assert eng._cwin                                   # the engine uses them


def test_system_gradient_is_the_cost_derivative_and_marginalisation_is_exact():
    fl, eng = _engine(False, n_fix=9)
    rng = np.random.default_rng(0)
    z = eng.z + 0.01 * rng.standard_normal(len(eng.z))
    H, g = eng.system(z)
    gfd = _fd(lambda v: [eng.cost(v)], z, 1e-4)[0]
    assert np.allclose(g, gfd, rtol=1e-6, atol=1e-6 * np.abs(g).max())
    Hfd = _fd(lambda v: eng.system(v)[1], z, 1e-4)
    assert np.allclose(H, Hfd, rtol=1e-6, atol=1e-7 * np.abs(H).max())
    # eliminating the oldest knots (Schur complement) leaves the Newton step of the others
    # as the joint solve gives it
    full = z - np.linalg.solve(H, g)
    red = copy.deepcopy(eng)
    red.z = z.copy()
    red.lag = red.kt[-1] - red.kt[2] + 1e-3          # knots 0 and 1 leave
    red._walk_idx = red._walk_idx[:0]                # the current's walk (tested below) off
    red._marginalise()
    assert red.n == eng.n - 2
    Hr, gr = red.system()
    step = red.z - np.linalg.solve(Hr, gr)
    keep = np.concatenate([np.arange(eng.P), np.arange(eng.P + 12, len(z))])
    assert np.allclose(step, full[keep], rtol=0, atol=1e-8 * np.abs(full).max())


@pytest.mark.slow
@pytest.mark.parametrize("usbl,seed", [(False, 2), (True, 2), (False, 3)])
def test_numpy_engine_agrees_with_gtsam_engine_and_truth(usbl, seed):
    m, truth, init = _mission(seed, usbl)
    window = 15.0 if usbl else 24.0
    # (the GTSAM engine holds the current and the heading offset constant: the numpy one
    # too, here; with the heading's walk its sigma is the walk's, about 3x the constant's)
    runs = {e: FixedLagSmoother(init=init, window=window,
                                settings=FGSettings().with_(online={"engine": e, "current_walk": 0.0,
                                                                    "heading_walk": 0.0})).run(m)
            for e in ("numpy", "gtsam")}
    a, b = runs["numpy"], runs["gtsam"]
    assert a.engine.name == "numpy" and b.engine.name == "gtsam"
    for n in VAR:
        assert abs(a.values[n] - b.values[n]) < 3 * a.sigma[n], (n, a.values[n], b.values[n])
        assert abs(a.values[n] - truth.params[n]) < 3 * a.sigma[n], (n, a.values[n])
        # same information (the GTSAM engine's marginals hold the released hold priors)
        assert 0.5 * b.sigma[n] < a.sigma[n] < 3 * b.sigma[n], n
    fa, fb = a.missions[0].filtered, b.missions[0].filtered
    assert np.array_equal(fa.t, fb.t)
    d = np.linalg.norm(fa.pos[:, :2] - fb.pos[:, :2], axis=1)
    assert np.median(d) < 1.5, np.median(d)
    ref = np.column_stack([np.interp(fa.t, truth.t, truth.pos[:, k]) for k in range(2)])
    assert np.sqrt(np.mean(np.sum((fa.pos[:, :2] - ref) ** 2, axis=1))) < 2.5
    assert len(a.history.t) == len(b.history.t) == len(np.unique(m.fix_times()))
    assert np.all(np.isfinite(a.history.values)) and np.all(np.isfinite(a.history.sigma))


def test_numpy_engine_takes_depth_readings():
    """An AUV diving 0.5-3.8 m with USBL fixes and 1-Hz depth readings: the numpy engine
    runs it (it left depth readings to the GTSAM engine), its down follows the depth (5.7 m
    RMS off without the depth factor) and its estimates are the truth's."""
    m, truth = simulate("auv", seed=5, duration=300.0, usbl=True, gnss_period=None)
    init = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    r = FixedLagSmoother(init=init, window=15.0,
                         settings=FGSettings().with_(online={"current_walk": 0.0,
                                                             "heading_walk": 0.0})).run(m)
    assert r.engine.name == "numpy"
    fa = r.missions[0].filtered
    down = np.interp(fa.t, truth.t, truth.pos[:, 2])
    assert np.sqrt(np.mean((fa.pos[:, 2] - down) ** 2)) < 0.2
    ref = np.column_stack([np.interp(fa.t, truth.t, truth.pos[:, k]) for k in range(2)])
    assert np.sqrt(np.mean(np.sum((fa.pos[:, :2] - ref) ** 2, axis=1))) < 1.5
    for n in VAR:
        assert abs(r.values[n] - truth.params[n]) < 3 * r.sigma[n], (n, r.values[n])


def test_wrong_model_completes_and_unsupported_configurations_fall_back():
    m, _, _ = _mission(1, False)
    # the paper's default constants (another vehicle's), held: a wrong model
    r = FixedLagSmoother(estimate=VAR, window=24.0).run(m)
    assert r.engine.name == "numpy"
    assert np.all(np.isfinite(r.missions[0].track.pos)) and np.all(np.isfinite(r.history.values))
    assert r.process_noise_scale > 1.0           # the fixes pull the track
    # a lever arm is a measurement effect: the GTSAM engine runs it
    fl = FixedLagSmoother(estimate=VAR, effects=("lever_arm",), window=24.0)
    fl.start(m)
    assert fl.engine == "gtsam" and "measurement" in fl.engine_note
    fl = FixedLagSmoother(window=24.0, settings=FGSettings().with_(online={"engine": "gtsam"}))
    fl.start(m)
    assert fl.engine == "gtsam"


def test_a_failed_step_is_recovered_and_recorded(monkeypatch):
    from aqfg.fg.fastlag import LagWindow
    m, _, init = _mission(3, False)
    fl = FixedLagSmoother(init=init, window=24.0)
    fl.start(m, plan=True)
    for _ in range(8):
        fl.update()
    real = LagWindow.step
    calls = {"n": 0}

    def flaky(self):
        calls["n"] += 1
        if calls["n"] == 1:
            raise np.linalg.LinAlgError("the window's system is not positive definite")
        return real(self)
    monkeypatch.setattr(LagWindow, "step", flaky)
    while fl.pending():
        fl.update()
    res = fl.result()
    assert any(e.event.startswith("restarted") for e in res.events)
    assert np.all(np.isfinite(res.missions[0].track.pos))
    assert np.all(np.isfinite(res.history.values[-1]))


def test_current_walk_is_the_marginal_walked_as_an_explicit_node():
    """``LagWindow._walk`` (the marginal's current moved by a first-order Gauss-Markov step:
    an affine map and Woodbury; the heading offset with its own variance) against the same
    process written out: the marginal's current as its own variable ``c``, joined to the window's by the factor
    ``z - mu0 - a (c - mu0) ~ N(0, S (1 - a^2))`` (``mu0``: the prior's centre), then
    eliminated (Schur complement)."""
    m, _, init = _mission(4, False)
    sw = 0.02
    fl = FixedLagSmoother(init=init, window=30.0, settings=FGSettings().with_(online={"current_walk": sw}))
    fl.start(m, plan=True)
    while fl.n_fix < 14:                  # ~100 s of 8-s fixes: knots have left the window
        fl.update()
    eng = fl.backend.win
    w = eng._walk_idx
    # the heading offset walks too (FGSettings.online.heading_walk, a plain walk)
    assert [eng.names[j] for j in w] == ["theta_e", "s_x", "s_y"]
    P, N = eng.P, len(eng.b)
    # the window's own dynamics factors, placed; the rest of the held quadratic is the marginal
    Hw, bw = np.zeros((N, N)), np.zeros(N)
    for i, d in enumerate(eng.dyn):
        r = np.concatenate([np.arange(P), P + 6 * i + np.arange(12)])
        Hw[np.ix_(r, r)] += d[2]
        bw[r] += d[3]
    Hm, bm = eng.H - Hw, eng.b - bw
    assert np.abs(Hm[np.ix_(w, w)]).max() > 0          # the past has informed the current
    for dt, stat in ((8.0, 0.3 ** 2), (8.0, np.inf)):   # Gauss-Markov, and a plain walk
        k = len(w)
        var = eng._walk_var                             # per walking parameter, per s
        if np.isfinite(stat):
            tau = 2 * stat / var
            a_all, q_all = np.exp(-dt / tau), stat * (1 - np.exp(-2 * dt / tau))
        else:
            a_all, q_all = np.ones(k), var * dt
        # explicit: variables [z (the window's current), c (the past's current)]
        A = np.zeros((N + k, N + k))
        v = np.zeros(N + k)
        mv = np.arange(N)
        mv[w] = N + np.arange(k)                       # the marginal reads c, not z[w]
        A[np.ix_(mv, mv)] += Hm
        v[mv] += bm
        A[:N, :N] += Hw
        v[:N] += bw
        for j, c, a, q in zip(w, N + np.arange(k), a_all, q_all):   # (z_j - a c - k0)^2 / q
            k0 = (1 - a) * eng.mu0[j]
            A[j, j] += 1 / q
            A[c, c] += a * a / q
            A[j, c] -= a / q
            A[c, j] -= a / q
            v[j] -= k0 / q
            v[c] += a * k0 / q
        c = N + np.arange(k)
        Ac = np.linalg.solve(A[np.ix_(c, c)], np.column_stack([A[c, :N], v[c]]))
        H_ref = A[:N, :N] - A[:N, c] @ Ac[:, :N]
        b_ref = v[:N] - A[:N, c] @ Ac[:, N]
        e = copy.deepcopy(eng)
        e._walk_stat, e._walk_cache = np.full(k, stat), {}
        e._walk(dt)
        assert np.allclose(e.H, H_ref, rtol=0, atol=1e-9 * np.abs(eng.H).max())
        assert np.allclose(e.b, b_ref, rtol=0, atol=1e-9 * np.abs(eng.b).max())
        # the information on the current fell; nothing untied to the marginal's current moved
        assert np.all(np.diag(e.H)[w] < np.diag(eng.H)[w])
        tied = np.abs(Hm[:, w]).sum(axis=1) > 1e-9 * np.abs(eng.H).max()
        other = np.flatnonzero(~tied)
        assert len(other) > N // 2
        assert np.allclose(e.H[np.ix_(other, other)], eng.H[np.ix_(other, other)],
                           rtol=0, atol=1e-12 * np.abs(eng.H).max())
