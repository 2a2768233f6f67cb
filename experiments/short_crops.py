"""Short stretches (``python experiments/short_crops.py``): the batch fit (all six
parameters) and the online fit with default constants on 80 crops of 2.5 and 5 min of the
Otter missions in tests/data, at 1- and 8-s GNSS plus USBL. One line per crop: theta_e
error (deg; the yaw-drift mission against the crop's mean), |error|/sigma, the current's
error (m/s) and its larger |error|/sigma of the two axes, and whether the
fit was held against sliding ("held"), named a non-sliding alternative ("named") or is
implausible ("IMPL"); the online causal RMSE (m). Committed run:
``results/short_crops.txt``, discussed in docs/independent-vehicle.md."""
from __future__ import annotations

import sys
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import common as C  # noqa: E402
import independent_vehicle as iv  # noqa: E402

from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import between, with_gnss_every  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def one(args) -> str:
    from aqfg.fg import fit_fg
    name, a, span, ge = args
    full = load_mission(DATA / name)
    tr = load_truth(DATA / name)
    b = min(a + span, float(full.imu.t[-1]))
    m = with_gnss_every(between(full, a, b), ge)
    out = f"{name[6:]:18s} [{a:4.0f},{b:4.0f}] {ge:g}s"
    try:
        r = fit_fg([m])
        th = tr.params["theta_e"] + tr.params.get("heading_drift.rate", 0.0) * 0.5 * (a + b)
        e = iv.wrap_deg(r.values["theta_e"] - th)
        flag = ("held" if "held_sway" in r.info else "named" if "alternative_held_sway" in r.info
                else "IMPL" if not r.plausible else "")
        ec = np.hypot(*(r.values[n] - tr.params.get(n, 0.0) for n in ("s_x", "s_y")))
        zc = max(abs(r.values[n] - tr.params.get(n, 0.0)) / r.sigma[n] for n in ("s_x", "s_y"))
        out += (f" | batch {e:6.1f} z={abs(e) / np.degrees(r.sigma['theta_e']):4.1f}"
                f" current {ec:5.3f} z={zc:4.1f} {flag}")
    except Exception as ex:  # a failure is a result here
        out += (f" | batch EXC {type(ex).__name__}: {str(ex)[:80]} @ "
                f"{traceback.extract_tb(ex.__traceback__)[-1].name}")
    try:
        r = fit_fg([m], mode="online")
        out += f" | default causal={iv.track_rmse(r.missions[0].filtered, tr):6.2f}"
    except Exception as ex:
        out += (f" | default EXC {type(ex).__name__}: {str(ex)[:80]} @ "
                f"{traceback.extract_tb(ex.__traceback__)[-1].name}")
    return out


def main() -> None:
    jobs = [(n, a, span, g) for n in iv.MISSIONS for a in (60.0, 200.0, 400.0, 600.0)
            for span in (150.0, 300.0) for g in (1.0, 8.0)]
    C.lines_to_results(one, jobs, "short_crops.txt")


if __name__ == "__main__":
    main()
