#!/usr/bin/env python3
"""Held-out Otter USV missions in aqfg-mission/1 format.

Physics: the Otter USV of Fossen's Python Vehicle Simulator (MIT licence; source
extracted to PVS_SRC), 6-DOF, stepped at 100 Hz with its own forward-Euler
`dynamics` (propeller shaft lag T_n = 0.1 s, k_pos/k_neg bollard curves, added mass,
linear + cross-flow damping, payload trim) and `attitudeEuler` kinematics. The only
change to the model is an optional per-propeller thrust scale (weak propeller), made
in a copy of `otter.dynamics` that is checked bit-for-bit against the original.

Conventions (verified against the example data's otter-*):
  * u = n / n_max in [n_min/n_max, 1] = [-0.978888, 1]; forward thrust k_pos n^2 =
    119.682 u|u| N per propeller; k = 119.682 / 85.5 kg = 1.3998.
  * truth velocity = ground velocity = water-relative velocity + current (PVS: nu is
    absolute, current V_c toward beta_c, s_x = V_c cos beta_c, s_y = V_c sin beta_c).
  * IMU reported yaw = true yaw - theta_e(t)  (true yaw = reported yaw + theta_e).
  * USBL bearing = atan2(east - e_s, north - n_s) (rad), range = slant range to station.

Usage:  PVS_SRC=.../PythonVehicleSimulator/src python experiments/heldout/otter_missions.py --out DIR [--seeds 1 2 ...]   (missions heldout-NN, seed NN)
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

import _pvs  # noqa: E402,F401  (the simulator on sys.path)
from aqfg.model.frames import wrap_angle as wrap  # noqa: E402
from aqfg.data.importers.frames import euler_to_quat  # noqa: E402
from python_vehicle_simulator.lib.gnc import Rzyx, Smtrx, attitudeEuler, crossFlowDrag, m2c, sat  # noqa: E402
from python_vehicle_simulator.vehicles.otter import otter  # noqa: E402

DT = 0.01            # s, simulation step (100 Hz)
CTRL_EVERY = 10      # controller / motors.csv / truth.csv at 10 Hz
IMU_EVERY = 2        # imu.csv at 50 Hz
G = 9.81
STATION = np.array([0.0, 0.0, 1.5])
U_MIN = None         # set from the model: n_min / n_max

# sensor noise (matched to the example Otter missions in tests/data)
SIG_RP = math.radians(0.5)     # IMU roll/pitch (white)
SIG_YAW = math.radians(0.3)    # IMU yaw (white)
SIG_GYRO = 0.01                # rad/s
SIG_ACC = 0.05                 # m/s^2
SIG_GNSS = 1.0                 # m per axis
SIG_RANGE = 0.15               # m
SIG_BEAR = math.radians(1.5)   # rad
P_OUTLIER = 0.03


class Otter(otter):
    """PVS Otter with per-propeller thrust scales (port, starboard)."""

    def __init__(self, V_current: float = 0.0, beta_current_deg: float = 0.0,
                 thrust_scale=(1.0, 1.0)):
        super().__init__("stepInput", 0, V_current, beta_current_deg, 0)
        self.thrust_scale = np.asarray(thrust_scale, float)

    def dynamics(self, eta, nu, u_actual, u_control, sampleTime):
        """Copy of python_vehicle_simulator otter.dynamics, plus thrust_scale."""
        n = np.array([u_actual[0], u_actual[1]])
        u_c = self.V_c * math.cos(self.beta_c - eta[5])
        v_c = self.V_c * math.sin(self.beta_c - eta[5])
        nu_c = np.array([u_c, v_c, 0, 0, 0, 0], float)
        Dnu_c = np.array([nu[5] * v_c, -nu[5] * u_c, 0, 0, 0, 0], float)
        nu_r = nu - nu_c
        CRB_CG = np.zeros((6, 6))
        CRB_CG[0:3, 0:3] = self.m_total * Smtrx(nu[3:6])
        CRB_CG[3:6, 3:6] = -Smtrx(np.matmul(self.Ig, nu[3:6]))
        CRB = self.H_rg.T @ CRB_CG @ self.H_rg
        CA = m2c(self.MA, nu_r)
        C = CRB + CA
        R = Rzyx(eta[3], eta[4], eta[5])
        f_payload = np.matmul(R.T, np.array([0, 0, self.mp * self.g], float))
        m_payload = np.matmul(self.S_rp, f_payload)
        g_0 = np.array([f_payload[0], f_payload[1], f_payload[2],
                        m_payload[0], m_payload[1], m_payload[2]])
        thrust = np.zeros(2)
        for i in range(0, 2):
            n[i] = sat(n[i], self.n_min, self.n_max)
            if n[i] > 0:
                thrust[i] = self.k_pos * n[i] * abs(n[i])
            else:
                thrust[i] = self.k_neg * n[i] * abs(n[i])
        thrust = thrust * self.thrust_scale
        tau = np.array([thrust[0] + thrust[1], 0, 0, 0, 0,
                        -self.l1 * thrust[0] - self.l2 * thrust[1]])
        tau_damp = -np.matmul(self.D, nu_r)
        tau_damp[5] = tau_damp[5] - 10 * self.D[5, 5] * abs(nu_r[5]) * nu_r[5]
        tau_crossflow = crossFlowDrag(self.L, self.B_pont, self.T, nu_r)
        sum_tau = (tau + tau_damp + tau_crossflow - np.matmul(C, nu_r)
                   - np.matmul(self.G, eta) + g_0)
        nu_dot = Dnu_c + np.matmul(self.Minv, sum_tau)
        n_dot = (u_control - n) / self.T_n
        nu = nu + sampleTime * nu_dot
        n = n + sampleTime * n_dot
        return nu, np.array(n, float)




# ------------------------------------------------------------------ waypoint controller
class WaypointController:
    """LOS heading + PI speed (over ground) on two propellers (differential for yaw).

    Legs: each waypoint i has a speed (m/s through water) and an optional pause (s, zero
    thrust) on arrival. Runs at 10 Hz and returns u = n/n_max for (port, starboard).
    """

    def __init__(self, vehicle: Otter, start, wps, speeds, pauses, t_start=5.0,
                 t_stop_after=810.0, t_hard_stop=945.0, accept=4.0, lookahead=8.0):
        self.v = vehicle
        self.wps = [np.asarray(w, float) for w in wps]
        self.prev = np.asarray(start, float)
        self.speeds, self.pauses = speeds, pauses
        self.i = 0
        self.t_start, self.t_stop_after, self.t_hard = t_start, t_stop_after, t_hard_stop
        self.accept, self.lookahead = accept, lookahead
        self.pause_until = -1.0
        self.done_at = None
        self.Tmax = vehicle.k_pos * vehicle.n_max ** 2          # 119.682 N
        self.Xu = vehicle.D[0, 0]                                 # N/(m/s)
        self.u_min = vehicle.n_min / vehicle.n_max
        self.r_max = math.radians(15.0)
        self.k_psi = 1.0        # 1/s: heading error -> yaw-rate demand
        self.k_r = 500.0        # N m per rad/s of rate error
        self.r_ref = 0.0
        self.kp_u, self.ki_u, self.i_u = 60.0, 15.0, 0.0   # N/(m/s), N/(m/s)/s, N

    def __call__(self, t, eta, nu):
        if t < self.t_start or self.done_at is not None or t < self.pause_until:
            return np.zeros(2)
        p = eta[:2]
        wp = self.wps[self.i]
        if np.linalg.norm(wp - p) < self.accept:            # waypoint reached
            pause = self.pauses[self.i]
            self.prev = wp
            self.i += 1
            if t >= self.t_stop_after or self.i >= len(self.wps):
                self.done_at = t
                return np.zeros(2)
            if pause > 0:
                self.pause_until = t + pause
                return np.zeros(2)
            wp = self.wps[self.i]
        if t >= self.t_hard:
            self.done_at = t
            return np.zeros(2)
        # LOS guidance on the segment prev -> wp
        d = wp - self.prev
        L = np.linalg.norm(d)
        tang = d / L
        along = float(np.dot(p - self.prev, tang))
        cross = float(-tang[1] * (p[0] - self.prev[0]) + tang[0] * (p[1] - self.prev[1]))
        pi_p = math.atan2(tang[1], tang[0])
        dist_left = np.linalg.norm(wp - p)
        if dist_left < self.lookahead * 1.5 or along < 0:
            psi_d = math.atan2(wp[1] - p[1], wp[0] - p[0])
        else:
            psi_d = pi_p - math.atan2(cross, self.lookahead)
        e = float(wrap(psi_d - eta[5]))
        r = nu[5]
        r_d = float(np.clip(self.k_psi * e, -self.r_max, self.r_max))
        tau_N = self.k_r * (r_d - r)
        # surge: feed-forward thrust for the leg speed, reduced while the heading is off
        U = self.speeds[self.i]
        # speed over ground along the heading, PI around the drag feed-forward
        sog = float(nu[0])
        err_u = U - sog
        if abs(e) < math.radians(20):
            self.i_u = float(np.clip(self.i_u + self.ki_u * err_u * 0.1, -60.0, 60.0))
        X = max(0.0, self.Xu * U + self.kp_u * err_u + self.i_u) * max(0.15, math.cos(e))
        # allocation: X = T1 + T2, N = 0.395 (T1 - T2)  (port = 1 pushes the bow to stbd)
        T1 = 0.5 * (X + tau_N / 0.395)
        T2 = 0.5 * (X - tau_N / 0.395)
        u = np.array([np.sign(T1) * math.sqrt(abs(T1) / self.Tmax),
                      np.sign(T2) * math.sqrt(abs(T2) / self.Tmax)])
        return np.clip(u, self.u_min, 1.0)


# ------------------------------------------------------------------ simulation core
def simulate(vehicle: Otter, eta0, controller, n_ctrl: int, theta_e0=0.0, theta_rate=0.0):
    """Step the vehicle at 100 Hz for n_ctrl controller periods (0.1 s each).

    Returns dict of arrays: truth (10 Hz), motors (10 Hz), imu_true (50 Hz: t, phi, theta,
    psi (unwrapped), p, q, r, fx, fy, fz).
    """
    eta = np.array(eta0, float)
    nu = np.zeros(6)
    ua = np.zeros(2)
    truth, motors, imu = [], [], []
    nstep = n_ctrl * CTRL_EVERY
    u = np.zeros(2)
    gvec = np.array([0.0, 0.0, G])
    for k in range(nstep):
        t = k * DT
        if k % CTRL_EVERY == 0:
            done = getattr(controller, "done_at", None)
            if done is not None and t > done + 16.0:
                break
            u = np.asarray(controller(t, eta, nu), float)
            R = Rzyx(eta[3], eta[4], eta[5])
            v_ned = R @ nu[:3]
            truth.append((t, eta[0], eta[1], 0.0, v_ned[0], v_ned[1], 0.0, float(wrap(eta[5]))))
            motors.append((t, u[0], u[1]))
        nu_new, ua = vehicle.dynamics(eta, nu, ua, u * vehicle.n_max, DT)
        if k % IMU_EVERY == 0:
            acc = (nu_new[:3] - nu[:3]) / DT + np.cross(nu[3:6], nu[:3])
            R = Rzyx(eta[3], eta[4], eta[5])
            f = acc - R.T @ gvec
            imu.append((t, eta[3], eta[4], eta[5], nu[3], nu[4], nu[5], f[0], f[1], f[2]))
        eta = attitudeEuler(eta, nu_new, DT)
        nu = nu_new
    return {"truth": np.array(truth), "motors": np.array(motors), "imu": np.array(imu)}


_TRIM = None


def trim_state():
    """(z, phi, theta) of the Otter floating at rest with zero thrust (its trim).

    Missions start from rest at this trim (the example missions do: their first 0.3 s of
    truth are reproduced to 0.1 mm by it; starting at z = phi = theta = 0 is not).
    """
    global _TRIM
    if _TRIM is None:
        v = Otter(0.0, 0.0)
        eta, nu, ua = np.zeros(6), np.zeros(6), np.zeros(2)
        for _ in range(20000):       # 200 s
            nu, ua = v.dynamics(eta, nu, ua, np.zeros(2), DT)
            eta = attitudeEuler(eta, nu, DT)
        _TRIM = (float(eta[2]), float(eta[3]), float(eta[4]))
    return _TRIM


# ------------------------------------------------------------------ mission design
BOX_N = (10.0, 145.0)
BOX_E = (-15.0, 155.0)
SPEEDS = (1.2, 1.5, 1.8, 2.1)


# --wide: conditions beyond those of the example missions, to test that nothing was tuned
# to them: currents 0.15-0.30 m/s, a propeller at 55-70 %, a heading offset drifting
# 0.03-0.05 deg/s, missions stopped after 8-15 min
WIDE = False


def design(seed: int):
    rng = np.random.default_rng(seed)
    # hidden physics variant: a fixed shuffle of 3 plain, 3 weak-propeller, 2 drift
    order = np.random.default_rng(20261123).permutation(
        ["plain"] * 3 + ["weakprop"] * 3 + ["yawdrift"] * 2)
    variant = str(order[(seed - 1) % 8])
    theta_e = float(rng.uniform(-np.pi, np.pi))
    cur_speed = float(rng.uniform(*((0.15, 0.30) if WIDE else (0.0, 0.15))))
    cur_dir = float(rng.uniform(0.0, 360.0))
    scale = (1.0, 1.0)
    rate = 0.0
    if variant == "weakprop":
        s = float(rng.uniform(*((0.55, 0.7) if WIDE else (0.7, 0.9))))
        scale = (1.0, s) if rng.random() < 0.5 else (s, 1.0)
    elif variant == "yawdrift":
        rate = math.radians(float(rng.uniform(*((0.03, 0.05) if WIDE else (0.01, 0.03))))
                            * rng.choice([-1, 1]))
    # route: random points in the box, legs 45-120 m, turns >= 45 deg
    start = np.array([rng.uniform(*BOX_N), rng.uniform(*BOX_E)])
    wps = []
    p, heading = start, None
    while len(wps) < 40:
        q = np.array([rng.uniform(*BOX_N), rng.uniform(*BOX_E)])
        L = np.linalg.norm(q - p)
        if not 45.0 <= L <= 120.0:
            continue
        h = math.atan2(q[1] - p[1], q[0] - p[0])
        if heading is not None and abs(wrap(h - heading)) < math.radians(45):
            continue
        wps.append(q)
        p, heading = q, h
    # leg speeds (m/s through water): 1.2/1.5/1.8/2.1, and two slow legs (0.4-0.6)
    # among the first ten, as in the example missions
    speeds = [float(rng.choice(SPEEDS)) for _ in wps]
    lens = [np.linalg.norm(wps[0] - start)] + [np.linalg.norm(wps[i] - wps[i - 1])
                                                for i in range(1, len(wps))]
    short = [i for i in range(10) if lens[i] <= 85.0]
    if len(short) < 2:
        short = list(np.argsort(lens[:10])[:2])
    for i in rng.choice(short, size=2, replace=False):
        speeds[i] = float(rng.uniform(0.4, 0.6))
    pauses = np.zeros(len(wps))
    idx = rng.choice(np.arange(0, 9), size=3, replace=False)
    pauses[idx] = rng.uniform(12.0, 24.0, size=3)
    psi0 = float(wrap(math.atan2(wps[0][1] - start[1], wps[0][0] - start[0])
                      + math.radians(rng.uniform(-45.0, 45.0))))
    return dict(seed=seed, variant=variant, theta_e=theta_e, cur_speed=cur_speed,
                cur_dir=cur_dir, scale=scale, rate=rate, start=start, wps=wps,
                speeds=speeds, pauses=pauses, psi0=psi0, rng=rng)


def write_mission(out: str, name: str, d: dict, sim: dict, end_idx: int):
    rng = d["rng"]
    os.makedirs(out, exist_ok=True)
    tr = sim["truth"][:end_idx]
    mo = sim["motors"][:end_idx]
    t_end = tr[-1, 0] + 0.1
    im = sim["imu"][sim["imu"][:, 0] < t_end - 1e-9]
    # truth
    with open(os.path.join(out, "truth.csv"), "w") as f:
        f.write("t,north,east,down,vn,ve,vd,yaw\n")
        for r in tr:
            f.write(f"{r[0]:.1f},{r[1]:.4f},{r[2]:.4f},{r[3]:.1f},{r[4]:.5f},{r[5]:.5f},"
                    f"{r[6]:.1f},{r[7]:.6f}\n")
    with open(os.path.join(out, "motors.csv"), "w") as f:
        f.write("t,u1,u2\n")
        for r in mo:
            f.write(f"{r[0]:.1f},{r[1]:.6f},{r[2]:.6f}\n")
    # IMU: reported yaw = true yaw - theta_e(t); gyro z carries the matching bias
    t = im[:, 0]
    th = d["theta_e"] + d["rate"] * t
    n = len(t)
    phi = im[:, 1] + rng.normal(0, SIG_RP, n)
    theta = im[:, 2] + rng.normal(0, SIG_RP, n)
    psi = im[:, 3] - th + rng.normal(0, SIG_YAW, n)
    qw, qx, qy, qz = euler_to_quat(phi, theta, psi).T
    w = im[:, 4:7] + rng.normal(0, SIG_GYRO, (n, 3))
    w[:, 2] -= d["rate"]
    a = im[:, 7:10] + rng.normal(0, SIG_ACC, (n, 3))
    with open(os.path.join(out, "imu.csv"), "w") as f:
        f.write("t,qw,qx,qy,qz,ax,ay,az,wx,wy,wz\n")
        for i in range(n):
            f.write(f"{t[i]:.2f},{qw[i]:.6f},{qx[i]:.6f},{qy[i]:.6f},{qz[i]:.6f},"
                    f"{a[i,0]:.4f},{a[i,1]:.4f},{a[i,2]:.4f},{w[i,0]:.5f},{w[i,1]:.5f},{w[i,2]:.5f}\n")
    # GNSS 1 Hz
    tt = tr[:, 0]
    tg = np.arange(0.0, t_end - 1e-9, 1.0)
    gn = np.interp(tg, tt, tr[:, 1]) + rng.normal(0, SIG_GNSS, len(tg))
    ge = np.interp(tg, tt, tr[:, 2]) + rng.normal(0, SIG_GNSS, len(tg))
    with open(os.path.join(out, "gnss.csv"), "w") as f:
        f.write("t,north,east,sigma\n")
        for i in range(len(tg)):
            f.write(f"{tg[i]:.1f},{gn[i]:.3f},{ge[i]:.3f},1.0\n")
    # USBL every 4.5 s from t = 2
    tu = np.arange(2.0, t_end - 1.0, 4.5)
    dn = np.interp(tu, tt, tr[:, 1]) - STATION[0]
    de = np.interp(tu, tt, tr[:, 2]) - STATION[1]
    dd = 0.0 - STATION[2]
    rg = np.sqrt(dn ** 2 + de ** 2 + dd ** 2) + rng.normal(0, SIG_RANGE, len(tu))
    br = np.arctan2(de, dn) + rng.normal(0, SIG_BEAR, len(tu))
    for i in range(len(tu)):
        if rng.random() < P_OUTLIER:
            sgn = rng.choice([-1.0, 1.0])
            if rng.random() < 0.5:
                rg[i] += sgn * rng.uniform(5.0, 18.0)
            else:
                br[i] += sgn * math.radians(rng.uniform(10.0, 35.0))
    br = wrap(br)
    with open(os.path.join(out, "usbl.csv"), "w") as f:
        f.write("t,range,bearing\n")
        for i in range(len(tu)):
            f.write(f"{tu[i]:.2f},{rg[i]:.3f},{br[i]:.5f}\n")
    # mission.toml
    sx = d["cur_speed"] * math.cos(math.radians(d["cur_dir"]))
    sy = d["cur_speed"] * math.sin(math.radians(d["cur_dir"]))
    te = d["theta_e"]
    extra = ""
    if d["variant"] == "weakprop":
        sp, ss = d["scale"]
        side = "starboard" if ss < 1 else "port"
        extra = (f'"thrust_asymmetry.ratio" = {ss / sp:.4f}   # starboard/port thrust; '
                 f'scales {sp:.4g}, {ss:.4g} ({side} propeller weak; k below is the nominal '
                 f'propeller, the port one gives k*{sp:.4g})\n')
    elif d["variant"] == "yawdrift":
        extra = (f'"heading_drift.rate" = {d["rate"]:.8f}   # rad/s '
                 f'({math.degrees(d["rate"]):+.4f} deg/s)\n')
        extra += f'theta_e_rate = {d["rate"]:.8f}   # rad/s, same as heading_drift.rate\n'
    when = " at t = 0" if d["variant"] == "yawdrift" else ""
    toml = f'''format = "aqfg-mission/1"
name = "{name}"
vehicle = "asv"

[thrusters]
direction = [[1, 0, 0], [1, 0, 0]]
position = [[0.0, -0.395, 0.0], [0.0, 0.395, 0.0]]

[usbl]
station = [0.0, 0.0, 1.5]

[truth]
source = "Otter USV model of Fossen's Python Vehicle Simulator (MIT licence), 100 Hz, waypoint controller (held-out generator experiments/heldout/otter_missions.py, seed {d['seed']})"
theta_e = {te:.7f}        # rad ({math.degrees(te):+.3f} deg{when})
s_x = {sx:.4f}               # m/s, current {d['cur_speed']:.3f} m/s toward {d['cur_dir']:.1f} deg
s_y = {sy:.4f}
k = 1.3998                  # forward thrust per u*abs(u), one propeller, over surge inertia 85.5 kg
{extra}variant = "{d['variant']}"
note = "the source model is richer than the quadratic-drag model: its physics is not all expressible as these parameters"
'''
    with open(os.path.join(out, "mission.toml"), "w") as f:
        f.write(toml)


def make(seed: int, outdir: str) -> float:
    d = design(seed)
    v = Otter(d["cur_speed"], d["cur_dir"], d["scale"])
    ctrl = WaypointController(v, d["start"], d["wps"], d["speeds"], d["pauses"],
                              t_stop_after=float(d["rng"].uniform(
                                  *((480.0, 900.0) if WIDE else (790.0, 900.0)))))
    z, phi, theta = trim_state()
    eta0 = [d["start"][0], d["start"][1], z, phi, theta, d["psi0"]]
    t0 = time.time()
    n_ctrl = 9800   # 980 s max
    sim = simulate(v, eta0, ctrl, n_ctrl, d["theta_e"], d["rate"])
    el = time.time() - t0
    t_done = ctrl.done_at if ctrl.done_at is not None else sim["truth"][-1, 0]
    end_idx = min(int(round((t_done + 15.4) / 0.1)), len(sim["truth"]))
    name = f"heldout-{seed:02d}"
    write_mission(os.path.join(outdir, name), name, d, sim, end_idx)
    print(f"{name}: variant={d['variant']} theta_e={math.degrees(d['theta_e']):+.1f} deg "
          f"current={d['cur_speed']:.3f} m/s toward {d['cur_dir']:.0f} deg scale={d['scale']} "
          f"rate={math.degrees(d['rate']):+.4f} deg/s  duration={end_idx/10:.1f} s  "
          f"waypoints reached={ctrl.i}  sim {el:.1f} s", flush=True)
    return el


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "missions"))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 9)))
    ap.add_argument("--wide", action="store_true",
                    help="conditions beyond the examples' (stronger currents, weaker "
                         "propeller, faster drift, shorter missions)")
    a = ap.parse_args()
    WIDE = a.wide
    for s in a.seeds:
        make(s, a.out)
