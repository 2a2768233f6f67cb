"""The Huber loss of whitened residuals, as GTSAM's ``noiseModel.mEstimator.Huber``.

A factor's whitened residual of norm ``d`` costs ``d^2 / 2`` within the threshold ``k``
and ``k d - k^2 / 2`` beyond (linear growth: an outlier's pull is bounded). Iteratively
reweighted least squares weighs the factor by ``w = 1`` within ``k``, ``k / d`` beyond
(residual and Jacobian scaled by ``sqrt(w)``), the weight at the current residual. A
threshold ``None`` is the plain Gaussian loss (weight 1).
"""
from __future__ import annotations

import numpy as np


def huber_cost(d: np.ndarray, k: float | None) -> np.ndarray:
    """Per-factor cost of the residual norms ``d`` (>= 0)."""
    if k is None:
        return 0.5 * d ** 2
    return np.where(d > k, k * (d - 0.5 * k), 0.5 * d ** 2)


def huber_cost_squared(u: np.ndarray, k2: float) -> np.ndarray:
    """:func:`huber_cost` of the norms ``sqrt(u)`` given their squares ``u`` and the
    threshold's square ``k2`` (a chi-square statistic and its quantile)."""
    return np.where(u <= k2, 0.5 * u, np.sqrt(k2 * u) - 0.5 * k2)


def huber_weight(d: np.ndarray, k: float | None) -> np.ndarray:
    """Per-factor IRLS weight of the residual norms ``d`` (>= 0)."""
    if k is None:
        return np.ones(np.shape(d))
    return np.where(d > k, k / np.maximum(d, 1e-300), 1.0)


def huber_scalar(d: float, k: float | None) -> tuple[float, float]:
    """``(weight, cost)`` of one residual norm ``d`` in Python floats (a numpy call costs
    microseconds where one fix is evaluated at a time)."""
    if k is None or d <= k:
        return 1.0, 0.5 * d * d
    return k / d, k * (d - 0.5 * k)


def row_norms(r: np.ndarray) -> np.ndarray:
    """Norms of the residual rows ``r`` (n, m)."""
    return np.sqrt(np.sum(r * r, axis=1))
