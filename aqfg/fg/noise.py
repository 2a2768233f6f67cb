"""How much process noise the model needs: the variance factor of the dynamics factors,
estimated from the fixes the model has to explain.

A model that is not the vehicle's (every real robot) makes errors the nominal process
noise does not allow for; held tight, it bends the parameters instead (on the Otter's
first straight leg a heading offset 40 deg off with a 1 m/s cross current explained six
fixes better than the truth, docs/independent-vehicle.md). The factor lets the track
follow the fixes in proportion to the model's measured error, so a wrong model costs
accuracy gracefully, towards a kinematic smoother.

The batch (:mod:`aqfg.fg.batch`) maximises the evidence over the factor: the smoothed
states absorb the model's error between fixes, so their fix-to-fix predictions cannot show
it. The fixed-lag smoother (:mod:`aqfg.fg.fixed_lag`) uses its causal innovations.
"""
from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from aqfg.fg.common import FGSettings
from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast


def excess(e2: npt.ArrayLike, var: npt.ArrayLike, q_pos: npt.ArrayLike) -> np.ndarray:
    """Normalised excess of fix innovations: ``max(|e|^2 / 2 - 2 R, 0) / Q_pos(dt)``.

    ``e2`` squared horizontal innovation (m^2) of a fix against the model's prediction
    from the previous fix, ``var`` the fix's per-axis variance R (m^2), ``q_pos`` the
    nominal process noise's per-axis position variance over the interval (m^2). The
    innovation's per-axis variance is ``q Q_pos + 2 R`` (prediction, the previous fix's
    uncertainty ~ R, this fix's R), so each value estimates the variance factor ``q``.
    """
    e2, var, q_pos = (np.asarray(a, float) for a in (e2, var, q_pos))
    return np.maximum(e2 / 2.0 - 2.0 * var, 0.0) / np.maximum(q_pos, 1e-300)


def excess_scalar(e2: float, var: float, q_pos: float) -> float:
    """:func:`excess` of one innovation, in Python floats (the online smoother's per-update
    path)."""
    return max(e2 / 2.0 - 2.0 * var, 0.0) / max(q_pos, 1e-300)


def variance_factor(values: npt.ArrayLike, settings: FGSettings, min_count: int = 3) -> float:
    """The process-noise variance factor from normalised excesses (:func:`excess`): their
    median, at least 1 and at most ``settings.adapt_max``, quantised to powers of sqrt 2
    (so noise models can be shared); 1 with fewer than ``min_count`` finite values."""
    if isinstance(values, list):               # the online path: a few floats
        fv = sorted(float(x) for x in values if math.isfinite(x))
        if len(fv) < min_count:
            return 1.0
        k = len(fv) // 2
        med = fv[k] if len(fv) % 2 else 0.5 * (fv[k - 1] + fv[k])
        target = min(max(med, 1.0), settings.adapt_max)
        return float(2.0 ** (round(2.0 * math.log2(target)) / 2.0))
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if len(v) < min_count:
        return 1.0
    target = float(np.clip(np.median(v), 1.0, settings.adapt_max))
    return float(2.0 ** (np.round(2.0 * np.log2(target)) / 2.0))


def evidence_search(fs: FastSystem, X: np.ndarray, th: np.ndarray, ev: dict,
                    settings: FGSettings, iterations: int = 5
                    ) -> tuple[float, np.ndarray, np.ndarray, dict[float, float]]:
    """The batch's process-noise variance factor: the largest log evidence
    (:meth:`FastSystem.log_evidence`, a Laplace approximation) over q = 1, 4, 16, ...
    (at most ``settings.adapt_max``), each solved by a few LM iterations warm-started
    from the previous one, stopping when the evidence falls.

    ``(X, th, ev)`` is the solution at the system's current factor (1). Returns the
    factor, the solution at it (not fully converged: the caller finishes it), and the
    evidence per factor tried. The system is left at the chosen factor.
    """
    q0 = fs.q
    best = (fs.log_evidence(ev), q0, X, th)
    tried = {q0: float(best[0])}
    q = q0
    while q * 4.0 <= settings.adapt_max:
        q *= 4.0
        fs.set_process_scale(q)
        Xq, thq, _, evq, *_ = levenberg_marquardt_fast(
            fs, None, settings, start=(best[2], best[3]), max_iterations=iterations)
        le = fs.log_evidence(evq)
        tried[q] = float(le)
        if not le > best[0]:
            break
        best = (le, q, Xq, thq)
    fs.set_process_scale(best[1])
    return best[1], best[2], best[3], tried
