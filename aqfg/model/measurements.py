"""Measurement functions: what GNSS, USBL and depth sensors report from the vehicle state.

One definition each, used by the factor graph (through :class:`aqfg.model.vehicle.Model`),
the EKF, the simulator, the re-trace and the diagnosis:

* :func:`sensor_position` -- the antenna / transponder at ``pos + R l`` (``l`` the sum of
  the :class:`~aqfg.model.effects.SensorOffsetTerm` offsets, the lever arm, body frame;
  ``R`` the heading-corrected attitude, :func:`aqfg.model.frames.heading`), and, given the
  state's velocity, ``- tau v`` for the stream's
  :class:`~aqfg.model.effects.FixDelayTerm` time offset ``tau``;
* :func:`sensor_positions` -- the same for many fixes at once (the batch solver's numpy
  form, :mod:`aqfg.fg.fastlm_meas`);
* :func:`h_gnss` -- north, east of the antenna;
* :func:`h_usbl` -- slant range ``|d|`` and bearing ``atan2(d_e, d_n)`` (rad, from north,
  clockwise) of the transponder seen from the station, then the
  :class:`~aqfg.model.effects.UsblTerm` distortions (range scale, bearing bias);
* :func:`usbl_inverse` -- its inverse: a fix's position from (range, bearing) and the
  vehicle's depth (the C++ twin is ``kernel::usbl_position`` in ``cpp_factors/kernel.hpp``);
* :func:`h_depth` -- the down coordinate of the centre of mass.

Positions NED (m); Jacobians w.r.t. the position (``d/dpos``) and w.r.t. the built-in
parameter table (``d/dp``, ``N_PARAMS`` columns). Where the functions take ``pos`` they also
take the whole state ``[pos, vel]`` (6,): the time offsets then apply, and ``d/dpos`` is
the derivative w.r.t. that state (6 columns).
"""
from __future__ import annotations

import numpy as np

from aqfg.model.effects import FixDelayTerm, SensorOffsetTerm, UsblTerm
from aqfg.model.frames import corrected_attitude, heading, heading_jacobian, heading_jacobian_many
from aqfg.model.params import MEASUREMENT_EFFECTS, N_PARAMS, SLICE
from aqfg.model.rotation import E_Z, rot_z

OFFSET_TERMS: tuple[tuple[SensorOffsetTerm, slice], ...] = tuple(
    (e, SLICE[e.name]) for e in MEASUREMENT_EFFECTS if isinstance(e, SensorOffsetTerm))
USBL_TERMS: tuple[tuple[UsblTerm, slice], ...] = tuple(
    (e, SLICE[e.name]) for e in MEASUREMENT_EFFECTS if isinstance(e, UsblTerm))
DELAY_TERMS: tuple[tuple[FixDelayTerm, slice], ...] = tuple(
    (e, SLICE[e.name]) for e in MEASUREMENT_EFFECTS if isinstance(e, FixDelayTerm))


def sensor_position(pos: np.ndarray, R_raw: np.ndarray, tm: float, p: np.ndarray,
                    stream: str = "gnss"):
    """Position (NED, m) of the position sensor (GNSS antenna / USBL transponder).

    ``pos + R @ l`` with ``l`` the sum of the sensor-offset terms (the lever arm, body) and
    ``R`` the heading-corrected attitude at ``tm`` s since the mission start. ``pos`` may be
    the state ``[pos, vel]`` (6,): then ``- tau vel`` is added, ``tau`` the sum of the time
    offsets of ``stream`` (a fix stamped ``t`` is the sensor at ``t - tau``, to first order).
    Returns the position, d/dpos (3 x len(pos)), d/dp (3 x N_PARAMS).
    """
    x = np.asarray(pos, dtype=float)
    R = corrected_attitude(R_raw, p, tm)
    Jp = np.zeros((3, N_PARAMS))
    Jx = np.eye(3, len(x))
    base = x[:3]
    if len(x) == 6:
        for d, sd in DELAY_TERMS:
            if d.stream != stream:
                continue
            tau = d.delay(p[sd])
            base = base - tau * x[3:6]
            Jx[:, 3:6] -= tau * np.eye(3)
            Jp[:, sd] -= np.outer(x[3:6], d.delay_jacobian(p[sd]))
    lever = np.zeros(3)
    for e, sl in OFFSET_TERMS:
        lever = lever + e.offset(p[sl])
        Jp[:, sl] += R @ e.offset_jacobian(p[sl])
    Rl = R @ lever
    dRl = E_Z @ Rl                          # d (R l) / d theta
    for i, dth in heading_jacobian(p, tm):
        Jp[:, i] += dRl * dth
    return base + Rl, Jx, Jp


def sensor_positions(X: np.ndarray, R_raw: np.ndarray, tm: np.ndarray, p: np.ndarray,
                     stream: str = "gnss"):
    """:func:`sensor_position` of states ``X`` (n, 6) with attitudes ``R_raw`` (n, 3, 3) at
    ``tm`` (n,) s since the mission start, one parameter vector ``p``. Returns the
    positions (n, 3), d/dstate (n, 3, 6), d/dp (n, 3, N_PARAMS)."""
    X = np.asarray(X, dtype=float)
    n = len(X)
    R = rot_z(heading(p, np.asarray(tm, dtype=float))) @ R_raw
    Jp = np.zeros((n, 3, N_PARAMS))
    Jx = np.zeros((n, 3, 6))
    Jx[:, [0, 1, 2], [0, 1, 2]] = 1.0
    base = X[:, :3].copy()
    for d, sd in DELAY_TERMS:
        if d.stream != stream:
            continue
        tau = d.delay(p[sd])
        base -= tau * X[:, 3:6]
        Jx[:, [0, 1, 2], [3, 4, 5]] -= tau
        Jp[:, :, sd] -= X[:, 3:6, None] * d.delay_jacobian(p[sd])[None, None, :]
    lever = np.zeros(3)
    for e, sl in OFFSET_TERMS:
        lever = lever + e.offset(p[sl])
        Jp[:, :, sl] += R @ e.offset_jacobian(p[sl])
    Rl = R @ lever
    if np.any(lever != 0.0):                # else the heading does not move the sensor
        dRl = Rl @ E_Z.T                    # d (R l) / d theta
        for i, dth in heading_jacobian_many(p, tm):
            Jp[:, :, i] += dRl * dth[:, None]
    return base + Rl, Jx, Jp


def h_gnss(pos: np.ndarray, R_raw: np.ndarray, tm: float, p: np.ndarray):
    """GNSS fix model: north, east of the antenna. Returns z (2,), d/dpos (2 x len(pos)),
    d/dp."""
    ps, Jx, Jp = sensor_position(pos, R_raw, tm, p, "gnss")
    return ps[:2], Jx[:2], Jp[:2]


def h_depth(pos: np.ndarray):
    """Depth sensor model: down coordinate of the centre of mass; z (1,), d/dpos (1x3)."""
    return np.array([pos[2]]), np.array([[0.0, 0.0, 1.0]])


def range_bearing(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slant range (m) and bearing (rad, from north, clockwise) of relative positions
    ``d`` (n, 3) NED, and their derivatives d/dd (n, 2, 3): the geometry of :func:`h_usbl`
    (vectorised for the batch solver)."""
    d = np.asarray(d, dtype=float)
    r = np.linalg.norm(d, axis=1)
    rh2 = d[:, 0] ** 2 + d[:, 1] ** 2
    z = np.column_stack([r, np.arctan2(d[:, 1], d[:, 0])])
    H = np.zeros((len(d), 2, 3))
    H[:, 0, :] = d / np.maximum(r, 1e-9)[:, None]
    H[:, 1, 0] = -d[:, 1] / np.maximum(rh2, 1e-12)
    H[:, 1, 1] = d[:, 0] / np.maximum(rh2, 1e-12)
    return z, H


def h_usbl(pos: np.ndarray, R_raw: np.ndarray, tm: float, p: np.ndarray, station: np.ndarray):
    """USBL model: slant range (m) and bearing (rad, from north, clockwise) of the
    transponder seen from ``station`` (NED), distorted by the USBL terms (range scale,
    bearing bias).

    Returns z (2,), d/dpos (2 x len(pos)), d/dp (2 x N_PARAMS).
    """
    ps, Jx, Jp = sensor_position(pos, R_raw, tm, p, "usbl")
    zz, HH = range_bearing(ps[None, :] - np.asarray(station, dtype=float))
    z, Hd = zz[0], HH[0]
    Jpos = Hd @ Jx
    Jpp = Hd @ Jp
    for e, sl in USBL_TERMS:
        Jz, Jq = e.distort_jacobian(z, p[sl])
        z = e.distort(z, p[sl])
        Jpos = Jz @ Jpos
        Jpp = Jz @ Jpp
        Jpp[:, sl] += Jq
    return z, Jpos, Jpp


def usbl_inverse(rng, bearing, down, station: np.ndarray, p: np.ndarray):
    """The position of USBL fixes: the inverse of :func:`h_usbl` given the vehicle's depth.

    ``rng`` (m), ``bearing`` (rad) as measured and ``down`` (m), scalars or arrays (n,). The
    USBL terms of ``p`` are undone first (range scale, bearing bias: ``r = range / scale``,
    ``b = bearing - bias``); the depth below the station fixes the vertical leg, so the
    horizontal range is ``r_h = sqrt(max(r^2 - dz^2, 0))``. The lever arm is not removed
    (the attitude is not known here): the position is the transponder's.

    Returns ``(pos, r, r_h, b)``: NED position (..., 3), corrected slant range, horizontal
    range and corrected bearing.
    """
    st = np.asarray(station, dtype=float)
    r, b = rng, bearing
    for e, sl in reversed(USBL_TERMS):
        r, b = e.undistort(r, b, p[sl])
    r = np.asarray(r, dtype=float)
    b = np.asarray(b, dtype=float)
    down = np.asarray(down, dtype=float)
    dz = down - st[2]
    rh = np.sqrt(np.maximum(r * r - dz * dz, 0.0))
    pos = np.stack([st[0] + rh * np.cos(b), st[1] + rh * np.sin(b),
                    np.broadcast_to(down, np.shape(rh))], axis=-1)
    return pos, r, rh, b
