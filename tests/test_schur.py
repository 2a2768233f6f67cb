"""The joint batch fit computed mission by mission (aqfg.fg.schur) equals BatchSmoother.run."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.fg.batch import BatchSmoother
from aqfg.fg.schur import (
    MissionProblem,
    MissionSession,
    combine,
    drive,
    joint_lm,
    solve_apart,
)
from aqfg.sim import simulate, true_params


@pytest.fixture(scope="module")
def missions():
    k = true_params("asv")["k"]
    return [simulate("asv", seed=s, duration=240.0, gnss_period=8.0, params={"k": 1.1 * k})[0]
            for s in (11, 12)]


@pytest.fixture(scope="module")
def batch(missions):
    return BatchSmoother().run(missions)


def _assert_equal(a, b, tol=0.05):
    """Every parameter (fixed, and each mission's own) within tol x the batch's model sigma
    and the same sigmas (model, and sandwich-inflated)."""
    sm = b.sigma_model or b.sigma
    for n in b.estimated:
        assert abs(a.values[n] - b.values[n]) < tol * sm[n], (n, a.values[n], b.values[n])
        assert a.sigma[n] == pytest.approx(b.sigma[n], rel=0.02), n      # sandwich-inflated
        assert a.sigma_model[n] == pytest.approx(sm[n], rel=0.02), n
    for m, pm in b.per_mission.items():
        for n, e in pm.items():
            got = a.per_mission[m][n]
            assert abs(got.value - e.value) < tol * sm[n], (m, n)
            assert got.sigma == pytest.approx(e.sigma, rel=0.02), (m, n)


def test_apart_equals_joint_batch(missions, batch):
    res = solve_apart(BatchSmoother(), missions)
    # the same Levenberg-Marquardt iterates, not only the same optimum
    assert res.iterations == batch.iterations
    assert res.cost == pytest.approx(batch.cost, rel=1e-9)
    _assert_equal(res, batch, tol=1e-3)
    for a, b in zip(res.missions, batch.missions):
        assert np.max(np.abs(a.track.pos - b.track.pos)) < 1e-4


def test_lost_mission_is_rebuilt_and_the_run_goes_on(missions, batch):
    """A session replaced by a fresh one mid-run (its worker died) re-solves its locals at
    the current fixed parameters; the run still converges to the joint optimum."""
    sm = BatchSmoother()
    sessions = [MissionSession(MissionProblem(sm, m, fixed_prior=(i == 0)))
                for i, m in enumerate(missions)]
    rounds = {"n": 0, "lost": 0}

    def serve(reqs):
        rounds["n"] += 1
        if rounds["n"] in (6, 9):          # lose mission 1 after a "sys" and after a "step"
            sessions[1] = MissionSession(MissionProblem(sm, missions[1], fixed_prior=False))
        reps = [s.handle(op, args) for s, (op, args) in zip(sessions, reqs)]
        rounds["lost"] += sum(bool(r.get("lost")) for r in reps)
        return reps
    sol = drive(joint_lm(len(sessions), sm.settings), serve)
    assert sol.recovered >= 1 and rounds["lost"] >= 1 and sol.converged
    _assert_equal(combine(sol), batch)


def test_numpy_session_serves_the_graphs_reduced_system(missions):
    """A mission's session on its numpy system (the default) answers "sys" and "step" with
    the Schur complement, right-hand side, damping scale and candidate cost of its GTSAM
    graph's session."""
    from aqfg.fg.settings import FGSettings
    sessions = [MissionSession(MissionProblem(BatchSmoother(settings=FGSettings().with_(solver={"fast_lm": f})),
                                              missions[0], fixed_prior=True))
                for f in (True, False)]
    assert sessions[0].fast is not None and sessions[1].fast is None
    f0 = sessions[0].handle("open", {})["f0"]
    assert np.array_equal(f0, sessions[1].handle("open", {})["f0"])
    f = f0 * 1.05                         # off the mission's own start: a real step follows
    for trial, lam in ((1, 1e-3), (2, 0.0)):
        reps = [s.handle("sys", {"f": f, "lam": lam, "trial": trial, "start": trial == 1})
                for s in sessions]
        a, b = reps[0]["system"], reps[1]["system"]
        assert a.cost == pytest.approx(b.cost, rel=1e-10)
        np.testing.assert_allclose(a.H, b.H, rtol=1e-7, atol=1e-9 * np.abs(b.H).max())
        np.testing.assert_allclose(a.eta, b.eta, rtol=1e-6, atol=1e-8 * np.abs(b.eta).max())
        np.testing.assert_allclose(a.hdiag, b.hdiag, rtol=1e-10)
        df = np.linalg.solve(b.H + np.diag(1e-3 * b.hdiag), b.eta)
        steps = [s.handle("step", {"trial": trial, "delta_f": df, "f_new": f + df,
                                   "mode": "try"}) for s in sessions]
        assert steps[0]["cost"] == pytest.approx(steps[1]["cost"], rel=1e-8)
        assert steps[0]["cost"] != pytest.approx(a.cost, rel=1e-6)   # the step moved it


def test_session_track_is_the_track_smoothed_at_the_joint_parameters(missions):
    """The adapted track a numpy session returns with its result is the one a separate
    smooth of the mission at the joint fit's parameters gives (the fleet's track step):
    the same process-noise factor, the same track."""
    from aqfg.fg.batch import smooth_track
    from aqfg.fg.settings import FGSettings
    st = FGSettings().with_(batch={"adapt_track": True})
    sm = BatchSmoother(settings=st)
    sessions = [MissionSession(MissionProblem(sm, m, fixed_prior=(i == 0)))
                for i, m in enumerate(missions)]

    def serve(reqs):
        return [s.handle(op, args) for s, (op, args) in zip(sessions, reqs)]
    sol = drive(joint_lm(len(sessions), st), serve)
    assert sol.tracks is not None and all(t is not None for t in sol.tracks)
    for m, res, (track, residuals, q) in zip(missions, sol.results, sol.tracks):
        ref_track, ref_res, ref_q = smooth_track(m, res.missions[0].p, settings=st)
        assert q == ref_q
        assert np.max(np.abs(track.pos - ref_track.pos)) < 1e-3
        assert set(residuals) == set(ref_res)
