"""A NaN in gnss.csv's optional sigma column means "the default" for the library calls too
(not only after the command line's reader): both estimators give finite results."""
from __future__ import annotations

import numpy as np

from aqfg.data.mission import with_gnss_every
from aqfg.ekf import fit_update_error
from aqfg.fg import fit_fg
from aqfg.sim.simulator import simulate


def test_nan_gnss_sigma_rows_use_the_default():
    m, tr = simulate("asv", seed=5, duration=180.0)
    m = with_gnss_every(m, 4.0)
    sig = np.full(len(m.gnss.t), 1.0)
    sig[::3] = np.nan
    m.gnss.sigma = sig
    vehicle = {n: tr.params[n] for n in ("k", "k_x", "k_yz")}
    est = ("theta_e", "s_x", "s_y")
    fg = fit_fg([m], estimate=est, init=vehicle)
    ue = fit_update_error([m], mode="batch", estimate=est, init=vehicle)
    for r in (fg, ue):
        assert all(np.isfinite(r.values[n]) for n in ("theta_e", "s_x", "s_y"))
        assert np.isfinite(r.sigma["theta_e"]) and r.sigma["theta_e"] > 0
        assert abs(r.values["theta_e"] - tr.params["theta_e"]) < 4 * r.sigma["theta_e"] + 0.02
