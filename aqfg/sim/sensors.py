"""Sensor streams of a simulated run: IMU, GNSS, USBL, depth and truth.

Every stream is computed from the closed-loop run (:class:`Run`) after the fact, vectorised
where possible. Position measurements go through the model's own measurement functions
(:meth:`aqfg.model.vehicle.Model.h_gnss` / ``h_usbl`` / ``h_depth``) with the true parameter vector,
so the measurement effects (range scale, bearing bias, lever arm) enter exactly as the
estimators model them; a stream's time offset (:class:`~aqfg.model.effects.FixDelayTerm`)
enters exactly: a fix stamped ``t`` is the sensor at ``t - tau`` (the estimators take it to
first order). Units: s, m, rad; frames NED (ground) and x-fwd/y-stbd/z-down (body).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.data.importers.frames import euler_to_quat
from aqfg.data.mission import Depth, Gnss, Imu, Truth, Usbl
from aqfg.model.frames import heading, wrap_angle
from aqfg.model.measurements import DELAY_TERMS
from aqfg.model.vehicle import Model, quat_to_rot

GRAVITY = 9.81                    # m/s^2
IMU_RATE = 50.0                   # Hz
IMU_ATT_SIGMA = np.radians(0.3)   # rad, roll/pitch noise of the reported attitude
IMU_ACC_SIGMA = 0.02              # m/s^2
IMU_GYRO_SIGMA = 0.002            # rad/s
DEPTH_PERIOD = 1.0                # s
DEPTH_SIGMA = 0.05                # m
TRUTH_RATE = 10.0                 # Hz (the controller tick)


@dataclass
class Run:
    """The closed-loop result.

    ``t_tick`` (K+1,) controller ticks (s); ``X`` (K+1, 6) true [pos, vel] NED at the ticks;
    ``U`` (K, N) commands held over each tick. ``t_fine`` (M+1,) the 100 Hz integration
    grid with the true ``yaw`` (unwrapped), yaw rate ``r``, ``roll``, ``pitch`` and their
    rates (rad, rad/s).
    """
    t_tick: np.ndarray
    X: np.ndarray
    U: np.ndarray
    t_fine: np.ndarray
    yaw: np.ndarray
    r: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    droll: np.ndarray
    dpitch: np.ndarray

    def pos_at(self, t: np.ndarray) -> np.ndarray:
        """True position (n, 3) at times ``t``: cubic Hermite between ticks (uses velocity)."""
        t = np.atleast_1d(np.asarray(t, float))
        tk = self.t_tick
        j = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
        h = tk[j + 1] - tk[j]
        s = ((t - tk[j]) / h)[:, None]
        p0, p1 = self.X[j, :3], self.X[j + 1, :3]
        v0, v1 = self.X[j, 3:], self.X[j + 1, 3:]
        h00 = 2 * s**3 - 3 * s**2 + 1
        h10 = s**3 - 2 * s**2 + s
        h01 = -2 * s**3 + 3 * s**2
        h11 = s**3 - s**2
        return h00 * p0 + h10 * h[:, None] * v0 + h01 * p1 + h11 * h[:, None] * v1

    def euler_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True roll, pitch, yaw (unwrapped), rad, at times ``t`` (linear between 100 Hz)."""
        t = np.atleast_1d(np.asarray(t, float))
        return (np.interp(t, self.t_fine, self.roll), np.interp(t, self.t_fine, self.pitch),
                np.interp(t, self.t_fine, self.yaw))


def sensed_times(t: np.ndarray, p: np.ndarray, stream: str) -> np.ndarray:
    """When the sensor of ``stream`` really was where its fixes stamped ``t`` say: ``t - tau``
    (``tau`` the sum of the stream's time offsets in ``p``), not before the run's start."""
    tau = sum(e.delay(p[sl]) for e, sl in DELAY_TERMS if e.stream == stream)
    return np.maximum(np.asarray(t, float) - tau, 0.0)


def raw_attitude(run: Run, p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Noise-free attitude (n, 3, 3) as the IMU reports it: yaw = true yaw - theta(t)."""
    roll, pitch, yaw = run.euler_at(t)
    return quat_to_rot(euler_to_quat(roll, pitch, yaw - heading(p, t)))


def imu_stream(run: Run, p: np.ndarray, rng: np.random.Generator) -> Imu:
    """IMU at 50 Hz: reported attitude (yaw = true - theta(t), exact; roll/pitch with
    ``IMU_ATT_SIGMA`` noise), specific force and body rates from the truth, with noise.

    The specific force uses the mean acceleration over each controller tick (the velocity
    change of the shared kernel over the tick / 0.1 s), ``f = R^T (a - g)``.
    """
    step = int(round(1.0 / (IMU_RATE * (run.t_fine[1] - run.t_fine[0]))))
    idx = np.arange(0, len(run.t_fine), step)
    t = run.t_fine[idx]
    roll, pitch, yaw = run.roll[idx], run.pitch[idx], run.yaw[idx]
    n = len(t)
    q = euler_to_quat(roll + rng.normal(0, IMU_ATT_SIGMA, n),
                      pitch + rng.normal(0, IMU_ATT_SIGMA, n),
                      wrap_angle(yaw - heading(p, t)))
    # specific force, body
    tick = run.t_tick[1] - run.t_tick[0]
    a_tick = np.diff(run.X[:, 3:], axis=0) / tick
    k = np.clip(np.floor(t / tick + 1e-9).astype(int), 0, len(a_tick) - 1)
    R_true = quat_to_rot(euler_to_quat(roll, pitch, yaw))
    f_g = a_tick[k] - np.array([0.0, 0.0, GRAVITY])
    acc = np.einsum("nji,nj->ni", R_true, f_g) + rng.normal(0, IMU_ACC_SIGMA, (n, 3))
    # body rates from Euler rates (ZYX)
    dr, dp, dy = run.droll[idx], run.dpitch[idx], run.r[idx]
    gyro = np.column_stack([dr - dy * np.sin(pitch),
                            dp * np.cos(roll) + dy * np.sin(roll) * np.cos(pitch),
                            -dp * np.sin(roll) + dy * np.cos(roll) * np.cos(pitch)])
    gyro = gyro + rng.normal(0, IMU_GYRO_SIGMA, (n, 3))
    return Imu(t=t, q=q, acc=acc, gyro=gyro)


def gnss_stream(run: Run, p: np.ndarray, model: Model, rng: np.random.Generator,
                period: float, sigma: float) -> Gnss:
    """GNSS fixes every ``period`` s from t = 0: the antenna position (centre of mass plus
    the rotated lever arm, :meth:`Model.h_gnss`) plus N(0, sigma^2) on north and on east."""
    t = np.arange(0.0, run.t_tick[-1] + 1e-9, period)
    ts = sensed_times(t, p, "gnss")
    pos = run.pos_at(ts)
    R = raw_attitude(run, p, ts)
    ne = np.array([model.h_gnss(pos[i], R[i], ts[i], p)[0] for i in range(len(t))])
    ne = ne.reshape(-1, 2) + rng.normal(0.0, sigma, (len(t), 2))
    return Gnss(t=t, ne=ne, sigma=np.full(len(t), float(sigma)))


def usbl_stream(run: Run, p: np.ndarray, model: Model, rng: np.random.Generator,
                period: float, station: np.ndarray, sigma_range: float,
                sigma_bearing: float, outlier_rate: float) -> tuple[Usbl, np.ndarray]:
    """USBL range/bearing every ``period`` s (first at a random phase within one period).

    True values from :meth:`Model.h_usbl` (range scale and bearing bias included), plus
    gaussian noise; a fraction ``outlier_rate`` are gross outliers: the range off by 10-40 m,
    the bearing off by 15-60 deg, or both (one third each). Returns the stream and the
    boolean outlier mask (for tests and evaluation).
    """
    t0 = rng.uniform(0.0, period)
    t = np.arange(t0, run.t_tick[-1] + 1e-9, period)
    n = len(t)
    ts = sensed_times(t, p, "usbl")
    pos = run.pos_at(ts)
    R = raw_attitude(run, p, ts)
    z = np.array([model.h_usbl(pos[i], R[i], ts[i], p, station)[0] for i in range(n)])
    z = z.reshape(-1, 2)
    rng_ = z[:, 0] + rng.normal(0.0, sigma_range, n)
    brg = z[:, 1] + rng.normal(0.0, sigma_bearing, n)
    out = rng.random(n) < outlier_rate
    kind = rng.integers(0, 3, n)                       # 0 range, 1 bearing, 2 both
    sign = np.where(rng.random((n, 2)) < 0.5, -1.0, 1.0)
    d_r = sign[:, 0] * rng.uniform(10.0, 40.0, n)
    d_b = sign[:, 1] * np.radians(rng.uniform(15.0, 60.0, n))
    rng_ = np.where(out & (kind != 1), np.abs(rng_ + d_r), rng_)
    brg = np.where(out & (kind != 0), brg + d_b, brg)
    return Usbl(t=t, range=np.abs(rng_), bearing=wrap_angle(brg)), out


def depth_stream(run: Run, model: Model, rng: np.random.Generator) -> Depth:
    """Pressure depth of the centre of mass at 1 Hz with ``DEPTH_SIGMA`` noise."""
    t = np.arange(0.0, run.t_tick[-1] + 1e-9, DEPTH_PERIOD)
    pos = run.pos_at(t)
    d = np.array([model.h_depth(x)[0][0] for x in pos])
    return Depth(t=t, depth=d + rng.normal(0.0, DEPTH_SIGMA, len(t)))


def truth_track(run: Run, params: dict) -> Truth:
    """Truth at the 10 Hz controller ticks: position, velocity, yaw (wrapped)."""
    idx = np.searchsorted(run.t_fine, run.t_tick - 1e-9)
    return Truth(t=run.t_tick.copy(), pos=run.X[:, :3].copy(), vel=run.X[:, 3:].copy(),
                 yaw=wrap_angle(run.yaw[idx]), params=params)
