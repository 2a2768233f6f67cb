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
from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast
from aqfg.fg.robust import huber_cost_squared
from aqfg.fg.settings import FGSettings

LR_CHI2_1 = 3.841           # chi-square(1) 95 % quantile
CHI2_2_99 = 9.21            # chi-square(2) 99 % quantile


def variance_factor(e2: npt.ArrayLike, var: npt.ArrayLike, q_pos: npt.ArrayLike,
                    settings: FGSettings, min_count: int = 3) -> float:
    """The process-noise variance factor ``q`` that best explains fix innovations, by
    maximum likelihood on a grid of powers of sqrt 2 in ``[1, settings.graph.process_scale_max]`` (so
    that noise models can be shared).

    ``e2`` squared horizontal innovation (m^2) of each fix against the model's prediction
    from the previous fix, ``var`` the fix's per-axis variance R (m^2), ``q_pos`` the
    nominal process noise's per-axis position variance over the interval (m^2). Each axis
    of an innovation has variance ``v = q Q_pos + 2 R`` (prediction, the previous fix's
    uncertainty ~ R, this fix's R), so ``u = e2 / v`` is chi-square with 2 degrees of
    freedom; the likelihood is pooled over the fixes (a short interval, whose innovation
    is mostly the fixes' own noise, weighs little; a per-fix statistic such as a median of
    ``(e2 / 2 - 2 R) / Q_pos`` was dominated by such intervals), with ``u`` Huberised
    beyond its 99 % quantile. 1 with fewer than
    ``min_count`` usable fixes, and 1 unless the best factor is significantly more likely.
    """
    if isinstance(e2, list) and nominal_suffices(e2, var, q_pos):   # type: ignore[arg-type]
        return 1.0
    ea, va, qa = (np.asarray(a, float).ravel() for a in (e2, var, q_pos))
    ok = np.isfinite(ea) & np.isfinite(va) & np.isfinite(qa) & (qa > 0)
    ea, va, qa = ea[ok], va[ok], qa[ok]
    if len(ea) < min_count:
        return 1.0
    n = int(np.floor(2.0 * np.log2(max(settings.graph.process_scale_max, 1.0)))) + 1
    grid = 2.0 ** (np.arange(n) / 2.0)
    v = grid[:, None] * qa[None, :] + 2.0 * va[None, :]
    u = ea[None, :] / v
    k = CHI2_2_99
    # a fix that not even the largest factor explains is an outlier of the fix, not the
    # model's error: left out (Huberised, a few outlying USBL fixes on a simulated AUV
    # raised q to the bound; clipped, large model errors kept q at 1) -- when they are a
    # minority: otherwise the model is what fails, and q is the bound
    keep = u[-1] <= k
    if keep.sum() < max(min_count, 0.5 * len(keep)):
        return float(grid[-1])
    # ... and when two of the last three are such fixes: a fix's outliers come alone, a
    # run of them is the model failing (on heldout-73 the factor flipped between 1 and
    # the bound every few fixes, and the causal track ran 7-15 m off the fixes at q = 1)
    if len(keep) >= 3 and int(np.count_nonzero(~keep[-3:])) >= 2:
        return float(grid[-1])
    u, v = u[:, keep], v[:, keep]
    rho = 2.0 * huber_cost_squared(u, k)
    nll = np.sum(0.5 * rho + np.log(v), axis=1)
    j = int(np.argmin(nll))
    # the nominal noise stays unless a larger one explains the innovations significantly
    # better (likelihood ratio, chi-square(1) at 5 %): with the fixes' own noise much
    # larger than the model's over an interval, ten innovations barely inform q, and the
    # plain maximum drew factors of 30-90 on a model that is the vehicle
    return float(grid[j]) if nll[0] - nll[j] > 0.5 * LR_CHI2_1 else 1.0


def nominal_suffices(e2: list[float], var: list[float], q_pos: list[float]) -> bool:
    """True when no factor q >= 1 can pass :func:`variance_factor`'s likelihood-ratio
    test, decided in Python floats (the online path runs it at every update; numpy calls
    cost microseconds each). Raising a fix's variance by r changes its term
    ``u / 2 + log v`` by at most ``g(u) = u / 2 - 1 - log(u / 2)`` (at r = u / 2, for
    u > 2, else 0), u at q = 1; the bound sums these, Huberisation ignored (it only lowers
    the gain)."""
    gains = []
    for a, r, q in zip(e2, var, q_pos):
        if not (math.isfinite(a) and math.isfinite(r) and q > 0):
            return False
        gains.append(lr_gain(a, r, q))
    return gains_suffice(gains)


def gains_suffice(gains: Iterable[float]) -> bool:
    """:func:`nominal_suffices` from its per-fix terms (:func:`lr_gain`), for a caller that
    keeps them as the fixes arrive."""
    return sum(gains) <= 0.5 * LR_CHI2_1


def lr_gain(e2: float, var: float, q_pos: float) -> float:
    """One fix's term of :func:`nominal_suffices`' bound (finite inputs, ``q_pos > 0``): the
    most its likelihood term can fall by raising its variance."""
    u = innovation_u(e2, var, q_pos)
    return 0.5 * u - 1.0 - math.log(0.5 * u) if u > 2.0 else 0.0


def innovation_u(e2: float, var: float, q_pos: float) -> float:
    """A fix's normalised squared innovation ``e2 / (q_pos + 2 var)``, chi-square with 2
    degrees of freedom under the noise model (:func:`variance_factor`'s ``u``; ``q_pos``
    already scaled by the variance factor in use)."""
    return e2 / (q_pos + 2.0 * var)


def evidence_search(fs: FastSystem, X: np.ndarray, th: np.ndarray, ev: dict,
                    settings: FGSettings, iterations: int = 5
                    ) -> tuple[float, np.ndarray, np.ndarray, dict[float, float]]:
    """The batch's process-noise variance factor: the largest log evidence
    (:meth:`FastSystem.log_evidence`, a Laplace approximation) over q = 1, 4, 16, ...
    (at most ``settings.graph.process_scale_max``), each solved by a few LM iterations warm-started
    from the previous one, stopping when the evidence falls.

    ``(X, th, ev)`` is the solution at the system's current factor (1). Returns the
    factor, the solution at it (not fully converged: the caller finishes it), and the
    evidence per factor tried. The system is left at the chosen factor.
    """
    best = (fs.log_evidence(ev), fs.q, X, th)
    tried = {fs.q: float(best[0])}
    best = _climb(fs, best, 4.0, settings, iterations, tried)
    fs.set_process_scale(best[1])
    return best[1], best[2], best[3], tried


def _climb(fs: FastSystem, best: tuple, step: float, settings: FGSettings, iterations: int,
           tried: dict[float, float]) -> tuple:
    """From ``best`` = ``(log evidence, factor, X, th)``, the factor multiplied by ``step``
    while it stays in ``[1, settings.graph.process_scale_max]``, each solved by ``iterations`` LM
    iterations warm-started from the best so far, until the evidence falls; the evidence
    of each factor tried into ``tried``. Returns the best; the system is left at the last
    factor tried."""
    q = best[1]
    while 1.0 <= q * step <= settings.graph.process_scale_max:
        q *= step
        fs.set_process_scale(q)
        Xq, thq, _, evq, *_ = levenberg_marquardt_fast(
            fs, None, settings, start=(best[2], best[3]), max_iterations=iterations)
        le = fs.log_evidence(evq)
        tried[q] = float(le)
        if not le > best[0]:
            break
        best = (le, q, Xq, thq)
    return best


def basin_evidence(fs: FastSystem, X: np.ndarray, th: np.ndarray, ev: dict,
                   settings: FGSettings, iterations: int = 5
                   ) -> tuple[float, float, np.ndarray, np.ndarray]:
    """The largest log evidence (:meth:`FastSystem.log_evidence`) of the basin of the
    solution ``(X, th, ev)`` at the system's current factor, over the factors 4x apart in
    ``[1, settings.graph.process_scale_max]``: searched upwards, then (where that gains nothing)
    downwards, each by a few LM iterations warm-started from the best so far, stopping
    when the evidence falls. Returns ``(log evidence, factor, X, th)`` (the solution not
    fully converged where the factor moved); the system is left at that factor.

    Two basins of a fit are compared by it (:class:`aqfg.fg.batch.BatchSmoother`): the
    Laplace approximation of each one's posterior mass, each under the noise that explains
    its own misfit, not the peak height under the noise one of them chose."""
    start = (fs.log_evidence(ev), fs.q, X, th)
    best = _climb(fs, start, 4.0, settings, iterations, {})
    if best[1] == start[1]:
        best = _climb(fs, start, 0.25, settings, iterations, {})
    fs.set_process_scale(best[1])
    return best


def track_noise_search(fs: FastSystem, X: np.ndarray, th: np.ndarray, ev: dict,
                       settings: FGSettings, iterations: int = 2
                       ) -> tuple[np.ndarray, np.ndarray, dict[float, list[float]]]:
    """Each mission part's process-noise factor for its track given the parameters ``th``
    (:attr:`FGSettings.batch.adapt_track`): the largest log evidence of its states
    (:meth:`FastSystem.part_log_evidence`) over q = 1, 4, 16, ... (at most
    ``settings.graph.process_scale_max``), each solved by a few LM iterations with the parameters held,
    warm-started from the previous one; a part's search stops when its evidence falls.

    ``(X, th, ev)`` is the solution at factor 1. Returns the factor per part, the states
    at each part's factor (not fully converged: the caller finishes them) and the evidence
    per part for each factor tried; the system is left at factor 1.
    """
    fs.set_process_scale(1.0)
    le = fs.part_log_evidence(ev)
    best_le, best_q = le.copy(), np.ones(len(le))
    active = np.isfinite(le)
    tried = {1.0: le.tolist()}
    q, Xq, X_best = 1.0, X, X.copy()
    rows = fs.part_of_state
    while q * 4.0 <= settings.graph.process_scale_max and active.any():
        q *= 4.0
        fs.set_process_scale(q)
        Xq, _, _, evq, *_ = levenberg_marquardt_fast(
            fs, None, settings, start=(Xq, th), max_iterations=iterations, hold_params=True)
        le = fs.part_log_evidence(evq)
        tried[q] = le.tolist()
        active &= le > best_le
        best_le[active], best_q[active] = le[active], q
        better = active[rows]
        X_best[better] = Xq[better]
    fs.set_process_scale(1.0)
    return best_q, X_best, tried
