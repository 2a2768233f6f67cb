"""Thruster sign check (aqfg.data.thrusters): a thruster whose command is negated is named,
a correct mission is silent, and the finding reaches the loader's warnings."""
from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

from aqfg.data.importers.frames import quat_mul
from aqfg.data.io import MissionWarning, load_mission, save_mission
from aqfg.data.thrusters import effective_n, negative_correlation, thruster_findings
from aqfg.sim import simulate


@pytest.fixture(scope="module")
def sim():
    m, _ = simulate("asv", seed=3, duration=600.0, gnss_sigma=0.3)
    return m


def yaw(q):
    w, x, y, z = q.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def flipped(m, j):
    out = copy.copy(m)
    u = m.motors.u.copy()
    u[:, j] *= -1.0
    out.motors = type(m.motors)(m.motors.t, u)
    return out


def test_correct_mission_is_silent(sim):
    assert thruster_findings(sim) == []


@pytest.mark.parametrize("j", [0, 1])
def test_negated_thruster_is_named(sim, j):
    found = thruster_findings(flipped(sim, j))
    assert [f.thruster for f in found] == [j]
    f = found[0]
    assert f.r < 0 and f.r_acc < 0 and f.p < 1e-3
    assert f"thruster {j + 1}" in f.message() and "reversed" in f.message()


def test_finding_reaches_the_loader(sim, tmp_path):
    save_mission(flipped(sim, 0), tmp_path / "m")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        load_mission(tmp_path / "m")
    hits = [w.message for w in rec if isinstance(w.message, MissionWarning)
            and "pushes against" in str(w.message)]
    assert len(hits) == 1 and hits[0].column == "u1"


def test_effective_n_of_autocorrelated_series():
    """Two independent AR(1) series with coefficient a: n_eff ~ n (1 - a^2) / (1 + a^2)."""
    rng = np.random.default_rng(0)
    a, n = 0.9, 20000

    def ar1():
        e = rng.normal(size=n)
        x = np.empty(n)
        x[0] = e[0]
        for i in range(1, n):
            x[i] = a * x[i - 1] + e[i]
        return x
    x, y = ar1(), ar1()
    assert effective_n(x, y) == pytest.approx(n * (1 - a * a) / (1 + a * a), rel=0.1)
    # independent white series: p uniform, not small; a strong negative link: tiny p
    w = rng.normal(size=500)
    assert negative_correlation(w, rng.normal(size=500))[2] > 1e-3
    assert negative_correlation(w, -w + 0.5 * rng.normal(size=500))[2] < 1e-20


def test_heading_offset_is_not_a_reversal_but_all_reversed_is(sim):
    """An IMU heading off by 180 deg (theta_e, unreferenced yaw) leaves the check silent;
    every thruster negated is found, the summed demand included."""
    turned = copy.copy(sim)
    q = quat_mul(sim.imu.q, [0.0, 0.0, 0.0, 1.0])     # a half turn about body z
    dyaw = np.angle(np.exp(1j * (yaw(q) - yaw(sim.imu.q))))
    assert np.allclose(np.abs(dyaw), np.pi)
    turned.imu = type(sim.imu)(sim.imu.t, q, sim.imu.acc, sim.imu.gyro)
    assert thruster_findings(turned) == []
    both = flipped(flipped(sim, 0), 1)
    assert None in [f.thruster for f in thruster_findings(both)]


def test_a_vehicle_drifting_astern_between_legs_is_not_reversed(sim):
    """A short driven leg, then a long idle drift astern (wind on an idle boat: no thrust,
    heading held, 0.25 m/s backwards): over time the vehicle went backwards more than
    forwards, but while its thrusters pushed it went forwards; the check takes that frame
    and stays silent. A negated thruster is still found."""
    from aqfg.data.mission import Gnss, Imu, Motors
    m = sim
    split = m.t0 + 60.0
    yaw_at = float(np.interp(split, m.imu.t, np.unwrap(yaw(m.imu.q))))
    q_hold = np.array([np.cos(yaw_at / 2), 0.0, 0.0, np.sin(yaw_at / 2)])
    q = np.where((m.imu.t > split)[:, None], q_hold, m.imu.q)
    u = np.where((m.motors.t > split)[:, None], 0.0, m.motors.u)
    g = m.gnss
    p0 = np.array([np.interp(split, g.t, g.ne[:, a]) for a in range(2)])
    astern = -0.25 * np.array([np.cos(yaw_at), np.sin(yaw_at)])
    rng = np.random.default_rng(0)
    late = g.t > split
    ne = g.ne.copy()
    ne[late] = p0 + np.outer(g.t[late] - split, astern) + rng.normal(0, 0.3, (late.sum(), 2))
    out = copy.copy(m)
    out.imu = Imu(m.imu.t, q)
    out.motors = Motors(m.motors.t, u)
    out.gnss = Gnss(g.t, ne, g.sigma)
    assert thruster_findings(out) == []
    assert thruster_findings(flipped(out, 0))      # still found (here by the summed demand)


def test_a_vehicle_driven_astern_is_not_reversed(sim):
    """The same motion logged as a vehicle driven astern (commands negated, heading turned
    half a circle, a correct compass): the motion while pushed points astern of the logged
    heading, which a reversal with a heading 180 deg off would explain as well; nothing is
    reported that holds in only one of the two frames."""
    q = quat_mul(sim.imu.q, [0.0, 0.0, 0.0, 1.0])
    astern = flipped(flipped(sim, 0), 1)
    astern.imu = type(sim.imu)(sim.imu.t, q, sim.imu.acc, sim.imu.gyro)
    assert thruster_findings(astern) == []
