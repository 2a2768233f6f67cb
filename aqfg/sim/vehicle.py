"""Simulated vehicles: thruster layout, the simulator-only rotational model, the controller.

Only the simulator has rotational dynamics (the estimators read attitude from the IMU,
paper §II-D2). Yaw follows the moment of the propeller thrusts about the centre of mass,
with linear + quadratic damping; roll and pitch are a small deterministic wobble. The
translational physics is NOT here: it is the shared kernel (:mod:`aqfg.model.reference`, via
:meth:`aqfg.model.vehicle.Model.propagate`).

Body frame x forward, y starboard, z down; ground frame NED; yaw clockwise from north.
Accelerations and moments are per unit mass (like the model's k, k_x, k_yz).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VehicleSpec:
    name: str
    thruster_dir: np.ndarray      # (N, 3) unit thrust axes, body
    thruster_pos: np.ndarray      # (N, 3) m, body
    planar: bool                  # surface vehicle
    base: dict                    # true k, k_x, k_yz (paper Table II)
    gyration2: float              # yaw inertia / mass, m^2
    yaw_damp_lin: float           # 1/s
    yaw_damp_quad: float          # 1/rad
    wobble_deg: float             # roll/pitch wobble amplitude, deg
    speed_range: tuple            # leg speeds drawn from this range, m/s
    fwd_alloc: np.ndarray         # (N,) demand per unit surge demand
    yaw_alloc: np.ndarray         # (N,) demand per unit differential (yaw) demand
    vert_alloc: np.ndarray        # (N,) demand per unit heave demand (AUV)
    pitch_alloc: np.ndarray       # (N,) demand per unit pitch demand (AUV)

    @property
    def n(self) -> int:
        return len(self.thruster_dir)

    @property
    def yaw_arm(self) -> np.ndarray:
        """(N,) yaw moment per unit thrust of each thruster: (pos x dir)_z, m."""
        p, d = self.thruster_pos, self.thruster_dir
        return p[:, 0] * d[:, 1] - p[:, 1] * d[:, 0]

    @property
    def side(self) -> np.ndarray:
        """+1 starboard, -1 port, 0 centre line (same rule as Mission.thruster_side)."""
        y = self.thruster_pos[:, 1]
        return np.where(y > 1e-9, 1.0, np.where(y < -1e-9, -1.0, 0.0))


def _a(x) -> np.ndarray:
    return np.array(x, dtype=float)


ASV = VehicleSpec(
    name="asv",
    # two propellers, port first (format doc example convention)
    thruster_dir=_a([[1, 0, 0], [1, 0, 0]]),
    thruster_pos=_a([[-0.25, -0.12, 0.0], [-0.25, 0.12, 0.0]]),
    planar=True,
    base={"k": 9.26, "k_x": 1.82, "k_yz": 0.14},          # Table II, ASV.3
    gyration2=0.03, yaw_damp_lin=2.0, yaw_damp_quad=30.0,
    wobble_deg=2.0, speed_range=(0.6, 1.4),
    fwd_alloc=_a([1, 1]), yaw_alloc=_a([1, -1]),
    vert_alloc=_a([0, 0]), pitch_alloc=_a([0, 0]),
)

AUV = VehicleSpec(
    name="auv",
    # 2 forward (port, starboard), 2 vertical (fore, aft), 1 lateral (fore)
    thruster_dir=_a([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0]]),
    thruster_pos=_a([[-0.30, -0.10, 0.0], [-0.30, 0.10, 0.0], [0.25, 0.0, 0.0],
                     [-0.20, 0.0, 0.0], [0.20, 0.0, 0.0]]),
    planar=False,
    base={"k": 4.42, "k_x": 0.55, "k_yz": 0.07},          # Table II, AUV
    gyration2=0.05, yaw_damp_lin=1.5, yaw_damp_quad=40.0,
    wobble_deg=1.0, speed_range=(0.5, 1.2),
    fwd_alloc=_a([1, 1, 0, 0, 0]), yaw_alloc=_a([1, -1, 0, 0, 0.3]),
    vert_alloc=_a([0, 0, 1, 1, 0]), pitch_alloc=_a([0, 0, 1, -1, 0]),
)

VEHICLES = {"asv": ASV, "auv": AUV}


# ---------------------------------------------------------------- roll/pitch wobble
@dataclass(frozen=True)
class Wobble:
    """Roll and pitch as sums of two sinusoids each (rad): amplitude, period, phase."""
    amp: np.ndarray      # (2, 2) [roll|pitch, component]
    omega: np.ndarray    # (2, 2) rad/s
    phase: np.ndarray    # (2, 2) rad

    @classmethod
    def random(cls, rng: np.random.Generator, amp_deg: float) -> Wobble:
        amp = np.radians(amp_deg) * np.array([[0.7, 0.3], [0.6, 0.4]]) * rng.uniform(0.7, 1.3, (2, 2))
        period = rng.uniform([[3.0, 7.0], [4.0, 9.0]], [[5.0, 13.0], [6.0, 15.0]])
        return cls(amp, 2 * np.pi / period, rng.uniform(0, 2 * np.pi, (2, 2)))

    def angles(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Roll, pitch (rad) and their rates (rad/s) at times ``t``."""
        arg = self.omega[:, :, None] * np.asarray(t)[None, None, :] + self.phase[:, :, None]
        ang = np.sum(self.amp[:, :, None] * np.sin(arg), axis=1)
        rate = np.sum((self.amp * self.omega)[:, :, None] * np.cos(arg), axis=1)
        return ang[0], ang[1], rate[0], rate[1]


# ---------------------------------------------------------------- controller
@dataclass
class Controller:
    """Waypoint follower (paper §IV: go to the next waypoint, switch within 3 m).

    Heading: P-control of the yaw rate towards the bearing of the waypoint, turned into a
    differential thrust demand (feed-forward of the yaw damping + rate feedback). Speed:
    feed-forward of the surge drag plus P on the surge speed; slows down for large heading
    errors and brakes for turns beyond 90 deg, so one propeller runs backwards in sharp
    turns. AUV depth: PD on the depth reference with the vertical thrusters. Commands are
    computed in demand space (u|u|) and mapped to u in [-1, 1].
    """
    spec: VehicleSpec
    waypoints: np.ndarray           # (n, 2); row 0 = launch point
    leg_speed: np.ndarray           # (n,) m/s, speed on the way to waypoint i
    k: float                        # the controller's idea of k, k_x, k_yz (true values)
    k_x: float
    k_yz: float
    accept_radius: float = 3.0      # m
    r_max: float = 0.5              # rad/s, commanded yaw-rate limit
    wp: int = 1                     # index of the current target
    leg_start: float = 0.0          # s, when the current leg began
    leg_budget: float = np.inf      # s, give up on a waypoint after this long
    switches: int = 0

    def _next(self, t: float, pos: np.ndarray) -> None:
        self.switches += 1
        self.wp = self.wp + 1 if self.wp + 1 < len(self.waypoints) else 1
        self.leg_start = t
        dist = np.linalg.norm(self.waypoints[self.wp] - pos[:2])
        self.leg_budget = 3.0 * dist / max(self.leg_speed[self.wp], 0.1) + 60.0

    def command(self, t: float, pos: np.ndarray, vel: np.ndarray, yaw: float, r: float,
                R: np.ndarray, depth_ref: tuple[float, float] | None) -> np.ndarray:
        """Motor commands u (N,) in [-1, 1] from the true state at time ``t`` (s)."""
        s = self.spec
        if not np.isfinite(self.leg_budget):
            self.leg_budget = 3.0 * np.linalg.norm(self.waypoints[self.wp] - pos[:2]) / \
                max(self.leg_speed[self.wp], 0.1) + 60.0
        delta = self.waypoints[self.wp] - pos[:2]
        if np.hypot(*delta) < self.accept_radius or t - self.leg_start > self.leg_budget:
            self._next(t, pos)
            delta = self.waypoints[self.wp] - pos[:2]
        e = float(np.arctan2(delta[1], delta[0]) - yaw)
        e = (e + np.pi) % (2 * np.pi) - np.pi

        # heading -> yaw moment -> differential demand
        r_des = float(np.clip(1.2 * e, -self.r_max, self.r_max))
        m_des = s.gyration2 * (s.yaw_damp_lin * r_des + s.yaw_damp_quad * r_des * abs(r_des)
                               + 4.0 * (r_des - r))
        D = m_des / (self.k * float(s.yaw_arm @ s.yaw_alloc))

        # speed: slow for large heading errors, brake beyond 90 deg
        v_surge = float((R.T @ vel)[0])
        v_des = self.leg_speed[self.wp] * max(np.cos(e), 0.0) ** 2
        n_fwd = float(s.fwd_alloc.sum())
        F = (self.k_x * v_des * abs(v_des) + 1.0 * (v_des - v_surge)) / (self.k * n_fwd)

        d = F * s.fwd_alloc + D * s.yaw_alloc
        if depth_ref is not None:
            z_ref, vz_ref = depth_ref
            a_z = (0.6 * (z_ref - pos[2]) + 1.5 * (vz_ref - vel[2])
                   + self.k_yz * vz_ref * abs(vz_ref))
            pitch = float(-np.arcsin(np.clip(R[2, 0], -1, 1)))
            n_vert = float(s.vert_alloc.sum())
            d = d + a_z / (self.k * n_vert) * s.vert_alloc - 0.02 * pitch * s.pitch_alloc
        d = np.clip(d, -1.0, 1.0)
        return np.sign(d) * np.sqrt(np.abs(d))
