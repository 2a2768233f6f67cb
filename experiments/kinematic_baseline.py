"""A wrong model against no model: the factor graph with the paper's constants (of another
vehicle) against a constant-velocity filter and smoother on the fixes alone
(:func:`aqfg.fg.kinematic.baseline_tracks`), the issue's "never does worse than a
kinematic smoother".

For every mission with truth under ``--data`` (default: the Otter missions and the REMUS
mission in tests/data) at 1-, 4- and 8-s GNSS (USBL as recorded): the online factor
graph's causal RMSE (first 60 s / whole run) against the filter's (its prediction from the
fixes so far), and the online corrected track and the batch smoothed track (all six
parameters) against the Rauch-Tung-Striebel smoother's. The kinematic tracks use the
factor graph's fix table and USBL gate, at PSD ``FGSettings.online.kinematic_q``.
Writes ``experiments/results/kinematic_baseline.md`` (``--out``).
Run: ``python experiments/kinematic_baseline.py [--data DIR --out FILE]``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common as C  # noqa: E402
from causal_start import SPLIT, run_missions, split_rmse  # noqa: E402

from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import with_gnss_every  # noqa: E402

MISSIONS = ("otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
            "otter-dev-current-weakprop", "otter-dev-yawdrift", "remus-dev-a")


def one(args) -> dict:
    path, every = args
    from aqfg.fg import FGSettings, fit_fg
    from aqfg.fg.common import robust_fix_table
    from aqfg.fg.kinematic import KinematicFilter, baseline_tracks
    m = with_gnss_every(load_mission(path), every)
    truth = load_truth(path)
    s = FGSettings()
    on = fit_fg([m], mode="online").missions[0]
    ba = fit_fg([m]).missions[0]
    causal = on.filtered if on.filtered is not None else on.track
    fixes = robust_fix_table(m, s)
    kc, _ = baseline_tracks(fixes, causal.t, KinematicFilter.from_settings(s))
    _, ks_on = baseline_tracks(fixes, on.track.t, KinematicFilter.from_settings(s))
    _, ks_ba = baseline_tracks(fixes, ba.track.t, KinematicFilter.from_settings(s))
    fg_c, kin_c = split_rmse(causal.t, causal.pos, truth), split_rmse(causal.t, kc, truth)
    return {"mission": path.name, "every": every,
            "fg_causal": (fg_c[0], fg_c[2]), "kin_causal": (kin_c[0], kin_c[2]),
            "fg_corrected": split_rmse(on.track.t, on.track.pos, truth)[2],
            "kin_smoothed_on": split_rmse(on.track.t, ks_on, truth)[2],
            "fg_batch": split_rmse(ba.track.t, ba.track.pos, truth)[2],
            "kin_smoothed_ba": split_rmse(ba.track.t, ks_ba, truth)[2]}


def summary(q: np.ndarray) -> str:
    return (f"{np.median(q):.2f}, {q.max():.2f}, {int(np.sum(q > 1))} of {len(q)}")


def main() -> None:
    rows, out, where, wall = run_missions(one, "kinematic_baseline", __doc__, MISSIONS)
    lines = [C.stamp(), "", f"# The paper's constants against no model ({where})", "",
             f"{len(rows)} runs, {wall:.0f} s wall. RMSE (m) from the "
             "truth. Kinematic: a constant-velocity filter (causal) and Rauch-Tung-Striebel "
             "smoother on the fixes alone, with the factor graph's fix table and USBL gate. "
             f"Causal: first {SPLIT:.0f} s / whole run.", "",
             "| mission | GNSS every | fg causal | kinematic causal | fg online corrected | "
             "fg batch smoothed | kinematic smoothed |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(
            f"| {r['mission']} | {r['every']:.0f} s | "
            f"{r['fg_causal'][0]:.2f} / {r['fg_causal'][1]:.2f} | "
            f"{r['kin_causal'][0]:.2f} / {r['kin_causal'][1]:.2f} | "
            f"{r['fg_corrected']:.2f} | {r['fg_batch']:.2f} | {r['kin_smoothed_ba']:.2f} |")
    lines += ["", "Factor graph over the kinematic baseline (median, largest, runs above 1):",
              "", "| track | ratio |", "| --- | --- |"]
    for label, q in (
            ("causal, first minute", [r["fg_causal"][0] / r["kin_causal"][0] for r in rows]),
            ("causal, whole run", [r["fg_causal"][1] / r["kin_causal"][1] for r in rows]),
            ("online corrected / smoothed", [r["fg_corrected"] / r["kin_smoothed_on"]
                                             for r in rows]),
            ("batch smoothed / smoothed", [r["fg_batch"] / r["kin_smoothed_ba"]
                                           for r in rows])):
        lines.append(f"| {label} | {summary(np.array(q))} |")
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
