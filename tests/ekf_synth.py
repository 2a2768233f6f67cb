"""A tiny synthetic mission for the EKF unit tests, made with the shared model itself.

Prescribed yaw and commands (no controller), truth integrated by :func:`aqfg.model.retrace.rollout`
with the true parameters, fixes from the truth plus noise. Small and fast, independent of
:mod:`aqfg.sim.simulator` so that the unit tests do not move when the simulator is retuned.
"""
from __future__ import annotations

import numpy as np

from aqfg.data.importers.frames import euler_to_quat
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Usbl
from aqfg.model.params import vector
from aqfg.model.retrace import rollout
from aqfg.model.vehicle import Model


def synth_mission(vehicle: str = "asv", duration: float = 60.0, seed: int = 0,
                  truth: dict | None = None, gnss_period: float = 2.0, usbl: bool = False,
                  imu_acc: bool = False, sigma_gnss: float = 0.5):
    rng = np.random.default_rng(seed)
    p_true = vector({"theta_e": 0.2, "s_x": 0.1, "s_y": -0.05, "k": 6.0, "k_x": 1.5,
                     "k_yz": 0.2, **(truth or {})})
    t_imu = np.arange(0.0, duration + 1e-9, 0.02)
    yaw = 0.6 * np.sin(2 * np.pi * t_imu / 40.0) + 0.01 * t_imu
    pitch = 0.05 * np.sin(2 * np.pi * t_imu / 7.0) if vehicle == "auv" else 0.01 * np.sin(t_imu)
    roll = 0.02 * np.sin(2 * np.pi * t_imu / 5.0)
    q = euler_to_quat(roll, pitch, yaw - p_true[0])          # reported yaw = true - theta_e
    t_m = np.arange(0.0, duration, 0.1)
    u1 = 0.5 + 0.3 * np.sin(2 * np.pi * t_m / 25.0)
    u2 = 0.5 + 0.3 * np.cos(2 * np.pi * t_m / 19.0)
    if vehicle == "auv":
        dirs = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])
        pos = np.array([[-0.3, -0.1, 0], [-0.3, 0.1, 0], [0, 0, 0]])
        u = np.column_stack([u1, u2, 0.3 * np.sin(2 * np.pi * t_m / 30.0)])
    else:
        dirs = np.array([[1.0, 0, 0], [1.0, 0, 0]])
        pos = np.array([[-0.25, -0.12, 0], [-0.25, 0.12, 0]])
        u = np.column_stack([u1, u2])
    m = Mission(name=f"synth-{vehicle}-{seed}", vehicle=vehicle, thruster_dir=dirs,
                thruster_pos=pos, imu=Imu(t_imu, q), motors=Motors(t_m, u))
    model = Model.for_mission(m)
    t_out = np.arange(0.0, duration + 1e-9, 0.02)
    tr = rollout(model, m, p_true, np.zeros(6), 0.0, t_out)
    tr_t = tr.t
    if imu_acc:
        a_g = np.gradient(tr.vel, tr_t, axis=0)
        from aqfg.model.vehicle import quat_to_rot
        R_true = quat_to_rot(euler_to_quat(roll, pitch, yaw))
        f = np.einsum("nji,nj->ni", R_true, a_g - np.array([0, 0, 9.80665]))
        m.imu.acc = f + rng.normal(0, 0.02, f.shape)
    tg = np.arange(0.0, duration + 1e-9, gnss_period)
    pg = np.array([np.interp(tg, tr_t, tr.pos[:, i]) for i in range(3)]).T
    m.gnss = Gnss(tg, pg[:, :2] + rng.normal(0, sigma_gnss, (len(tg), 2)),
                  np.full(len(tg), sigma_gnss))
    if usbl:
        st = np.array([-20.0, 10.0, 1.5])
        tu = np.arange(1.0, duration + 1e-9, 4.5)
        pu = np.array([np.interp(tu, tr_t, tr.pos[:, i]) for i in range(3)]).T
        d = pu - st
        m.usbl = Usbl(tu, np.linalg.norm(d, axis=1) + rng.normal(0, 0.3, len(tu)),
                      np.arctan2(d[:, 1], d[:, 0]) + rng.normal(0, 0.01, len(tu)))
        m.usbl_station = st
    if vehicle == "auv":
        td = np.arange(0.0, duration + 1e-9, 1.0)
        m.depth = Depth(td, np.interp(td, tr_t, tr.pos[:, 2]) + rng.normal(0, 0.05, len(td)))
    return m, p_true, tr
