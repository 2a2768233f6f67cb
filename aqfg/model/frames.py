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
from aqfg.model.rotation import rot_z

I_THETA = INDEX["theta_e"]
HEADING_TERMS: tuple[tuple[HeadingTerm, slice], ...] = tuple(
    (e, SLICE[e.name]) for e in DYNAMICS_EFFECTS if isinstance(e, HeadingTerm))
# the parameters theta depends on
HEADING_PARAMS: tuple[str, ...] = ("theta_e",) + tuple(n for e, _ in HEADING_TERMS for n in e.params)


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


def heading_jacobian_many(p: np.ndarray, tm: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """:func:`heading_jacobian` at each of the times ``tm`` (n,): ``[(index in p, (n,)
    values), ...]``."""
    tm = np.asarray(tm, dtype=float)
    out = [(I_THETA, np.ones(len(tm)))]
    for e, sl in HEADING_TERMS:
        J = np.array([e.heading_jacobian(float(t), p[sl]) for t in tm]).reshape(len(tm), -1)
        out += [(sl.start + j, J[:, j]) for j in range(J.shape[1])]
    return out


def corrected_attitude(R_raw: np.ndarray, p: np.ndarray, tm: float) -> np.ndarray:
    """Ground attitude (3x3, body->ground) from the IMU's ``R_raw`` (Eq. 6)."""
    return rot_z(heading(p, tm)) @ R_raw


def wrap_angle(a):
    """Angles (rad) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
