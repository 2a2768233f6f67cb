"""Which parameters did the data determine? A verdict per parameter, so that a fit never
hands out a confident number the data cannot support (paper §III-F: flag unobservability
and non-convergence instead of hiding them).

Two sources, both reported:

* **information**: the share of a parameter's information that came from the data rather
  than from its (weak) prior, ``1 - sigma_post^2 / sigma_prior^2``, and its honest sigma
  relative to the parameter's typical magnitude (``ParamSpec.scale``);
* **excitation**: what the inputs actually did. Thrust and drag constants need thrust and
  motion through the water; the heading offset needs motion over ground (and, to be told
  apart from a current, more than one heading); the drag constants need the speed to vary.

Verdicts: ``determined`` (data information >= 90 % and sigma <= 0.2 x scale),
``weakly determined`` (data information >= 50 %), ``not determined`` (otherwise, or no
excitation), each with a reason in words.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model import retrace
from aqfg.model.vehicle import Model, attitude_at, yaw_of

DETERMINED = "determined"
WEAK = "weakly determined"
NOT = "not determined"


@dataclass
class Excitation:
    """What a mission's inputs and fixes excite (fractions of the mission time)."""
    thrust: float        # share of the mission time with a non-negligible command
    moving: float        # share of fix intervals with ground speed > 0.1 m/s
    heading_spread: float  # circular spread of the yaw while moving (rad, 0 = one heading)
    speed_cv: float      # coefficient of variation of the ground speed while moving
    fixes: int = 3       # absolute fixes (GNSS, USBL) the motion is measured by

    def as_dict(self) -> dict:
        return {"thrust": self.thrust, "moving": self.moving,
                "heading_spread_deg": float(np.degrees(self.heading_spread)),
                "speed_cv": self.speed_cv}


def thrust_share(mission: Mission, threshold: float = 0.05) -> float:
    """Share of the mission's span (its inputs' ``t0 .. t1``) during which some command
    exceeds ``threshold`` (commands held between rows; none outside the motors' rows, so
    commands that span no time excite nothing)."""
    mo = mission.motors
    if mo is None or len(mo.t) < 2 or not mo.t[-1] > mo.t[0] or not mission.t1 > mission.t0:
        return 0.0
    grid = np.linspace(mission.t0, mission.t1, 4001)
    on = np.max(np.abs(mo.u), axis=1) > threshold
    j = np.clip(np.searchsorted(mo.t, grid, side="right") - 1, 0, len(on) - 1)
    return float(np.mean(on[j] & (grid >= mo.t[0]) & (grid <= mo.t[-1])))


def excitation(mission: Mission) -> Excitation:
    """Excitation measures of one mission (see :class:`Excitation`)."""
    thrust = thrust_share(mission)
    t, p = retrace.fixes(mission)
    if len(t) < 3:
        return Excitation(thrust, 0.0, 0.0, 0.0, len(t))
    dt = np.diff(t)
    ok = dt > 1e-3
    v = np.linalg.norm(np.diff(p[:, :2], axis=0)[ok], axis=1) / dt[ok]
    tm = 0.5 * (t[1:] + t[:-1])[ok]
    # fix noise makes short intervals look fast: use intervals of >= 5 s
    if len(tm) and np.median(dt[ok]) < 5.0:
        step = int(np.ceil(5.0 / max(np.median(dt[ok]), 1e-3)))
        idx = np.arange(0, len(t), step)
        if len(idx) >= 3:
            d = np.diff(t[idx])
            v = np.linalg.norm(np.diff(p[idx, :2], axis=0), axis=1) / np.maximum(d, 1e-3)
            tm = 0.5 * (t[idx][1:] + t[idx][:-1])
    mov = v > 0.1
    moving = float(np.mean(mov)) if len(v) else 0.0
    spread = 0.0
    cv = 0.0
    if mov.sum() >= 3:
        yaw = yaw_of(attitude_at(mission, tm[mov]))
        R = np.abs(np.mean(np.exp(1j * yaw)))
        spread = float(np.sqrt(max(-2.0 * np.log(max(R, 1e-12)), 0.0)))
        cv = float(np.std(v[mov]) / max(np.mean(v[mov]), 1e-9))
    return Excitation(thrust, moving, spread, cv, len(t))


def lacking(n: str, ex: Excitation) -> str:
    """Why inputs of excitation ``ex`` cannot determine parameter ``n`` (words), or ""."""
    why = ""
    if n in ("k", "k_x", "k_yz") or n.startswith(("thrust_", "reverse_", "linear_drag")):
        if ex.thrust < 0.05:
            why = "the propellers were (almost) never commanded"
        elif ex.moving < 0.1:
            why = "the vehicle (almost) never moved"
        elif n in ("k_x", "k_yz") and ex.speed_cv < 0.05 and ex.heading_spread < np.radians(10):
            why = "one speed on one heading: thrust and drag are seen only as their ratio"
    if n in ("theta_e", "s_x", "s_y", "heading_drift.rate"):
        if n in ("theta_e", "heading_drift.rate") and ex.thrust < 0.05:
            # no push through the water: the heading offset turns nothing the model
            # predicts (as aqfg.ekf.uncertainty.no_motion_through_water)
            why = "the propellers were (almost) never commanded"
        elif ex.moving < 0.1:
            why = "the vehicle (almost) never moved over ground"
        elif ex.heading_spread < np.radians(10):
            why = "the vehicle kept one heading: a heading offset and a cross current look alike"
    if ex.fixes < 3:
        why = (f"only {ex.fixes} absolute fix{'es' if ex.fixes != 1 else ''} (GNSS, USBL): "
               "nothing measures the motion between them")
    return why


def mission_verdicts(model: Model, missions: list[Mission], estimated: tuple[str, ...]
                     ) -> dict[str, dict[str, str]]:
    """``{mission: {name: reason}}``: the per-mission parameters (group "variable") of a
    joint fit that a mission's own inputs cannot determine (:func:`lacking` of its
    excitation), where another mission's can; empty for one mission."""
    if len(missions) < 2:
        return {}
    names = [n for n in estimated if model.spec(n).group == "variable"]
    out: dict[str, dict[str, str]] = {}
    for m in missions:
        ex = excitation(m)
        why = {n: w for n in names if (w := lacking(n, ex))}
        if why:
            out[m.name] = why
    return out


def verdicts(model: Model, missions: list[Mission], estimated: tuple[str, ...],
             sigma: dict[str, float], sigma_model: dict[str, float],
             prior_sigma: dict[str, float]) -> dict[str, dict]:
    """``{name: {"verdict", "reason", "data_information"}}`` for the estimated parameters
    (the excitation the best of the missions gives; a joint fit's per-mission parameters
    each mission's alone: :func:`mission_verdicts`)."""
    ex = [excitation(m) for m in missions]
    best = Excitation(max(e.thrust for e in ex), max(e.moving for e in ex),
                      max(e.heading_spread for e in ex), max(e.speed_cv for e in ex),
                      max(e.fixes for e in ex))
    out: dict[str, dict] = {}
    for n in estimated:
        sp = prior_sigma.get(n, np.inf)
        sm = sigma_model.get(n, np.nan)
        sh = sigma.get(n, sm)
        info = float(1.0 - (sm / sp) ** 2) if np.isfinite(sm) and np.isfinite(sp) and sp > 0 \
            else float("nan")
        scale = model.spec(n).scale
        reason = ""
        no_excitation = lacking(n, best)
        if no_excitation:
            verdict, reason = NOT, no_excitation
        elif not np.isfinite(info) or info < 0.5:
            verdict, reason = NOT, "the prior, not the data, sets its value"
        elif info < 0.9 or not np.isfinite(sh) or sh > 0.2 * scale:
            verdict = WEAK
            reason = (f"sigma {sh:.3g} is large against its typical size {scale:g}"
                      if np.isfinite(sh) and sh > 0.2 * scale else
                      f"only {100 * info:.0f} % of its information comes from the data")
        else:
            verdict, reason = DETERMINED, ""
        out[n] = {"verdict": verdict, "reason": reason,
                  "data_information": None if not np.isfinite(info) else round(info, 4)}
    return out
