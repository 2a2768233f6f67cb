"""What a finished fit may claim: a parameter the data do not determine is reported "not
determined" with no sigma and a reason, never a Hessian sigma around an arbitrary value.

Two sources, for either estimator:

* the estimator's own verdicts (``Result.observability``: :mod:`aqfg.fg.observability`,
  :mod:`aqfg.ekf.uncertainty`), e.g. no thrust command, no motion, one heading;
* :func:`heading_against_accelerometer`: the fitted track's horizontal acceleration
  against the IMU's specific force turned into the ground frame with the fitted heading
  offset. The accelerometer measures along the hull's own axes, whatever the thrusters'
  signs, so it tells a heading offset from one turned by 180 degrees, which the motion
  model cannot: with a thruster's sign or direction reversed in the log, a fit explains
  the motion with the heading offset turned half a circle, and the vehicle then moves
  against its thrust (:data:`FLIPPED` degrees off the accelerometer).

:func:`settle` applies both to a :class:`aqfg.result.Result` in place.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NOT = "not determined"
WINDOW_S = 2.0          # s over which the track's and the accelerometer's acceleration are averaged
MIN_WINDOWS = 30        # fewer averaged windows: no verdict from the accelerometer
MIN_AGREEMENT = 0.5     # |correlation| of the two accelerations at their best rotation
DISAGREE_DEG = 45.0     # the accelerometer puts the heading this far from the fit's: not determined
FLIPPED_DEG = 120.0     # ... this far: the vehicle moves against its thrust
LARGE_OFFSET_DEG = 90.0  # without an accelerometer: a heading offset this large is questioned


@dataclass(frozen=True)
class HeadingCheck:
    """The fit's heading against the accelerometer's: ``offset_deg`` is the angle to add
    to the fitted heading offset for the accelerations to agree (wrapped to +-180),
    ``agreement`` their correlation at that rotation (1: the same signal), ``windows`` the
    number of averaged windows compared."""
    offset_deg: float
    agreement: float
    windows: int

    @property
    def telling(self) -> bool:
        return self.windows >= MIN_WINDOWS and self.agreement >= MIN_AGREEMENT


def _window_means(t: np.ndarray, x: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """Time averages of the samples ``x`` (n, d) over ``[c - half, c + half]`` (trapezoids
    of the cumulative integral)."""
    dt = np.diff(t)
    cum = np.vstack([np.zeros(x.shape[1]), np.cumsum(0.5 * (x[1:] + x[:-1]) * dt[:, None], axis=0)])
    hi = np.column_stack([np.interp(centres + half, t, cum[:, k]) for k in range(x.shape[1])])
    lo = np.column_stack([np.interp(centres - half, t, cum[:, k]) for k in range(x.shape[1])])
    return (hi - lo) / (2 * half)


def heading_against_accelerometer(mission, track, theta_e: float) -> HeadingCheck | None:
    """Compare the track's horizontal acceleration (velocity differences over
    :data:`WINDOW_S`) with the IMU's specific force, turned to the ground frame by the
    attitude and the heading offset ``theta_e`` (rad) and gravity removed, averaged over
    the same windows. None without accelerometer columns or a track of fewer than three
    states."""
    from aqfg.model.vehicle import quat_to_rot
    imu = mission.imu
    acc = getattr(imu, "acc", None)
    if acc is None or len(imu.t) < 3 or len(track.t) < 3:
        return None
    ok = np.all(np.isfinite(acc), axis=1)
    if ok.sum() < 3:
        return None
    t_imu = np.asarray(imu.t, dtype=float)[ok]
    c, s = math.cos(theta_e), math.sin(theta_e)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    with np.errstate(all="ignore"):
        a_world = np.einsum("ij,njk,nk->ni", rz, quat_to_rot(np.asarray(imu.q)[ok]),
                            np.asarray(acc, dtype=float)[ok])[:, :2]
    half = WINDOW_S / 2
    t_tr = np.asarray(track.t, dtype=float)
    lo = max(t_tr[0], t_imu[0]) + half
    hi = min(t_tr[-1], t_imu[-1]) - half
    if not hi > lo:
        return None
    centres = np.arange(lo, hi, WINDOW_S)
    v = np.asarray(track.vel, dtype=float)[:, :2]
    a_track = np.column_stack([np.interp(centres + half, t_tr, v[:, k])
                               - np.interp(centres - half, t_tr, v[:, k])
                               for k in range(2)]) / WINDOW_S
    a_imu = _window_means(t_imu, a_world, centres, half)
    good = np.all(np.isfinite(a_track), axis=1) & np.all(np.isfinite(a_imu), axis=1)
    if good.sum() < 3:
        return None
    z_track = a_track[good, 0] + 1j * a_track[good, 1]
    z_imu = a_imu[good, 0] + 1j * a_imu[good, 1]
    cross = np.sum(z_imu * np.conj(z_track))
    norm = math.sqrt(float(np.sum(np.abs(z_imu) ** 2) * np.sum(np.abs(z_track) ** 2)))
    if not norm > 0:
        return None
    # the accelerometer's heading is the fit's + offset: z_imu(theta_e) ~ z_track e^{-i offset}
    offset = -math.degrees(float(np.angle(cross)))
    return HeadingCheck(offset, float(abs(cross) / norm), int(good.sum()))


def _verdict(result, name: str) -> tuple[str | None, str]:
    """(verdict, reason) of ``name`` in either estimator's ``Result.observability``."""
    v = (result.observability or {}).get(name)
    if isinstance(v, dict):
        return v.get("verdict"), str(v.get("reason") or "")
    return v, str((result.sigma_notes or {}).get(name) or "")


def _mark_not_determined(result, name: str, reason: str) -> None:
    if result.observability is None:
        result.observability = {}
    obs = result.observability
    if _verdict(result, name)[0] == NOT:
        return                          # the estimator's own reason stands
    if isinstance(obs.get(name), dict):
        obs[name].update(verdict=NOT, reason=reason)
    else:
        obs[name] = NOT
        if result.sigma_notes is None:
            result.sigma_notes = {}
        result.sigma_notes[name] = reason


def heading_finding(check: HeadingCheck, theta_e: float, mission_name: str) -> str | None:
    """The words for a telling :class:`HeadingCheck` that disagrees with the fit, else None."""
    if not check.telling or abs(check.offset_deg) <= DISAGREE_DEG:
        return None
    fit_deg = math.degrees(math.remainder(theta_e, 2 * math.pi))
    if abs(check.offset_deg) > FLIPPED_DEG:
        return (f"{mission_name}: the vehicle moves against its thrust: the accelerometer puts "
                f"the heading {abs(check.offset_deg):.0f} deg from the fit's (theta_e "
                f"{fit_deg:.1f} deg), so the fit explained a reversed push with a heading "
                "offset turned half a circle. Likely cause: a thruster's command sign or its "
                "[thrusters] direction is reversed (or the heading offset is really near "
                "180 deg, with thrust reversed too); check motors.csv against mission.toml")
    return (f"{mission_name}: the accelerometer puts the heading {check.offset_deg:+.0f} deg "
            f"from the fit's (theta_e {fit_deg:.1f} deg): the motion model does not explain "
            "which way the vehicle accelerates")


def _mark(result, i: int, name: str, reason: str) -> None:
    """Mark ``name`` not determined for the ``i``-th mission of ``result``: in a joint fit
    where it is per mission, that mission's entry in ``result.per_mission`` (sigma NaN,
    ``sigma_note``; the first reason found stands) and, for the first mission, whose values
    the top level reports, the top-level verdict; otherwise the top-level verdict."""
    per = result.per_mission.get(result.missions[i].name) or {}
    if len(result.missions) > 1 and name in per:
        per[name] = per[name].not_determined(f"{NOT}: {reason}")
        if i > 0:
            return
    _mark_not_determined(result, name, reason)


def _mission_excitation(result, new: list[str]) -> None:
    """A joint fit's per-mission parameters that a mission's own inputs cannot determine
    (``Result.observability_per_mission``, :func:`aqfg.fg.observability.mission_verdicts`),
    each said in a warning naming the mission."""
    per = result.observability_per_mission or {}
    for i, mr in enumerate(result.missions):
        by_reason: dict[str, list[str]] = {}
        for name, reason in (per.get(mr.name) or {}).items():
            _mark(result, i, name, reason)
            by_reason.setdefault(reason, []).append(name)
        for reason, names in by_reason.items():
            new.append(f"{mr.name}: {', '.join(names)} not determined by this mission: "
                       f"{reason}")


def _heading_checks(result, missions, new: list[str]) -> None:
    """The accelerometer check of each mission's track (:func:`settle`)."""
    from aqfg.model.params import INDEX
    by_name = {m.name: m for m in missions}
    checks: dict[str, HeadingCheck] = {}
    for i, mr in enumerate(result.missions):
        m = by_name.get(mr.name)
        if m is None:
            continue
        th = float(mr.p[INDEX["theta_e"]])
        chk = heading_against_accelerometer(m, mr.track, th)
        if chk is None:
            if abs(math.remainder(th, 2 * math.pi)) > math.radians(LARGE_OFFSET_DEG):
                new.append(f"{mr.name}: the heading offset is {math.degrees(th):.0f} deg: "
                           "unless the compass is that far off, the vehicle moves against "
                           "its thrust (a thruster's command sign or [thrusters] direction "
                           "reversed); the IMU has no accelerometer columns to tell")
            continue
        checks[mr.name] = HeadingCheck(round(chk.offset_deg, 2), round(chk.agreement, 3),
                                       chk.windows)
        words = heading_finding(chk, th, mr.name)
        if not words:
            continue
        new.append(words)
        reason = ("the vehicle moves against its thrust (a reversed thruster sign or "
                  "direction?)" if abs(chk.offset_deg) > FLIPPED_DEG else
                  "the accelerometer disagrees with the fitted heading")
        # a joint fit's heading offset is each mission's own: only this mission's
        _mark(result, i, "theta_e", reason)
    if checks:
        result.heading_check = checks


def settle(result, missions=()) -> list[str]:
    """Apply the module's rules to ``result`` in place: the accelerometer check on each
    mission's track (a disagreement makes ``theta_e`` not determined: in a joint fit that
    mission's, whose ``per_mission`` entry gets sigma NaN and a ``sigma_note``), a joint
    fit's per-mission parameters that a mission's own inputs cannot determine (likewise),
    then a sigma of NaN (written ``null``) with the reason in ``result.sigma_notes`` for
    every parameter whose verdict is "not determined". Returns the new warnings (also appended
    to ``result.warnings``)."""
    new: list[str] = []
    if "theta_e" in result.estimated:
        _heading_checks(result, missions, new)
    _mission_excitation(result, new)
    if result.sigma_notes is None:
        result.sigma_notes = {}
    notes = result.sigma_notes
    per = result.per_mission
    # the top level reports the first mission's per-mission values: its verdict is theirs
    first = [result.missions[0].name] if len(result.missions) > 1 else list(per)
    for n in result.estimated:
        verdict, reason = _verdict(result, n)
        if verdict != NOT:
            continue
        result.sigma[n] = float("nan")
        notes[n] = f"not determined: {reason}" if reason else NOT
        for m in first:
            if n in (per.get(m) or {}):
                per[m][n] = per[m][n].not_determined(notes[n])
    for d in per.values():              # a mission's own verdict (update-error's entries)
        for n, e in d.items():
            if e.note is not None and e.note.verdict == NOT:
                d[n] = e.not_determined(f"{NOT}: {e.note.reason}" if e.note.reason else NOT)
    if new:
        result.warnings = [*result.warnings, *new]
    return new
