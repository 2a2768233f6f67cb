"""Is a batch solution physically plausible? Detects the degenerate basins a misspecified
model can prefer.

When the model is not the vehicle, the lowest cost can belong to a solution no vessel can
realise: a heading offset tens of degrees off, with the vehicle sliding sideways through
the water (sway drag near zero), the process noise doing the work the thrust should do.
Two checks, neither tied to a particular vehicle:

* **slip**: a propeller pushes a hull along its thrust axis; the water-relative velocity
  of a propelled vehicle on a straight course is (nearly) along that axis. The median
  angle between the water-relative body velocity and the thrust axis, over the samples
  where the vehicle thrusts, moves and has held its course (heading within ``STRAIGHT_DEG``
  over the last ``STRAIGHT_S`` s), must stay below ``max_slip`` (45 deg: halfway to
  sideways). Above ``SUSPECT_SLIP`` (15 deg) the fit is suspect: the right fits of the
  Otter missions slip 1-4 deg and their sliding ones 32-47 deg, but the paper's own
  vehicles, whose sway drag is below their surge drag, slip 10-24 deg on aqfg's simulator
  (docs/independent-vehicle.md). In turns a hull
  with little sway drag really does slide (the paper's own ASV
  constants give 60 deg in a sustained turn), so turns are not judged; on straight legs
  any sway drag brings the slip to zero within seconds.
* **bounds**: an estimated thrust or drag constant pinned at its lower bound (no thrust,
  or no drag on an axis) is not a vehicle; nor is a current at its bound (a batch of the
  first 40 s of a crop of an Otter mission, all six free, put both components there).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model.frames import heading
from aqfg.model.reference import rot_z
from aqfg.model.vehicle import Model, attitude_at, demand

STRAIGHT_S = 10.0       # s of held course before a sample is judged
STRAIGHT_DEG = 10.0     # deg, largest heading change over that time
SUSPECT_SLIP = 15.0     # deg: a plausible fit slipping more is checked against a non-sliding one


@dataclass
class Plausibility:
    """Verdict on one solution."""
    plausible: bool
    slip_deg: float | None               # median slip angle (deg); None if not testable
    pinned: list[str] = field(default_factory=list)   # at a bound: constants low, currents
    reasons: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"plausible": self.plausible, "slip_deg": self.slip_deg,
                "pinned": list(self.pinned), "reasons": list(self.reasons)}


def slip_angle(model: Model, mission: Mission, t: np.ndarray, X: np.ndarray, p: np.ndarray
               ) -> float | None:
    """Median angle (deg) between the water-relative body velocity and the thrust axis at
    times ``t`` (states ``X`` (n, 6), parameters ``p``), over thrusting, moving samples on a
    held course; None when too few samples qualify."""
    if mission.motors is None or not len(mission.motors.t) or len(t) < 10:
        return None
    th = heading(p, t - model.t0)
    R_raw = attitude_at(mission, t)
    th = np.broadcast_to(th, t.shape)
    R = np.einsum("nij,njk->nik", np.array([rot_z(a) for a in th]), R_raw)
    v_r = X[:, 3:6] - np.array([p[model.index("s_x")], p[model.index("s_y")], 0.0])
    v_b = np.einsum("nji,nj->ni", R, v_r)
    jm = np.clip(np.searchsorted(mission.motors.t, t, side="right") - 1, 0, None)
    d = demand(mission.motors.u[jm])                      # (n, N)
    f_b = d @ model.geometry.dirs                         # (n, 3) thrust direction, body
    vh, fh = v_b[:, :2], f_b[:, :2]
    sv, sf = np.linalg.norm(vh, axis=1), np.linalg.norm(fh, axis=1)
    if not np.any(sf > 0) or not np.any(sv > 0):
        return None
    yaw = np.unwrap(np.arctan2(R_raw[:, 1, 0], R_raw[:, 0, 0]))
    yaw_before = np.interp(t - STRAIGHT_S, t, yaw, left=np.nan)
    straight = np.abs(yaw - yaw_before) < np.radians(STRAIGHT_DEG)     # NaN: not judged
    sel = (sf > 0.2 * np.percentile(sf, 90)) & (sv > max(0.25 * np.median(sv), 0.05)) & straight
    if sel.sum() < max(10, 0.1 * len(t)):
        return None
    c = np.abs(np.sum(vh[sel] * fh[sel], axis=1)) / (sv[sel] * sf[sel])
    return float(np.degrees(np.median(np.arccos(np.clip(c, 0.0, 1.0)))))


def check(model: Model, mission: Mission, t: np.ndarray, X: np.ndarray, p: np.ndarray,
          estimated: tuple[str, ...], max_slip: float = 45.0) -> Plausibility:
    """Slip and bound checks of one mission's solution (see the module docstring)."""
    reasons = []
    slip = slip_angle(model, mission, t, X, p)
    if slip is not None and slip > max_slip:
        reasons.append(f"the vehicle moves {slip:.0f} deg off its thrust axis through the water "
                       f"(a hull is pushed along it; above {max_slip:.0f} deg is not a vessel)")
    pinned, why = bounds(model, p, estimated)
    return Plausibility(not reasons and not why, slip, pinned, reasons + why)


def limits(model: Model, name: str) -> tuple[float, float]:
    """The open interval the magnitude of a thrust/drag constant or a current component must
    stay in (:func:`bounds`): above ten times a constant's lower bound, below 99 % of the
    current's bound."""
    spec = model.spec(name)
    if name in ("s_x", "s_y"):
        return -np.inf, 0.99 * spec.upper
    return spec.lower * 10.0, np.inf


def bounds(model: Model, p: np.ndarray, estimated: tuple[str, ...]) -> tuple[list[str], list[str]]:
    """The bounds check of the parameter vector ``p`` (see the module docstring): the
    estimated parameters pinned at a bound no vehicle has, and the reasons in words."""
    pinned: list[str] = [n for n in ("k", "k_x", "k_yz")
                         if n in estimated and p[model.index(n)] <= limits(model, n)[0]]
    reasons = [f"{', '.join(pinned)} at the lower bound (no thrust or no drag)"] if pinned else []
    at_bound = [n for n in ("s_x", "s_y") if n in estimated
                and abs(p[model.index(n)]) >= limits(model, n)[1]]
    if at_bound:
        pinned += at_bound
        reasons.append(f"{', '.join(at_bound)} at the {model.spec(at_bound[0]).upper:g} m/s "
                       "bound (a current no vehicle of this kind works in)")
    return pinned, reasons
