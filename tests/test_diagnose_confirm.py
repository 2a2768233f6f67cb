"""The pieces of the diagnose -> add loop that are pure maths: joint marginals of a chain
with parameters, the held-out paired test, the direction rule, shared information, and the
model file's reader/writer."""
import json
import math

import numpy as np
import pytest
import scipy.sparse as sp

from aqfg.diagnose.confirm import (
    MIN_GAIN,
    Evidence,
    HeldoutGain,
    direction_agrees,
    heldout_gain,
    implausible,
    practical_gain,
)
from aqfg.diagnose.heldout import HeldOut
from aqfg.diagnose.marginals import anchor_covariances
from aqfg.fg.score import LinearSystem, Projected, covariance, shared_information
from aqfg.model.modelfile import ModelFile, ModelFileError, read_model


def _chain_system(K=40, p=3, seed=0):
    """A whitened system with the graph's arrow shape: K knots of 6 (priors, dynamics
    linking consecutive knots, one measurement per knot) and p parameters seen by all."""
    rng = np.random.default_rng(seed)
    n = 6 * K + p
    rows = []
    for k in range(K):
        r = np.zeros((6, n)); r[:, 6 * k:6 * k + 6] = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
        r[:, 6 * K:] = rng.normal(size=(6, p)) * 0.2
        rows.append(r)
        if k + 1 < K:
            d = np.zeros((6, n))
            d[:, 6 * k:6 * k + 6] = -np.eye(6) - 0.1 * rng.normal(size=(6, 6))
            d[:, 6 * k + 6:6 * k + 12] = np.eye(6)
            d[:, 6 * K:] = rng.normal(size=(6, p)) * 0.5
            rows.append(d)
    A = sp.csr_matrix(np.vstack(rows))
    kc = np.arange(6 * K).reshape(K, 6)
    m = A.shape[0]
    return LinearSystem(A, np.zeros((m, 0)), np.zeros(m), (), np.zeros(m), np.zeros(m, "<U8"),
                        np.zeros(0), np.zeros(0), np.zeros(0), knots=[np.arange(K, dtype=float)],
                        knot_cols=[kc], param_cols={}), 6 * K + np.arange(p)


def test_anchor_covariances_equal_the_dense_inverse():
    lin, pcols = _chain_system()
    knots = np.array([0, 7, 20, 39])
    got = anchor_covariances(lin, 0, knots, pcols)
    N = (lin.A.T @ lin.A).toarray()
    full = np.linalg.inv(N)
    for i, k in enumerate(knots):
        idx = np.concatenate([lin.knot_cols[0][k], pcols])
        assert np.allclose(got[i], full[np.ix_(idx, idx)], rtol=1e-6, atol=1e-9)
    # and the sparse per-column solver agrees (same ridge)
    ref = covariance(lin.A, np.concatenate([lin.knot_cols[0][7], pcols]))
    assert np.allclose(got[1], ref, rtol=1e-8, atol=1e-12)


def test_anchor_covariances_fall_back_when_not_a_chain():
    lin, pcols = _chain_system(K=12)
    A = lin.A.toarray()
    extra = np.zeros((6, A.shape[1])); extra[:, 0:6] = np.eye(6); extra[:, 60:66] = -np.eye(6)
    lin.A = sp.csr_matrix(np.vstack([A, extra]))          # knot 0 linked to knot 10
    got = anchor_covariances(lin, 0, np.array([0, 10]), pcols)
    full = np.linalg.inv((lin.A.T @ lin.A).toarray())
    idx = np.concatenate([lin.knot_cols[0][10], pcols])
    assert np.allclose(got[1], full[np.ix_(idx, idx)], rtol=1e-6, atol=1e-9)


def _heldout(t, ll):
    n = len(t)
    S = np.repeat(np.eye(2)[None], n, axis=0)
    nis = -2 * np.asarray(ll) - 2 * np.log(2 * np.pi)      # so that .loglik == ll
    return HeldOut(np.array(["gnss"] * n), np.asarray(t, float), np.ones(n), np.zeros(n, int),
                   np.zeros(1), np.zeros((n, 2)), S, nis, np.ones(n), np.ones(n),
                   np.zeros(n, bool), [], np.zeros((n, 2)))


def test_heldout_gain_is_calibrated_and_paired():
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 900.0, 2.0)
    base = _heldout(t, rng.normal(size=len(t)))
    # the same fixes, no difference in expectation: p roughly uniform
    ps = []
    for s in range(200):
        r = np.random.default_rng(100 + s)
        other = _heldout(t, base.loglik + r.normal(scale=0.3, size=len(t)))
        ps.append(heldout_gain([base], [other], 60.0).p)
    ps = np.array(ps)
    assert 0.03 < np.mean(ps < 0.1) < 0.2
    # a real gain is seen, and the test pairs the fixes by (sensor, time)
    better = _heldout(t, base.loglik + 0.5 + rng.normal(scale=0.3, size=len(t)))
    g = heldout_gain([base], [better], 60.0)
    assert isinstance(g, HeldoutGain) and g.p < 1e-6 and g.n == len(t) and g.blocks == 15
    assert g.dll == pytest.approx(float(np.sum(better.loglik - base.loglik)))


def test_direction_rule():
    assert direction_agrees(np.array([2.0]), np.array([0.3]))
    assert not direction_agrees(np.array([2.0]), np.array([-0.3]))      # against the score
    assert not direction_agrees(np.array([2.0]), np.array([0.0]))       # did not move
    assert direction_agrees(np.array([1.0, -1.0]), np.array([0.5, 0.2]))  # g.delta > 0
    assert not direction_agrees(np.array([1.0, -1.0]), np.array([0.1, 0.5]))
    ev = Evidence(True, True, True, False, True, True)
    assert not ev.confirmed and ev.failed() == ["refit moves against the score's direction"]


def test_practical_gain_is_measured_beyond_the_noise():
    assert MIN_GAIN == 0.10
    assert practical_gain(1.0, 0.98) == pytest.approx(0.02)       # significant, negligible
    assert practical_gain(0.94, 0.61) == pytest.approx(0.351, abs=1e-3)
    assert practical_gain(1.62, 0.0) == 1.0                        # down to within the noise
    assert practical_gain(0.0, 0.0) == 0.0                         # nothing left to gain
    assert practical_gain(0.5, 0.6) < 0
    assert math.isnan(practical_gain(float("nan"), 0.3))
    ok = dict(score=True, lr=True, bic=True, direction=True, heldout=True, dr_error=True)
    assert Evidence(**ok).confirmed
    assert Evidence(**ok, practical=False).statistical and not Evidence(**ok, practical=False).confirmed
    assert not Evidence(**ok, plausible=False).confirmed
    assert "estimate implausible" in Evidence(**ok, plausible=False).failed()


def test_plausible_ranges_come_from_the_catalogue_and_the_hull():
    from types import SimpleNamespace

    from aqfg.model.effects import BUILTIN
    rt = BUILTIN["reverse_thrust"]
    assert implausible(rt, {"reverse_thrust.ratio": {"value": 1.63}}) == \
        ["ratio = 1.63 outside [0.3, 1.5]"]
    assert implausible(rt, {"reverse_thrust.ratio": {"value": 0.5}}) == []
    assert "thrust curve" in rt.absorbs
    la = BUILTIN["lever_arm"]
    arm = {"lever_arm.x": {"value": 1.0}, "lever_arm.y": {"value": 0.1},
           "lever_arm.z": {"value": 0.0}}
    assert implausible(la, arm) == []                               # no hull: catalogue range
    boat = SimpleNamespace(hull=(1.2, 0.9))
    assert implausible(la, arm, [boat]) == ["x = 1 m outside [-0.6, 0.6]"]
    assert "time offset" in la.absorbs
    # every built-in parameter's plausible range lies within its bounds and holds its null
    # and the typical value the simulator hides
    for e in BUILTIN.values():
        for s in e.specs():
            lo, hi = e.plausible_range(s)
            assert s.lower <= lo <= s.null <= hi <= s.upper, s.name
            assert s.typical is None or lo <= s.typical <= hi, s.name
            assert e.absorbs, e.name


def test_shared_information():
    rng = np.random.default_rng(2)
    m = 500
    a = rng.normal(size=m)
    b_same = 3 * a + 0.01 * rng.normal(size=m)
    b_indep = rng.normal(size=m)
    Ct = np.column_stack([a, b_same, b_indep])
    pr = Projected(Ct, np.zeros(m), ("a.x", "b.x", "c.x"), np.zeros(m), np.zeros(3),
                   np.zeros(3), np.zeros(3), m - 3, 0.0)
    assert shared_information(pr, ("a.x",), ("b.x",)) > 0.99
    assert shared_information(pr, ("a.x",), ("c.x",)) < 0.02


def _model_file():
    return ModelFile("asv", ("linear_drag", "reverse_thrust"),
                     {"k": {"value": 1.3, "sigma": 0.02}, "k_x": {"value": 0.05, "sigma": 0.01},
                      "k_yz": {"value": 2.0, "sigma": 0.3},
                      "linear_drag.c_x": {"value": 0.57, "sigma": 0.016},
                      "linear_drag.c_yz": {"value": 0.0, "sigma": math.nan},
                      "reverse_thrust.ratio": {"value": 0.53, "sigma": 0.023}},
                     {"m1": {"theta_e": {"value": -0.5, "sigma": 0.004}}}, {"made_by": "test"})


def test_model_file_round_trip(tmp_path):
    mf = _model_file()
    p = mf.write(tmp_path / "model.json")
    back = read_model(p)
    assert back.vehicle == "asv" and back.effects == ("linear_drag", "reverse_thrust")
    assert back.parameters["reverse_thrust.ratio"] == {"value": 0.53, "sigma": 0.023}
    assert math.isnan(back.parameters["linear_drag.c_yz"]["sigma"])
    # what a fit takes: the vehicle's fixed (and sensor) values, not the per-mission ones
    assert back.init() == {"k": 1.3, "k_x": 0.05, "k_yz": 2.0, "linear_drag.c_x": 0.57,
                           "linear_drag.c_yz": 0.0, "reverse_thrust.ratio": 0.53}
    with pytest.raises(FileExistsError):
        mf.write(p)


@pytest.mark.parametrize("edit, words", [
    (lambda d: d.update(format="aqfg-model/9"), "format"),
    (lambda d: d.update(vehicle="boat"), "vehicle"),
    (lambda d: d["effects"].append({"name": "warp_drive"}), "unknown effect 'warp_drive'"),
    (lambda d: d["effects"][0]["parameters"].update({"k": {"value": 1}}), "not a parameter of linear_drag"),
    (lambda d: d["fixed"].update(k={"value": "fast"}), "fixed.k.value"),
    (lambda d: d["fixed"].update(k={"value": -1.0}), "outside its bounds"),
    (lambda d: d["fixed"].update(theta_e={"value": 0.1}), "not a fixed parameter"),
])
def test_model_file_bad_input_names_the_key(tmp_path, edit, words):
    data = _model_file().to_json()
    edit(data)
    p = tmp_path / "model.json"
    p.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match=words):
        read_model(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_model(p)
