"""Typed Result attributes read and write the same facts as the ``info`` keys older code uses."""
from __future__ import annotations

import math

import numpy as np

from aqfg.result import Estimate, ParamHistory, Result, SolveSummary


def _result(info=None, history=None) -> Result:
    return Result("fg", "batch", ("k",), {"k": 8.0}, {"k": 0.1}, [], history=history,
                  info=dict(info or {}))


def test_typed_attributes_read_info():
    r = _result({"per_mission": {"a": {"theta_e": {"value": 0.5, "sigma": 0.01}},
                                 "b": {"theta_e": {"value": 0.6}}},
                 "kernel": "cpp"})
    assert r.per_mission["a"]["theta_e"] == Estimate(0.5, 0.01)
    assert r.per_mission["b"]["theta_e"].value == 0.6 and math.isnan(r.per_mission["b"]["theta_e"].sigma)
    assert (r.kernel, r.settings) == ("cpp", None)


def test_the_solve_summary_is_read_as_converged_iterations_and_cost():
    r = _result()
    assert (r.converged, r.iterations, r.solve) == (None, None, None) and math.isnan(r.cost)
    r.solve = SolveSummary(True, 12.5, 7, 9)
    assert (r.converged, r.iterations, r.cost) == (True, 7, 12.5)
    assert not r.solve.hit_iteration_limit and "iterations" not in r.info
    r.solve = SolveSummary(False)                  # the update-error batch: converged only
    assert r.converged is False and r.iterations is None and math.isnan(r.cost)


def test_typed_attributes_write_info():
    r = _result()
    assert r.per_mission == {} and r.histories == [] and r.converged is None
    r.per_mission = {"m": {"s_x": Estimate(0.1, 0.02)}}
    assert r.info["per_mission"] == {"m": {"s_x": {"value": 0.1, "sigma": 0.02}}}
    h = ParamHistory(np.zeros(1), ("k",), np.ones((1, 1)), np.ones((1, 1)))
    assert _result(history=h).histories == [h]
    r.histories = [h, h]
    assert r.info["histories"] == [h, h] and len(r.histories) == 2


def test_per_mission_reads_a_sigma_the_estimator_could_not_give():
    """The update-error method writes ``"sigma": None`` (JSON null) for a parameter its
    window does not determine; the typed view reads it as NaN (it raised TypeError, which
    ended `aqfg fit --method update-error` on a 40-s mission)."""
    r = _result(info={"per_mission": {"a": {"s_y": {"value": -0.26, "sigma": None},
                                             "k": {"value": 8.0, "sigma": 0.1}}}})
    e = r.per_mission["a"]
    assert math.isnan(e["s_y"].sigma) and e["s_y"].value == -0.26
    assert e["k"].sigma == 0.1
