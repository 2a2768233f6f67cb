"""How well can any estimator know the heading offset after the 10th fix? A Cramér-Rao
bound on the Otter missions (tests/data), for the issue's "theta_e within 5 deg after the
tenth fix".

The bound gives the estimator more than it has: the vehicle's velocity through the water is
known exactly (taken from the truth), so the only unknowns are those of the paper's
kinematics, ``p(t) = p0 + Rz(theta_e) w(t) + s t`` (w: the water-relative displacement in
the IMU's heading frame, s: the current). Each fix adds its information (GNSS: sigma per
axis; USBL: range and bearing sigmas in their own directions); the current gets aqfg's
default prior (0.3 m/s per axis) or none, or is known. The Fisher information's inverse
gives the smallest sigma(theta_e) an unbiased estimator can have with these fixes; an
estimator with a model from another mission can only do worse.

Beside the bound, what estimators given that much actually get on these fixes: the closed
form of :func:`aqfg.fg.init.closed_form` (robust least squares of ``p0``, the current with
aqfg's prior, and a rotation and scale of ``w``) with ``w`` from the truth's water velocity,
and with ``w`` from the IMU's accelerometer (specific force rotated by the IMU attitude,
gravity added, integrated twice: the ground velocity's change, the start velocity taking
the current's place), errors in degrees.

Writes experiments/results/tenth_fix_bound.md. Run: ``python experiments/tenth_fix_bound.py``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.integrate import cumulative_trapezoid

sys.path.insert(0, str(Path(__file__).parent))
import common as C  # noqa: E402
from independent_vehicle import DATA, EVERY, MISSIONS, RESULTS  # noqa: E402

from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import with_gnss_every  # noqa: E402
from aqfg.fg.settings import FGSettings  # noqa: E402
from aqfg.model.retrace import fixes  # noqa: E402

N_FIX = 10


def rot(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def fix_information(m, t: np.ndarray, p: np.ndarray) -> list[np.ndarray]:
    """Per fix, the inverse of its horizontal NE covariance (m^-2)."""
    sn = FGSettings().graph.sensors
    out = []
    ut = m.usbl.t if m.usbl is not None else np.zeros(0)
    st = np.asarray(m.usbl_station, float) if m.usbl is not None else None
    for tk, pk in zip(t, p):
        j = int(np.searchsorted(ut, tk - 1e-6))
        if j < len(ut) and abs(ut[j] - tk) < 1e-6 and st is not None:
            d = pk[:2] - st[:2]
            rh = max(float(np.hypot(*d)), 1e-3)
            er = d / rh
            et = np.array([-er[1], er[0]])
            sr, sb = sn.usbl_sigmas(float(m.usbl.range[j]))
            # slant range: horizontal range error ~ slant error x (slant / horizontal)
            sl = float(np.hypot(rh, pk[2] - st[2]))
            cov = (sr * sl / rh) ** 2 * np.outer(er, er) + (sb * rh) ** 2 * np.outer(et, et)
        else:
            g = sn.gnss_sigma
            if m.gnss is not None and m.gnss.sigma is not None:
                i = int(np.searchsorted(m.gnss.t, tk - 1e-6))
                if i < len(m.gnss.t) and np.isfinite(m.gnss.sigma[i]) and m.gnss.sigma[i] > 0:
                    g = float(m.gnss.sigma[i])
            cov = g * g * np.eye(2)
        out.append(np.linalg.inv(cov))
    return out


def accelerometer_displacement(m, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    """Times and the horizontal displacement (n, 2) m from ``t0`` in the IMU's heading
    frame, integrated twice from the accelerometer (zero velocity at ``t0``)."""
    from aqfg.model.vehicle import quat_to_rot
    k = (m.imu.t >= t0) & (m.imu.t <= t1 + 0.05)
    t = m.imu.t[k]
    a = np.einsum("kij,kj->ki", quat_to_rot(m.imu.q[k]), m.imu.acc[k]) + np.array([0, 0, 9.81])
    v = cumulative_trapezoid(a, t, axis=0, initial=0.0)
    return t, cumulative_trapezoid(v, t, axis=0, initial=0.0)[:, :2]


def realised(m, t, p, t0: float, t10: float, th10: float, w_truth: tuple) -> dict:
    """The closed form's heading error (deg) at the 10th fix from the truth's water
    displacement and from the accelerometer's (see the module docstring)."""
    from aqfg.fg.init import closed_form
    out = {}
    for label, (tw, w) in (("truth_w", w_truth), ("acc", accelerometer_displacement(m, t0, t10))):
        cf = closed_form(w, tw, t, p, None, (0.3, 0.3))
        out[label] = (float("nan") if cf is None
                      else float(np.degrees(np.angle(np.exp(1j * (cf[0] - th10))))))
    return out


def bound_estimator(t, p, wk, info, t0: float, th0: float, prior: float = 0.3) -> float:
    """The bound's own estimator: weighted least squares (Gauss-Newton) of start position,
    current (prior ``prior`` m/s per axis) and theta_e, given the truth's water
    displacement ``wk`` at the fixes and their information matrices; its heading error
    (deg) at the truth ``th0``."""
    x = np.array([p[0, 0], p[0, 1], 0.0, 0.0, th0 + 0.3])
    for _ in range(50):
        H, g = np.zeros((5, 5)), np.zeros(5)
        for tk, pk, w_, W in zip(t, p, wk, info):
            R = rot(x[4])
            r = pk[:2] - (x[:2] + (tk - t0) * x[2:4] + R @ w_)
            J = np.zeros((2, 5))
            J[:, :2] = np.eye(2)
            J[:, 2:4] = (tk - t0) * np.eye(2)
            J[:, 4] = np.array([[0.0, -1.0], [1.0, 0.0]]) @ R @ w_
            H += J.T @ W @ J
            g += J.T @ W @ r
        H[2:4, 2:4] += np.eye(2) / prior ** 2
        g[2:4] -= x[2:4] / prior ** 2
        dx = np.linalg.solve(H, g)
        x += dx
        if np.max(np.abs(dx)) < 1e-10:
            break
    return float(np.degrees(np.angle(np.exp(1j * (x[4] - th0)))))


def bound(name: str, every: float) -> dict:
    m = with_gnss_every(load_mission(DATA / name), every)
    tr = load_truth(DATA / name)
    t_all, p_all = fixes(m)
    tu = np.unique(t_all)[:N_FIX]
    keep = t_all <= tu[-1] + 1e-9
    t, p = t_all[keep], p_all[keep]
    P = tr.params
    th = P["theta_e"] + P.get("heading_drift.rate", 0.0) * tr.t
    s_true = np.array([P.get("s_x", 0.0), P.get("s_y", 0.0)])
    # water-relative velocity in the IMU heading frame, integrated from the first fix
    vw = tr.vel[:, :2] - s_true
    vi = np.einsum("kij,kj->ki", np.stack([rot(-a) for a in th]), vw)
    w = cumulative_trapezoid(vi, tr.t, axis=0, initial=0.0)
    wk = np.column_stack([np.interp(t, tr.t, w[:, a]) for a in range(2)])
    wk -= np.array([np.interp(tu[0], tr.t, w[:, a]) for a in range(2)])
    th0 = float(np.interp(tu[0], tr.t, th))
    Rp = np.array([[0.0, -1.0], [1.0, 0.0]]) @ rot(th0)       # d Rz / d theta
    info = fix_information(m, t, p)
    out = {"mission": name, "every": every, "t10": float(tu[-1]), "n": len(t),
           "dist": float(np.hypot(*(np.interp(tu[-1], tr.t, tr.pos[:, 0]) - tr.pos[0, 0],
                                   np.interp(tu[-1], tr.t, tr.pos[:, 1]) - tr.pos[0, 1])))}
    for label, prior in (("none", 0.0), ("0.3", 1 / 0.3 ** 2), ("known", 1e12)):
        F = np.zeros((5, 5))                 # p0 (2), s (2), theta
        for tk, wk_, Wk in zip(t, wk, info):
            J = np.zeros((2, 5))
            J[:, :2] = np.eye(2)
            J[:, 2:4] = (tk - tu[0]) * np.eye(2)
            J[:, 4] = Rp @ wk_
            F += J.T @ Wk @ J
        F[2:4, 2:4] += prior * np.eye(2)
        out[label] = float(np.degrees(np.sqrt(np.linalg.inv(F)[4, 4])))
    out["wls"] = bound_estimator(t, p, wk, info, tu[0], th0)
    tw = np.linspace(tu[0], tu[-1], 200)
    ww = np.column_stack([np.interp(tw, tr.t, w[:, a]) for a in range(2)])
    out.update(realised(m, t, p, float(tu[0]), float(tu[-1]), float(np.interp(tu[-1], tr.t, th)),
                        (tw, ww - ww[0])))
    return out


def main() -> None:
    rows = [bound(n, e) for n in MISSIONS for e in EVERY]
    lines = [C.stamp(), "", "# θe after the 10th fix: the Cramér-Rao bound", "",
             "Smallest σ(θe) (°) any unbiased estimator can have from the first 10 fixes, "
             "given the vehicle's velocity through the water exactly (from the truth); "
             "unknowns: start position, current, θe (`experiments/tenth_fix_bound.py`). "
             "Columns: the current unknown with no prior, with aqfg's default prior "
             "(0.3 m/s per axis), and known. The last three: the errors (°) of the bound's own "
             "estimator (weighted least squares with the prior, the truth's water velocity), "
             "and of the closed form `aqfg.fg.init.closed_form` on the same fixes, given the "
             "water displacement from the truth, and from the IMU's accelerometer.", "",
             "| mission | GNSS every | 10th fix at (s) | distance from start (m) | "
             "σ, current free (°) | σ, current prior 0.3 m/s (°) | σ, current known (°) | "
             "error, the bound's estimator (°) | error, closed form, truth's water velocity (°) | "
             "error, closed form, accelerometer (°) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['mission']} | {r['every']:.0f} s | {r['t10']:.1f} | {r['dist']:.1f} | "
                     f"{r['none']:.1f} | {r['0.3']:.1f} | {r['known']:.2f} | "
                     f"{r['wls']:.1f} | {r['truth_w']:.1f} | {r['acc']:.1f} |")
    text = "\n".join(lines) + "\n"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "tenth_fix_bound.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
