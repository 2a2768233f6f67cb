"""Process noise of a white-acceleration (constant-velocity) error model, shared by the
EKF's covariance prediction (:mod:`aqfg.ekf.window`), the dynamics factors
(:class:`aqfg.fg.factors.ProcessNoise`) and the kinematic filter
(:mod:`aqfg.fg.kinematic`).
"""
from __future__ import annotations

import numpy as np


def white_acceleration(q: float, dt: float) -> np.ndarray:
    """Covariance (2x2) of [position, velocity] on one axis after ``dt`` s of white
    acceleration of power spectral density ``q`` ((m/s^2)^2/Hz = m^2/s^3): exact for a
    double integrator, ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]``."""
    return q * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0], [dt ** 2 / 2.0, dt]])
