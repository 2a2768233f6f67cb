"""The timestamped history of the update-error method (paper §III-B, Fig. 3).

A :class:`History` holds, for one mission, everything the EKF needs to recompute any stretch
of the past with any parameters (Eq. 13):

* the *timeline*: knot times (every update-node time plus an output grid) and, between
  consecutive knots, the kernel input steps (motor commands and IMU attitude samples, as
  :func:`aqfg.model.build_steps` cuts them);
* the *update nodes*: motor commands (zero update error), GNSS and USBL fixes, depth and
  IMU acceleration, each attached to a knot;
* the *anchor states*: EKF state and covariance at the start (the first absolute fix, which
  initialises the position, paper §II-E5) and after each absolute fix, recorded by whoever
  runs the filter (:meth:`History.set_anchor`).

Frames and units: NED metres, m/s, body-frame m/s^2; times in seconds on the mission clock.
The EKF state is ``X = [x_g (3), v_g (3), a_b (3)]`` (Eq. 5).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .kernel_ref import Steps
from .mission import Mission
from .model import Model, attitude_at, build_steps

# Update-node kinds (mirrored in cpp_factors/ekf.hpp).
MOTOR, GNSS, USBL, DEPTH, IMU_ACC = 0, 1, 2, 3, 4
KIND_NAMES = {MOTOR: "motor", GNSS: "gnss", USBL: "usbl", DEPTH: "depth", IMU_ACC: "imu_acc"}
FIX_KINDS = (GNSS, USBL)
# Order in which nodes sharing a knot are applied: motors, IMU, depth, then the absolute
# fixes, so that an anchor recorded after a fix holds every update of that instant.
_APPLY_ORDER = {MOTOR: 0, IMU_ACC: 1, DEPTH: 2, GNSS: 3, USBL: 4}

GRAVITY = 9.80665  # m/s^2, NED +z


@dataclass(frozen=True)
class EkfConfig:
    """Noise model of the EKF, gates and sampling. Units in each field's comment.

    Process noise (empirical, as in the paper §II-E3): the model's ground acceleration is
    wrong by a white noise of power spectral density ``q_h`` (north, east) and ``q_v``
    (down; ignored for surface vehicles), discretised exactly for a double integrator over
    the interval between two covariance propagations:
    ``Q = q [[T^3/3, T^2/2], [T^2/2, T]]`` per axis. The body acceleration ``a_b`` is
    recomputed by the model (Eq. 10) at every knot with an error of ``sigma_ab`` per axis.
    The defaults were tuned on simulated ASV/AUV missions (Monte Carlo over seeds, GNSS every
    8 s and USBL-only): smaller ``q`` makes the estimates of k, k_x, k_yz less biased,
    larger ``q`` makes the USBL-only filter follow the fixes better; 1e-3 sits between.

    Covariance Jacobian (``cov_model``). The mean is always predicted with the full model.
    With ``"kinematic"`` (default, as the authors' public code) the covariance is carried with
    the kinematic Jacobian of Eq. 8-9 only, ``Phi = [[I, T I], [0, I]]``, and ``a_b`` gets no
    covariance with ``v`` (their ``d a_b / d v`` term is multiplied by 0). With ``"full"`` the
    covariance uses the model's Jacobian (drag damping ``d a / d v``) and ``a_b = R^T a``
    covaries with ``v`` -- a textbook EKF, but then the Kalman gains depend on the
    parameters, and the update error ``K (z - h)`` can be lowered by parameters that make
    the filter over-confident instead of accurate: large drag shrinks the velocity
    uncertainty, hence ``K`` and ``E``. Measured on simulated USBL-only missions: E fell
    from 1860 to 130 as k_yz went from its true 0.14 to 850 while the track error grew from
    2 to 15 m. With the kinematic covariance, ``K`` does not depend on the dynamics
    parameters and ``E`` is a fixed-weight sum of squared innovations.
    """
    q_h: float = 1e-3            # m^2/s^3, horizontal acceleration noise PSD
    q_v: float = 1e-3            # m^2/s^3, vertical (AUV only)
    sigma_ab: float = 0.1        # m/s^2, model error of a_b (Eq. 10)
    sigma_v0: float = 0.1        # m/s, initial velocity (vehicle at rest at launch)
    sigma_gnss: float = 1.0      # m, per horizontal axis, when gnss.csv has no sigma
    sigma_range: float = 0.3     # m, USBL slant range
    sigma_bearing: float = float(np.radians(1.5))  # rad, USBL bearing
    sigma_depth: float = 0.05    # m
    sigma_acc: float = 0.2       # m/s^2, accelerometer (after averaging, per axis)
    use_imu_acc: bool = True     # IMU acceleration updates when imu.acc is present
    cov_model: str = "kinematic"  # covariance Jacobian: "kinematic" or "full" (see below)
    imu_acc_rate: float = 10.0   # Hz: accelerometer samples are averaged into nodes at this rate
    usbl_vmax: float = 2.5       # m/s, pre-filter: fastest plausible ground speed
    usbl_nsigma: float = 3.0     # pre-filter: allowed scatter, in fix sigmas
    gate_usbl: float = 13.8      # chi^2(2) gate on the USBL innovation (p = 0.999)
    gate_gnss: float = np.inf    # chi^2(2) gate on GNSS innovations (off)
    max_rejects: int = 3         # after this many consecutive rejections the next fix is taken
    output_rate: float = 10.0    # Hz, extra knots where the state is recorded
    gravity: float = GRAVITY     # m/s^2

    def vector(self, lookback: float) -> np.ndarray:
        """The numbers the window evaluation reads (layout fixed, see ``cpp_factors/ekf.hpp``)."""
        return np.array([self.q_h, self.q_v, self.sigma_ab, self.sigma_range,
                         self.sigma_bearing, self.gate_usbl, self.gate_gnss,
                         float(self.max_rejects), float(lookback),
                         float(self.cov_model == "full")])

    def __post_init__(self):
        if self.cov_model not in ("kinematic", "full"):
            raise ValueError(f"EkfConfig.cov_model must be 'kinematic' or 'full', "
                             f"got {self.cov_model!r}")


@dataclass
class Anchor:
    """EKF state ``x`` (9,) and covariance ``P`` (9, 9) at knot ``k`` (after its updates),
    and the number of consecutive USBL rejections there (the gate's rescue counter)."""
    k: int
    x: np.ndarray
    P: np.ndarray
    rejects: int = 0


@dataclass
class History:
    """Timeline, update nodes and anchor states of one mission (paper §III-B)."""
    mission: Mission
    model: Model
    config: EkfConfig
    knots: np.ndarray        # (K,) s, strictly increasing
    steps: Steps             # kernel steps, contiguous in time from knots[0]
    offsets: np.ndarray      # (K,) int64: steps of segment [knots[k], knots[k+1]] = offsets[k]:offsets[k+1]
    step_t: np.ndarray       # (n_steps,) s, start time of each step
    k_start: int             # knot of the first absolute fix (filter start, anchor at t=0)
    node_knot: np.ndarray    # (M,) int64, knot of each update node (non-decreasing)
    node_kind: np.ndarray    # (M,) int32
    node_z: np.ndarray       # (M, 4): see build_history
    node_R: np.ndarray       # (M, 9) raw IMU attitude at the node (row-major)
    node_tm: np.ndarray      # (M,) s since mission start
    station: np.ndarray      # (3,) USBL station, NED (zeros if none)
    usbl_kept: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # pre-filter mask
    anchors: dict[int, Anchor] = field(default_factory=dict)

    # ---- look-ups
    @property
    def t_start(self) -> float:
        return float(self.knots[self.k_start])

    @property
    def t_end(self) -> float:
        return float(self.knots[-1])

    def knot_of(self, t: float) -> int:
        """Index of the last knot at or before ``t``."""
        if t < self.knots[0] - 1e-9 or t > self.knots[-1] + 1e-9:
            raise ValueError(f"time {t} outside the history [{self.knots[0]}, {self.knots[-1]}] "
                             f"of mission {self.mission.name!r}")
        return int(np.searchsorted(self.knots, t + 1e-9, side="right") - 1)

    def nodes_between(self, k0: int, k1: int) -> tuple[int, int]:
        """Node index range ``[a, b)`` of the nodes with knot in ``(k0, k1]``."""
        a = int(np.searchsorted(self.node_knot, k0, side="right"))
        b = int(np.searchsorted(self.node_knot, k1, side="right"))
        return a, b

    def fix_knots(self) -> np.ndarray:
        """Knots holding an absolute fix (GNSS or USBL), the start knot first."""
        ks = self.node_knot[np.isin(self.node_kind, FIX_KINDS)]
        ks = ks[ks > self.k_start]
        return np.unique(np.concatenate([[self.k_start], ks])).astype(np.int64)

    def warm_start(self, k: int) -> int:
        """First step of the thrust-lag warm-up before knot ``k`` (= offsets[k] without lag)."""
        lb = self.model.lookback
        s = int(self.offsets[k])
        if lb <= 0:
            return s
        return int(np.searchsorted(self.step_t, self.knots[k] - lb - 1e-9))

    # ---- anchors (§III-B)
    def set_anchor(self, k: int, x: np.ndarray, P: np.ndarray, rejects: int = 0) -> None:
        self.anchors[int(k)] = Anchor(int(k), np.array(x, float), np.array(P, float),
                                      int(rejects))

    def anchor_at_or_before(self, k: int) -> Anchor:
        ks = [a for a in self.anchors if a <= k]
        if not ks:
            raise ValueError(f"no anchor state at or before knot {k} (t={self.knots[k]:.3f}) "
                             f"in mission {self.mission.name!r}")
        return self.anchors[max(ks)]

    def clear_anchors_after(self, k: int) -> None:
        for a in [a for a in self.anchors if a > k]:
            del self.anchors[a]


def _absolute_fixes(mission: Mission, cfg: EkfConfig):
    """GNSS rows (t, n, e, sigma) and USBL rows (t, range, bearing, down)."""
    from .retrace import usbl_positions
    g = np.zeros((0, 4))
    if mission.gnss is not None and len(mission.gnss.t):
        s = (np.full(len(mission.gnss.t), cfg.sigma_gnss) if mission.gnss.sigma is None
             else np.asarray(mission.gnss.sigma, float))
        g = np.column_stack([mission.gnss.t, mission.gnss.ne, s])
    u = np.zeros((0, 4))
    if mission.usbl is not None and len(mission.usbl.t):
        if mission.usbl_station is None:
            raise ValueError(f"mission {mission.name!r} has USBL data but no [usbl] station")
        down = usbl_positions(mission)[:, 2]
        u = np.column_stack([mission.usbl.t, mission.usbl.range, mission.usbl.bearing, down])
    return g, u


def usbl_prefilter(t: np.ndarray, pos: np.ndarray, sigma: np.ndarray, t0: float,
                   pos0: np.ndarray, sigma0: float, vmax: float, nsigma: float,
                   n_prev: int = 3) -> np.ndarray:
    """Causal outlier pre-filter of USBL fixes, independent of the model and its parameters.

    Fix ``i`` (horizontal position ``pos[i]``, major-axis std ``sigma[i]``) is consistent
    with an earlier fix ``j`` when ``|pos_i - pos_j| <= vmax |t_i - t_j| + nsigma
    sqrt(sigma_i^2 + sigma_j^2)``. It is kept unless it is inconsistent with every one of
    the (up to) ``n_prev`` previous fixes and the launch fix ``(t0, pos0, sigma0)``, or with
    a majority of them when there are ``n_prev``. The EKF's chi^2 gate then handles the
    smaller outliers that pass. Keeping gross outliers out before the filter makes ``E(P)``
    free of the jumps a gate alone causes when the parameters are far off (paper §IV-C:
    the USBL error model holds "after outlier rejection").
    Returns the keep mask (n,).
    """
    n = len(t)
    keep = np.ones(n, bool)
    T = np.concatenate([[t0], t])
    Pp = np.vstack([np.asarray(pos0, float)[None, :2], pos[:, :2]])
    S = np.concatenate([[sigma0], sigma])
    for i in range(n):
        j = np.arange(max(0, i + 1 - n_prev), i + 1)          # indices into T (i+1 = fix i)
        if i + 1 - n_prev > 0:
            j = j[j > 0]
        d = np.linalg.norm(Pp[i + 1] - Pp[j], axis=1)
        allow = vmax * np.abs(T[i + 1] - T[j]) + nsigma * np.sqrt(S[i + 1] ** 2 + S[j] ** 2)
        bad = d > allow
        keep[i] = not (bad.all() or (len(j) >= n_prev and bad.sum() * 2 > len(j)))
    return keep


def _imu_acc_nodes(mission: Mission, cfg: EkfConfig) -> np.ndarray:
    """Accelerometer nodes (t, a_b north... body x, y, z): specific force averaged over
    ``1/imu_acc_rate`` bins, with gravity added back using the IMU's own attitude:
    ``a_b = f + R_raw^T [0, 0, g]`` (roll and pitch are accurate; yaw does not matter
    because gravity is vertical)."""
    imu = mission.imu
    if not cfg.use_imu_acc or imu.acc is None or not len(imu.t):
        return np.zeros((0, 4))
    R = attitude_at(mission, imu.t)
    ab = np.asarray(imu.acc, float) + cfg.gravity * R[:, 2, :]   # R^T e_z = third row of R
    if cfg.imu_acc_rate <= 0:
        return np.column_stack([imu.t, ab])
    b = np.floor((imu.t - imu.t[0]) * cfg.imu_acc_rate + 1e-9).astype(int)
    _, start, cnt = np.unique(b, return_index=True, return_counts=True)
    t = np.add.reduceat(imu.t, start) / cnt
    a = np.add.reduceat(ab, start, axis=0) / cnt[:, None]
    return np.column_stack([t, a])


def build_history(model: Model, mission: Mission, config: EkfConfig | None = None) -> History:
    """The history of one mission: timeline, update nodes, and the initial anchor.

    The filter starts at the first absolute fix (GNSS or USBL): position from that fix,
    velocity zero, ``a_b`` zero (paper §II-E5); nodes at or before it are not applied.
    ``node_z`` columns by kind: GNSS (north, east, sigma, 0); USBL (range, bearing, down,
    0) converted to a position inside the filter; depth (depth, sigma, 0, 0); IMU
    acceleration (a_x, a_y, a_z body, sigma); motors (0, 0, 0, 0).
    """
    cfg = config or EkfConfig()
    g, u = _absolute_fixes(mission, cfg)
    if not len(g) and not len(u):
        raise ValueError(f"mission {mission.name!r} has no absolute fix (gnss.csv or usbl.csv): "
                         "the update-error method needs at least one to start from")
    from .retrace import fixes as all_fixes
    from .retrace import usbl_positions
    tf, pf = all_fixes(mission)
    t_s = float(tf[0])
    usbl_kept = np.ones(len(u), bool)
    if len(u):
        pu = usbl_positions(mission)
        su = np.maximum(cfg.sigma_range, np.linalg.norm(pu[:, :2] - mission.usbl_station[:2], axis=1)
                        * cfg.sigma_bearing)
        s0 = float(g[0, 3]) if len(g) and abs(g[0, 0] - t_s) < 1e-9 else float(su[0])
        usbl_kept = usbl_prefilter(u[:, 0], pu, su, t_s, pf[0], s0, cfg.usbl_vmax,
                                   cfg.usbl_nsigma)
        u = u[usbl_kept]
    t_e = float(mission.t1)
    if t_e <= t_s:
        raise ValueError(f"mission {mission.name!r}: first fix at t={t_s} is at or after the "
                         f"last input at t={t_e}")
    rows = []  # (t, kind, z0..z3)
    rows += [(r[0], GNSS, r[1], r[2], r[3], 0.0) for r in g]
    rows += [(r[0], USBL, r[1], r[2], r[3], 0.0) for r in u]
    if mission.depth is not None and len(mission.depth.t) and not mission.planar:
        rows += [(t, DEPTH, d, cfg.sigma_depth, 0.0, 0.0)
                 for t, d in zip(mission.depth.t, mission.depth.depth)]
    acc = _imu_acc_nodes(mission, cfg)
    rows += [(r[0], IMU_ACC, r[1], r[2], r[3], cfg.sigma_acc) for r in acc]
    rows += [(t, MOTOR, 0.0, 0.0, 0.0, 0.0) for t in mission.motors.t]
    nodes = np.array(rows, dtype=float).reshape(-1, 6)
    nodes = nodes[(nodes[:, 0] > t_s + 1e-9) & (nodes[:, 0] <= t_e + 1e-9)]
    order = np.lexsort(([_APPLY_ORDER[int(k)] for k in nodes[:, 1]], nodes[:, 0]))
    nodes = nodes[order]

    # knots: warm-up start, filter start, node times, output grid, end
    lb = model.lookback
    grid = t_s + np.arange(1, int(np.floor((t_e - t_s) * cfg.output_rate)) + 1) / cfg.output_rate
    grid = grid[grid < t_e - 1e-9]
    knots = np.concatenate([[t_s], nodes[:, 0], grid, [t_e]] + ([[t_s - lb]] if lb > 0 else []))
    knots = np.unique(np.round(knots, 9))
    steps, off = build_steps(mission, knots, lookback=0.0)
    step_t = steps.tm + mission.t0
    k_start = int(np.searchsorted(knots, t_s - 1e-9))
    node_knot = np.searchsorted(knots, np.round(nodes[:, 0], 9) - 1e-9).astype(np.int64)
    node_R = attitude_at(mission, nodes[:, 0]).reshape(-1, 9) if len(nodes) else np.zeros((0, 9))
    station = (np.zeros(3) if mission.usbl_station is None
               else np.asarray(mission.usbl_station, float))
    h = History(mission=mission, model=model, config=cfg, knots=knots, steps=steps,
                offsets=np.asarray(off, np.int64), step_t=step_t, k_start=k_start,
                node_knot=node_knot, node_kind=nodes[:, 1].astype(np.int32),
                node_z=np.ascontiguousarray(nodes[:, 2:6]), node_R=np.ascontiguousarray(node_R),
                node_tm=nodes[:, 0] - mission.t0, station=station, usbl_kept=usbl_kept)
    h.set_anchor(k_start, *initial_state(mission, pf[0], t_s, g, u, cfg))
    return h


def initial_state(mission: Mission, pos0: np.ndarray, t_s: float, g: np.ndarray, u: np.ndarray,
                  cfg: EkfConfig) -> tuple[np.ndarray, np.ndarray]:
    """State and covariance at the first fix: position from the fix, at rest (§II-E5)."""
    x = np.zeros(9)
    x[:3] = pos0
    if len(g) and abs(g[0, 0] - t_s) < 1e-9:
        sp = float(g[0, 3])
    else:  # USBL: the tangential error dominates
        sp = float(np.hypot(cfg.sigma_range, u[0, 1] * cfg.sigma_bearing))
    sv = cfg.sigma_v0
    vert = 0.0 if mission.planar else 1.0
    P = np.diag([sp**2, sp**2, (vert * cfg.sigma_depth) ** 2,
                 sv**2, sv**2, (vert * sv) ** 2,
                 cfg.sigma_ab**2, cfg.sigma_ab**2, cfg.sigma_ab**2])
    return x, P
