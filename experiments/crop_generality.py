"""Generality check (``python experiments/crop_generality.py``): the independent-vehicle
targets on crops of the Otter missions in tests/data -- other start states and leg
geometry, data no constant was tuned on. One line per crop and fix rate; the committed
run is ``results/crop_generality.txt``, discussed in docs/independent-vehicle.md.

Per line: batch fg (all six) theta_e error (deg; yaw-drift mission against the mean over
the crop), its |error|/sigma and the current error (m/s); online fg with the constants of
another mission's batch fit: causal RMSE (m), theta_e error at the end and |error|/sigma;
online with the paper's default constants: causal and corrected-track RMSE (m) of the
factor graph and of the update-error method.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import common as C  # noqa: E402
import independent_vehicle as iv  # noqa: E402

from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import between, with_gnss_every  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
MISSIONS = ["otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
            "otter-dev-current-weakprop", "otter-dev-yawdrift"]
CROPS = [(150.0, 1e9), (300.0, 1e9), (0.0, 450.0)]


def one(args) -> str:
    from aqfg.ekf import fit_update_error
    from aqfg.fg import fit_fg
    name, (a, b), ge = args
    tr = load_truth(DATA / name)
    full = load_mission(DATA / name)
    b = min(b, float(full.imu.t[-1]))
    m = with_gnss_every(between(full, a, b), ge)
    d = fit_fg([load_mission(DATA / iv.DONOR[name])])
    init, d_eff = d.vehicle_constants(), d.effects
    P = tr.params
    out = f"{name[6:]:20s} [{a:4.0f},{b:4.0f}] {ge:g}s"
    try:
        r = fit_fg([m])
        th = P["theta_e"] + P.get("heading_drift.rate", 0.0) * 0.5 * (a + b)
        e = iv.wrap_deg(r.values["theta_e"] - th)
        ec = np.hypot(r.values["s_x"] - P.get("s_x", 0), r.values["s_y"] - P.get("s_y", 0))
        out += (f" | batch th={e:6.2f} z={abs(e) / np.degrees(r.sigma['theta_e']):4.1f} "
                f"cur={ec:.3f}")
    except Exception as ex:  # a failure is a result here
        out += f" | batch ERROR {type(ex).__name__}: {ex}"
    try:
        r = fit_fg([m], mode="online", init=init, effects=d_eff)
        h = r.history
        i = list(h.names).index("theta_e")
        e = iv.wrap_deg(h.values[-1, i] - iv.theta_true(tr, h.t[-1]))
        out += (f" | donor causal={iv.track_rmse(r.missions[0].filtered, tr):5.2f} "
                f"th_end={e:6.2f} z={abs(e) / np.degrees(h.sigma[-1, i]):4.1f}")
    except Exception as ex:
        out += f" | donor ERROR {type(ex).__name__}: {ex}"
    try:
        r = fit_fg([m], mode="online")
        u = fit_update_error([m], mode="online")
        uc = u.missions[0].filtered if u.missions[0].filtered is not None else u.missions[0].track
        out += (f" | default causal fg={iv.track_rmse(r.missions[0].filtered, tr):5.2f} "
                f"ue={iv.track_rmse(uc, tr):5.2f} "
                f"smooth fg={iv.track_rmse(r.missions[0].track, tr):5.2f} "
                f"ue={iv.track_rmse(u.missions[0].track, tr):5.2f}")
    except Exception as ex:
        out += f" | default ERROR {type(ex).__name__}: {ex}"
    return out


def main() -> None:
    jobs = [(n, c, g) for n in MISSIONS for c in CROPS for g in (4.0, 8.0)]
    C.lines_to_results(one, jobs, "crop_generality.txt")


if __name__ == "__main__":
    main()
