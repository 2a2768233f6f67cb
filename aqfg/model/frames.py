"""Frames: the heading correction that turns the IMU's attitude into the ground frame.

The IMU's yaw is unreferenced (paper §II-D2); the true attitude is the reported one turned
about the vertical by the heading offset (Eq. 6)::

    R = Rz(theta(tm)) @ R_raw,    theta(tm) = theta_e + (terms of the heading effects)

with ``tm`` the time since the mission start (s); the heading effects
(:class:`~aqfg.model.effects.HeadingTerm`, e.g. ``heading_drift``) add their terms.
:func:`heading` is the only place that forms ``theta``: the dynamics, the measurement
functions, the simulator and the evaluation all call it (the C++ twin is
``kernel::heading`` in ``cpp_factors/kernel.hpp``).

Frames: ground NED, body x forward / y starboard / z down; ``R`` maps body to ground.
"""
from __future__ import annotations

import numpy as np

from aqfg.model.effects import HeadingTerm
from aqfg.model.params import DYNAMICS_EFFECTS, INDEX, SLICE

I_THETA = INDEX["theta_e"]
HEADING_TERMS: tuple[tuple[HeadingTerm, slice], ...] = tuple(
    (e, SLICE[e.name]) for e in DYNAMICS_EFFECTS if isinstance(e, HeadingTerm))
# the parameters theta depends on
HEADING_PARAMS: tuple[str, ...] = ("theta_e",) + tuple(n for e, _ in HEADING_TERMS for n in e.params)

# d Rz(theta) / d theta = E_Z @ Rz(theta)
E_Z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def rot_z(theta) -> np.ndarray:
    """Rotation (3x3, or (n, 3, 3) for an array) by ``theta`` (rad) about the down axis
    (yaw, clockwise seen from above)."""
    c, s = np.cos(theta), np.sin(theta)
    if np.ndim(theta) == 0:
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = np.zeros(np.shape(theta) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def heading(p: np.ndarray, tm):
    """Heading offset ``theta`` (rad) at ``tm`` s since the mission start (scalar or array),
    for the full parameter vector ``p`` (Eq. 6 with the heading effects)."""
    th = p[I_THETA]
    for e, sl in HEADING_TERMS:
        th = th + e.heading(tm, p[sl])
    return th


def heading_jacobian(p: np.ndarray, tm: float) -> list[tuple[int, float]]:
    """``d theta / d p`` at ``tm`` as ``[(index in p, value), ...]``."""
    out = [(I_THETA, 1.0)]
    for e, sl in HEADING_TERMS:
        out += [(sl.start + j, float(v)) for j, v in enumerate(e.heading_jacobian(tm, p[sl]))]
    return out


def corrected_attitude(R_raw: np.ndarray, p: np.ndarray, tm: float) -> np.ndarray:
    """Ground attitude (3x3, body->ground) from the IMU's ``R_raw`` (Eq. 6)."""
    return rot_z(heading(p, tm)) @ R_raw


def wrap_angle(a):
    """Angles (rad) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
