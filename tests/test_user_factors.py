"""Factors of the user's own (aqfg.fg.user_factors): GTSAM factors on a state or a
parameter key, added through the batch smoother's graph API, are solved with the rest."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from aqfg.fg.batch import BatchSmoother
from aqfg.fg.settings import FGSettings
from aqfg.sim import simulate

LOOSE = 1e3          # sigma of the entries a factor leaves free


@pytest.fixture(scope="module")
def sparse():
    """A 240-s ASV mission with a GNSS fix every 40 s: between fixes the track is the
    model's, and a known position in the middle of a gap has something to correct."""
    return simulate("asv", seed=11, duration=240.0, gnss_period=40.0, gnss_sigma=2.0)


def _settings() -> FGSettings:
    return FGSettings().with_(batch={"auto_effect": False, "heading_profile": False, "adapt_track": False})


def _at(track, t: float) -> np.ndarray:
    return np.array([np.interp(t, track.t, track.pos[:, j]) for j in range(3)])


def test_a_known_position_prior_on_a_state_key_is_solved(sparse):
    m, truth = sparse
    t_known = 100.0
    p_true = _at(truth, t_known)
    plain = BatchSmoother(settings=_settings()).run([m])
    seen = {}

    def mooring(keys):
        key, t = keys.state(t_known)
        seen["t"] = t
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[0.05, 0.05, 0.05, LOOSE, LOOSE, LOOSE])
        return [gtsam.PriorFactorVector(key, np.r_[_at(truth, t), 0.0, 0.0, 0.0], noise)]

    res = BatchSmoother(settings=_settings(), factors=mooring).run([m])
    tr = res.missions[0].track
    i = int(np.argmin(np.abs(tr.t - seen["t"])))
    err_plain = np.linalg.norm(_at(plain.missions[0].track, seen["t"])[:2] - p_true[:2])
    err = np.linalg.norm(tr.pos[i, :2] - _at(truth, seen["t"])[:2])
    assert err < 0.2, err                      # the solution goes through the known point
    assert err_plain > 2 * err                 # which the fixes alone did not give


def test_a_prior_on_a_parameter_key_moves_the_parameter(sparse):
    m, _ = sparse
    plain = BatchSmoother(settings=_settings()).run([m])
    target = 1.3 * plain.values["k"]

    def pin_k(keys):
        key, j = keys.param("k")
        dim = len(keys.layout.names["fixed"])
        mean, sig = np.zeros(dim), np.full(dim, LOOSE)
        mean[j], sig[j] = target, 1e-4 * target
        return [gtsam.PriorFactorVector(key, mean, gtsam.noiseModel.Diagonal.Sigmas(sig))]

    res = BatchSmoother(settings=_settings(), factors=pin_k).run([m])
    assert res.values["k"] == pytest.approx(target, rel=1e-3)
    assert abs(res.values["theta_e"] - plain.values["theta_e"]) < np.radians(20)


def test_keys_name_what_is_missing(sparse):
    m, _ = sparse

    def far(keys):
        keys.state(1e6)
        return []

    with pytest.raises(ValueError, match="no state knot"):
        BatchSmoother(settings=_settings(), factors=far).run([m])

    def unknown(keys):
        keys.param("no_such_parameter")
        return []

    with pytest.raises(KeyError, match="not an estimated parameter"):
        BatchSmoother(settings=_settings(), factors=unknown).run([m])
