"""Recorded vehicle runs, scored against their own GNSS: both methods, batch and online.

``python experiments/real_vehicle.py DIR`` reads every mission directory under DIR
(aqfg-mission/1, each with a 5-Hz-or-so gnss.csv and no truth) and, per run:

* heading: the batch factor-graph theta_e +- sigma (GNSS every 8 s) beside a reference from
  the course over ground on straight legs (surge > 0.4 m/s, |yaw rate| < 0.1 rad/s, 2-s
  baselines between fixes): the median of course - reported yaw, its spread (1.4826 MAD) and
  its sigma (spread / sqrt(independent baselines) x 1.25, the median's efficiency);
  the same fit with 30 deg added to the reported yaw (recovery: the shift of theta_e + 30;
  a run that misses it is named with what ``aqfg fit`` says of its theta_e);
* batch, GNSS every 8 s (``--gnss-every 8``): RMSE of the smoothed track at the fixes it
  was not given; the model's 60-s prediction from the smoothed states (start every 5 s at
  a smoothed state, dead-reckon 60 s with the fitted model, RMSE against the fixes in
  those 60 s; median over starts) -- for the factor graph and the update-error method;
* batch, every fix: RMSE of the model-only re-trace (``inertial.csv``: from the first fix,
  model alone) against every fix, and the 60-s prediction from that fit's states;
* online (``--mode online``), the vehicle constants from a joint batch fit of the OTHER
  runs (``--params-from``), GNSS every 4 and 8 s: RMSE of the causal track (what the
  vehicle knew at each time) and of the corrected track against every fix;
* diagnosis (``aqfg diagnose RUN --auto``, ``diagnose_sequence``): the effects it adds, each
  with its estimate and the fall of the held-out dead-reckoning error beyond the fixes'
  noise, the RMS distance to the held-out fixes (bare -> final) beside their noise floor,
  and the effects that fit but are implausible at any step (with what they probably
  absorb) or are significant but negligible at the last; the check: every added effect
  within its plausible range (the mission's hull for a lever arm) and with a gain of at
  least ``min_gain``; and the factor graph's batch scores again with the model that
  diagnosis learned (``aqfg fit --model``; chosen on the run's own held-out fixes);
* wall times.

The fixes themselves are the reference: a GNSS error (1-2 m, correlated over seconds) is in
every RMSE. Writes experiments/results/real_vehicle.md (``--out FILE`` names another), stamped
with the command and the commit, with the checks at its end.
"""
from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from aqfg.data import load_mission  # noqa: E402
from aqfg.data.mission import Imu, Mission, with_gnss_every  # noqa: E402
from aqfg.fg import gnss_noise  # noqa: E402
from aqfg.fg.settings import FGSettings  # noqa: E402
from aqfg.model.measurements import sensor_positions  # noqa: E402
from aqfg.model.params import MEASUREMENT_EFFECTS  # noqa: E402
from aqfg.model.retrace import rollout  # noqa: E402
from aqfg.model.vehicle import attitude_at  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
METHODS = ("fg", "update-error")
HORIZON = 60.0          # s, model-only prediction
PRED_EVERY = 5.0        # s between prediction starts
INJECT = np.radians(30.0)


# ---------------------------------------------------------------- reference and scores
def yaw_of(m: Mission, t: np.ndarray) -> np.ndarray:
    """Reported yaw (rad, unwrapped) at times ``t``."""
    q = m.imu.q
    yaw = np.unwrap(np.arctan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]),
                               1 - 2 * (q[:, 2] ** 2 + q[:, 3] ** 2)))
    return np.interp(t, m.imu.t, yaw)


def wrap(a):
    return np.angle(np.exp(1j * np.asarray(a, float)))


def cog_reference(m: Mission, base: float = 2.0, v_min: float = 0.4, r_max: float = 0.1) -> dict:
    """Course over ground minus reported yaw on straight legs (module docstring)."""
    t, ne = m.gnss.t, m.gnss.ne
    j = np.searchsorted(t, t + base - 1e-6)
    ok = j < len(t)
    i = np.nonzero(ok)[0]
    j = j[ok]
    dt = t[j] - t[i]
    keep = np.abs(dt - base) < 0.5 * base
    i, j, dt = i[keep], j[keep], dt[keep]
    d = ne[j] - ne[i]
    speed = np.hypot(d[:, 0], d[:, 1]) / dt
    course = np.arctan2(d[:, 1], d[:, 0])
    tm = 0.5 * (t[i] + t[j])
    # yaw over the baseline: mean of the yaw at its fixes' times, and its largest rate
    grid = np.linspace(0.0, 1.0, 9)
    yw = np.array([yaw_of(m, t[i] + g * dt) for g in grid])
    rate = np.max(np.abs(np.diff(yw, axis=0)), axis=0) / (dt / (len(grid) - 1))
    # surge, not speed: a boat backing down a straight leg has course - yaw = 180 deg
    surge = speed * np.cos(course - yaw_of(m, tm))
    sel = (surge > v_min) & (rate < r_max)
    # time moving: fixes whose 2-s baseline is faster than v_min, times their spacing
    motion = float(np.sum(speed > v_min) * np.median(np.diff(t)))
    if sel.sum() < 3:
        return {"n": int(sel.sum()), "value": float("nan"), "spread": float("nan"),
                "sigma": float("nan"), "motion_s": motion, "straight_s": 0.0}
    e = wrap(course[sel] - yaw_of(m, tm[sel]))
    c = float(np.angle(np.mean(np.exp(1j * e))))
    r = wrap(e - c)
    med = c + float(np.median(r))
    spread = 1.4826 * float(np.median(np.abs(wrap(e - med))))
    # independent baselines: the straight time over the baseline
    ts = np.unique(np.round(tm[sel] / base))
    sigma = 1.2533 * spread / np.sqrt(max(len(ts), 1))
    return {"n": int(sel.sum()), "value": float(wrap(med)), "spread": spread, "sigma": float(sigma),
            "motion_s": motion, "straight_s": float(len(ts) * base)}


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def sensor_of(result, i: int = 0):
    """``(model, p)`` of a result whose model has GNSS sensor effects (a time offset, a lever
    arm: a fix is then compared with the antenna's position at its stamp as the model puts
    it, ``Model.h_gnss``), else None (the track's own position, the same number there)."""
    names = {e.name for e in result.model.effects}
    if not names & {e.name for e in MEASUREMENT_EFFECTS}:
        return None
    return result.model, result.missions[i].p


def _fix_positions(sensor, m: Mission, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Where the model puts the GNSS antenna at stamps ``t`` from states ``X`` (n, 6)."""
    model, p = sensor
    return sensor_positions(X, attitude_at(m, t), t - model.t0, p)[0][:, :2]


def track_error(track, t: np.ndarray, ne: np.ndarray, sensor=None, m: Mission | None = None
                ) -> np.ndarray:
    """Horizontal distance (m) of ``track`` from positions ``ne`` at times ``t`` in its span
    (``sensor``, ``m``: the fixes as the model predicts them, :func:`sensor_of`)."""
    k = (t >= track.t[0] - 1e-9) & (t <= track.t[-1] + 1e-9)
    if sensor is None or m is None:
        est = np.column_stack([np.interp(t[k], track.t, track.pos[:, a]) for a in range(2)])
    else:
        X = np.column_stack([np.interp(t[k], track.t, track.pos[:, a]) for a in range(3)]
                            + [np.interp(t[k], track.t, track.vel[:, a]) for a in range(3)])
        est = _fix_positions(sensor, m, t[k], X)
    return np.hypot(*(est - ne[k]).T)


def prediction_rmse(result, m: Mission, horizon: float = HORIZON, every: float = PRED_EVERY) -> float:
    """Median over starts (every ``every`` s on the smoothed track) of the RMSE of the model
    alone over ``horizon`` s against every fix in it (NaN: run shorter than the horizon)."""
    mr = result.missions[0]
    tr, model = mr.track, result.model
    sensor = sensor_of(result)
    t, ne = m.gnss.t, m.gnss.ne
    out = []
    for t0 in np.arange(t[0], t[-1] - horizon + 1e-9, every):
        x0 = np.array([np.interp(t0, tr.t, tr.pos[:, c]) for c in range(3)]
                      + [np.interp(t0, tr.t, tr.vel[:, c]) for c in range(3)])
        k = (t > t0 + 1e-9) & (t <= t0 + horizon + 1e-9)
        pr = rollout(model, m, mr.p, x0, t0, t[k])
        est = (pr.pos[1:, :2] if sensor is None else
               _fix_positions(sensor, m, t[k], np.hstack([pr.pos[1:], pr.vel[1:]])))
        out.append(_rms(np.hypot(*(est - ne[k]).T)))
    return float(np.median(out)) if out else float("nan")


def heldout_rmse(track, m: Mission, given: Mission, sensor=None) -> float:
    """RMSE of ``track`` at the fixes of ``m`` that ``given`` does not hold."""
    keep = ~np.isin(m.gnss.t, given.gnss.t)
    return _rms(track_error(track, m.gnss.t[keep], m.gnss.ne[keep], sensor, m))


# ---------------------------------------------------------------- fits
def fit(method: str, missions, **kw):
    t0 = time.perf_counter()
    if method == "fg":
        from aqfg.fg.fit import fit_fg
        r = fit_fg(missions, **kw)
    else:
        from aqfg.ekf.estimator import fit_update_error
        r = fit_update_error(missions, **kw)
    return r, time.perf_counter() - t0


def rotated(m: Mission, angle: float) -> Mission:
    """``m`` with ``angle`` (rad) added to the reported yaw."""
    q = m.imu.q
    c, s = np.cos(angle / 2), np.sin(angle / 2)
    # q_z(angle) (x) q: a yaw turn in the ground frame
    qn = np.column_stack([c * q[:, 0] - s * q[:, 3], c * q[:, 1] - s * q[:, 2],
                          c * q[:, 2] + s * q[:, 1], c * q[:, 3] + s * q[:, 0]])
    out = copy.copy(m)
    out.imu = Imu(m.imu.t, qn, m.imu.acc, m.imu.gyro)
    return out


def batch_scores(method: str, m: Mission, sparse: dict, dense: dict, heading: bool = True
                 ) -> dict:
    """``sparse``: keyword arguments of the fits of decimated fixes (the factor graph's
    settings with the GNSS noise measured on the other runs); ``dense``: of the fits of
    every fix; ``heading``: also the factor graph's verdict on theta_e and the +30 deg
    recovery."""
    row: dict = {}
    m8 = with_gnss_every(m, 8.0)
    r8, w8 = fit(method, [m8], **sparse)
    row["theta"] = (r8.values["theta_e"], r8.sigma.get("theta_e", float("nan")))
    row["heldout8"] = heldout_rmse(r8.missions[0].track, m, m8, sensor_of(r8))
    row["pred8"] = prediction_rmse(r8, m)
    row["retrace8"] = _rms(track_error(r8.missions[0].inertial, m.gnss.t, m.gnss.ne,
                                       sensor_of(r8), m))
    r1, w1 = fit(method, [m], **dense)
    row["retrace1"] = _rms(track_error(r1.missions[0].inertial, m.gnss.t, m.gnss.ne,
                                       sensor_of(r1), m))
    row["pred1"] = prediction_rmse(r1, m)
    row["theta1"] = (r1.values["theta_e"], r1.sigma.get("theta_e", float("nan")))
    row["wall_batch"] = w8 + w1
    row["constants1"] = r1.vehicle_constants()
    if method == "fg" and heading:
        # what aqfg fit writes (identifiability.settle): a heading offset the data do not
        # determine has no sigma, and a reason
        from aqfg.identifiability import settle
        said = copy.deepcopy(r8)
        settle(said, [m8])
        row["theta_note"] = ("" if np.isfinite(said.sigma["theta_e"])
                             else said.sigma_notes.get("theta_e", "not determined"))
        ri, wi = fit(method, [with_gnss_every(rotated(m, INJECT), 8.0)], **sparse)
        row["inject"] = float(np.degrees(wrap(ri.values["theta_e"] - r8.values["theta_e"] + INJECT)))
        row["wall_batch"] += wi
    return row


def donor_values(method: str, others: list[Mission], kw: dict) -> tuple[dict, tuple, float]:
    """The vehicle constants (and effects) of a joint batch fit of ``others``."""
    r, w = fit(method, others, **kw)
    return r.vehicle_constants(), tuple(r.effects), w


def online_scores(method: str, m: Mission, init: dict, effects: tuple, sparse: dict) -> dict:
    row: dict = {}
    for every in (4.0, 8.0):
        me = with_gnss_every(m, every)
        try:
            r, w = fit(method, [me], mode="online", init=dict(init), effects=effects, **sparse)
        except Exception as e:       # an estimator's failure is a result of the run, not the end
            print(f"{m.name} {method} online {every:.0f} s failed: {type(e).__name__}: {e}",
                  file=sys.stderr)
            row.update({f"causal{every:.0f}": float("nan"), f"corrected{every:.0f}": float("nan"),
                        f"wall_online{every:.0f}": float("nan")})
            row.setdefault("failed", []).append(f"online {every:.0f} s: {type(e).__name__}")
            continue
        mr = r.missions[0]
        causal = mr.filtered if mr.filtered is not None else mr.track
        row[f"causal{every:.0f}"] = _rms(track_error(causal, m.gnss.t, m.gnss.ne))
        row[f"corrected{every:.0f}"] = _rms(track_error(mr.track, m.gnss.t, m.gnss.ne))
        row[f"wall_online{every:.0f}"] = w
    return row


def diagnosis_scores(m: Mission) -> dict:
    """What ``aqfg diagnose RUN --auto`` says of one run (module docstring)."""
    from aqfg.diagnose.confirm import implausible
    from aqfg.diagnose.sequence import diagnose_sequence
    from aqfg.model.effects import resolve
    t0 = time.perf_counter()
    try:
        seq = diagnose_sequence([m])
    except Exception as e:       # a failure is a result of the run, not the end
        print(f"{m.name} diagnose failed: {type(e).__name__}: {e}", file=sys.stderr)
        return {"failed": f"{type(e).__name__}: {e}", "wall_diag": time.perf_counter() - t0}
    last = seq.diagnoses[-1]
    est = [", ".join(f"{n.split('.')[-1]} {v['value']:.3g}±{v['sigma']:.2g}"
                     for n, v in s.estimate.items()) for s in seq.steps]
    return {"added": [f"{s.effect} ({e}; {s.beyond_text()})" for s, e in zip(seq.steps, est)],
            "plausible": [not implausible(resolve(s.effect), s.estimate, [m]) for s in seq.steps],
            "gains": [float(s.gain) for s in seq.steps],
            "min_gain": float(last.settings.get("min_gain", float("nan"))),
            "implausible": list({c.effect: f"{c.effect} ({c.estimate_text()}; "
                                           f"{', '.join(c.implausible)}): {c.absorbs or '?'}"
                                 for d in seq.diagnoses for c in d.labelled("implausible")
                                 }.values()),
            "negligible": [c.effect for c in last.labelled("negligible")],
            "bare": seq.bare.rmse_raw, "final": seq.final.rmse_raw, "floor": seq.bare.noise_floor,
            "wall_diag": time.perf_counter() - t0,
            "model": seq.model_file() if seq.steps else None}


def learned_scores(m: Mission, model_file, sparse: dict, dense: dict) -> dict:
    """The factor graph's batch scores (:func:`batch_scores`) with the model the run's own
    diagnosis learned (as ``aqfg fit --model model.json``: its effects, its values to
    start from); the effects were chosen on this run's held-out fixes."""
    kw = {"effects": tuple(model_file.effects), "init": model_file.init()}
    try:
        return batch_scores("fg", m, {**sparse, **kw}, {**dense, **kw}, heading=False)
    except Exception as e:   # a failure is a result of the run, not the end
        print(f"{m.name} fit with the diagnosed model failed: {type(e).__name__}: {e}",
              file=sys.stderr)
        return failed_row(f"with the diagnosed model: {type(e).__name__}")


def failed_row(why: str) -> dict:
    """The scores of a method whose batch fit failed on a run: all NaN, and why."""
    nan = float("nan")
    row: dict = {k: nan for k in ("heldout8", "pred8", "retrace8", "retrace1", "pred1", "inject",
                                  "wall_batch", "wall_donor", "causal4", "corrected4", "causal8",
                                  "corrected8", "wall_online4", "wall_online8")}
    row.update(theta=(nan, nan), theta1=(nan, nan), theta_note="", failed=[why])
    return row


# ---------------------------------------------------------------- table
def f2(x, f="{:.2f}") -> str:
    return "n/a" if x is None or not np.isfinite(x) else f.format(x)


def table(runs: dict) -> str:
    names = sorted(runs)
    lines = ["## GNSS noise (AR(1) about a constant-velocity track; aqfg.fg.gnss_noise)", "",
             "| run | sigma m (own fixes) | tau s (own) | sigma m (other runs) | tau s (other runs) |",
             "|---|---|---|---|---|"]
    for n in names:
        a, b = runs[n].get("noise_own"), runs[n].get("noise")
        lines.append(f"| {n} | " + " | ".join(
            "white" if x is None else f"{getattr(x, k):.3f}" if k == "sigma" else f"{getattr(x, k):.1f}"
            for x in (a, b) for k in ("sigma", "tau")) + " |")
    lines += ["", "## Heading offset (batch factor graph, GNSS every 8 s)", "",
             "| run | moving s | straight s | theta_e deg | COG ref deg | spread deg | z | "
             "+30 deg recovery deg |",
             "|---|---|---|---|---|---|---|---|"]
    for n in names:
        r = runs[n]
        th, sg = r["fg"]["theta"]
        ref = r["cog"]
        z = wrap(th - ref["value"]) / np.hypot(sg, ref["sigma"])
        sig = f"± {np.degrees(sg):.1f}" + (", not determined" if r["fg"].get("theta_note") else "")
        lines.append(f"| {n} | {ref['motion_s']:.0f} | {ref['straight_s']:.0f} | "
                     f"{np.degrees(th):.1f} {sig} | "
                     f"{f2(np.degrees(ref['value']), '{:.1f}')} ± {f2(np.degrees(ref['sigma']), '{:.1f}')} | "
                     f"{f2(np.degrees(ref['spread']), '{:.1f}')} | {f2(z)} | {f2(r['fg']['inject'])} |")
    lines += ["", "## Model-only prediction (m; fg / update-error)", "",
              "| run | held-out smoothed, 8 s | 60-s prediction, 8 s | re-trace, 8 s | "
              "60-s prediction, all fixes | re-trace, all fixes |", "|---|---|---|---|---|---|"]
    for n in names:
        a, b = runs[n]["fg"], runs[n]["update-error"]
        lines.append(f"| {n} | " + " | ".join(f"{f2(a[k])} / {f2(b[k])}" for k in
                     ("heldout8", "pred8", "retrace8", "pred1", "retrace1")) + " |")
    lines += ["", "## Online, constants from the other runs (RMSE vs every fix, m; fg / update-error)",
              "", "| run | causal 4 s | corrected 4 s | causal 8 s | corrected 8 s |",
              "|---|---|---|---|---|"]
    for n in names:
        a, b = runs[n]["fg"], runs[n]["update-error"]
        lines.append(f"| {n} | " + " | ".join(f"{f2(a[k])} / {f2(b[k])}" for k in
                     ("causal4", "corrected4", "causal8", "corrected8")) + " |")
    if any("diagnosis" in runs[n] for n in names):
        lines += ["", "## Diagnosis (aqfg diagnose RUN --auto)", "",
                  "| run | added (estimate ± sigma; held-out error beyond the noise) | "
                  "held-out RMS bare -> final m (noise floor) | fits, but implausible: "
                  "probably absorbing | significant but negligible | time s |",
                  "|---|---|---|---|---|---|"]
        for n in names:
            d = runs[n].get("diagnosis", {})
            if "failed" in d or not d:
                lines.append(f"| {n} | failed: {d.get('failed', 'not run')} | | | | |")
                continue
            lines.append(f"| {n} | {'; '.join(d['added']) or 'nothing'} | {f2(d['bare'])} -> "
                         f"{f2(d['final'])} ({f2(d['floor'])}) | "
                         f"{'; '.join(d['implausible']) or '–'} | "
                         f"{', '.join(d['negligible']) or '–'} | {d['wall_diag']:.0f} |")
    learned = [n for n in names if "learned" in runs[n]]
    if learned:
        lines += ["", "## With the diagnosed model (aqfg fit --model, the run's own diagnosis; "
                  "m, fg as given -> with the model / update-error)", "",
                  "| run | 60-s prediction, 8 s | re-trace, 8 s | 60-s prediction, all fixes | "
                  "re-trace, all fixes |", "|---|---|---|---|---|"]
        for n in learned:
            a, b, c = runs[n]["fg"], runs[n]["learned"], runs[n]["update-error"]
            lines.append(f"| {n} | " + " | ".join(f"{f2(a[k])} -> {f2(b[k])} / {f2(c[k])}" for k in
                         ("pred8", "retrace8", "pred1", "retrace1")) + " |")
    lines += ["", "## Wall times (s; fg / update-error)", "",
              "| run | batch (8 s, all, +30 deg) | donor fit (other runs) | online 4 s | online 8 s |",
              "|---|---|---|---|---|"]
    for n in names:
        a, b = runs[n]["fg"], runs[n]["update-error"]
        lines.append(f"| {n} | " + " | ".join(f"{f2(a[k], '{:.1f}')} / {f2(b[k], '{:.1f}')}" for k in
                     ("wall_batch", "wall_donor", "wall_online4", "wall_online8")) + " |")
    return "\n".join(lines + ["", checks(runs)])


def checks(runs: dict) -> str:
    names = sorted(runs)
    out = ["## Checks", ""]
    ok_z, ok_inj, ok_sig, missed = [], [], [], []
    for n in names:
        r = runs[n]
        th, sg = r["fg"]["theta"]
        ref = r["cog"]
        if np.isfinite(ref["value"]):
            ok_z.append(abs(wrap(th - ref["value"])) <= 3 * np.hypot(sg, ref["sigma"]))
        ok_inj.append(abs(r["fg"]["inject"]) <= 1.0)
        if not ok_inj[-1]:                    # with what aqfg fit says of that heading
            note = r["fg"].get("theta_note")
            missed.append(n + (f", where aqfg fit reports theta_e {note}" if note else ""))
        if ref["motion_s"] >= 100:
            ok_sig.append(np.degrees(sg) <= 3.0)
    out.append(f"- (a) theta_e within 3 sigma of the COG reference: {sum(ok_z)}/{len(ok_z)} runs; "
               f"+30 deg recovered within 1 deg: {sum(ok_inj)}/{len(ok_inj)}"
               + (f" (not: {'; '.join(missed)})" if missed else "")
               + f"; sigma <= 3 deg with >= 100 s of motion: {sum(ok_sig)}/{len(ok_sig)}")
    for key, label in (("pred8", "60-s prediction (8 s)"), ("pred1", "60-s prediction (all fixes)"),
                       ("retrace1", "re-trace (all fixes)"), ("retrace8", "re-trace (8 s)")):
        a = np.array([runs[n]["fg"][key] for n in names])
        b = np.array([runs[n]["update-error"][key] for n in names])
        k = np.isfinite(a) & np.isfinite(b)
        out.append(f"- (b) {label}: fg no worse than update-error on {int(np.sum(a[k] <= b[k] + 1e-9))}"
                   f"/{int(k.sum())} runs; median {np.median(a[k]):.2f} vs {np.median(b[k]):.2f} m")
    if any("learned" in runs[n] for n in names):
        for key, label in (("pred1", "60-s prediction (all fixes)"),
                           ("retrace1", "re-trace (all fixes)")):
            a = np.array([runs[n].get("learned", runs[n]["fg"])[key] for n in names])
            b = np.array([runs[n]["update-error"][key] for n in names])
            k = np.isfinite(a) & np.isfinite(b)
            out.append(f"- (b) {label}, fg with the run's diagnosed model where it has one: no "
                       f"worse than update-error on {int(np.sum(a[k] <= b[k] + 1e-9))}/{int(k.sum())}"
                       f" runs; median {np.median(a[k]):.2f} vs {np.median(b[k]):.2f} m")
    for key in ("causal4", "corrected4", "causal8", "corrected8"):
        a = np.array([runs[n]["fg"][key] for n in names])
        b = np.array([runs[n]["update-error"][key] for n in names])
        out.append(f"- (c) online {key}: fg no worse than update-error on {int(np.sum(a <= b + 1e-9))}"
                   f"/{len(a)} runs; median {np.median(a):.2f} vs {np.median(b):.2f} m")
    fails = [f"{n} {k}: {', '.join(runs[n][k]['failed'])}" for n in names for k in METHODS
             if runs[n].get(k, {}).get("failed")]
    if fails:
        out.append("- failed (scored as n/a, counted against the method): " + "; ".join(fails))
    diags = [runs[n]["diagnosis"] for n in names if "diagnosis" in runs[n]]
    if diags:
        ok = [d for d in diags if "failed" not in d]
        added = [(p, g, d["min_gain"]) for d in ok for p, g in zip(d["plausible"], d["gains"])]
        good = sum(p and g >= mg - 1e-12 for p, g, mg in added)
        out.append(f"- (4) diagnosis: {len(ok)}/{len(diags)} runs diagnosed; effects named "
                   f"missing {len(added)} in all, {good} within their plausible range and with "
                   f"a held-out gain of at least the minimum; "
                   f"{sum(bool(d['implausible']) for d in ok)} runs with an effect that fits "
                   "but is implausible (reported as such, never added)")
    return "\n".join(out)


def import_csv_runs(folder: Path, map_path: Path, out: Path) -> Path:
    """Each ``*.csv`` of ``folder`` imported with the map ``map_path`` into ``out/<stem>``
    (as ``aqfg import csv``); returns ``out``."""
    import copy

    from aqfg.data.importers import import_log, load_map
    from aqfg.data.io import save_mission
    imap = load_map(str(map_path))
    for f in sorted(folder.glob("*.csv")):
        m = copy.copy(imap)
        m.name = f.stem
        save_mission(import_log("csv", str(f), m).mission, out / f.stem)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("dir", help="folder of mission directories (aqfg-mission/1 with gnss.csv), "
                                "or of CSV exports (with --map)")
    ap.add_argument("--map", default="", help="import map of the CSV exports in DIR "
                                              "(aqfg import csv; e.g. examples/maps/blueboat-csv.toml)")
    ap.add_argument("--out", default=str(RESULTS / "real_vehicle.md"), help="table to write")
    ap.add_argument("--runs", default="", help="comma-separated run names (default: all)")
    ap.add_argument("--save", default="", help="also pickle the per-run numbers to this file")
    ap.add_argument("--white", action="store_true",
                    help="factor graph: the fixes at their stated sigma (FGSettings.graph.gnss_noise=None)")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods (default: both)")
    ap.add_argument("--no-diagnosis", action="store_true", help="leave out aqfg diagnose --auto")
    args = ap.parse_args(argv)
    started = time.perf_counter()
    src = Path(args.dir)
    if args.map:                       # CSV exports: imported as `aqfg import csv` does
        src = import_csv_runs(src, Path(args.map), Path(tempfile.mkdtemp(prefix="aqfg-real-")))
    dirs = sorted(p for p in src.iterdir() if (p / "mission.toml").is_file())
    if args.runs:
        dirs = [p for p in dirs if p.name in args.runs.split(",")]
    if len(dirs) < 2:
        print(f"real_vehicle: error: {args.dir}: fewer than two mission directories", file=sys.stderr)
        return 3
    missions = {p.name: load_mission(p) for p in dirs}
    runs: dict = {}
    for n, m in missions.items():
        others = [o for k, o in missions.items() if k != n]
        runs[n] = {"cog": cog_reference(m)}
        noise = None if args.white else gnss_noise.measure(others, FGSettings().online.kinematic_q,
                                                             FGSettings().graph.sensors.gnss_sigma)
        runs[n]["noise_own"] = (None if args.white else
                                gnss_noise.measure([m], FGSettings().online.kinematic_q,
                                                   FGSettings().graph.sensors.gnss_sigma))
        runs[n]["noise"] = noise
        for method in args.methods.split(","):
            if method == "fg":
                sparse = {"settings": FGSettings().with_(graph={"gnss_noise": noise})}
                dense = {"settings": FGSettings().with_(graph={"gnss_noise": None})} if args.white else {}
            else:
                sparse = dense = {}
            try:
                row = batch_scores(method, m, sparse, dense)
                init, effects, wd = donor_values(method, others, dense)
            except Exception as e:   # an estimator's failure is a result of the run, not the end
                print(f"{n} {method} batch failed: {type(e).__name__}: {e}", file=sys.stderr)
                runs[n][method] = failed_row(f"batch: {type(e).__name__}")
                continue
            row.update(online_scores(method, m, init, effects, sparse))
            row["wall_donor"] = wd
            runs[n][method] = row
        if not args.no_diagnosis:
            d = runs[n]["diagnosis"] = diagnosis_scores(m)
            print(f"{n} diagnosis: {d}", file=sys.stderr, flush=True)
            if d.get("model") is not None:
                noise = runs[n]["noise"]
                runs[n]["learned"] = learned_scores(
                    m, d.pop("model"), {"settings": FGSettings().with_(graph={"gnss_noise": noise})},
                    {"settings": FGSettings().with_(graph={"gnss_noise": None})} if args.white else {})
            d.pop("model", None)
            print(f"{n} {method}: " + ", ".join(f"{k} {v:.2f}" for k, v in row.items()
                                                if isinstance(v, float)), file=sys.stderr, flush=True)
    if args.save:
        import pickle
        Path(args.save).write_bytes(pickle.dumps(runs))
    body = table(runs)
    print(body)
    from experiments.common import stamp
    foot = (f"\n\n---\nWall time {time.perf_counter() - started:.0f} s, "
            f"{time.strftime('%Y-%m-%d %H:%M')}.\n")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(stamp(argv, __file__) + "\n\n# Recorded runs, scored against their own GNSS\n\n"
                   + __doc__.split("\n\n", 1)[1]
                   .strip() + "\n\n" + body + foot)
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
