"""The multi-step predictions the dead-reckoning refinements minimise
(aqfg.fg.predictions): their exact Jacobian against central differences, for the thrust/drag
constants (by their logarithm) and for the current."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import data_path

from aqfg.data.io import load_mission
from aqfg.data.mission import with_gnss_every
from aqfg.fg import FGSettings, fit_fg
from aqfg.fg.predictions import MIN_LEAD, Predictions, segments


@pytest.fixture(scope="module")
def calm_b():
    m = with_gnss_every(load_mission(data_path("otter-dev-calm-b")), 8.0)
    return m, fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False}))


@pytest.mark.parametrize("names, logs", [(("k", "k_x", "k_yz"), True), (("s_x", "s_y"), False)])
def test_the_prediction_errors_jacobian_is_exact(calm_b, names, logs):
    # the Jacobian (the kernel's interval Jacobians chained along each prediction)
    # against central differences of the prediction errors
    m, r = calm_b
    model = r.model
    segs = segments(model, [m], r, 60.0)
    idx = np.array([model.index(n) for n in names])
    lg = np.full(len(names), logs)
    pred = Predictions(model, segs, [r.missions[0].p.copy()], idx, lg)
    assert pred.analytic
    v = np.array([r.values[n] for n in names])
    x = np.log(v) if logs else v
    J = pred.jacobian(x)
    Jn = np.empty_like(J)
    for c in range(len(names)):
        e = np.zeros(len(names))
        e[c] = 1e-6
        Jn[:, c] = (pred.residuals(x + e) - pred.residuals(x - e)) / 2e-6
    assert J.shape == (len(pred.residuals(x)), len(names))
    np.testing.assert_allclose(J, Jn, rtol=0, atol=1e-5 * np.abs(Jn).max())


def test_segments_predict_the_fixes_within_the_horizon_divided_by_their_lead(calm_b):
    m, r = calm_b
    segs = segments(r.model, [m], r, 60.0)
    assert len(segs) >= 10
    starts = np.array([s.t0 for s in segs])
    assert np.all(np.diff(starts) >= 60.0 / 4 - 1e-9)
    for s in segs:
        assert np.all((s.lead > 0) & (s.lead <= 60.0 + 1e-9))
    pred = Predictions(r.model, segs, [r.missions[0].p.copy()], np.array([r.model.index("k")]),
                       np.array([True]))
    x = np.log([r.values["k"]])
    lead = np.concatenate([np.repeat(s.lead, 2) for s in segs])
    np.testing.assert_allclose(pred.residuals(x), pred.errors(x) / np.maximum(lead, MIN_LEAD))
