"""The batch smoother's prior on the sway drag k_yz (FGSettings.graph.prior_sigma) lets a hull with
a large sway drag (a catamaran's, a keeled hull's) have it."""
from __future__ import annotations

import warnings

from aqfg.data.mission import with_gnss_every
from aqfg.fg.settings import FGSettings
from aqfg.fg.fit import fit_fg
from aqfg.sim.simulator import simulate


def test_a_large_sway_drag_is_estimated_not_held_by_the_prior():
    m, tr = simulate("asv", seed=5, duration=300.0, params={"k_yz": 20.0})
    m = with_gnss_every(m, 4.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False})).values["k_yz"]
        # a prior of the paper vehicle's size (0.9 1/m around 0.3) holds it far below
        paper = FGSettings().with_(batch={"auto_effect": False},
                                   graph={"prior_sigma": {"s_x": 0.3, "s_y": 0.3}})
        held = fit_fg([m], settings=paper).values["k_yz"]
    assert 10.0 < got < 40.0
    assert held < 5.0
