"""The heading offset's profile evidence over the whole circle, for data too short for the
sandwich: where a few fixes barely constrain theta_e, the curvature of one basin (and the
spread of the basins the starts happened to find) can claim 12 deg at a heading 147 deg off
(docs/independent-vehicle.md, "A short batch's heading over the whole circle").

At each heading of a grid over the circle, theta_e is held and the states and every other
parameter are solved (continuing from the neighbouring grid point), and the Laplace
approximation of the evidence with theta_e given is taken. With a flat prior on theta_e
these are its posterior's values on the grid; their weights make a mixture whose second
moments about the fit are the sigmas the data support.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from aqfg.fg.fastlm import FastSystem, levenberg_marquardt_fast

# grid points over the circle (30 deg apart)
N_GRID = 12
# log evidence below the best point's at which a walk round the circle stops (its weight
# e^-10, 5e-5)
DEPTH = 10.0


def worth_walking(sigma_theta: float, n: int = N_GRID) -> bool:
    """Whether a fit whose heading sigma (rad, its basin's curvature and the spread of the
    basins found) is ``sigma_theta`` is worth a profile: where the quadratic model of its
    basin puts the neighbouring grid point (360/n deg away) more than 4 :data:`DEPTH`
    below the fit (sigma under 3.4 deg at 30 deg apart), the walk would stop there; on a
    5-min crop its two solves cost 40 % of the batch (docs/independent-vehicle.md)."""
    step = 2.0 * np.pi / n
    return not 0.5 * (step / sigma_theta) ** 2 > 4.0 * DEPTH


@dataclass
class HeadingProfile:
    """theta_e (rad, wrapped) of the grid, the log evidence with it held, and the solved
    parameter vector (the numpy system's ``th``) at each; index 0 is the fit itself."""
    theta: np.ndarray
    log_evidence: np.ndarray
    params: np.ndarray

    def weights(self) -> np.ndarray:
        """The grid points' posterior weights (sum 1; a flat prior on theta_e); NaN where
        no point has a finite evidence (the sigmas are then left as they are)."""
        le = np.where(np.isfinite(self.log_evidence), self.log_evidence, -np.inf)
        if not np.isfinite(np.max(le)):
            # no grid point's Hessian was positive definite: the profile says nothing
            return np.full(len(le), np.nan)
        w = np.exp(le - np.max(le))
        return w / w.sum()

    def spread(self, j: int) -> float:
        """Second moment (the parameter's unit^2) of parameter ``j`` of ``params`` about
        the fit's value (index 0), over the posterior weights; differences not wrapped
        (theta_e's: :meth:`heading_spread`)."""
        d = self.params[:, j] - self.params[0, j]
        return float(np.sum(self.weights() * d ** 2))

    def heading_spread(self) -> float:
        """Second moment (rad^2) of theta_e about the fit, over the posterior weights."""
        d = np.angle(np.exp(1j * (self.theta - self.theta[0])))
        return float(np.sum(self.weights() * d ** 2))


def heading_profile(fs: FastSystem, X: np.ndarray, th: np.ndarray, j: int, settings,
                    held: Sequence[int] = (), n: int = N_GRID) -> HeadingProfile:
    """:class:`HeadingProfile` of the numpy system ``fs`` (at its current process-noise
    factor) around the solution ``(X, th)``, ``j`` the index of theta_e in ``th``: ``n``
    headings 360/n deg apart, each solved by LM from its neighbour's solution towards the
    fit, going both ways round until the evidence falls :data:`DEPTH` below the best
    point's; the parameters ``held`` (indices) stay at the fit's values
    (the thrust/drag constants: free, a held heading far off slid into a hull drifting
    sideways, k_yz near zero, which the batch's plausibility check refuses)."""
    hold = sorted({j, *held})
    lo, hi = float(fs.lo[j]), float(fs.hi[j])
    th0 = float(th[j])
    step = 2.0 * np.pi / n
    thetas = [th0]
    les = [fs.log_evidence(fs.evaluate(X, th), held=hold)]
    params = [th.copy()]
    for sign, count in ((1.0, n // 2), (-1.0, n - 1 - n // 2)):
        Xc, thc = X, th
        for k in range(1, count + 1):
            t = float(np.angle(np.exp(1j * (th0 + sign * k * step))))
            if not lo <= t <= hi:
                t = float(np.clip(t, lo, hi))
            start = thc.copy()
            start[j] = t
            Xk, thk, _, ev, *_ = levenberg_marquardt_fast(fs, None, settings, start=(Xc, start),
                                                          hold_params=hold)
            le = fs.log_evidence(ev, held=hold)
            thetas.append(t)
            les.append(le)
            params.append(thk.copy())
            if np.isfinite(le):
                Xc, thc = Xk, thk
            # the walk ends where the evidence has fallen far below the best point: the
            # rest of the circle behind that ridge weighs nothing (a basin beyond it is
            # the batch's starts' to find)
            if not le > max(les) - DEPTH:
                break
    return HeadingProfile(np.array(thetas), np.array(les), np.array(params))
