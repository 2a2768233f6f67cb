"""Frame conversions into the mission's frames (ground NED, body FRD: x forward, y
starboard, z down). Quaternions are Hamilton, scalar first (w, x, y, z), body -> ground.

ROS (REP-103, REP-145) reports attitude as body FLU (x forward, y left, z up) -> ground ENU
(east, north, up). The NED attitude of the same body is

    R_ned_frd = R_ned_enu @ R_enu_flu @ R_flu_frd,

with R_ned_enu = [[0, 1, 0], [1, 0, 0], [0, 0, -1]] (a half turn about (1, 1, 0)/sqrt 2,
q = (0, 1/sqrt 2, 1/sqrt 2, 0)) and R_flu_frd = diag(1, -1, -1) (a half turn about x,
q = (0, 1, 0, 0)). Body vectors (angular rate, specific force) go FLU -> FRD by negating
y and z. MAVLink, DataFlash and ULog are already NED/FRD.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

_S = np.sqrt(0.5)
Q_NED_ENU = np.array([0.0, _S, _S, 0.0])     # ENU -> NED
Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])   # FRD -> FLU
FLU_TO_FRD = np.array([1.0, -1.0, -1.0])     # body vector components


def quat_mul(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Hamilton product a * b of (..., 4) w, x, y, z quaternions (broadcasting)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def enu_flu_to_ned_frd(q_enu_flu: ArrayLike) -> np.ndarray:
    """(n, 4) attitude body FLU -> ENU (ROS) to body FRD -> NED; the norm is kept."""
    return quat_mul(quat_mul(Q_NED_ENU, q_enu_flu), Q_FLU_FRD)


def flu_to_frd(v: ArrayLike) -> np.ndarray:
    """(n, 3) body vectors from FLU (ROS) to FRD components."""
    return np.asarray(v, dtype=float) * FLU_TO_FRD


def euler_to_quat(roll, pitch, yaw) -> np.ndarray:
    """(n, 4) quaternions w, x, y, z from ZYX Euler angles (rad): R = Rz(yaw) Ry(pitch)
    Rx(roll)."""
    cr, sr = np.cos(np.asarray(roll) / 2), np.sin(np.asarray(roll) / 2)
    cp, sp = np.cos(np.asarray(pitch) / 2), np.sin(np.asarray(pitch) / 2)
    cy, sy = np.cos(np.asarray(yaw) / 2), np.sin(np.asarray(yaw) / 2)
    return np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=-1)
