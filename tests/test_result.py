"""Typed Result attributes read and write the same facts as the ``info`` keys older code uses,
and each mission's estimates are written as their estimator gives them."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from aqfg.outputs import dumps
from aqfg.parameters_doc import per_mission_document
from aqfg.result import (
    SIGMA_ABSENT,
    SIGMA_NULL,
    Estimate,
    EstimateNote,
    ParamHistory,
    Result,
    SolveSummary,
)


def _result(info=None, history=None) -> Result:
    return Result("fg", "batch", ("k",), {"k": 8.0}, {"k": 0.1}, [], history=history,
                  info=dict(info or {}))


def test_typed_attributes_read_info():
    r = _result({"kernel": "cpp"})
    assert (r.kernel, r.settings) == ("cpp", None)


def test_the_solve_summary_is_read_as_converged_iterations_and_cost():
    r = _result()
    assert (r.converged, r.iterations, r.solve) == (None, None, None) and math.isnan(r.cost)
    r.solve = SolveSummary(True, 12.5, 7, 9)
    assert (r.converged, r.iterations, r.cost) == (True, 7, 12.5)
    assert not r.solve.hit_iteration_limit and "iterations" not in r.info
    r.solve = SolveSummary(False)                  # the update-error batch: converged only
    assert r.converged is False and r.iterations is None and math.isnan(r.cost)


def test_typed_fields_are_not_kept_in_info():
    r = _result()
    assert (r.per_mission, r.histories, r.events, r.reinit_batches, r.rejected_usbl) == \
        ({}, [], None, None, None)
    r.per_mission = {"m": {"s_x": Estimate(0.1, 0.02)}}
    h = ParamHistory(np.zeros(1), ("k",), np.ones((1, 1)), np.ones((1, 1)))
    r.histories = [h, h]
    assert r.info == {} and len(r.histories) == 2


def test_a_mission_estimate_is_written_as_its_estimator_gives_it():
    """parameters.json's ``per_mission`` entry: value and sigma (a NaN the writer makes null
    with its reason); the update-error method's verdict and note; a sigma it did not
    compute written null without a reason (batch) or left out (online). Marked not
    determined, the sigma is NaN and the first ``sigma_note`` stands."""
    assert Estimate(0.5, 0.01).document() == {"value": 0.5, "sigma": 0.01}
    ue = Estimate(-0.26, float("nan"), EstimateNote("not determined", "no information",
                                                    sigma_missing=SIGMA_NULL))
    d = ue.document()
    assert d == {"value": -0.26, "sigma": None, "verdict": "not determined",
                 "note": "no information"}
    assert list(d) == ["value", "sigma", "verdict", "note"] and not ue.sigma_computed
    on = Estimate(0.3, note=EstimateNote(sigma_missing=SIGMA_ABSENT))
    assert on.document() == {"value": 0.3} and not on.sigma_computed
    nd = on.not_determined("not determined: first").not_determined("second")
    d = nd.document()
    assert list(d) == ["value", "sigma", "sigma_note"] and math.isnan(d["sigma"])
    assert d["sigma_note"] == "not determined: first" and nd.sigma_computed
    doc = json.loads(dumps({"per_mission": per_mission_document({"a": {"s_y": ue, "k": nd}})}))
    assert doc["per_mission"]["a"]["s_y"]["sigma"] is None
    assert doc["per_mission"]["a"]["k"]["sigma"] is None
    # only the NaN the estimator computed has a null reason
    assert list(doc["null_reasons"]) == ["/per_mission/a/k/sigma"]


def test_the_online_records_are_written_in_their_documents_order():
    """parameters.json's ``online``: an event is ``t``, ``event``, then its own figures; a
    batch re-initialisation writes ``constants_free`` only where the constants were
    checked."""
    from aqfg.fg.online.records import ConstantsCheck, OnlineEvent, ReinitBatch
    from aqfg.parameters_doc import online_document
    ev = OnlineEvent(8.0, "fix skipped", {"error": "indeterminate"})
    assert list(ev.document().items()) == [("t", 8.0), ("event", "fix skipped"),
                                           ("error", "indeterminate")]
    b = ReinitBatch(16.0, 0.5, 0.1, 1.0, None, True, 12.0, 0.0, 0.2, 0.3, False, True,
                    "batch", 0.5, 0.1)
    d = b.document()
    assert "constants_free" not in d and list(d)[:3] == ["t", "theta_e", "sigma_theta_e"]
    assert d["process_noise_measured"] is None and d["reference"] == "batch"
    check = ConstantsCheck({"theta_e": 0.2}, 0.7, 0.05, {"theta_e": 0.05}, True, ["k"], 11.0)
    d = dataclasses.replace(b, constants_free=check).document()
    assert list(d)[-1] == "constants_free" and d["constants_free"]["free"] == ["k"]
    r = Result("fg", "online", ("k",), {"k": 8.0}, {"k": 0.1}, [], events=[ev],
               reinit_batches=[b], rejected_usbl=[96.5], process_noise_scale=2.0)
    assert list(online_document(r)) == ["events", "reinit_batches", "rejected_usbl",
                                        "process_noise_scale"]
    assert online_document(r)["rejected_usbl"] == [96.5]
