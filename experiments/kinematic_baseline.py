"""A wrong model against no model: the factor graph with the paper's constants (of another
vehicle) against a constant-velocity filter and smoother on the fixes alone
(:func:`aqfg.fg.kinematic.baseline_tracks`), the issue's "never does worse than a
kinematic smoother".

For every mission with truth under ``--data`` (default: the Otter missions and the REMUS
mission in tests/data) at 1-, 4- and 8-s GNSS (USBL as recorded): the online factor
graph's causal RMSE (first 60 s / whole run) against the filter's (its prediction from the
fixes so far), and the online corrected track and the batch smoothed track (all six
parameters) against the Rauch-Tung-Striebel smoother's. The kinematic tracks use the
factor graph's fix table and USBL gate, at PSD ``FGSettings.online_kinematic_q``.
Writes ``experiments/results/kinematic_baseline.md`` (``--out``).
Run: ``python experiments/kinematic_baseline.py [--data DIR --out FILE]``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from causal_start import SPLIT, run_missions  # noqa: E402

from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import with_gnss_every  # noqa: E402

MISSIONS = ("otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
            "otter-dev-current-weakprop", "otter-dev-yawdrift", "remus-dev-a")


def rmse(t: np.ndarray, pos: np.ndarray, truth, first: bool = False) -> float:
    """Horizontal RMSE (m) of positions ``pos`` at ``t`` against the truth (over the first
    ``SPLIT`` s only with ``first``)."""
    ref = np.column_stack([np.interp(t, truth.t, truth.pos[:, a]) for a in range(2)])
    d2 = np.sum((pos[:, :2] - ref) ** 2, axis=1)
    if first:
        d2 = d2[t - t[0] < SPLIT]
    return float(np.sqrt(np.mean(d2)))


def one(args) -> dict:
    path, every = args
    from aqfg.fg import FGSettings, fit_fg
    from aqfg.fg.common import robust_fix_table
    from aqfg.fg.kinematic import baseline_tracks
    m = with_gnss_every(load_mission(path), every)
    truth = load_truth(path)
    s = FGSettings()
    on = fit_fg([m], mode="online").missions[0]
    ba = fit_fg([m]).missions[0]
    causal = on.filtered if on.filtered is not None else on.track
    fixes = robust_fix_table(m, s)
    kc, _ = baseline_tracks(fixes, causal.t, q=s.online_kinematic_q, gate=s.online_gate_usbl)
    _, ks_on = baseline_tracks(fixes, on.track.t, q=s.online_kinematic_q,
                               gate=s.online_gate_usbl)
    _, ks_ba = baseline_tracks(fixes, ba.track.t, q=s.online_kinematic_q,
                               gate=s.online_gate_usbl)
    return {"mission": path.name, "every": every,
            "fg_causal": (rmse(causal.t, causal.pos, truth, True),
                          rmse(causal.t, causal.pos, truth)),
            "kin_causal": (rmse(causal.t, kc, truth, True), rmse(causal.t, kc, truth)),
            "fg_corrected": rmse(on.track.t, on.track.pos, truth),
            "kin_smoothed_on": rmse(on.track.t, ks_on, truth),
            "fg_batch": rmse(ba.track.t, ba.track.pos, truth),
            "kin_smoothed_ba": rmse(ba.track.t, ks_ba, truth)}


def summary(q: np.ndarray) -> str:
    return (f"{np.median(q):.2f}, {q.max():.2f}, {int(np.sum(q > 1))} of {len(q)}")


def main() -> None:
    rows, out, where, wall = run_missions(one, "kinematic_baseline", __doc__, MISSIONS)
    lines = [f"# The paper's constants against no model ({where})", "",
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
    out = out or Path(__file__).resolve().parent / "results" / "kinematic_baseline.md"
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
