"""Rotation about the down axis, the one rotation the model forms (paper Eq. 6).

Frames: ground NED, body x forward / y starboard / z down. A leaf module: the effects and
the frames both use it.
"""
from __future__ import annotations

import numpy as np

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
