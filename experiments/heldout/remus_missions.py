#!/usr/bin/env python3
"""Generate held-out REMUS 100 AUV test missions in aqfg-mission/1 format.

Physics: the REMUS 100 model of Fossen's Python Vehicle Simulator (MIT licence;
T. I. Fossen, Handbook of Marine Craft Hydrodynamics and Motion Control, 2nd ed.,
Wiley 2021), vehicles/remus100.py `dynamics` (6-DOF, propeller K_T(J), rudder and
stern planes, fin lift/drag, current via relative velocity) and lib/gnc.py
`attitudeEuler`, stepped at 100 Hz.  Guidance/control (written here): waypoint
pursuit with a rate-limited heading PD on the rudder, a rate-limited depth
reference with a pitch cascade on the stern planes, and a speed PI on the propeller
(u1 = n / nMax), all run at 10 Hz with zero-order hold (the rows of motors.csv).

Conventions imitated from the example data's remus-dev-a (see README in this folder):
  * IMU yaw = true yaw - theta_e (true yaw = reported yaw + theta_e)
  * truth velocity = ground velocity = water-relative + current
  * u1 = commanded rpm / 1525; k = 0.9 rho D^4 K_T0 (1525/60)^2 / M11 = 3.2833
  * k_effective = least squares of actual thrust/M11 on (n/nMax)|n/nMax| over the mission

Usage:  PVS_SRC=.../PythonVehicleSimulator/src python experiments/heldout/remus_missions.py --out DIR [--seeds 1 2 3 4]
"""
import argparse
import math
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
import _pvs  # noqa: E402,F401  (the simulator on sys.path)
from aqfg.model.frames import wrap_angle as wrap  # noqa: E402
from aqfg.data.importers.frames import euler_to_quat  # noqa: E402
from python_vehicle_simulator.lib.gnc import Rzyx, attitudeEuler, ssa  # noqa: E402
from python_vehicle_simulator.vehicles.remus100 import remus100  # noqa: E402

DT = 0.01            # dynamics step (100 Hz)
CTRL_EVERY = 10      # control / motors rate 10 Hz
G = 9.80665
STATION = np.array([0.0, 0.0, 1.0])
N_MAX = 1525.0
D2R = math.pi / 180




# --------------------------------------------------------------------------- plan
def make_plan(rng):
    plan = {}
    plan["theta_e"] = rng.uniform(-math.pi, math.pi)
    plan["V_c"] = rng.uniform(0.0, 0.15)
    plan["beta_c"] = rng.uniform(0.0, 2 * math.pi)           # direction the current flows toward
    plan["t_surface"] = float(rng.integers(40, 91))           # s on the surface with GNSS
    plan["T"] = float(rng.integers(600, 841))                 # mission length (s)
    plan["t_idle"] = 5.0                                      # at rest before the start
    plan["t_coast"] = float(rng.uniform(5.0, 7.0))            # all commands 0 at the end
    # start near the station, random heading
    r0, a0 = rng.uniform(5, 25), rng.uniform(0, 2 * math.pi)
    plan["start"] = np.array([r0 * math.cos(a0), r0 * math.sin(a0)])
    plan["psi0"] = rng.uniform(-math.pi, math.pi)
    plan["r_max"] = rng.uniform(2.0, 2.6) * D2R              # autopilot turn rate per m/s of speed
    # waypoints: legs of 35-85 m, turns 50-160 deg, inside 100 m of the station
    wps, speeds = [], []
    p = plan["start"].copy()
    hdg = plan["psi0"] + rng.uniform(-2.5, 2.5)
    for _ in range(60):
        for _try in range(200):
            h = hdg + rng.choice([-1, 1]) * rng.uniform(50, 160) * D2R if wps else hdg
            L = rng.uniform(35, 85)
            q = p + L * np.array([math.cos(h), math.sin(h)])
            if np.hypot(*q) < 100:
                break
        wps.append(q)
        speeds.append(rng.uniform(1.0, 1.5))
        hdg, p = h, q
    plan["wps"] = np.array(wps)
    plan["speeds"] = np.array(speeds)
    # depth schedule after the surface phase: (start time, target depth)
    sched = []
    t = plan["t_surface"]
    z = 0.0
    while t < plan["T"]:
        for _try in range(100):
            znew = rng.uniform(5.0, 20.0)
            if abs(znew - z) > 3.0:
                break
        sched.append((t, znew))
        z = znew
        t += rng.uniform(150, 320)
    plan["depth_sched"] = sched
    return plan


# --------------------------------------------------------------------------- autopilot
class Autopilot:
    def __init__(self, plan):
        self.plan = plan
        self.wp_i = 0
        self.z_ref = 0.0
        self.theta_int = 0.0
        self.z_int = 0.0
        self.psi_int = 0.0
        self.u_int = 0.0
        self.u1 = 0.0

    def step(self, t, eta, nu, dt):
        p = self.plan
        if t < p["t_idle"] or t >= p["T"] - p["t_coast"]:
            return 0.0, 0.0, 0.0
        pos = eta[0:2]
        wps = p["wps"]
        # waypoint switching (acceptance circle 10 m)
        while np.hypot(*(wps[self.wp_i] - pos)) < 10.0 and self.wp_i < len(wps) - 1:
            self.wp_i += 1
        tgt = wps[self.wp_i]
        psi_d = math.atan2(tgt[1] - pos[1], tgt[0] - pos[0])
        U_d = p["speeds"][self.wp_i]
        # ---- heading: saturated yaw-rate reference, Nomoto feed-forward (K ~ 0.16 U) + rate P + slow I
        psi, r = eta[5], nu[5]
        e = float(ssa(psi_d - psi))
        r_max = p["r_max"] * max(nu[0], 0.5)         # turn rate the rudder can give (~12 deg)
        r_d = max(-r_max, min(r_max, 0.3 * e))
        if abs(e) < 0.15:                              # integral only near the course
            self.psi_int = max(-0.05, min(0.05, self.psi_int + dt * 0.02 * e))
        delta_r = r_d / (0.16 * max(nu[0], 0.5)) + 1.0 * (r_d - r) + self.psi_int
        delta_r = max(-15 * D2R, min(15 * D2R, delta_r))
        # ---- depth: rate-limited reference, pitch cascade on stern planes
        z_tgt = 0.0
        for ts, zz in p["depth_sched"]:
            if t >= ts:
                z_tgt = zz
        rate = 0.13 * max(nu[0], 0.5) * dt             # depth-reference rate (0.2 m/s at 1.5 m/s)
        self.z_ref += max(-rate, min(rate, z_tgt - self.z_ref))
        z, theta, q = eta[2], eta[4], nu[4]
        ez = z - self.z_ref
        self.z_int = max(-20.0, min(20.0, self.z_int + dt * ez))
        theta_d = 0.12 * ez + 0.004 * self.z_int
        theta_d = max(-14 * D2R, min(14 * D2R, theta_d))
        eth = float(ssa(theta - theta_d))
        self.theta_int = max(-0.5, min(0.5, self.theta_int + dt * eth))
        delta_s = 3.0 * eth + 2.0 * q + 0.3 * self.theta_int
        delta_s = max(-15 * D2R, min(15 * D2R, delta_s))
        # ---- speed: rpm feed-forward per leg with a slow PI trim
        u = nu[0]
        eu = U_d - u
        self.u_int = max(-0.05, min(0.05, self.u_int + dt * 0.005 * eu))
        u_cmd = 0.385 * U_d + 0.05 * eu + self.u_int
        u_cmd = max(0.0, min(0.8, u_cmd))
        step = 0.06 * dt
        self.u1 += max(-step, min(step, u_cmd - self.u1))
        return self.u1, delta_r, delta_s


# --------------------------------------------------------------------------- simulate
def simulate(plan):
    auv = remus100("depthHeadingAutopilot", 0, 0, 0, plan["V_c"], plan["beta_c"] / D2R)
    M11 = auv.M[0][0]
    N = int(round(plan["T"] / DT))
    eta = np.array([plan["start"][0], plan["start"][1], 0.0, 0.0, 0.0, plan["psi0"]], float)
    nu = np.zeros(6)
    u_act = np.zeros(3)
    ap = Autopilot(plan)
    X = np.zeros((N, 6)); V = np.zeros((N, 6)); A = np.zeros((N, 3))
    CMD = np.zeros((N, 3)); NACT = np.zeros(N); THR = np.zeros(N)
    cmd = (0.0, 0.0, 0.0)
    rho, Dp, KT0, KTm, Jm = 1026, 0.14, 0.4566, 0.1798, 0.6632
    for i in range(N):
        t = i * DT
        if i % CTRL_EVERY == 0:
            cmd = ap.step(t, eta, nu, DT * CTRL_EVERY)
        u1, dr, ds = cmd
        X[i] = eta; V[i] = nu; CMD[i] = cmd; NACT[i] = u_act[2]
        # actual propeller thrust / M11 (same formula as remus100.dynamics)
        n_rps = min(u_act[2], N_MAX) / 60
        U = math.sqrt(nu[0] ** 2 + nu[1] ** 2 + nu[2] ** 2)
        if n_rps > 0:
            Xp = rho * Dp ** 4 * (KT0 * n_rps * n_rps + (KTm - KT0) / Jm * (0.944 * U / Dp) * n_rps)
        else:
            Xp = rho * Dp ** 4 * KT0 * abs(n_rps) * n_rps
        THR[i] = 0.9 * Xp / M11
        nu_old = nu.copy()
        nu, u_act = auv.dynamics(eta, nu.copy(), u_act, np.array([dr, ds, u1 * N_MAX]), DT)
        # body acceleration (d nu/dt + omega x v) for the accelerometer
        A[i] = (nu[0:3] - nu_old[0:3]) / DT + np.cross(nu_old[3:6], nu_old[0:3])
        eta = attitudeEuler(eta.copy(), nu, DT)
        if not np.all(np.isfinite(eta)) or abs(eta[4]) > 1.2:
            raise RuntimeError(f"simulation diverged at t={t}")
    x = (NACT / N_MAX) * np.abs(NACT / N_MAX)
    k_eff = float((THR * x).sum() / (x * x).sum())
    k0 = 0.9 * rho * Dp ** 4 * KT0 * (N_MAX / 60) ** 2 / M11
    return dict(t=np.arange(N) * DT, eta=X, nu=V, acc=A, cmd=CMD, k_eff=k_eff, k0=k0, M11=M11)


# --------------------------------------------------------------------------- write
def write_mission(out, name, plan, sim, rng):
    os.makedirs(out, exist_ok=True)
    t, eta, nu = sim["t"], sim["eta"], sim["nu"]
    N = len(t)
    # ground velocity
    vel = np.zeros((N, 3))
    for i in range(N):
        vel[i] = Rzyx(eta[i, 3], eta[i, 4], eta[i, 5]) @ nu[i, 0:3]
    yaw = wrap(eta[:, 5])

    # truth + motors, 10 Hz
    idx10 = np.arange(0, N, 10)
    with open(f"{out}/truth.csv", "w") as f:
        f.write("t,north,east,down,vn,ve,vd,yaw\n")
        for i in idx10:
            f.write("%.1f,%.4f,%.4f,%.4f,%.5f,%.5f,%.5f,%.6f\n" % (
                t[i], eta[i, 0], eta[i, 1], eta[i, 2], vel[i, 0], vel[i, 1], vel[i, 2], yaw[i]))
    with open(f"{out}/motors.csv", "w") as f:
        f.write("t,u1,delta_r,delta_s\n")
        for i in idx10:
            f.write("%.1f,%.6f,%.5f,%.5f\n" % (t[i], sim["cmd"][i, 0], sim["cmd"][i, 1], sim["cmd"][i, 2]))

    # IMU, 50 Hz: attitude with heading offset and noise, specific force, gyro
    idx50 = np.arange(0, N, 2)
    n50 = len(idx50)
    phi = eta[idx50, 3] + rng.normal(0, 0.5 * D2R, n50)
    th = eta[idx50, 4] + rng.normal(0, 0.5 * D2R, n50)
    ps = eta[idx50, 5] - plan["theta_e"] + rng.normal(0, 0.3 * D2R, n50)
    qw, qx, qy, qz = euler_to_quat(phi, th, ps).T
    qn = np.sqrt(qw ** 2 + qx ** 2 + qy ** 2 + qz ** 2)
    with open(f"{out}/imu.csv", "w") as f:
        f.write("t,qw,qx,qy,qz,ax,ay,az,wx,wy,wz\n")
        for j, i in enumerate(idx50):
            R = Rzyx(eta[i, 3], eta[i, 4], eta[i, 5])
            fb = sim["acc"][i] - R.T @ np.array([0, 0, G]) + rng.normal(0, 0.05, 3)
            w = nu[i, 3:6] + rng.normal(0, 0.01, 3)
            f.write("%.2f,%.6f,%.6f,%.6f,%.6f,%.4f,%.4f,%.4f,%.5f,%.5f,%.5f\n" % (
                t[i], qw[j] / qn[j], qx[j] / qn[j], qy[j] / qn[j], qz[j] / qn[j],
                fb[0], fb[1], fb[2], w[0], w[1], w[2]))

    # depth, 1 Hz, 0.05 m
    idx1 = np.arange(0, N, 100)
    with open(f"{out}/depth.csv", "w") as f:
        f.write("t,depth\n")
        for i in idx1:
            f.write("%.1f,%.3f\n" % (t[i], eta[i, 2] + rng.normal(0, 0.05)))

    # GNSS, 1 Hz, only while on the surface (t <= t_surface), sigma 1 m
    with open(f"{out}/gnss.csv", "w") as f:
        f.write("t,north,east,sigma\n")
        for i in idx1:
            if t[i] > plan["t_surface"] + 1e-9:
                break
            f.write("%.1f,%.3f,%.3f,1.0\n" % (t[i], eta[i, 0] + rng.normal(0, 1.0), eta[i, 1] + rng.normal(0, 1.0)))

    # USBL every 4.5 s once submerged (depth > 0.5 m), 0.15 m, 1.5 deg, ~3 % outliers
    sub = np.where((eta[:, 2] > 0.5) & (t > plan["t_surface"]))[0]
    n_out = 0
    with open(f"{out}/usbl.csv", "w") as f:
        f.write("t,range,bearing\n")
        if len(sub):
            tu = math.ceil(t[sub[0]] * 2) / 2
            while tu <= t[-1] + 1e-9:
                i = int(round(tu / DT))
                d = eta[i, 0:3] - STATION
                rg = float(np.linalg.norm(d)) + rng.normal(0, 0.15)
                br = math.atan2(d[1], d[0]) + rng.normal(0, 1.5 * D2R)
                if rng.random() < 0.03:
                    n_out += 1
                    if rng.random() < 0.7:
                        jump = rng.choice([-1, 1]) * rng.uniform(4, 20)
                        if rg + jump < abs(d[2]) + 1.0:      # never shorter than the depth difference
                            jump = -jump
                        rg += jump
                    else:
                        br += rng.choice([-1, 1]) * rng.uniform(10, 40) * D2R
                f.write("%.2f,%.3f,%.5f\n" % (tu, abs(rg), float(wrap(br))))
                tu += 4.5

    th_deg = plan["theta_e"] / D2R
    s_x = plan["V_c"] * math.cos(plan["beta_c"])
    s_y = plan["V_c"] * math.sin(plan["beta_c"])
    toml = f'''format = "aqfg-mission/1"
name = "{name}"
vehicle = "auv"

[thrusters]
direction = [[1, 0, 0]]
position = [[-0.8, 0.0, 0.0]]

[usbl]
station = [0.0, 0.0, 1.0]

[truth]
source = "REMUS 100 AUV model of Fossen's Python Vehicle Simulator (MIT licence), 100 Hz, waypoint/depth/speed autopilot"
theta_e = {plan["theta_e"]:.7f}        # rad ({th_deg:+.1f} deg at t = 0)
s_x = {s_x:.4f}               # m/s, current {plan["V_c"]:.3f} m/s toward {(plan["beta_c"] / D2R) % 360:.0f} deg
s_y = {s_y:.4f}
k = {sim["k0"]:.4f}                  # thrust at zero advance speed per u*abs(u), over surge inertia {sim["M11"]:.2f} kg; falls with speed (K_T(J))
k_effective = {sim["k_eff"]:.4f}        # least-squares k over this mission
note = "the source model is richer than the quadratic-drag model (propeller K_T(J), fin lift and drag, speed-dependent linear damping): its physics is not all expressible as these parameters"
'''
    with open(f"{out}/mission.toml", "w") as f:
        f.write(toml)
    return n_out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(HERE, "missions"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    a = ap.parse_args()
    for s in a.seeds:
        name = f"heldout-auv-{s:02d}"
        plan_ss, noise_ss = np.random.SeedSequence(s).spawn(2)
        plan = make_plan(np.random.default_rng(plan_ss))
        t0 = time.time()
        sim = simulate(plan)
        t_sim = time.time() - t0
        n_out = write_mission(os.path.join(a.out, name), name, plan, sim, np.random.default_rng(noise_ss))
        print(f"{name}: T={plan['T']:.0f}s surface={plan['t_surface']:.0f}s theta_e={plan['theta_e'] / D2R:+.1f}deg "
              f"current={plan['V_c']:.3f}m/s toward {(plan['beta_c'] / D2R) % 360:.0f}deg "
              f"k_eff={sim['k_eff']:.4f} usbl_outliers={n_out} depths={[round(z, 1) for _, z in plan['depth_sched']]} "
              f"sim {t_sim:.1f}s, total {time.time() - t0:.1f}s", flush=True)


if __name__ == "__main__":
    main()
