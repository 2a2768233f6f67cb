"""Right on a vehicle that is not the model: the factor graph on missions of Fossen's 6-DOF
Otter USV (tests/data; truth in mission.toml), whose physics the paper's model lacks.

Tolerances are those the independent-vehicle work asks for: batch theta_e within 3 deg of
truth, current within 0.05 m/s, |error| / sigma <= 3; online runs complete, recover from
GTSAM failures and never leave a NaN in their estimates.
"""
from __future__ import annotations

import numpy as np
import pytest

from conftest import data_path

from aqfg.data import load_mission, load_truth
from aqfg.data.mission import with_gnss_every
from aqfg.fg import BatchSmoother, FGSettings, FixedLagSmoother, fit_fg
from aqfg.fg.common import robust_fix_table
from aqfg.fg.kinematic import KinematicFilter, baseline_tracks
from aqfg.fg.online import policy, recovery
from aqfg.result import Track

DEG = np.pi / 180
# the batches' basins ranked by cost, as before FGSettings.batch.rank_by_evidence: what the
# online safety nets met then, and still meet in batches too long for the evidence
BY_COST = FGSettings().with_(batch={"rank_by_evidence": False})
# the model's own causal track, without the kinematic floor while the parameters are held
# (FGSettings.online.kinematic_q): the tests of the hold's mechanisms (re-seeds, the first
# batch's timing, the held model's noise) measure what they do to the model's prediction,
# which the floor would otherwise hide
MODEL_TRACK = FGSettings().with_(online={"kinematic_q": 0.0})
# the sway drag's prior of the paper's vehicles (0.9 1/m around 0.3: FGSettings.graph.prior_sigma
# without k_yz), under which these crops slide: the basins the plausibility rules and their
# rescues are for; the default prior (30 1/m) fits them without sliding
# (test_the_sway_prior_fits_the_sliding_crops_without_a_rescue)
SLIDING = {"s_x": 0.3, "s_y": 0.3}


def wrap(a: float) -> float:
    return float(np.angle(np.exp(1j * a)))


def mission(name: str, every: float):
    return with_gnss_every(load_mission(data_path(name)), every), load_truth(data_path(name))


def check_batch(res, truth, theta_true=None):
    P = truth.params
    th = P["theta_e"] if theta_true is None else theta_true
    e_th = wrap(res.values["theta_e"] - th)
    assert abs(e_th) < 3 * DEG, f"theta_e off by {e_th / DEG:.1f} deg"
    assert abs(e_th) <= 3 * res.sigma["theta_e"], "theta_e error above 3 sigma"
    for n in ("s_x", "s_y"):
        e = res.values[n] - P.get(n, 0.0)
        assert abs(e) < 0.05, f"{n} off by {e:.3f} m/s"
        assert abs(e) <= 3 * res.sigma[n], f"{n} error {e:.3f} above 3 sigma {res.sigma[n]:.3f}"
    assert res.plausible


@pytest.mark.slow
@pytest.mark.parametrize("name, every", [("otter-dev-calm-a", 8.0), ("otter-dev-calm-b", 4.0),
                                         ("otter-dev-current-weakprop", 8.0)])
def test_batch_heading_and_current_on_the_otter(name, every):
    """calm-a at 8-s fixes used to end at theta_e -49 deg (k_yz -> 0) with sigma 0.56 deg."""
    m, truth = mission(name, every)
    res = fit_fg([m])
    check_batch(res, truth)
    # the model is wrong here: the honest sigma is above the Hessian's, and it says so
    assert res.sigma["s_x"] > res.sigma_model["s_x"]
    assert any("does not explain the fixes" in w for w in res.warnings)
    # a whole mission has the sandwich's blocks: the short data's jackknife does not run
    assert not res.too_short_for_sandwich and res.block_jackknife is None


def test_an_unexplained_fit_tries_the_effects_the_test_ranks_first():
    """otter-dev-calm-a at 8-s fixes: the model as given does not explain the fixes (sigma
    inflated 9.6x) and no effect reaches the structural test's level after Holm (linear
    drag's robust p 3e-4 x 7); the effect of largest score statistic, the linear drag,
    is tried, and added: it lowers the cost by far more than its two parameters cost
    (BIC). theta_e -1.18 -> -0.05 deg off."""
    m, truth = mission("otter-dev-calm-a", 8.0)
    res = fit_fg([m])
    rec = res.effect_step
    assert rec is not None and rec.untested and rec.adopted and res.effects == ("linear_drag",)
    assert rec.tried is None                        # the one of largest statistic alone
    e_base = abs(wrap(rec.base.values["theta_e"] - truth.params["theta_e"]))
    e = abs(wrap(res.values["theta_e"] - truth.params["theta_e"]))
    assert e < 0.5 * e_base
    check_batch(res, truth)
    assert any("no effect reached the structural test's level" in w
               for w in res.warnings)
    from aqfg.parameters_doc import effect_step_document
    assert effect_step_document(rec)["untested"] is True     # parameters.json says so


def kinematic_baseline(m, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The constant-velocity filter's causal and smoothed states at ``t`` on the fixes of
    ``m`` (the factor graph's fix table, and its causal floor's filter)."""
    s = FGSettings()
    return baseline_tracks(robust_fix_table(m, s), t, KinematicFilter.from_settings(s))


def track_rmse(track, truth) -> float:
    pt = np.column_stack([np.interp(track.t, truth.t, truth.pos[:, a]) for a in range(2)])
    return float(np.sqrt(np.mean(np.sum((track.pos[:, :2] - pt) ** 2, axis=1))))


def test_the_batch_track_follows_the_fixes_where_the_model_is_not_the_vehicle():
    """The parameters come from the nominal process noise, the track from the noise the
    evidence chooses given them: with the track at the nominal noise the smoothed track
    was 1.4 m RMS from the truth between 8-s fixes, following the model's error."""
    m, truth = mission("otter-dev-calm-a", 8.0)
    # the smoother's own constants, the model as given (with the linear drag the effect
    # step adds, the model explains more of the motion: 0.48 against 0.58 m)
    st = FGSettings().with_(batch={"dr_horizon": 0.0, "auto_effect": False})
    on, off = fit_fg([m], settings=st), fit_fg([m], settings=st.with_(batch={"adapt_track": False}))
    assert on.track_noise_scale[m.name] > 1.0
    assert off.track_noise_scale is None
    for n in on.estimated:
        assert on.values[n] == off.values[n] and on.sigma[n] == off.sigma[n], n
    e_on, e_off = track_rmse(on.missions[0].track, truth), track_rmse(off.missions[0].track, truth)
    assert e_on < 0.6 * e_off, (e_on, e_off)
    # and beats no model at all: a constant-velocity smoother on the fixes (1.27 m here)
    _, ks = kinematic_baseline(m, on.missions[0].track.t)
    e_kin = track_rmse(Track(on.missions[0].track.t, ks[:, :2], ks[:, 2:]), truth)
    assert e_on < 0.7 * e_kin, (e_on, e_kin)
    # the residuals are the reported track's: the fixes are closer to it
    r_on = on.missions[0].residuals["gnss"].raw
    r_off = off.missions[0].residuals["gnss"].raw
    assert np.sqrt(np.mean(r_on ** 2)) < np.sqrt(np.mean(r_off ** 2))


@pytest.mark.slow
def test_the_batch_track_is_unchanged_where_the_model_is_the_vehicle():
    from aqfg.sim.simulator import simulate
    m, _ = simulate("asv", seed=4, duration=300.0, usbl=True)
    m = with_gnss_every(m, 8.0)
    st = FGSettings().with_(batch={"dr_horizon": 0.0})
    on, off = fit_fg([m], settings=st), fit_fg([m], settings=st.with_(batch={"adapt_track": False}))
    assert on.track_noise_scale == {m.name: 1.0}
    assert np.array_equal(on.missions[0].track.pos, off.missions[0].track.pos)


def test_ambiguity_variance_is_the_spread_of_the_basins():
    from aqfg.fg.batch import ambiguity_variance
    chosen = {"theta_e": 0.1, "s_x": 0.0, "k": 1.0}
    # one basin across the wrap, as good: half the weight at 0.2 rad
    same = [{"values": {"theta_e": 2 * np.pi - 0.1, "s_x": 0.4}, "cost": 10.0}]
    v = ambiguity_variance(chosen, same, 10.0)
    assert v["theta_e"] == pytest.approx(0.5 * 0.2 ** 2) and v["s_x"] == pytest.approx(0.5 * 0.16)
    assert "k" not in v                                 # not in the basins' values
    # worse by ln 3: a quarter of the weight
    worse = [{"values": {"theta_e": 1.1, "s_x": 0.0}, "cost": 10.0 + np.log(3.0)}]
    assert ambiguity_variance(chosen, worse, 10.0)["theta_e"] == pytest.approx(0.25)


CONSTANTS_94 = {"k": 0.396, "k_x": 0.166, "k_yz": 31.8}    # a batch fit of seed 94


def test_an_ambiguous_batch_reports_the_spread_of_its_basins():
    """20 s of seed 93 at 8-s fixes with another mission's constants: four heading basins
    fit as well; the chosen one, 142 deg off, had sigma 17 deg."""
    m, truth = mission("otter-heldout-93-40s", 8.0)
    from aqfg.data.mission import between
    res = fit_fg([between(m, -np.inf, 20.0)], estimate=("theta_e", "s_x", "s_y"),
                 init=CONSTANTS_94)
    assert len(res.ambiguous) >= 2
    e = abs(wrap(res.values["theta_e"] - truth.params["theta_e"]))
    assert e > 3 * res.sigma_unimodal["theta_e"]        # one basin's sigma
    assert e <= 3 * res.sigma["theta_e"]
    assert any("the sigmas cover the basins" in w for w in res.warnings)


# a batch fit of otter-dev-calm-b at 8-s fixes (its effect added): another mission's constants
CONSTANTS_CALM_B = {"k": 1.011, "k_x": 0.0475, "k_yz": 3.78, "linear_drag.c_x": 0.525,
                    "linear_drag.c_yz": 0.0}


def test_a_short_batch_heading_sigma_holds_its_profile_over_the_circle():
    """The first 11 s of seed 93 (five fixes) with calm-b's constants: all four starts end in
    one basin 147 deg off, whose curvature claimed sigma 12 deg; the evidence over the whole
    circle is nearly flat, and the sigma says so."""
    from aqfg.data.mission import between
    from aqfg.fg.settings import FGSettings
    from aqfg.fg.profile import N_GRID
    m, truth = mission("otter-heldout-93-40s", 8.0)
    c = between(m, -np.inf, 11.01)
    kw = dict(estimate=("theta_e", "s_x", "s_y"), init=CONSTANTS_CALM_B, effects=["linear_drag"])
    one = fit_fg([c], settings=FGSettings().with_(batch={"heading_profile": False}), **kw)
    res = fit_fg([c], **kw)
    e = abs(wrap(res.values["theta_e"] - truth.params["theta_e"]))
    assert e > np.radians(90.0) and e > 3 * one.sigma["theta_e"]      # the defect
    assert res.values["theta_e"] == one.values["theta_e"]              # the same fit ...
    assert e <= 3 * res.sigma["theta_e"]                               # ... honestly
    assert res.sigma_unimodal["theta_e"] == one.sigma["theta_e"]
    assert len(res.heading_profile.theta_e) == N_GRID       # the whole circle
    assert any("hardly determine the heading offset" in w for w in res.warnings)
    for n in ("s_x", "s_y"):
        assert abs(res.values[n] - truth.params[n]) <= 3 * res.sigma[n]


@pytest.mark.slow
def test_online_sigma_holds_a_short_batch_heading_profile():
    """The online smoother's re-initialisation batches walk the heading profile too: on
    seed 66 at 8-s fixes with calm-b's constants, the 15.5-s batch's basin claimed
    sigma 6 deg at a heading 22 deg off; the same solve, and a sigma that holds it."""
    from aqfg.fg.settings import FGSettings
    m, truth = mission("otter-heldout-66-90s", 8.0)
    kw = dict(mode="online", init=CONSTANTS_CALM_B, effects=["linear_drag"])
    runs = [fit_fg([m], settings=FGSettings().with_(batch={"heading_profile": p}), **kw)
            for p in (False, True)]
    (h0, h1) = (r.history for r in runs)
    i = list(h1.names).index("theta_e")
    k = int(np.argmin(np.abs(h1.t - 15.5)))
    e = abs(wrap(h1.values[k, i] - truth.params["theta_e"]))
    assert np.array_equal(h0.values, h1.values)                      # the same estimates
    assert e > 3 * h0.sigma[k, i] and e <= 3 * h1.sigma[k, i]


def test_online_sigma_covers_an_ambiguous_batch_until_the_next():
    m, truth = mission("otter-heldout-93-40s", 8.0)
    res = fit_fg([m], mode="online", init=CONSTANTS_94)
    h = res.history
    i = list(h.names).index("theta_e")
    k10 = 9                                       # the tenth fix (24.5 s)
    e = abs(wrap(h.values[k10, i] - truth.params["theta_e"]))
    first = res.reinit_batches[0]
    assert first.t == 20.0 and e > 3 * first.reference_sigma_theta_e
    assert e <= 3 * h.sigma[k10, i]


@pytest.mark.slow
def test_the_restart_fix_reports_the_spread_of_the_batch_basins():
    """otter-dev-calm-a at 4-s GNSS with the paper's constants: a re-initialisation batch
    restarts the smoother where other basins fit as well (its sigma over them is many times
    the chosen basin's). The restart's own fix, where the parameters are still held at the
    batch's values, reports that spread, not the hold prior's sigma alone (which is twice
    the one basin's: 3 deg against 16.5). (The basins ranked by cost: ranked by evidence,
    that batch is not ambiguous; a batch too long for the evidence still ranks by cost.)"""
    m, _ = mission("otter-dev-calm-a", 4.0)
    res = fit_fg([m], mode="online", settings=BY_COST.with_(graph={"prior_sigma": SLIDING}))
    h = res.history
    i = list(h.names).index("theta_e")
    amb = [b for b in res.reinit_batches
           if b.restarted and b.reference != "non-sliding alternative"
           and b.sigma_theta_e > 3 * b.reference_sigma_theta_e]
    assert amb, res.reinit_batches
    for b in amb:
        k = int(np.argmin(np.abs(h.t - b.t)))
        assert h.t[k] == pytest.approx(b.t)
        assert h.sigma[k, i] >= b.sigma_theta_e, (b, h.sigma[k, i])


@pytest.mark.slow
def test_released_constants_at_their_bounds_are_caught_before_the_track_runs_away(monkeypatch):
    """otter-heldout-201 (a 0.23 m/s current, the offset drifting 0.042 deg/s), 8-s GNSS, the
    paper's constants, all six free: after the 160-s re-initialisation batch the released
    thrust and surge drag fell to their lower bounds, and the causal track ran 45 km off
    within a minute. The batches' bounds check now watches the released estimates: the
    fixes so far are solved as a batch again. Since the replays keep the batch's own priors
    on the offset and the current, that run no longer releases such constants, so the same
    failure is injected: the released window's thrust and surge drag held at their lower
    bounds from 170 to 260 s. Caught, the track stays within metres of the truth after the
    first 40 s and below the update-error method's; without the check it ran 17.6 m off."""
    from aqfg.ekf import fit_update_error
    from aqfg.fg.fastlag import LagWindow
    m, truth = mission("otter-heldout-201", 8.0)

    def causal(r):
        c = r.missions[0].filtered
        pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
        return c.t, np.hypot(*(c.pos[:, :2] - pt).T)
    real = LagWindow.step
    pinned: dict = {}

    def step(self):
        real(self)
        # the window released at 160 s (a restart makes a new window, which is left alone)
        if 170.0 < self.kt[-1] < 260.0 and self.hold_w is None \
                and pinned.setdefault("window", self) is self:
            for n in ("k", "k_x"):
                j = self.names.index(n)
                self.z[j] = self.lo[j]
    monkeypatch.setattr(LagWindow, "step", step)
    r = fit_fg([m], mode="online", settings=BY_COST)
    assert any(e.event == "released parameters implausible" and 170.0 < e.t < 260.0
               for e in r.events), r.events
    t, e = causal(r)
    assert np.max(e[t > 40.0]) < 10.0, np.max(e[t > 40.0])
    monkeypatch.setattr(LagWindow, "step", real)
    _, e_u = causal(fit_update_error([m], mode="online"))
    assert np.sqrt(np.mean(e ** 2)) < np.sqrt(np.mean(e_u ** 2))


@pytest.mark.slow
def test_heading_drift_recovered_on_the_otter():
    m, truth = mission("otter-dev-yawdrift", 8.0)
    res = fit_fg([m], effects=["heading_drift"])
    check_batch(res, truth)
    rate, true_rate = res.values["heading_drift.rate"], truth.params["heading_drift.rate"]
    assert abs(rate - true_rate) < 3 * res.sigma["heading_drift.rate"]


def test_short_data_rank_heading_basins_by_their_evidence():
    """otter-heldout-52-300s (300 s, 1-s GNSS, the offset drifting): too short for the
    sandwich, so the evidence chooses the process noise. Under the noise the closed-form
    basin chose, a hull sliding sideways 43 deg off had the lower cost (by 7), and the batch
    returned it with sigma 3.5 deg; each basin under the noise its own misfit asks for, the
    sliding one has 14.5 less log evidence. Ranked by evidence, the batch is within 10 deg
    of the crop's mean offset, and the lower-cost basin is listed with the higher rank."""
    m, truth = mission("otter-heldout-52-300s", 0.0)
    res = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False}))
    basins = res.basins
    assert res.too_short_for_sandwich and all("log_evidence" in b for b in basins)
    cost = res.cost
    cheaper = [b for b in basins if b["cost"] < cost - 1.0]
    assert cheaper and all(b["rank"] > cost + 2.0 for b in cheaper), basins
    P = truth.params
    th = P["theta_e"] + P["heading_drift.rate"] * 0.5 * (m.t0 + float(m.fix_times()[-1]))
    assert abs(wrap(res.values["theta_e"] - th)) < 10 * DEG, res.values["theta_e"] / DEG


@pytest.mark.slow
def test_a_degenerate_start_is_detected_and_left():
    """Started in the degenerate basin the first fit reached (the vehicle sliding sideways
    at a heading 80 deg off, no sway drag), the solve recognises it as implausible,
    solves from the closed-form heading basins and returns the plausible one."""
    m, truth = mission("otter-dev-calm-a", 8.0)
    res = BatchSmoother(init={"theta_e": -0.85, "k": 1.45, "k_x": 19.0, "k_yz": 9e-4}).run([m])
    basins = res.basins
    assert not basins[0]["plausible"] and basins[0]["start"] == "user start"
    assert basins[0]["checks"][m.name]["slip_deg"] > 45
    assert any(b["plausible"] for b in basins[1:])
    # (the user's values also centre the weak priors, k_x ~ 19 +- 3 here, so only the
    # heading is held to the usual tolerance)
    assert res.plausible
    assert abs(wrap(res.values["theta_e"] - truth.params["theta_e"])) < 3 * DEG


@pytest.mark.slow
def test_online_all_six_parameters_completes():
    m, truth = mission("otter-dev-calm-a", 8.0)
    res = FixedLagSmoother(estimate=("theta_e", "s_x", "s_y", "k", "k_x", "k_yz")).run(m)
    assert np.all(np.isfinite(res.history.values))
    assert np.all(np.isfinite(res.missions[0].filtered.pos))
    assert abs(wrap(res.values["theta_e"] - truth.params["theta_e"])) < 5 * DEG
    assert any(e.event.startswith("re-initialised") for e in res.events)


@pytest.mark.slow
def test_online_with_another_missions_fixed_parameters():
    """The paper's protocol: fixed parameters from an offline fit of another mission of the
    same vehicle, heading offset and current online."""
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    m, truth = mission("otter-example", 8.0)
    # the other fit's constants with its effects (the linear drag its fit added)
    res = FixedLagSmoother(init=other.vehicle_constants(), effects=other.effects).run(m)
    assert abs(wrap(res.values["theta_e"] - truth.params["theta_e"])) < 5 * DEG
    f = res.missions[0].filtered
    pt = np.column_stack([np.interp(f.t, truth.t, truth.pos[:, a]) for a in range(2)])
    rmse = float(np.sqrt(np.mean(np.sum((f.pos[:, :2] - pt) ** 2, axis=1))))
    assert rmse < 4.0, f"causal RMSE {rmse:.2f} m"


@pytest.mark.slow
def test_the_released_window_solves_the_batchs_own_problem():
    """otter-dev-calm-a at 8-s fixes with otter-dev-calm-b's constants. The 20-s batch
    restarts the smoother; its replay holds the heading offset and the current at the
    batch's values, but their priors stay the batch's own (the current's zero-mean one),
    so once released the window solves the problem the batch solved. With the batch's
    marginals as the replay's priors, centred on its values, the zero-mean prior on the
    current was gone: the released estimate slid along the offset-current ridge, 6 deg
    from a batch of the same fixes at the next fix and 8.6 deg from the truth at the tenth
    (heldout-232: 7 deg and a 0.45 m/s cross current)."""
    from aqfg.fg.fixed_lag import _mission_until
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    init, eff = other.vehicle_constants(), other.effects
    m, truth = mission("otter-dev-calm-a", 8.0)
    fl = FixedLagSmoother(init=init, effects=eff)
    fl.start(m, plan=True)
    while fl.hist_t[-1] < 24.0 - 1e-9:   # to the fix after the 20-s batch
        fl.update()
    assert [b.t for b in fl.reinit_batches] == [20.0] and fl.reinit_batches[0].restarted
    eng = fl.backend.win
    assert eng is not None and eng.hold_w is None            # released
    j = [eng.names.index(n) for n in ("s_x", "s_y")]
    assert np.all(eng.mu0[j] == 0.0)      # the current's prior: zero-mean, as the batch's
    assert np.all(eng.th0[j] != 0.0)      # (held at the batch's values in the replay)
    t = fl.hist_t[-1]
    assert t == pytest.approx(24.0)
    b = fit_fg([_mission_until(m, t)], init=init, effects=eff,
               estimate=("theta_e", "s_x", "s_y"))
    i = eng.names.index("theta_e")
    gap = abs(wrap(float(eng.z[i]) - b.values["theta_e"]))
    assert gap < 2.5 * DEG, np.degrees(gap)


def causal_rmse(res, truth) -> float:
    f = res.missions[0].filtered
    pt = np.column_stack([np.interp(f.t, truth.t, truth.pos[:, a]) for a in range(2)])
    return float(np.sqrt(np.mean(np.sum((f.pos[:, :2] - pt) ** 2, axis=1))))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["otter-example", "otter-dev-calm-a",
                                  "otter-dev-current-weakprop"])
def test_online_paper_protocol_causal_accuracy(name):
    """The issue's target for the paper's protocol at 8-s fixes: fixed parameters from a
    batch fit of another mission, causal RMSE within 3 m and the heading offset within
    5 deg at the end (the missions with a constant offset)."""
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    m, truth = mission(name, 8.0)
    res = FixedLagSmoother(init=other.vehicle_constants(), effects=other.effects).run(m)
    assert causal_rmse(res, truth) <= 3.0
    e = abs(wrap(res.values["theta_e"] - truth.params["theta_e"]))
    assert e < 5 * DEG
    assert e <= 3 * res.sigma["theta_e"], "online sigma not honest"


@pytest.mark.slow
def test_online_random_walk_survives_failed_releases():
    """All six parameters online with a random walk on the heading offset on
    otter-dev-calm-b at 8-s fixes: a failed release after the 80-s batch used to end in a
    Python error (a walk segment's node inserted twice by the restart), and once fixed, in
    skipped fixes whose causal track ran to 1e7 m. Troubled updates now re-initialise from
    a batch of the fixes so far. (Without the USBL gate.) The run no longer gets into
    trouble by itself (the heading search of the re-initialisation batches), so a skipped
    fix is also injected after the 80-s release: the next update must re-initialise."""
    from aqfg.fg.online.records import OnlineEvent
    from aqfg.fg.settings import FGSettings

    class Troubled(FixedLagSmoother):
        injected = False

        def _solve(self, t_fix, n_new):
            info = super()._solve(t_fix, n_new)
            if 100.0 <= t_fix and not Troubled.injected:
                Troubled.injected = True
                self.events.append(OnlineEvent(float(t_fix), "fix skipped",
                                               {"error": "injected by the test"}))
            return info

    m, truth = mission("otter-dev-calm-b", 8.0)
    st = FGSettings().with_(graph={"walk_sigma": {"theta_e": 0.0026}, "prior_sigma": SLIDING},
                            online={"gate_usbl": np.inf})
    for cls in (FixedLagSmoother, Troubled):
        res = cls(settings=st).run(m)
        f = res.missions[0].filtered
        pt = np.column_stack([np.interp(f.t, truth.t, truth.pos[:, a]) for a in range(2)])
        err = np.hypot(*(f.pos[:, :2] - pt).T)
        print(cls.__name__, "causal RMSE", causal_rmse(res, truth),
              "knots > 100 m", int(np.sum(err > 100.0)))
        assert np.mean(err > 100.0) < 0.01        # was 76 of 928 knots
        assert causal_rmse(res, truth) < 3.0
    skipped = [e.t for e in res.events if e.event == "fix skipped"]
    assert skipped
    assert any(e.event.startswith("re-initialised") and abs(e.t - skipped[0]) < 1e-6
               for e in res.events), res.events   # a forced one


def test_reinit_batch_of_a_straight_start_is_not_confidently_wrong():
    """The first 40 s of otter-dev-calm-a are one straight leg after a start-up transient
    the model does not know. Under the nominal process noise the batch of those fixes puts
    the model's error into a heading offset tens of degrees off with a sigma of a few
    degrees; choosing the noise by the evidence (what the online re-initialisation does)
    gives a heading within its sigma, and the nominal fit's error is above 3 sigma. With
    the smoother's own constants of another mission: those refined for dead reckoning
    (aqfg.fg.dead_reckoning, what fit_fg returns) make even the nominal fit right here
    (3.2 deg off, sigma 9 deg)."""
    from aqfg.fg.settings import FGSettings
    from aqfg.fg.fixed_lag import _mission_until
    other = BatchSmoother().run([load_mission(data_path("otter-dev-calm-b"))])
    init = {n: other.values[n] for n in ("k", "k_x", "k_yz")}
    m, truth = mission("otter-dev-calm-a", 8.0)
    view = _mission_until(m, 40.0)
    th = truth.params["theta_e"]
    est = ("theta_e", "s_x", "s_y")
    nominal = BatchSmoother(estimate=est, init=init,
                            settings=FGSettings().with_(batch={"adapt_noise": False})).run([view])
    adapted = BatchSmoother(estimate=est, init=init,
                            settings=FGSettings().with_(batch={"adapt_noise": True})).run([view])
    e_nom = abs(wrap(nominal.values["theta_e"] - th))
    e_ad = abs(wrap(adapted.values["theta_e"] - th))
    assert nominal.process_noise_scale == 1.0
    assert e_nom > 3 * nominal.sigma["theta_e"] and e_nom > 20 * DEG
    assert adapted.process_noise_scale >= 16.0
    assert e_ad < 10 * DEG and e_ad <= 2 * adapted.sigma["theta_e"]


def test_evidence_keeps_the_nominal_noise_when_the_model_is_right():
    """On aqfg's own simulator (the model is the vehicle) the evidence search keeps q = 1
    and the estimate is the nominal fit's."""
    from aqfg.fg.settings import FGSettings
    from aqfg.sim import simulate
    m, truth = simulate("asv", seed=4, duration=300.0, gnss_period=4.0)
    fixed = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    est = ("theta_e", "s_x", "s_y")
    a = BatchSmoother(estimate=est, init=fixed,
                      settings=FGSettings().with_(batch={"adapt_noise": True})).run([m])
    b = BatchSmoother(estimate=est, init=fixed).run([m])
    assert a.process_noise_scale == 1.0
    assert set(a.process_noise_evidence) == {1.0, 4.0}
    assert abs(a.values["theta_e"] - b.values["theta_e"]) < 1e-9


def test_online_survives_a_gtsam_failure(monkeypatch):
    """A failing smoother update (GTSAM's indeterminate-system and missing-key failures
    after marginalisation) is recovered by a restart and recorded, not raised."""
    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=3, duration=120.0, gnss_period=8.0)
    fl = FixedLagSmoother(window=24.0, settings=FGSettings().with_(online={"engine": "gtsam"}))
    fl.start(m, plan=True)
    for _ in range(5):
        fl.update()
    real = type(fl.backend.smoother).update
    calls = {"n": 0}

    def flaky(self, *a):
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("Indeterminate linear system detected while working near variable")
        return real(self, *a)
    monkeypatch.setattr(type(fl.backend.smoother), "update", flaky)
    while fl.pending():
        fl.update()
    res = fl.result()
    assert any(e.event.startswith("restarted") for e in res.events)
    assert np.all(np.isfinite(res.missions[0].track.pos))


def test_restart_while_held_keeps_the_hold_and_the_release_removes_only_it():
    """GTSAM engine, parameters held before the first batch: a restart builds a new
    smoother, so the hold priors' factor indices of the old one mean nothing there. The
    release used to remove the factors at those stale indices (the knot's prior: every
    later update indeterminate, the causal track 3.7 km off on otter-dev-calm-b)."""
    import gtsam

    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=3, duration=120.0, gnss_period=4.0)
    fl = FixedLagSmoother(window=24.0, settings=FGSettings().with_(online={"engine": "gtsam"}))
    fl.start(m, plan=True)
    for _ in range(3):
        fl.update()
    eng = fl.backend
    assert fl.held and eng.hold_idx
    eng.restart(fl.knots[-1])
    fg = eng.smoother.getFactors()
    nodes = {eng.node(g) for g in fl.layout.groups}
    assert len(eng.hold_idx) == len(fl.layout.groups)
    for i in eng.hold_idx:                     # the new smoother's own hold priors
        assert isinstance(fg.at(i), gtsam.PriorFactorVector) and set(fg.at(i).keys()) <= nodes
    fl.release(fl.knots[-1])
    assert fl.events[-1].event == "parameters released"
    while fl.pending():
        fl.update()
    skipped = [e for e in fl.events if e.event == "fix skipped"]
    assert not skipped, skipped
    assert np.all(np.isfinite(fl.result().missions[0].filtered.pos))


@pytest.mark.parametrize("gnss_period, t_first", [(4.0, 12.0), (8.0, 24.0)])
def test_a_failing_held_model_is_rescued_from_the_fourth_fix(gnss_period, t_first, monkeypatch):
    """Heading offset 150 deg off its start value, GNSS only, the constants given: the held
    model fails its fixes from the start. Its heading is re-seeded at the third fix (the
    GNSS fixes are scored without USBL too); where the re-seed cannot help, the first batch
    used to wait for six fixes (20 s at 4-s GNSS, 40 s at 8 s) and now runs at the fourth."""
    from aqfg.sim import simulate
    m, tr = simulate("asv", seed=12, duration=60.0, params={"theta_e": np.radians(150.0)},
                     gnss_period=gnss_period)
    assert m.usbl is None
    init = {n: tr.params[n] for n in ("k", "k_x", "k_yz")}

    def run():
        res = FixedLagSmoother(init=init).run(m)
        e = wrap(res.values["theta_e"] - tr.params["theta_e"])
        assert abs(e) < 10 * DEG and abs(e) <= 3 * res.sigma["theta_e"], (
            e / DEG, res.sigma["theta_e"] / DEG)
        return res.events
    ev = run()
    assert ev and ev[0].event.startswith("held heading re-seeded"), ev
    assert abs(ev[0].t - (t_first - gnss_period)) < 1e-6, ev
    monkeypatch.setattr(recovery, "reseed", lambda fl, t: None)
    ev = run()
    first = [e.t for e in ev if e.event.startswith(("re-initialised", "parameters released"))]
    assert first and abs(first[0] - t_first) < 1e-6, ev


def test_one_outlying_fix_does_not_make_a_held_model_fail():
    """The rescue's rule: two of the last three fixes beyond chi-square(2)'s 99 % quantile
    (their median), not their sum, which one USBL outlier 34 m off decided at 6.5 s of
    heldout-01 (1-s GNSS): the batch of 6.5 s with that fix last came out 100 deg off
    with sigma 3 deg, and the causal track ran 14 m off."""
    from aqfg.sim import simulate
    m, tr = simulate("asv", seed=3, duration=120.0, gnss_period=4.0)
    fl = FixedLagSmoother(init={n: tr.params[n] for n in ("k", "k_x", "k_yz")})
    fl.start(m, plan=True)
    for _ in range(4):
        fl.update()
    assert fl.held and not fl.policy.batch_tried
    t = float(fl.knots[-1])
    fl.gate.taken_m2 = [1.0, 2.0, 120.0]
    assert not recovery.reinit_due(fl, t)
    fl.gate.taken_m2 = [1.0, 30.0, 120.0]
    assert recovery.reinit_due(fl, t)
    # with the thrust/drag constants free the rescue waits for the sixth fix (a batch of
    # the first 8 s of heldout-32 with all six free came out 60 deg off)
    free = FixedLagSmoother()
    free.start(m, plan=True)
    for _ in range(4):
        free.update()
    free.gate.taken_m2 = [1.0, 30.0, 120.0]
    assert free.n_fix < 6 and not recovery.reinit_due(free, float(free.knots[-1]))


@pytest.mark.slow
def test_process_noise_adapts_only_when_the_model_is_wrong():
    """With the true parameters the fixes are explained and the process noise stays
    nominal; with the paper's parameters of another vehicle it grows."""
    from aqfg.sim import simulate
    m, truth = simulate("asv", seed=2, duration=300.0, gnss_period=4.0)
    true_fixed = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    good = FixedLagSmoother(init=true_fixed).run(m)
    bad = FixedLagSmoother(init={"k": 40.0, "k_x": 0.5, "k_yz": 0.3}).run(m)
    assert good.process_noise_scale <= 2.0
    assert bad.process_noise_scale >= 4.0 * good.process_noise_scale


@pytest.mark.slow
def test_online_holds_the_parameters_until_the_batch_start_then_follows_the_data():
    """Constants of a batch fit of another mission (calm-b) on calm-a at 8-s fixes: single
    incremental steps on the heading offset used to run off (178 deg off at the end). The
    parameters are held at their start values until the batch re-initialisation, then
    released, and the offset ends within 5 deg; the history before the restart is what
    was reported then (the start values), not the replay's."""
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    m, truth = mission("otter-dev-calm-a", 8.0)
    res = FixedLagSmoother(init=other.vehicle_constants(), effects=other.effects).run(m)
    ev = [e.event for e in res.events]
    assert "parameters released" in ev
    t_rel = min(e.t for e in res.events if e.event == "parameters released")
    h = res.history
    i = list(h.names).index("theta_e")
    before = h.values[h.t < t_rel, i]
    assert len(before) >= 3 and np.allclose(before, 0.0, atol=1e-3)     # held at the start
    # ... and reported with the prior's sigma, not the hold priors' (1e-3 of the scale),
    # which would claim a heading known to 0.03 deg while it is only held
    assert np.all(h.sigma[h.t < t_rel, i] >= 1.0)
    assert np.ptp(h.values[h.t > t_rel, i]) > 1 * DEG                   # then it moves
    assert abs(wrap(res.values["theta_e"] - truth.params["theta_e"])) < 5 * DEG


@pytest.mark.slow
def test_dense_fixes_start_the_batch_by_their_count():
    """With 1-s GNSS the held start (heading 30 deg off) dragged the causal track 5 m RMS
    off the fixes until the 20-s batch; the first batch now runs after
    ``online.init_fixes`` fixes when they come sooner, and the track follows the fixes."""
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    m, truth = mission("otter-dev-calm-a", 1.0)
    res = FixedLagSmoother(init=other.vehicle_constants(), effects=other.effects,
                           settings=MODEL_TRACK).run(m)
    first = min(e.t for e in res.events if "batch" in e.event)
    assert first - m.fix_times().min() < 15.0
    f = res.missions[0].filtered
    t = f.t - f.t[0]
    pt = np.column_stack([np.interp(f.t, truth.t, truth.pos[:, a]) for a in range(2)])
    err = np.linalg.norm(f.pos[:, :2] - pt, axis=1)
    assert np.sqrt(np.mean(err[t < 30.0] ** 2)) < 2.5, "the start drags the causal track"
    assert causal_rmse(res, truth) < 1.5


def test_online_without_the_vehicles_constants_estimates_them_and_says_so(caplog):
    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=4, duration=90.0, gnss_period=4.0)
    with caplog.at_level("WARNING"):
        res = FixedLagSmoother().run(m)
    assert {"k", "k_x", "k_yz"} <= set(res.estimated)
    assert any("estimates them too" in w for w in res.warnings)
    assert "--params-from" in caplog.text
    held = FixedLagSmoother(estimate=("theta_e", "s_x", "s_y")).run(m)
    assert "k" not in held.estimated
    assert any("another vehicle" in w for w in held.warnings)
    given = FixedLagSmoother(init={"k": 9.0, "k_x": 1.8, "k_yz": 0.15}).run(m)
    assert "k" not in given.estimated and not given.warnings


def crop(m, a: float, b: float):
    """The mission between a and b s: another start state and leg geometry, data no
    constant was chosen on."""
    from aqfg.data.mission import between
    return between(m, a, b)


@pytest.mark.slow
def test_an_implausibly_sliding_fit_is_replaced_by_a_plausible_one():
    """On this crop every start of the all-six batch slid 47 deg off the thrust axis
    (theta_e 51 deg off, |error|/sigma 5.4): implausible, so the fit is solved again with
    the sway drag held high, and says so. That held fit has its structural test too (it
    went without: its numpy system was not passed on), so the effect step adds the linear
    drag the data call for, whose fit is plausible with the sway drag free."""
    full = load_mission(data_path("otter-dev-calm-a"))
    truth = load_truth(data_path("otter-dev-calm-a"))
    m = with_gnss_every(crop(full, 0.0, 450.0), 8.0)
    given = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False},
                                                    graph={"prior_sigma": SLIDING}))
    res = fit_fg([m], settings=FGSettings().with_(graph={"prior_sigma": SLIDING}))
    assert "held_sway" in given.info and given.plausible
    assert "k_yz" not in given.estimated
    assert any("slid sideways" in w for w in given.warnings)
    assert given.structural_test is not None
    assert given.structural_test.called_for[0]["effect"] == "linear_drag"
    assert res.effect_step is not None and res.effect_step.adopted
    assert res.effects == ("linear_drag",)
    assert res.plausible and "k_yz" in res.estimated
    for r in (given, res):
        e = abs(wrap(r.values["theta_e"] - truth.params["theta_e"]))
        assert e < 3 * DEG and e <= 3 * r.sigma["theta_e"], (e / DEG, r.sigma["theta_e"] / DEG)


@pytest.mark.slow
def test_a_suspiciously_sliding_fit_names_the_non_sliding_answer():
    """On this crop the all-six fit of the model as given slides 32 deg (below the 45-deg
    implausibility, which the paper's own low-sway-drag vehicles need) with theta_e 36 deg
    off: the output keeps it but names the non-sliding fit, which is within 3 deg of the
    truth. The default fit adds the linear drag it lacks (untested: its sigma is inflated
    and no effect reaches the test's level) and is within 3 deg itself."""
    full = load_mission(data_path("otter-example"))
    truth = load_truth(data_path("otter-example"))
    m = with_gnss_every(crop(full, 300.0, 900.0), 4.0)
    res = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False},
                                                  graph={"prior_sigma": SLIDING}))
    alt = res.info["alternative_held_sway"]
    assert any("with the sway drag held high" in w for w in res.warnings)
    assert abs(wrap(alt["values"]["theta_e"] - truth.params["theta_e"])) < 3 * DEG
    assert abs(wrap(res.values["theta_e"] - truth.params["theta_e"])) > 30 * DEG
    auto = fit_fg([m], settings=FGSettings().with_(graph={"prior_sigma": SLIDING}))
    assert auto.effects == ("linear_drag",) and auto.effect_step is not None and auto.effect_step.untested
    check_batch(auto, truth)


def test_online_survives_a_diverged_prediction_in_the_numpy_engine():
    """otter-example from 150 s at 8-s fixes, all six online: a replayed update's
    prediction diverged, and the numpy engine's dynamics factor then lost its propagator
    (IndexError at the next relinearisation)."""
    m = with_gnss_every(crop(load_mission(data_path("otter-example")), 150.0, 900.0), 8.0)
    res = fit_fg([m], mode="online")
    assert res.engine.name == "numpy"
    assert np.all(np.isfinite(res.missions[0].track.pos))


@pytest.mark.slow
def test_online_does_not_restart_from_an_implausible_batch():
    """otter-dev-calm-b from 300 s at 4-s fixes, all six online: the 40-s re-initialisation
    batch put both currents at their 2 m/s bound and the thrust at 500x; replayed with
    those values held, every prediction diverged and the causal track ran 42 m RMS from
    the truth. Such a batch is implausible now, and not used."""
    full = load_mission(data_path("otter-dev-calm-b"))
    truth = load_truth(data_path("otter-dev-calm-b"))
    res = fit_fg([with_gnss_every(crop(full, 300.0, 838.0), 4.0)], mode="online")
    assert causal_rmse(res, truth) < 4.0
    assert not any(e.event == "prediction diverged" for e in res.events)


@pytest.mark.slow
def test_data_too_short_for_the_sandwich_get_the_evidence_noise():
    """Five minutes of otter-example at 8-s fixes: too few 60-s blocks for the sandwich,
    so the Hessian sigma alone claimed theta_e to 0.2 deg with an error of 2.7 deg; by
    default such data now get the evidence-chosen process noise, and an honest sigma."""
    from aqfg.data.mission import between
    from aqfg.fg.settings import FGSettings
    full = load_mission(data_path("otter-example"))
    th = load_truth(data_path("otter-example")).params["theta_e"]
    m = with_gnss_every(between(full, 60.0, 360.0), 8.0)
    auto = fit_fg([m])
    nominal = fit_fg([m], settings=FGSettings().with_(batch={"adapt_noise": False,
                                                             "structural_sigma": False}))
    assert auto.process_noise_scale > 1.0 and nominal.process_noise_scale == 1.0
    assert abs(wrap(nominal.values["theta_e"] - th)) > 3 * nominal.sigma["theta_e"]
    assert abs(wrap(auto.values["theta_e"] - th)) <= 3 * auto.sigma["theta_e"]


@pytest.mark.slow
def test_default_constants_online_no_worse_than_the_update_error_method():
    """The issue's target for the paper's default constants (of another vehicle): the
    factor graph's corrected and causal tracks no worse than the update-error method's on
    the same run. On the yaw-drift mission at 8-s fixes the process noise sits at its bound
    and, before the USBL gate, four range outliers (7-16 m) pulled the corrected track up to
    14 m off (1.71 m RMS against the update-error method's 1.31)."""
    from aqfg.ekf import fit_update_error
    m, truth = mission("otter-dev-yawdrift", 8.0)
    fg = fit_fg([m], mode="online")
    ue = fit_update_error([m], mode="online")
    for kind in ("track", "filtered"):
        f, u = (track_rmse(getattr(r.missions[0], kind), truth) for r in (fg, ue))
        assert f <= u, f"{kind}: factor graph {f:.2f} m, update-error method {u:.2f} m"
        # "never worse than a kinematic smoother": the constant-velocity filter's prediction
        # (causal) and smoother (corrected) on the same fixes, 3.66 and 1.23 m here
        tr = getattr(fg.missions[0], kind)
        causal, smooth = kinematic_baseline(m, tr.t)
        k = causal if kind == "filtered" else smooth
        e_kin = track_rmse(Track(tr.t, k[:, :2], k[:, 2:]), truth)
        assert f < 0.8 * e_kin, f"{kind}: factor graph {f:.2f} m, kinematic {e_kin:.2f} m"
    # the fixes left out are the gross outliers (from the truth: range or bearing more
    # than 10 sigma off), all but at most one: with the process noise at its bound (q = 256
    # here) the prediction over 4.5 s is about 1.8 m per axis, so a 6.7-m range outlier
    # (380 s) sits at the gate's 99.9 % quantile and is left out or not by the replay's
    # held values (left out with the 640-s batch's evidence-chosen noise, taken with the
    # nominal noise that batch now keeps; the tracks' RMSE above either way)
    u = m.usbl
    d = np.column_stack([np.interp(u.t, truth.t, truth.pos[:, a]) for a in range(3)]) \
        - np.asarray(m.usbl_station)
    e_r = u.range - np.linalg.norm(d, axis=1)
    e_b = np.angle(np.exp(1j * (u.bearing - np.arctan2(d[:, 1], d[:, 0]))))
    gross = set(u.t[(np.abs(e_r) > 1.5) | (np.abs(e_b) > 15 * DEG)].tolist())
    out = set(fg.rejected_usbl)
    assert len(gross) >= 5
    assert len(gross - out) <= 1, f"outliers kept: {sorted(gross - out)}"
    e_gross = np.maximum(np.abs(e_r) / 0.15, np.abs(e_b) / (1.5 * DEG))
    kept = [t for t in gross - out if e_gross[int(np.argmin(np.abs(u.t - t)))] > 60.0]
    assert not kept, f"outliers beyond 60 sigma kept: {kept}"
    assert len(out - gross) <= 2, f"good fixes left out: {sorted(out - gross)}"


@pytest.mark.slow
def test_the_fix_of_a_re_initialisation_reports_the_re_initialised_estimate():
    """At 4-s GNSS the first batch runs at the fix at 20 s; that fix's entry of the history
    is the batch's heading (data up to it, none later), not the held start value with its
    prior's sigma."""
    m, truth = mission("otter-example", 4.0)
    res = FixedLagSmoother(init={"k": 1.4, "k_x": 0.4, "k_yz": 4.0}).run(m)
    h = res.history
    i = list(h.names).index("theta_e")
    ev = [e.t for e in res.events if e.event.startswith("re-initialised")]
    assert ev and ev[0] in h.t.tolist()
    k = h.t.tolist().index(ev[0])
    assert abs(h.values[k - 1, i]) < 1e-3 and h.sigma[k - 1, i] > 1.0   # held, said so
    assert abs(h.values[k, i]) > 0.1 and h.sigma[k, i] < 0.5
    assert abs(wrap(h.values[k, i] - truth.params["theta_e"])) < 3 * h.sigma[k, i]


@pytest.mark.slow
@pytest.mark.parametrize("name, start, every", [("otter-dev-calm-a", 300.0, 4.0),
                                                ("otter-dev-current-weakprop", 150.0, 8.0)])
def test_the_usbl_gate_stands_down_when_the_track_is_off(name, start, every):
    """Crops where the model fails with the process noise still nominal, with the paper's
    constants: the gate left out the good fixes that held the track (causal RMSE 3.39 ->
    11.3 m on the first, 2.22 -> 3.45 m on the second). It stands down until the model has
    shown what it is (noise adapted up, or fixes explained); then it costs the causal
    track nothing."""
    from aqfg.data.mission import between
    full, truth = load_mission(data_path(name)), load_truth(data_path(name))
    m = with_gnss_every(between(full, start, float(full.imu.t[-1])), every)
    gated = fit_fg([m], mode="online")
    plain = fit_fg([m], mode="online", settings=FGSettings().with_(online={"gate_usbl": np.inf}))
    assert causal_rmse(gated, truth) <= causal_rmse(plain, truth) + 0.1


@pytest.mark.parametrize("name,t0", [("otter-dev-calm-a", 320.0), ("otter-example", 40.0)])
def test_a_short_batch_searches_the_heading_all_round(name, t0):
    """24 s of an Otter mission at 8-s fixes with another mission's constants (an online
    re-initialisation's batch): the closed form's start is poor on so little data and led
    to a heading basin 104 deg (calm-a from 320 s, sigma 5.5 deg) and 178 deg (example
    from 40 s) off; solving from the start turned by 90, 180 and 270 deg as well finds the
    basin of lower cost, within its sigma of the truth."""
    from aqfg.data.mission import between
    other = fit_fg([load_mission(data_path("otter-dev-calm-b"))])
    m, truth = mission(name, 8.0)
    r = BatchSmoother(estimate=("theta_e", "s_x", "s_y"), init=other.vehicle_constants(),
                      effects=other.effects,
                      settings=FGSettings().with_(batch={"adapt_noise": True})
                      ).run([between(m, t0, t0 + 24.0)])
    err = abs(wrap(r.values["theta_e"] - truth.params["theta_e"]))
    assert any(b["start"].startswith("turned heading start") for b in r.basins)
    assert err < np.radians(20.0) and err < 3.0 * r.sigma["theta_e"], (np.degrees(err),
                                                                      r.basins)


@pytest.mark.slow
def test_long_reinit_batch_keeps_the_nominal_noise_and_the_right_basin():
    """otter-heldout-46 (a held-out Otter mission, offset +146 deg), all six parameters online
    at 8-s fixes: the 640-s re-initialisation batch, solved with the process noise chosen by
    the evidence, slid into a hull sliding sideways 44 deg off and replaced a right online
    estimate, which ended 44 deg off with sigma 7.5 deg. A batch long enough for the
    sandwich (n_p + 2 blocks of 60 s) now keeps the nominal noise, as the whole-mission batch
    does; it still measures the factor by the evidence, which stays the floor of the online
    noise."""
    m, truth = mission("otter-heldout-46", 8.0)
    r = fit_fg([m], mode="online", estimate=("theta_e", "s_x", "s_y", "k", "k_x", "k_yz"))
    batches = r.reinit_batches
    n_p = 6
    long_ = [b for b in batches if b.t - m.t0 >= 60.0 * (n_p + 2)]
    short = [b for b in batches if b.t - m.t0 < 60.0 * (n_p + 1)]
    assert long_ and short
    assert all(not b.noise_by_evidence and b.process_noise_scale == 1.0 for b in long_)
    assert all(b.noise_by_evidence for b in short)
    assert all(b.process_noise_measured is not None for b in batches)
    assert r.process_noise_scale >= batches[-1].process_noise_measured
    i = list(r.history.names).index("theta_e")
    err = abs(wrap(r.history.values[-1, i] - truth.params["theta_e"]))
    assert err < 5 * DEG, np.degrees(err)
    assert err <= 3 * r.history.sigma[-1, i]


@pytest.mark.slow
def test_a_sliding_batch_does_not_replace_the_online_heading_within_its_own_sigma():
    """otter-heldout-44 (offset drifting +0.03 deg/s), online with the paper's constants at
    8-s fixes: the 640-s re-initialisation batch slides off the thrust axis (k_yz near zero)
    with theta_e 46 deg off the truth and a sigma of 22 deg; the online heading is 13 deg
    off. The restart tolerance was capped at 10 deg, so that batch replaced it and the run
    ended 44 deg off. A sliding batch (slip above plausibility.SUSPECT_SLIP) now restarts
    the smoother only beyond its own 3 sigma, or, where it names a non-sliding alternative
    (as this one does), beyond the alternative's."""
    from aqfg.fg import plausibility
    m, truth = mission("otter-heldout-44", 8.0)
    r = fit_fg([m], mode="online")
    sliding = [b for b in r.reinit_batches
               if b.slip_deg > plausibility.SUSPECT_SLIP and b.t > 600.0]
    assert sliding, r.reinit_batches
    for b in sliding:
        # judged by its non-sliding alternative where it names one, else by its own 3 sigma
        assert not b.restarted and (b.reference == "non-sliding alternative"
                                    or b.tolerance >= 3 * b.sigma_theta_e)
    i = list(r.history.names).index("theta_e")
    t_end = r.history.t[-1]
    th_true = truth.params["theta_e"] + truth.params["heading_drift.rate"] * t_end
    err = abs(wrap(r.history.values[-1, i] - th_true))
    assert err < 25 * DEG, np.degrees(err)


def test_a_failing_held_heading_is_reseeded_from_the_fixes():
    """otter-heldout-46 (offset +146 deg), the first 90 s at 4-s GNSS with all six parameters
    free from the defaults: held at theta_e = 0 until the first batch (which needs six fixes
    with the constants free), the causal track ran 20 m off, 5.0 m RMS over the first 40 s.
    While the held model fails, the held heading and current are re-seeded from the
    closed-form start of the fixes so far (global in theta_e) and replayed, still held."""
    from aqfg.data.mission import between
    full, truth = mission("otter-heldout-46", 4.0)
    m = between(full, 0.0, 90.0)
    r = FixedLagSmoother(settings=MODEL_TRACK).run(m)
    seeds = [e for e in r.events if e.event.startswith("held heading re-seeded")]
    assert seeds, r.events
    assert abs(wrap(seeds[0].details["theta_e_after"] - truth.params["theta_e"])) < 20 * DEG
    c = r.missions[0].filtered
    pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
    e = np.hypot(*(c.pos[:, :2] - pt).T)[c.t < m.t0 + 40.0]
    assert np.sqrt(np.mean(e ** 2)) < 4.0, np.sqrt(np.mean(e ** 2))


def test_a_held_heading_that_misses_the_third_fix_is_reseeded_there(monkeypatch):
    """remus-heldout-13 (offset +61 deg) from 3 s in, GNSS every 8 s on the surface, the
    paper's constants: the held heading (0) misses the third fix, the first that gives two
    legs (the update-error method's three-fix window has the heading there); re-seeded
    there, from the closed form of three fixes with the current held at zero, instead of at
    the fourth, the causal track's first 40 s are 2.0 m RMS from the truth instead of 3.6."""
    from aqfg.data.mission import between
    full, truth = mission("remus-heldout-13", 0.0)
    m = with_gnss_every(between(full, full.t0 + 3.0, full.t1), 8.0)
    third = float(np.unique(m.fix_times())[2])

    def early_rmse():
        r = fit_fg([m], mode="online", settings=MODEL_TRACK)
        seeds = [e.t for e in r.events if e.event.startswith("held heading")]
        c = r.missions[0].filtered
        pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
        e = np.hypot(*(c.pos[:, :2] - pt).T)[c.t < m.t0 + 40.0]
        return seeds, float(np.sqrt(np.mean(e ** 2)))
    seeds, rmse = early_rmse()
    assert seeds and seeds[0] == pytest.approx(third), (seeds, third)
    monkeypatch.setattr(policy, "RESEED_EARLY_FIXES", 4)     # from the fourth fix
    seeds4, rmse4 = early_rmse()
    assert seeds4 and seeds4[0] > third + 1.0
    assert rmse < 0.7 * rmse4, (rmse, rmse4)


def test_gnss_only_a_reseed_takes_the_speed_scale_and_beats_the_baseline(monkeypatch):
    """otter-heldout-93-40s (offset +175 deg) without its USBL, GNSS every 8 s, the paper's
    constants (another vehicle's): the held heading is re-seeded at the third fix, and
    with it the thrust gain by the closed form's speed scale (the paper's constants drive
    the Otter 2.4x too fast). Before, the heading re-seeded right still ran the causal track
    6-11 m off until the first batch at 40 s, and the whole run was above the update-error
    method's (6.3 m against 3.9)."""
    import dataclasses

    from aqfg.ekf import fit_update_error
    full, truth = mission("otter-heldout-93-40s", 0.0)
    m = with_gnss_every(dataclasses.replace(full, usbl=None), 8.0)
    third = float(np.unique(m.fix_times())[2])

    def causal(res):
        c = res.missions[0].filtered
        pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
        return c.t, np.hypot(*(c.pos[:, :2] - pt).T)

    def run():
        r = fit_fg([m], mode="online", settings=MODEL_TRACK)
        seeds = [e for e in r.events if e.event.startswith("held heading")]
        t, e = causal(r)
        return seeds, float(np.sqrt(np.mean(e ** 2))), float(np.max(e[(t > third) & (t < 40.0)]))
    seeds, rmse, after = run()
    assert seeds and seeds[0].t == pytest.approx(third), seeds
    s0 = seeds[0]
    assert abs(wrap(s0.details["theta_e_after"] - truth.params["theta_e"])) < 20 * DEG
    assert s0.details["k_after"] == pytest.approx(s0.details["k_before"] * s0.details["speed_scale"] ** 2)
    t_u, e_u = causal(fit_update_error([m], mode="online"))
    assert rmse < float(np.sqrt(np.mean(e_u ** 2))), (rmse, float(np.sqrt(np.mean(e_u ** 2))))
    assert after < 2.5, after
    monkeypatch.setattr(recovery, "RESEED_RHO", (0.0, np.inf))     # the heading alone
    _, rmse_h, after_h = run()
    assert after_h > 2.0 * after, (after_h, after)


def test_a_reseed_keeps_the_thrust_gain_where_the_speed_scale_is_not_determined(monkeypatch):
    """The same GNSS-only crop, the closed form's start replaced by one whose speed scale is
    13 +- 6.5 (what three fixes of a REMUS that had barely moved gave; scaled, k went 8 ->
    1357 and the causal track 21 m off): the heading is re-seeded, the thrust gain kept.
    With the same scale known to +- 0.5 it is scaled."""
    import dataclasses

    from aqfg.fg import init as fg_init
    full, truth = mission("otter-heldout-93-40s", 0.0)
    m = with_gnss_every(dataclasses.replace(full, usbl=None), 8.0)
    real = fg_init.candidate_starts

    def run(rho, sd):
        def starts(*a, **k):
            out = real(*a, **k)
            v_fix = 1.0                       # the crop's GNSS sigma: 1 m
            return [dataclasses.replace(s, rho=rho, rho_var=sd ** 2 / v_fix) for s in out]
        monkeypatch.setattr(fg_init, "candidate_starts", starts)
        r = fit_fg([m], mode="online")
        return [e for e in r.events if e.event.startswith("held heading")][0]
    e = run(13.0, 6.5)
    assert e.details["k_after"] == e.details["k_before"], e
    e = run(13.0, 0.5)
    assert e.details["k_after"] > 10.0 * e.details["k_before"], e


@pytest.mark.slow
def test_three_fixes_with_a_usbl_fix_reseed_neither_heading_nor_gain():
    """The same crop with its USBL, the third fix (a USBL fix, 6.5 s) made a 17-m range
    outlier, as on a fresh Otter mission where it gave a speed scale of 13 +- 3.8 (k x 170,
    the causal track 190 m off), and on another a heading 140 deg off (the causal track 20 m
    off): three fixes have none to spare, so neither the thrust gain nor the held heading is
    re-seeded from them; with the outlier a gross error beyond the gate, the causal track
    stays within tens of metres, not hundreds."""
    import dataclasses
    m, truth = mission("otter-heldout-93-40s", 8.0)
    third = float(np.unique(m.fix_times())[2])
    j = int(np.flatnonzero(np.abs(m.usbl.t - third) < 1e-9)[0])
    rng = m.usbl.range.copy()
    rng[j] += 17.0
    m = dataclasses.replace(m, usbl=dataclasses.replace(m.usbl, range=rng))
    r = fit_fg([m], mode="online", settings=MODEL_TRACK)
    seeds = [e for e in r.events if e.event.startswith("held heading")]
    assert not [e for e in seeds if e.t <= third + 1e-9], seeds
    assert all(e.details["k_after"] == e.details["k_before"] for e in seeds), seeds
    c = r.missions[0].filtered
    pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
    assert np.max(np.hypot(*(c.pos[:, :2] - pt).T)) < 50.0


@pytest.mark.slow
def test_a_sliding_batch_with_a_non_sliding_alternative_restarts_to_the_alternative():
    """otter-heldout-52-300s (the first 300 s of a held-out mission, 1-s GNSS), online with
    the default constants: the 256-s re-initialisation batch slides 16 deg off the thrust
    axis with theta_e 53 deg off and sigma 3 deg, and names a non-sliding alternative (the
    sway drag held high) that explains the fixes almost as well. Restarted to the sliding
    batch, the online heading ran 55 deg off; the alternative is now the reference. (The
    basins ranked by cost: ranked by evidence, the batch chooses a non-sliding basin itself,
    test_short_data_rank_heading_basins_by_their_evidence.)"""
    from aqfg.fg import plausibility
    m, truth = mission("otter-heldout-52-300s", 0.0)
    r = FixedLagSmoother(settings=BY_COST.with_(graph={"prior_sigma": SLIDING})).run(m)
    sliding = [b for b in r.reinit_batches if b.slip_deg > plausibility.SUSPECT_SLIP]
    assert sliding and all(b.reference == "non-sliding alternative" for b in sliding), \
        r.reinit_batches
    h = r.history
    i = list(h.names).index("theta_e")
    th = truth.params["theta_e"] + truth.params["heading_drift.rate"] * h.t
    err = np.abs(np.angle(np.exp(1j * (h.values[:, i] - th))))
    assert np.max(err[h.t >= sliding[0].t]) < 15 * DEG, np.degrees(err[h.t >= sliding[0].t])


def test_a_first_batch_that_explains_no_fix_is_not_used():
    """otter-heldout-42-90s (the first 90 s of a held-out mission, offset +99 deg), 4-s GNSS,
    all six parameters free from the defaults: the first batch (12 s) chose the process noise
    at its bound, with constants of a hull 4x faster and theta_e 70 deg off; released, the
    causal track ran 33 m off (8.9 m RMS over the first 40 s). Such a batch is not used
    while the constants are free: the parameters stay held (re-seeded from the fixes) until
    a batch explains them."""
    m, truth = mission("otter-heldout-42-90s", 4.0)
    r = FixedLagSmoother(settings=MODEL_TRACK).run(m)
    refused = [e for e in r.events if e.event.startswith(
        "batch re-initialisation explains no fix")]
    assert refused and refused[0].t - m.t0 < 15.0, r.events
    c = r.missions[0].filtered
    pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
    e = np.hypot(*(c.pos[:, :2] - pt).T)[c.t < m.t0 + 40.0]
    assert np.sqrt(np.mean(e ** 2)) < 6.5 and e.max() < 20.0, (np.sqrt(np.mean(e ** 2)), e.max())


def test_a_run_of_unexplained_fixes_raises_the_held_models_noise():
    """otter-heldout-66-90s (the first 90 s of a held-out mission, offset +153 deg), 4-s
    GNSS, all six parameters free from the defaults: while held (re-seeded at 11 s; its
    batches explain no fix until 40 s) the paper's constants run the model at 2 m/s
    against the Otter's 1.2. The process noise stayed nominal while the fixes the largest
    factor could not explain were a minority of the last ten, and the causal track ran
    5-10 m off the fixes for 17 s (7.8 m RMS over the first 60 s). Two such fixes among the
    last three are the model failing (aqfg.fg.noise.variance_factor)."""
    m, truth = mission("otter-heldout-66-90s", 4.0)
    r = FixedLagSmoother(settings=MODEL_TRACK).run(m)
    c = r.missions[0].filtered
    pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
    e = np.hypot(*(c.pos[:, :2] - pt).T)[c.t < m.t0 + 60.0]
    assert np.sqrt(np.mean(e ** 2)) < 6.0, np.sqrt(np.mean(e ** 2))


def test_an_ambiguous_batch_keeps_the_basin_of_the_online_estimate():
    """otter-heldout-73-170s (the first 170 s of a held-out mission whose offset drifts by
    +0.03 deg/s), 4-s GNSS, the default constants: the 160-s re-initialisation batch's best
    basin is 46 deg off the truth, and the solve from the online estimate (2 deg off) ends
    in a basin only 2.0 higher in cost -- within the batch's ambiguity margin. Restarted to
    the best, the online heading ran 41-46 deg off; the data do not decide between the two,
    and the solution from the online estimate is the reference (within 13 deg). (The
    basins ranked by cost: ranked by evidence, that batch chooses a basin 9 deg off.)"""
    m, truth = mission("otter-heldout-73-170s", 4.0)
    r = FixedLagSmoother(settings=BY_COST).run(m)
    own = [b for b in r.reinit_batches if b.reference.startswith("solution from")]
    assert own, r.reinit_batches
    h = r.history
    i = list(h.names).index("theta_e")
    th = truth.params["theta_e"] + truth.params["heading_drift.rate"] * h.t
    err = np.abs(np.angle(np.exp(1j * (h.values[:, i] - th))))
    after = h.t >= own[0].t
    assert np.max(err[after]) < 15 * DEG, np.degrees(err[after])


@pytest.mark.slow
def test_the_online_heading_follows_a_drifting_offset():
    """otter-heldout-44 (offset drifting +0.03 deg/s, 27 deg over the mission), 8-s GNSS, the
    paper's constants: with one heading offset per mission the online heading ended 16 deg
    behind the drifted offset; the walk of the heading offset in the window's past
    (FGSettings.online.heading_walk) lets it follow."""
    m, truth = mission("otter-heldout-44", 8.0)

    def end_error(settings):
        r = fit_fg([m], mode="online", settings=settings)
        h = r.history
        i = list(h.names).index("theta_e")
        th = truth.params["theta_e"] + truth.params["heading_drift.rate"] * h.t[-1]
        return abs(wrap(h.values[-1, i] - th))

    walk = end_error(FGSettings())
    const = end_error(FGSettings().with_(online={"heading_walk": 0.0}))
    assert FGSettings().online.heading_walk > 0
    assert walk < 10 * DEG and walk < 0.6 * const, (np.degrees(walk), np.degrees(const))


@pytest.mark.slow
def test_the_alternative_of_a_batch_that_does_not_determine_the_heading_is_not_used():
    """`otter-heldout-111` at 8-s fixes, online with the paper's constants: the 160-s
    re-initialisation batch kept one heading (its observability verdict: heading offset and
    cross current look alike) and named a non-sliding alternative 146 deg off; it replaced
    an online heading 23 deg off and the causal track ran up to 15 m off for 160 s. Such a
    batch's alternative is no longer the reference (its own solution, 24 deg off, is)."""
    d = data_path("otter-heldout-111")
    m = with_gnss_every(load_mission(d), 8.0)
    res = fit_fg([m], mode="online")
    b160 = [b for b in res.reinit_batches if abs(b.t - 160.0) < 1e-6]
    assert b160 and not b160[0].theta_e_determined and not b160[0].restarted
    assert b160[0].reference == "batch"
    assert track_rmse(res.missions[0].filtered, load_truth(d)) < 2.0


@pytest.mark.slow
def test_online_sigma_carries_how_much_the_given_constants_decide():
    """Online with constants that are not this vehicle's (the paper's, given explicitly, as
    --params-from another vehicle would): each re-initialisation batch is solved again with
    the constants free, and the reported sigma of the heading offset is at least the
    difference between the two solves (capped by the free solve's sigma where it does not
    determine the heading) until the next batch. On otter-example the difference reaches
    14-36 deg; with the constants held the batch's sigma was 5-14 deg."""
    from aqfg.model.params import OLD_PARAMS
    m = with_gnss_every(load_mission(data_path("otter-example")), 8.0)
    res = fit_fg([m], mode="online", init={n: float(OLD_PARAMS[n]) for n in ("k", "k_x", "k_yz")})
    h = res.history
    i = list(h.names).index("theta_e")
    free = [b for b in res.reinit_batches if b.constants_free is not None]
    assert free and max(b.constants_free.difference["theta_e"] for b in free) > 10 * DEG
    for b in free:
        k = min(int(np.searchsorted(h.t, b.t + 1e-6)), len(h.t) - 1)
        c = b.constants_free
        d = c.difference["theta_e"]
        if not c.theta_e_determined:
            # a free solve that does not determine the heading moves by about its sigma
            d = min(d, c.sigma_theta_e)
        assert h.sigma[k, i] >= 0.99 * d, (b.t, h.sigma[k, i], d)


CONSTANTS_201 = {"k": 1.947, "k_x": 0.0383, "k_yz": 0.7195,     # a batch fit of wide seed 201
                 "linear_drag.c_x": 1.1246, "linear_drag.c_yz": 0.0}


def test_data_too_short_for_the_closed_form_are_searched_over_the_heading():
    """The first 8 s of otter-heldout-208 (wide seed 208, theta_e 163.5 deg) at 8-s GNSS
    with another mission's constants: four fixes, too few and too slow for the closed-form
    start. Started at the null heading offset alone, the batch (the online rescue batch of
    that run) reported theta_e 146 deg off the truth with sigma 18 deg. The other quarters
    of the circle are started too: a basin near the truth fits almost as well, the output
    says the heading is ambiguous, and the sigma covers the truth."""
    from aqfg.data.mission import between
    m, truth = mission("otter-heldout-208-30s", 8.0)
    res = fit_fg([between(m, -np.inf, 8.0)], estimate=("theta_e", "s_x", "s_y"),
                 init=CONSTANTS_201, effects=("linear_drag",))
    starts = [b["start"] for b in res.basins]
    assert starts[0] == "null heading start (no closed form)"
    assert sum("(no closed form)" in s for s in starts) == 4
    near = [b for b in res.basins
            if abs(wrap(b["values"]["theta_e"] - truth.params["theta_e"])) < 20 * DEG]
    assert near, starts
    e = abs(wrap(res.values["theta_e"] - truth.params["theta_e"]))
    assert e <= 3 * res.sigma["theta_e"], (np.degrees(e), np.degrees(res.sigma["theta_e"]))
    assert any("the heading offset is ambiguous" in w for w in res.warnings)


def test_a_held_heading_is_not_reseeded_from_three_fixes_with_a_usbl_fix():
    """otter-heldout-281-60s (a --wide mission: 0.29 m/s current, a hull barely under way,
    USBL at 166 m with a 14-m range outlier at 6.5 s, the third fix), 8-s GNSS, the paper's
    constants: the closed form of the first three fixes put the heading 140 deg off and was
    re-seeded, and the causal track ran 21 m off the truth. Three fixes have no outlier to
    spare: the held heading now waits for a fourth, and the track stays nearer."""
    m, truth = mission("otter-heldout-281-60s", 8.0)
    third = float(np.unique(m.fix_times())[2])
    r = fit_fg([m], mode="online", settings=MODEL_TRACK)
    seeds = [e for e in r.events if e.event.startswith("held heading re-seeded")]
    assert seeds and seeds[0].t > third + 1e-9, seeds
    c = r.missions[0].filtered
    pt = np.column_stack([np.interp(c.t, truth.t, truth.pos[:, a]) for a in range(2)])
    assert np.max(np.hypot(*(c.pos[:, :2] - pt).T)) < 17.0


@pytest.mark.slow
def test_the_causal_track_has_a_kinematic_floor_while_the_parameters_are_held():
    """otter-heldout-281-60s, 8-s GNSS, the paper's constants (another vehicle's): while the
    parameters are held at start values no data chose (before the first batch), the model's
    prediction ran the causal track 7-12 m off the truth between fixes (5.8 m RMS over the
    minute). The causal track follows a constant-velocity filter on the fixes there (where
    it predicted the fixes better than the model beyond what the fixes' noise explains:
    :func:`aqfg.fg.kinematic.advantage_z`); the smoother and its estimates do not see it,
    and the model takes the track over at the fix that releases the parameters."""
    m, truth = mission("otter-heldout-281-60s", 8.0)

    def run(q: float):
        fl = FixedLagSmoother(window=24.0, settings=FGSettings().with_(online={"kinematic_q": q}))
        return fl, fl.run(m)

    fl, on = run(FGSettings().online.kinematic_q)
    _, off = run(0.0)
    e_on = track_rmse(on.missions[0].filtered, truth)
    e_off = track_rmse(off.missions[0].filtered, truth)
    # measured 4.5 against 6.2 m: at 8 s a GNSS fix (sigma 1 m) shows the model 8 m closer
    # than the filter, outweighing two USBL fixes (4-5 m tangential sigma) around it that
    # favour the filter, and the model keeps the track until 16 s
    assert e_off > 4.5 and e_on < 0.8 * e_off, (e_on, e_off)
    # the estimates, the corrected track and the model's knots after the release: the same
    np.testing.assert_array_equal(on.history.values, off.history.values)
    np.testing.assert_array_equal(on.missions[0].track.pos, off.missions[0].track.pos)
    t_model = fl._floor.until
    assert t_model < m.t1 and any(e.event.startswith("causal track follows the model")
                                  for e in on.events)
    after = on.missions[0].filtered.t >= t_model
    np.testing.assert_array_equal(on.missions[0].filtered.pos[after],
                                  off.missions[0].filtered.pos[after])
    assert not np.array_equal(on.missions[0].filtered.pos[~after],
                              off.missions[0].filtered.pos[~after])
    # before it, horizontally the filter's prediction from the fixes so far where it had
    # predicted the fixes better than the model (here most of the minute), else the model's
    causal, _ = kinematic_baseline(m, on.missions[0].filtered.t[~after])
    got = on.missions[0].filtered.pos[~after, :2]
    is_f = np.all(np.abs(got - causal[:, :2]) < 1e-9, axis=1)
    is_m = np.all(np.abs(got - off.missions[0].filtered.pos[~after, :2]) < 1e-9, axis=1)
    assert np.all(is_f | is_m) and is_f.sum() > is_m.sum(), (is_f.sum(), is_m.sum())


def test_the_sway_prior_fits_the_sliding_crops_without_a_rescue():
    """The two crops on which the all-six fit slid 32-47 deg under the paper vehicles' sway
    prior (above): with the default prior the model as given fits them within 3 deg of the
    truth's heading offset, plausible, with no held-sway fit or alternative."""
    for name, t0, t1, every in (("otter-dev-calm-a", 0.0, 450.0, 8.0),
                                ("otter-example", 300.0, 900.0, 4.0)):
        truth = load_truth(data_path(name))
        m = with_gnss_every(crop(load_mission(data_path(name)), t0, t1), every)
        r = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False}))
        assert r.plausible and "held_sway" not in r.info
        assert "alternative_held_sway" not in r.info and "k_yz" in r.estimated
        assert abs(wrap(r.values["theta_e"] - truth.params["theta_e"])) < 3 * DEG, name
